"""``valve-emulator scenario SCENARIO.yaml``: play a scenario's timed faults on an emulator (docs/scenarios.md).

The player's front end is :mod:`valve_emulator.clients.scenario` (its flags, its ``run``); it is imported only
when this command runs, so that the other commands do not load pymodbus's client.
"""

from __future__ import annotations

import argparse

NAME = "scenario"
HELP = "play an operator-training scenario (timed malfunctions, set points) on an emulator"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from valve_emulator.clients.scenario import add_arguments

    add_arguments(p)


def run(args: argparse.Namespace) -> int:
    from valve_emulator.clients.scenario import run

    return run(args)
