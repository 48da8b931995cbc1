"""``valve-emulator record``: the recorder, :mod:`valve_emulator.clients.recorder`, as a sub-command.

The same flags and behaviour as ``python -m valve_emulator.clients.recorder`` (the client's own ``add_arguments``
and ``run``; exit codes 0 done, 1 the device failed, 2 bad flags). The client, and with it pymodbus, is
imported only when this command is chosen.
"""

from __future__ import annotations

import argparse

NAME = "record"
HELP = "poll a Modbus device and write the standard recording CSV, one flushed line per sample"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from valve_emulator.clients.recorder import add_arguments

    add_arguments(p)


def run(args: argparse.Namespace) -> int:
    from valve_emulator.clients.recorder import run

    return run(args, prog=f"valve-emulator {NAME}")
