r"""What a reader returns, and the steps every format shares: time axis, units, AUTO/MANUAL segments.

Segments
--------
When the file has a mode column, only samples in automatic mode describe the closed loop. Each maximal run of
AUTO samples is an *AUTO segment*; each run of other samples is an *excluded* segment, reported as
``(t_start, t_end)``: the times of its first and last sample. :attr:`LoadedRecording.recording` is the
**longest AUTO segment** (the earliest of equally long ones), because the diagnosis fits one continuous record;
:meth:`LoadedRecording.segments` gives all of them for a caller that wants to look at each.

PV scale
--------
``pv_scale`` is the robust range of PV on the returned segment, the 99.5th minus the 0.5th percentile, in the
file's PV units. A diagnosis divides by it to work on a unit-free PV and multiplies back when it reports
(``0.0`` for a flat PV, which no diagnosis can use).
"""

from __future__ import annotations

import enum
import types
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np

from valve_emulator.physics.signal_chain import DEFAULT_MA_TABLE, LookupTable
from valve_emulator.recordings.errors import ReaderError
from valve_emulator.recordings.recording import Recording, first_gap
from valve_emulator.recordings.table import Table

__all__ = [
    "Format",
    "OP_UNITS",
    "DEFAULT_AUTO_VALUES",
    "LoadedRecording",
    "Parsed",
    "time_axis",
    "auto_mask",
    "signal_columns",
    "finish",
]


class Format(enum.StrEnum):
    """A recording file's format, as ``read_recording(fmt=...)`` and ``--format`` name it (compares equal to
    those strings)."""

    AUTO = "auto"  #: detect it (:func:`~valve_emulator.recordings.reader.detect_format`); a request, never a result
    STANDARD = "standard"  #: the project's recording CSV (:mod:`~valve_emulator.recordings.recording`)
    CSV = "csv"  #: generic delimited text with a column mapping (:mod:`~valve_emulator.recordings.delimited`)
    DCS = "dcs"  #: the DCS text export (:mod:`~valve_emulator.recordings.dcs`)


OP_UNITS: Final = ("%", "mA")
#: Mode cells meaning "the controller is closing the loop" (compared case-insensitively; numbers by value):
#: ``1`` is the DCS export's AUTO flag (``.MODE`` described as ``Aut``), the words are common DCS mode names.
DEFAULT_AUTO_VALUES: Final = ("1", "AUTO", "AUT", "CAS", "CASCADE")
#: DCS stamps may be off the declared grid by up to this many samples (see :func:`time_axis`).
_GRID_TOLERANCE: Final = 1.0


@dataclass
class Parsed:
    """A format reader's output before the shared steps (internal; arrays not yet checked for units)."""

    source: str
    fmt: Format
    t: np.ndarray
    op: np.ndarray
    pv: np.ndarray
    sp: np.ndarray | None = None
    mv: np.ndarray | None = None
    auto: np.ndarray | None = None
    columns: dict[str, str] = field(default_factory=dict)
    tag: str = ""
    description: str = ""
    start: str | None = None
    info: dict[str, str] = field(default_factory=dict)
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True, eq=False)
class LoadedRecording:
    """A recording read from a file, with what the file said about it.

    Attributes
    ----------
    recording : the longest AUTO segment (the whole file without a mode column); ``t`` in s from the file's
        first sample, ``op`` in % travel, ``pv``/``sp`` in the file's units, ``mv`` NaN unless the file has
        the valve position (only the standard format does).
    full : every sample of the file, AUTO or not (mode and flag columns as extras when present).
    source_format : :attr:`Format.STANDARD`, :attr:`Format.CSV` or :attr:`Format.DCS` (equal to the strings
        ``"standard"``, ``"csv"``, ``"dcs"``).
    tag, description : the loop's tag and description when the file names them (else the file stem, ``""``).
    op_units : OP's units in the file (``"%"`` or ``"mA"``); ``recording.op`` is always in %.
    pv_units : PV's units as given by the caller (``""`` = unknown; files of these formats do not say).
    pv_scale : robust PV range on ``recording`` (99.5th − 0.5th percentile), PV units.
    columns : which file column fed each role (``time``, ``op``, ``pv``, ``sp``, ``mode``).
    auto_segments, excluded : ``(t_start, t_end)`` of the AUTO runs and of the excluded (MANUAL) runs.
    start : the first sample's time stamp as written in the file (``None`` without stamps).
    info : further header facts (declared sample time, row count, the DCS's own stiction parameters, ...).
    notes : things that were tolerated and that a user should know (irregular stamps, flags, MANUAL samples).
        Whether OP really is in the units declared is for the diagnosis to judge (its unit-free frame and the
        ``op_units_refuted`` rule, :mod:`~valve_emulator.diagnosis.fit.frame`), not the reader.
    """

    recording: Recording
    full: Recording
    source_format: Format
    tag: str = ""
    description: str = ""
    op_units: str = "%"
    pv_units: str = ""
    pv_scale: float = 0.0
    columns: Mapping[str, str] = field(default_factory=dict)
    auto_segments: tuple[tuple[float, float], ...] = ()
    excluded: tuple[tuple[float, float], ...] = ()
    start: str | None = None
    info: Mapping[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "columns", types.MappingProxyType(dict(self.columns)))
        object.__setattr__(self, "info", types.MappingProxyType(dict(self.info)))

    def segments(self) -> tuple[Recording, ...]:
        """Every AUTO segment as its own recording (views into :attr:`full`), in time order."""
        t = self.full.t
        out = []
        for t0, t1 in self.auto_segments:
            i0, i1 = int(np.searchsorted(t, t0)), int(np.searchsorted(t, t1, side="right"))
            out.append(self.full.slice(i0, i1))
        return tuple(out)

    def report(self) -> str:
        """A few lines for a user: what was read, from where, and what was left out."""
        rec = self.recording
        lines = [f"{self.full.source}: {self.source_format} format, tag {self.tag or '-'}",
                 f"  {len(rec)} samples used of {len(self.full)}, "
                 + (f"dt {rec.dt:g} s, " if len(rec) > 1 else "") + f"t {rec.t[0]:g}..{rec.t[-1]:g} s",
                 "  columns: " + ", ".join(f"{k}={v}" for k, v in self.columns.items()),
                 f"  OP in {self.op_units} (shown in %), {np.min(rec.op):g}..{np.max(rec.op):g}; "
                 f"PV scale {self.pv_scale:g} {self.pv_units}".rstrip()]
        for t0, t1 in self.excluded:
            lines.append(f"  excluded (not AUTO): {t0:g}..{t1:g} s")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


def time_axis(stamps: np.ndarray, table: Table, j: int, *, declared_ts: float | None = None,
              gap_factor: float | None = 1.5) -> tuple[np.ndarray, list[str]]:
    """Seconds from the first sample, from the time column ``j`` of ``table`` (``stamps`` already parsed).

    A stamp earlier than the one before it is an error naming both lines. With ``declared_ts`` (a DCS export
    states its sample time) and stamps that stay within one sample of the declared grid -- the archive repeats a
    stamp and skips the next while the rows stay periodic -- the grid ``k·ts`` is returned and the irregular
    stamps are noted. Otherwise stamps must increase strictly, and with ``gap_factor`` a step larger than that
    many median steps is an error.
    """
    notes: list[str] = []
    steps = np.diff(stamps)
    back = np.flatnonzero(steps < 0)
    if back.size:
        i = int(back[0]) + 1
        raise table.error(f"time goes backwards, {table.cell(i, j)!r} is earlier than {table.cell(i - 1, j)!r} "
                          f"on line {table.first_line + i - 1}", i, j)
    t = stamps - stamps[0]
    if declared_ts is not None and t.size:
        grid = declared_ts * np.arange(t.size)
        off = np.abs(t - grid)
        if float(off.max()) <= _GRID_TOLERANCE * declared_ts:
            n_off = int(np.count_nonzero(off > 1e-6 * declared_ts))
            if n_off:
                notes.append(f"{n_off} time stamps are off the declared {declared_ts:g} s grid by up to "
                             f"{float(off.max()):g} s (repeated or skipped stamps); the grid was used")
            return grid, notes
        notes.append(f"time stamps do not follow the declared {declared_ts:g} s sample time; the stamps were used")
    same = np.flatnonzero(steps == 0)
    if same.size:
        i = int(same[0]) + 1
        raise table.error(f"time stamp {table.cell(i, j)!r} repeats line "
                          f"{table.first_line + i - 1}; time must increase (pass ts=SECONDS to ignore the "
                          "time column and use a regular grid)", i, j)
    if (gap := first_gap(steps, gap_factor)) is not None:
        i, median = gap
        raise table.error(f"gap in time: {float(steps[i - 1]):g} s after line {table.first_line + i - 1}, more "
                          f"than {gap_factor:g} x the median step {median:g} s", i, j)
    return t, notes


def _mode_key(cell: str) -> str:
    try:
        return format(float(cell), "g")
    except ValueError:
        return cell.strip().upper()


def auto_mask(table: Table, j: int, auto_values: Collection[str] | None = None) -> np.ndarray:
    """True where the mode column ``j`` says AUTO (see :data:`DEFAULT_AUTO_VALUES`); empty cells are not."""
    auto = {_mode_key(str(v)) for v in (DEFAULT_AUTO_VALUES if auto_values is None else auto_values)}
    return np.array([bool(c) and _mode_key(c) in auto for c in table.cells(j)], dtype=bool)


def signal_columns(table: Table, cols: Mapping[str, int], *, decimal: str = ".",
                   auto_values: Collection[str] | None = None) -> dict:
    """The :class:`Parsed` fields read from resolved columns ``cols`` (role → index): ``op`` and ``pv``
    (required numbers), ``sp`` (numbers, empty cells allowed) and ``auto`` (:func:`auto_mask` of ``mode``),
    None for a role without a column."""
    return dict(op=table.numbers(cols["op"], decimal=decimal), pv=table.numbers(cols["pv"], decimal=decimal),
                sp=table.numbers(cols["sp"], decimal=decimal, required=False) if "sp" in cols else None,
                auto=auto_mask(table, cols["mode"], auto_values) if "mode" in cols else None)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(i0, i1)`` (inclusive) of every maximal run of True."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return list(zip(starts.tolist(), stops.tolist()))


def _robust_range(x: np.ndarray) -> float:
    lo, hi = np.percentile(x, [0.5, 99.5])
    return float(hi - lo)


def finish(p: Parsed, *, op_units: str = "%", ma_table: Sequence[Sequence[float]] | None = None,
           pv_units: str = "", min_samples: int = 2) -> LoadedRecording:
    """Convert OP to %, split AUTO/MANUAL, pick the longest AUTO segment and compute the PV scale."""
    if op_units not in OP_UNITS:
        raise ReaderError(f"{p.source}: op_units must be one of {', '.join(OP_UNITS)}, got {op_units!r}")
    if ma_table is not None and op_units != "mA":
        raise ReaderError(f"{p.source}: ma_table is only used with op_units='mA'")
    op = p.op
    if op_units == "mA":
        try:
            table = LookupTable(tuple(map(tuple, ma_table)) if ma_table is not None else DEFAULT_MA_TABLE)
        except (TypeError, ValueError) as exc:
            raise ReaderError(f"{p.source}: ma_table: {exc}") from None
        op = table.to_pct(op)
        p.notes.append("OP converted from mA to % travel with the table "
                       + ", ".join(f"{a:g} mA = {b:g} %" for a, b in table.points))
    extra = dict(p.extra)
    if p.auto is not None:
        extra.setdefault("mode", p.auto.astype(float))
    full = Recording(p.t, p.sp, op, p.mv, p.pv, extra=extra, source=p.source)
    n = len(full)
    auto = np.ones(n, dtype=bool) if p.auto is None else p.auto
    auto_runs, other_runs = _runs(auto), _runs(~auto)
    span = lambda runs: tuple((float(p.t[a]), float(p.t[b])) for a, b in runs)  # noqa: E731
    if not auto_runs:
        raise ReaderError(f"{p.source}: no sample is in AUTO mode (mode column {p.columns.get('mode')!r}); "
                          "there is no closed-loop data to read")
    a, b = max(auto_runs, key=lambda r: (r[1] - r[0], -r[0]))
    if b - a + 1 < min_samples:
        where = "the longest AUTO segment has" if p.auto is not None else "the file has"
        raise ReaderError(f"{p.source}: {where} {b - a + 1} sample(s); at least min_samples={min_samples} "
                          "are needed")
    rec = full.slice(a, b + 1)
    if other_runs:
        p.notes.append(f"{int(np.count_nonzero(~auto))} samples not in AUTO were excluded; using the longest "
                       f"AUTO segment, {float(p.t[a]):g}..{float(p.t[b]):g} s")
    return LoadedRecording(
        recording=rec, full=full, source_format=p.fmt, tag=p.tag, description=p.description,
        op_units=op_units, pv_units=str(pv_units), pv_scale=_robust_range(rec.pv), columns=p.columns,
        auto_segments=span(auto_runs), excluded=span(other_runs), start=p.start, info=p.info,
        notes=tuple(p.notes))
