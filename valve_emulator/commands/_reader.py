"""The flags that say how to read a recording, shared by the commands that read one (``diagnose``, ``simulate``).

They map one to one to the options of :func:`valve_emulator.recordings.read_recording`.
"""

from __future__ import annotations

import argparse

__all__ = ["add_reader_arguments", "reader_options"]


def add_reader_arguments(p: argparse.ArgumentParser, *, op_range: bool = True) -> None:
    """Add the group "reading the file" (``op_range``: also ``--op-range``, OP's values at 0 and 100 % travel)."""
    g = p.add_argument_group("reading the file (see valve_emulator.recordings.read_recording)")
    g.add_argument("--format", dest="fmt", choices=("auto", "standard", "csv", "dcs"), default="auto",
                   help="file format (default: detect)")
    g.add_argument("--op", metavar="COL", help="controller output column (name or 1-based number)")
    g.add_argument("--pv", metavar="COL", help="process value column")
    g.add_argument("--sp", metavar="COL", help="set point column")
    g.add_argument("--time", metavar="COL", help="time column (seconds or date-times)")
    g.add_argument("--ts", type=float, metavar="SECONDS", help="sample time, when there is no time column")
    g.add_argument("--skip", type=int, default=0, metavar="N", help="lines to skip before the header")
    g.add_argument("--decimal", choices=(".", ","), default=".", help="decimal mark (default '.')")
    g.add_argument("--op-units", choices=("%", "mA"), default=None,
                   help="OP is %% of travel, or mA (4-20 mA = 0-100 %%); default: the standard format is %%, "
                        "otherwise OP may be in any units (the answer does not depend on them)")
    if op_range:
        g.add_argument("--op-range", nargs=2, type=float, metavar=("LO", "HI"),
                       help="OP's values at 0 and 100 %% travel, in OP's units (e.g. 0 27648 for raw counts): S and "
                            "J are then also given in %% travel")
    g.add_argument("--pv-units", default="", metavar="UNITS", help="PV's engineering units (for the report)")
    g.add_argument("--encoding", default="utf-8", help="text encoding of the file (default utf-8)")


def reader_options(args: argparse.Namespace) -> dict:
    """The reader's keyword arguments from the parsed flags (``op_units`` None: the format's default)."""
    return dict(fmt=args.fmt, op=args.op, pv=args.pv, sp=args.sp, time=args.time, ts=args.ts, skip=args.skip,
                decimal=args.decimal, op_units=args.op_units, pv_units=args.pv_units, encoding=args.encoding)
