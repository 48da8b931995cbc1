"""``valve-emulator registers [CONFIG] --format md|csv|json|kepware|ignition|node-red``: the Modbus register map.

Without a ``device.register_map`` in CONFIG the standard map; with one, the map as configured (references in the
file's base, the tags it does not place named below the table). ``kepware``, ``ignition`` and ``node-red``
export the served map of one unit (``--unit``, default the first loop's) for those tools
(:mod:`valve_emulator.device.registers.export`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

NAME = "registers"
HELP = ("print the Modbus register map (holding and input registers, coils and discrete inputs), or export it as "
        "a Kepware tag CSV, Ignition tag JSON or a Node-RED flow")
_TABLES = ("md", "csv", "json")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, nargs="?", metavar="CONFIG",
                   help="server or loop config (default: the embedded default)")
    p.add_argument("--format", choices=(*_TABLES, "kepware", "ignition", "node-red"), default="md",
                   help="md, csv, json: the map as a table; kepware: KEPServerEX tag-import CSV; ignition: "
                        "Ignition tag JSON; node-red: a flow of node-red-contrib-modbus nodes (default %(default)s)")
    p.add_argument("--unit", type=int, default=None,
                   help="the unit id an export describes (default: the first loop's)")
    p.add_argument("--host", default="127.0.0.1", help="the server address a Node-RED flow connects to")
    p.add_argument("--port", type=int, default=None,
                   help="the server port a Node-RED flow connects to (default: serve's, 5020)")
    p.add_argument("--device", default="valve_emulator",
                   help="the Modbus device (connection) name of an Ignition export (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    from valve_emulator.device.registers import DEFAULT_PORT, Scaling, format_registers, registers_table
    from valve_emulator.device.registers.export import export
    from valve_emulator.device.registers.mapping import register_map_of
    from valve_emulator.device.registers.render import not_served
    from valve_emulator.device.runtime import load_server_or_default
    from valve_emulator.errors import UserError

    cfg = load_server_or_default(args.config)
    regmap = register_map_of(cfg)
    if args.format in _TABLES:
        sys.stdout.write(format_registers(registers_table(cfg), args.format))
        missing = not_served(regmap)
        if missing and args.format == "md":
            sys.stdout.write(f"\nNot served by this map (no address in device.register_map): {', '.join(missing)}\n")
        return 0
    units = [lp.device.unit for lp in cfg.loops]
    unit = units[0] if args.unit is None else args.unit
    if unit not in units:
        raise UserError(f"--unit {unit}: the config has no loop on unit {unit} (units {sorted(set(units))})")
    index = units.index(unit)
    sys.stdout.write(export(args.format, regmap, Scaling.from_config(cfg), index=index,
                            pv_units=cfg.loops[index].plant.units, host=args.host,
                            port=DEFAULT_PORT if args.port is None else args.port, unit=unit, device=args.device,
                            tick=cfg.device.tick))
    return 0
