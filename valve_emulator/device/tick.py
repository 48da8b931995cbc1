"""The device's heartbeat: a drift-free real-time schedule that steps the loop bank and refreshes registers.

Pure asyncio (no pymodbus). One :class:`Device` owns a ``LoopBank`` of ``n`` loops, the register
:class:`~valve_emulator.device.registers.Scaling` of those loops and the register image the Modbus adapter
serves (one contiguous ``bytearray`` of big-endian words laid out by
:class:`~valve_emulator.device.image.ImageLayout`: ``2·N_REGISTERS`` bytes per unit with one loop per
unit, a region of 32-register blocks per unit when units carry several loops).

Schedule
--------
Tick ``j`` is due at the absolute deadline ``d_j = t0 + j·P`` with ``P = dt / time_scale`` (``dt`` the
bank's simulated step, ``t0`` the clock at start). Sleeping until an absolute deadline rather than for
``P`` after the previous tick keeps the mean period exact: lateness of one tick (jitter) never
accumulates. Each tick

1. applies the writes received since the previous tick, in arrival order (the last write to a quantity
   wins; OP is then held until the next write),
2. steps every loop one ``dt`` (``bank.step()``: one compiled call for all loops),
3. re-encodes the register image of every loop (one compiled pass,
   :class:`~valve_emulator.device.registers.kernel.ImageEncoder`, the compiled ``encode_image`` bound to the image).

With a ``LoopBank`` (whose state is packed in a few arrays) and the standard loop current, 2 and 3 are one
compiled call (:class:`~valve_emulator.device.tick_kernel.SteppingEncoder`): what a lockstep ``step`` = 1 waits for.

At plant scale the tick's own compute time matters as much as its lateness: while it runs, no request is
answered. :attr:`Device.tick_time` keeps the duration of each tick (steps 1–3) next to the lateness.

Lateness ``L = clock() − d_j`` is recorded in a bounded ring buffer (:class:`JitterBuffer`, p50/p99).
When a tick wakes more than one period late (``L > P``: a slow step, a stalled event loop) it counts one
*overrun*, runs that tick once, and re-anchors to the next deadline still in the future on the same
grid, ``d_{j+m}`` with ``m = ⌊L/P⌋ + 1``. The missed ticks are skipped, not replayed in a burst, so
simulated time then lags wall-clock time by ``(m − 1)·dt`` for each overrun.

Time scale: ``time_scale = 1`` is real time, ``> 1`` faster. ``math.inf`` runs ticks back to back as fast
as possible (yielding to the event loop between ticks; no jitter is recorded). ``0`` freezes time: no tick
task runs and only :meth:`Device.advance` steps the bank. That is *lockstep* (:attr:`Device.lockstep`,
``serve --lockstep``): the clock is the client's, who runs N ticks by writing N to the ``step`` register
(the server calls :meth:`Device.advance` before it answers the write), and the testing kit's manual clock.
Nothing in a tick reads the wall clock, so the same writes between the same ticks give the same state, bit
for bit. Tests synchronise on :meth:`Device.wait_for_tick`
instead of sleeping. The clock and the sleep function are injectable for tests.

Run/freeze and speed at runtime: :meth:`Device.freeze` stops the tick task (simulated time and the ``tick``
register stand still, writes are still accepted and queue for the next tick), :meth:`Device.resume` starts
it again, and :meth:`Device.set_time_scale` changes the period; each re-anchors the schedule at the clock's
now, so no burst of catch-up ticks follows a freeze or a change of speed.

Snapshots and malfunctions (the instructor station, ``docs/station.md``): :meth:`Device.snapshot` captures the
complete state (:mod:`~valve_emulator.device.snapshots`) and :meth:`Device.restore` puts it back between two
ticks; :attr:`Device.malfunctions` holds the ramped faults, advanced at each tick before the loops step.
Callbacks in :attr:`Device.on_tick` run after every tick (the station's trends, scoring and backtrack).
:attr:`Device.alarms` (:class:`~valve_emulator.device.alarms.PvAlarms`) compares every PV with its alarm
limits whenever the image is refreshed and writes the ``alarms`` register of the loops whose alarm changed.

Writes arrive through :meth:`Device.write` (validated by the register map; a refused write raises a
:class:`~valve_emulator.device.registers.RegisterError` and changes nothing). An accepted write shows in
the register image at once, so a client reads back what it wrote; the physics sees it at the next tick.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import logging
import math
import struct
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

import numpy as np

from valve_emulator.device._tasks import cancel_and_wait
from valve_emulator.device.alarms import PvAlarms
from valve_emulator.device.image import ImageLayout
from valve_emulator.device.malfunctions import Malfunction, MalfunctionBank
from valve_emulator.device.registers import (
    N_REGISTERS,
    Fault,
    Scaling,
    address_of,
    decode_write,
    encode_value,
    patches,
)
from valve_emulator.device.registers.columns import encode_rows
from valve_emulator.device.registers.kernel import ImageEncoder
from valve_emulator.device.registers.mapping import STANDARD, RegisterMap, register_map_of
from valve_emulator.device.snapshots import Snapshot, SnapshotError
from valve_emulator.device.write_plan import WritePlan, write_plan

__all__ = ["JitterBuffer", "Device", "TICK_TASK_NAME"]

TICK_TASK_NAME = "valve-emulator-tick"
#: Loop-ticks (ticks × loops) :meth:`Device.advance` runs in one compiled call when nothing else acts in them
#: (the call's output arrays take about 50 bytes per loop-tick).
QUIET_RUN = 1 << 16
#: Fewer ticks than this run one by one: a compiled run's set-up costs about as much as eight single steps
#: (one loop, CPU: 27 µs against 3.6 µs a tick; ``advance(5)`` 31 µs as a run, 19 µs one by one).
QUIET_MIN = 10
_ALARMS = address_of("alarms")
_WORDS = {width: f">{width}H" for width in (1, 2, 4)}   # struct formats of a register's big-endian words
_log = logging.getLogger(__name__)


class JitterBuffer:
    """The last ``size`` tick latenesses (s), with percentile helpers."""

    def __init__(self, size: int = 4096) -> None:
        if size < 1:
            raise ValueError(f"JitterBuffer size must be >= 1, got {size}")
        self._buf = np.zeros(size)
        self._count = 0

    def add(self, lateness: float) -> None:
        self._buf[self._count % self._buf.size] = lateness
        self._count += 1

    def add_many(self, value: float, count: int) -> None:
        """``count`` latenesses of ``value`` each (a run of ticks timed together)."""
        size = self._buf.size
        count = int(count)
        if count >= size:
            self._buf[:] = value
        else:
            at = (self._count + np.arange(count)) % size
            self._buf[at] = value
        self._count += count

    def __len__(self) -> int:
        return min(self._count, self._buf.size)

    @property
    def total(self) -> int:
        """Latenesses recorded since the start (the buffer keeps only the last ``size``)."""
        return self._count

    def values(self) -> np.ndarray:
        """Copy of the retained latenesses, oldest first."""
        n, size = len(self), self._buf.size
        return np.roll(self._buf, -(self._count % size))[size - n:] if self._count > size else self._buf[:n].copy()

    def percentile(self, q: float) -> float:
        """``q``-th percentile (0..100) of the retained latenesses; ``nan`` when empty."""
        return float(np.percentile(self._buf[: len(self)], q)) if len(self) else math.nan

    @property
    def p50(self) -> float:
        return self.percentile(50.0)

    @property
    def p99(self) -> float:
        return self.percentile(99.0)


class Device:
    """``n`` emulated loops behind a register image, advanced by a tick task.

    Parameters
    ----------
    bank : a ``LoopBank`` (or anything with its interface: ``n, dt, t, sample_time, step(), op_external, set_sp,
        set_auto, set_manual_op, set_tuning, set_valve`` and the state arrays read by
        :func:`~valve_emulator.device.registers.encode`; the instructor's fault registers also need
        ``set_load, set_noise, set_frozen``).
    scaling : register scalings of the same ``n`` loops.
    units : the unit id of each loop, in bank order (unique unless ``blocks`` tells loops of one unit apart).
    blocks : the block of each loop inside its unit (default all 0: one loop per unit); see
        :class:`~valve_emulator.device.image.ImageLayout`.
    time_scale : simulated seconds per real second; ``math.inf`` as fast as possible, ``0`` frozen
        (step with :meth:`advance`).
    clock, sleep : ``time.monotonic`` and ``asyncio.sleep`` unless injected (fake time in tests).
    jitter_size : capacity of the lateness ring buffer (and of :attr:`tick_time`).
    register_map : the :class:`~valve_emulator.device.registers.mapping.RegisterMap` the protocol adapters
        serve (default the standard map).

    The image is :attr:`image`; loop ``i``'s registers start at byte :attr:`offsets` ``[i]`` (with one loop
    per unit that is ``i·stride``). It always holds the standard map's words (OPC UA, the station and the
    testing kit read it). What Modbus clients read is :attr:`served` laid out by :attr:`served_layout`: the
    image itself with the standard map, a second image of the configured map's rows otherwise, encoded at the
    same tick (:func:`~valve_emulator.device.registers.columns.encode_rows`).
    """

    def __init__(self, bank: Any, scaling: Scaling, *, units: Sequence[int], blocks: Sequence[int] | None = None,
                 time_scale: float = 1.0,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Awaitable[Any]] = asyncio.sleep, jitter_size: int = 4096,
                 register_map: RegisterMap = STANDARD) -> None:
        units = tuple(int(u) for u in units)
        if not (bank.n == scaling.n == len(units)):
            raise ValueError(f"Device: bank ({bank.n}), scaling ({scaling.n}) and units ({len(units)}) "
                             f"must describe the same number of loops")
        if blocks is None and (len(set(units)) != len(units) or not all(0 <= u <= 255 for u in units)):
            raise ValueError(f"Device: units must be unique ids in 0..255, got {units}")
        if not (time_scale >= 0):  # also refuses NaN
            raise ValueError(f"Device: time_scale must be >= 0 (inf = as fast as possible), got {time_scale}")
        if not (bank.dt > 0):
            raise ValueError(f"Device: bank.dt must be > 0, got {bank.dt}")
        self.layout = ImageLayout(units, blocks)   # checks (unit, block) pairs
        self.bank, self.scaling, self.units = bank, scaling, units
        #: unit id -> index of its (first) loop, block 0
        self.unit_index = {u: loops[0] for u, loops in self.layout.loops_of.items()}
        self.time_scale = float(time_scale)
        self.period = float(bank.dt) / self.time_scale if 0 < self.time_scale < math.inf else math.nan
        self.stride = 2 * N_REGISTERS
        self.ticks = 0
        self.overruns = 0
        self.jitter = JitterBuffer(jitter_size)
        #: duration of each tick (apply writes, step, encode), s: requests wait while it runs
        self.tick_time = JitterBuffer(jitter_size)
        self.error: BaseException | None = None
        self._clock, self._sleep = clock, sleep
        self._pending: dict[tuple[int, str], float] = {}
        self._plans: dict[tuple[bool, int, int], WritePlan | None] = {}   # see _write_plan
        self._waiters: list[tuple[int, int, asyncio.Future]] = []
        self._seq = itertools.count()
        self._task: asyncio.Task | None = None
        self._frozen = False
        self._started = False
        #: ramped instructor faults (only with a bank that has the sensor and fault setters)
        self.malfunctions = MalfunctionBank(bank) if hasattr(bank, "set_sensor") else None
        #: callables run after every tick with the device (keep them short: the tick waits for them)
        self.on_tick: list[Callable[[Device], None]] = []
        #: callables run whenever the register image changed (a refresh after ticks, an accepted write, an alarm
        #: word): what publishes the image to another process (:mod:`valve_emulator.opcua.shared`). Unlike
        #: :attr:`on_tick` they leave quiet ticks to one compiled call; keep them to a copy.
        self.image_listeners: list[Callable[[], None]] = []
        self.offsets = self.layout.offsets
        self.image = bytearray(self.layout.size)
        self._encode = ImageEncoder(scaling, self.image, self.offsets)
        #: a tick that refreshes the image: the bank's step and the encoding in one compiled call, when the bank
        #: keeps its state packed (:mod:`.tick_kernel`); None: ``bank.step()``, then the encoder
        self._step_encode: Callable[..., None] | None = None
        if hasattr(bank, "step_by"):   # a loop bank: the simulation it imports is loaded already
            from valve_emulator.device.tick_kernel import SteppingEncoder

            if SteppingEncoder.fits(bank, scaling):
                self._step_encode = SteppingEncoder(scaling, self.image, self.offsets).step
        self.register_map = register_map
        if register_map.standard:
            self.served_layout, self.served = self.layout, self.image
        else:
            self.served_layout = ImageLayout(units, blocks, row_words=register_map.row_words)
            self.served = bytearray(self.served_layout.size)
        #: the PV alarms of the bank's loops (``plant.alarm_limits``); None for a bank without loop configs
        self.alarms = PvAlarms.of_loops(bank.loops) if hasattr(bank, "loops") else None
        if self.alarms is not None:
            self.alarms.listeners.append(self._show_alarm)
        self._refresh()

    @classmethod
    def from_config(cls, config: Any, *, bank: Any = None, time_scale: float = 1.0,
                    clock: Callable[[], float] = time.monotonic,
                    sleep: Callable[[float], Awaitable[Any]] = asyncio.sleep, jitter_size: int = 4096) -> Device:
        """Device for a ``ServerConfig`` (each loop at its ``device.unit`` and ``device.block``); ``bank``
        defaults to a new ``LoopBank``."""
        if bank is None:
            from valve_emulator.simulation.loop import LoopBank  # the bank is heavy; import only when needed
            bank = LoopBank(config.loops, dt=config.device.tick)
        units = [lp.device.unit for lp in config.loops]
        blocks = [lp.device.block for lp in config.loops]
        return cls(bank, Scaling.from_config(config), units=units, blocks=blocks if any(blocks) else None,
                   time_scale=time_scale, clock=clock, sleep=sleep, jitter_size=jitter_size,
                   register_map=register_map_of(config))

    # --- writes -------------------------------------------------------------------------------------

    def effective_auto(self, index: int) -> bool:
        """Controller mode of loop ``index`` including a mode write not yet applied."""
        pending = self._pending.get((index, "auto"))
        return bool(self.bank.auto[index]) if pending is None else bool(pending)

    def write(self, index: int, address: int, values: Sequence[int], *,
              role: Any = None) -> list[tuple[str, float]]:
        """Validate and queue a write of raw ``values`` at holding ``address`` of the standard map on loop
        ``index`` by a client of ``role`` (what the station, OPC UA, scenarios and coil writes use, whatever map
        Modbus serves). ``role`` is a :class:`~valve_emulator.device.roles.Role`: what it may write, the same on
        every interface; None: a client without credentials, see
        :func:`~valve_emulator.device.registers.decode_write`.

        Returns the accepted ``(quantity, value)`` changes; raises a ``RegisterError`` (nothing changed).
        """
        return self._write(STANDARD, index, address, values, role)

    def write_served(self, index: int, address: int, values: Sequence[int], *,
                     role: Any = None) -> list[tuple[str, float]]:
        """:meth:`write` at holding ``address`` of the served map (:attr:`register_map`): a Modbus client's."""
        return self._write(self.register_map, index, address, values, role)

    def _write(self, regmap: RegisterMap, index: int, address: int, values: Sequence[int],
               role: Any) -> list[tuple[str, float]]:
        if len(values) == 1:
            change = self._planned(regmap, index, address, values[0], role)
            if change is not None:
                return [change]
        # the mode matters only to a loop with a controller: asking the bank costs more than the rest of a check
        auto = bool(self.scaling.has_controller[index]) and self.effective_auto(index)
        changes = decode_write(address, values, self.scaling, index, role=role, auto=auto, regmap=regmap)
        for quantity, value in changes:
            self._queue(index, quantity, value)
        self._patch(self.image, int(self.offsets[index]), STANDARD, changes, index)
        if self.served is not self.image:
            self._patch(self.served, int(self.served_layout.offsets[index]), self.register_map, changes, index)
        self._image_changed()
        return changes

    def write_served_word(self, index: int, address: int, word: int, *, role: Any = None) -> bool:
        """A one-word :meth:`write_served` carried out from the tables of its address (:mod:`.write_plan`) when
        they accept it: ``True``. ``False``: nothing changed and nothing refused, :meth:`write_served` judges it
        (a Modbus server's quick way for FC6, the most frequent write)."""
        return self._planned(self.register_map, index, address, word, role) is not None

    def _planned(self, regmap: RegisterMap, index: int, address: int, word: int,
                 role: Any) -> tuple[str, Any] | None:
        """The change of a one-word write its plan accepts, queued and shown; ``None``: the general way."""
        plan = self._write_plan(regmap, index, address)
        if plan is None:
            return None
        value = plan.accept(word, role, self.effective_auto)
        if value is None:
            return None
        self._queue(index, plan.quantity, value)
        plan.show(value)
        self._image_changed()
        return plan.quantity, value

    def _queue(self, index: int, quantity: str, value: Any) -> None:
        """Queue an accepted change for the next tick (after any earlier change: arrival order is kept)."""
        self._pending.pop((index, quantity), None)
        self._pending[(index, quantity)] = value

    def _write_plan(self, regmap: RegisterMap, index: int, address: int) -> WritePlan | None:
        """The plan of a one-word write at ``address`` of ``regmap`` (the standard or the served map) on loop
        ``index``, made at the first such write (the maps, scalings and images of a device never change)."""
        key = (regmap is STANDARD, index, address)
        try:
            return self._plans[key]
        except KeyError:
            shown = [(STANDARD, self.image, int(self.offsets[index]))]
            if self.served is not self.image:
                shown.append((self.register_map, self.served, int(self.served_layout.offsets[index])))
            plan = self._plans[key] = write_plan(tuple(shown), regmap, self.scaling, index, address)
            return plan

    def _patch(self, image: bytearray, start: int, regmap: RegisterMap, changes: list[tuple[str, Any]],
               index: int) -> None:
        """Show accepted ``changes`` of loop ``index`` at once in ``image`` (its row of ``regmap`` at ``start``):
        only the words that show them, written in place (a write costs a few registers, not the row)."""
        def read(at: int, width: int) -> tuple[int, ...]:
            return struct.unpack_from(_WORDS[width], image, start + 2 * at)

        for quantity, value in changes:
            for at, words in patches(read, quantity, value, self.scaling, index, regmap=regmap):
                struct.pack_into(_WORDS[len(words)], image, start + 2 * at, *words)

    def _apply_pending(self) -> None:
        bank = self.bank
        for (i, quantity), value in self._pending.items():
            try:
                if quantity == "op":
                    if bank.has_controller[i]:
                        bank.set_manual_op(i, value)
                    else:
                        bank.op_external[i] = value
                elif quantity == "sp":
                    bank.set_sp(i, value)
                elif quantity == "auto":
                    bank.set_auto(i, bool(value))
                elif quantity in ("kc", "ti", "td"):
                    bank.set_tuning(i, **{quantity: value})
                elif quantity == "load":
                    bank.set_load(i, value)
                elif quantity == "noise":
                    bank.set_noise(i, value)
                elif quantity == "fault":
                    bank.set_frozen(i, bool(int(value) & Fault.SEIZED))
                else:  # S, J
                    bank.set_valve(i, **{quantity: value})
            except ValueError as exc:
                # The register map validated the value; a bank that still refuses it must not stop the
                # tick of every other loop. The next refresh shows the bank's unchanged value.
                _log.error("unit %d: write %s = %r refused by the loop bank: %s", self.units[i], quantity,
                           value, exc)
        self._pending.clear()

    # --- one tick -----------------------------------------------------------------------------------

    def _refresh(self) -> None:
        self._encode(self.bank, tick=self.ticks, overruns=self.overruns, time=self.bank.sample_time)
        self._encoded()

    def _encoded(self) -> None:
        """What follows an encoding of the image: the alarms, a configured map's rows, the listeners."""
        if self.alarms is not None:
            self.alarms.update(self.bank.pv)
        if self.served is not self.image:   # a configured map: every loop's row (one per unit, back to back)
            rows = encode_rows(self.bank, self.scaling, self.register_map, tick=self.ticks, overruns=self.overruns,
                               time=self.bank.sample_time,
                               alarms=None if self.alarms is None else self.alarms.words)
            self.served[:] = rows.astype(">u2").tobytes()
        self._image_changed()

    def _image_changed(self) -> None:
        for listener in self.image_listeners:
            listener()

    def _show_alarm(self, change: Any) -> None:
        """Write loop ``change.index``'s new alarm word into its ``alarms`` register (and the served map's)."""
        at = int(self.offsets[change.index]) + 2 * _ALARMS
        self.image[at:at + 2] = change.word.to_bytes(2, "big")
        if self.served is not self.image:
            at = int(self.served_layout.offsets[change.index])
            for reg in self.register_map.showing("alarms"):
                k = at + 2 * self.register_map.word_offset(reg.table, reg.address)
                words = encode_value(reg, change.word, self.scaling, change.index)
                self.served[k:k + 2 * reg.width] = np.asarray(words, dtype=">u2").tobytes()
        self._image_changed()

    def tick(self, *, refresh: bool = True) -> None:
        """One tick now: apply pending writes, step the bank, refresh the image, wake waiters.

        ``refresh=False`` leaves the image as it was, for a caller that runs another tick at once and refreshes
        after it (:meth:`advance`): the image is a function of the bank's state and the counters only, so one
        refresh after the last tick shows what one after every tick would.
        """
        start = self._clock()
        if self._pending:
            self._apply_pending()
        if self.malfunctions is not None and self.malfunctions.ramping:
            self.malfunctions.apply(self.bank.t)
        if not (refresh or self.on_tick):   # (a callback may read the image)
            self.bank.step()
            self.ticks += 1
        elif self._step_encode is not None:
            self._step_encode(self.bank, self.ticks + 1, self.overruns)
            self.ticks += 1
            self._encoded()
        else:
            self.bank.step()
            self.ticks += 1
            self._refresh()
        for callback in self.on_tick:
            callback(self)
        self.tick_time.add(self._clock() - start)
        if self._waiters:
            self._wake()

    def _wake(self) -> None:
        """Resolve the waiters of every tick count reached."""
        waiters = self._waiters
        while waiters and waiters[0][0] <= self.ticks:
            fut = heapq.heappop(waiters)[2]
            if not fut.done():
                fut.set_result(self.ticks)

    def advance(self, k: int = 1) -> int:
        """Run ``k`` ticks immediately (only with ``time_scale == 0`` or frozen); returns the tick count.

        Ticks that nothing can tell apart from the bank's own stepping -- no write pending, no ramp running,
        no :attr:`on_tick` callback -- run as one compiled ``bank.run`` (from :data:`QUIET_MIN` ticks, at most
        :data:`QUIET_RUN` loop-ticks at a time), which the loop bank guarantees equal to as many ``bank.step()``
        calls, bit for bit; the image is then encoded once, after the last of them. Ticks run one by one encode
        the image once too, after the last (unless an :attr:`on_tick` callback, which may read it, runs between).
        """
        if self.time_scale != 0 and not self._frozen:
            raise RuntimeError(f"Device.advance needs frozen time (time_scale=0 or freeze()), "
                               f"not time_scale={self.time_scale}")
        end = self.ticks + int(k)
        try:
            while self.ticks < end:
                if end - self.ticks >= QUIET_MIN and self._quiet():
                    self._run_quiet(min(end - self.ticks, max(QUIET_MIN, QUIET_RUN // self.bank.n)))
                else:
                    self.tick(refresh=self.ticks + 1 == end)
        except Exception:
            self._refresh()   # the image shows the last tick that ran
            raise
        return self.ticks

    def _quiet(self) -> bool:
        """May the next ticks run as one ``bank.run`` (nothing but the bank acts in them)?"""
        return (not self._pending and not self.on_tick and hasattr(self.bank, "run")
                and (self.malfunctions is None or not self.malfunctions.ramping))

    def _run_quiet(self, m: int) -> None:
        start = self._clock()
        self.bank.run(m)
        self.ticks += m
        self._refresh()
        self.tick_time.add_many((self._clock() - start) / m, m)
        self._wake()

    async def wait_for_tick(self, k: int) -> int:
        """Wait until at least ``k`` ticks have run; returns the tick count."""
        if self.error is not None:
            raise RuntimeError("the tick task has failed") from self.error
        if self.ticks >= k:
            return self.ticks
        fut = asyncio.get_running_loop().create_future()
        heapq.heappush(self._waiters, (k, next(self._seq), fut))
        return await fut

    # --- instructor: run/freeze, speed, snapshots, malfunctions --------------------------------------

    @property
    def lockstep(self) -> bool:
        """``True`` with ``time_scale == 0``: only :meth:`advance` (a client's ``step`` write) moves the clock."""
        return self.time_scale == 0

    @property
    def frozen(self) -> bool:
        """``True`` while frozen by :meth:`freeze` (or with ``time_scale == 0``): no tick runs by itself."""
        return self._frozen or self.time_scale == 0

    async def _reschedule(self) -> None:
        task, self._task = self._task, None
        await cancel_and_wait(task)
        if self._started and not self.frozen:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=TICK_TASK_NAME)

    async def freeze(self) -> None:
        """Stop simulated time: no tick runs until :meth:`resume` (writes still queue)."""
        self._frozen = True
        await self._reschedule()

    async def resume(self) -> None:
        """Run again after :meth:`freeze`, on a schedule anchored at now."""
        self._frozen = False
        await self._reschedule()

    async def set_time_scale(self, time_scale: float) -> None:
        """Change the speed while running (``> 0``, finite or ``inf``); re-anchors the schedule at now."""
        if not (time_scale > 0):
            raise ValueError(f"time_scale must be > 0 (freeze() stops time), got {time_scale!r}")
        self.time_scale = float(time_scale)
        self.period = float(self.bank.dt) / self.time_scale if self.time_scale < math.inf else math.nan
        await self._reschedule()

    def _fingerprint(self) -> dict[str, Any]:
        return {"units": list(self.units), "blocks": [int(b) for b in self.layout.blocks], "n": int(self.bank.n),
                "dt": float(self.bank.dt)}

    def snapshot(self, name: str) -> Snapshot:
        """The complete state now, between two ticks (see :mod:`~valve_emulator.device.snapshots`)."""
        if not hasattr(self.bank, "state"):
            raise SnapshotError("this loop bank cannot be captured", field="bank")
        ramps = self.malfunctions.state() if self.malfunctions is not None else []
        device = {"ticks": self.ticks, "ramps": ramps, "config": self._fingerprint()}
        if self.alarms is not None:
            device["alarms"] = self.alarms.words.tolist()
        return Snapshot(name=name, time=float(self.bank.sample_time), ticks=self.ticks, bank=self.bank.state(),
                        device=device)

    def restore(self, snap: Snapshot) -> None:
        """Put ``snap`` back: the device continues as after the save; pending writes are dropped.

        Raises :class:`~valve_emulator.device.snapshots.SnapshotError` (nothing changed) for a snapshot of
        another configuration, of another number of loops, holding a NaN or infinity where the bank never
        does (``NON_FINITE_STATE`` of the bank), or an integer outside its range or unlike the configuration's
        (``dynamic_int_state``); every check runs before anything is written."""
        if snap.device.get("config") != self._fingerprint():
            raise SnapshotError(f"snapshot {snap.label} was taken on another configuration "
                                f"({snap.device.get('config')}); this device is {self._fingerprint()}",
                                field="name")
        snap.check_finite(getattr(self.bank, "NON_FINITE_STATE", {}))
        if hasattr(self.bank, "dynamic_int_state"):
            snap.check_integers(self.bank.state(), self.bank.dynamic_int_state())
        ramps = snap.device.get("ramps", [])
        if self.malfunctions is not None:
            try:
                ramps = self.malfunctions.parse_state(ramps, n=self.bank.n)
            except (TypeError, ValueError, KeyError) as exc:
                raise SnapshotError(f"snapshot {snap.label}: malfunction ramps do not fit this device: {exc}",
                                    field="file") from None
        alarm_words = None
        if self.alarms is not None:
            try:
                alarm_words = self.alarms.checked_words(snap.device.get("alarms"))
            except ValueError as exc:
                raise SnapshotError(f"snapshot {snap.label}: {exc}", field="file") from None
        try:
            self.bank.set_state(snap.bank)
        except ValueError as exc:   # StateMismatch: checked before anything was written
            raise SnapshotError(f"snapshot {snap.label} does not fit this device: {exc}", field="name") from exc
        if self.malfunctions is not None:
            self.malfunctions.set_state(ramps)
        if self.alarms is not None:
            self.alarms.set_words(alarm_words)
            words = np.frombuffer(self.image, dtype=">u2")   # every loop's alarms register at once
            words[self.offsets // 2 + _ALARMS] = self.alarms.words
        self._pending.clear()
        self.ticks = int(snap.device["ticks"])
        self._refresh()

    def inject(self, malfunction: Malfunction) -> None:
        """Apply a checked malfunction (:func:`~valve_emulator.device.malfunctions.parse_malfunction`) now."""
        if self.malfunctions is None:
            raise RuntimeError("this loop bank takes no malfunctions")
        self.malfunctions.inject(malfunction, float(self.bank.t))
        self._refresh()

    # --- schedule and lifecycle ---------------------------------------------------------------------

    async def _run(self) -> None:
        try:
            if self.time_scale == math.inf:
                while True:
                    self.tick()
                    await asyncio.sleep(0)  # let requests in between back-to-back ticks
            period, clock = self.period, self._clock
            t0, j = clock(), 0
            while True:
                j += 1
                deadline = t0 + j * period  # absolute: jitter never accumulates into drift
                delay = deadline - clock()
                await (self._sleep(delay) if delay > 0 else asyncio.sleep(0))
                late = clock() - deadline
                if late > period:
                    self.overruns += 1
                    j += int(late // period)  # next deadline is the first grid point after now
                self.jitter.add(late)
                self.tick()
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a broken bank: keep serving the last image, report once
            self.error = exc
            _log.error("tick task stopped at tick %d: %r", self.ticks, exc, exc_info=exc)
            for _, _, fut in self._waiters:
                if not fut.done():
                    fut.set_exception(RuntimeError("the tick task has failed"))
            self._waiters.clear()

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    async def start(self) -> None:
        """Start the tick task (nothing to start with ``time_scale == 0`` or while frozen)."""
        self._started = True
        if self._task is None and not self.frozen:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=TICK_TASK_NAME)

    async def stop(self) -> None:
        """Cancel the tick task and wait for it; cancel whoever still waits for a tick."""
        self._started = False
        task, self._task = self._task, None
        await cancel_and_wait(task)
        for _, _, fut in self._waiters:
            fut.cancel()
        self._waiters.clear()

    async def __aenter__(self) -> Device:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()
