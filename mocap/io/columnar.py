"""Columnar reading and writing of the tables (tracks, points, motion) through pyarrow.

A CSV file is first read by pyarrow with strict types; any file it cannot read that way
(quotes it disagrees on, padded fields, a bad number, ...) is read with the csv module,
whose checks name the line. A ``.parquet`` path is read and written as Parquet with the
same columns. `parse_table` does both for a table of a given `Layout`, from the file's
bytes (read once, by `mocap.io.text.read_input`), in one call.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from mocap.errors import InputError
from mocap.io.atomic import atomic_path
from mocap.io.text import read_input

MAX_BYTES = 2**31  # as mocap.io.text: a larger file is left to the checked reader


# a CSV column of few distinct names, read once each, as bytes (UTF-8 is checked once per name)
NAMES = pa.dictionary(pa.int32(), pa.binary())


def parse_table(data: bytes, path: str | Path, layout: Layout, hint: str, parquet: bool) -> Table:
    """The table of a file's bytes, a Parquet file's (`parquet`) or a CSV file's, read the
    fast way (pyarrow, strict types, whole-column checks) when every value passes, else
    the checked way; a file that is not such a table is an InputError naming its line or
    row (`path` names it, `hint`: what the user should check). A CSV file's bytes are
    UTF-8 text (`read_input` checked them)."""
    path = Path(path)
    if parquet:
        table = _parquet(data, path, hint, tuple(layout.names))
        missing = [h for h in layout.required if h not in table.column_names]
        if missing:
            raise InputError(f"lacks the columns {', '.join(missing)}; expected columns {layout.expected}", path=path)
        rows = np.arange(1, table.num_rows + 1)
        typed = _typed(table, layout, rows, "row")
        return typed if typed is not None else _parquet_text(table, layout, rows, path)
    types = {h: NAMES for h in layout.names} | {h: NAMES for h in layout.counts}
    types |= {h: pa.float64() for h in layout.floats(layout.required + layout.optional)}
    table = _read_strict(data, types, tuple(layout.counts))
    typed = None if table is None else _typed(table, layout, lambda: _line_numbers(data), "line")
    return typed if typed is not None else _checked_csv(data, path, layout)


def _typed(table: pa.Table, layout: Layout, rows, unit: str) -> Table | None:
    """The Table of a typed pyarrow table whose every value passes the whole-column checks
    (names plain, counts whole, floats finite or empty, required floats not empty), else
    None (it is then read the checked way, which names the first bad row)."""
    if any(h not in table.column_names for h in layout.required):
        return None
    names = {h: plain_strings(table[h], longest) for h, longest in layout.names.items() if h in table.column_names}
    counts = {h: whole_numbers(table[h], largest) for h, largest in layout.counts.items() if h in table.column_names}
    if any(v is None for v in (*names.values(), *counts.values())):
        return None
    values = {name: float_columns([table[h] for h in columns]) for name, columns in layout.vectors.items()}
    inside = {h for columns in layout.vectors.values() for h in columns}
    values |= {h: floats(table[h]) for h in layout.floats(table.column_names) if h not in inside}
    if any(v is None for v in values.values()):
        return None
    for name, v in values.items():
        nulls = sum(table[h].null_count for h in layout.vectors.get(name, (name,)))
        if nulls and (name in layout.required or name in layout.vectors):
            return None  # a required float empty
        if nulls:
            finite = np.count_nonzero(np.isfinite(v)) == v.size - nulls
        else:  # a NaN or an infinity shows in the least or the greatest
            finite = not v.size or bool(np.isfinite(v.min()) and np.isfinite(v.max()))
        if not finite:
            return None  # infinite, or a NaN written out rather than an empty field
    return Table(rows, unit, names, values, counts)


def _bytes(path: Path) -> bytes | None:
    """The file's bytes, None when it cannot be read (the checked reader then says why)."""
    try:
        if not path.is_file() or path.stat().st_size > MAX_BYTES:
            return None
        return path.read_bytes()
    except OSError:
        return None


def _read_strict(data: bytes, types: dict[str, pa.DataType], counts: tuple[str, ...] = (),
                 default: pa.DataType | None = None) -> pa.Table | None:
    """`read_csv_strict` of the file's bytes."""
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    if b"\0" in data or b'"' in data:
        return None
    end = data.find(b"\n")
    first = (data if end < 0 else data[:end]).rstrip(b"\r")
    try:
        header = next(csv.reader([first.decode("utf-8")]), [])
    except (UnicodeDecodeError, csv.Error):  # not UTF-8, or lines that end in a lone "\r"
        return None
    if not header or len(set(header)) != len(header) or any(h != h.strip() or not h for h in header):
        return None
    wanted = [h for h in header if h in types or default is not None]
    column_types = {h: types.get(h, default) for h in wanted}
    if counts and not _integer_lookalikes(data, max(end, 0)):
        column_types |= {h: pa.int64() for h in counts if h in column_types}
    try:
        table = pacsv.read_csv(
            pa.py_buffer(data),
            parse_options=pacsv.ParseOptions(newlines_in_values=False, ignore_empty_lines=True),
            convert_options=pacsv.ConvertOptions(
                column_types=column_types, include_columns=wanted, null_values=[""],
                strings_can_be_null=True, quoted_strings_can_be_null=True, true_values=[], false_values=[]),
        )
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
        return None
    return table if table.num_rows else None


_NEGATIVE_ZERO = re.compile(rb"-0+[ \t]*(?:[,\r\n]|\Z)")


def _integer_lookalikes(data: bytes, start: int) -> bool:
    """Whether the rows (from `start`) may hold a field pyarrow reads as an integer that is
    not plain digits: hexadecimal (``0x``) or a negative zero (any other sign shows in the
    value). Single bytes are looked for first (fast); the patterns only where they occur."""
    hexadecimal = any(data.find(x, start) >= 0 and data.find(b"0" + x, start) >= 0 for x in (b"x", b"X"))
    return hexadecimal or (data.find(b"-", start) >= 0 and _NEGATIVE_ZERO.search(data, start) is not None)


def _line_numbers(data: bytes) -> np.ndarray:
    """(R,) the line number of each row pyarrow reads from `data`: its lines end in
    ``\\n``, ``\\r\\n`` or ``\\r``, and it skips the empty ones."""
    byte = np.frombuffer(data, np.uint8)
    newline, cr = byte == ord("\n"), byte == ord("\r")
    crlf = cr & np.r_[newline[1:], False]
    ends = np.flatnonzero(newline | (cr & ~crlf))
    starts, stops = np.r_[0, ends + 1], np.r_[ends, len(byte)]
    stops = stops - np.r_[crlf[np.maximum(ends - 1, 0)] & (ends > 0), False]  # "\r\n" ends a line at its "\r"
    return np.flatnonzero(stops > starts)[1:] + 1  # the header on line 1


def _checked_csv(data: bytes, path: Path, layout: Layout) -> Table:
    """The Table of a CSV file's bytes (UTF-8) read with the csv module: the header, the width
    of every row and every float checked, the first fault named by its line; blank rows
    skipped; lines end in ``\\n``, ``\\r\\n`` or ``\\r``."""
    reader = csv.reader(io.StringIO(data.decode("utf-8-sig"), newline=None))
    try:
        header = next(reader, None)
        if header is None:
            raise InputError(f"empty file; expected a header {','.join(layout.required)}", path=path)
        header = [h.strip() for h in header]
        rows, lines = [], []
        for row in reader:
            if row and any(v.strip() for v in row):
                rows.append(row)
                lines.append(reader.line_num)
    except csv.Error as exc:
        raise InputError(f"not a readable CSV ({exc})", path=path, where=f"line {reader.line_num}") from None
    missing = [h for h in layout.required if h not in header]
    if missing:
        raise InputError(f"header lacks {', '.join(missing)}; expected columns {layout.expected}", path=path,
                         where="line 1")
    lines = np.asarray(lines, dtype=int)
    widths = np.fromiter((len(r) for r in rows), dtype=int, count=len(rows))
    bad = np.flatnonzero(widths != len(header))
    if len(bad):
        raise InputError(f"{widths[bad[0]]} fields, the header has {len(header)}", path=path,
                         where=f"line {lines[bad[0]]}")
    cells = np.array(rows, dtype=str).reshape(len(rows), len(header))
    columns = [h for h in layout.required + layout.optional if h in header]
    text = {h: np.char.strip(cells[:, header.index(h)]) for h in columns}
    return _from_text(text, layout, lines, "line", path)


def _parquet_text(table: pa.Table, layout: Layout, rows: np.ndarray, path: Path) -> Table:
    """The Table of a Parquet table that fails the whole-column checks, from the text of
    its values (an empty field for null), to be checked value by value."""
    columns = [h for h in layout.required + layout.optional if h in table.column_names]
    text = {h: np.char.strip(np.array(["" if v is None else str(v) for v in table[h].to_pylist()], dtype=str)
                             .reshape(-1)) for h in columns}
    return _from_text(text, layout, rows, "row", path)


def _from_text(text: dict[str, np.ndarray], layout: Layout, rows: np.ndarray, unit: str, path: Path) -> Table:
    """A Table of text columns: names coded, counts and floats parsed (the first that is
    not a whole number in range, or not a number, named by its row)."""

    def fail(mask: np.ndarray, message) -> None:
        bad = np.flatnonzero(mask)
        if len(bad):
            raise InputError(message(bad[0]), path=path, where=f"{unit} {rows[bad[0]]}")

    counts = {}
    for h, largest in layout.counts.items():
        if h not in text:
            continue
        digits = text[h]
        fail(np.char.startswith(digits, "-") & ascii_digits(np.char.lstrip(digits, "-")),
             lambda k: f"{h} {digits[k]} is negative; {h}s count from 0")
        fail(~ascii_digits(digits), lambda k: f"{h} {str(digits[k])[:40]!r} is not an integer")
        fail(np.char.str_len(np.char.lstrip(digits, "0")) > len(str(largest)),
             lambda k: f"{h} {digits[k]} is beyond {largest:,}; a typo?")
        counts[h] = digits.astype(np.int64)
        fail(counts[h] > largest, lambda k: f"{h} {counts[h][k]:,} is beyond {largest:,}; a typo?")
    names = {}
    for h in layout.names:
        if h in text:
            encoded = pa.array(text[h], pa.string()).dictionary_encode()
            names[h] = tuple(encoded.dictionary.to_pylist()), encoded.indices.to_numpy(zero_copy_only=False)
    values = {h: parse_floats(np.where(np.char.str_len(text[h]) == 0, "nan", text[h]), h, rows, path, unit)
              for h in layout.floats(text)}
    for name, columns in layout.vectors.items():
        values[name] = np.column_stack([values.pop(h) for h in columns])
    return Table(rows, unit, names, values, counts,
                 {h: v for h, v in text.items() if h not in layout.names and h not in layout.counts})


def read_parquet(path: Path, hint: str, names: tuple[str, ...] = ()) -> pa.Table:
    """The Parquet file's table, the columns `names` (where present) as dictionaries (read
    once per name, not per row); an unreadable file is an InputError."""
    return _parquet(read_input(path, hint, text=False), path, hint, names)


def _parquet(data: bytes, path: Path, hint: str, names: tuple[str, ...]) -> pa.Table:
    try:
        return pq.read_table(pa.BufferReader(data), read_dictionary=list(names) or None)
    except (pa.ArrowException, OSError) as exc:
        raise InputError(f"not a readable Parquet file ({str(exc).splitlines()[0][:200]}); {hint}",
                         path=path) from None


def plain_strings(column: pa.ChunkedArray, longest: int) -> tuple[tuple[str, ...], np.ndarray] | None:
    """The distinct values (K,) of a text column (string, or UTF-8 bytes) whose every value
    is a non-empty string of at most `longest` characters without surrounding white space,
    and each row's (N,) code: its index into them. None for any other column."""
    if column.null_count:
        return None
    values, codes = _distinct(column)
    values = _text(values)
    if values is None or not _plain(values, longest):
        return None
    return tuple(values.to_pylist()), codes


def _distinct(column: pa.ChunkedArray) -> tuple[pa.Array, np.ndarray]:
    """A column without nulls as its distinct values (K,) and each row's index (N,) into
    them: a dictionary column's own (read once per name), else dictionary-encoded."""
    if not pa.types.is_dictionary(column.type):
        encoded = column.combine_chunks().dictionary_encode()
        return encoded.dictionary, encoded.indices.to_numpy()
    column = column.unify_dictionaries()
    if not column.num_chunks:
        return pa.array([], column.type.value_type), np.zeros(0, np.int64)
    indices = [c.indices.to_numpy() for c in column.chunks]
    return column.chunk(0).dictionary, indices[0] if len(indices) == 1 else np.concatenate(indices)


def _text(values: pa.Array) -> pa.Array | None:
    """String values as they are, bytes decoded as UTF-8; None for anything else or
    bytes that are not UTF-8."""
    if pa.types.is_string(values.type) or pa.types.is_large_string(values.type):
        return values
    if not pa.types.is_binary(values.type) and not pa.types.is_large_binary(values.type):
        return None
    try:
        return pc.cast(values, pa.string() if pa.types.is_binary(values.type) else pa.large_string())
    except pa.ArrowInvalid:
        return None


def _plain(values: pa.Array, longest: int) -> bool:
    length = pc.utf8_length(values)
    if len(values) and (pc.min(length).as_py() < 1 or pc.max(length).as_py() > longest):
        return False
    return pc.all(pc.equal(pc.utf8_trim_whitespace(values), values)).as_py() is not False


def whole_numbers(column: pa.ChunkedArray, largest: int) -> np.ndarray | None:
    """(N,) int64 of a column of whole numbers 0 ... `largest` (written with at most as
    many digits as `largest`), or None. Text is checked once per distinct value."""
    if column.null_count:
        return None
    if pa.types.is_dictionary(column.type) or pa.types.is_string(column.type) or pa.types.is_large_string(column.type) \
            or pa.types.is_binary(column.type):
        values, index = _distinct(column)
        values = _text(values)
        if values is None:
            return None
        length = pc.binary_length(values)
        if len(values) and (pc.min(length).as_py() < 1 or pc.max(length).as_py() > len(str(largest))):
            return None
        if pc.all(pc.and_(pc.string_is_ascii(values), pc.utf8_is_digit(values))).as_py() is False:
            return None
        numbers = pc.cast(values, pa.int64()).to_numpy(zero_copy_only=False)[index]
    elif pa.types.is_integer(column.type):
        numbers = _writable(column.to_numpy())  # a chunked column is concatenated once
    else:
        return None
    numbers = numbers.astype(np.int64, copy=False)
    if len(numbers) and (numbers.min() < 0 or numbers.max() > largest):
        return None
    return numbers


def floats(column: pa.ChunkedArray) -> np.ndarray | None:
    """(N,) float64, NaN for null, or None if the column is not numeric."""
    if not (pa.types.is_floating(column.type) or pa.types.is_integer(column.type)):
        return None
    if column.type == pa.float64() and not column.null_count:
        return _writable(column.to_numpy())  # a chunked column is concatenated once
    return pc.cast(column.combine_chunks(), pa.float64()).fill_null(np.nan).to_numpy(zero_copy_only=False)


def float_columns(columns: list[pa.ChunkedArray]) -> np.ndarray | None:
    """(N, K) float64 of K numeric columns side by side (NaN for null), filled chunk by
    chunk (no concatenated copy), or None if a column is not numeric."""
    if not all(pa.types.is_floating(c.type) or pa.types.is_integer(c.type) for c in columns):
        return None
    out = np.empty((len(columns[0]), len(columns)))
    for k, column in enumerate(columns):
        if column.type != pa.float64() or column.null_count:
            out[:, k] = floats(column)
            continue
        start = 0
        for chunk in column.chunks:
            out[start : start + len(chunk), k] = chunk.to_numpy()
            start += len(chunk)
    return out


def _writable(values: np.ndarray) -> np.ndarray:
    """`values`, copied if pyarrow's memory backs them (read-only)."""
    return values if values.flags.writeable else values.copy()


def parse_floats(text: np.ndarray, key: str, lines: np.ndarray, path, unit: str = "line") -> np.ndarray:
    """Text (N,) as floats; the first that is not a number is an InputError naming its
    `unit` and number from `lines` (N,)."""
    try:
        return text.astype(float)
    except ValueError:
        for k, value in enumerate(text):  # only on the way to the error: find the row
            try:
                float(value)
            except ValueError:
                raise InputError(f"{key} {str(value)[:40]!r} is not a number", path=path,
                                 where=f"{unit} {lines[k]}") from None
        raise


def ascii_digits(text: np.ndarray) -> np.ndarray:
    """(R,) whether each string is made of the digits 0-9 only (no '²', no other scripts' digits)."""
    ascii = np.char.str_len(np.char.encode(text, "utf-8")) == np.char.str_len(text)
    return np.char.isdigit(text) & ascii


def read_csv_strict(path: Path, types: dict[str, pa.DataType], counts: tuple[str, ...] = (),
                    default: pa.DataType | None = None) -> pa.Table | None:
    """The columns of `types` present in the header, typed (with a `default` type, every
    other column of the header too, typed so); an empty field is null. None
    when the file is anything but a plain UTF-8 CSV of one header line, stripped unique
    names and rows of the header's width (the caller then reads it the checked way).

    The columns `counts` (of whole numbers, each typed NAMES in `types`) are read as int64
    straight away when the file holds no text that pyarrow reads as an integer but the
    checked reader refuses (hexadecimal ``0x1f``, a negative zero ``-0``), else as names,
    to be checked by `whole_numbers`."""
    data = _bytes(path)
    return None if data is None else _read_strict(data, types, counts, default)


def write_parquet(columns: dict[str, np.ndarray], path: str | Path) -> None:
    """Write named (N,) columns as a Parquet file, atomically."""
    table = pa.table({name: text(value) if np.asarray(value).dtype.kind in "OUS" else pa.array(value, from_pandas=True)
                      for name, value in columns.items()})  # NaN -> null
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)


def write_csv(columns: dict[str, np.ndarray], path: str | Path, digits: dict[str, int]) -> None:
    """Write named (N,) columns as a CSV file, atomically: whole numbers as they are, floats
    rounded to `digits` decimals of their name (written without trailing zeros), NaN as an
    empty field, text unquoted (a value that would need quotes goes through the csv module)."""
    arrays = {}
    for name, values in columns.items():
        values = np.asarray(values)
        if values.dtype.kind == "f":
            values = np.round(values, digits[name]) if name in digits else values
            arrays[name] = pa.array(values, from_pandas=True)  # NaN -> null -> empty field
        elif values.dtype.kind in "iub":
            arrays[name] = pa.array(values.astype(np.int64))
        else:
            arrays[name] = text(values)
    table = pa.table(arrays)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write((",".join(columns) + "\n").encode("utf-8"))
            try:
                pacsv.write_csv(table, fh, pacsv.WriteOptions(include_header=False, quoting_style="none"))
                return
            except pa.ArrowInvalid:  # a comma or quote in a name: quoted by the csv module
                pass
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(list(columns))
            writer.writerows(zip(*(["" if v is None else v for v in table[n].to_pylist()] for n in columns)))


def text(values: np.ndarray) -> pa.Array:
    """A string array of (N,) names: an object array of str converted as it is (no
    fixed-width copy), anything else through str."""
    values = np.asarray(values)
    if values.dtype == object:
        try:
            return pa.array(values, pa.string())
        except (pa.ArrowTypeError, pa.ArrowInvalid):  # not all str
            pass
    return pa.array(values.astype(str))


@dataclass(frozen=True)
class Layout:
    """The columns of a table file: `required` and `optional` names (header order is
    free); `names` the text columns of few distinct names, each with its longest length;
    `counts` the whole-number columns, each with its largest value; the others are
    floats (an empty field is NaN; a `required` float is never empty), those of a
    `vectors` entry given side by side under its name."""

    required: tuple[str, ...]
    optional: tuple[str, ...] = ()
    names: dict[str, int] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    vectors: dict[str, tuple[str, ...]] = field(default_factory=dict)  # required floats read side by side: (R, K)

    @property
    def expected(self) -> str:
        """The columns as the messages state them: ``a,b,c[,d,e]``."""
        return ",".join(self.required) + (f"[,{','.join(self.optional)}]" if self.optional else "")

    def floats(self, present) -> list[str]:
        """The float columns among `present`, each vector's columns first."""
        inside = [h for columns in self.vectors.values() for h in columns]
        return inside + [h for h in self.required + self.optional
                         if h in present and h not in self.names and h not in self.counts and h not in inside]


@dataclass(frozen=True)
class Table:
    """A table file read once, R rows: `names` {column: (distinct names (K,), each row's
    code (R,))}, `counts` {column: (R,) int64} and `values` {float column: (R,) NaN where
    empty}, whichever way it was read. Read the fast way, `text` is None; read the checked way
    (a field pyarrow reads otherwise than the checks, or a value the checks refuse),
    `text` {float column: (R,) its stripped text} as well, for the checks of the caller.
    A vector of the layout is in `values` under its name, (R, K), its columns not apart.
    `rows` (R,) numbers each row for messages, as its `unit` (a CSV's line, a Parquet
    file's row)."""

    numbering: np.ndarray | Callable[[], np.ndarray]  # `rows`, or how to count them when first asked
    unit: str
    names: dict[str, tuple[tuple[str, ...], np.ndarray]]
    values: dict[str, np.ndarray]
    counts: dict[str, np.ndarray]
    text: dict[str, np.ndarray] | None = None

    @cached_property
    def rows(self) -> np.ndarray:
        return self.numbering if isinstance(self.numbering, np.ndarray) else self.numbering()

    def __len__(self) -> int:
        for column in (*(codes for _, codes in self.names.values()), *self.values.values()):
            return len(column)
        return len(self.rows)
