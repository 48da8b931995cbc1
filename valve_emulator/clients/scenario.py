"""The scenario player's front end: plays a scenario's timeline on an emulator, started here or attached over Modbus.

``valve-emulator scenario SCENARIO.yaml`` (or ``python -m valve_emulator.clients.scenario``) checks the scenario
(:mod:`valve_emulator.scenario`), then either starts an emulator of the scenario's device config and plays the
events on it in this process, or attaches to a running one (``--attach HOST:PORT``) and plays them by writing
its registers -- the same way an instructor's Modbus client would -- optionally recording the run
(``--record REC.csv``).

The engine -- due ticks, applying events, the check of an attached device before the first event -- is
:mod:`valve_emulator.scenario.player`; this module gives it a Modbus channel (:class:`LinkChannel`) and a clock
when attached, and owns the flags.

Timing: an event at ``at`` seconds is due at tick ``round(at / tick)`` counted from the start of the scenario.
With an emulator started here the scenario starts at the device's tick 0 (so a recording's ``t`` equals the
scenario's time) and each event is applied right after its due tick has run, on the device itself
(:func:`~valve_emulator.scenario.player.play_on_device`): every fault kind, ramps included, exactly on time.
Attached, the scenario starts at the device tick found on connecting and the player polls the ``tick``
register (:class:`ModbusClock`); each write is a read/write request (function code 23) that also returns the
tick at which the device accepted it, and the log shows it. Over Modbus only what the register map carries can
be played: no ramps, no sensor faults (refused, naming the line, before anything is written).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys
import time
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

from valve_emulator.clients._channels import emulator_channels
from valve_emulator.clients._modbus import DEFAULT_PORT, DeviceError, Link, Point
from valve_emulator.clients._run import pause, run_until_stopped
from valve_emulator.clients.recorder import RecorderOptions, record
from valve_emulator.device.record import TickRecorder
from valve_emulator.device.registers import address_of
from valve_emulator.errors import UserError
from valve_emulator.scenario import (
    Applied,
    Scenario,
    WriteRefused,
    check_registers_carry,
    follow,
    load_scenario,
    play,
    play_on_device,
    probe,
)

__all__ = ["LinkChannel", "ModbusClock", "add_arguments", "build_parser", "main", "run", "run_scenario"]

PROG = "valve-emulator scenario"
_TICK = Point("holding", address_of("tick"), "uint32")


class LinkChannel:
    """The engine's :class:`~valve_emulator.scenario.player.RegisterChannel` over a Modbus TCP :class:`Link`.

    Writes are read/write requests (function code 23) that read the ``tick`` register back; an exception
    response to a write becomes :class:`~valve_emulator.scenario.player.WriteRefused` with the same message.
    """

    def __init__(self, link: Link, *, word_order: str) -> None:
        self.link, self.word_order = link, word_order
        self.where = f"{link.host}:{link.port} unit {link.unit}"

    async def read(self, address: int, count: int) -> list[int]:
        return await self.link.read("holding", address, count)

    async def write(self, address: int, words: Sequence[int]) -> int:
        try:
            got = await self.link.write_read(address, words, _TICK.address, _TICK.width)
        except DeviceError as exc:
            raise WriteRefused(str(exc), address=address) from None
        return int(_TICK.decode(got, self.word_order))

    async def tick(self) -> int:
        return int(_TICK.decode(await self.read(_TICK.address, _TICK.width), self.word_order))


class ModbusClock:
    """Waits for a device tick by polling the ``tick`` register, sleeping about half the time still to go."""

    def __init__(self, channel: LinkChannel, *, ticks_per_second: float, stop: asyncio.Event | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.channel, self.stop, self.clock = channel, stop, clock
        self.rate = ticks_per_second   # first guess; measured once the device has ticked
        self.measured = False
        self._origin: tuple[float, int] | None = None

    async def now(self) -> int:
        tick = await self.channel.tick()
        wall = self.clock()
        if self._origin is None:
            self._origin = (wall, tick)
        elif tick > self._origin[1] and wall > self._origin[0]:
            self.rate = (tick - self._origin[1]) / (wall - self._origin[0])
            self.measured = True
        return tick

    async def until(self, tick: int) -> int:
        while True:
            now = await self.now()
            if now >= tick or (self.stop is not None and self.stop.is_set()):
                return now
            # half the predicted time to go; short naps until the device's rate has been measured
            wait = 0.5 * (tick - now) / self.rate
            await pause(min(max(wait, 0.001), 0.5 if self.measured else 0.01), self.stop)


async def run_scenario(scenario: Scenario, *, attach: tuple[str, int] | None = None, host: str = "127.0.0.1",
                       port: int = DEFAULT_PORT, time_scale: float | None = None, record_to: Path | None = None,
                       record_step: float | None = None, log: TextIO | None = None,
                       stop: asyncio.Event | None = None, ready: Callable[[Any], None] | None = None) -> list[Applied]:
    """Start an emulator (or attach to one), check it, play the scenario, and optionally record it.

    ``time_scale`` defaults to the scenario's. The recording takes a row every ``record_step`` simulated
    seconds (default 5 ticks) on the device's time grid: inside the emulator when it is started here
    (:class:`~valve_emulator.device.record.TickRecorder`, nothing missed at any time-scale), by polling over
    Modbus when attached (:mod:`valve_emulator.clients.recorder`).
    ``ready(server)`` is called once an emulator started here listens (before the check and the events).
    """
    scale = scenario.time_scale if time_scale is None else time_scale
    step = 5 * scenario.dt if record_step is None else record_step
    period = step / scale   # wall time per row: paces the recorder until it has measured the device
    word_order = scenario.config.device.word_order

    def say(line: str) -> None:
        if log is not None:
            print(line, file=log, flush=True)

    def on_applied(done: Applied) -> None:
        say(done.line(scenario.dt))

    @contextlib.asynccontextmanager
    async def recording(target: tuple[str, int], start: int, server: Any) -> AsyncIterator[None]:
        """Record while the body plays: inside an emulator of our own, else by polling it over Modbus."""
        if record_to is None:
            yield
        elif server is not None:
            # an emulator of our own: record inside it, every row on the tick grid, nothing missed
            recorder = TickRecorder(server.device, record_to, units=[scenario.unit],
                                    every=max(1, round(step / scenario.dt)))
            await recorder.start()
            try:
                yield
            finally:
                await recorder.stop()
                say(f"recorded {record_to}: {recorder.rows} rows on the tick grid"
                    + "".join(f"; FAILED: {why}" for why in recorder.failed.values()))
        else:
            rec_stop = asyncio.Event()
            opts = RecorderOptions(out=record_to, channels=emulator_channels(), host=target[0], port=target[1],
                                   unit=scenario.unit, word_order=word_order, period=period, step=step,
                                   until=(start + scenario.tick_of(scenario.duration)) * scenario.dt)
            task = asyncio.create_task(record(opts, stop=rec_stop), name="scenario-recorder")
            try:
                yield
                if not (stop is not None and stop.is_set()):
                    # it stops by itself once it has recorded the end time: a poll or two from now
                    await asyncio.wait([task], timeout=10 * period + 5.0)
            finally:
                rec_stop.set()
                summary = await task
                say(f"recorded {summary.line()}")

    async def attached(target: tuple[str, int]) -> list[Applied]:
        check_registers_carry(scenario)
        link = Link(*target, scenario.unit, timeout=2.0)
        channel = LinkChannel(link, word_order=word_order)
        try:
            await link.connect()
            start = await probe(scenario, channel)
            clock = ModbusClock(channel, ticks_per_second=scale / scenario.dt, stop=stop)
            async with recording(target, start, None):
                return await play(scenario, channel, clock, start_tick=start, on_applied=on_applied, stop=stop)
        finally:
            link.close()

    if attach is not None:
        return await attached(attach)

    from valve_emulator.device.server import EmulatorServer

    server = EmulatorServer(scenario.config, host=host, port=port, time_scale=scale)
    player = follow(scenario, server.device, on_applied=on_applied)   # before the first tick: t = 0 is exact
    async with server as srv:
        say(f"{PROG}: {scenario.name}: emulator on {host}:{srv.port} unit {scenario.unit}, time-scale "
            f"{scale:g}, {scenario.duration:g} s simulated ({scenario.duration / scale:.0f} s wall)")
        if ready is not None:
            ready(srv)
        async with recording((host, srv.port), 0, srv):
            return await play_on_device(scenario, srv.device, player=player, stop=stop)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The player's flags (``valve-emulator scenario`` and ``python -m valve_emulator.clients.scenario``)."""
    p.add_argument("scenario", type=Path, metavar="SCENARIO.yaml", help="the timeline (see configs/scenarios/)")
    p.add_argument("--check", action="store_true", help="only check the scenario and list its events")
    p.add_argument("--attach", metavar="HOST:PORT", help="play on a running emulator instead of starting one")
    p.add_argument("--host", default="127.0.0.1", help="address the started emulator binds (default %(default)s)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="its port (default %(default)s; 0 = any free)")
    p.add_argument("--time-scale", type=float, metavar="X", help="simulated s per wall s (default: the scenario's)")
    p.add_argument("--record", type=Path, metavar="REC.csv", help="also record the run (standard recording CSV)")
    p.add_argument("--record-step", type=float, metavar="S",
                   help="simulated seconds between recorded rows (default: 5 ticks)")


def _attach(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise UserError(f"--attach must be HOST:PORT, got {text!r}")
    return host, int(port)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``valve-emulator scenario`` (errors are ``ValueError``/``OSError``: exit code 2)."""
    scenario = load_scenario(args.scenario)   # everything is checked before anything starts
    attach = _attach(args.attach) if args.attach else None
    if args.time_scale is not None and not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise UserError(f"--time-scale must be a finite number > 0, got {args.time_scale}")
    if args.record_step is not None and not args.record_step > 0:
        raise UserError(f"--record-step must be > 0 s, got {args.record_step}")
    if not 0 <= args.port <= 65535:
        raise UserError(f"--port must be 0..65535, got {args.port}")
    print(f"{scenario.name}: {len(scenario.events)} events over {scenario.duration:g} s on unit {scenario.unit} "
          f"({scenario.loop.name})")
    if scenario.description:
        print("\n".join("  " + line for line in scenario.description.splitlines()))
    if scenario.triggers or scenario.hints:
        print(f"  ({len(scenario.triggers)} triggers and {len(scenario.hints)} hints are the instructor station's; "
              "this player plays the timed events)")
    if args.check:
        for ev in scenario.events:
            print(f"  {ev.at:8.1f} s  {ev.describe()}" + (f' -- "{ev.say}"' if ev.say else ""))
        return 0
    applied = run_until_stopped(lambda stop: run_scenario(
        scenario, attach=attach, host=args.host, port=args.port, time_scale=args.time_scale,
        record_to=args.record, record_step=args.record_step, log=sys.stdout, stop=stop))
    print(f"{PROG}: {len(applied)} of {len(scenario.events)} events applied")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m valve_emulator.clients.scenario", description=__doc__.splitlines()[0])
    add_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m valve_emulator.clients.scenario``: the same as ``valve-emulator scenario``."""
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except (ValueError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
