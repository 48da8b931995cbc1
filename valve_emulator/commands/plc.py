"""``valve-emulator plc``: the soft PLC, :mod:`valve_emulator.clients.pi_controller`, as a sub-command.

The same flags and behaviour as ``python -m valve_emulator.clients.pi_controller`` (the client's own ``add_arguments``
and ``run``; exit codes 0 done, 1 the device failed, 2 bad flags). The client, and with it pymodbus, is
imported only when this command is chosen.
"""

from __future__ import annotations

import argparse

NAME = "plc"
HELP = "soft PLC: a PI(D) controller over Modbus TCP (reads PV, writes OP at a fixed scan time)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from valve_emulator.clients.pi_controller import add_arguments

    add_arguments(p)


def run(args: argparse.Namespace) -> int:
    from valve_emulator.clients.pi_controller import run

    return run(args, prog=f"valve-emulator {NAME}")
