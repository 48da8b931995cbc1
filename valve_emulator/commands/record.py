"""``valve-emulator record``: the recorder, :mod:`valve_emulator.clients.recorder`, as a sub-command.

The same flags and behaviour as ``python -m valve_emulator.clients.recorder`` (see :mod:`._client`).
"""

from __future__ import annotations

from types import ModuleType

from valve_emulator.commands._client import client_command

NAME = "record"
HELP = "poll a Modbus device and write the standard recording CSV, one flushed line per sample"


def _client() -> ModuleType:
    from valve_emulator.clients import recorder

    return recorder


add_arguments, run = client_command(NAME, _client)
