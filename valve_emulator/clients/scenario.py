"""The scenario player: plays an operator-training timeline on an emulator through its Modbus registers.

``valve-emulator scenario SCENARIO.yaml`` (or ``python -m valve_emulator.clients.scenario``) checks the scenario
(:mod:`valve_emulator.scenario`), then either starts an emulator of the scenario's device config (with
instructor writes allowed from this host) or attaches to a running one (``--attach HOST:PORT``), and
applies each event at its simulated time by writing the device's own registers -- the same way a field
fault would show -- optionally recording the run (``--record REC.csv``).

Timing: an event at ``at`` seconds is due at tick ``round(at / tick)`` counted from the start of the
scenario. With an emulator started here the scenario starts at the device's tick 0 (so a recording's
``t`` equals the scenario's time) and the player waits on the device's tick counter directly; attached,
the scenario starts at the device tick found on connecting and the player polls the ``tick`` register.
Each write is a read/write request (function code 23) that also returns the tick at which the device
accepted it; the change takes effect from that tick's sample on, and the log shows it. Events at ``t = 0``
land as soon as the player is connected, typically a tick or two after the start.

Before the first event the player checks the device: the register map version, whether the loop has an
internal controller as the config says, and -- if the scenario writes instructor registers -- that the
device accepts instructor writes from here (it writes the current ``S`` and ``J`` back, which changes
nothing).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol, TextIO

from valve_emulator.device.registers import MAP_VERSION, N_REGISTERS, REGISTERS, RW_INSTRUCTOR, Status, address_of
from valve_emulator.scenario import Event, Scenario, load_scenario

from valve_emulator.clients._channels import emulator_channels
from valve_emulator.clients._modbus import DEFAULT_PORT, DeviceError, Link, Point
from valve_emulator.clients._run import pause, run_until_stopped
from valve_emulator.clients.recorder import RecorderOptions, record
from valve_emulator.device.record import TickRecorder

__all__ = ["Applied", "DeviceClock", "ModbusClock", "probe", "play", "run_scenario", "run", "main"]

PROG = "valve-emulator scenario"
_BY_NAME = {r.name: r for r in REGISTERS}
_TICK = Point("holding", address_of("tick"), "uint32")


@dataclass(frozen=True)
class Applied:
    """An event as it happened: the device tick (from the scenario's start) that first saw it."""

    event: Event
    tick: int
    due: int

    @property
    def late(self) -> int:
        return self.tick - self.due


class Clock(Protocol):
    async def until(self, tick: int) -> int: ...


class DeviceClock:
    """Waits on the tick counter of an emulator running in this process (exact, no polling)."""

    def __init__(self, device: Any, *, stop: asyncio.Event | None = None) -> None:
        self.device, self.stop = device, stop

    async def until(self, tick: int) -> int:
        if self.stop is None:
            return await self.device.wait_for_tick(tick)
        waits = [asyncio.ensure_future(self.device.wait_for_tick(tick)), asyncio.ensure_future(self.stop.wait())]
        try:
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                w.cancel()
            await asyncio.gather(*waits, return_exceptions=True)
        return self.device.ticks


class ModbusClock:
    """Waits for a device tick by polling the ``tick`` register, sleeping about half the time still to go."""

    def __init__(self, link: Link, *, word_order: str, ticks_per_second: float,
                 stop: asyncio.Event | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.link, self.word_order, self.stop, self.clock = link, word_order, stop, clock
        self.rate = ticks_per_second   # first guess; measured once the device has ticked
        self.measured = False
        self._origin: tuple[float, int] | None = None

    async def now(self) -> int:
        tick = int(_TICK.decode(await self.link.read("holding", _TICK.address, 2), self.word_order))
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


def _groups(writes: tuple[tuple[str, int], ...]) -> list[tuple[int, list[int]]]:
    """Contiguous runs of register words: ``[(address, words), ...]``."""
    out: list[tuple[int, list[int]]] = []
    for name, raw in writes:
        a = _BY_NAME[name].address
        if out and out[-1][0] + len(out[-1][1]) == a:
            out[-1][1].append(raw)
        else:
            out.append((a, [raw]))
    return out


async def _write(link: Link, writes: tuple[tuple[str, int], ...], word_order: str) -> int:
    """Apply ``writes``; return the device tick at which the first group was accepted."""
    ticks = []
    for address, words in _groups(writes):
        got = await link.write_read(address, words, _TICK.address, 2)
        ticks.append(int(_TICK.decode(got, word_order)))
    return ticks[0]


async def probe(scenario: Scenario, link: Link) -> int:
    """Check the device against the scenario (module docstring); return its current tick.

    Raises ``ValueError`` naming what does not match (nothing is changed on the device).
    """
    wo = scenario.config.device.word_order
    where = f"{link.host}:{link.port} unit {link.unit}"
    words = await link.read("holding", 0, N_REGISTERS)
    version = words[address_of("map_version")]
    if version != MAP_VERSION:
        raise ValueError(f"{where}: register map version {version}, this player needs {MAP_VERSION} "
                         "(an emulator of another release, or not the emulator)")
    has_ctl = bool(words[address_of("status")] & Status.CONTROLLER)
    if has_ctl != (scenario.loop.controller is not None):
        raise ValueError(f"{where}: the loop {'has' if has_ctl else 'has no'} internal controller, but the "
                         f"scenario's device config ({scenario.loop.name}) says otherwise")
    tick = int(_TICK.decode(words[_TICK.address:_TICK.address + 2], wo))
    if any(_BY_NAME[n].access == RW_INSTRUCTOR for ev in scenario.events for n, _ in ev.writes):
        a = address_of("S")
        try:  # write the current S and J back: allowed or not, nothing changes
            tick = int(_TICK.decode(await link.write_read(a, words[a:a + 2], _TICK.address, 2), wo))
        except DeviceError as exc:
            raise ValueError(f"{where} refuses instructor writes ({exc}); allow them with device."
                             "instructor_writes (and instructor_hosts) in its config") from None
    return tick


async def play(scenario: Scenario, link: Link, clock: Clock, *, start_tick: int = 0, log: TextIO | None = None,
               stop: asyncio.Event | None = None) -> list[Applied]:
    """Apply every event at its tick (``start_tick`` + its own), then wait for the end of the scenario.

    Returns what was applied, in order; stops early, between events, once ``stop`` is set.
    """
    wo, dt = scenario.config.device.word_order, scenario.dt
    applied: list[Applied] = []
    for ev in scenario.events:
        due = start_tick + scenario.tick_of(ev.at)
        await clock.until(due)
        if stop is not None and stop.is_set():
            break
        tick = await _write(link, ev.writes, wo)
        done = Applied(ev, tick - start_tick, due - start_tick)
        applied.append(done)
        if log is not None:
            late = f" (late by {done.late} ticks)" if done.late > 1 else ""
            say = f' -- "{ev.say}"' if ev.say else ""
            print(f"[t = {done.tick * dt:8.1f} s] {ev.describe()}{say}{late}", file=log, flush=True)
    if stop is None or not stop.is_set():
        await clock.until(start_tick + scenario.tick_of(scenario.duration))
    return applied


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

    async def session(target: tuple[str, int], clock_for: Callable[[Link], Clock], server: Any = None) -> list[Applied]:
        link = Link(*target, scenario.unit, timeout=2.0)
        try:
            await link.connect()
            tick = await probe(scenario, link)
            start = 0 if server is not None else tick   # a started emulator: scenario time = device time
            rec_stop = asyncio.Event()
            recorder = None
            tick_recorder = None
            if record_to is not None and server is not None:
                # an emulator of our own: record inside it, every row on the tick grid, nothing missed
                tick_recorder = TickRecorder(server.device, record_to, units=[scenario.unit],
                                             every=max(1, round(step / scenario.dt)))
                await tick_recorder.start()
            elif record_to is not None:
                opts = RecorderOptions(out=record_to, channels=emulator_channels(), host=target[0],
                                       port=target[1], unit=scenario.unit, word_order=scenario.config.device.word_order,
                                       period=period, step=step,
                                       until=(start + scenario.tick_of(scenario.duration)) * scenario.dt)
                recorder = asyncio.create_task(record(opts, stop=rec_stop), name="scenario-recorder")
            try:
                applied = await play(scenario, link, clock_for(link), start_tick=start, log=log, stop=stop)
                if recorder is not None and not (stop is not None and stop.is_set()):
                    # it stops by itself once it has recorded the end time: a poll or two from now
                    await asyncio.wait([recorder], timeout=10 * period + 5.0)
            finally:
                if tick_recorder is not None:
                    await tick_recorder.stop()
                    if log is not None:
                        print(f"recorded {record_to}: {tick_recorder.rows} rows on the tick grid"
                              + "".join(f"; FAILED: {why}" for why in tick_recorder.failed.values()),
                              file=log, flush=True)
                if recorder is not None:
                    rec_stop.set()
                    summary = await recorder
                    if log is not None:
                        print(f"recorded {summary.line()}", file=log, flush=True)
            return applied
        finally:
            link.close()

    if attach is not None:
        return await session(attach, lambda link: ModbusClock(
            link, word_order=scenario.config.device.word_order, ticks_per_second=scale / scenario.dt, stop=stop))

    from valve_emulator.device.server import EmulatorServer

    async with EmulatorServer(scenario.server_config(), host=host, port=port, time_scale=scale) as srv:
        if log is not None:
            print(f"{PROG}: {scenario.name}: emulator on {host}:{srv.port} unit {scenario.unit}, time-scale "
                  f"{scale:g}, {scenario.duration:g} s simulated ({scenario.duration / scale:.0f} s wall)",
                  file=log, flush=True)
        if ready is not None:
            ready(srv)
        return await session((host, srv.port), lambda link: DeviceClock(srv.device, stop=stop), server=srv)


def _attach(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise ValueError(f"--attach must be HOST:PORT, got {text!r}")
    return host, int(port)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``valve-emulator scenario`` (errors are ``ValueError``/``OSError``: exit code 2)."""
    scenario = load_scenario(args.scenario)   # everything is checked before anything starts
    attach = _attach(args.attach) if args.attach else None
    if args.time_scale is not None and not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise ValueError(f"--time-scale must be a finite number > 0, got {args.time_scale}")
    if args.record_step is not None and not args.record_step > 0:
        raise ValueError(f"--record-step must be > 0 s, got {args.record_step}")
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be 0..65535, got {args.port}")
    print(f"{scenario.name}: {len(scenario.events)} events over {scenario.duration:g} s on unit {scenario.unit} "
          f"({scenario.loop.name})")
    if scenario.description:
        print("\n".join("  " + line for line in scenario.description.splitlines()))
    if args.check:
        for ev in scenario.events:
            print(f"  {ev.at:8.1f} s  {ev.describe()}" + (f' -- "{ev.say}"' if ev.say else ""))
        return 0
    applied = run_until_stopped(lambda stop: run_scenario(
        scenario, attach=attach, host=args.host, port=args.port, time_scale=args.time_scale,
        record_to=args.record, record_step=args.record_step, log=sys.stdout, stop=stop))
    print(f"{PROG}: {len(applied)} of {len(scenario.events)} events applied")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m valve_emulator.clients.scenario``: the same as ``valve-emulator scenario``."""
    from valve_emulator.commands.scenario import add_arguments

    p = argparse.ArgumentParser(prog="python -m valve_emulator.clients.scenario", description=__doc__.splitlines()[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except (ValueError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
