"""The scenario engine: a checked scenario's events applied to a device at their ticks.

One schedule, :class:`Timeline`: an event at ``at`` seconds is due at tick ``round(at / dt)`` counted from the
start of the scenario; with the scenario started at device tick ``t0`` it is due at device tick

.. math:: n_k = t_0 + \\operatorname{round}(a_k / \\Delta t),

and is applied once the device has run that tick, so it acts from the next sample on.

Two ways to apply an event, both from here:

- on a device in this process (:class:`DevicePlayer`, driven by the device's ``on_tick``): a malfunction goes
  to :meth:`Device.inject <valve_emulator.device.tick.Device.inject>` -- ramps, sensor and communication
  faults included -- and a set point or register write to :meth:`Device.write
  <valve_emulator.device.tick.Device.write>` with instructor rights. The station's scenario runner and the
  player's own emulator (``valve-emulator scenario``) use it; :func:`play_on_device` waits for the end.
- on a device elsewhere, over its registers (:func:`play`, with a :class:`RegisterChannel` and a
  :class:`Clock`): each event becomes the register words an instructor would write
  (:func:`register_writes`). Only what the register map carries can go this way (no ramps, no sensor faults);
  :func:`check_registers_carry` refuses the rest before anything is written, and :func:`probe` checks the device
  is the one the scenario was written for.

Pure asyncio: no sockets, no wall clock, no printing.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from valve_emulator.device.malfunctions import REGISTER_OF, Kind, Malfunction, register_word
from valve_emulator.device.registers import (
    MAP_VERSION,
    N_REGISTERS,
    REGISTERS,
    RW_INSTRUCTOR,
    UNIT_REGISTERS,
    CommFault,
    Scaling,
    Status,
    address_of,
)
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.errors import UserError
from valve_emulator.scenario.timeline import Event, RegisterWrite, Scenario, ScenarioError, SetPoint

__all__ = [
    "Applied",
    "Clock",
    "DeviceMismatch",
    "DevicePlayer",
    "RegisterChannel",
    "Timeline",
    "WriteRefused",
    "check_registers_carry",
    "due_ticks",
    "follow",
    "play",
    "play_on_device",
    "probe",
    "register_writes",
    "write_groups",
]

_ADDRESS = {r.name: r.address for r in REGISTERS + UNIT_REGISTERS}
_ACCESS = {r.name: r.access for r in REGISTERS + UNIT_REGISTERS}


@dataclass(frozen=True, kw_only=True)
class Applied:
    """An event as it happened: ``tick`` (from the scenario's start) is the tick after which it took effect,
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


def due_ticks(events: Sequence[Event], dt: float, *, start_tick: int = 0) -> list[tuple[int, Event]]:
    """Each event with the device tick it is due at: ``start_tick + round(at / dt)``, in timeline order."""
    return [(start_tick + round(ev.at / dt), ev) for ev in events]


class Timeline:
    """The events of a scenario started at device tick ``start_tick``, handed out as the ticks reach them."""

    def __init__(self, events: Sequence[Event], dt: float, *, start_tick: int = 0) -> None:
        self.start_tick = start_tick
        self._due = due_ticks(events, dt, start_tick=start_tick)
        self.played = 0

    @property
    def next_tick(self) -> int | None:
        """The device tick the next event is due at (``None`` when all have been handed out)."""
        return self._due[self.played][0] if self.played < len(self._due) else None

    def due(self, tick: int) -> list[tuple[int, Event]]:
        """The events due at device tick ``tick`` or before, not handed out yet (each once, in order)."""
        out = []
        while self.played < len(self._due) and self._due[self.played][0] <= tick:
            out.append(self._due[self.played])
            self.played += 1
        return out


# --- on a device in this process ------------------------------------------------------------------------

def apply_on_device(device: Any, event: Event) -> None:
    """Apply ``event`` to a :class:`~valve_emulator.device.tick.Device` in this process (say and hint: nothing)."""
    action = event.action
    if isinstance(action, Malfunction):
        device.inject(action)
    elif isinstance(action, SetPoint | RegisterWrite):
        name = "sp" if isinstance(action, SetPoint) else action.register
        device.write(action.index, _ADDRESS[name], [action.word], role=INSTRUCTOR)


class DevicePlayer:
    """Plays a scenario's events on a device in this process: :meth:`on_tick` applies the events due by a tick.

    ``apply`` carries an event out (the station's logs the malfunction and releases hints; :func:`follow` uses
    :func:`apply_on_device`); ``on_applied`` hears of each :class:`Applied`.
    """

    def __init__(self, events: Sequence[Event], dt: float, *, start_tick: int,
                 apply: Callable[[Event], None], on_applied: Callable[[Applied], None] | None = None) -> None:
        self.timeline = Timeline(events, dt, start_tick=start_tick)
        self.apply, self.on_applied = apply, on_applied
        self.applied: list[Applied] = []
        self._device: Any = None

    @property
    def finished(self) -> bool:
        return self.timeline.next_tick is None

    def on_tick(self, tick: int) -> None:
        """Apply every event due by device tick ``tick`` (the tick that has just run)."""
        start = self.timeline.start_tick
        for due, event in self.timeline.due(tick):
            self.apply(event)
            done = Applied(event=event, tick=tick - start, due=due - start)
            self.applied.append(done)
            if self.on_applied is not None:
                self.on_applied(done)

    def _hook(self, device: Any) -> None:
        self.on_tick(device.ticks)
        if self.finished:   # an idle hook would keep a fast device from batching its ticks
            self.detach()

    def attach(self, device: Any) -> None:
        """Apply the events due now, and the others after their ticks from the device's ``on_tick``."""
        self.on_tick(device.ticks)
        if not self.finished:
            self._device = device
            device.on_tick.append(self._hook)

    def detach(self) -> None:
        """Stop following the device. A new list, not a removal: the device may be iterating over its
        ``on_tick`` right now (this player's own hook ends it there), and would skip the next callback."""
        if self._device is not None:
            self._device.on_tick = [cb for cb in self._device.on_tick if cb != self._hook]
            self._device = None


def follow(scenario: Scenario, device: Any, *, on_applied: Callable[[Applied], None] | None = None) -> DevicePlayer:
    """Start playing ``scenario`` on a device in this process from its current tick (attached to its
    ``on_tick``). Before the device's first tick, events at ``t = 0`` act from the first sample on."""
    player = DevicePlayer(scenario.events, scenario.dt, start_tick=device.ticks,
                          apply=lambda event: apply_on_device(device, event), on_applied=on_applied)
    player.attach(device)
    return player


async def play_on_device(scenario: Scenario, device: Any, *, player: DevicePlayer | None = None,
                         on_applied: Callable[[Applied], None] | None = None,
                         stop: asyncio.Event | None = None) -> list[Applied]:
    """Play ``scenario`` on a running device in this process until its ``duration`` has run (or ``stop`` is
    set); ``player`` is one :func:`follow` started earlier (e.g. before the device's first tick), else one
    starts now. Returns what was applied."""
    player = player if player is not None else follow(scenario, device, on_applied=on_applied)
    end = device.wait_for_tick(player.timeline.start_tick + scenario.tick_of(scenario.duration))
    waits = [asyncio.ensure_future(end)] + ([asyncio.ensure_future(stop.wait())] if stop is not None else [])
    try:
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
    finally:
        player.detach()
        for w in waits:
            w.cancel()
        await asyncio.gather(*waits, return_exceptions=True)
    return player.applied


# --- over the registers ----------------------------------------------------------------------------------

class WriteRefused(OSError):
    """The device refused a write (a Modbus exception response, for a Modbus channel).

    ``address`` is the first register of the refused write; the message is the device's answer.
    """

    def __init__(self, message: str, *, address: int) -> None:
        super().__init__(message)
        self.address = address


class DeviceMismatch(UserError):
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


def _clear_writes(scenario: Scenario) -> list[tuple[str, int]]:
    """``clear`` as registers: the configured S, J and noise, no load, no seizure, no communication fault."""
    loop, index = scenario.loop, scenario.index
    scaling = Scaling.from_config(scenario.config)
    noise = min(loop.plant.noise, float(scaling.pv_hi[index] - scaling.pv_lo[index]))
    return [("S", register_word("S", loop.valve.S, scaling, index)),
            ("J", register_word("J", loop.valve.J, scaling, index)),
            ("load", 0), ("noise", register_word("noise", noise, scaling, index)), ("fault", 0),
            ("comm_fault", int(CommFault.NONE)), ("comm_delay_ms", 0)]


def register_writes(event: Event, scenario: Scenario) -> list[tuple[str, int]] | None:
    """The ``(register, word)`` writes (in address order) an instructor would make for ``event`` over Modbus;
    ``None`` when the register map cannot carry it (a ramp, a sensor fault)."""
    action = event.action
    if isinstance(action, SetPoint):
        return [("sp", action.word)]
    if isinstance(action, RegisterWrite):
        return [(action.register, action.word)]
    if not isinstance(action, Malfunction):
        return []
    if action.ramp > 0 or action.kind in (Kind.SENSOR_STUCK, Kind.SENSOR_DRIFT):
        return None
    scaling = Scaling.from_config(scenario.config)
    if action.kind in (Kind.SEIZE, Kind.RELEASE):
        writes = [("fault", int(action.kind is Kind.SEIZE))]
    elif action.kind is Kind.CLEAR:
        writes = _clear_writes(scenario)
    elif action.kind is Kind.COMM:
        writes = [(REGISTER_OF[k], int(v)) for k, v in action.params.items()]
    else:
        writes = [(REGISTER_OF[k], register_word(REGISTER_OF[k], v, scaling, action.index))
                  for k, v in action.params.items()]
    return sorted(writes, key=lambda w: _ADDRESS[w[0]])


#: comm_fault values under which the unit does not carry out the player's own writes
_SILENCING = frozenset({CommFault.NO_RESPONSE, CommFault.BUSY, CommFault.FAILURE, CommFault.CLOSE})


def check_registers_carry(scenario: Scenario) -> None:
    """Refuse, naming the line, a scenario that cannot be played over the registers: an event the register map
    cannot carry, or one that falls inside a communication fault that keeps the unit from carrying out writes."""
    silenced_by: Event | None = None
    for ev in scenario.events:
        writes = register_writes(ev, scenario)
        if writes is None:
            raise ScenarioError(f"{scenario.source}:{ev.line}: {ev.describe()}: the device's registers carry no "
                                "ramps and no sensor faults, so it cannot be played on a device attached over "
                                "Modbus; play it on an emulator the player starts (without --attach)")
        if isinstance(ev.action, Malfunction) and ev.action.kind is Kind.COMM and "fault" in ev.action.params:
            silenced_by = ev if int(ev.action.params["fault"]) in _SILENCING else None
        elif writes and silenced_by is not None:
            raise ScenarioError(f"{scenario.source}:{ev.line}: a {ev.kind} event at {ev.at:g} s falls inside the "
                                f"communication fault set at {silenced_by.at:g} s (line {silenced_by.line}), when "
                                "the unit carries out no write; move it, or end the fault first")


def write_groups(writes: Sequence[tuple[str, int]]) -> list[tuple[int, list[int]]]:
    """``(register, word)`` writes (in address order) as contiguous runs ``[(address, words)]``."""
    out: list[tuple[int, list[int]]] = []
    for name, raw in writes:
        a = _ADDRESS[name]
        if out and out[-1][0] + len(out[-1][1]) == a:
            out[-1][1].append(raw)
        else:
            out.append((a, [raw]))
    return out


async def probe(scenario: Scenario, channel: RegisterChannel) -> int:
    """Check the device against the scenario before anything is written; return its current tick.

    From one read of the whole register map: the register map version, whether the loop has an internal
    controller as the scenario's config says, and -- only if an event writes an instructor register -- that the
    device accepts instructor writes from here (it writes the current ``S`` and ``J`` back, which changes
    nothing). Raises :class:`DeviceMismatch` naming what does not match.
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
    writes = [w for ev in scenario.events for w in register_writes(ev, scenario) or ()]
    if any(_ACCESS[name] == RW_INSTRUCTOR for name, _ in writes):
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
    """Write every event's registers at its due tick, then wait for the end of the scenario.

    Each event is one request per contiguous run of addresses; the tick the device returns for the first is
    when it took effect. ``on_applied`` is called with each :class:`Applied` as it happens (ticks counted from
    ``start_tick``). Returns what was applied, in order; stops early, between events, once ``stop`` is set.
    Call :func:`check_registers_carry` and :func:`probe` first.
    """
    applied: list[Applied] = []
    for due, event in due_ticks(scenario.events, scenario.dt, start_tick=start_tick):
        await clock.until(due)
        if stop is not None and stop.is_set():
            break
        groups = write_groups(register_writes(event, scenario) or [])
        ticks = [await channel.write(address, words) for address, words in groups]
        done = Applied(event=event, tick=(ticks[0] if ticks else due) - start_tick, due=due - start_tick)
        applied.append(done)
        if on_applied is not None:
            on_applied(done)
    if stop is None or not stop.is_set():
        await clock.until(start_tick + scenario.tick_of(scenario.duration))
    return applied
