"""The testing kit's Emulator: a real server on a free port, a clock the test owns, state, faults, traffic."""

from __future__ import annotations

import asyncio
import gc
import math
import os
import socket
import threading

import numpy as np
import pytest

from valve_emulator.config.schema import ConfigError
from valve_emulator.device.malfunctions import MalfunctionError
from valve_emulator.device.registers import RegisterAccessError, RegisterValueError, Status
from valve_emulator.testing import Emulator

#: Two loops, the first with an internal PI in auto and measurement noise (so determinism means something).
TWO_LOOPS = {
    "device": {"tick": 0.1},
    "loops": [
        {"unit": 1, "plant": {"num": [3.0], "den": [10.0, 1.0], "noise": 0.05, "pv_range": [0.0, 10.0]},
         "valve": {"S": 5.0, "J": 2.0}, "controller": {"kc": 0.5, "ti": 10.0, "mode": "auto", "sp": 4.0}},
        {"unit": 7, "plant": {"num": [2.0], "den": [5.0, 1.0]}},
    ],
}


def _same(a, b) -> bool:
    """Equal to the bit: nested dicts, lists and arrays of the loop bank's state (NaN equals NaN)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray | float):
        return np.array_equal(a, b, equal_nan=True)
    return a == b


def _refused(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    except ConnectionRefusedError:
        return True
    return False


def test_manual_clock_runs_exactly_the_ticks_asked_and_none_by_itself():
    with Emulator() as emu:
        with emu.client() as c:
            first = c.read_holding_registers(14, count=2, device_id=1).registers
            threading.Event().wait(0.2)                                 # wall time passes, simulated time does not
            assert c.read_holding_registers(14, count=2, device_id=1).registers == first == [0, 0]
            assert emu.advance(10.0) == 100 and emu.ticks == 100
            assert c.read_holding_registers(14, count=2, device_id=1).registers == [0, 100]
        assert emu.advance(0.26) == 103                                  # round(2.6) ticks
        assert emu.time == pytest.approx(102 * 0.1)                      # the sample the registers show
        assert emu.state(0)["tick"] == 103
        with pytest.raises(ValueError, match="seconds"):
            emu.advance(-1.0)


def test_same_inputs_give_the_same_state_bit_for_bit():
    def run() -> tuple[dict, dict]:
        with Emulator(TWO_LOOPS) as emu:
            emu.advance(30.0)
            emu.set(0, sp=6.0)
            emu.inject("load", 0, flow=5.0, ramp=20.0)
            emu.advance(61.3)
            return emu.state(0), emu.snapshot().bank

    (s1, b1), (s2, b2) = run(), run()
    assert s1 == s2
    assert _same(b1, b2)
    assert s1["sp"] == pytest.approx(6.0) and s1["load"] == pytest.approx(5.0)


def test_state_set_and_the_register_map_checks():
    with Emulator(TWO_LOOPS) as emu:
        assert emu.units == (1, 7)
        s = emu.state(0)
        assert s["mode"] is True and s["sp"] == pytest.approx(4.0) and s["ti"] == pytest.approx(10.0)
        assert "kc" not in emu.state(1) and emu.state(-1) == emu.state(1)   # loop 7 has no controller
        with pytest.raises(RegisterAccessError, match="op_pct.*manual"):
            emu.set(0, op_pct=30.0)                                       # OP is the controller's in auto
        emu.set(0, mode=False, op_pct=30.0)
        emu.advance(60.0)
        s = emu.state(0)
        assert s["op_pct"] == pytest.approx(30.0) and s["op_f32"] == pytest.approx(30.0)
        assert s["op_ma"] == pytest.approx(4 + 16 * 0.30)
        with pytest.raises(RegisterValueError, match="sp"):
            emu.set(0, sp=12.0)                                           # outside pv_range 0..10
        with pytest.raises(RegisterAccessError, match="read-only"):
            emu.set(0, pv=1.0)
        with pytest.raises(IndexError, match="loops 0..1"):
            emu.state(2)


def test_malfunctions_ramp_in_simulated_time():
    with Emulator() as emu:
        emu.inject("stiction", S=9.0, J=4.0, ramp=10.0)
        emu.advance(5.0)
        halfway = emu.state(0)["S"]
        emu.advance(6.0)
        assert 5.0 < halfway < 9.0 and emu.state(0)["S"] == pytest.approx(9.0)
        emu.inject("seize")
        emu.advance(0.1)
        assert emu.state(0)["status"] & Status.SEIZED
        with pytest.raises(MalfunctionError, match="kind"):
            emu.inject("melt")


def test_restore_replays_the_same_future():
    with Emulator(TWO_LOOPS) as emu:
        emu.advance(20.0)
        snap = emu.snapshot()
        emu.advance(40.0)
        later = emu.state(0)
        emu.restore(snap)
        assert emu.ticks == 200
        emu.advance(40.0)
        assert emu.state(0) == later


def test_traffic_records_every_request_with_its_client_and_answer():
    with Emulator() as emu, emu.client() as c:
        c.read_holding_registers(0, count=5, device_id=1)
        c.write_register(0, 2500, device_id=1)
        c.write_register(4, 1, device_id=1)                               # pv is read-only: 0x02
        c.read_input_registers(24, count=2, device_id=9)                  # no unit 9: 0x0B
        host, port = c.socket.getsockname()[:2]
        local = f"{host}:{port}"
        rows = list(emu.traffic)
    assert [(r.function, r.unit, r.address, r.count, r.exception) for r in rows] == [
        (3, 1, 0, 5, None), (6, 1, 0, 1, None), (6, 1, 4, 1, 2), (4, 9, 24, 2, 11)]
    assert {r.client for r in rows} == {local} and [r.is_write for r in rows] == [False, True, True, False]
    assert all(r.time == 0.0 and r.answered for r in rows)


def test_real_clock_advance_waits_for_the_ticks():
    with Emulator(clock="real", time_scale=200.0) as emu:
        start = emu.ticks
        assert emu.advance(2.0) >= start + 20


def _open_fds() -> set[str]:
    """The file descriptors this process has open (sockets, the event loop's selector and self-pipe, ...), after
    a garbage collection (so that objects earlier tests dropped do not close theirs in between)."""
    gc.collect()
    return {f"{fd}->{os.readlink(f'/proc/self/fd/{fd}')}" for fd in os.listdir("/proc/self/fd")
            if os.path.exists(f"/proc/self/fd/{fd}")}


def test_sync_flavour_leaves_no_thread_socket_or_open_client():
    fds = _open_fds()
    with Emulator() as emu:
        port = emu.port
        client = emu.client()
        client.connect()
        thread = emu._thread
        assert len(_open_fds() - fds) >= 4      # listener, both ends of the connection, the loop's selector
    assert not thread.is_alive() and not client.connected and _refused(port)
    assert not [t for t in threading.enumerate() if t.name == "valve-emulator-testing"]
    assert _open_fds() <= fds


async def test_async_flavour_leaves_no_task_or_socket():
    before, fds = asyncio.all_tasks(), _open_fds()
    async with Emulator() as emu:
        port = emu.port
        async with emu.client() as c:
            await emu.advance(1.0)
            assert (await c.read_holding_registers(14, count=2, device_id=1)).registers == [0, 10]
    await asyncio.sleep(0)
    assert asyncio.all_tasks() == before and _refused(port) and _open_fds() <= fds


async def test_requests_are_answered_while_a_long_advance_runs():
    async with Emulator() as emu, emu.client() as c:
        hour = asyncio.create_task(emu.advance(3600.0))
        await asyncio.sleep(0)
        reply = await c.read_holding_registers(14, count=2, device_id=1)
        seen = reply.registers[1] + (reply.registers[0] << 16)
        assert not hour.done() or seen < 36000   # answered from between two ticks, not after the hour
        assert await hour == 36000


def test_configs_from_a_file_a_mapping_or_bad_input(tmp_path):
    path = tmp_path / "dev.yaml"
    path.write_text("device: {tick: 0.5}\nloops:\n  - unit: 3\n    plant: {num: [1.0], den: [2.0, 1.0]}\n")
    emu = Emulator(path)
    assert emu.units == (3,) and emu.dt == 0.5
    with pytest.raises(ConfigError, match="tick"):
        Emulator({"device": {"tick": -1}, "loops": [{"unit": 1}]})
    with pytest.raises(ConfigError, match="lockstep"):
        Emulator({"device": {"lockstep": "yes"}, "loops": [{"unit": 1, "plant": {"num": [1.0], "den": [1.0, 1.0]}}]})
    with pytest.raises(ValueError, match="clock"):
        Emulator(clock="fast")
    with pytest.raises(ValueError, match="lockstep"):
        Emulator({"device": {"lockstep": True}, "loops": [{"unit": 1, "plant": {"num": [1.0], "den": [1.0, 1.0]}}]},
                 clock="real")
    with pytest.raises(RuntimeError, match="not running"):
        emu.state(0)
    assert math.isfinite(Emulator().dt)
