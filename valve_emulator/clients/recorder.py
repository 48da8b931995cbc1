"""``valve-emulator record --out REC.csv`` (or ``python -m valve_emulator.clients.recorder``): poll a Modbus
device and write the standard recording CSV.

The file is the project's recording format (:mod:`valve_emulator.recordings.recording`): header
``t,sp,op,mv,pv`` then the extra columns (by default the emulator's ``flow, op_ma, stuck, S, J, load,
noise, fault, tick``; see :mod:`valve_emulator.clients._channels` for pointing the columns at any device).
Each sample is
one line, written and flushed at once (``--fsync`` also forces it to disk), so a recorder that is killed
loses at most the line it was writing; :func:`~valve_emulator.recordings.recording.read_csv` drops such a partial
last line with a warning.

Time axis
---------
``t`` is the device's own simulated time (the emulator's ``time`` register) when it has one, so a run at
``--time-scale 10`` records simulated seconds; a sample whose device time has not moved since the last row
(polling faster than the device ticks) is not written again. With ``--time none`` ``t`` is wall seconds
since the start. Float32 registers are written as the shortest decimal that reads back to the same
float32 (``12.3``, not ``12.300000190734863``).

Sampling
--------
``--period S`` polls every S wall seconds at absolute deadlines (lateness never accumulates into drift; a
poll more than one period late skips the missed deadlines, counted as ``late``). The device time then
advances by about ``period × time-scale`` per row, give or take a tick of polling jitter: the steps of
``t`` are uneven. ``read_csv`` accepts that (its gap check rejects only steps over 1.5 × the median: keep
each row several device ticks long), but identification (``valve_emulator.diagnosis``) wants uniform
sampling. ``--step S`` gives it: rows are taken on the device's own time grid, exactly S device seconds
apart (S a multiple of the device tick; see :mod:`valve_emulator.clients._schedule`); a row the recorder was too slow to
catch on time is taken late and counted as ``off-grid``. The summary line reports late polls, off-grid
rows and gaps, so a recording that a strict reader would refuse never goes unnoticed.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from valve_emulator.clients._channels import Channels, add_channel_arguments, channels_from_args
from valve_emulator.clients._modbus import (
    ConnectionSettings,
    DeviceTimeError,
    add_connection_arguments,
    check_connection_arguments,
    connection_from_args,
)
from valve_emulator.clients._run import client_main
from valve_emulator.clients._schedule import next_or_retry, schedule_for
from valve_emulator.errors import UserError
from valve_emulator.recordings.recording import CsvRecordingWriter

__all__ = [
    "RecordSummary",
    "RecorderOptions",
    "add_arguments",
    "build_parser",
    "main",
    "options_from_args",
    "record",
    "run",
]

PROG = "python -m valve_emulator.clients.recorder"


@dataclass(frozen=True)
class RecorderOptions(ConnectionSettings):
    """Everything :func:`record` needs; :func:`options_from_args` builds it from the command line."""

    out: Path
    channels: Channels
    period: float = 0.1             # s of wall time between polls
    step: float | None = None       # device s between rows, on the device's time grid (needs the t channel)
    duration: float | None = None   # s of wall time; None = until stopped
    until: float | None = None      # stop once t reaches this (the t column's seconds)
    max_gap: int = 8
    fsync: bool = False


@dataclass
class RecordSummary:
    """What a recording run did: rows written, polls skipped, read errors, the span of ``t``."""

    path: Path
    rows: int = 0
    repeats: int = 0        # polls that found the device time unchanged (not written again)
    late: int = 0           # deadlines skipped because a poll came more than one period late
    off_grid: int = 0       # --step: rows taken after their grid time (the grid tick went by unseen)
    errors: int = 0         # failed polls (connection lost, exception responses) after the first
    gaps: int = 0           # steps of t larger than 1.5 x the median step (read_csv would reject them)
    t_first: float = math.nan
    t_last: float = math.nan
    steps: list[float] = field(default_factory=list, repr=False)

    def line(self) -> str:
        span = f"t = {self.t_first:g} .. {self.t_last:g} s" if self.rows else "no rows"
        extra = "".join(f", {n} {w}" for n, w in ((self.late, "late polls"), (self.off_grid, "off-grid rows"),
                                                  (self.errors, "read errors"), (self.gaps, "gaps")) if n)
        return f"{self.path}: {self.rows} rows, {span}{extra}"


async def record(opts: RecorderOptions, *, stop: asyncio.Event | None = None, progress: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic, prog: str = PROG) -> RecordSummary:
    """Poll the device and append rows to ``opts.out`` until ``stop`` is set, ``duration`` (wall s) has
    passed or ``t`` reaches ``until``; every ``opts.period`` wall seconds, or on the device's time grid
    every ``opts.step`` device seconds (see :mod:`valve_emulator.clients._schedule`).

    The first poll must succeed (``ConnectionError``/:class:`DeviceError`, nothing written beyond the
    header otherwise); later failures are counted and polling goes on (reconnecting as needed).
    ``progress`` receives a progress line (``\\r``-updated on a terminal) and the summary, prefixed with ``prog``.
    """
    ch = opts.channels
    if opts.step is not None and ch.t is None:
        raise UserError("--step samples the device's time grid: it needs the --time channel")
    reader = ch.reader(word_order=opts.word_order, max_gap=opts.max_gap)
    link = opts.link()
    summary = RecordSummary(opts.out)
    tty = progress is not None and getattr(progress, "isatty", lambda: False)()
    writer = CsvRecordingWriter(opts.out, extra_columns=tuple(ch.extras), fsync=opts.fsync)

    async def read() -> dict[str, float]:
        return await reader.read(link)

    def failed(exc: Exception) -> None:   # counted; the first reported
        summary.errors += 1
        if progress is not None and summary.errors == 1:
            print(("\n" if tty else "") + f"{prog}: {exc}; retrying", file=progress, flush=True)

    try:
        await link.connect()
        sample: dict[str, float] | None = await read()  # fail early: wrong port, unit or address
        writer.open()
        t0 = now = clock()
        schedule = schedule_for(opts.step, opts.period, clock)
        last_t, next_report = -math.inf, t0
        while True:
            if sample is not None:
                t = sample["t"] if ch.t is not None else now - t0
                if summary.rows == 0:
                    schedule.seen(t)
                sp, op, mv, pv, extras = ch.values(sample)
                if t > last_t:
                    writer.write_row(t, sp, op, mv, pv, *extras)
                    if summary.rows:
                        summary.steps.append(t - last_t)
                    else:
                        summary.t_first = t
                    summary.rows += 1
                    summary.t_last = last_t = t
                elif t < last_t and ch.t is not None:
                    raise DeviceTimeError(f"device time went back from {last_t!r} to {t!r} s (device restarted?); "
                                     f"{opts.out} holds everything up to then")
                else:
                    summary.repeats += 1   # the device has not ticked since the last row
            if progress is not None and now >= next_report:
                next_report = now + (0.5 if tty else 5.0)
                text = f"{prog}: {summary.rows} rows, t = {summary.t_last:.1f} s"
                print("\r" + text if tty else text, end="" if tty else "\n", file=progress, flush=True)
            if ((stop is not None and stop.is_set()) or (opts.until is not None and last_t >= opts.until)
                    or (opts.duration is not None and clock() - t0 >= opts.duration)):
                break
            sample = await next_or_retry(schedule, read, stop, retry=opts.period, failed=failed)
            now = clock()
            if sample is None and stop is not None and stop.is_set():
                break
        summary.late, summary.off_grid = schedule.late, schedule.off_grid
    finally:
        writer.close()
        link.close()
    if len(summary.steps) > 1:
        steps = np.asarray(summary.steps)
        summary.gaps = int(np.count_nonzero(steps > 1.5 * np.median(steps)))
    if progress is not None:
        print(("\r" if tty else "") + f"{prog}: wrote {summary.line()}", file=progress, flush=True)
    return summary


DESCRIPTION = ("Poll a Modbus TCP device and write the standard recording CSV (t,sp,op,mv,pv,...), one flushed "
               "line per sample.")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The recorder's flags (``python -m valve_emulator.clients.recorder`` and ``valve-emulator record``)."""
    add_connection_arguments(p)
    g = p.add_argument_group("recording")
    g.add_argument("--out", required=True, type=Path, metavar="REC.csv", help="file to write (overwritten)")
    g.add_argument("--period", type=float, default=0.1, metavar="S",
                   help="wall seconds between polls (default %(default)s)")
    g.add_argument("--step", type=float, metavar="S",
                   help="instead: one row every S seconds of device time, on the device's own time grid "
                        "(uniform sampling; S a multiple of the device tick)")
    g.add_argument("--duration", type=float, metavar="S", help="stop after this many wall seconds (default: Ctrl-C)")
    g.add_argument("--until", type=float, metavar="T", help="stop once t reaches T (device seconds)")
    g.add_argument("--fsync", action="store_true", help="force every line to disk (survives a power cut)")
    g.add_argument("--quiet", action="store_true", help="no progress line")
    add_channel_arguments(p)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION)
    add_arguments(p)
    return p


def options_from_args(args: argparse.Namespace) -> RecorderOptions:
    """Checked options; ``UserError`` naming the flag."""
    check_connection_arguments(args)
    if not (math.isfinite(args.period) and args.period > 0):
        raise UserError(f"--period must be > 0 s, got {args.period}")
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration}")
    if args.step is not None and not (math.isfinite(args.step) and args.step > 0):
        raise UserError(f"--step must be > 0 s, got {args.step}")
    if args.until is not None and not math.isfinite(args.until):
        raise UserError(f"--until must be a finite time, got {args.until}")
    return RecorderOptions(out=args.out, channels=channels_from_args(args), **connection_from_args(args),
                           period=args.period, step=args.step, duration=args.duration, until=args.until,
                           max_gap=args.max_gap, fsync=args.fsync)


def run(args: argparse.Namespace, *, prog: str = PROG) -> int:
    """Record as the flags say; messages start with ``prog``.

    Exit codes: 0 done (also after Ctrl-C), 1 the device failed, 2 bad flags.
    """
    progress = None if args.quiet else sys.stderr
    return client_main(prog, args, options_from_args,
                       lambda opts, stop: record(opts, stop=stop, progress=progress, prog=prog))


def main(argv: list[str] | None = None) -> int:
    """``python -m valve_emulator.clients.recorder``; exit codes as :func:`run`."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
