"""Communication faults on demand, seen from the client's side over real sockets: no response (a timeout),
exception 0x06 / 0x04, a closed connection, added latency; writes to the two unit registers are always
carried out and answered, and clearing them restores normal answers."""

import asyncio
import struct
import time

import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import COMM_BASE, address_of
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

UNIT, OTHER = 1, 2
FAULT, DELAY = COMM_BASE, COMM_BASE + 1
READ_OP = struct.pack(">BHH", 3, address_of("op_pct"), 1)


def _config(**device):
    plant = {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]}
    return server_from_mapping({"device": {"tick": 0.1, "instructor_writes": True, **device},
                                "loops": [{"unit": UNIT, "plant": plant}, {"unit": OTHER, "plant": plant}]})


@pytest.fixture
def make_server(fake_bank_cls):
    def make(config=None):
        config = config or _config()
        return EmulatorServer(config, bank=fake_bank_cls.for_config(config), time_scale=0)
    return make


def _set(address, value):
    return struct.pack(">BHH", 6, address, value)


async def test_no_response_times_out_and_clearing_over_the_wire_restores_answers(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        assert await raw.ask(UNIT, _set(FAULT, 1)) == _set(FAULT, 1)            # the write itself is answered
        raw.send(UNIT, READ_OP)
        t0 = time.monotonic()
        with pytest.raises(asyncio.TimeoutError):
            await raw.receive(timeout=0.5)
        assert time.monotonic() - t0 >= 0.5
        assert (await raw.ask(OTHER, READ_OP))[:2] == b"\x03\x02"               # other units answer
        assert await raw.ask(UNIT, struct.pack(">BHH", 3, FAULT, 2)) == b"\x03\x04\x00\x01\x00\x00"
        # FC23 writing the unit registers (what the scenario player sends) is answered too, its read included
        clear_and_read = struct.pack(">BHHHHBH", 23, address_of("op_pct"), 1, DELAY, 1, 2, 0)
        assert await raw.ask(UNIT, clear_and_read) == b"\x17\x02\x13\x88"
        assert await raw.ask(UNIT, _set(FAULT, 0)) == _set(FAULT, 0)
        assert await raw.ask(UNIT, READ_OP) == b"\x03\x02\x13\x88"              # 5000: 50.00 %


@pytest.mark.parametrize(("fault", "code"), [(2, 0x06), (3, 0x04)])
async def test_busy_and_failure_answer_with_their_exception_code(make_server, raw_for, fault, code):
    async with make_server() as srv:
        raw = await raw_for(srv)
        assert await raw.ask(UNIT, _set(FAULT, fault)) == _set(FAULT, fault)
        before = bytes(srv.device.image)
        assert await raw.ask(UNIT, READ_OP) == bytes((0x83, code))
        assert await raw.ask(UNIT, _set(address_of("op_pct"), 7000)) == bytes((0x86, code))   # not carried out
        assert await raw.ask(UNIT, b"\x2b\x0e\x01\x00") == bytes((0xAB, code))
        assert bytes(srv.device.image) == before
        assert await raw.ask(UNIT, _set(FAULT, 0)) == _set(FAULT, 0)
        assert await raw.ask(UNIT, READ_OP) == b"\x03\x02\x13\x88"
        assert srv.throttled == 0                                                # not charged to the client


async def test_close_ends_the_connection_and_a_new_one_can_clear_it(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        assert await raw.ask(UNIT, _set(FAULT, 4)) == _set(FAULT, 4)
        raw.send(UNIT, READ_OP)
        assert await asyncio.wait_for(raw.reader.read(), 2) == b""               # closed, nothing answered
        raw = await raw_for(srv)
        assert await raw.ask(UNIT, _set(FAULT, 0)) == _set(FAULT, 0)
        assert await raw.ask(UNIT, READ_OP) == b"\x03\x02\x13\x88"


async def test_delay_holds_answers_in_order_while_the_unit_registers_answer_at_once(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        assert await raw.ask(UNIT, _set(DELAY, 300)) == _set(DELAY, 300)
        t0 = time.monotonic()
        assert await raw.ask(UNIT, READ_OP) == b"\x03\x02\x13\x88"
        assert 0.3 <= time.monotonic() - t0 < 0.6
        first, second = raw.send(UNIT, READ_OP), raw.send(OTHER, READ_OP)      # pipelined behind the delay
        t0 = time.monotonic()
        assert (await raw.receive())[0] == first and (await raw.receive())[0] == second
        assert 0.3 <= time.monotonic() - t0 < 0.6
        t0 = time.monotonic()
        assert await raw.ask(UNIT, _set(DELAY, 0)) == _set(DELAY, 0)
        assert await raw.ask(UNIT, READ_OP) == b"\x03\x02\x13\x88"
        assert time.monotonic() - t0 < 0.2


async def test_unit_registers_are_instructor_only_and_range_checked(make_server, raw_for):
    async with make_server(_config(instructor_writes=False)) as srv:
        raw = await raw_for(srv)
        assert await raw.ask(UNIT, _set(FAULT, 1)) == b"\x86\x02"
        assert await raw.ask(UNIT, struct.pack(">BHH", 3, FAULT, 2)) == b"\x03\x04\x00\x00\x00\x00"  # readable
    async with make_server() as srv:
        raw = await raw_for(srv)
        assert await raw.ask(UNIT, _set(FAULT, 6)) == b"\x86\x03"
        assert await raw.ask(UNIT, _set(DELAY, 10001)) == b"\x86\x03"
        bad_pair = struct.pack(">BHHBHH", 16, FAULT, 2, 4, 2, 20000)             # whole or nothing
        assert await raw.ask(UNIT, bad_pair) == b"\x90\x03"
        assert await raw.ask(UNIT, struct.pack(">BHHBHHH", 16, FAULT, 3, 6, 0, 0, 0)) == b"\x90\x02"
        assert srv.comm.state(UNIT).words == (0, 0) and not srv.comm.active
        pair = struct.pack(">BHHBHH", 16, FAULT, 2, 4, 2, 100)
        assert await raw.ask(UNIT, pair) == struct.pack(">BHH", 16, FAULT, 2)
        assert srv.comm.state(UNIT).words == (2, 100) and srv.comm.state(OTHER).words == (0, 0)
