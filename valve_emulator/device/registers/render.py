"""Renderings of the register table for people: Markdown, CSV and JSON (``valve-emulator registers``)."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Sequence
from typing import Any, Final

from valve_emulator.device.registers.bits import COILS, DISCRETE_INPUTS, Bit, reference
from valve_emulator.device.registers.mapping import TAGS, RegisterMap, register_map_of
from valve_emulator.device.registers.table import (
    CLOCK_REGISTERS,
    INPUT_REGISTERS,
    REGISTERS,
    UNIT_REGISTERS,
    Conversion,
)

__all__ = ["format_registers", "not_served", "registers_table"]

_COLUMNS: Final = ("name", "table", "address", "reference", "type", "scale", "units", "access")
#: A configured map's rows also say the word order of their 32/64-bit values.
_CONFIGURED_COLUMNS: Final = _COLUMNS + ("word_order",)


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
        regmap = register_map_of(config)
        if not regmap.standard:
            return _configured_rows(regmap, pv_units, config.device.word_order.value)
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


def _scale_text(row: Any) -> Any:
    """The ``scale`` column of a configured row: the standard scale, or ``raw lo..hi = lo..hi`` counts."""
    if row.conversion is not Conversion.COUNTS:
        return row.scale
    (lo, hi), span = row.counts, row.span
    over = "pv_range" if span is None else f"{span[0]:g}..{span[1]:g}"
    return f"raw {lo:g}..{hi:g} = {over}"


def _configured_rows(regmap: RegisterMap, pv_units: str, word_order: str) -> list[dict]:
    """The rows of a configured map, references in the configuration's base; the unit registers follow."""
    rows = []
    for table in ("holding", "input", "coil", "discrete_input"):
        for r in regmap.rows(table):
            if isinstance(r, Bit):
                values = (r.name, table, r.address, regmap.reference(table, r.address), "bit", 1, r.meaning,
                          r.access.value if table == "coil" else "R", "")
            else:
                units = pv_units if r.units in ("PV units", "% of pv_range") and (
                    r.type.is_float or r.conversion is Conversion.COUNTS) else r.units
                order = (r.word_order.value if r.word_order else word_order) if r.width > 1 else ""
                values = (r.name, table, r.address, regmap.reference(table, r.address), r.type.value,
                          _scale_text(r), units, r.access.value, order)
            rows.append(dict(zip(_CONFIGURED_COLUMNS, values)))
    for r in UNIT_REGISTERS + CLOCK_REGISTERS:
        rows.append(dict(zip(_CONFIGURED_COLUMNS, (r.name, "holding", r.address, reference("holding", r.address),
                                                   r.type.value, r.scale, r.units, r.access.value, ""))))
    return rows


def not_served(regmap: RegisterMap) -> list[str]:
    """The tags of the device a configured map does not place (nothing for the standard map)."""
    if regmap.standard:
        return []
    placed = {r.name for r in regmap.registers + regmap.coils + regmap.discrete_inputs}
    names = [*TAGS, *(b.name for b in COILS + DISCRETE_INPUTS)]
    return [n for n in dict.fromkeys(names) if n not in placed]


def format_registers(rows: Sequence[dict], fmt: str = "md") -> str:
    """Render rows from :func:`registers_table` as ``"md"`` (Markdown table), ``"csv"`` or ``"json"``."""
    columns = tuple(rows[0]) if rows else _COLUMNS
    if fmt == "json":
        return json.dumps(list(rows), indent=2) + "\n"
    if fmt == "csv":
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        return buf.getvalue()
    if fmt == "md":
        cells = [list(columns)] + [[str(row[c]) for c in columns] for row in rows]
        widths = [max(len(r[j]) for r in cells) for j in range(len(columns))]
        line = lambda r: "| " + " | ".join(c.ljust(wd) for c, wd in zip(r, widths)) + " |"  # noqa: E731
        sep = "|" + "|".join("-" * (wd + 2) for wd in widths) + "|"
        return "\n".join([line(cells[0]), sep] + [line(r) for r in cells[1:]]) + "\n"
    raise ValueError(f"format_registers: fmt must be 'md', 'csv' or 'json', got {fmt!r}")
