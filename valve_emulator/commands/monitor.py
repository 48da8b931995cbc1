"""``valve-emulator monitor``: the instructor's monitor, :mod:`valve_emulator.clients.monitor`, as a sub-command.

The same flags and behaviour as ``python -m valve_emulator.clients.monitor`` (see :mod:`._client`).
"""

from __future__ import annotations

from types import ModuleType

from valve_emulator.commands._client import client_command

NAME = "monitor"
HELP = "live terminal view of a loop over Modbus: SP, PV, OP, MV, valve state and a trend"


def _client() -> ModuleType:
    from valve_emulator.clients import monitor

    return monitor


add_arguments, run = client_command(NAME, _client)
