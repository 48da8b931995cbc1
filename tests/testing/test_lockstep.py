"""Lockstep: the ``step`` register and ``POST /api/step`` run ticks only when a client asks, deterministically."""

from __future__ import annotations

import time

import pytest
from aiohttp.test_utils import TestClient, TestServer
from pymodbus.client import ModbusTcpClient

from valve_emulator.device.registers import STEP_ADDRESS
from valve_emulator.device.roles import UNAUTHENTICATED
from valve_emulator.device.server import EmulatorServer
from valve_emulator.station.app import make_app
from valve_emulator.station.core import Station
from valve_emulator.testing import Emulator, load_config

F32 = ModbusTcpClient.DATATYPE.FLOAT32
U32 = ModbusTcpClient.DATATYPE.UINT32


def _tick(c: ModbusTcpClient) -> int:
    return c.convert_from_registers(c.read_holding_registers(14, count=2, device_id=1).registers, U32)


def test_a_step_write_is_answered_after_its_ticks_have_run():
    with Emulator() as emu, emu.client() as c:
        assert not c.write_register(STEP_ADDRESS, 25, device_id=1).isError()
        assert _tick(c) == 25 and emu.ticks == 25
        assert c.read_holding_registers(STEP_ADDRESS, count=1, device_id=1).registers == [0]
        assert not c.write_register(STEP_ADDRESS, 0, device_id=1).isError() and emu.ticks == 25
        wide = c.write_registers(STEP_ADDRESS, [1, 1], device_id=1)          # step is written alone
        assert wide.isError() and wide.exception_code == 2 and emu.ticks == 25
        step = [r for r in emu.traffic if r.address == STEP_ADDRESS and r.function == 6]
        assert [r.time for r in step] == [0.0, pytest.approx(2.4)]         # arrival, before the ticks


def test_fc23_writes_step_then_reads_what_the_ticks_left():
    with Emulator() as emu, emu.client() as c:
        tick = c.readwrite_registers(read_address=14, read_count=2, write_address=STEP_ADDRESS, values=[7],
                                     device_id=1)
        assert c.convert_from_registers(tick.registers, U32) == 7 == emu.ticks


def test_a_step_write_is_refused_while_the_device_runs_its_own_clock():
    with Emulator(clock="real", time_scale=1.0) as emu, emu.client() as c:
        refused = c.write_register(STEP_ADDRESS, 10, device_id=1)
        assert refused.isError() and refused.exception_code == 2


def _pi_client(port: int, steps: int) -> list[float]:
    """A scripted PLC: read PV, PI, write OP, write step 5; the PV it read after each step."""
    pvs, op, integral = [], 50.0, 0.0
    with ModbusTcpClient("127.0.0.1", port=port, timeout=5) as c:
        for _ in range(steps):
            pv = c.convert_from_registers(c.read_holding_registers(24, count=2, device_id=1).registers, F32)
            integral += 0.5 * (2.0 - pv) / 20.0
            op = min(max(50.0 + 0.5 * (2.0 - pv) + integral, 0.0), 100.0)
            c.write_register(0, round(op * 100), device_id=1)
            c.write_register(STEP_ADDRESS, 5, device_id=1)
            pvs.append(pv)
    return pvs


def test_serve_lockstep_twice_gives_byte_identical_recordings_and_no_tick_unasked(serve, tmp_path):
    recordings = []
    for run in range(2):
        path = tmp_path / f"run{run}.csv"
        with serve("--lockstep", "--record", str(path)) as port:
            assert "lockstep" in serve.banner
            with ModbusTcpClient("127.0.0.1", port=port, timeout=5) as c:
                first = _tick(c)
                time.sleep(0.3)                                             # the client waits; the clock does not
                assert _tick(c) == first == 0
            _pi_client(port, 120)
        recordings.append(path.read_bytes())
    assert recordings[0] == recordings[1]
    assert recordings[0].count(b"\n") == 1 + 600                            # header + one row per tick


async def test_post_api_step_runs_ticks_in_lockstep_only():
    made = []
    try:
        for lockstep in (True, False):
            cfg = load_config({"device": {"tick": 0.1, "lockstep": lockstep},
                               "loops": [{"unit": 1, "plant": {"num": [1.0], "den": [5.0, 1.0]}}]})
            srv = EmulatorServer(cfg, time_scale=1.0)
            await srv.start()
            client = TestClient(TestServer(make_app(Station(srv.device)), host="127.0.0.1", port=0))
            await client.start_server()
            made.append((srv, client))
        (lock_srv, lock), (_, free) = made
        answer = await lock.post("/api/step", json={"ticks": 7})
        assert answer.status == 200 and (await answer.json())["ticks"] == 7 == lock_srv.device.ticks
        assert (await (await lock.post("/api/step", json={})).json())["ticks"] == 8
        bad = await lock.post("/api/step", json={"ticks": 1.5})
        assert bad.status == 400 and (await bad.json())["field"] == "ticks" and lock_srv.device.ticks == 8
        assert (await free.post("/api/step", json={"ticks": 1})).status == 409
    finally:
        for srv, client in made:
            await client.close()
            await srv.stop()


def test_valve_emulator_registers_lists_step(capsys):
    from valve_emulator.cli import main

    assert main(["registers", "--format", "csv"]) == 0
    assert "step,holding,65296,465297,uint16,1,ticks to run (lockstep),RW" in capsys.readouterr().out


async def test_a_broadcast_step_runs_its_ticks_once_and_other_broadcasts_reach_every_unit():
    cfg = load_config({"device": {"tick": 0.1, "lockstep": True}, "loops": [
        {"unit": u, "plant": {"num": [1.0], "den": [5.0, 1.0]}} for u in (1, 2, 3)]})
    srv = EmulatorServer(cfg)
    srv.broadcast(bytes((6,)) + STEP_ADDRESS.to_bytes(2, "big") + (5).to_bytes(2, "big"), UNAUTHENTICATED)
    assert srv.device.ticks == 5
    srv.broadcast(bytes((6, 0, 0)) + (2500).to_bytes(2, "big"), UNAUTHENTICATED)       # op_pct 25 % on every unit
    srv.device.advance(1)
    assert list(srv.device.bank.op_external) == [25.0, 25.0, 25.0]
