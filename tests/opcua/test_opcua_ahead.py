"""The OPC UA process's publisher registers each tick's hand-off on the grid ahead and samples the shared image when a
chunk's timer fires (``OpcUaServer._publish_ahead``): so an event loop held past several hand-offs (asyncua's
publish of thousands of values, a core not given) still runs each hand-off before every publish due after it, and
each publishing interval holds exactly one value of every item; each hand-off samples the tick it is for while the
shared image keeps it (``shared.SLOTS`` ticks), so a hand-off run after the device published the next tick does not
take that tick from the next hand-off (docs/benchmarks.md §9.16-9.17, §9.19).

The device is the one of another process as the shared image shows it: a tick every :data:`PERIOD` whatever this
event loop does. The subscriptions publish as asyncua's do (a drift-free ``asyncio.sleep`` loop), the hand-off is
recorded instead of reaching asyncua; the loop is held by a ``time.sleep`` placed around a publish."""

import asyncio
import contextlib
import time

import pytest
from asyncua import ua

from valve_emulator.opcua import server as server_module
from valve_emulator.opcua.server import OpcUaServer, _Group, _Watch
from valve_emulator.opcua.shared import SLOTS

#: The tick period (s) ...
PERIOD = 0.05
#: ... the items' sampling and the subscriptions' publishing interval, in ticks ...
TICKS = 10
#: ... the monitored variables (three chunks of the hand-off) ...
VARIABLES = 450
#: ... and the subscriptions' phases (publish due at these ticks after the first, mod TICKS; between the grid's
#: hand-offs, which fall half way between ticks).
PHASES = (0.2, 2.7, 5.2, 7.9)
#: The hold begins this many ticks before a publish (at tick 20.2) and ends one tick before the hand-off after it.
HOLD_BEFORE = 2.2


class _Image:
    """The shared image of a device ticking in another process, from ``start`` on (tick 1 at ``start``), keeping its
    last ``keeps`` ticks (``ImageReader.at_most``); reads inside :meth:`sampling` see one tick."""

    offsets = ()

    def __init__(self, start: float, keeps: int = SLOTS, period: float = PERIOD) -> None:
        self.loop, self.start, self.keeps, self.period = asyncio.get_running_loop(), start, keeps, period
        self._pinned: int | None = None

    @property
    def ticks(self) -> int:
        if self._pinned is not None:
            return self._pinned
        return 1 + int((self.loop.time() - self.start) // self.period)

    @property
    def sample_time(self) -> float:
        return (self.ticks - 1) * self.period

    @property
    def tick_time(self) -> float:
        """The device's wall time of the tick the image holds."""
        return time.time() - (self.loop.time() - (self.start + (self.ticks - 1) * self.period))

    @contextlib.contextmanager
    def sampling(self, tick: int | None = None):
        newest = self.ticks
        self._pinned = newest if tick is None or not newest - self.keeps < tick < newest else tick
        try:
            yield
        finally:
            self._pinned = None

    async def wait_for_tick(self, k: int) -> int:
        await asyncio.sleep(max(0.0, self.start + (k - 1) * self.period - self.loop.time()))
        return self.ticks


async def _run(hold_ticks: float, seconds: float = 3.2, *, ticks: int = TICKS, phases: tuple = PHASES,
               hold_before: float = HOLD_BEFORE, keeps: int = SLOTS, period: float = PERIOD):
    """Run the publisher with subscriptions publishing every ``ticks`` ticks at ``phases`` (ticks after the first),
    the items sampled at that interval, the loop held ``hold_ticks`` ticks from ``hold_before`` ticks before tick
    20.2, the image keeping ``keeps`` ticks of ``period`` s; returns the order of events: ("hand", variable, the
    tick of its value) and ("publish", subscription)."""
    loop = asyncio.get_running_loop()
    start = loop.time() + 0.02
    image = _Image(start, keeps, period)
    publisher = OpcUaServer(image, loops=[], hand_ahead=True)
    order: list[tuple] = []

    async def hand(items):
        order.extend(("hand", watch.groups[0].key[0], dv.Value.Value) for _, watch, dv, _ in items)

    publisher._hand = hand
    publisher.publishes_late = []   # (when a publish was due, how late it ran), in ticks from the start
    interval = ticks * period
    sampled = interval if ticks > 1 else 0.0   # revised_sampling: one tick is every tick
    publisher._active = [_Watch(None, lambda: (image.ticks, ua.VariantType.Int64, None),
                                (_Group((k, sampled), sampled, (k,)),)) for k in range(VARIABLES)]
    publisher._dirty = False
    end = start + seconds

    async def subscription(k: int, phase: float) -> None:   # asyncua's InternalSubscription._subscription_loop
        due = start + phase * period
        await asyncio.sleep(max(due - loop.time(), 0))
        while loop.time() < end:
            order.append(("publish", k))
            publisher.publishes_late.append(((due - start) / period, (loop.time() - due) / period))
            due += interval
            await asyncio.sleep(max(due - loop.time(), 0))

    async def held() -> None:
        await asyncio.sleep(start + (20.2 - hold_before) * period - loop.time())
        publisher.hold_began = (loop.time() - start) / period   # in ticks from the start (the machine may be late)
        time.sleep(hold_ticks * period)   # the event loop held: asyncua's publish of thousands of values

    task = loop.create_task(publisher._publish_ahead())
    try:
        await asyncio.gather(held(), *(subscription(k, phase) for k, phase in enumerate(phases)))
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    return order, publisher


def _windows(order, k):
    """Per publishing interval of subscription ``k`` (between two of its publishes, from the second on): how many
    values each variable was handed."""
    marks = [i for i, event in enumerate(order) if event == ("publish", k)]
    windows = []
    for a, b in zip(marks[1:], marks[2:], strict=False):
        counts = dict.fromkeys(range(VARIABLES), 0)
        for event in order[a:b]:
            if event[0] == "hand":
                counts[event[1]] += 1
        windows.append(counts)
    return windows


def _lost(order, subscriptions: int = len(PHASES)):
    """The (subscription, interval, variable) with other than one value in that interval: with a queue of one, a
    variable handed twice lost the older value, one handed none went without."""
    return [(k, w, v, n) for k in range(subscriptions) for w, counts in enumerate(_windows(order, k))
            for v, n in counts.items() if n != 1]


async def test_after_a_hold_longer_than_the_hand_offs_registered_ahead_every_item_is_handed_once_an_interval_again():
    """A hold past every registered hand-off (whose own registrations ahead were past by then) does not end the
    hand-offs: the publisher registers them anew from the next tick's note."""
    order, _ = await _run(25, seconds=4.0)
    for k in range(len(PHASES)):
        last = _windows(order, k)[-1]
        assert set(last.values()) == {1}, k


@pytest.mark.parametrize("hold_ticks", [0, 1, 3, 7])
async def test_a_loop_held_k_ticks_still_hands_every_item_due_in_them_before_each_publish_due_after_its_hand_off(
        hold_ticks, monkeypatch):
    """Holds shorter than the hand-offs registered ahead; those are set to 20 ticks here (HAND_AHEAD is 10) so that
    a loaded test machine's own stall of the test process (a hold too, 0.15 s and more seen at load 10 beside a
    7-tick hold) does not take the hold past them."""
    monkeypatch.setattr(server_module, "HAND_AHEAD", 20)
    order, publisher = await _run(hold_ticks)
    assert sum(event == ("publish", 0) for event in order) >= 5
    assert not _lost(order)
    # no value older than the newest tick handed after a newer one: the ticks handed never go back
    ticks = [event[2] for event in order if event[0] == "hand"]
    assert ticks == sorted(ticks)
    # after a hold the hand-offs due in it sample each its own tick, which the shared image still keeps: none skipped
    assert publisher.skipped == 0


async def test_registered_only_one_tick_ahead_a_hold_of_three_ticks_loses_values(monkeypatch):
    """The rule's test can fail: with each hand-off registered only when the one before it fires, the hand-offs
    due in the hold after the first go on the heap after the publish due among them has woken, and come after it."""
    monkeypatch.setattr(server_module, "HAND_AHEAD", 1)
    order, _ = await _run(3)
    lost = _lost(order)
    assert lost and {n for *_, n in lost} <= {0, 2}


#: Subscriptions publishing every tick, between the grid's hand-offs (half way between ticks) and after them.
EVERY_TICK_PHASES = (0.2, 0.8)
#: The publishing intervals around the hold (from tick 19.45) that the every-tick tests look at: from the publishes
#: at ticks 18.2 / 18.8 to those at 22.2 / 22.8. (The machine's own stalls of the test process elsewhere in the run are
#: not the rule's: at load 10 one in six runs had an interval of two values away from the hold.)
AROUND_THE_HOLD = range(17, 21)


#: Their tick period (s): longer than the other tests', so that a loaded machine's own stall of the test process (0.1 s
#: and more at load 14) is not a hold past a publish of its own.
EVERY_TICK_PERIOD = 0.2


def _stalled(publisher, hold_ticks: float) -> bool:
    """Whether the loaded machine held the test's event loop besides the hold (a publish due before the hold, or due
    more than a tick after its end, ran over a third of a tick late), or the hold began late (after the hand-off it
    is to hold back): at load 13 a first run in a process had a stall of 1.5 ticks just before the hold, which made
    it a hold longer than the publishing interval."""
    hold = 20.2 - 0.75
    if publisher.hold_began > hold + 0.05:   # began after the hand-off it was to hold back (due at tick 19.5)
        return True
    return any(late > 1 / 3 for due, late in publisher.publishes_late
               if 15 <= due < hold or hold + hold_ticks + 1 < due < 24)


@pytest.mark.parametrize("hold_ticks", [0.7, 1.4])
async def test_sampled_every_tick_a_hand_off_run_after_the_next_tick_hands_its_own_tick_and_no_interval_goes_without(
        hold_ticks):
    """The 1-client row at 100 ms (docs/benchmarks.md §9.19): items sampled and published every tick. A hold from
    just before a hand-off past the next tick's arrival (0.7 ticks: the hand-off runs after the device published
    the next tick) leaves every publishing interval of every subscription with one value of every item, each
    variable handed every tick in order. (A hold longer than the publishing interval merges publishes in asyncua's
    own catch-up, whatever the server hands.)"""
    for _ in range(3):   # a run the machine stalled besides the hold, or whose hold began late, again (_stalled)
        order, publisher = await _run(hold_ticks, 6.0, ticks=1, phases=EVERY_TICK_PHASES, hold_before=0.75,
                                      period=EVERY_TICK_PERIOD)
        if not _stalled(publisher, hold_ticks):
            break
    assert sum(event == ("publish", 0) for event in order) >= 25
    assert not [miss for miss in _lost(order, len(EVERY_TICK_PHASES)) if miss[1] in AROUND_THE_HOLD]
    handed = [event[2] for event in order if event[0] == "hand" and event[1] == 0]
    assert handed == list(range(handed[0], handed[0] + len(handed)))
    assert publisher.skipped == 0


async def test_sampled_every_tick_with_the_newest_tick_only_a_late_hand_off_leaves_an_interval_without_the_item():
    """The rule's test can fail: an image that keeps the newest tick only (as before 2026-11-28) hands the next
    tick at the late hand-off and nothing at the next one (the same tick: unchanged), so a publishing interval goes
    without every item the late hand-off handed."""
    for _ in range(3):   # a run whose hold began late (after the hand-off it holds back) is no test of the rule
        order, publisher = await _run(0.7, 6.0, ticks=1, phases=EVERY_TICK_PHASES, hold_before=0.75, keeps=1,
                                      period=EVERY_TICK_PERIOD)
        if not _stalled(publisher, 0.7):
            break
    lost = [miss for miss in _lost(order, len(EVERY_TICK_PHASES)) if miss[1] in AROUND_THE_HOLD]
    assert lost and 0 in {n for *_, n in lost}
