"""The emulator over Modbus with the real LoopBank: stiction seen by a client, controller registers."""

import math

import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import N_REGISTERS, Status, address_of
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

S, J = 5.0, 2.0
CONCENTRATION = {"plant": {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0, "pv_range": [-10.0, 10.0]}}


def _config(**device):
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [
        {"unit": 1, "valve": {"model": "kano", "S": S, "J": J}, **CONCENTRATION},
        {"unit": 2, "valve": {"model": "kano", "S": S, "J": J}, **CONCENTRATION,
         "controller": {"kc": 0.2, "ti": 10.0, "sp": 0.0}},
    ]})


async def _regs(client, unit):
    rr = await client.read_holding_registers(0, count=N_REGISTERS, device_id=unit)
    assert not rr.isError(), rr
    return rr.registers


async def _set_op_and_settle(srv, client, op_pct, unit=1, ticks=10):
    """Write OP (% travel), let the valve come to rest (kano rest_time 0.5 s = 5 ticks), return registers."""
    rr = await client.write_register(address_of("op_pct"), round(op_pct * 100), device_id=unit)
    assert not rr.isError(), rr
    srv.device.advance(ticks)
    return await _regs(client, unit)


async def test_stiction_seen_through_modbus(client_for):
    """S = 5, J = 2 (kano): after a reversal a 2 % step leaves MV where it is; a further 4 % step breaks
    the valve free. It then slips by J plus the 1 % that OP has gone beyond the band S (6 % − 5 %), landing
    (S − J)/2 above OP, as the 2005 model says (MV = OP − d·(S − J)/2)."""
    async with EmulatorServer(_config(), time_scale=0) as srv:
        client = await client_for(srv)
        up = await _set_op_and_settle(srv, client, 60.0)                  # moving up: MV lags OP by 1.5
        assert up[address_of("mv_pct")] == round((60.0 - (S - J) / 2) * 100)
        mv0 = up[address_of("mv_pct")]
        small = await _set_op_and_settle(srv, client, 58.0)                # reversal, 2 % < S
        assert small[address_of("mv_pct")] == mv0
        assert small[address_of("status")] & Status.STUCK
        big = await _set_op_and_settle(srv, client, 54.0)                  # 6 % in total > S
        jump = (mv0 - big[address_of("mv_pct")]) / 100
        assert jump == pytest.approx(J + (6.0 - S))
        assert big[address_of("mv_pct")] == round((54.0 + (S - J) / 2) * 100)
        assert big[address_of("op_ma")] == round((4 + 0.16 * 54.0) * 1000)


async def test_instructor_changes_stiction_of_a_running_valve(client_for):
    async with EmulatorServer(_config(instructor_writes=True), time_scale=0) as srv:
        client = await client_for(srv)
        rr = await client.write_registers(address_of("S"), [0, 0], device_id=1)     # a healthy valve
        assert not rr.isError()
        regs = await _set_op_and_settle(srv, client, 55.0)
        assert srv.device.bank.S[0] == 0.0 and regs[address_of("S")] == 0
        assert regs[address_of("mv_pct")] == 5500                         # no stiction: MV = OP
        assert srv.device.bank.S[1] == S                                  # the other loop untouched


async def test_controller_registers_with_the_real_bank(client_for):
    async with EmulatorServer(_config(), time_scale=0) as srv:
        client = await client_for(srv)
        regs = await _regs(client, 2)
        assert regs[address_of("mode")] == 1 and regs[address_of("kc")] == 200 and regs[address_of("ti")] == 100
        assert regs[address_of("status")] & Status.CONTROLLER and regs[address_of("status")] & Status.AUTO
        assert regs[address_of("sp")] == 5000                             # sp 0 in range -10..10
        assert not (await client.write_register(address_of("sp"), 7500, device_id=2)).isError()   # sp 5
        assert not (await client.write_register(address_of("ti"), 0, device_id=2)).isError()      # P only
        srv.device.advance(1)
        assert srv.device.bank.sp[1] == pytest.approx(5.0) and math.isinf(srv.device.bank.ti[1])
        regs = await _regs(client, 2)
        assert regs[address_of("sp")] == 7500 and regs[address_of("ti")] == 0
        srv.device.advance(100)                                          # the PI reacts: OP rises
        assert (await _regs(client, 2))[address_of("op_pct")] > 5000


async def test_manual_op_must_respect_controller_limits(client_for):
    cfg = server_from_mapping({"device": {"tick": 0.1}, "loops": [
        {"unit": 1, **CONCENTRATION, "controller": {"kc": 0.2, "ti": 10.0, "op_limits": [10.0, 90.0],
                                                    "mode": "manual"}}]})
    async with EmulatorServer(cfg, time_scale=0) as srv:
        client = await client_for(srv)
        rr = await client.write_register(address_of("op_pct"), 9500, device_id=1)
        assert rr.isError() and rr.exception_code == 0x03
        assert not (await client.write_register(address_of("op_pct"), 8500, device_id=1)).isError()
        srv.device.advance(2)
        assert srv.device.bank.op[0] == 85.0 and srv.device.error is None


async def test_real_time_scale_runs_the_bank(client_for):
    async with EmulatorServer(_config(), time_scale=math.inf) as srv:
        await srv.device.wait_for_tick(50)
        client = await client_for(srv)
        regs = await _regs(client, 1)
        assert (regs[address_of("tick")] << 16 | regs[address_of("tick") + 1]) >= 50
    assert srv.device.bank.k == srv.device.ticks
