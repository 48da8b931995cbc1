"""Renderings of the register table for people: Markdown, CSV and JSON (``valve-emulator registers``)."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Sequence
from typing import Any, Final

from valve_emulator.device.registers.bits import COILS, DISCRETE_INPUTS, reference
from valve_emulator.device.registers.table import CLOCK_REGISTERS, INPUT_REGISTERS, REGISTERS, UNIT_REGISTERS

__all__ = ["format_registers", "registers_table"]

_COLUMNS: Final = ("name", "table", "address", "reference", "type", "scale", "units", "access")


def registers_table(config: Any = None) -> list[dict]:
    """The map as rows with exactly the keys name, table, address, reference, type, scale, units, access.

    ``address`` is the zero-based PDU address, ``reference`` the one-based reference of an HMI tag editor
    (4xxxx holding, 3xxxx input, 0xxxx coil, 1xxxx discrete input). ``config`` (a ``ServerConfig``, a
    ``LoopConfig`` or ``None``) only fills in the PV engineering units of the float32 copies when every loop
    shares them. Holding rows come first (the loop's, then the unit registers and the clock's ``step``), then
    the input mirror, the coils and the discrete inputs (type ``bit``, ``units`` says what 1 means).
    """
    pv_units = "PV units"
    if config is not None:
        units = {lp.plant.units for lp in getattr(config, "loops", (config,))}
        if len(units) == 1 and next(iter(units)):
            pv_units = next(iter(units))
    rows = []
    for table, regs in (("holding", REGISTERS + UNIT_REGISTERS + CLOCK_REGISTERS), ("input", INPUT_REGISTERS)):
        for r in regs:
            units = pv_units if r.units == "PV units" else r.units
            rows.append(dict(zip(_COLUMNS, (r.name, table, r.address, reference(table, r.address), r.type.value,
                                             r.scale, units, r.access.value))))
    for b in (*COILS, *DISCRETE_INPUTS):
        rows.append(dict(zip(_COLUMNS, (b.name, b.table.value, b.address, reference(b.table, b.address), "bit", 1,
                                         b.meaning, b.access.value))))
    return rows


def format_registers(rows: Sequence[dict], fmt: str = "md") -> str:
    """Render rows from :func:`registers_table` as ``"md"`` (Markdown table), ``"csv"`` or ``"json"``."""
    if fmt == "json":
        return json.dumps(list(rows), indent=2) + "\n"
    if fmt == "csv":
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        return buf.getvalue()
    if fmt == "md":
        cells = [list(_COLUMNS)] + [[str(row[c]) for c in _COLUMNS] for row in rows]
        widths = [max(len(r[j]) for r in cells) for j in range(len(_COLUMNS))]
        line = lambda r: "| " + " | ".join(c.ljust(wd) for c, wd in zip(r, widths)) + " |"  # noqa: E731
        sep = "|" + "|".join("-" * (wd + 2) for wd in widths) + "|"
        return "\n".join([line(cells[0]), sep] + [line(r) for r in cells[1:]]) + "\n"
    raise ValueError(f"format_registers: fmt must be 'md', 'csv' or 'json', got {fmt!r}")
