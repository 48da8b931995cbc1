"""A fleet served over Modbus (blocks of 32 registers per loop) gives each loop's own trajectory, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.image import ImageLayout
from valve_emulator.device.record import TickRecorder
from valve_emulator.device.registers import (
    BLOCK_STRIDE,
    N_REGISTERS,
    Scaling,
    address_of,
    encode,
    encode_image,
    encode_loop,
)
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.tick import Device
from valve_emulator.simulation.loop import LoopBank

pytestmark = pytest.mark.usefixtures("no_task_leak")

PER_UNIT = 16


def fleet_config():
    """Two classic loops (one unit each) and 40 open-loop fleet loops, 16 per unit (units 1, 2, 3)."""
    return server_from_mapping({
        "device": {"tick": 0.1, "instructor_writes": True},
        "loops": [
            {"unit": 100, "valve": {"S": 5.0, "J": 2.0},
             "plant": {"fopdt": {"gain": 3.0, "tau": 10.0, "delay": 1.0}, "noise": 0.02},
             "controller": {"kc": 0.2, "ti": 10.0, "sp_steps": [[0.5, 1.0]]}},
            {"unit": 101, "valve": {"S": 3.0, "J": 1.0}, "plant": {"integrator": {"gain": 0.1}, "pv0": 50.0}},
        ],
        "fleet": {"count": 40, "loops_per_unit": PER_UNIT, "seed": 5,
                  "base": {"valve": {"S": 4.0, "J": 1.0, "op0": 45.0},
                           "plant": {"fopdt": {"gain": 1.0, "tau": 4.0, "delay": 0.3},
                                     "disturbance": {"type": "sine", "amplitude": 4.0, "period": 3.0}}},
                  "vary": {"S": [0.5, 3.0], "J": [0.0, 1.0], "gain": [0.5, 2.0], "delay": [0.0, 1.0]}},
    })


async def read_unit(client, unit, blocks):
    """Every register of a unit in reads of 125 (each spans about four loops); pads included."""
    words, end = [], BLOCK_STRIDE * (blocks - 1) + N_REGISTERS
    while len(words) < end:
        rr = await client.read_holding_registers(len(words), count=min(125, end - len(words)), device_id=unit)
        assert not rr.isError(), rr
        words += rr.registers
    return np.array(words, dtype=np.int64)


def f32(words, at):
    """float32 (ABCD) at register ``at`` of each row of ``words``."""
    hi, lo = words[:, at].astype(np.uint32), words[:, at + 1].astype(np.uint32)
    return ((hi << 16) | lo).astype(np.uint32).view(np.float32)


async def test_fleet_over_modbus_equals_each_loop_stepped_alone(client_for):
    cfg = fleet_config()
    alone = [LoopBank([lp], dt=cfg.device.tick) for lp in cfg.loops]
    async with EmulatorServer(cfg, time_scale=0) as srv:
        client = await client_for(srv)
        units = {1: PER_UNIT, 2: PER_UNIT, 3: 40 - 2 * PER_UNIT, 100: 1, 101: 1}

        async def compare():
            for unit, blocks in units.items():
                words = await read_unit(client, unit, blocks)
                rows = np.stack([words[BLOCK_STRIDE * b:BLOCK_STRIDE * b + N_REGISTERS] for b in range(blocks)])
                idx = [i for i, lp in enumerate(cfg.loops) if lp.device.unit == unit]
                for name, at in (("op", "op_f32"), ("mv", "mv_f32"), ("pv", "pv_f32")):
                    expected = np.array([getattr(alone[i], name)[0] for i in idx], dtype=np.float32)
                    assert np.array_equal(f32(rows, address_of(at)), expected), (unit, name)
                assert set(rows[:, address_of("tick") + 1]) == {srv.device.ticks}
                if blocks > 1:
                    assert not words[BLOCK_STRIDE - 1::BLOCK_STRIDE].any()   # pads read 0

        def advance(k):
            srv.device.advance(k)
            for b in alone:
                for _ in range(k):
                    b.step()

        advance(15)
        await compare()
        # the operator moves loop 21 (unit 2, block 5); the instructor makes loop 5 (unit 1, block 3) stickier
        i_op, i_s = cfg.loops.index(next(lp for lp in cfg.loops if lp.name == "fleet_002_0005")), 5
        assert (cfg.loops[i_s].device.unit, cfg.loops[i_s].device.block) == (1, 3)
        rr = await client.write_register(BLOCK_STRIDE * 5 + address_of("op_pct"), 6500, device_id=2)
        assert not rr.isError()
        rr = await client.write_registers(BLOCK_STRIDE * 3 + address_of("S"), [725, 150], device_id=1)
        assert not rr.isError()
        alone[i_op].op_external[0] = 65.0
        alone[i_s].set_valve(0, S=7.25, J=1.5)
        advance(25)
        await compare()
        assert alone[i_op].op[0] == 65.0 and alone[i_s].S[0] == 7.25


async def test_block_addressing_rules_over_the_wire(client_for):
    cfg = fleet_config()
    async with EmulatorServer(cfg, time_scale=0) as srv:
        client = await client_for(srv)
        image = bytes(srv.device.image)

        async def code(coro):
            rr = await coro
            return rr.exception_code if rr.isError() else 0

        status = address_of("status")
        # an input read inside one block mirrors the holding registers; across blocks it is refused
        rr = await client.read_input_registers(BLOCK_STRIDE + status, count=N_REGISTERS - status, device_id=1)
        hr = await client.read_holding_registers(BLOCK_STRIDE + status, count=N_REGISTERS - status, device_id=1)
        assert rr.registers == hr.registers
        assert await code(client.read_input_registers(BLOCK_STRIDE + status, count=25, device_id=1)) == 2
        # writes stay inside one block: crossing into the pad / next block changes nothing
        assert await code(client.write_registers(BLOCK_STRIDE + 30, [0, 0], device_id=1)) == 2
        assert await code(client.write_register(BLOCK_STRIDE + 31, 0, device_id=1)) == 2
        assert bytes(srv.device.image) == image
        # past the last block of unit 3 (8 loops) and on a unit without loops
        last = BLOCK_STRIDE * 7 + N_REGISTERS
        assert await code(client.read_holding_registers(last - 1, count=1, device_id=3)) == 0
        assert await code(client.read_holding_registers(last, count=1, device_id=3)) == 2
        assert await code(client.write_register(BLOCK_STRIDE * 8, 100, device_id=3)) == 2
        assert await code(client.read_holding_registers(0, count=1, device_id=9)) == 0x0B
        # a unit with one loop keeps the classic map: address 31 is outside it
        assert await code(client.read_holding_registers(0, count=N_REGISTERS, device_id=100)) == 0
        assert await code(client.read_holding_registers(0, count=N_REGISTERS + 1, device_id=100)) == 2
        # an FC23 whose write half crosses a block is refused before anything is written
        rr = await client.readwrite_registers(read_address=0, read_count=4, write_address=BLOCK_STRIDE - 2,
                                              values=[1, 2, 3], device_id=1)
        assert rr.isError() and rr.exception_code == 2 and bytes(srv.device.image) == image


def test_image_layout_places_blocks_and_units_and_refuses_bad_ones():
    layout = ImageLayout([5, 5, 5, 7, 9, 9], [0, 1, 2, 0, 1, 0])
    row, block = 2 * N_REGISTERS, 2 * BLOCK_STRIDE
    assert layout.regions == {5: (0, 3), 7: (2 * block + row, 1), 9: (2 * block + 2 * row, 2)}
    assert list(layout.offsets) == [0, block, 2 * block, 2 * block + row, 2 * block + 2 * row + block,
                                    2 * block + 2 * row]
    assert layout.size == 2 * block + 2 * row + block + row and layout.blocked
    assert layout.locate_write(5, 2 * BLOCK_STRIDE + 4, 2) == (2, 4)
    assert layout.locate_write(7, 40, 1) == (3, 40)      # one block: the register map judges the address
    assert not ImageLayout([1, 2, 3]).blocked and list(ImageLayout([1, 2, 3]).offsets) == [0, row, 2 * row]
    with pytest.raises(ValueError, match="unique"):
        ImageLayout([5, 5], [1, 1])
    with pytest.raises(ValueError, match="without gaps"):
        ImageLayout([5, 5], [0, 2])


def test_encode_image_writes_each_loop_at_its_offset_and_leaves_the_alarms_word_to_the_device():
    cfg = fleet_config()
    bank = LoopBank(cfg.loops, dt=0.1)
    for _ in range(7):
        bank.step()
    dev = Device.from_config(cfg, bank=bank, time_scale=0)
    scaling = Scaling.from_config(cfg)
    words = encode(bank, scaling, tick=3, overruns=1, time=0.7)
    image = bytearray(b"\xAA" * dev.layout.size)
    encode_image(bank, scaling, image, dev.offsets, tick=3, overruns=1, time=0.7)
    alarms = address_of("alarms")
    for i, off in enumerate(dev.offsets):
        row = np.frombuffer(image, ">u2", N_REGISTERS, int(off)).tolist()
        assert row[:alarms] == words[i].tolist()[:alarms]
        assert row[alarms] == 0xAAAA           # the PV alarms are the device's (Device.alarms), not the encoder's


def test_a_loop_bank_encodes_from_its_own_arrays_as_the_codec_reads_its_properties():
    """The encoder reads a bank's live arrays and derives mv, stuck, ti, the saturation flags, auto and the loop
    current itself: the same words as the plain-Python codec reading the bank's properties, loop by loop, in
    auto and manual, without integral action, saturated, seized, loaded, noisy and through a custom mA table."""
    cfg = server_from_mapping({
        "device": {"tick": 0.1},
        "loops": [
            {"unit": 1, "valve": {"S": 5.0, "J": 2.0}, "plant": {"fopdt": {"gain": 3.0, "tau": 10.0}},
             "controller": {"kc": 0.2, "ti": 10.0, "td": 0.5}},
            {"unit": 2, "valve": {"S": 3.0, "J": 1.0, "ma_table": [[4.0, 100.0], [20.0, 0.0]]},
             "plant": {"integrator": {"gain": 0.1}, "pv0": 50.0}},
            {"unit": 3, "valve": {"S": 0.0, "J": 0.0}, "plant": {"fopdt": {"gain": 1.0, "tau": 2.0}},
             "controller": {"kc": 1.0, "ti": 5.0, "mode": "manual"}},
            {"unit": 4, "valve": {"S": 4.0, "J": 4.0, "op0": 30.0}, "plant": {"fopdt": {"gain": 1.0, "tau": 2.0}}},
        ]})
    bank = LoopBank(cfg.loops, dt=0.1)
    scaling = Scaling.from_config(cfg)
    bank.set_tuning(0, ti=float("inf"))
    bank.set_manual_op(2, 100.0)
    bank.op_external[1], bank.op_external[3] = 0.0, 57.3
    bank.set_frozen(3, True)
    bank.set_load(1, 2.5)
    bank.set_noise(3, 0.25)
    seen = set()
    for k in range(30):
        bank.step()
        words = encode(bank, scaling, tick=k, overruns=1, time=bank.sample_time)
        for i in range(bank.n):
            assert list(words[i]) == list(encode_loop(bank, scaling, i, tick=k, overruns=1, time=bank.sample_time))
        seen |= {("stuck", bool(s)) for s in bank.stuck} | {("sat", bool(s)) for s in bank.sat_high | bank.sat_low}
    assert seen == {("stuck", True), ("stuck", False), ("sat", True), ("sat", False)}   # both sides of each flag


def test_tick_time_is_recorded_and_blocked_devices_cannot_be_recorded(tmp_path):
    cfg = fleet_config()
    dev = Device.from_config(cfg, time_scale=0)
    dev.advance(3)
    assert len(dev.tick_time) == 3 and np.all(dev.tick_time.values() >= 0)
    with pytest.raises(ValueError, match="one loop per unit"):
        TickRecorder(dev, tmp_path / "x.csv")
