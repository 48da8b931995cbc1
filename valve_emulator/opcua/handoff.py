"""When the publisher hands a tick's values to the subscriptions: on a grid of the tick period, not when they arrive.

asyncua publishes each subscription on a timer of its own, started when the client created the subscription and
drift-free: its k-th publish is due at its start + k publishing intervals, at a phase of the tick nobody
chooses. The device ticks on a drift-free grid too, but its values reach the publisher late by an amount that
varies from tick to tick (the tick's own lateness, the note from the device process, the event loop's latency).
Were each tick's values handed as they arrive, a publish due within that variation of the arrival would come
now before the hand-off, now after it: one publishing interval would carry two ticks of an item and the next
none -- and with a queue of one, what a SCADA client asks for (the latest value), the older of the two is
discarded.

So a tick's values are handed at a time *due on a grid*: :data:`HAND_OFF_DELAY` of a period after the tick's
expected arrival on a grid of the tick period, anchored at a tick's arrival. The grid stays put while the ticks come
near it (a grid that followed every earlier arrival would move by a little now and then, and a publish due within
that little of the hand-off would see two ticks, or none, in one interval). The publisher samples the values when
the tick arrives and waits for the due time on the event loop's timer (:func:`until`, ``loop.call_at``), the way
asyncua waits for a publish (``asyncio.sleep`` to its due time). The event loop runs timers in the order of their
due times, however late it runs them; so a hand-off and a publish due on grids of the same period come in the same
order at every tick, and each publishing interval holds exactly one hand-off, whatever the tick's jitter and the
subscription's phase, provided a hand-off does not yield to the event loop mid-way (a publish already woken would
then run in between). The publisher hands a large tick in chunks, each due on a grid time of its own
(``OpcUaServer._hand_all``), so that a publish due meanwhile waits for one chunk, not for all of them.

What is left to chance: a publish that does not wait for its timer. asyncua publishes a subscription whose
client had no Publish request queued (a client busy with the last publish) when the next request arrives, at
any time; with a queue of one, values handed before it are then overwritten. A client that wants every sample
keeps Publish requests queued or asks for a queue of two.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence

__all__ = ["EARLY", "HAND_OFF_DELAY", "HAND_SPREAD", "PATIENCE", "TAKE_LATE", "HandOffGrid", "Wakeups", "chunk_times",
           "until"]

#: A tick's values are handed this share of the tick period after the tick's expected arrival: half way to the
#: next tick, so that ticks up to half a period later than the earliest are still handed on the grid, sampling
#: has half a period to be done by then, and the hand-off half a period before the next tick.
HAND_OFF_DELAY = 0.5
#: A tick's hand-off in chunks ends within this share of the tick period of its first chunk's due time, however
#: many chunks: with :data:`HAND_OFF_DELAY` its last chunk is due three quarters of a period after the tick, a
#: quarter before the next one arrives, so the publisher is waiting for that tick when it comes. (Chunks spaced at a
#: fixed share did not: 4,000 monitored variables in 20 chunks 5 % apart spread over 95 % of the period, and the
#: publisher, still handing the last chunks when the next tick came, sampled that tick late, or not at all:
#: docs/benchmarks.md §9.8.)
HAND_SPREAD = 0.25
#: A tick this share of the period earlier than the grid expects moves the grid to it.
EARLY = 0.25
#: A tick that came while the publisher was busy is still taken at once when its hand-off on the grid is past by
#: less than this share of the period (:meth:`HandOffGrid.overdue`): the next tick is not due before then, so
#: waiting for it would lose the publishes due until its hand-off, while taking this one loses only those due in
#: the few ms it is late (docs/benchmarks.md §9.16: a third of the runs of skipped ticks ended so).
TAKE_LATE = 0.5
#: After this many ticks in a row later than their hand-off was due, the grid moves to them (the device's
#: schedule moved: a resume, a restored snapshot).
PATIENCE = 3


class HandOffGrid:
    """The due time of each tick's hand-off (see the module docstring): :meth:`due`.

    The grid is anchored at a tick's arrival. A tick later than its hand-off is handed at once; the grid moves
    to a tick that comes more than :data:`EARLY` of a period before it expects, after :data:`PATIENCE` late ticks
    in a row (the device's schedule moved: a resume, a restored snapshot, a first tick that came late), and with
    a new period or a tick count that went back. Without a real-time period (lockstep, as fast as possible)
    every hand-off is due at once."""

    def __init__(self, delay: float = HAND_OFF_DELAY, patience: int = PATIENCE) -> None:
        self.delay, self.patience = delay, patience
        self._period = math.nan
        self._tick = 0
        self._arrival = math.nan   # the expected arrival of tick _tick
        self._late = 0
        #: times the grid was (re-)anchored
        self.anchors = 0
        #: the last tick's hand-off time on the grid: what :meth:`due` answered, or for a tick later than that, the
        #: grid's time it was handed after (the time its samples are taken at: a tick's lateness does not move them)
        self.on_grid = math.nan

    def due(self, tick: int, arrived: float, period: float) -> float:
        """When to hand the values of tick number ``tick``, which arrived at ``arrived`` (the event loop's
        clock), ticks being ``period`` seconds apart (not finite: no real-time schedule)."""
        if not (math.isfinite(period) and period > 0):
            self._period = self.on_grid = math.nan
            return arrived
        if period != self._period or tick < self._tick:
            return self._anchor(tick, arrived, period)
        expected = self._arrival + (tick - self._tick) * period
        if arrived < expected - EARLY * period:
            return self._anchor(tick, arrived, period)
        self.on_grid = due = expected + self.delay * period
        if arrived <= due:
            self._late = 0
            return due
        self._late += 1
        if self._late >= self.patience:
            return self._anchor(tick, arrived, period)
        return arrived

    @property
    def period(self) -> float:
        """The period of the grid (NaN without one)."""
        return self._period

    def at(self, tick: int) -> float:
        """Tick number ``tick``'s hand-off time on the grid as it stands (NaN without a grid): for a tick not yet
        come, where its hand-off is registered ahead."""
        if not math.isfinite(self._period) or tick < self._tick:
            return math.nan
        return self._arrival + (tick - self._tick + self.delay) * self._period

    def overdue(self, tick: int, now: float, period: float) -> bool:
        """Whether tick number ``tick``'s hand-off on the grid was past by :data:`TAKE_LATE` of a period or more at
        ``now`` (without moving the grid): for a tick that came while the publisher was still busy with an earlier
        one. False without a grid (no real-time period, a new period, a tick count that went back)."""
        if not (math.isfinite(period) and period > 0) or period != self._period or tick < self._tick:
            return False
        return now >= self._arrival + (tick - self._tick + self.delay + TAKE_LATE) * period

    def _anchor(self, tick: int, arrived: float, period: float) -> float:
        self._period, self._tick, self._arrival, self._late = period, tick, arrived, 0
        self.anchors += 1
        self.on_grid = arrived + self.delay * period
        return self.on_grid


def chunk_times(due: float, period: float, chunks: int, spacing: float) -> list[float]:
    """When each of a tick's ``chunks`` chunks is due: the first at ``due``, the others ``spacing`` of the tick
    ``period`` apart, or closer where that would spread them over more than :data:`HAND_SPREAD` of it. Chunks closer
    than their work takes run one after the other, in order (:class:`Wakeups`): a publish due between two chunks'
    times still comes between them."""
    if chunks <= 1:
        return [due] * chunks
    step = min(spacing, HAND_SPREAD / (chunks - 1)) * period
    return [due + k * step for k in range(chunks)]


def _wake(fut: asyncio.Future) -> None:
    if not fut.done():
        fut.set_result(None)


async def until(when: float) -> None:
    """Wait until the event loop's clock reads ``when`` (at once if it has), on the loop's timer heap: ahead of
    every timer due later, behind every timer due earlier."""
    loop = asyncio.get_running_loop()
    fut = loop.create_future()
    handle = loop.call_at(when, _wake, fut)
    try:
        await fut
    finally:
        handle.cancel()


class Wakeups:
    """Several due times put on the event loop's timer heap at once: :meth:`wait` for the ``k``-th, each in a task
    of its own.

    The event loop runs due timers in the order of their due times, however late; a timer here sets a future and
    the task waiting for it runs at the loop's next pass -- as a task that waits with ``asyncio.sleep`` (asyncua's
    publish) is woken. So tasks waiting for these due times and tasks asyncua wakes run in the order of their due
    times whatever the loop's lateness, provided each waits in a task of its own. Two ways lose that order when the
    loop runs late (a publish of thousands of values holding it): waiting for the due times one after the other
    with :func:`until` (the ``k``-th goes on the heap only once the ``(k-1)``-th's work is done; a publish due
    between the two was by then on the ready queue and runs first), and waiting for all of them in one task (the
    ``k``-th is already done when the ``(k-1)``-th's work ends, so the work due after a publish runs before it).
    Use as a context manager: the wake-ups not waited for are cancelled on leaving."""

    def __init__(self, whens: Sequence[float]) -> None:
        loop = asyncio.get_running_loop()
        self._futures = [loop.create_future() for _ in whens]
        self._handles = [loop.call_at(when, _wake, fut) for when, fut in zip(whens, self._futures, strict=True)]

    def __len__(self) -> int:
        return len(self._futures)

    async def wait(self, k: int) -> None:
        """Until the ``k``-th due time."""
        await self._futures[k]

    def cancel(self) -> None:
        for handle in self._handles:
            handle.cancel()

    def __enter__(self) -> Wakeups:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.cancel()
