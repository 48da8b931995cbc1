"""One entry point for every recording file: :func:`read_recording`.

Its keyword arguments map one to one onto command-line flags (``fmt`` ↔ ``--format``, ``op`` ↔ ``--op``,
``pv`` ↔ ``--pv``, ``sp`` ↔ ``--sp``, ``time`` ↔ ``--time``, ``ts`` ↔ ``--ts``, ``skip`` ↔ ``--skip``,
``decimal`` ↔ ``--decimal``; the others likewise by name), so a command passes its parsed flags straight through.
"""

from __future__ import annotations

import math
import os
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Final

import numpy as np

from valve_emulator.recordings.dcs import looks_like_dcs, parse_dcs
from valve_emulator.recordings.delimited import parse_delimited
from valve_emulator.recordings.errors import ReaderError
from valve_emulator.recordings.loaded import (
    OP_UNITS,
    Format,
    LoadedRecording,
    Parsed,
    auto_mask,
    finish,
)
from valve_emulator.recordings.recording import read_csv
from valve_emulator.recordings.table import ColumnSpec, Table, resolve_column
from valve_emulator.recordings.text import decode, is_utf8, split_cells, split_lines

__all__ = ["Format", "FORMATS", "read_recording", "detect_format"]


FORMATS: Final = tuple(f.value for f in Format)
_STANDARD_NAMES: Final = frozenset(("t", "op", "pv"))


def detect_format(lines: Sequence[str], *, skip: int = 0, mapped: bool = False, op_units: str = "%",
                  encoding: str = "utf-8") -> Format:
    """The format of decoded ``lines``: :attr:`Format.DCS`, :attr:`Format.STANDARD` or :attr:`Format.CSV`.

    * **DCS export**: its first line (after ``skip``) starts with ``PROCESSDATA`` or its third with ``tagname``.
    * **Standard recording**, only when nothing is skipped and no column mapping is asked for (``mapped``:
      columns, a sample time, a decimal comma, a delimiter, no header): a comma-separated first line that
      names ``t``, ``op`` and ``pv``; or one of two or more cells that begins with ``t`` when, besides, OP in %
      and UTF-8 are asked for (the arguments as given to the reader) -- a standard file missing a column,
      whose error then names the missing column.
    * Anything else is tried as **delimited text** (the delimiter is checked when parsing).
    """
    body = lines[skip:]
    if body and looks_like_dcs(list(body)):
        return Format.DCS
    if body and skip == 0 and not mapped:
        cells = split_cells(body[0], ",")
        if set(cells) >= _STANDARD_NAMES:
            return Format.STANDARD
        if len(cells) > 1 and cells[0] == "t" and op_units == "%" and is_utf8(encoding):
            return Format.STANDARD
    return Format.CSV


def _standard(path: str, *, mode: ColumnSpec | None | bool, auto_values: Collection[str] | None,
              gap_factor: float | None) -> Parsed:
    rec = read_csv(path, min_samples=1, gap_factor=gap_factor)
    extra = dict(rec.extra)
    auto, columns = None, {"time": "t", "op": "op", "pv": "pv"}
    if rec.has_sp:
        columns["sp"] = "sp"
    names = list(rec.columns)
    jm = None
    if mode is not False and mode is not None:
        jm = resolve_column(mode, names, role="mode", source=path)
    elif mode is None and "mode" in extra:
        jm = names.index("mode")
    if jm is not None:
        name = names[jm]
        cells = [format(v, "g") if np.isfinite(v) else "" for v in rec.column(name).tolist()]
        auto = auto_mask(Table(path, [name], [[c] for c in cells], first_line=2), 0, auto_values)
        columns["mode"] = name
        extra.pop(name, None)
    return Parsed(source=path, fmt=Format.STANDARD, t=rec.t - rec.t[0], op=rec.op, pv=rec.pv,
                  sp=rec.sp if rec.has_sp else None, mv=rec.mv if rec.has_mv else None, auto=auto,
                  columns=columns, tag=Path(path).stem, extra=extra,
                  info={"t0": repr(float(rec.t[0]))} if rec.t[0] != 0 else {})


def read_recording(path: str | os.PathLike, *, fmt: Format | str = Format.AUTO, op: ColumnSpec | None = None,
                   pv: ColumnSpec | None = None, sp: ColumnSpec | None = None, time: ColumnSpec | None = None,
                   ts: float | None = None, skip: int = 0, decimal: str = ".", delimiter: str | None = None,
                   header: bool = True, op_units: str = "%", ma_table: Sequence[Sequence[float]] | None = None,
                   pv_units: str = "", mode: ColumnSpec | None | bool = None,
                   auto_values: Collection[str] | None = None, encoding: str = "utf-8",
                   gap_factor: float | None = 1.5, min_samples: int = 2) -> LoadedRecording:
    """Read one loop's recording from a standard CSV, a delimited text export or a DCS export.

    Parameters
    ----------
    path : the file.
    fmt : a :class:`Format` or its name: ``"auto"`` (detect, see :func:`detect_format`), ``"standard"``,
        ``"csv"`` or ``"dcs"``. A file detected as standard that the standard reader refuses (a text mode
        column, say) is tried as delimited text, with a note; if that fails too, the standard reader's error
        is raised.
    op, pv, sp, time, mode : the columns for controller output, process value, set point, time and controller
        mode, by name or 1-based number (``None``: the format's default column, if any; ``mode=False``: ignore
        a mode column). The standard format has fixed columns and accepts only ``mode``.
    ts : sample time in s; the time axis is then ``k·ts`` and any time column is ignored.
    skip : lines to skip before the format's first line (header).
    decimal : ``"."`` or ``","`` (decimal comma; ``,`` is then never a delimiter).
    delimiter : cell separator of delimited text (``None``: detected among tab, ``;``, ``,``, ``|``).
    header : delimited text has a header line of column names (else columns are ``1``, ``2``, ...).
    op_units : ``"%"`` (of travel) or ``"mA"``; mA is converted through ``ma_table`` (``[[mA, %], ...]``,
        default 4–20 mA = 0–100 %, linear beyond the ends).
    pv_units : PV's engineering units, reported back as given.
    auto_values : mode cells meaning AUTO (default :data:`~valve_emulator.recordings.loaded.DEFAULT_AUTO_VALUES`).
    encoding : the file's text encoding (default UTF-8, as in the shared plant data).
    gap_factor : a time step larger than this many median steps is an error (``None``: accept).
    min_samples : fewest samples the returned (AUTO) segment may have.

    Returns
    -------
    LoadedRecording
        ``.recording`` is the longest AUTO segment, ``t`` in s from the file's first sample, ``op`` in %.

    Raises
    ------
    ReaderError
        (a ``ValueError``) naming the file and, where it applies, the line and column: an undecodable or
        mixed-encoding file (with the byte offset), a format that cannot be detected, a column that does not
        exist (listing those that do), a non-numeric cell, time that goes backwards, repeats or has a gap,
        no AUTO data, too few samples, or contradictory arguments.
    OSError
        When the file cannot be read at all.
    """
    source = str(path)
    if fmt not in FORMATS:
        raise ReaderError(f"{source}: fmt must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if ts is not None and (isinstance(ts, bool) or not isinstance(ts, (int, float)) or not math.isfinite(ts)
                           or ts <= 0):
        raise ReaderError(f"{source}: ts must be a sample time in seconds > 0, got {ts!r}")
    if isinstance(skip, bool) or not isinstance(skip, int) or skip < 0:
        raise ReaderError(f"{source}: skip must be a whole number of lines >= 0, got {skip!r}")
    if decimal not in (".", ","):
        raise ReaderError(f"{source}: decimal must be '.' or ',', got {decimal!r}")
    if delimiter is not None and (not isinstance(delimiter, str) or len(delimiter) != 1 or delimiter == decimal):
        raise ReaderError(f"{source}: delimiter must be one character other than the decimal mark, "
                          f"got {delimiter!r}")
    if gap_factor is not None and not (math.isfinite(gap_factor) and gap_factor > 1):
        raise ReaderError(f"{source}: gap_factor must be a number > 1 or None, got {gap_factor!r}")
    if op_units not in OP_UNITS:
        raise ReaderError(f"{source}: op_units must be one of {', '.join(OP_UNITS)}, got {op_units!r}")
    if isinstance(min_samples, bool) or not isinstance(min_samples, int) or min_samples < 1:
        raise ReaderError(f"{source}: min_samples must be an integer >= 1, got {min_samples!r}")

    lines = split_lines(decode(Path(path).read_bytes(), source, encoding), source)
    mapped = any(v is not None for v in (op, pv, sp, time, ts, delimiter)) or decimal != "." or not header
    kind = Format(fmt)
    if kind is Format.AUTO:
        kind = detect_format(lines, skip=skip, mapped=mapped, op_units=op_units, encoding=encoding)
    if kind is Format.STANDARD:
        if mapped or skip:
            raise ReaderError(f"{source}: the standard format has the fixed columns t,sp,op,mv,pv and no "
                              "options but mode=; use fmt='csv' to map columns")
        if op_units != "%":
            raise ReaderError(f"{source}: the standard format holds OP in % of travel; op_units must be '%'")
        if not is_utf8(encoding):
            raise ReaderError(f"{source}: the standard format is UTF-8 text; encoding must be 'utf-8'")
        try:
            parsed = _standard(source, mode=mode, auto_values=auto_values, gap_factor=gap_factor)
        except ReaderError as exc:
            if fmt != Format.AUTO:
                raise
            # A header naming t, op and pv is not proof of the standard format (a text mode column, say):
            # try it as generic delimited text, and report the standard format's complaint if that fails too.
            try:
                parsed = parse_delimited(lines, source, mode=mode, auto_values=auto_values,
                                         gap_factor=gap_factor)
            except ReaderError:
                raise exc from None
            parsed.notes.append(f"read as generic delimited text, not as a standard recording ({exc})")
    elif kind is Format.DCS:
        if not header or delimiter not in (None, "\t"):
            raise ReaderError(f"{source}: a DCS export is tab-separated with its own 5 header lines; "
                              "header= and delimiter= do not apply")
        parsed = parse_dcs(lines[skip:], source, skip=skip, op=op, pv=pv, sp=sp, time=time, ts=ts, mode=mode,
                           auto_values=auto_values, decimal=decimal, gap_factor=gap_factor)
    else:
        parsed = parse_delimited(lines[skip:], source, skip=skip, header=header, delimiter=delimiter,
                                 decimal=decimal, op=op, pv=pv, sp=sp, time=time, ts=ts, mode=mode,
                                 auto_values=auto_values, gap_factor=gap_factor)
    return finish(parsed, op_units=op_units, ma_table=ma_table, pv_units=pv_units, min_samples=min_samples)
