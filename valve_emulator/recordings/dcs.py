"""The DCS text export of the shared refinery data (StictionGPT ``plant_data``; Xue et al., CEP 2025).

Layout (tab-separated, UTF-8, ``\\r\\n`` line ends in the files seen)::

    line 1  PROCESSDATA <tab> <title, e.g. "2111FIC46005 Data"> <tab> yyyy-MM-dd HH:mm:ss
    line 2  <number of columns after the stamp> <tab> <sample time, s> <tab> <start stamp> <tab> <row count>
    line 3  tagname <tab> TAG.MV <tab> TAG.PV <tab> TAG.SV <tab> TAG.MODE <tab> bOpOFL <tab> bPvOFL ...
    line 4  desc <tab> one description per column (Chinese text in the shared files)
    line 5  parameters of the plant's own stiction routine (key=value cells)
    line 6+ <stamp> <tab> MV <tab> PV <tab> SV <tab> MODE <tab> bOpOFL <tab> bPvOFL <tab> bSpOFL <tab> bAutOFL

In this DCS ``.MV`` is the **controller output** (OP, % of travel), ``.SV`` the set point and ``.MODE`` an AUTO
flag (1 = automatic; the column is described as ``Aut``); the valve position is not recorded. The ``b…OFL``
columns are kept as extra columns and the number of flagged rows is noted; their values are kept (in the shared
files a flagged row repeats the previous row's values).
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Final

import numpy as np

from valve_emulator.recordings.errors import ReaderError
from valve_emulator.recordings.loaded import Format, Parsed, signal_columns, time_axis
from valve_emulator.recordings.table import ColumnSpec, Table, resolve_column
from valve_emulator.recordings.text import located, split_cells

__all__ = ["looks_like_dcs", "parse_dcs", "HEADER_LINES"]

HEADER_LINES: Final = 5
_DEFAULT_COLUMNS: Final = {"op": "MV", "pv": "PV", "sp": "SV", "mode": "MODE"}


def looks_like_dcs(lines: list[str]) -> bool:
    """True when the first line starts with ``PROCESSDATA`` or the third with ``tagname`` (tab-separated)."""
    first = _cells(lines[0])[0].upper()
    third = _cells(lines[2])[0].lower() if len(lines) > 2 else ""
    return first == "PROCESSDATA" or third == "tagname"


def _cells(line: str) -> list[str]:
    return split_cells(line, "\t")


def _expect(lines: list[str], k: int, word: str, source: str, skip: int) -> list[str]:
    cells = _cells(lines[k])
    if cells[0].lower() != word:
        raise located(source, f"expected a DCS export header line starting with {word!r} (line 1 PROCESSDATA, "
                              f"2 counts, 3 tagname, 4 desc, 5 parameters), found {lines[k][:60]!r}",
                      line=skip + k + 1)
    return cells


def parse_dcs(lines: list[str], source: str, *, skip: int = 0, op: ColumnSpec | None = None,
              pv: ColumnSpec | None = None, sp: ColumnSpec | None = None, time: ColumnSpec | None = None,
              ts: float | None = None, mode: ColumnSpec | None | bool = None,
              auto_values: Collection[str] | None = None, decimal: str = ".",
              gap_factor: float | None = 1.5) -> Parsed:
    """Parse the lines (after ``skip``) of a DCS export into :class:`Parsed`; see the module docstring."""
    if len(lines) <= HEADER_LINES:
        raise ReaderError(f"{source}: a DCS export needs {HEADER_LINES} header lines and data rows, the file has "
                          f"{len(lines) + skip} line(s)")
    names_line = _expect(lines, 2, "tagname", source, skip)
    desc_line = _expect(lines, 3, "desc", source, skip)
    names = ["timestamp"] + names_line[1:]
    descs = dict(zip(names[1:], desc_line[1:]))
    first = skip + HEADER_LINES + 1
    table = Table.from_lines(source, names, lines[HEADER_LINES:], "\t", first_line=first)
    table.refuse_blank_rows()

    info: dict[str, str] = {}
    notes: list[str] = []
    title = _cells(lines[0])
    if len(title) > 1:
        info["title"] = title[1]
    counts = _cells(lines[1])
    declared_ts = None
    try:
        declared_ts = float(counts[1])
        if not declared_ts > 0:
            declared_ts = None
    except (IndexError, ValueError):
        notes.append(f"line {skip + 2} does not give the sample time; it was taken from the time stamps")
    if declared_ts is not None:
        info["declared_ts"] = f"{declared_ts:g}"
    if len(counts) > 3:
        info["declared_rows"] = counts[3]
        if counts[3].isdigit() and int(counts[3]) != len(table):
            notes.append(f"the header declares {counts[3]} rows, the file has {len(table)}")
    info["parameters"] = "\t".join(c for c in _cells(lines[4]) if c)

    cols: dict[str, int] = {}
    for role, spec in (("op", op), ("pv", pv), ("sp", sp), ("mode", mode)):
        if spec is False:
            continue
        if spec is None:
            try:
                cols[role] = resolve_column(_DEFAULT_COLUMNS[role], names, role=role, source=source)
            except ReaderError:
                if role in ("op", "pv"):
                    raise located(source, f"no column ending in .{_DEFAULT_COLUMNS[role]} for {role}; pass "
                                          f"{role}= (the columns are {', '.join(names)})", line=skip + 3) from None
            continue
        cols[role] = resolve_column(spec, names, role=role, source=source)
    jt = 0 if time is None else resolve_column(time, names, role="time", source=source)

    if ts is not None:
        t = ts * np.arange(len(table))
        stamps_used = False
    else:
        stamps = table.times(jt, decimal=decimal)
        t, more = time_axis(stamps, table, jt, declared_ts=declared_ts, gap_factor=gap_factor)
        notes += more
        stamps_used = True

    op_name = names[cols["op"]]
    tag = op_name.rsplit(".", 1)[0] if "." in op_name else info.get("title", "").removesuffix(" Data")
    extra = {}
    for j, name in enumerate(names):
        if name.lower().startswith("b") and name.lower().endswith("ofl") and j not in cols.values():
            flags = table.numbers(j, decimal=decimal, required=False)
            extra[name] = flags
            if (k := int(np.count_nonzero(flags == 1))):
                notes.append(f"{name} is set on {k} of {len(table)} rows (values kept)")
    return Parsed(
        source=source, fmt=Format.DCS, t=t,
        **signal_columns(table, cols, decimal=decimal, auto_values=auto_values),
        columns={"time": names[jt] if stamps_used else f"ts={ts:g} s",
                 **{role: names[j] for role, j in cols.items()}},
        tag=tag, description=descs.get(names[cols["pv"]], ""),
        start=table.cell(0, jt) or None,
        info=info, extra=extra, notes=notes)
