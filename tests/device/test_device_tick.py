"""The tick: drift-free schedule on a fake clock, overruns, jitter, writes applied at ticks, lifecycle."""

import asyncio
import logging
import math
import random

import numpy as np
import pytest

from valve_emulator.device.registers import N_REGISTERS, RegisterValueError, Scaling, address_of
from valve_emulator.device.tick import TICK_TASK_NAME, Device, JitterBuffer

pytestmark = pytest.mark.usefixtures("no_task_leak")


def _device(bank, **kw):
    scaling = Scaling.build(bank.n, has_controller=bank.has_controller)
    return Device(bank, scaling, units=range(1, bank.n + 1), **kw)


def _word(device, index, name):
    a = device.stride * index + 2 * address_of(name)
    return int.from_bytes(device.image[a:a + 2], "big")


def _stamp(clock, times):
    return lambda bank: times.append(clock())


@pytest.mark.parametrize("time_scale", [1.0, 10.0])
async def test_mean_period_is_exact_despite_jitter(fake_bank_cls, fake_clock, time_scale):
    bank = fake_bank_cls(1, dt=0.1)
    period = 0.1 / time_scale
    rng = random.Random(1)
    fake_clock.extra = lambda: rng.uniform(0.0, 0.4 * period)     # every wake-up is late by up to 0.4 P
    times = []
    bank.on_step.append(_stamp(fake_clock, times))
    async with _device(bank, time_scale=time_scale, clock=fake_clock, sleep=fake_clock.sleep) as dev:
        await dev.wait_for_tick(1000)
    mean = (times[-1] - times[0]) / (len(times) - 1)
    assert mean == pytest.approx(period, rel=1e-3)
    assert dev.overruns == 0
    assert 0.0 < dev.jitter.p50 < dev.jitter.p99 <= 0.4 * period
    assert bank.t == pytest.approx(0.1 * dev.ticks)   # simulated time = ticks · dt whatever the scale


async def test_slow_step_counts_an_overrun_and_reanchors_without_a_burst(fake_bank_cls, fake_clock):
    bank = fake_bank_cls(1, dt=0.1)
    times = []

    def slow(b):
        times.append(fake_clock())
        if b.k == 10:
            fake_clock.now += 0.25                      # this step takes 2.5 periods

    bank.on_step.append(slow)
    t0 = fake_clock()
    async with _device(bank, clock=fake_clock, sleep=fake_clock.sleep) as dev:
        await dev.wait_for_tick(20)
    assert dev.overruns == 1
    assert dev.jitter.total == 20
    grid = (np.array(times) - t0) / 0.1
    assert grid[:11] == pytest.approx(np.arange(1, 12))      # on schedule up to the slow step
    assert grid[11] == pytest.approx(13.5)                   # the late tick runs once, at once
    assert grid[12:] == pytest.approx(np.arange(14, 22))     # then back on the grid: tick 12 skipped
    assert np.all(np.diff(grid) >= 0.5 - 1e-9)               # no burst of catch-up ticks


async def test_overrun_counter_reaches_the_registers(fake_bank_cls, fake_clock):
    bank = fake_bank_cls(1)
    bank.on_step.append(lambda b: setattr(fake_clock, "now", fake_clock.now + (0.35 if b.k in (3, 7) else 0)))
    async with _device(bank, clock=fake_clock, sleep=fake_clock.sleep) as dev:
        await dev.wait_for_tick(12)
    assert dev.overruns == 2
    a_over, a_tick = 2 * address_of("overruns"), 2 * address_of("tick")
    assert int.from_bytes(dev.image[a_over:a_over + 4], "big") == 2          # uint32, ABCD
    assert int.from_bytes(dev.image[a_tick:a_tick + 4], "big") == dev.ticks


def test_jitter_buffer_keeps_the_last_values():
    buf = JitterBuffer(4)
    assert math.isnan(buf.p50) and len(buf) == 0
    for x in range(1, 11):
        buf.add(float(x))
    assert len(buf) == 4 and buf.total == 10
    assert list(buf.values()) == [7.0, 8.0, 9.0, 10.0]
    assert buf.p50 == 8.5 and buf.percentile(100) == 10.0
    with pytest.raises(ValueError, match="size"):
        JitterBuffer(0)


async def test_frozen_time_steps_only_on_advance(fake_bank_cls):
    bank = fake_bank_cls(2)
    async with _device(bank, time_scale=0) as dev:
        assert dev.ticks == 0 and not dev.running
        waiter = asyncio.create_task(dev.wait_for_tick(3))
        await asyncio.sleep(0)
        assert not waiter.done()
        assert dev.advance(3) == 3 and bank.k == 3
        assert await waiter == 3
    fast = _device(fake_bank_cls(1), time_scale=math.inf)
    with pytest.raises(RuntimeError, match="time_scale=0"):
        fast.advance()


async def test_write_shows_at_once_and_reaches_the_bank_at_the_next_tick(fake_bank_cls):
    bank = fake_bank_cls(2)
    dev = _device(bank, time_scale=0)
    dev.write(1, address_of("op_pct"), [2500])
    assert _word(dev, 1, "op_pct") == 2500 and _word(dev, 1, "op_ma") == 8000
    assert bank.op_external[1] == 50.0                   # physics untouched until the tick
    assert _word(dev, 0, "op_pct") == 5000               # other units untouched
    dev.advance(1)
    assert bank.op_external[1] == 25.0 and bank.mv[1] == 25.0
    assert _word(dev, 1, "mv_pct") == 2500
    dev.advance(5)
    assert bank.op_external[1] == 25.0                   # OP held between writes


async def test_refused_write_changes_nothing(fake_bank_cls):
    bank = fake_bank_cls(1)
    dev = _device(bank, time_scale=0)
    image = bytes(dev.image)
    with pytest.raises(RegisterValueError, match="register op_ma"):
        dev.write(0, address_of("op_pct"), [1000, 3])     # op_pct fine, op_ma 3 µA out of range
    assert bytes(dev.image) == image
    dev.advance(1)
    assert bank.op_external[0] == 50.0


async def test_pending_writes_apply_in_arrival_order(fake_bank_cls):
    bank = fake_bank_cls(1, has_controller=True)
    dev = _device(bank, time_scale=0)
    dev.write(0, address_of("mode"), [0])                 # manual first: then OP becomes writable
    assert dev.effective_auto(0) is False and bool(bank.auto[0])
    dev.write(0, address_of("op_pct"), [3000])
    dev.write(0, address_of("kc"), [1500])
    dev.write(0, address_of("mode"), [1])                 # back to auto, last
    dev.advance(1)
    assert [c[0] for c in bank.calls] == ["manual_op", "tuning", "auto"]
    assert bank.calls[0] == ("manual_op", 0, 30.0) and bank.kc[0] == 1.5 and bank.auto[0]


async def test_failing_step_is_reported_and_wakes_waiters(fake_bank_cls, caplog):
    bank = fake_bank_cls(1)

    def boom(b):
        if b.k == 2:
            raise FloatingPointError("plant blew up")

    bank.on_step.append(boom)
    async with _device(bank, time_scale=math.inf) as dev:
        with pytest.raises(RuntimeError, match="tick task has failed"):
            await dev.wait_for_tick(10)
    assert isinstance(dev.error, FloatingPointError) and dev.ticks == 2
    assert any("plant blew up" in r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)


async def test_tick_task_is_named_and_gone_after_exit(fake_bank_cls):
    async with _device(fake_bank_cls(1), time_scale=math.inf) as dev:
        await dev.wait_for_tick(5)
        assert TICK_TASK_NAME in {t.get_name() for t in asyncio.all_tasks()}
    assert not dev.running
    assert TICK_TASK_NAME not in {t.get_name() for t in asyncio.all_tasks() if not t.done()}


def test_constructor_rejects_inconsistent_arguments(fake_bank_cls):
    bank = fake_bank_cls(2)
    with pytest.raises(ValueError, match="time_scale"):
        _device(bank, time_scale=-1)
    with pytest.raises(ValueError, match="same number of loops"):
        Device(bank, Scaling.build(3), units=[1, 2])
    with pytest.raises(ValueError, match="unique"):
        Device(bank, Scaling.build(2), units=[1, 1])
    assert len(_device(bank).image) == 2 * 2 * N_REGISTERS


async def test_real_clock_never_ticks_early(fake_bank_cls):
    bank = fake_bank_cls(1, dt=0.1)
    async with _device(bank, time_scale=100.0) as dev:              # period 1 ms of real time
        start = asyncio.get_running_loop().time()
        await dev.wait_for_tick(30)
        elapsed = asyncio.get_running_loop().time() - start
    assert elapsed >= 29 * dev.period                              # absolute deadlines: never ahead
    assert dev.jitter.total >= 30 and dev.jitter.p50 >= 0.0


def test_advance_in_batches_equals_tick_by_tick_to_the_bit():
    """Quiet ticks run as compiled ``bank.run`` batches; a write, a ramp or a callback makes ticks run one by one.
    Either way the state and the register image are those of as many single ticks."""
    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.malfunctions import parse_malfunction

    cfg = server_from_mapping({"device": {"tick": 0.1}, "loops": [
        {"unit": u, "plant": {"num": [3.0], "den": [10.0, 1.0], "noise": 0.05, "delay": 2.0},
         "controller": {"kc": 0.5, "ti": 10.0, "mode": "auto", "sp_steps": [[30.0, 1.0]]}} for u in (1, 2)]})
    batched, single = (Device.from_config(cfg, time_scale=0) for _ in range(2))
    for dev, run in ((batched, batched.advance), (single, lambda k: [single.tick() for _ in range(k)])):
        run(500)
        dev.write(1, address_of("sp"), [2000])
        dev.inject(parse_malfunction({"unit": 2, "kind": "load", "flow": 4.0, "ramp": 5.0},
                                     unit_index=dev.unit_index, scaling=dev.scaling))
        run(333)
    assert batched.ticks == single.ticks == 833 and batched.image == single.image
    a, b = batched.bank.state(), single.bank.state()
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            assert np.array_equal(a[key], b[key], equal_nan=True), key


def test_a_tick_callback_reads_each_ticks_image_while_an_advance_runs_them():
    """Ticks run one by one encode the image once, after the last; a callback between them sees its own tick."""
    from valve_emulator.config import server_from_mapping

    cfg = server_from_mapping({"device": {"tick": 0.1},
                               "loops": [{"unit": 1, "plant": {"num": [1.0], "den": [2.0, 1.0]}}]})
    dev = Device.from_config(cfg, time_scale=0)
    at = 2 * address_of("tick")
    seen = []
    dev.on_tick.append(lambda d: seen.append(int.from_bytes(d.image[at:at + 4], "big")))
    dev.advance(5)
    assert seen == [1, 2, 3, 4, 5]
    dev.on_tick.clear()
    dev.write(0, address_of("op_pct"), [2500])   # a pending write: the first tick runs alone, then a batch
    dev.advance(4)
    assert int.from_bytes(dev.image[at:at + 4], "big") == 9 and _word(dev, 0, "op_pct") == 2500
