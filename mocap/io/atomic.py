"""Atomic output: write to a temporary file beside the target, then rename.

A target that cannot be written (its folder read-only, missing and not creatable, on /proc,
or the target itself a folder) is an InputError naming it, raised before anything is
written; an interrupted or failed write leaves the target as it was.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from glob import escape as glob_escape
from pathlib import Path

from mocap.errors import InputError

# the place's fault, not the program's: full, over quota, read-only, not allowed, a folder
_PLACE_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EISDIR, errno.ENOTDIR,
                 errno.EXDEV, errno.EFBIG}
_FULL_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}  # no space left for the file


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside `path`; on success it is renamed onto `path`.

    On an exception the temporary file is removed and `path` is left as it was.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError("is a folder; name a file to write", path=path)
    folder = next((p for p in path.parents if p.exists()), None)
    if folder is not None and not folder.is_dir():
        raise InputError(f"{folder} is a file, not a folder; choose another output path", path=path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise InputError(f"cannot write here ({exc.strerror or exc}); choose another output path",
                         path=path) from None
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
    try:
        try:
            yield Path(tmp)
            os.replace(tmp, path)
            _remove_leftovers(path)
        except OSError as exc:
            if exc.errno not in _PLACE_ERRORS:
                raise
            if exc.errno in _FULL_ERRORS:
                raise InputError(_full_message(exc, Path(tmp), path), path=path) from None
            raise InputError(f"cannot write here ({exc.strerror or exc}); choose another output path",
                             path=path) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _remove_leftovers(path: Path) -> None:
    """The temporary files of an earlier writer of `path` killed mid-write (SIGKILL leaves
    no chance to remove them): the file is now whole, they are of no use."""
    for stale in path.parent.glob(f".{glob_escape(path.name)}.*.tmp"):
        with contextlib.suppress(OSError):
            stale.unlink()


def _full_message(exc: OSError, tmp: Path, path: Path) -> str:
    """What a write that ran out of space says: how much was written before it stopped (the
    least the file needs) and how much the disk has free; nothing of it is kept."""
    import shutil

    try:
        written = tmp.stat().st_size
    except OSError:
        written = 0
    try:
        free = f"{_size(shutil.disk_usage(path.parent).free)} free there"
    except OSError:
        free = "free space unknown"
    limit = " or over the file-size limit (ulimit -f)" if exc.errno == errno.EFBIG else ""
    return (f"the disk is full{limit} ({exc.strerror or exc}): the file needs more than the {_size(written)} "
            f"written before it stopped ({free}); nothing of it was kept and earlier files are as they were: "
            "free some space or choose another output path, then run again")


def _size(n: int) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} bytes"


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike):
    """Yield a temporary folder beside `path`; on success it replaces `path` (whose old
    contents are removed). On an exception the temporary folder is removed."""
    import shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; give the folder the usual permissions
    try:
        yield tmp
        if path.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            os.replace(path, old / path.name)
            os.replace(tmp, path)
            shutil.rmtree(old)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
