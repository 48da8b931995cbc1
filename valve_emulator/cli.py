"""``valve-emulator`` command line: one sub-command per module in :mod:`valve_emulator.commands`.

Each command module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``. Only the
command being run gets its arguments added (a command may import its heavy parts in ``add_arguments``:
``valve-emulator --help`` and the other commands do not pay for them).

Errors the user can fix (bad config, bad recording, bad flag: a :class:`~valve_emulator.errors.UserError`) are
printed as one line on stderr with exit code 2; nothing is written in that case (``--debug`` shows their
traceback too). Any other exception is a bug: it is not caught, so Python prints its traceback and exits 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback
from collections.abc import Sequence

from valve_emulator.errors import UserError

__all__ = ["COMMANDS", "main"]

#: Command modules, in the order ``--help`` lists them.
COMMANDS = (
    "serve",
    "registers",
    "certs",
    "simulate",
    "limit_cycle",
    "figure5",
    "scenario",
    "plc",
    "record",
    "monitor",
    "diagnose",
    "prove",
    "evaluate",
    "compile",
)

_DEBUG_HELP = "also show the traceback of an error in what you gave (a bug always shows its traceback)"


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``valve-emulator`` parser; with ``command`` only that sub-command's arguments (default: all)."""
    parser = argparse.ArgumentParser(
        prog="valve-emulator",
        description="A sticky control valve (Choudhury-Thornhill-Shah stiction model) as a Modbus TCP device, "
                    "with closed-loop simulation and mismatch diagnosis.",
    )
    parser.add_argument("--debug", action="store_true", help=_DEBUG_HELP)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        module = importlib.import_module(f"valve_emulator.commands.{name}")
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=_DEBUG_HELP)
        if command is None or command == module.NAME:
            module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # The top-level parser has no option that takes a value: the first word that is not an option is the
    # command ("" when there is none: ``valve-emulator --help`` needs no command's arguments).
    command = next((a for a in argv if not a.startswith("-")), "")
    args = build_parser(command).parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except UserError as exc:  # ConfigError, RecordingError, a bad flag ...: anything else is a bug and shows
        if args.debug:
            traceback.print_exc()
        print(f"valve-emulator {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
