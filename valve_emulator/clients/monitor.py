"""``valve-emulator monitor`` (or ``python -m valve_emulator.clients.monitor``): the instructor's live view of a
loop in a terminal.

Shows the latest SP, PV, OP and MV, whether the valve is moving, stuck or seized, the instructor's fault
settings (emulator only) and a scrolling trend, one row per sample, newest at the bottom::

       t [s]       SP       PV    OP %    MV %  valve   |o OP  m MV (0..100 %)  s SP  p PV (-10..10)|
       612.0    1.000    0.412   47.91   46.40  stuck   |          s p           m o               |

OP and MV share a 0..100 % axis; PV and SP share one from ``--pv-range`` (default: the range seen so far,
which only grows). The valve state comes from the emulator's ``status`` word when it is read, otherwise
from the samples: MV unchanged since the previous sample = stuck.

Modes: on a terminal the screen is redrawn in place (ANSI escapes); ``--plain`` (the default when the
output is not a terminal) prints one trend row per sample, which scrolls by itself, and the column heading
again whenever the PV axis has grown. ``--once`` prints one sample and exits; ``--duration S`` stops after S
wall seconds. Reads the
same channels as the recorder (see :mod:`valve_emulator.clients._channels`), so it works on any device.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TextIO

from valve_emulator.clients._channels import Channels, add_channel_arguments, channels_from_args
from valve_emulator.clients._modbus import (
    ConnectionSettings,
    DeviceError,
    add_connection_arguments,
    check_connection_arguments,
    connection_from_args,
)
from valve_emulator.clients._run import client_main, pause
from valve_emulator.device.registers import Status
from valve_emulator.errors import UserError

__all__ = [
    "MonitorOptions",
    "Sample",
    "add_arguments",
    "build_parser",
    "main",
    "monitor",
    "render_frame",
    "render_row",
    "run",
    "valve_state",
]

PROG = "python -m valve_emulator.clients.monitor"
_CLEAR = "\x1b[H\x1b[J"   # cursor home, clear to the end of the screen


@dataclass(frozen=True)
class MonitorOptions(ConnectionSettings):
    channels: Channels
    period: float = 0.5                          # wall s between samples
    duration: float | None = None                # wall s
    once: bool = False
    plain: bool = False
    width: int = 60                              # trend columns
    rows: int = 20                               # trend rows kept on screen (redraw mode)
    pv_range: tuple[float, float] | None = None
    max_gap: int = 8


@dataclass(frozen=True)
class Sample:
    t: float
    sp: float
    pv: float
    op: float
    mv: float
    state: str
    extras: dict[str, float]


def valve_state(status: int | None, mv: float, mv_before: float | None) -> str:
    """``seized``, ``stuck`` or ``moving`` (``?`` when unknown): from the status word, else from MV."""
    if status is not None:
        if status & Status.SEIZED:
            return "SEIZED"
        return "stuck" if status & Status.STUCK else "moving"
    if math.isnan(mv) or mv_before is None or math.isnan(mv_before):
        return "?"
    return "stuck" if mv == mv_before else "moving"


def _col(x: float, lo: float, hi: float, width: int) -> int | None:
    if not math.isfinite(x):
        return None
    return min(max(int(round((x - lo) / (hi - lo) * (width - 1))), 0), width - 1)


def render_row(s: Sample, *, width: int, pv_range: tuple[float, float]) -> str:
    """One trend row: numbers, valve state and a strip of ``width`` columns with s, p, o, m marks."""
    strip = [" "] * width
    for mark, x, lo, hi in (("s", s.sp, *pv_range), ("p", s.pv, *pv_range), ("o", s.op, 0.0, 100.0),
                            ("m", s.mv, 0.0, 100.0)):
        c = _col(x, lo, hi, width)
        if c is not None:
            strip[c] = mark   # later marks win a shared column: MV over OP over PV over SP
    return (f"{s.t:10.1f} {_num(s.sp, 8, 3)} {_num(s.pv, 8, 3)} {_num(s.op, 7, 2)} {_num(s.mv, 7, 2)}  "
            f"{s.state:7s} |{''.join(strip)}|")


def _num(x: float, width: int, digits: int) -> str:
    return f"{'-':>{width}s}" if not math.isfinite(x) else f"{x:{width}.{digits}f}"


def _heading(width: int, pv_range: tuple[float, float]) -> str:
    axis = f"o OP  m MV (0..100 %)  s SP  p PV ({pv_range[0]:g}..{pv_range[1]:g})"
    return f"{'t [s]':>10s} {'SP':>8s} {'PV':>8s} {'OP %':>7s} {'MV %':>7s}  {'valve':7s} |{axis[:width]:<{width}s}|"


def render_frame(history: Sequence[Sample], *, where: str, width: int, rows: int,
                 pv_range: tuple[float, float]) -> str:
    """The whole screen: title, latest values, instructor settings and the last ``rows`` trend rows."""
    last = history[-1]
    lines = [f"valve monitor -- {where}    t = {last.t:.1f} s",
             (f"  SP {_num(last.sp, 9, 3)}   PV {_num(last.pv, 9, 3)}   OP {_num(last.op, 7, 2)} %   "
              f"MV {_num(last.mv, 7, 2)} %   valve {last.state}")]
    faults = [(k, last.extras[k]) for k in ("S", "J", "load", "noise", "fault") if k in last.extras]
    if faults:
        units = {"S": " %", "J": " %", "load": " % flow", "noise": " % of range", "fault": ""}
        lines.append("  instructor: " + "   ".join(f"{k} {v:g}{units[k]}" for k, v in faults))
    lines += ["", _heading(width, pv_range)]
    lines += [render_row(s, width=width, pv_range=pv_range) for s in list(history)[-rows:]]
    return "\n".join(lines) + "\n"


class _Range:
    """The PV axis: fixed, or the span seen so far (it only grows, so rows stay comparable)."""

    def __init__(self, fixed: tuple[float, float] | None) -> None:
        self.fixed, self.lo, self.hi = fixed, math.inf, -math.inf

    def update(self, *xs: float) -> tuple[float, float]:
        if self.fixed is not None:
            return self.fixed
        for x in xs:
            if math.isfinite(x):
                self.lo, self.hi = min(self.lo, x), max(self.hi, x)
        if not self.lo < self.hi:
            mid = 0.0 if not math.isfinite(self.lo) else self.lo
            return mid - 1.0, mid + 1.0
        pad = 0.05 * (self.hi - self.lo)
        return self.lo - pad, self.hi + pad


async def monitor(opts: MonitorOptions, *, out: TextIO, stop: asyncio.Event | None = None,
                  clock: Callable[[], float] = time.monotonic, prog: str = PROG) -> int:
    """Show samples on ``out`` until stopped, ``duration`` passes or after one sample (``once``).

    Returns the number of samples shown. The first read must succeed (``ConnectionError`` /
    :class:`DeviceError`); later failures are shown as a line (prefixed with ``prog``) and polling goes on.
    """
    ch = opts.channels
    reader = ch.reader(word_order=opts.word_order, max_gap=opts.max_gap)
    link = opts.link()
    where = f"{opts.host}:{opts.port} unit {opts.unit}"
    history: deque[Sample] = deque(maxlen=max(opts.rows, 1))
    axis = _Range(opts.pv_range)
    shown, mv_before, t0 = 0, None, clock()
    heading_range: tuple[float, float] | None = None
    try:
        await link.connect()
        k = 0
        while True:
            now = clock()
            try:
                raw = await reader.read(link)
            except (ConnectionError, DeviceError) as exc:
                if shown == 0:
                    raise
                print(f"{prog}: {exc}", file=out, flush=True)
            else:
                sp, op, mv, pv, extras = ch.values(raw)
                t = raw["t"] if ch.t is not None else now - t0
                state = valve_state(ch.status_bits(raw), mv, mv_before)
                mv_before = mv
                history.append(Sample(t, sp, pv, op, mv, state, dict(zip(ch.extras, extras))))
                rng = axis.update(sp, pv)
                if opts.plain:
                    if shown == 0:
                        print(f"valve monitor -- {where}", file=out)
                    if rng != heading_range:   # the PV axis grew: say so before rows drawn on it
                        print(_heading(opts.width, rng), file=out)
                        heading_range = rng
                    print(render_row(history[-1], width=opts.width, pv_range=rng), file=out, flush=True)
                else:
                    out.write(_CLEAR + render_frame(history, where=where, width=opts.width, rows=opts.rows,
                                                    pv_range=rng))
                    out.flush()
                shown += 1
            if opts.once or (stop is not None and stop.is_set()) or (
                    opts.duration is not None and clock() - t0 >= opts.duration):
                break
            k += 1
            await pause(t0 + k * opts.period - clock(), stop)
            if stop is not None and stop.is_set():
                break
    finally:
        link.close()
    return shown


DESCRIPTION = "Live terminal view of a control loop over Modbus TCP: SP, PV, OP, MV, valve state and a scrolling trend."


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The monitor's flags (``python -m valve_emulator.clients.monitor`` and ``valve-emulator monitor``)."""
    add_connection_arguments(p)
    g = p.add_argument_group("display")
    g.add_argument("--period", type=float, default=0.5, metavar="S",
                   help="wall seconds per sample (default %(default)s)")
    g.add_argument("--once", action="store_true", help="show one sample and exit")
    g.add_argument("--duration", type=float, metavar="S", help="stop after S wall seconds (default: Ctrl-C)")
    g.add_argument("--plain", action="store_true",
                   help="no screen redraw: one line per sample (default off a terminal)")
    g.add_argument("--width", type=int, default=60, help="trend columns (default %(default)s)")
    g.add_argument("--rows", type=int, default=20, help="trend rows on screen (default %(default)s)")
    g.add_argument("--pv-range", type=float, nargs=2, metavar=("LO", "HI"), help="PV/SP axis (default: as seen)")
    add_channel_arguments(p)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION)
    add_arguments(p)
    return p


def options_from_args(args: argparse.Namespace, *, tty: bool) -> MonitorOptions:
    check_connection_arguments(args)
    if not (math.isfinite(args.period) and args.period > 0):
        raise UserError(f"--period must be > 0 s, got {args.period}")
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration}")
    if args.width < 10 or args.rows < 1:
        raise UserError(f"--width must be >= 10 and --rows >= 1, got {args.width} and {args.rows}")
    if args.pv_range is not None and not args.pv_range[0] < args.pv_range[1]:
        raise UserError(f"--pv-range must be LO HI with LO < HI, got {args.pv_range}")
    return MonitorOptions(channels=channels_from_args(args), **connection_from_args(args), period=args.period,
                          duration=args.duration, once=args.once, plain=args.plain or not tty, width=args.width,
                          rows=args.rows, pv_range=tuple(args.pv_range) if args.pv_range else None,
                          max_gap=args.max_gap)


def run(args: argparse.Namespace, *, prog: str = PROG) -> int:
    """Show the loop as the flags say; messages start with ``prog``.

    Exit codes: 0 done (also after Ctrl-C), 1 the device failed, 2 bad flags.
    """
    return client_main(prog, args, lambda a: options_from_args(a, tty=sys.stdout.isatty()),
                       lambda opts, stop: monitor(opts, out=sys.stdout, stop=stop, prog=prog))


def main(argv: list[str] | None = None) -> int:
    """``python -m valve_emulator.clients.monitor``; exit codes as :func:`run`."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
