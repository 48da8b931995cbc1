"""A Modbus client as a ``valve-emulator`` sub-command: the client's own flags and ``run``, loaded on demand.

Each client (:mod:`valve_emulator.clients`) defines ``add_arguments(parser)`` and ``run(args, *, prog) -> int``;
its command module names it and gets the two hooks the command line wants from :func:`client_command`. The client
-- and with it pymodbus -- is imported only when its sub-command is chosen.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from types import ModuleType

__all__ = ["client_command"]


def client_command(name: str, client: Callable[[], ModuleType]) -> tuple[
        Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]:
    """``(add_arguments, run)`` of the sub-command ``name`` for the client module ``client()`` returns.

    ``run`` runs the client with messages prefixed ``valve-emulator NAME`` (its exit codes: 0 done, 1 the
    device failed, 2 bad flags).
    """

    def add_arguments(p: argparse.ArgumentParser) -> None:
        client().add_arguments(p)

    def run(args: argparse.Namespace) -> int:
        return client().run(args, prog=f"valve-emulator {name}")

    return add_arguments, run
