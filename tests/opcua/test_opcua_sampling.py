"""Monitored items are sampled at their sampling interval: a SCADA client asking for 1 s costs one notification
per item per second on a 0.1 s tick, and gets the tick's latest value; sampling 0 still gets every tick's change.
asyncua's client, both server modes."""

import asyncio

import pytest
from asyncua import Client

from valve_emulator.device.server import EmulatorServer
from valve_emulator.opcua import NAMESPACE
from valve_emulator.opcua.server import first_due, next_due, revised_sampling

from .modes import serve_opcua

TICK = 0.1


async def _time_nodes(client):
    """The ``time`` variable (the sample time, which changes by one tick at every tick) of both loops."""
    ns = await client.get_namespace_index(NAMESPACE)
    return (client.get_node(f"ns={ns};s=Unit1.FIC101.time"), client.get_node(f"ns={ns};s=Unit2.XV2.time"))


@pytest.mark.slow
async def test_item_sampled_at_one_second_gets_the_latest_value_once_a_second_and_sampling_zero_every_tick(
        opcua_mode, config):
    got: dict[str, list[tuple[float, float]]] = {"slow": [], "fast": []}
    # the fast item's latest value, kept across the clearing below: a publish carries the slow item before the fast
    # one (their places in the publisher's list), so the window's first slow value may come before its first fast one
    latest = {"fast": float("nan")}

    class Handler:
        def datachange_notification(self, node, val, data):
            name = "slow" if node == slow_node else "fast"
            got[name].append((val, latest["fast"]))
            if name == "fast":
                latest["fast"] = val

    async with EmulatorServer(config, port=0, time_scale=1.0) as srv, \
            serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0) as opc, Client(opc.url) as client:
        slow_node, fast_node = await _time_nodes(client)
        sub = await client.create_subscription(100, Handler())
        await sub.subscribe_data_change(slow_node, queuesize=1, sampling_interval=1000)
        await sub.subscribe_data_change(fast_node, sampling_interval=0)
        await asyncio.sleep(1.5)   # the initial values arrive
        for values in got.values():
            values.clear()
        ticks0 = srv.device.ticks
        await asyncio.sleep(4.0)
        ticks = srv.device.ticks - ticks0
        await sub.delete()

    slow = [v for v, _ in got["slow"]]
    fast = [v for v, _ in got["fast"]]
    # one notification a second, not one a tick
    assert 3 <= len(slow) <= 5, slow
    # one sample a second apart in the device's time
    assert all(0.75 <= b - a <= 1.25 for a, b in zip(slow, slow[1:])), slow
    # each is the value of the tick it was sampled at, not one from the start of its second
    assert all(abs(v - latest_fast) <= 2.5 * TICK for v, latest_fast in got["slow"]), got["slow"]
    # sampling 0: every tick's change (a tick the machine ran late may come with the next)
    assert len(fast) >= 0.8 * ticks, (len(fast), ticks)
    steps = [round((b - a) / TICK) for a, b in zip(fast, fast[1:])]
    assert min(steps) >= 1 and steps.count(1) >= 0.8 * len(steps), steps


async def test_revised_sampling_interval_is_the_one_honoured(opcua_mode, config):
    """-1 is the publishing interval, 0 or less than a tick the tick, a longer one itself."""
    async with EmulatorServer(config, port=0, time_scale=0) as srv, \
            serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0) as opc, Client(opc.url) as client:
        node, _ = await _time_nodes(client)

        class Quiet:
            def datachange_notification(self, node, val, data):
                pass

        sub = await client.create_subscription(500, Quiet())
        handle = await sub.subscribe_data_change(node, sampling_interval=0)
        revised = {}
        for requested in (-1.0, 0.0, 20.0, 1000.0):
            result = await sub.modify_monitored_item(handle, requested, new_queuesize=1)
            revised[requested] = result[0].RevisedSamplingInterval
        await sub.delete()
    assert revised == {-1.0: 500.0, 0.0: 1000 * TICK, 20.0: 1000 * TICK, 1000.0: 1000.0}


def test_revised_sampling_honours_every_tick_below_a_tick_and_the_publishing_interval_for_a_negative_request():
    tick = 1000 * TICK
    assert revised_sampling(0.0, 1000.0, tick) == (0.0, tick)
    assert revised_sampling(50.0, 1000.0, tick) == (0.0, tick)
    assert revised_sampling(-1.0, 1000.0, tick) == (1000.0, 1000.0)
    assert revised_sampling(float("nan"), 250.0, tick) == (250.0, 250.0)
    assert revised_sampling(2000.0, 1000.0, tick) == (2000.0, 2000.0)


def test_next_due_keeps_its_grid_through_late_ticks_and_restarts_after_falling_behind():
    assert next_due(10.0, 10.08, 1.0) == 11.0          # a late tick does not stretch the interval
    assert next_due(10.0, 11.5, 1.0) == 12.5           # a whole interval behind: from now
    assert next_due(10.0, 10.0, 0.0) == 10.0           # every tick


def test_first_samples_of_many_variables_spread_evenly_over_the_interval():
    ticks = [int(10 * (first_due(0.0, 1.0, index) - 0.0)) for index in range(1000)]
    per_tick = [ticks.count(k) for k in range(10)]
    assert all(80 <= n <= 120 for n in per_tick), per_tick
    assert first_due(5.0, 0.0, 7) == 5.0   # sampled every tick: due at once
