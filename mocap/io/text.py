"""Reading a text or TOML input file, with the one-line errors every reader gives."""

from __future__ import annotations

import contextlib
import csv
import io
import tomllib
from pathlib import Path

from mocap.errors import InputError

MAX_TEXT_BYTES = 2**31  # 2 GiB: beyond this a text input is not one of ours


@contextlib.contextmanager
def opening(path: Path, hint: str):
    """The ways any input file fails to open (missing, a folder, not readable), each as its
    one-line InputError with `hint`; other errors pass through to the reader's own handling."""
    try:
        yield
    except FileNotFoundError:
        raise InputError(f"file not found; {hint}", path=path) from None
    except IsADirectoryError:
        raise InputError(f"is a folder, not a file; {hint}", path=path) from None
    except PermissionError:
        raise InputError(f"not readable (permission denied); {hint}", path=path) from None


def read_text(path: str | Path, hint: str) -> str:
    """The file's text (UTF-8, a byte-order mark dropped); `hint` tells the user what to do
    when it is missing ("check the tracks path" …)."""
    path = Path(path)
    try:
        with opening(path, hint):
            if path.is_file() and path.stat().st_size > MAX_TEXT_BYTES:
                raise InputError(f"{path.stat().st_size} bytes is too large for a text input; {hint}", path=path)
            text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"not a UTF-8 text file (byte {exc.start}); {hint}", path=path) from None
    except OSError as exc:
        raise InputError(f"cannot read it ({exc.strerror or exc}); {hint}", path=path) from None
    if "\0" in text:
        line = text.count("\n", 0, text.index("\0")) + 1
        raise InputError(f"a NUL byte: not a text file; {hint}", path=path, where=f"line {line}")
    return text


def read_toml(path: str | Path, hint: str) -> dict:
    try:
        return tomllib.loads(read_text(path, hint))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML ({exc})", path=path) from None


def csv_rows(text: str, path: str | Path) -> list[list[str]]:
    """The rows of a CSV text; a field beyond the csv module's limit (128 KiB) or a NUL byte
    is an InputError naming the line."""
    reader = csv.reader(io.StringIO(text))
    try:
        return list(reader)
    except csv.Error as exc:
        raise InputError(f"not a readable CSV ({exc})", path=path, where=f"line {reader.line_num}") from None
