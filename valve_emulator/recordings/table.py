"""Rows of cells with their line numbers: numbers, times and column choices read with precise messages.

Every reader builds one :class:`Table` from its data lines (:meth:`Table.from_lines`) and reads the columns it
needs from it. A cell that is not a number is an error naming the file, the line (1-based, as an editor counts)
and the column, never a silent NaN.

Two number syntaxes (:class:`NumberSyntax`)
-------------------------------------------
``DECIMAL``, for plant exports: optional sign, digits with one decimal mark (``.`` or ``,``), optional
exponent; ``nan``, ``inf``, ``1_000`` or a value too large for a double are refused. ``PYTHON``, for the
project's standard recording: whatever Python's ``float`` reads, so that the ``repr`` of every double --
``inf`` and ``nan`` included -- reads back to the same double.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Final

import numpy as np

from valve_emulator.recordings.errors import ReaderError
from valve_emulator.recordings.text import located, split_columns, split_rows

__all__ = ["ColumnSpec", "NumberSyntax", "Table", "resolve_column"]

#: A column chosen by name (exact, then case-insensitive, then the part after the last ``.``) or by its
#: 1-based position (an ``int`` or a string of digits that is not itself a column name).
ColumnSpec = str | int

_DECIMAL: Final = re.compile(r"\s*[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\s*")
#: Characters of a column of DECIMAL numbers (the cells joined by newlines): text made only of these that
#: ``float`` reads is exactly what :data:`_DECIMAL` accepts, so a whole column is checked in one pass.
_DECIMAL_TEXT: Final = {".": re.compile(r"[0-9eE+\-. \t\n]*"), ",": re.compile(r"[0-9eE+\-, \t\n]*")}
_TIME_FORMATS: Final = ("%Y/%m/%d %H:%M:%S", "%Y/%m/%d %H:%M:%S.%f", "%Y/%m/%d %H:%M")


class NumberSyntax(enum.Enum):
    """How a cell writes a number (see the module docstring)."""

    DECIMAL = "decimal"
    PYTHON = "python"


class Table:
    """Rows of cells with their line numbers, for parsing columns with precise messages.

    Parameters
    ----------
    source : file name used in messages.
    names : column names (from the header line, or ``"1"``, ``"2"``, … without one).
    rows : the data rows as lists of cells (not necessarily stripped).
    first_line : 1-based line number of ``rows[0]`` in the file.
    """

    def __init__(self, source: str, names: Sequence[str], rows: list[list[str]], first_line: int) -> None:
        self.source, self.names, self.first_line = source, list(names), first_line
        self._rows: list[list[str]] | None = rows
        self._columns: list[list[str]] | None = None
        self._n = len(rows)

    @classmethod
    def from_lines(cls, source: str, names: Sequence[str], lines: Sequence[str], delimiter: str, *,
                   first_line: int) -> Table:
        """The table of data ``lines`` split at ``delimiter`` (see :mod:`~valve_emulator.recordings.text`)."""
        columns = split_columns(lines, delimiter)
        if columns is None:
            return cls(source, names, split_rows(lines, delimiter), first_line)
        table = cls(source, names, [], first_line)
        table._rows, table._columns, table._n = None, columns, len(lines)
        return table

    def __len__(self) -> int:
        return self._n

    @property
    def rows(self) -> list[list[str]]:
        """The rows as lists of cells (built on first use when the table was stored by column)."""
        if self._rows is None:
            self._rows = [list(row) for row in zip(*self._columns)]
        return self._rows

    def cell(self, i: int, j: int) -> str:
        """Row ``i``, column ``j`` (0-based), stripped."""
        return (self._columns[j][i] if self._columns is not None else self.rows[i][j]).strip()

    def error(self, what: str, i: int, j: int | None = None) -> ReaderError:
        """The error ``file: line L, column 'name' (k): what`` for row ``i`` and column ``j`` (0-based), carrying
        the file, line and column name as attributes."""
        return located(self.source, what, line=self.first_line + i,
                       column=None if j is None else self.names[j], number=None if j is None else j + 1)

    def refuse_blank_rows(self) -> None:
        """A row of blank cells is an error: blank lines are allowed only at the end of a file."""
        for i, row in enumerate(self.rows if self._columns is None else zip(*self._columns)):
            if not any(c.strip() for c in row):
                raise self.error("blank line inside the data", i)

    def refuse_ragged_rows(self) -> None:
        """Every row must have exactly one cell per column name."""
        ncol = len(self.names)
        if self._columns is not None and len(self._columns) == ncol:
            return
        for i, row in enumerate(self.rows):
            if len(row) == ncol:
                continue
            if not any(c.strip() for c in row):
                raise self.error("blank line inside the data", i)
            if len(row) < ncol:
                what = f"column {self.names[len(row)]!r} ({len(row) + 1}) is missing"
            else:
                what = f"cell {ncol + 1} is beyond the last column {self.names[-1]!r}"
            raise self.error(f"expected {ncol} cells, found {len(row)} ({what})", i)

    def raw(self, j: int) -> list[str]:
        """Column ``j`` (0-based) as written, spaces included; a row too short for it is an error."""
        if self._columns is not None and j < len(self._columns):
            return self._columns[j]
        try:
            return [row[j] for row in self.rows]
        except IndexError:
            i = next(i for i, row in enumerate(self.rows) if j >= len(row))
            raise self.error(f"expected at least {j + 1} cells for column {self.names[j]!r}, found "
                             f"{len(self.rows[i])}", i) from None

    def cells(self, j: int) -> list[str]:
        """Column ``j`` (0-based), each cell stripped; a row too short for it is an error."""
        return [c.strip() for c in self.raw(j)]

    def numbers(self, j: int, *, syntax: NumberSyntax = NumberSyntax.DECIMAL, decimal: str = ".",
                required: bool = True) -> np.ndarray:
        """Column ``j`` as float64; empty cells are NaN unless ``required``.

        With ``syntax=DECIMAL`` (``decimal`` is its decimal mark) every value must also be finite; with
        ``PYTHON`` a cell may say ``inf`` or ``nan`` (``decimal`` must then be ``"."``). The first offending
        cell is named with its line and column.
        """
        raw = self.raw(j)
        values = _convert(raw, syntax, decimal, required)
        if values is None:  # some cell is empty, or not a number: find the first one and say so
            values = np.array([self._number(c, i, j, syntax, decimal, required) for i, c in enumerate(raw)],
                              dtype=np.float64)
        if syntax is NumberSyntax.DECIMAL and (bad := np.flatnonzero(np.isinf(values))).size:
            i = int(bad[0])  # an exponent such as 1e999 overflows
            raise self.error(f"number out of range: {raw[i].strip()!r}", i, j)
        return values

    def _number(self, cell: str, i: int, j: int, syntax: NumberSyntax, decimal: str, required: bool) -> float:
        """One cell's value, or the error that names it (the slow path of :meth:`numbers`)."""
        c = cell.strip()
        if not c:
            if required:
                raise self.error(f"empty cell; {self.names[j]} is required in every row", i, j)
            return np.nan
        if syntax is NumberSyntax.PYTHON:
            try:
                return float(c)
            except ValueError:
                raise self.error(f"not a number: {c!r}", i, j) from None
        text = c
        if decimal != ".":
            if "." in c:
                raise self.error(f"not a number: {c!r} (decimal={decimal!r} was given, so '.' is not "
                                 "accepted)", i, j)
            text = c.replace(decimal, ".")
        if _DECIMAL.fullmatch(text) is None:
            hint = " (a decimal comma? pass decimal=',')" if decimal == "." and re.fullmatch(r"[+-]?\d+,\d+", c) \
                else ""
            raise self.error(f"not a number: {c!r}{hint}", i, j)
        return float(text)

    def times(self, j: int, *, decimal: str = ".") -> np.ndarray:
        """Column ``j`` as time in seconds: plain numbers are seconds (with the file's ``decimal`` mark),
        otherwise date-times.

        Date-times are ISO 8601 (``2024-06-27 21:55:00``, ``2024-06-27T21:55:00.5``, with or without a UTC
        offset) or ``YYYY/MM/DD HH:MM[:SS[.f]]``; they are returned as POSIX seconds (naive stamps taken as
        UTC, so only differences matter). All cells of the column must be of the same kind.
        """
        cells = self.cells(j)
        if cells and _DECIMAL.fullmatch(cells[0].strip().replace(decimal, ".")):
            return self.numbers(j, decimal=decimal)
        out = np.empty(len(cells))
        for i, c in enumerate(cells):
            stamp = _parse_datetime(c)
            if stamp is None:
                raise self.error(f"not a time: {c!r} (expected a date-time such as '2024-06-27 21:55:00', or "
                                 "seconds in every row)", i, j)
            out[i] = stamp
        return out


def _convert(cells: list[str], syntax: NumberSyntax, decimal: str, required: bool) -> np.ndarray | None:
    """All cells at once (numpy reads text as ``float`` does), or None when some cell needs a closer look."""
    if syntax is NumberSyntax.DECIMAL:
        text = "\n".join(cells)
        if _DECIMAL_TEXT[decimal].fullmatch(text) is None:
            return None
        if decimal != ".":
            cells = text.replace(decimal, ".").split("\n")
    try:
        return np.array(cells, dtype=np.float64)
    except ValueError:
        if required:
            return None
    try:  # empty cells are allowed here: NaN
        return np.array([c if c.strip() else "nan" for c in cells], dtype=np.float64)
    except ValueError:
        return None


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
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()


def resolve_column(spec: ColumnSpec, names: Sequence[str], *, role: str, source: str) -> int:
    """0-based index of the column that ``spec`` names, for the reader argument ``role`` (``op``, …).

    Order: an ``int`` is a 1-based position; a string equal to a column name; equal ignoring case; equal to
    the part of exactly one name after its last ``.`` (so ``"PV"`` finds ``FIC101.PV``); a string of digits is a
    1-based position. Anything else is an error listing the available columns.
    """
    available = ", ".join(f"{k + 1}: {n!r}" for k, n in enumerate(names))
    if isinstance(spec, bool) or not isinstance(spec, (int, str)):
        raise ReaderError(f"{source}: {role}= must be a column name or a 1-based column number, got {spec!r}",
                          source=source)
    if isinstance(spec, str):
        exact = [k for k, n in enumerate(names) if n == spec]
        if len(exact) > 1:
            raise ReaderError(f"{source}: {role}={spec!r} names {len(exact)} columns "
                              f"({', '.join(str(k + 1) for k in exact)}); give its number instead", source=source)
        if exact:
            return exact[0]
        for matcher in (lambda n: n.lower() == spec.lower(),
                        lambda n: n.rsplit(".", 1)[-1].lower() == spec.lower()):
            hits = [k for k, n in enumerate(names) if matcher(n)]
            if len(hits) == 1:
                return hits[0]
            if len(hits) > 1:
                raise ReaderError(f"{source}: {role}={spec!r} matches several columns "
                                  f"({', '.join(repr(names[k]) for k in hits)}); give the full name", source=source)
        if not spec.strip().isdigit():
            raise ReaderError(f"{source}: {role}={spec!r}: no such column; the columns are {available}",
                              source=source)
        spec = int(spec)
    if not 1 <= spec <= len(names):
        raise ReaderError(f"{source}: {role}={spec}: column numbers are 1-based and the file has "
                          f"{len(names)} columns ({available})", source=source)
    return spec - 1
