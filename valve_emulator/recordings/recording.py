"""The standard recording: one loop's ``t, sp, op, mv, pv`` (+ extra columns) in memory and as CSV.

File format
-----------
UTF-8 text, ``\\n`` line ends (``\\r\\n`` and ``\\r`` are accepted on reading), one header line, then one row
per sample::

    t,sp,op,mv,pv[,extra...]
    0.0,50.0,47.5,46.0,50.0
    0.1,50.0,47.6,,50.01

* ``t`` in seconds, strictly increasing, finite; ``op`` and ``mv`` in % of valve travel; ``pv`` and ``sp`` in
  engineering units.
* ``t``, ``op`` and ``pv`` are required and every cell of them must be a finite number. ``sp`` and ``mv`` may
  be left out or have empty cells (a loop without set point, a valve without position feedback); they are
  read as NaN. Extra columns follow in any order; empty cells there are NaN too.
* Written floats use ``repr`` (shortest text that reads back to the same double), so the same data always
  gives byte-identical files and a write/read round trip is exact. NaN is written as an empty cell.

Reading goes through the package's one text parser (:mod:`~valve_emulator.recordings.text`,
:mod:`~valve_emulator.recordings.table`; numbers in its ``PYTHON`` syntax, so ``inf`` and ``nan`` read back)
and raises :class:`~valve_emulator.recordings.errors.ReaderError` (a :class:`RecordingError`) naming the file,
the line (1-based, as an editor counts, the header being line 1) and the column for: undecodable UTF-8 (with
the byte offset), an empty file, missing required columns, duplicate or empty column names, ragged rows,
non-numeric cells, missing values in required columns, non-finite ``t``, ``t`` that repeats or goes back, gaps
in ``t`` (a step larger than ``gap_factor`` times the median step) and too few rows. A last line without its
newline -- a process killed in the middle of a write -- is kept if it is a complete, valid row and otherwise
dropped with a :class:`RecordingWarning`.
"""

from __future__ import annotations

import math
import os
import types
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Final

import numpy as np
from numpy.typing import ArrayLike

from valve_emulator.recordings.errors import (
    ReaderError,
    RecordingError,
    RecordingWarning,
)
from valve_emulator.recordings.table import NumberSyntax, Table
from valve_emulator.recordings.text import (
    decode,
    located,
    split_cells,
    split_terminated,
)

__all__ = [
    "CORE_COLUMNS",
    "first_gap",
    "Recording",
    "RecordingError",
    "ReaderError",
    "RecordingWarning",
    "write_csv",
    "CsvRecordingWriter",
    "read_csv",
]

CORE_COLUMNS: Final = ("t", "sp", "op", "mv", "pv")
_REQUIRED: Final = ("t", "op", "pv")  # sp and mv may be absent
_FORBIDDEN_IN_NAMES: Final = frozenset(',"\r\n')


def _frozen_array(x: ArrayLike | None, name: str, n: int | None, *, optional: bool = False) -> np.ndarray:
    """1-D read-only float64 array of length ``n`` (all-NaN for ``None`` when ``optional``).

    No copy is made when ``x`` already is a read-only float64 array whose memory nobody can write through
    (as the columns of another Recording are), so :meth:`Recording.slice` returns views.
    """
    if x is None:
        if not optional or n is None:
            raise ValueError(f"{name} is required")
        return _readonly(np.full(n, np.nan))
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} samples but t has {n}")
    base = arr
    while isinstance(base, np.ndarray):
        if base.flags.writeable:
            return _readonly(arr.copy())
        base = base.base
    return arr


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _check_column_name(name: object) -> str:
    if not isinstance(name, str) or not name or name != name.strip() or _FORBIDDEN_IN_NAMES & set(name):
        raise ValueError(
            f"column name {name!r} is not usable: it must be a non-empty string without commas, quotes, "
            "line breaks or surrounding spaces")
    if name in CORE_COLUMNS:
        raise ValueError(f"extra column {name!r} clashes with a standard column ({', '.join(CORE_COLUMNS)})")
    return name


@dataclass(frozen=True, eq=False)  # eq=False: element-wise array comparison has no single truth value
class Recording:
    """One loop's samples. All arrays are float64, one-dimensional, the same length and read-only.

    Parameters
    ----------
    t : sample times, s.
    sp, op, mv, pv : set point, controller output (% travel), valve position (% travel), process value.
        ``sp`` and ``mv`` may be ``None`` (stored as all-NaN) when the data do not have them.
    extra : further named columns, kept in the given order.
    source : where the data came from (a file name), used in messages.
    """

    t: np.ndarray
    sp: np.ndarray | None
    op: np.ndarray
    mv: np.ndarray | None
    pv: np.ndarray
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        t = _frozen_array(self.t, "t", None)
        n = t.shape[0]
        values = {"t": t}
        for name in ("sp", "op", "mv", "pv"):
            values[name] = _frozen_array(getattr(self, name), name, n, optional=name in ("sp", "mv"))
        extra = {}
        for name, col in dict(self.extra).items():
            extra[_check_column_name(name)] = _frozen_array(col, name, n)
        for name, arr in values.items():
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "extra", types.MappingProxyType(extra))
        object.__setattr__(self, "source", str(self.source))

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def columns(self) -> tuple[str, ...]:
        """Column names in file order: the five standard ones, then the extra ones."""
        return CORE_COLUMNS + tuple(self.extra)

    def column(self, name: str) -> np.ndarray:
        """The column called ``name`` (standard or extra)."""
        if name in CORE_COLUMNS:
            return getattr(self, name)
        try:
            return self.extra[name]
        except KeyError:
            raise KeyError(f"{self.source or 'recording'} has no column {name!r}; "
                           f"columns are {', '.join(self.columns)}") from None

    @property
    def dt(self) -> float:
        """Sample step, s: the median of the steps of ``t`` (robust to a few irregular ones)."""
        if len(self) < 2:
            raise ValueError(f"{self.source or 'recording'}: dt needs at least 2 samples, has {len(self)}")
        return float(np.median(np.diff(self.t)))

    @property
    def has_sp(self) -> bool:
        """True when ``sp`` holds at least one number."""
        return bool(np.any(~np.isnan(self.sp)))

    @property
    def has_mv(self) -> bool:
        """True when ``mv`` holds at least one number."""
        return bool(np.any(~np.isnan(self.mv)))

    def slice(self, i0: int | None, i1: int | None) -> Recording:
        """Rows ``i0`` to ``i1 - 1`` (Python slice rules, negative indices allowed); arrays are views."""
        s = slice(i0, i1)
        return Recording(self.t[s], self.sp[s], self.op[s], self.mv[s], self.pv[s],
                         extra={k: v[s] for k, v in self.extra.items()}, source=self.source)


# --------------------------------------------------------------------------------------------- writing

def _cell(x: float) -> str:
    return "" if math.isnan(x) else repr(x)


def _column_cells(col: np.ndarray) -> list[str]:
    """``repr`` of every value, ``""`` for NaN; tolist() gives Python floats, whose repr is the short one."""
    cells = list(map(repr, col.tolist()))
    for i in np.flatnonzero(np.isnan(col)).tolist():
        cells[i] = ""
    return cells


def _format_row(values: Sequence[float]) -> str:
    return ",".join(_cell(float(v)) for v in values) + "\n"


def write_csv(rec: Recording, path_or_file: str | os.PathLike | IO[str]) -> None:
    """Write ``rec`` in the standard format to a path (overwritten) or an open text file.

    The header is ``t,sp,op,mv,pv`` followed by the extra columns; see the module docstring for the format.
    """
    cols = [rec.t, rec.sp, rec.op, rec.mv, rec.pv, *rec.extra.values()]
    header = ",".join(rec.columns) + "\n"
    body = "".join(line + "\n" for line in map(",".join, zip(*(_column_cells(c) for c in cols))))
    if isinstance(path_or_file, (str, os.PathLike)):
        with open(path_or_file, "w", encoding="utf-8", newline="") as fh:
            fh.write(header)
            fh.write(body)
    else:
        path_or_file.write(header)
        path_or_file.write(body)


class CsvRecordingWriter:
    """Write a recording row by row, flushing every line, so that a reader sees whole rows as they come.

    Each row goes out in one ``write`` followed by ``flush`` (and ``os.fsync`` when ``fsync=True``, for
    data that must survive a power cut; it costs a disk round trip per row). A process killed mid-write
    leaves at most one partial last line, which :func:`read_csv` drops with a warning.

    Parameters
    ----------
    path : file to create (overwritten if it exists).
    extra_columns : names of further columns after ``t,sp,op,mv,pv``.
    fsync : also ``os.fsync`` after every row.

    Examples
    --------
    >>> with CsvRecordingWriter(path, extra_columns=("flow",)) as w:   # doctest: +SKIP
    ...     w.write_row(0.0, 50.0, 47.5, float("nan"), 50.0, 47.5)
    """

    def __init__(self, path: str | os.PathLike, *, extra_columns: Sequence[str] = (),
                 fsync: bool = False) -> None:
        self.path = Path(path)
        self.extra_columns = tuple(_check_column_name(c) for c in extra_columns)
        if len(set(self.extra_columns)) != len(self.extra_columns):
            raise ValueError(f"extra_columns has duplicate names: {self.extra_columns!r}")
        self.fsync = bool(fsync)
        self.rows_written = 0
        self._fh: IO[str] | None = None
        self._last_t = -math.inf

    @property
    def closed(self) -> bool:
        return self._fh is None

    def open(self) -> CsvRecordingWriter:
        """Create the file and write the header; returns ``self``."""
        if self._fh is not None:
            raise ValueError(f"{self.path} is already open")
        self._fh = open(self.path, "w", encoding="utf-8", newline="")  # noqa: SIM115 - held open row by row until close()
        self.rows_written = 0
        self._last_t = -math.inf
        self._emit(",".join(CORE_COLUMNS + self.extra_columns) + "\n")
        return self

    def write_row(self, t: float, sp: float, op: float, mv: float, pv: float, *extra: float) -> None:
        """Append one sample. ``sp``/``mv``/extras may be NaN (written empty).

        Raises ``ValueError`` and writes nothing if the writer is closed, the number of extra values is not
        ``len(extra_columns)``, ``t`` is not finite or not after the previous ``t``, or ``op``/``pv`` is not
        finite -- rows that :func:`read_csv` would reject.
        """
        if self._fh is None:
            raise ValueError(f"{self.path}: write_row on a closed writer (call open() or use 'with')")
        if len(extra) != len(self.extra_columns):
            raise ValueError(f"{self.path}: expected {len(self.extra_columns)} extra values "
                             f"({', '.join(self.extra_columns) or 'none'}), got {len(extra)}")
        t, op, pv = float(t), float(op), float(pv)
        if not math.isfinite(t) or t <= self._last_t:
            raise ValueError(f"{self.path}: t must be finite and increase, got {t!r} after {self._last_t!r}")
        for name, v in (("op", op), ("pv", pv)):
            if not math.isfinite(v):
                raise ValueError(f"{self.path}: {name} must be finite, got {v!r} at t={t!r}")
        self._emit(_format_row((t, sp, op, mv, pv, *extra)))
        self._last_t = t
        self.rows_written += 1

    def _emit(self, line: str) -> None:
        assert self._fh is not None
        self._fh.write(line)
        self._fh.flush()
        if self.fsync:
            os.fsync(self._fh.fileno())

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._fh is not None:
            fh, self._fh = self._fh, None
            fh.close()

    def __enter__(self) -> CsvRecordingWriter:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------------- reading

def _parse_header(source: str, line: str) -> list[str]:
    names = split_cells(line, ",")
    seen: dict[str, int] = {}
    for j, name in enumerate(names):
        if not name:
            raise located(source, "empty column name", line=1, number=j + 1)
        if name in seen:
            raise located(source, f"duplicate of column {seen[name] + 1}", line=1, column=name, number=j + 1)
        if name not in CORE_COLUMNS:
            try:
                _check_column_name(name)
            except ValueError as exc:
                raise located(source, str(exc), line=1, number=j + 1) from None
        seen[name] = j
    for name in _REQUIRED:
        if name not in seen:
            raise located(source, f"missing required column (the header must contain {', '.join(_REQUIRED)}; "
                                  f"found {', '.join(names)})", line=1, column=name)
    return names


def first_gap(steps: np.ndarray, gap_factor: float | None) -> tuple[int, float] | None:
    """``(i, median)`` for the first time step longer than ``gap_factor`` × the median step: row ``i`` follows
    the gap (step ``steps[i - 1]``). None when there is no such step, no step, or ``gap_factor`` is None."""
    if gap_factor is None or not steps.size:
        return None
    median = float(np.median(steps))
    gaps = np.flatnonzero(steps > gap_factor * median)
    return (int(gaps[0]) + 1, median) if gaps.size else None


def _columns(table: Table, gap_factor: float | None) -> dict[str, np.ndarray]:
    """Check every cell and the time axis; return the columns as float arrays."""
    table.refuse_ragged_rows()
    out = {name: table.numbers(j, syntax=NumberSyntax.PYTHON, required=name in _REQUIRED)
           for j, name in enumerate(table.names)}
    for name in _REQUIRED:
        bad = np.flatnonzero(~np.isfinite(out[name]))
        if bad.size:
            i, j = int(bad[0]), table.names.index(name)
            raise table.error(f"{name} must be finite, got {table.cell(i, j)!r}", i, j)
    t, jt = out["t"], table.names.index("t")
    steps = np.diff(t)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        i = int(back[0]) + 1
        verb = "repeats" if steps[i - 1] == 0 else "goes back from"
        raise table.error(f"t must increase strictly; t = {float(t[i])!r} {verb} t = {float(t[i - 1])!r} on "
                          f"line {table.first_line + i - 1}", i, jt)
    if (gap := first_gap(steps, gap_factor)) is not None:
        i, median = gap
        raise table.error(f"gap in t: step of {float(steps[i - 1])!r} s from line {table.first_line + i - 1} "
                          f"is more than {gap_factor!r} x the median step {median!r} s", i, jt)
    return out


def read_csv(path: str | os.PathLike, *, min_samples: int = 2, gap_factor: float | None = 1.5) -> Recording:
    """Read and check a recording in the standard CSV format (see the module docstring).

    Parameters
    ----------
    path : the CSV file.
    min_samples : fewest data rows accepted (default 2, the least that has a sample step).
    gap_factor : a step of ``t`` larger than this times the median step is a gap and an error; ``None``
        accepts irregular sampling.

    Returns
    -------
    Recording
        With ``source`` set to ``str(path)``; absent ``sp``/``mv`` are all-NaN, extra columns in file order.

    Raises
    ------
    ReaderError
        (a :class:`RecordingError`) for every defect listed in the module docstring; the message names the
        file, line and column, which the error also carries as attributes.
    ValueError
        For a bad ``min_samples`` or ``gap_factor``.
    OSError
        When the file cannot be read at all.
    """
    if isinstance(min_samples, bool) or not isinstance(min_samples, (int, np.integer)) or min_samples < 0:
        raise ValueError(f"min_samples must be an integer >= 0, got {min_samples!r}")
    if gap_factor is not None and not (math.isfinite(gap_factor) and gap_factor > 1):
        raise ValueError(f"gap_factor must be a finite number > 1 or None, got {gap_factor!r}")
    source = str(path)
    text = decode(Path(path).read_bytes(), source, other_encodings=False)
    lines, rest = split_terminated(text, source)
    names = _parse_header(source, lines[0])
    table = Table.from_lines(source, names, lines[1:], ",", first_line=2)
    cols = _columns(table, gap_factor)
    if rest is not None:
        # A last line without newline may be a write cut short: keep it only if the whole file still checks.
        longer = Table.from_lines(source, names, lines[1:] + [rest], ",", first_line=2)
        try:
            cols = _columns(longer, gap_factor)
            table = longer
        except RecordingError as exc:
            warnings.warn(f"{source}: line {len(lines) + 1}: dropped an incomplete last line (no newline at end "
                          f"of file): {exc}", RecordingWarning, stacklevel=2)
    for arr in cols.values():
        _readonly(arr)  # so that Recording keeps these arrays without copying them
    n = len(table)
    if n < min_samples:
        raise located(source, f"{n} data row(s), at least min_samples={min_samples} needed",
                      line=table.first_line + n - 1)
    extra = {name: cols[name] for name in names if name not in CORE_COLUMNS}
    return Recording(cols["t"], cols.get("sp"), cols["op"], cols.get("mv"), cols["pv"], extra=extra,
                     source=source)
