"""``valve-emulator registers [CONFIG] --format md|csv|json``: print the Modbus register map."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

NAME = "registers"
HELP = ("print the Modbus register map: holding and input registers, coils and discrete inputs "
        "(name, table, address, reference, type, scale, units, access)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, nargs="?", metavar="CONFIG",
                   help="server or loop config (default: the embedded default)")
    p.add_argument("--format", choices=("md", "csv", "json"), default="md", help="output format (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    from valve_emulator.device.registers import format_registers, registers_table
    from valve_emulator.device.runtime import load_server_or_default

    cfg = load_server_or_default(args.config)
    sys.stdout.write(format_registers(registers_table(cfg), args.format))
    return 0
