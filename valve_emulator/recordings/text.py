"""Text-level helpers shared by the readers: decoding, lines, delimiters, cells, numbers and time stamps.

Everything here is strict on purpose: a cell that is not a number is an error naming the file, the line (1-based,
as an editor counts) and the column, never a silent NaN. Bad input raises :class:`ReaderError` and returns
nothing.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Sequence
from datetime import datetime, timezone
from typing import Final

import numpy as np

from valve_emulator.recordings.recording import RecordingError

__all__ = [
    "ReaderError",
    "ColumnSpec",
    "DELIMITERS",
    "decode",
    "split_lines",
    "sniff_delimiter",
    "split_cells",
    "split_rows",
    "Table",
    "resolve_column",
]

#: A column chosen by name (exact, then case-insensitive, then the part after the last ``.``) or by its
#: 1-based position (an ``int`` or a string of digits that is not itself a column name).
ColumnSpec = str | int

#: Delimiters tried by :func:`sniff_delimiter`, in order of preference when several fit.
DELIMITERS: Final = ("\t", ";", ",", "|")

_NUMBER: Final = re.compile(r"\s*[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\s*")
_TIME_FORMATS: Final = ("%Y/%m/%d %H:%M:%S", "%Y/%m/%d %H:%M:%S.%f", "%Y/%m/%d %H:%M")


class ReaderError(RecordingError):
    """A file that cannot be read as a recording; the message names the file and what was expected.

    A :class:`~valve_emulator.recordings.recording.RecordingError` (hence a ``ValueError``), so callers that already
    handle bad standard recordings handle these too.
    """


def decode(data: bytes, source: str, encoding: str = "utf-8") -> str:
    """Decode a whole file strictly; a byte-order mark is dropped.

    A file that is not valid in ``encoding`` is refused with the byte offset and line of the first bad byte.
    When the bytes before it already held valid non-ASCII UTF-8 text the file mixes encodings (typically a UTF-8
    export with rows pasted from a GBK or Latin-1 editor); the message says so, because no single ``encoding``
    can then read it.
    """
    try:
        text = data.decode(encoding)
    except LookupError:
        raise ReaderError(f"{source}: unknown text encoding {encoding!r}") from None
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        bad = data[exc.start:exc.start + 4].hex(" ")
        utf8 = encoding.lower().replace("-", "").replace("_", "") == "utf8"
        name = "UTF-8" if utf8 else encoding
        msg = (f"{source}: line {line}: not {name} text at byte offset {exc.start} (bytes {bad}: "
               f"{exc.reason}); expected the whole file in {name}")
        if utf8:
            # Whole earlier lines that decode to non-ASCII text mean the file started out as UTF-8; a stray
            # pair of bytes on the failing line itself proves nothing (a GBK pair can look like UTF-8).
            head = data[:data.rfind(b"\n", 0, exc.start) + 1]
            if any(b > 0x7F for b in head):
                msg += ("; the lines before it are UTF-8 with non-ASCII characters, so the file mixes "
                        "encodings (re-export it in one encoding)")
            else:
                msg += " (pass encoding=... if the whole file is in another encoding, e.g. 'gb18030')"
        raise ReaderError(msg) from None
    return text.removeprefix("\ufeff")


def split_lines(text: str, source: str) -> list[str]:
    """Lines without terminators (``\\n``, ``\\r\\n`` or ``\\r``); trailing blank lines dropped.

    Only these end a line: ``str.splitlines`` would also split at form feeds or U+2028 inside a cell.
    """
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise ReaderError(f"{source}: line 1: the file is empty")
    return lines


def sniff_delimiter(lines: Sequence[str], *, decimal: str = ".") -> str | None:
    """The delimiter that splits the first lines into the same number (≥ 2) of cells, or ``None``.

    Up to 20 non-blank lines are looked at. ``,`` is not considered with a decimal comma. Among the delimiters
    that fit, the one giving the most columns wins (ties: the order of :data:`DELIMITERS`).
    """
    sample = [ln for ln in lines[:40] if ln.strip()][:20]
    best, best_n = None, 1
    for d in DELIMITERS:
        if d == decimal:
            continue
        counts = {len(split_cells(ln, d)) for ln in sample}
        if len(counts) == 1 and (n := counts.pop()) > best_n:
            best, best_n = d, n
    return best


def split_cells(line: str, delimiter: str) -> list[str]:
    """Cells of one line, quotes handled as in CSV, surrounding spaces stripped."""
    return [c.strip() for c in next(csv.reader([line], delimiter=delimiter), [""])]


def split_rows(lines: Sequence[str], delimiter: str) -> list[list[str]]:
    """Cells of many lines (not stripped: :class:`Table` strips the cells it reads)."""
    return list(csv.reader(lines, delimiter=delimiter))


class Table:
    """Rows of cells with their line numbers, for parsing columns with precise messages.

    Parameters
    ----------
    source : file name used in messages.
    names : column names (from the header line, or ``"1"``, ``"2"``, … without one).
    rows : the data rows as lists of cells.
    first_line : 1-based line number of ``rows[0]`` in the file.
    """

    def __init__(self, source: str, names: Sequence[str], rows: list[list[str]], first_line: int) -> None:
        self.source, self.names, self.rows, self.first_line = source, list(names), rows, first_line

    def __len__(self) -> int:
        return len(self.rows)

    def where(self, i: int, j: int | None = None) -> str:
        loc = f"{self.source}: line {self.first_line + i}"
        if j is not None:
            loc += f", column {self.names[j]!r} ({j + 1})"
        return loc

    def cells(self, j: int) -> list[str]:
        """Column ``j`` (0-based); a row too short for it is an error."""
        out = []
        for i, row in enumerate(self.rows):
            if j >= len(row):
                raise ReaderError(f"{self.where(i)}: expected at least {j + 1} cells for column "
                                  f"{self.names[j]!r}, found {len(row)}")
            out.append(row[j].strip())
        return out

    def numbers(self, j: int, *, decimal: str = ".", required: bool = True) -> np.ndarray:
        """Column ``j`` as float64. Empty cells are NaN unless ``required``; values must be finite.

        Accepted: optional sign, digits with one decimal mark (``decimal``), optional exponent. Text such as
        ``nan``, ``inf``, ``1_000`` or ``1.5`` with a decimal comma is refused with its line and column.
        """
        cells = self.cells(j)
        values = np.full(len(cells), np.nan)
        for i, c in enumerate(cells):
            if not c:
                if required:
                    raise ReaderError(f"{self.where(i, j)}: empty cell; {self.names[j]!r} needs a number in "
                                      "every row")
                continue
            text = c
            if decimal != ".":
                if "." in c:
                    raise ReaderError(f"{self.where(i, j)}: not a number: {c!r} (decimal={decimal!r} was "
                                      "given, so '.' is not accepted)")
                text = c.replace(decimal, ".")
            if _NUMBER.fullmatch(text) is None:
                hint = ""
                if decimal == "." and re.fullmatch(r"[+-]?\d+,\d+", c):
                    hint = " (a decimal comma? pass decimal=',')"
                raise ReaderError(f"{self.where(i, j)}: not a number: {c!r}{hint}")
            values[i] = float(text)
        bad = np.flatnonzero(np.isinf(values))
        if bad.size:  # an overflowing exponent such as 1e999
            i = int(bad[0])
            raise ReaderError(f"{self.where(i, j)}: number out of range: {self.rows[i][j]!r}")
        return values

    def times(self, j: int) -> np.ndarray:
        """Column ``j`` as time in seconds: plain numbers are seconds, otherwise date-times.

        Date-times are ISO 8601 (``2024-06-27 21:55:00``, ``2024-06-27T21:55:00.5``, with or without a UTC
        offset) or ``YYYY/MM/DD HH:MM[:SS[.f]]``; they are returned as POSIX seconds (naive stamps taken as
        UTC, so only differences matter). All cells of the column must be of the same kind.
        """
        cells = self.cells(j)
        if cells and _NUMBER.fullmatch(cells[0]):
            return self.numbers(j)
        out = np.empty(len(cells))
        for i, c in enumerate(cells):
            stamp = _parse_datetime(c)
            if stamp is None:
                raise ReaderError(f"{self.where(i, j)}: not a time: {c!r} (expected a date-time such as "
                                  "'2024-06-27 21:55:00', or seconds in every row)")
            out[i] = stamp
        return out


def _parse_datetime(cell: str) -> float | None:
    try:
        dt = datetime.fromisoformat(cell)
    except ValueError:
        dt = None
        for fmt in _TIME_FORMATS:
            try:
                dt = datetime.strptime(cell, fmt)
                break
            except ValueError:
                continue
    if dt is None:
        return None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.timestamp()


def resolve_column(spec: ColumnSpec, names: Sequence[str], *, role: str, source: str) -> int:
    """0-based index of the column that ``spec`` names, for the reader argument ``role`` (``op``, …).

    Order: an ``int`` is a 1-based position; a string equal to a column name; equal ignoring case; equal to
    the part of exactly one name after its last ``.`` (so ``"PV"`` finds ``FIC101.PV``); a string of digits is a
    1-based position. Anything else is an error listing the available columns.
    """
    available = ", ".join(f"{k + 1}: {n!r}" for k, n in enumerate(names))
    if isinstance(spec, bool) or not isinstance(spec, (int, str)):
        raise ReaderError(f"{source}: {role}= must be a column name or a 1-based column number, got {spec!r}")
    if isinstance(spec, str):
        exact = [k for k, n in enumerate(names) if n == spec]
        if len(exact) > 1:
            raise ReaderError(f"{source}: {role}={spec!r} names {len(exact)} columns "
                              f"({', '.join(str(k + 1) for k in exact)}); give its number instead")
        if exact:
            return exact[0]
        for matcher in (lambda n: n.lower() == spec.lower(),
                        lambda n: n.rsplit(".", 1)[-1].lower() == spec.lower()):
            hits = [k for k, n in enumerate(names) if matcher(n)]
            if len(hits) == 1:
                return hits[0]
            if len(hits) > 1:
                raise ReaderError(f"{source}: {role}={spec!r} matches several columns "
                                  f"({', '.join(repr(names[k]) for k in hits)}); give the full name")
        if not spec.strip().isdigit():
            raise ReaderError(f"{source}: {role}={spec!r}: no such column; the columns are {available}")
        spec = int(spec)
    if not 1 <= spec <= len(names):
        raise ReaderError(f"{source}: {role}={spec}: column numbers are 1-based and the file has "
                          f"{len(names)} columns ({available})")
    return spec - 1
