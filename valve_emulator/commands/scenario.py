"""``valve-emulator scenario SCENARIO.yaml``: play an operator-training timeline on an emulator.

The player is a Modbus client (:mod:`clients.scenario`); this module only plugs it into the command line.
"""

from __future__ import annotations

import argparse

NAME = "scenario"
HELP = "play an operator-training scenario (stiction, load, noise, seized valve, set point) on an emulator"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from clients.scenario import add_arguments as add

    add(p)


def run(args: argparse.Namespace) -> int:
    from clients.scenario import run as play

    return play(args)
