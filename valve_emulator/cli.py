"""``valve-emulator`` command line: one sub-command per module in :mod:`valve_emulator.commands`.

Each command module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``. Errors
the user can fix (bad config, bad recording, bad flag) are printed as one line on stderr with exit code 2;
nothing is written in that case.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

__all__ = ["main", "COMMANDS"]

#: Command modules, in the order ``--help`` lists them.
COMMANDS = (
    "serve",
    "registers",
    "simulate",
    "limit_cycle",
    "figure5",
    "scenario",
    "diagnose",
    "prove",
    "evaluate",
)


def _load(name: str):
    try:
        return importlib.import_module(f"valve_emulator.commands.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"valve_emulator.commands.{name}":
            return None  # a command that is not built yet is simply not offered
        raise


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="valve-emulator",
        description="A sticky control valve (Choudhury-Thornhill-Shah stiction model) as a Modbus TCP device, "
                    "with closed-loop simulation and mismatch diagnosis.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        module = _load(name)
        if module is None:
            continue
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (ValueError, OSError) as exc:  # ConfigError, RecordingError, ... subclass ValueError
        print(f"valve-emulator {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
