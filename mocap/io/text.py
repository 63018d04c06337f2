"""Reading a text or TOML input file, with the one-line errors every reader gives."""

from __future__ import annotations

import tomllib
from pathlib import Path

from mocap.errors import InputError


def read_text(path: str | Path, hint: str) -> str:
    """The file's text; `hint` tells the user what to do when it is missing ("check the
    tracks path" …)."""
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"file not found; {hint}", path=path) from None
    except IsADirectoryError:
        raise InputError(f"is a folder, not a file; {hint}", path=path) from None
    except UnicodeDecodeError:
        raise InputError("not a UTF-8 text file", path=path) from None


def read_toml(path: str | Path, hint: str) -> dict:
    try:
        return tomllib.loads(read_text(path, hint))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML ({exc})", path=path) from None
