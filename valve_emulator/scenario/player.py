"""The scenario player's engine: a checked timeline applied to a device at its ticks, whatever the transport.

The player needs two things from a device, both given as small protocols so that the engine runs the same
against an emulator over Modbus (:mod:`valve_emulator.clients.scenario`), in this process, or a fake in a
test:

- a :class:`RegisterChannel` -- the holding registers of the scenario's loop: read words, write words (the
  device answers with the tick at which it accepted them), read the current tick;
- a :class:`Clock` -- "wait until the device has reached tick ``n``": :class:`DeviceClock` waits on the tick
  counter of an emulator in this process; a client polls the ``tick`` register instead.

Timing
------
An event at ``at`` seconds is due at tick ``round(at / dt)`` counted from the start of the scenario
(``dt`` the device tick, :meth:`~valve_emulator.scenario.timeline.Scenario.tick_of`); with the scenario
started at device tick ``t0``, the event is due at device tick

.. math:: n_k = t_0 + \\operatorname{round}(a_k / \\Delta t).

:func:`play` waits for each due tick, then writes the event's register words, one request per contiguous
run of addresses; the tick the device returns for the first run is when the event took effect
(:class:`Applied`, ``late = tick - due``). After the last event it waits for the end of the scenario.

Probe
-----
Before the first event :func:`probe` checks, from one read of the whole register map, that the device is the
one the scenario was written for: the register map version, whether the loop has an internal controller as
the scenario's config says, and -- only if an event writes an instructor register -- that the device accepts
instructor writes from here (it writes the current ``S`` and ``J`` back, which changes nothing). A mismatch
raises :class:`DeviceMismatch` naming the device; nothing is written.

Pure asyncio: no sockets, no wall clock, no printing. Sits beside the device layer (it reads the register map).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from valve_emulator.device.registers import (
    MAP_VERSION,
    N_REGISTERS,
    REGISTERS,
    RW_INSTRUCTOR,
    UNIT_REGISTERS,
    Status,
    address_of,
)
from valve_emulator.scenario.timeline import Event, Scenario

__all__ = [
    "Applied",
    "Clock",
    "DeviceClock",
    "DeviceMismatch",
    "RegisterChannel",
    "WriteRefused",
    "due_ticks",
    "play",
    "probe",
    "write_groups",
]

_ADDRESS = {r.name: r.address for r in REGISTERS + UNIT_REGISTERS}
_ACCESS = {r.name: r.access for r in REGISTERS + UNIT_REGISTERS}


class WriteRefused(OSError):
    """The device refused a write (a Modbus exception response, for a Modbus channel).

    ``address`` is the first register of the refused write; the message is the device's answer.
    """

    def __init__(self, message: str, *, address: int) -> None:
        super().__init__(message)
        self.address = address


class DeviceMismatch(ValueError):
    """The device is not the one the scenario was written for; ``where`` names the device."""

    def __init__(self, message: str, *, where: str) -> None:
        super().__init__(message)
        self.where = where


class RegisterChannel(Protocol):
    """The holding registers of the scenario's loop on one device."""

    #: names the device in messages, e.g. ``127.0.0.1:5020 unit 1``
    where: str

    async def read(self, address: int, count: int) -> Sequence[int]:
        """``count`` raw words from ``address`` on (one consistent snapshot)."""

    async def write(self, address: int, words: Sequence[int]) -> int:
        """Write raw words from ``address`` on; return the device tick at which it accepted them.

        A refusal raises :class:`WriteRefused`.
        """

    async def tick(self) -> int:
        """The device's tick counter now."""


class Clock(Protocol):
    """Waits for the device to reach a tick."""

    async def until(self, tick: int) -> int:
        """Return once the device tick is ``>= tick`` (or the player is stopped); the tick then."""


class DeviceClock:
    """Waits on the tick counter of an emulator running in this process (exact, no polling).

    ``device`` is a :class:`valve_emulator.device.tick.Device` (``wait_for_tick``, ``ticks``); a set ``stop``
    ends the wait early.
    """

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


@dataclass(frozen=True, kw_only=True)
class Applied:
    """An event as it happened: ``tick`` (from the scenario's start) is the first device tick that saw it,
    ``due`` the tick it was due at."""

    event: Event
    tick: int
    due: int

    @property
    def late(self) -> int:
        return self.tick - self.due

    def line(self, dt: float) -> str:
        """The instructor's log line: ``[t =    60.3 s] stiction S=3 J=1.5 -- "say" (late by 2 ticks)``."""
        late = f" (late by {self.late} ticks)" if self.late > 1 else ""
        say = f' -- "{self.event.say}"' if self.event.say else ""
        return f"[t = {self.tick * dt:8.1f} s] {self.event.describe()}{say}{late}"


def due_ticks(scenario: Scenario, *, start_tick: int = 0) -> list[tuple[int, Event]]:
    """Each event with the device tick it is due at: ``start_tick + round(at / dt)``, in timeline order."""
    return [(start_tick + scenario.tick_of(ev.at), ev) for ev in scenario.events]


def write_groups(writes: Sequence[tuple[str, int]]) -> list[tuple[int, list[int]]]:
    """An event's ``(register, word)`` writes (in address order) as contiguous runs ``[(address, words)]``."""
    out: list[tuple[int, list[int]]] = []
    for name, raw in writes:
        a = _ADDRESS[name]
        if out and out[-1][0] + len(out[-1][1]) == a:
            out[-1][1].append(raw)
        else:
            out.append((a, [raw]))
    return out


async def _apply(channel: RegisterChannel, event: Event) -> int:
    """Write ``event``'s registers; return the device tick at which the first run was accepted."""
    ticks = [await channel.write(address, words) for address, words in write_groups(event.writes)]
    return ticks[0]


async def probe(scenario: Scenario, channel: RegisterChannel) -> int:
    """Check the device against the scenario (see the module docstring); return its current tick.

    Raises :class:`DeviceMismatch` (a ``ValueError``) naming what does not match; nothing changes on the device.
    """
    where = channel.where
    words = await channel.read(0, N_REGISTERS)
    version = words[address_of("map_version")]
    if version != MAP_VERSION:
        raise DeviceMismatch(f"{where}: register map version {version}, this player needs {MAP_VERSION} "
                             "(an emulator of another release, or not the emulator)", where=where)
    has_ctl = bool(words[address_of("status")] & Status.CONTROLLER)
    if has_ctl != (scenario.loop.controller is not None):
        raise DeviceMismatch(f"{where}: the loop {'has' if has_ctl else 'has no'} internal controller, but the "
                             f"scenario's device config ({scenario.loop.name}) says otherwise", where=where)
    if any(_ACCESS[name] == RW_INSTRUCTOR for ev in scenario.events for name, _ in ev.writes):
        a = address_of("S")
        try:  # write the current S and J back: allowed or not, nothing changes
            return await channel.write(a, words[a:a + 2])
        except WriteRefused as exc:
            raise DeviceMismatch(f"{where} refuses instructor writes ({exc}); allow them with device."
                                 "instructor_writes (and instructor_hosts) in its config", where=where) from None
    return await channel.tick()


async def play(scenario: Scenario, channel: RegisterChannel, clock: Clock, *, start_tick: int = 0,
               on_applied: Callable[[Applied], None] | None = None,
               stop: asyncio.Event | None = None) -> list[Applied]:
    """Apply every event at its due tick (:func:`due_ticks`), then wait for the end of the scenario.

    ``on_applied`` is called with each :class:`Applied` as it happens (ticks counted from ``start_tick``).
    Returns what was applied, in order; stops early, between events, once ``stop`` is set.
    """
    applied: list[Applied] = []
    for due, ev in due_ticks(scenario, start_tick=start_tick):
        await clock.until(due)
        if stop is not None and stop.is_set():
            break
        tick = await _apply(channel, ev)
        done = Applied(event=ev, tick=tick - start_tick, due=due - start_tick)
        applied.append(done)
        if on_applied is not None:
            on_applied(done)
    if stop is None or not stop.is_set():
        await clock.until(start_tick + scenario.tick_of(scenario.duration))
    return applied
