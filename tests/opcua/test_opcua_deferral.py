"""A tick's values reach each monitored item in the publishing interval they belong to, also when the publisher's
pass over a tick overruns its share of the tick (the OPC UA process preempted, a full garbage collection): in a
process of its own nothing is deferred to the next tick, whose hand-off can fall after the item's publish (with a
queue of one that publish goes out without the item, and the next one keeps only its newer sample:
docs/benchmarks.md §9.11-9.12). In the device's process the tick comes first: there the rest of an overrun pass is
still deferred.

Deterministic: the publisher's pass (``_sample`` then ``_hand_all``, as ``_publish`` runs them) is driven by hand over
a lockstep device, every pass stalled past its budget, and ten subscriptions of asyncua's server "publish" (their
queues taken, as asyncua's publish takes them) each after the hand-off of a different tick of the sampling interval."""

import asyncio
import time

import pytest
from asyncua import ua

from valve_emulator.device.tick import Device
from valve_emulator.opcua import server as server_module
from valve_emulator.opcua.handoff import Wakeups
from valve_emulator.opcua.server import PROCESS_PUBLISH_BUDGET, PUBLISH_BUDGET, OpcUaServer
from valve_emulator.opcua.source import LocalSource

#: The tick period of the publisher's time axis (s; the device is lockstep, the pass is given its due times) ...
PERIOD = 0.02
#: ... the items' sampling and the subscriptions' publishing interval, in ticks ...
TICKS = 10
#: ... and how long each pass stalls before it samples: more than any budget's share of the period.
STALL = 1.2 * PERIOD


class _Quiet:
    def datachange_notification(self, node, val, data):
        pass


class _Stalled:
    """The server's tick clock, whose stamp (taken at the start of each pass) stalls the pass first."""

    def __init__(self, clock):
        self.clock = clock

    def stamp(self):
        time.sleep(STALL)
        return self.clock.stamp()


def _tick(value, dt):
    """The tick a value of ``tick`` (the count) or ``time`` (the sample time, s: the tick's start, (tick - 1) dt)
    was sampled at."""
    return value if isinstance(value, int) else round(value / dt) + 1


async def _publishes(config, budget):
    """Drive the publisher over 5 sampling intervals with every pass stalled; returns, per subscription (the k-th
    publishing after the hand-off of ticks k, k + TICKS, ...), the list of its publishes, each (the tick it followed,
    {item: [the ticks of the values queued]}), and the number of deferred passes. The items: ``tick`` and ``time``
    of both loops (both change at every tick), sampled and published every TICKS ticks, queue of one."""
    device = Device.from_config(config, time_scale=0)
    async with OpcUaServer(LocalSource(device), loops=config.loops, port=0, publish_budget=budget,
                           yield_while_sampling=False) as opc:
        publisher, opc._publisher = opc._publisher, None   # the test drives the passes
        publisher.cancel()
        await asyncio.gather(publisher, return_exceptions=True)
        ns = opc.ns
        nodes = [opc.server.get_node(ua.NodeId(f"Unit{u}.{name}.{var}", ns))
                 for u, name in ((1, "FIC101"), (2, "XV2")) for var in ("tick", "time")]
        internals = []
        for _ in range(TICKS):
            sub = await opc.server.create_subscription(3_600_000, _Quiet())   # publishes only when the test asks
            await sub.subscribe_data_change(nodes, queuesize=1, sampling_interval=1000 * TICKS * PERIOD)
            internals.append(opc.server.iserver.subscription_service.subscriptions[sub.subscription_id])
        for node in nodes:   # the sampling interval each item is honoured at (as a client's request sets it)
            attval = opc.server.iserver.aspace._nodes[node.nodeid].attributes[ua.AttributeIds.Value]
            for handle in attval.datachange_callbacks:
                opc._intervals[handle] = TICKS * PERIOD
        opc._dirty = True
        for internal in internals:
            internal._triggered_datachanges.clear()   # the initial values
        loop = asyncio.get_running_loop()
        clock, opc.tick_clock = opc.tick_clock, _Stalled(opc.tick_clock)
        published: list[list[tuple[int, dict[int, list[int]]]]] = [[] for _ in internals]
        at = 0
        for tick in range(1, 5 * TICKS + 1):
            device.advance(1)
            clock.stamp()
            if opc._dirty:
                opc._dirty, at = False, 0
                opc._active = opc._watches()
            handing, at = await opc._sample(at, tick * PERIOD, PERIOD, opc.publish_budget * PERIOD)
            with Wakeups([loop.time()]) as wakeups:
                await opc._hand_all(handing, wakeups)
            internal = internals[tick % TICKS]
            queued = {mid: [_tick(n.Value.Value.Value, config.device.tick) for n in notes] for mid, notes in
                      internal._triggered_datachanges.items()}
            internal._triggered_datachanges.clear()
            published[tick % TICKS].append((device.ticks, queued))
        return published, opc.deferred


async def test_an_overrun_pass_in_a_process_of_its_own_hands_every_item_in_its_publishing_interval(config,
                                                                                                 monkeypatch):
    """Each publish after the first interval carries each item once, a value of a tick since the publish before:
    what a publisher that kept up hands a queue of one. Before (a budget of 0.7 of the tick there too), each pass
    stopped after one variable and the other went on at the next tick, past the publish that followed its own."""
    monkeypatch.setattr(server_module, "YIELD_EVERY", 1)   # the budget looked at after every variable
    published, deferred = await _publishes(config, PROCESS_PUBLISH_BUDGET)
    for publishes in published:
        for (before, _), (last, queued) in zip(publishes, publishes[1:]):
            assert len(queued) == 4, (last, queued)
            for values in queued.values():
                assert len(values) == 1 and before < values[0] <= last, (before, last, queued)
    assert deferred == 0


async def test_an_overrun_pass_in_the_devices_process_defers_the_rest_to_the_next_tick(config, monkeypatch):
    """The tick comes first there: a pass over its budget stops, and some publish goes out without an item."""
    monkeypatch.setattr(server_module, "YIELD_EVERY", 1)
    published, deferred = await _publishes(config, PUBLISH_BUDGET)
    assert deferred == 5 * TICKS
    lacking = [queued for publishes in published for queued in [q for _, q in publishes[1:]] if len(queued) < 4]
    assert lacking


@pytest.mark.parametrize("step", [1, 3])
async def test_ticks_the_publisher_never_sampled_are_counted(config, step):
    """A publisher that finds the device several ticks on (behind it) counts ticks it skipped (of each 3 run at
    once, it samples the first or the last and at least one in between is skipped); one that keeps up none."""
    device = Device.from_config(config, time_scale=0)
    async with OpcUaServer(LocalSource(device), loops=config.loops, port=0) as opc:
        for _ in range(20):   # the publisher waits for the first tick
            await asyncio.sleep(0)
        for _ in range(4):
            device.advance(step)
            for _ in range(20):   # its pass over this tick
                await asyncio.sleep(0)
        counters = await opc.counters()
    skipped = counters.skipped
    assert skipped == 0 if step == 1 else 4 <= skipped <= 4 * (step - 1)
    # each skipped tick is kept for --trace: one record each, none of them a tick the publisher took (every step-th)
    kept = [t.tick for t in counters.off_grid if t.skipped]
    assert len(kept) == len(set(kept)) == skipped and all(tick % step for tick in kept)
