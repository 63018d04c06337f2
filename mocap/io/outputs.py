"""Checking a command's output paths before any work: never over an input, never onto a
folder, only where a file can be written.

Every command calls `check_outputs` with the files it will write and the files it reads,
so that a mistyped `--out` fails at once with one line, before minutes of computing and
without touching anything.
"""

from __future__ import annotations

import os
from pathlib import Path

from mocap.errors import InputError


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two paths name the same file (resolved: links, `..`, case of the path as given)."""
    a, b = Path(a), Path(b)
    if a.exists() and b.exists():
        try:
            return os.path.samefile(a, b)
        except OSError:
            pass
    return a.resolve() == b.resolve()


def check_outputs(outputs: dict[str, object], inputs: dict[str, object] | None = None,
                  *, may_replace: tuple[str, ...] = ()) -> None:
    """Refuse outputs that would overwrite an input or each other, or that cannot be written.

    `outputs` {option: path or None}, `inputs` {what: path, list of paths or None};
    `may_replace` names inputs an output may replace on purpose (sync's calibration).
    """
    for option, path in outputs.items():
        if path is not None and str(path).endswith(("/", os.sep)):
            raise InputError(f"{option} {path} ends in a separator; name a file, not a folder")
    given = {option: Path(path) for option, path in outputs.items() if path is not None}
    read = []
    for what, value in (inputs or {}).items():
        if value is None:
            continue
        for path in value if isinstance(value, (list, tuple)) else [value]:
            if what == "machine model":
                path = _machine_file(path)
            if what not in may_replace and Path(path).exists():
                read.append((what, Path(path)))
    seen: list[tuple[str, Path]] = []
    for option, path in given.items():
        for what, source in read:
            if same_file(path, source):
                raise InputError(
                    f"{option} {path} is the {what} input; writing it would destroy the input: "
                    "choose another output path"
                )
        for other, earlier in seen:
            if same_file(path, earlier):
                raise InputError(f"{option} and {other} are the same file {path}; give each its own path")
        seen.append((option, path))
        check_writable(path, option)


def check_writable(path: str | os.PathLike, option: str = "output") -> None:
    """Refuse a file path that is a folder, or whose folder cannot be made or written into."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{option} {path} is a folder; name a file inside it")
    folder = _nearest_existing(path.parent)
    if not folder.is_dir():
        raise InputError(f"{option} {path}: {folder} is a file, not a folder; choose another output path")
    if not os.access(folder, os.W_OK | os.X_OK) or _read_only_filesystem(folder):
        raise InputError(f"{option} {path}: the folder {folder} is not writable; choose another output path")


def check_output_folder(path: str | os.PathLike, option: str = "--out") -> None:
    """Refuse a folder path that is a file, or that cannot be made or written into."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{option} {path} is a file, not a folder; name a new folder")
    folder = _nearest_existing(path)
    if not folder.is_dir():
        raise InputError(f"{option} {path}: {folder} is a file, not a folder; choose another folder")
    if not os.access(folder, os.W_OK | os.X_OK) or _read_only_filesystem(folder):
        raise InputError(f"{option} {path}: the folder {folder} is not writable; choose another folder")


def _machine_file(name_or_path) -> Path:
    """A machine model's file, also when it is given by a shipped model's name."""
    from mocap.io.machine_toml import resolve_machine_path

    try:
        return resolve_machine_path(str(name_or_path))
    except InputError:
        return Path(name_or_path)


def _nearest_existing(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _read_only_filesystem(folder: Path) -> bool:
    """A read-only mount or a kernel's virtual file system (/proc, /sys), where even root
    cannot create a file."""
    try:
        stat = os.statvfs(folder)
    except OSError:
        return True
    if stat.f_flag & os.ST_RDONLY:
        return True
    real = Path(os.path.realpath(folder))
    return real.parts[1:2] in (("proc",), ("sys",))
