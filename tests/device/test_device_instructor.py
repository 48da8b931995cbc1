"""The instructor's controls on the device core: snapshots (exact restore, files), run/freeze, speed,
malfunctions with ramps."""

import asyncio
import math
import time

import numpy as np
import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.malfunctions import MalfunctionError, parse_malfunction
from valve_emulator.device.registers import address_of
from valve_emulator.device.snapshots import BacktrackRing, SnapshotError, SnapshotNotFound, SnapshotStore
from valve_emulator.device.tick import Device

pytestmark = pytest.mark.usefixtures("no_task_leak")

PLANT = {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0, "pv_range": [-10.0, 10.0], "noise": 0.05,
         "disturbance": {"type": "random_walk", "std": 0.3}}


def _config(tick=0.1, n_extra=0):
    loops = [
        {"unit": 1, "valve": {"model": "kano", "S": 5.0, "J": 2.0}, "plant": PLANT,
         "controller": {"kc": 0.2, "ti": 10.0, "sp": 1.0}, "simulation": {"seed": 7}},
        {"unit": 2, "valve": {"model": "kano", "S": 3.0, "J": 1.0}, "plant": PLANT, "simulation": {"seed": 3}},
    ]
    loops += [{"unit": 3 + k, "valve": {"model": "kano", "S": 1.0, "J": 0.5}, "plant": PLANT} for k in range(n_extra)]
    return server_from_mapping({"device": {"tick": tick, "instructor_writes": True}, "loops": loops})


def _trace(device, ticks):
    """``ticks`` ticks of every loop: time, PV, OP, MV, the valve's state row and the whole register image."""
    rows = []
    for _ in range(ticks):
        device.advance(1)
        b = device.bank
        rows.append((b.sample_time, b.pv.copy(), b.op.copy(), b.mv, b._vstate.copy(), bytes(device.image)))
    return rows


def _assert_same(a, b):
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        assert ra[0] == rb[0]
        for xa, xb in zip(ra[1:5], rb[1:5]):
            np.testing.assert_array_equal(xa, xb)
        assert ra[5] == rb[5]


def _stir(device):
    """Something happening: an OP ramp on the open loop, an SP step on the controlled one."""
    for k in range(60):
        device.write(1, address_of("op_pct"), [5000 + 40 * k])
        if k == 20:
            device.write(0, address_of("sp"), [5500])
        device.advance(1)


def test_restore_gives_the_saved_state_exactly():
    device = Device.from_config(_config(), time_scale=0)
    _stir(device)
    snap = device.snapshot("lesson1")
    after_save = _trace(device, 100)
    device.restore(snap)
    assert device.ticks == snap.ticks and device.bank.sample_time == snap.time
    after_restore = _trace(device, 100)
    _assert_same(after_save, after_restore)
    # the 100 ticks actually moved something (not a trivially frozen loop)
    assert np.ptp([r[1][0] for r in after_save]) > 0.05


def test_snapshots_persist_to_files_and_survive_a_restart(tmp_path):
    device = Device.from_config(_config(), time_scale=0)
    _stir(device)
    inject = parse_malfunction({"unit": 1, "kind": "load", "flow": 8.0, "ramp": 5.0},
                               unit_index=device.unit_index, scaling=device.scaling)
    device.inject(inject)
    device.advance(10)   # mid-ramp: the running ramp is part of the state
    SnapshotStore(tmp_path).put(device.snapshot("mid_ramp"))
    expected = _trace(device, 100)

    restarted = Device.from_config(_config(), time_scale=0)   # a new process: fresh bank, store read from disk
    store = SnapshotStore(tmp_path)
    assert [s.name for s in store] == ["mid_ramp"]
    restarted.restore(store.get("mid_ramp"))
    _assert_same(expected, _trace(restarted, 100))


def test_snapshot_of_another_configuration_is_refused_and_changes_nothing(tmp_path):
    other = Device.from_config(_config(n_extra=1), time_scale=0)
    device = Device.from_config(_config(), time_scale=0)
    device.advance(5)
    before = bytes(device.image)
    with pytest.raises(SnapshotError, match="another configuration"):
        device.restore(other.snapshot("x"))
    assert bytes(device.image) == before
    store = SnapshotStore(tmp_path)
    with pytest.raises(SnapshotNotFound, match="no snapshot named 'nope'"):
        store.get("nope")
    with pytest.raises(SnapshotError, match="field 'name'"):
        store.put(device.snapshot("../escape"))
    assert list(tmp_path.iterdir()) == []


def test_backtrack_ring_keeps_the_last_points_and_forgets_the_future():
    device = Device.from_config(_config(), time_scale=0)
    ring = BacktrackRing(interval=1.0, size=3)

    def take(dev):
        if ring.due(dev.bank.sample_time):
            ring.add(dev.snapshot(f"bt-{dev.bank.sample_time:.1f}"))

    device.on_tick.append(take)
    device.advance(55)   # sample times 0.0 .. 5.4: points at 0, 1, ..., 5; the last three kept
    assert [s.time for s in ring] == pytest.approx([3.0, 4.0, 5.0])
    device.restore(ring.get("bt-4.0"))
    ring.reset(device.bank.sample_time)
    assert [s.time for s in ring] == pytest.approx([3.0, 4.0])


def _tick_words(device):
    """The two words of the Modbus ``tick`` register of the first loop."""
    start = int(device.offsets[0]) + 2 * address_of("tick")
    return bytes(device.image[start:start + 4])


async def test_freeze_holds_simulated_time_and_the_tick_register():
    device = Device.from_config(_config(tick=0.01), time_scale=1.0)
    async with device:
        await device.wait_for_tick(5)
        await device.freeze()
        t, tick_words = device.bank.sample_time, _tick_words(device)
        assert tick_words != b"\0\0\0\0"
        await asyncio.sleep(0.25)   # 25 ticks would have run
        assert device.bank.sample_time == t
        assert _tick_words(device) == tick_words
        ticks = device.ticks
        await device.resume()
        await device.wait_for_tick(ticks + 5)
        assert device.bank.sample_time > t


@pytest.mark.realtime   # a wall-clock rate: it needs the machine alone, as .ci/run's realtime phase gives it
async def test_speed_five_runs_five_times_faster_within_ten_percent():
    device = Device.from_config(_config(tick=0.05), time_scale=1.0)
    async with device:
        await device.wait_for_tick(2)
        await device.set_time_scale(5.0)
        k0, w0 = device.ticks, time.monotonic()
        await asyncio.sleep(1.0)
        k1, w1 = device.ticks, time.monotonic()
    rate = (k1 - k0) * 0.05 / (w1 - w0)   # simulated s per wall s
    assert rate == pytest.approx(5.0, rel=0.10)


async def test_set_time_scale_refuses_zero_and_nan():
    device = Device.from_config(_config(), time_scale=1.0)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="time_scale"):
            await device.set_time_scale(bad)
    assert device.time_scale == 1.0


# --- malfunctions ----------------------------------------------------------------------------------------

def _parse(device, body):
    return parse_malfunction(body, unit_index=device.unit_index, scaling=device.scaling)


@pytest.mark.parametrize(("quantity", "body", "read"), [
    ("S", {"kind": "stiction", "S": 9.0, "J": 4.0}, lambda b: b.S[1]),
    ("load", {"kind": "load", "flow": -6.0}, lambda b: b.load[1]),
    ("bias", {"kind": "sensor_drift", "bias": 1.5}, lambda b: b.pv_bias[1]),
])
def test_a_ramped_malfunction_reaches_its_value_at_the_ramps_end(quantity, body, read):
    device = Device.from_config(_config(), time_scale=0)
    device.advance(3)
    start = read(device.bank)
    device.inject(_parse(device, {"unit": 2, **body, "ramp": 4.0}))   # 40 ticks of 0.1 s
    target = next(v for k, v in body.items() if k != "kind")
    device.advance(20)   # samples t0 .. t0 + 1.9 s
    assert read(device.bank) == pytest.approx(start + (target - start) * 19 / 40, abs=1e-9)
    device.advance(20)   # up to t0 + 3.9 s: not there yet
    assert read(device.bank) != target
    device.advance(1)    # the tick that computes sample t0 + 4 s
    assert read(device.bank) == target
    device.advance(5)
    assert read(device.bank) == target


def test_immediate_malfunctions_and_clear():
    device = Device.from_config(_config(), time_scale=0)
    device.advance(3)
    device.inject(_parse(device, {"unit": 2, "kind": "seize"}))
    assert device.bank.frozen[1]
    device.inject(_parse(device, {"unit": 2, "kind": "sensor_stuck", "value": 4.25}))
    device.write(1, address_of("op_pct"), [9000])
    device.advance(200)
    assert device.bank.pv[1] == 4.25   # the transmitter shows 4.25 whatever the plant does
    device.inject(_parse(device, {"unit": 2, "kind": "clear"}))
    assert not device.bank.frozen[1] and math.isnan(device.bank.pv_stuck[1])
    device.advance(1)
    assert device.bank.pv[1] != 4.25


@pytest.mark.parametrize(("body", "field"), [
    ({"unit": 2, "kind": "leak"}, "kind"),
    ({"unit": 9, "kind": "seize"}, "unit"),
    ({"unit": 2, "kind": "stiction", "S": 150.0}, "S"),
    ({"unit": 2, "kind": "stiction", "S": "big"}, "S"),
    ({"unit": 2, "kind": "load", "flow": 150.0}, "flow"),
    ({"unit": 2, "kind": "load"}, "flow"),
    ({"unit": 2, "kind": "seize", "ramp": 5}, "ramp"),
    ({"unit": 2, "kind": "noise", "std": 1.0, "ramp": -1}, "ramp"),
    ({"unit": 2, "kind": "noise", "std": 1.0, "colour": "pink"}, "colour"),
    ([1, 2], "body"),
])
def test_bad_malfunction_names_the_field_and_changes_nothing(body, field):
    device = Device.from_config(_config(), time_scale=0)
    before = bytes(device.image)
    with pytest.raises(MalfunctionError) as info:
        _parse(device, body)
    assert info.value.field == field
    assert field in str(info.value)
    assert bytes(device.image) == before
