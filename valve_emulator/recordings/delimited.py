"""Generic delimited text (CSV, TSV, ``;``-separated with decimal comma, ...) with a column mapping.

After ``skip`` lines comes one header line of column names (or none, with ``header=False``: the columns are
then called ``1``, ``2``, ...), then one row per sample. Columns are chosen by name or 1-based number
(:func:`~valve_emulator.recordings.table.resolve_column`); without a choice the reader takes the column called ``op``,
``pv``, ``sp``, ``mode`` and ``t``/``time``/``timestamp``/``datetime``/``date`` (ignoring case), and asks for
the mapping when ``op`` or ``pv`` is not found. Only the chosen columns are parsed, so other columns may hold
anything. The time column holds seconds or date-times; without one, give the sample time ``ts``.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import Final

import numpy as np

from valve_emulator.recordings.errors import ReaderError
from valve_emulator.recordings.loaded import Format, Parsed, signal_columns, time_axis
from valve_emulator.recordings.table import ColumnSpec, Table, resolve_column
from valve_emulator.recordings.text import located, sniff_delimiter, split_cells

__all__ = ["parse_delimited", "TIME_NAMES"]

TIME_NAMES: Final = ("t", "time", "timestamp", "datetime", "date")
_DEFAULT_NAMES: Final = {"op": ("op",), "pv": ("pv",), "sp": ("sp",), "mode": ("mode",)}


def _find(names: list[str], candidates: tuple[str, ...]) -> int | None:
    low = [n.lower() for n in names]
    for c in candidates:
        if low.count(c) == 1:
            return low.index(c)
    return None


def parse_delimited(lines: list[str], source: str, *, skip: int = 0, header: bool = True,
                    delimiter: str | None = None, decimal: str = ".", op: ColumnSpec | None = None,
                    pv: ColumnSpec | None = None, sp: ColumnSpec | None = None,
                    time: ColumnSpec | None = None, ts: float | None = None,
                    mode: ColumnSpec | None | bool = None, auto_values: Collection[str] | None = None,
                    gap_factor: float | None = 1.5) -> Parsed:
    """Parse the lines (after ``skip``) of a delimited file into :class:`Parsed`; see the module docstring."""
    if not lines:
        raise ReaderError(f"{source}: nothing left after skipping {skip} line(s)")
    if delimiter is None:
        delimiter = sniff_delimiter(lines, decimal=decimal)
        if delimiter is None:
            raise located(source, "cannot detect the format: expected a standard recording (header "
                                  "t,sp,op,mv,pv), a DCS export (first line PROCESSDATA) or delimited text with the "
                                  "same number (>= 2) of tab, ';', ',' or '|' separated cells on every line (title "
                                  f"lines above the header? pass skip=N); found {lines[0][:60]!r}", line=skip + 1)
    first_cells = split_cells(lines[0], delimiter)
    if header:
        names = [c or str(k + 1) for k, c in enumerate(first_cells)]
        data, first = lines[1:], skip + 2
    else:
        names, data, first = [str(k + 1) for k in range(len(first_cells))], lines, skip + 1
    if not data:
        raise located(source, "no data rows after the header", line=first - 1)
    table = Table.from_lines(source, names, data, delimiter, first_line=first)
    table.refuse_blank_rows()

    cols: dict[str, int] = {}
    for role, spec in (("op", op), ("pv", pv), ("sp", sp), ("mode", mode)):
        if spec is False:
            continue
        if spec is not None:
            cols[role] = resolve_column(spec, names, role=role, source=source)
        elif (j := _find(names, _DEFAULT_NAMES[role])) is not None:
            cols[role] = j
        elif role in ("op", "pv"):
            raise located(source, f"no column called {role!r}; pass {role}= with a column name or 1-based number "
                                  f"(the columns are {', '.join(f'{k + 1}: {n!r}' for k, n in enumerate(names))})",
                          line=first - 1)
    columns = {}
    if ts is not None:
        if time is not None:
            raise ReaderError(f"{source}: give either time= (a time column) or ts= (a sample time), not both")
        t, notes, start = ts * np.arange(len(table)), [], None
        columns["time"] = f"ts={ts:g} s"
    else:
        jt = resolve_column(time, names, role="time", source=source) if time is not None else \
            _find(names, TIME_NAMES)
        if jt is None:
            raise located(source, f"no time column (none called {'/'.join(TIME_NAMES)}); pass time= with a "
                                  "column, or ts= with the sample time in seconds", line=first - 1)
        t, notes = time_axis(table.times(jt, decimal=decimal), table, jt, gap_factor=gap_factor)
        start, columns["time"] = table.cell(0, jt), names[jt]
    columns.update({role: names[j] for role, j in cols.items()})
    return Parsed(
        source=source, fmt=Format.CSV, t=t,
        **signal_columns(table, cols, decimal=decimal, auto_values=auto_values),
        columns=columns, tag=Path(source).stem, start=start,
        info={"delimiter": {"\t": "tab"}.get(delimiter, delimiter)}, notes=notes)
