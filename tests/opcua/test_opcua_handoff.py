"""A subscription publishing at the tick with a queue of one gets every tick's value once: the publisher hands each
tick's values on a grid of the tick period, in the same order against every publish whatever the tick's jitter
and the subscription's phase. asyncua's client, both server modes, a device whose ticks come late by a random
0-20 ms."""

import asyncio
import contextlib
import math
import random
import time

import pytest
from asyncua import Client

from valve_emulator.device.tick import Device
from valve_emulator.opcua import NAMESPACE
from valve_emulator.opcua.handoff import (
    EARLY,
    HAND_OFF_DELAY,
    HAND_SPREAD,
    PATIENCE,
    TAKE_LATE,
    HandOffGrid,
    Wakeups,
    chunk_times,
    until,
)

from .modes import serve_opcua

TICK = 0.1


def test_hand_offs_fall_on_a_grid_of_the_period_whatever_the_ticks_lateness():
    rng = random.Random(7)
    grid = HandOffGrid()
    arrivals = [1000.0 + k * TICK + (0.0 if k == 0 else rng.uniform(0.0, 0.4 * TICK)) for k in range(200)]
    due = [grid.due(k, at, TICK) for k, at in enumerate(arrivals)]
    assert due == pytest.approx([1000.0 + (k + HAND_OFF_DELAY) * TICK for k in range(200)], abs=1e-9)
    assert all(at <= d for at, d in zip(arrivals, due, strict=True))


def test_the_grid_stays_put_for_early_ticks_moves_to_much_earlier_ones_and_skipped_ticks_keep_their_place():
    grid = HandOffGrid()
    assert grid.due(5, 10.03, TICK) == pytest.approx(10.03 + HAND_OFF_DELAY * TICK)
    early = 10.13 - 0.9 * EARLY * TICK
    assert grid.due(6, early, TICK) == pytest.approx(10.13 + HAND_OFF_DELAY * TICK)          # stays put
    assert grid.due(9, 10.43, TICK) == pytest.approx(10.43 + HAND_OFF_DELAY * TICK)          # ticks 7, 8 unseen
    much_earlier = 10.53 - 1.1 * EARLY * TICK
    assert grid.due(10, much_earlier, TICK) == pytest.approx(much_earlier + HAND_OFF_DELAY * TICK)   # moved


def test_a_tick_later_than_its_hand_off_is_handed_at_once_and_a_schedule_that_moved_is_followed():
    grid = HandOffGrid()
    grid.due(0, 50.0, TICK)
    late = 50.0 + (1 + HAND_OFF_DELAY + 0.2) * TICK   # tick 1, past its hand-off on the grid
    dues = [grid.due(k, late + (k - 1) * TICK, TICK) for k in range(1, PATIENCE + 2)]
    assert dues[:PATIENCE - 1] == [late + k * TICK for k in range(PATIENCE - 1)]                   # at once
    assert dues[PATIENCE - 1:] == pytest.approx([late + (k + HAND_OFF_DELAY) * TICK              # moved
                                                 for k in range(PATIENCE - 1, PATIENCE + 1)])


def test_a_tick_is_overdue_once_its_hand_off_on_the_grid_is_past_by_half_a_tick_and_asking_does_not_move_the_grid():
    """What the publisher asks of a tick that came while it was busy: skip it (its hand-off is past by half a tick
    or more: wait for the next) or take it at once (less: the next is not due before then)."""
    grid = HandOffGrid()
    assert not grid.overdue(3, 99.0, TICK)   # no grid yet
    grid.due(0, 20.0, TICK)
    hand_off = 20.0 + (2 + HAND_OFF_DELAY) * TICK   # tick 2's
    assert grid.at(2) == pytest.approx(hand_off)
    assert not grid.overdue(2, hand_off - 0.001, TICK)
    assert not grid.overdue(2, hand_off + 0.001, TICK)   # past, by less than half a tick: taken at once
    assert not grid.overdue(2, hand_off + (TAKE_LATE - 0.01) * TICK, TICK)
    assert grid.overdue(2, hand_off + (TAKE_LATE + 0.01) * TICK, TICK)
    assert not grid.overdue(2, hand_off + TICK, 2 * TICK)   # another period: no grid for it
    assert not grid.overdue(2, hand_off + TICK, math.inf)   # no real-time period
    assert grid.due(1, 20.0 + TICK, TICK) == pytest.approx(20.0 + (1 + HAND_OFF_DELAY) * TICK)   # unmoved


def test_a_tick_handed_late_keeps_its_grid_time_for_sampling():
    """A tick later than its hand-off is handed at once, but the samples it takes are those due at its time on the
    grid: which tick samples an item sampled at 1 s does not depend on how late the ticks come (were it the
    arrival, an item due between the grid time and a late arrival would move to the tick before, its hand-off a
    tick earlier, across a subscription's publish: one interval with two values, the older discarded)."""
    grid = HandOffGrid()
    grid.due(0, 50.0, TICK)
    assert grid.on_grid == pytest.approx(50.0 + HAND_OFF_DELAY * TICK)
    late = 50.0 + (1 + HAND_OFF_DELAY + 0.2) * TICK
    assert grid.due(1, late, TICK) == late                                                       # at once
    assert grid.on_grid == pytest.approx(50.0 + (1 + HAND_OFF_DELAY) * TICK)                    # its grid time
    assert grid.due(2, 50.0 + 2.01 * TICK, TICK) == pytest.approx(50.0 + (2 + HAND_OFF_DELAY) * TICK)
    assert grid.on_grid == pytest.approx(50.0 + (2 + HAND_OFF_DELAY) * TICK)
    grid.due(3, 1.0, float("nan"))
    assert math.isnan(grid.on_grid)                                                              # lockstep


@pytest.mark.parametrize("chunks", [1, 2, 6, 7, 10, 20, 100])
def test_a_ticks_chunks_are_spaced_as_asked_but_end_a_quarter_period_before_the_next_tick_however_many(chunks):
    """The hand-off of a tick ends HAND_OFF_DELAY + HAND_SPREAD of a period after it, before the next tick comes:
    the publisher then waits for that tick and samples it at once. At a fixed 5 % apart, 4,000 monitored
    variables (20 chunks) spread over 95 % of the period, and the publisher, still handing when the next tick
    came, sampled it late or skipped it (docs/benchmarks.md §9.8)."""
    from valve_emulator.opcua.server import HAND_SPACING

    due, period = 7.0, 0.1
    times = chunk_times(due, period, chunks, HAND_SPACING)
    assert len(times) == chunks and times[0] == due
    steps = [b - a for a, b in zip(times, times[1:])]
    assert all(step > 0 for step in steps) and max(steps, default=0) - min(steps, default=0) < 1e-12
    assert times[-1] <= due + HAND_SPREAD * period + 1e-12
    assert HAND_OFF_DELAY + HAND_SPREAD <= 0.75
    if chunks * HAND_SPACING <= HAND_SPREAD + HAND_SPACING:   # few chunks: as far apart as asked
        assert steps == pytest.approx([HAND_SPACING * period] * (chunks - 1))


def test_a_new_period_or_a_tick_count_that_went_back_anchors_the_grid_anew_and_no_period_hands_at_once():
    grid = HandOffGrid()
    grid.due(10, 1.0, TICK)
    assert grid.due(11, 1.105, TICK / 2) == pytest.approx(1.105 + HAND_OFF_DELAY * TICK / 2)   # a speed change
    assert grid.due(3, 1.2, TICK / 2) == pytest.approx(1.2 + HAND_OFF_DELAY * TICK / 2)        # a restored snapshot
    assert grid.due(4, 1.3, float("nan")) == 1.3                                               # lockstep


@pytest.mark.parametrize("hand_first", [True, False])
async def test_until_runs_in_due_order_with_asyncio_sleep_even_when_the_loop_wakes_late_for_both(hand_first):
    """The premise of the grid: the event loop runs due timers by due time, so a hand-off due before a publish
    (asyncua waits for it with asyncio.sleep) runs before it, and one due after it after, however late."""
    loop, order = asyncio.get_running_loop(), []
    start = loop.time()
    hand_at, publish_in = (start + 0.001, 0.002) if hand_first else (start + 0.002, 0.001)

    async def publish():
        await asyncio.sleep(publish_in)
        order.append("publish")

    async def hand():
        await until(hand_at)
        order.append("hand")

    tasks = [asyncio.create_task(publish()), asyncio.create_task(hand())]
    await asyncio.sleep(0)      # both wait on their timers
    time.sleep(0.01)            # and the loop wakes up late for both
    await asyncio.gather(*tasks)
    assert order == (["hand", "publish"] if hand_first else ["publish", "hand"])


#: Seconds after a tick at which the subscriptions are created: their publishes fall at these phases of the tick,
#: next to the tick's arrival (where a hand-off on arrival would race them) and next to the grid's hand-off.
PHASES = (0.0, 0.002, 0.004, 0.006, 0.045, 0.05, 0.055)


@pytest.mark.slow
@pytest.mark.realtime
async def test_queue_of_one_at_the_tick_gets_every_ticks_value_once_at_every_phase_despite_tick_jitter(opcua_mode,
                                                                                                      config):
    """One session per subscription: asyncua's client keeps one Publish request at the server per session, and the
    subscriptions of one session would take turns with it (a subscription due while the request is away publishes
    when the next one comes, at any time)."""
    rng = random.Random(11)

    async def late_sleep(delay):   # each tick 0-20 ms late: the jitter of a loaded machine
        await asyncio.sleep(delay + rng.uniform(0.0, 0.02))

    device = Device.from_config(config, time_scale=1.0, sleep=late_sleep)
    got: list[dict[str, list[int]]] = [{} for _ in PHASES]

    def handler(received):
        class Handler:
            def datachange_notification(self, node, val, data):
                received.setdefault(node.nodeid.Identifier, []).append(val)
        return Handler()

    async with device, serve_opcua(opcua_mode, device, loops=config.loops, port=0) as opc, \
            contextlib.AsyncExitStack() as sessions:
        clients = [await sessions.enter_async_context(Client(opc.url)) for _ in PHASES]
        ns = await clients[0].get_namespace_index(NAMESPACE)
        for phase, received, client in zip(PHASES, got, clients, strict=True):
            nodes = [client.get_node(f"ns={ns};s=Unit1.FIC101.tick"), client.get_node(f"ns={ns};s=Unit2.XV2.tick")]
            await device.wait_for_tick(device.ticks + 1)
            await asyncio.sleep(phase)
            sub = await client.create_subscription(1000 * TICK, handler(received))
            await sub.subscribe_data_change(nodes, queuesize=1, sampling_interval=1000 * TICK)
        await asyncio.sleep(0.5)           # the initial values arrive
        for received in got:
            received.clear()
        first = device.ticks
        await asyncio.sleep(3.0)
        last = device.ticks

    # every tick's value once and in order; at most one tick of the ~28 missing per item (a stall of a loaded
    # machine: a publish whose timer the event loop ran a whole interval late); handed on arrival, the items at
    # the phases next to the arrival missed about one tick in three
    assert last - first >= 25
    for phase, received in zip(PHASES, got, strict=True):
        assert len(received) == 2
        for item, values in received.items():
            window = [v for v in values if first + 2 <= v <= last - 2]   # the ends may be in flight
            missing = set(range(first + 2, last - 1)) - set(window)
            assert window == sorted(set(window)) and len(missing) <= 1, (phase, item, values)


def _chunked_publisher(order):
    """An OpcUaServer reduced to its hand-off (no address space, no asyncua): handing a variable appends it to
    ``order``."""
    from valve_emulator.opcua.server import OpcUaServer

    publisher = OpcUaServer.__new__(OpcUaServer)
    publisher._hand_cost = 20e-6

    async def hand(items):
        order.extend(watch for _, watch, _, _ in items)

    publisher._hand = hand
    return publisher


@pytest.mark.parametrize("loop_late", [False, True])
async def test_a_large_hand_off_goes_in_chunks_by_place_each_at_its_own_time_so_a_publish_waits_for_one_chunk(
        loop_late):
    """Variables at places 0-199 are handed at the due time, 200-399 a HAND_SPACING of the period later, and so
    on; a publish due between two chunks' times comes between them, whichever variables changed this tick -- also
    when the event loop wakes up late for all of them (a publish of thousands of values holding it): with each
    chunk's time put on the timer heap only once the chunk before it was handed, the publish, already on the ready
    queue beside the first chunk, came before the second."""
    from valve_emulator.opcua.server import HAND_CHUNK, HAND_SPACING

    loop, order = asyncio.get_running_loop(), []
    publisher = _chunked_publisher(order)
    period = 0.1
    due = loop.time() + 0.01
    places = [p for p in range(3 * HAND_CHUNK) if p % 7]   # some did not change
    handing = [(place, place // HAND_CHUNK, None, []) for place in places]

    async def publish():
        await asyncio.sleep(due + 1.5 * HAND_SPACING * period - loop.time())
        order.append("publish")

    publishing = asyncio.create_task(publish())
    with Wakeups([due + k * HAND_SPACING * period for k in range(3)]) as wakeups:
        await asyncio.sleep(0)
        if loop_late:
            time.sleep(due + 3 * HAND_SPACING * period - loop.time())   # past every chunk's time and the publish's
        await publisher._hand_all(handing, wakeups)
    await publishing
    assert order == [0] * len([p for p in places if p < HAND_CHUNK]) \
        + [1] * len([p for p in places if HAND_CHUNK <= p < 2 * HAND_CHUNK]) + ["publish"] \
        + [2] * len([p for p in places if p >= 2 * HAND_CHUNK])


@pytest.mark.parametrize("how, expected", [
    ("a task per due time", [0, 1, "publish", 2]),
    ("until, one after the other", [0, "publish", 1, 2]),   # before Wakeups: the second chunk after the publish
    ("one task waiting for each in turn", [0, 1, 2, "publish"]),   # the third before the publish
])
async def test_wakeups_each_waited_for_in_a_task_keep_their_order_with_asyncio_sleep_when_the_loop_is_late(
        how, expected):
    """What :class:`Wakeups` is for: a publish (asyncio.sleep) due between the second and third due time comes
    between the second and third piece of work, however late the loop wakes -- when each waits in a task of its
    own; the other two ways lose that order."""
    loop, order = asyncio.get_running_loop(), []
    start = loop.time()
    whens = [start + 0.001, start + 0.003, start + 0.005]

    async def publish():
        await asyncio.sleep(0.004)
        order.append("publish")

    async def one(wakeups, k):
        await wakeups.wait(k)
        order.append(k)

    async def work():
        if how == "until, one after the other":
            for k, when in enumerate(whens):
                if k == 0:
                    await asyncio.sleep(0)
                    time.sleep(0.01)   # the loop wakes up late for all of them
                await until(when)
                order.append(k)
            return
        with Wakeups(whens) as wakeups:
            await asyncio.sleep(0)
            time.sleep(0.01)
            if how == "a task per due time":
                await asyncio.gather(*(one(wakeups, k) for k in range(len(whens))))
            else:
                for k in range(len(whens)):
                    await one(wakeups, k)

    await asyncio.gather(publish(), work())
    assert order == expected


async def test_wakeups_not_waited_for_are_cancelled_on_leaving():
    loop = asyncio.get_running_loop()
    with Wakeups([loop.time() + 0.001, loop.time() + 3600]) as wakeups:
        await wakeups.wait(0)
        assert len(wakeups) == 2
    assert all(handle.cancelled() for handle in wakeups._handles)
