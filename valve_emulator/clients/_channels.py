"""The values a recorder or monitor reads from a device: ``t, sp, op, mv, pv`` and extra columns.

Defaults fit the emulator's register map (``valve-emulator registers``); every channel can be pointed at
another address with a SPEC (see :mod:`valve_emulator.clients._modbus`) or dropped with ``none``:

============  ===================  ==============================================================
channel       default              meaning
============  ===================  ==============================================================
``t``         ``time``             simulated seconds of the device; ``none``: wall seconds since start
``sp``        ``sp_f32``           set point (PV units); a number = a constant set point (the one
                                   an external controller uses); the emulator's ``sp`` reads 0 on a
                                   loop without internal controller, recorded then as empty (NaN)
``op``        ``op_f32``           controller output, % travel
``mv``        ``mv_f32``           valve position, % travel; ``none`` = no position feedback
``pv``        ``pv_f32``           process value, PV units
extras        see :data:`EXTRAS`   ``--extra NAME=SPEC`` adds one, ``--no-extras`` drops the defaults
============  ===================  ==============================================================

The emulator's ``status`` register is read as well while the default ``sp`` or the default extras are in
use (it costs nothing: the whole map is one request), to tell a loop without controller (``sp`` empty) and
the valve's state. Pointing the channels at another device: give ``--sp`` and ``--no-extras``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Final

from valve_emulator.clients._modbus import Point, Reader, parse_point
from valve_emulator.device.registers import Status
from valve_emulator.errors import UserError

__all__ = ["EXTRAS", "Channels", "add_channel_arguments", "channels_from_args", "emulator_channels"]

CORE_DEFAULTS: Final = {"t": "time", "sp": "sp_f32", "op": "op_f32", "mv": "mv_f32", "pv": "pv_f32"}
#: Extra columns recorded from the emulator by default (same names as the offline simulator's extras
#: where they exist: ``flow``, ``op_ma``, ``stuck``).
EXTRAS: Final = {"flow": "flow_pct", "op_ma": "op_ma", "stuck": "holding:12:bit0", "S": "S", "J": "J",
                 "load": "load", "noise": "noise", "fault": "fault", "tick": "tick"}
_STATUS: Final = "status"


@dataclass(frozen=True)
class Channels:
    """Resolved channels: points to read (``None`` = absent) and a constant set point, if any."""

    t: Point | None
    sp: Point | float | None
    op: Point
    mv: Point | None
    pv: Point
    extras: Mapping[str, Point] = field(default_factory=dict)
    status: Point | None = None   # the emulator's status word: decides whether sp is served

    def points(self) -> dict[str, Point]:
        """Every point to read, by an internal name (``extra:NAME`` for extras)."""
        out = {"op": self.op, "pv": self.pv}
        for name in ("t", "mv"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        if isinstance(self.sp, Point):
            out["sp"] = self.sp
        if self.status is not None:
            out[_STATUS] = self.status
        out.update({f"extra:{k}": p for k, p in self.extras.items()})
        return out

    def reader(self, *, word_order: str, max_gap: int = 8) -> Reader:
        return Reader(self.points(), word_order=word_order, max_gap=max_gap)

    def values(self, sample: Mapping[str, float]) -> tuple[float, float, float, float, list[float]]:
        """``(sp, op, mv, pv, extras)`` of one sample (NaN where absent)."""
        if isinstance(self.sp, Point):
            sp = sample["sp"]
            if _STATUS in sample and not int(sample[_STATUS]) & Status.CONTROLLER:
                sp = math.nan   # the emulator has no set point for this loop: the register reads 0
        else:
            sp = math.nan if self.sp is None else float(self.sp)
        mv = sample.get("mv", math.nan)
        return sp, sample["op"], mv, sample["pv"], [sample[f"extra:{k}"] for k in self.extras]

    @staticmethod
    def status_bits(sample: Mapping[str, float]) -> int | None:
        """The emulator's status word of a sample, when it was read."""
        return int(sample[_STATUS]) if _STATUS in sample else None


def add_channel_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("what to read (SPEC: a register name of the emulator, TABLE:ADDRESS[:TYPE"
                             "[:SCALE[:OFFSET]]] or TABLE:ADDRESS:bitN; 'none' drops a channel)")
    g.add_argument("--time", metavar="SPEC", default=CORE_DEFAULTS["t"],
                   help="device time, s (default %(default)s; none = wall time since start)")
    g.add_argument("--sp", metavar="SPEC|VALUE", default=CORE_DEFAULTS["sp"],
                   help="set point: a register or a constant number (default %(default)s)")
    g.add_argument("--op", metavar="SPEC", default=CORE_DEFAULTS["op"],
                   help="controller output, %% (default %(default)s)")
    g.add_argument("--mv", metavar="SPEC", default=CORE_DEFAULTS["mv"], help="valve position, %% (default %(default)s)")
    g.add_argument("--pv", metavar="SPEC", default=CORE_DEFAULTS["pv"], help="process value (default %(default)s)")
    g.add_argument("--extra", metavar="NAME=SPEC", action="append", default=[],
                   help="one more column (repeatable)")
    g.add_argument("--no-extras", action="store_true",
                   help=f"do not read the emulator's extra columns ({', '.join(EXTRAS)})")
    g.add_argument("--max-gap", type=int, default=8, metavar="N",
                   help="read across up to N unused registers to save requests (default %(default)s; 0 = never)")


def _optional(text: str, what: str) -> Point | None:
    return None if text.strip().lower() == "none" else parse_point(text, what=what)


def channels_from_args(args: argparse.Namespace) -> Channels:
    """Channels from the flags of :func:`add_channel_arguments`; ``UserError`` naming the flag."""
    sp: Point | float | None
    try:
        sp = float(args.sp)
    except ValueError:
        sp = _optional(args.sp, "--sp")
    else:
        if not math.isfinite(sp):
            raise UserError(f"--sp: a constant set point must be finite, got {args.sp!r}")
    extras: dict[str, Point] = {}
    if not args.no_extras:
        extras.update({k: parse_point(v, what=f"extra {k}") for k, v in EXTRAS.items()})
    for item in args.extra:
        name, sep, spec = item.partition("=")
        name = name.strip()
        if not sep or not name or any(c in name for c in ',"\r\n'):
            raise UserError(f"--extra: expected NAME=SPEC with a plain column name, got {item!r}")
        if name in CORE_DEFAULTS:
            raise UserError(f"--extra: {name!r} is a standard column; use --{name if name != 't' else 'time'}")
        extras[name] = parse_point(spec, what=f"--extra {name}")
    if args.max_gap < 0:
        raise UserError(f"--max-gap must be >= 0, got {args.max_gap}")
    # The emulator's status word is read along with its defaults (sp served? valve stuck or seized?).
    emulator = args.sp == CORE_DEFAULTS["sp"] or not args.no_extras
    return Channels(t=_optional(args.time, "--time"), sp=sp, op=parse_point(args.op, what="--op"),
                    mv=_optional(args.mv, "--mv"), pv=parse_point(args.pv, what="--pv"), extras=extras,
                    status=parse_point(_STATUS) if emulator else None)


def emulator_channels() -> Channels:
    """The default channels: everything the recorder reads from the emulator."""
    p = argparse.ArgumentParser()
    add_channel_arguments(p)
    return channels_from_args(p.parse_args([]))
