"""Reading an input file (text, TOML, or a Parquet file's bytes), with the one-line errors
every reader gives."""

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


def is_parquet(path: str | Path) -> bool:
    """Whether a table file is Parquet (its suffix), not CSV text."""
    return Path(path).suffix.lower() == ".parquet"


def read_input(path: str | Path, hint: str, text: bool = True) -> bytes:
    """The file's bytes, read once; with `text`, checked to be UTF-8 text without NUL bytes
    and at most `MAX_TEXT_BYTES`. `hint` tells the user what to do when it is missing,
    unreadable or not text ("check the tracks path" …)."""
    path = Path(path)
    data = _read(path, hint, MAX_TEXT_BYTES if text else None)
    if text:
        _decoded(data, path, hint)
    return data


def read_text(path: str | Path, hint: str) -> str:
    """The file's text (UTF-8, a byte-order mark dropped, line ends as ``\\n``); `hint` tells
    the user what to do when it is missing ("check the tracks path" …)."""
    path = Path(path)
    text = _decoded(_read(path, hint, MAX_TEXT_BYTES), path, hint)
    return text.replace("\r\n", "\n").replace("\r", "\n")  # as a file opened as text reads


def _read(path: Path, hint: str, largest: int | None) -> bytes:
    try:
        with opening(path, hint):
            if largest is not None and path.is_file() and path.stat().st_size > largest:
                raise InputError(f"{path.stat().st_size} bytes is too large for a text input; {hint}", path=path)
            return path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read it ({exc.strerror or exc}); {hint}", path=path) from None


def _decoded(data: bytes, path: Path, hint: str) -> str:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"not a UTF-8 text file (byte {exc.start}); {hint}", path=path) from None
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
