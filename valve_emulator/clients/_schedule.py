"""When to poll: on a wall-clock period, or locked to the device's own time grid.

:class:`WallSchedule` polls at absolute wall deadlines ``k·period`` (lateness never accumulates into
drift; deadlines already missed are skipped, not burst). The device time seen at each poll then advances
by ``period × time-scale`` plus the polling jitter, quantised to device ticks: steps vary by a tick or
so.

:class:`GridSchedule` samples the device's time axis itself: row ``n`` is the first reading with device
time ``t >= t0 + n·step``. It predicts from the measured rate (device seconds per wall second) when the
device reaches the next grid time and closes in (half the predicted time to go, then again), then polls
four times per device tick from a tick before until it is there. The reading then normally has exactly the
grid time (the device holds a value for a
whole tick), so rows come exactly ``step`` apart: the uniform sampling that identification wants. A
reading already past the grid time (the process was too slow to catch the tick) is used as it is and
counted as ``off_grid``; the grid continues from the next grid time after it.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable

from valve_emulator.clients._modbus import DeviceError
from valve_emulator.clients._run import pause

__all__ = ["GridSchedule", "WallSchedule", "schedule_for", "next_or_retry"]

Read = Callable[[], Awaitable[dict[str, float]]]


class WallSchedule:
    """Poll every ``period`` wall seconds from ``t0``; ``late`` counts deadlines skipped."""

    def __init__(self, period: float, *, clock: Callable[[], float]) -> None:
        self.period, self.clock = period, clock
        self.t0 = clock()
        self.k = 0
        self.late = 0
        self.off_grid = 0

    def seen(self, device_t: float) -> None:  # the wall schedule ignores device time
        pass

    async def next(self, read: Read, stop: asyncio.Event | None) -> dict[str, float] | None:
        self.k += 1
        deadline = self.t0 + self.k * self.period
        await pause(deadline - self.clock(), stop)
        if stop is not None and stop.is_set():
            return None
        late = self.clock() - deadline
        if late > self.period:   # skip the deadlines already missed instead of bursting
            missed = int(late // self.period)
            self.k += missed
            self.late += missed
        return await read()


class GridSchedule:
    """Sample the device time grid ``t0 + n·step`` (see the module docstring); needs the ``t`` channel.

    ``hint`` (wall s) paces the polls until the rate of device time is known.
    """

    def __init__(self, step: float, *, clock: Callable[[], float], hint: float = 0.1) -> None:
        self.step, self.clock, self.hint = step, clock, hint
        self.t0: float | None = None
        self.n = 0
        self.late = 0
        self.off_grid = 0
        self.tick: float | None = None   # smallest increment of device time seen: the device's tick
        self.rate = math.nan             # device seconds per wall second
        self._origin: tuple[float, float] | None = None   # (wall, device t) when time was first seen moving
        self._last: tuple[float, float] | None = None

    def seen(self, device_t: float) -> None:
        """Record a reading: the first anchors the grid; each refines rate and tick."""
        wall = self.clock()
        if self.t0 is None:
            self.t0 = device_t
        if self._last is not None and device_t > self._last[1]:
            inc = device_t - self._last[1]
            self.tick = inc if self.tick is None else min(self.tick, inc)
            # The rate is measured from the first reading that saw device time move (a tick had just
            # happened: no bias from a device slow to start), and trusted once it spans 3 ticks.
            if self._origin is None:
                self._origin = (wall, device_t)
            elif wall > self._origin[0] and device_t - self._origin[1] >= 3 * self.tick:
                self.rate = (device_t - self._origin[1]) / (wall - self._origin[0])
        self._last = (wall, device_t)

    def target(self) -> float:
        assert self.t0 is not None
        return self.t0 + self.n * self.step

    async def next(self, read: Read, stop: asyncio.Event | None) -> dict[str, float] | None:
        assert self._last is not None and self.t0 is not None, "seen() the first reading before next()"
        self.n += 1
        goal = self.target()
        eps = 1e-6 * max(1.0, abs(goal))   # device times are decimals read back from float32
        while True:
            wall_last, t_last = self._last
            if self.rate > 0:
                tick = self.tick if self.tick is not None else self.step / 8
                tick_wall = tick / self.rate
                ahead = (goal - t_last) / self.rate - (self.clock() - wall_last)
                # Close in: sleep half the predicted time to go (a reading on the way corrects the rate)
                # until within a tick (at least 2 ms: timer slack), then poll four times per tick.
                lead = max(tick_wall, 0.002)
                wait = 0.5 * ahead if ahead > 2 * lead else max(ahead - lead, 0.25 * tick_wall)
            else:   # rate not known yet: short polls (only for the first few ticks)
                wait = min(0.25 * self.hint, 0.005)
            await pause(wait, stop)
            if stop is not None and stop.is_set():
                return None
            sample = await read()
            t = sample["t"]
            self.seen(t)
            if t >= goal - eps:
                if t > goal + eps:   # the tick at the grid time went by unseen: use this reading
                    self.off_grid += 1
                    self.n = math.floor((t - self.t0) / self.step + 1e-9)
                return sample


def schedule_for(step: float | None, period: float, clock: Callable[[], float]) -> WallSchedule | GridSchedule:
    """A client's schedule: every ``period`` wall seconds, or, given a ``step`` (device s; needs the ``t``
    channel), on the device's time grid, paced by ``period`` until the rate of device time is known."""
    return GridSchedule(step, clock=clock, hint=period) if step is not None else WallSchedule(period, clock=clock)


async def next_or_retry(schedule: WallSchedule | GridSchedule, read: Read, stop: asyncio.Event | None, *,
                        retry: float, failed: Callable[[Exception], None]) -> dict[str, float] | None:
    """``schedule.next(read, stop)``; a read that fails (``ConnectionError``, :class:`DeviceError`) is passed to
    ``failed``, then ``retry`` wall seconds go by (a device that just failed is not hammered) and None is
    returned."""
    try:
        return await schedule.next(read, stop)
    except (ConnectionError, DeviceError) as exc:
        failed(exc)
        await pause(retry, stop)
        return None
