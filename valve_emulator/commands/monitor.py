"""``valve-emulator monitor``: the instructor's monitor, :mod:`valve_emulator.clients.monitor`, as a sub-command.

The same flags and behaviour as ``python -m valve_emulator.clients.monitor`` (the client's own ``add_arguments``
and ``run``; exit codes 0 done, 1 the device failed, 2 bad flags). The client, and with it pymodbus, is
imported only when this command is chosen.
"""

from __future__ import annotations

import argparse

NAME = "monitor"
HELP = "live terminal view of a loop over Modbus: SP, PV, OP, MV, valve state and a trend"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from valve_emulator.clients.monitor import add_arguments

    add_arguments(p)


def run(args: argparse.Namespace) -> int:
    from valve_emulator.clients.monitor import run

    return run(args, prog=f"valve-emulator {NAME}")
