"""``valve-emulator plc``: the soft PLC, :mod:`valve_emulator.clients.pi_controller`, as a sub-command.

The same flags and behaviour as ``python -m valve_emulator.clients.pi_controller`` (see :mod:`._client`).
"""

from __future__ import annotations

from types import ModuleType

from valve_emulator.commands._client import client_command

NAME = "plc"
HELP = "soft PLC: a PI(D) controller over Modbus TCP (reads PV, writes OP at a fixed scan time)"


def _client() -> ModuleType:
    from valve_emulator.clients import pi_controller

    return pi_controller


add_arguments, run = client_command(NAME, _client)
