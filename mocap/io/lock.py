"""A session folder's lock: one command at a time writes into it.

The lock is the file ``.mocap.lock`` in the folder, made with O_EXCL (atomic on a local
disk), holding ``pid host command`` of its holder. A second command refuses with one line
naming the first (InputError). A lock whose process is dead on this host (a command killed
or a laptop that restarted) is stale and taken over. The same process may take it again (a
command running another inside it, as `mocap run` runs `mocap track`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import socket
from pathlib import Path

from mocap.errors import InputError

LOCK_NAME = ".mocap.lock"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _holder(path: Path) -> tuple[int, str, str] | None:
    """(pid, host, command) of the lock file, or None if it is unreadable or half written."""
    try:
        fields = path.read_text(encoding="utf-8").split(" ", 2)
        return int(fields[0]), fields[1], fields[2].strip()
    except (OSError, ValueError, IndexError):
        return None


def check_free(folder: str | os.PathLike, name: str = LOCK_NAME) -> None:
    """InputError naming the holder if another live process holds the lock of `folder`."""
    _refuse_if_held(Path(folder), Path(folder) / name, socket.gethostname())


def _refuse_if_held(folder: Path, path: Path, host: str) -> bool:
    """Raise if another live process holds `path`; True if this process holds it, False if
    it is free or stale."""
    if not path.exists():
        return False
    holder = _holder(path)
    if holder is not None and holder[0] == os.getpid() and holder[1] == host:
        return True  # this process holds it already (a command inside another)
    if holder is not None and (holder[1] != host or _alive(holder[0])):
        pid, where, other = holder
        raise InputError(f"in use by `{other}` (process {pid} on {where}, lock file {path}); wait for it "
                         "to end, or delete the lock file if that process is gone", path=folder)
    if holder is None and _young(path):
        raise InputError(f"in use (lock file {path} being written); try again", path=folder)
    return False


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, command: str, name: str = LOCK_NAME):
    """Hold the lock `name` of `folder` while the block runs; InputError if another live
    process holds it. Nothing is done when `folder` does not exist (there is nothing to share)."""
    folder = Path(folder)
    if not folder.is_dir():
        yield
        return
    path = folder / name
    host = socket.gethostname()
    mine = f"{os.getpid()} {host} {command}\n"
    for _ in range(3):
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            if _refuse_if_held(folder, path, host):
                yield
                return
            with contextlib.suppress(FileNotFoundError):  # stale: its process is dead
                os.unlink(path)
            continue
        except OSError as exc:
            if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
                yield  # a read-only folder: nothing will be written into it to share
                return
            raise
        try:
            os.write(fd, mine.encode("utf-8"))
        finally:
            os.close(fd)
        break
    else:
        raise InputError(f"cannot take the lock file {path}: other commands keep taking it", path=folder)
    try:
        yield
    finally:
        if _holder(path) is not None and _holder(path)[:2] == (os.getpid(), host):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)


def _young(path: Path, seconds: float = 5.0) -> bool:
    """Whether `path` was made in the last few seconds (a holder still writing its pid)."""
    import time

    try:
        return time.time() - path.stat().st_mtime < seconds
    except FileNotFoundError:
        return False
