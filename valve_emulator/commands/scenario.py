"""``valve-emulator scenario SCENARIO.yaml``: play an operator-training timeline on an emulator.

The flags live here (so that ``--help`` stays light); the player is a Modbus client, :mod:`valve_emulator.clients.scenario`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from valve_emulator.device.registers import DEFAULT_PORT

NAME = "scenario"
HELP = "play an operator-training scenario (stiction, load, noise, seized valve, set point) on an emulator"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", type=Path, metavar="SCENARIO.yaml", help="the timeline (see configs/scenarios/)")
    p.add_argument("--check", action="store_true", help="only check the scenario and list its events")
    p.add_argument("--attach", metavar="HOST:PORT", help="play on a running emulator instead of starting one")
    p.add_argument("--host", default="127.0.0.1", help="address the started emulator binds (default %(default)s)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="its port (default %(default)s; 0 = any free)")
    p.add_argument("--time-scale", type=float, metavar="X", help="simulated s per wall s (default: the scenario's)")
    p.add_argument("--record", type=Path, metavar="REC.csv", help="also record the run (standard recording CSV)")
    p.add_argument("--record-step", type=float, metavar="S",
                   help="simulated seconds between recorded rows (default: 5 ticks)")


def run(args: argparse.Namespace) -> int:
    from valve_emulator.clients.scenario import run as play

    return play(args)
