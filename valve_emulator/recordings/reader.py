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
from valve_emulator.recordings.loaded import OP_UNITS, LoadedRecording, Parsed, auto_mask, finish
from valve_emulator.recordings.text import ColumnSpec, ReaderError, Table, decode, resolve_column, split_lines
from valve_emulator.recordings.recording import RecordingError, read_csv

__all__ = ["FORMATS", "read_recording", "detect_format"]

FORMATS: Final = ("auto", "standard", "csv", "dcs")


def _is_standard_header(line: str) -> bool:
    return {"t", "op", "pv"} <= {c.strip() for c in line.split(",")}


def detect_format(lines: Sequence[str], *, skip: int = 0, mapped: bool = False) -> str:
    """``"dcs"``, ``"standard"`` or ``"csv"`` for decoded ``lines`` (the delimiter is checked when parsing).

    A DCS export is recognised by its first (``PROCESSDATA``) or third (``tagname``) line; a standard recording
    by a comma-separated first line naming ``t``, ``op`` and ``pv`` when no column mapping is asked for
    (``mapped``) and nothing is skipped; anything else is tried as delimited text.
    """
    body = lines[skip:]
    if body and looks_like_dcs(list(body)):
        return "dcs"
    if body and skip == 0 and not mapped and _is_standard_header(body[0]):
        return "standard"
    return "csv"


def _standard(path: str, *, mode: ColumnSpec | None | bool, auto_values: Collection[str] | None,
              gap_factor: float | None) -> Parsed:
    try:
        rec = read_csv(path, min_samples=1, gap_factor=gap_factor)
    except RecordingError as exc:
        raise ReaderError(str(exc)) from None
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
    return Parsed(source=path, fmt="standard", t=rec.t - rec.t[0], op=rec.op, pv=rec.pv,
                  sp=rec.sp if rec.has_sp else None, mv=rec.mv if rec.has_mv else None, auto=auto,
                  columns=columns, tag=Path(path).stem, extra=extra,
                  info={"t0": repr(float(rec.t[0]))} if rec.t[0] != 0 else {})


def read_recording(path: str | os.PathLike, *, fmt: str = "auto", op: ColumnSpec | None = None,
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
    fmt : ``"auto"`` (detect, see :func:`detect_format`), ``"standard"``, ``"csv"`` or ``"dcs"``.
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
    kind = detect_format(lines, skip=skip, mapped=mapped) if fmt == "auto" else fmt
    if kind == "standard":
        if mapped or skip:
            raise ReaderError(f"{source}: the standard format has the fixed columns t,sp,op,mv,pv and no "
                              "options but mode=; use fmt='csv' to map columns")
        if op_units != "%":
            raise ReaderError(f"{source}: the standard format holds OP in % of travel; op_units must be '%'")
        if encoding.lower().replace("-", "").replace("_", "") != "utf8":
            raise ReaderError(f"{source}: the standard format is UTF-8 text; encoding must be 'utf-8'")
        try:
            parsed = _standard(source, mode=mode, auto_values=auto_values, gap_factor=gap_factor)
        except ReaderError as exc:
            if fmt != "auto":
                raise
            # A header naming t, op and pv is not proof of the standard format (a text mode column, say):
            # try it as generic delimited text, and report the standard format's complaint if that fails too.
            try:
                parsed = parse_delimited(lines, source, mode=mode, auto_values=auto_values,
                                         gap_factor=gap_factor)
            except ReaderError:
                raise exc from None
            parsed.notes.append(f"read as generic delimited text, not as a standard recording ({exc})")
    elif kind == "dcs":
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
