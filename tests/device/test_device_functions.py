"""Function codes beyond registers, as raw frames over a real socket: bits (1, 2, 5, 15), diagnostics (8),
mask write (22) and device identification (43), answered per the Modbus Application Protocol V1.1b3."""

import struct

import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import Status, address_of
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

OPEN_LOOP, WITH_PI = 1, 2


def _config(**device):
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [
        {"name": "FIC-101", "description": "feed flow", "unit": OPEN_LOOP,
         "plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]}},
        {"name": "TIC-7", "unit": WITH_PI, "plant": {"num": [1.0], "den": [1.0, 0.0], "pv_range": [-10.0, 10.0]},
         "controller": {"kc": 0.4, "ti": 2.0}},
    ]})


@pytest.fixture
def make_server(fake_bank_cls):
    def make(config=None):
        config = config or _config()
        return EmulatorServer(config, bank=fake_bank_cls.for_config(config), time_scale=0)
    return make


async def _register(raw, unit, name):
    pdu = await raw.ask(unit, struct.pack(">BHH", 3, address_of(name), 1))
    assert pdu[:2] == b"\x03\x02", pdu
    return struct.unpack(">H", pdu[2:])[0]


def _exception(fc, code):
    return bytes((fc | 0x80, code))


async def test_discrete_inputs_are_the_status_bits_packed_lsb_first(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        for unit in (OPEN_LOOP, WITH_PI):
            status = await _register(raw, unit, "status")
            assert await raw.ask(unit, struct.pack(">BHH", 2, 0, 7)) == bytes((2, 1, status & 0x7F))
        # the PI loop: stuck (bit 0), controller (4), auto (5); the open loop: stuck only
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 2, 0, 7)) == b"\x02\x01\x31"
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 2, 4, 2)) == b"\x02\x01\x00"
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 2, 4, 2)) == b"\x02\x01\x03"   # shifted to bit 0
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 2, 6, 2)) == _exception(2, 2)  # past input 6
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 2, 0, 0)) == _exception(2, 3)  # count 0
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 2, 0, 2001)) == _exception(2, 3)
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 1, 0, 2)) == b"\x01\x01\x01"   # auto on, not seized


async def test_write_single_coil_switches_the_controller_to_manual(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        request = struct.pack(">BHH", 5, 0, 0x0000)
        assert await raw.ask(WITH_PI, request) == request                       # the response echoes
        assert await _register(raw, WITH_PI, "mode") == 0
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 1, 0, 1)) == b"\x01\x01\x00"
        assert not await _register(raw, WITH_PI, "status") & Status.AUTO
        srv.device.advance(1)
        assert srv.device.bank.calls == [("auto", 1, False)]
        request = struct.pack(">BHH", 5, 0, 0xFF00)
        assert await raw.ask(WITH_PI, request) == request
        assert await _register(raw, WITH_PI, "mode") == 1


async def test_refused_coil_writes_change_nothing(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        before = bytes(srv.device.image)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 5, 0, 0xFF00)) == _exception(5, 2)  # no controller
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 5, 1, 0xFF00)) == _exception(5, 2)    # not instructor
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 5, 2, 0xFF00)) == _exception(5, 2)    # no coil 2
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 5, 0, 0x1234)) == _exception(5, 3)    # not on/off
        # FC15 of coils 0 (allowed) and 1 (refused): whole or nothing, so auto stays on
        assert await raw.ask(WITH_PI, struct.pack(">BHHBB", 15, 0, 2, 1, 0b10)) == _exception(15, 2)
        assert await raw.ask(WITH_PI, struct.pack(">BHHBB", 15, 0, 2, 2, 0)) == _exception(15, 3)  # byte count
        assert await raw.ask(WITH_PI, struct.pack(">BHHB", 15, 0, 0, 0)) == _exception(15, 3)      # count 0
        assert bytes(srv.device.image) == before and srv.device._pending == {}


async def test_write_multiple_coils_with_instructor_permission(make_server, raw_for):
    async with make_server(_config(instructor_writes=True)) as srv:
        raw = await raw_for(srv)
        assert await raw.ask(WITH_PI, struct.pack(">BHHBB", 15, 0, 2, 1, 0b10)) == struct.pack(">BHH", 15, 0, 2)
        assert await _register(raw, WITH_PI, "mode") == 0
        assert await _register(raw, WITH_PI, "fault") == 1
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 1, 0, 2)) == b"\x01\x01\x02"
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 2, 6, 1)) == b"\x02\x01\x01"        # seized input


async def test_diagnostics_echo_and_counters(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        echo = struct.pack(">BH", 8, 0) + b"\xA5\x37"
        assert await raw.ask(OPEN_LOOP, echo) == echo
        assert await raw.ask(OPEN_LOOP, struct.pack(">BH", 8, 0)) == struct.pack(">BH", 8, 0)   # no data: echo
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 8, 0x0A, 0)) == struct.pack(">BHH", 8, 0x0A, 0)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 3, 40, 1)) == _exception(3, 2)      # one exception
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 8, 0x0D, 0)) == struct.pack(">BHH", 8, 0x0D, 1)
        # messages since the clear: the read, the 0x0D request and this one
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 8, 0x0E, 0)) == struct.pack(">BHH", 8, 0x0E, 3)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 8, 0x0C, 0)) == struct.pack(">BHH", 8, 0x0C, 0)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 8, 0x0E, 7)) == _exception(8, 3)    # data not 0
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 8, 0x01, 0)) == _exception(8, 1)    # restart comms
        assert await raw.ask(OPEN_LOOP, b"\x08\x00") == _exception(8, 3)                       # too short


async def test_mask_write_is_checked_like_a_register_write(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        op = address_of("op_pct")
        assert await _register(raw, OPEN_LOOP, "op_pct") == 5000                   # 0x1388
        request = struct.pack(">BHHH", 22, op, 0x00F2, 0x0025)
        assert await raw.ask(OPEN_LOOP, request) == request
        # (0x1388 AND 0x00F2) OR (0x0025 AND NOT 0x00F2) = 0x0080 OR 0x0005, the spec's §6.16 arithmetic
        assert await _register(raw, OPEN_LOOP, "op_pct") == 0x0085
        before = bytes(srv.device.image)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHHH", 22, op, 0, 0xFFFF)) == _exception(22, 3)  # 65535
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHHH", 22, address_of("mv_pct"), 0, 1)) == _exception(22, 2)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHHH", 22, address_of("S"), 0, 1)) == _exception(22, 2)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHHH", 22, 31, 0, 1)) == _exception(22, 2)
        assert await raw.ask(OPEN_LOOP, struct.pack(">BHH", 22, op, 0)) == _exception(22, 3)          # short
        assert bytes(srv.device.image) == before


async def test_read_only_mode_refuses_every_write_function(make_server, raw_for):
    async with make_server(_config(read_only=True)) as srv:
        raw = await raw_for(srv)
        before = bytes(srv.device.image)
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 5, 0, 0)) == _exception(5, 1)
        assert await raw.ask(WITH_PI, struct.pack(">BHHBB", 15, 0, 1, 1, 0)) == _exception(15, 1)
        assert await raw.ask(WITH_PI, struct.pack(">BHHH", 22, 0, 0, 100)) == _exception(22, 1)
        assert await raw.ask(WITH_PI, struct.pack(">BHH", 1, 0, 2)) == b"\x01\x01\x01"        # reads still work
        assert bytes(srv.device.image) == before


def _objects(pdu):
    """``(code, conformity, more, next, {id: value})`` of a read device identification response."""
    assert pdu[:2] == b"\x2b\x0e", pdu
    code, conformity, more, nxt, n = pdu[2:7]
    objects, pos = {}, 7
    for _ in range(n):
        oid, length = pdu[pos], pdu[pos + 1]
        objects[oid] = pdu[pos + 2:pos + 2 + length].decode()
        pos += 2 + length
    assert pos == len(pdu)
    return code, conformity, more, nxt, objects


async def test_read_device_identification(make_server, raw_for):
    import valve_emulator

    async with make_server() as srv:
        raw = await raw_for(srv)
        code, conformity, more, nxt, basic = _objects(await raw.ask(OPEN_LOOP, b"\x2b\x0e\x01\x00"))
        assert (code, conformity, more, nxt) == (1, 0x82, 0, 0)
        assert sorted(basic) == [0, 1, 2] and basic[2] == valve_emulator.__version__
        _, _, _, _, regular = _objects(await raw.ask(OPEN_LOOP, b"\x2b\x0e\x02\x00"))
        assert sorted(regular) == list(range(7))
        assert (regular[5], regular[6]) == ("FIC-101", "feed flow")                 # ModelName, application
        assert _objects(await raw.ask(WITH_PI, b"\x2b\x0e\x04\x05"))[4] == {5: "TIC-7"}   # individual access
        assert sorted(_objects(await raw.ask(OPEN_LOOP, b"\x2b\x0e\x02\x04"))[4]) == [4, 5, 6]  # from id 4
        assert sorted(_objects(await raw.ask(OPEN_LOOP, b"\x2b\x0e\x01\x05"))[4]) == [0, 1, 2]  # restarts at 0
        assert sorted(_objects(await raw.ask(OPEN_LOOP, b"\x2b\x0e\x03\x00"))[4]) == list(range(7))
        assert await raw.ask(OPEN_LOOP, b"\x2b\x0e\x04\x07") == _exception(43, 2)   # unknown object
        assert await raw.ask(OPEN_LOOP, b"\x2b\x0e\x04\x80") == _exception(43, 2)
        assert await raw.ask(OPEN_LOOP, b"\x2b\x0e\x05\x00") == _exception(43, 3)   # read code 5
        assert await raw.ask(OPEN_LOOP, b"\x2b\x0e\x01") == _exception(43, 3)       # short
        assert await raw.ask(OPEN_LOOP, b"\x2b\x0d\x00\x00\x00") == _exception(43, 1)   # CANopen MEI


async def test_unsupported_function_codes_get_illegal_function(make_server, raw_for):
    async with make_server() as srv:
        raw = await raw_for(srv)
        for fc in (7, 11, 17, 20, 24, 0x41):
            assert await raw.ask(OPEN_LOOP, bytes((fc, 0, 0, 0, 1))) == _exception(fc, 1)


async def test_pymodbus_client_decodes_identification_bits_and_diagnostics(make_server, client_for):
    async with make_server() as srv:
        client = await client_for(srv)
        rr = await client.read_device_information(read_code=2, object_id=0, device_id=WITH_PI)
        assert not rr.isError() and rr.information[5] == b"TIC-7" and rr.information[0] == b"valve_emulator"
        rr = await client.read_discrete_inputs(0, count=7, device_id=WITH_PI)
        assert rr.bits[:7] == [True, False, False, False, True, True, False]
        rr = await client.write_coil(0, False, device_id=WITH_PI)
        assert not rr.isError()
        assert (await client.read_coils(0, count=1, device_id=WITH_PI)).bits[0] is False
        rr = await client.diag_read_bus_message_count(device_id=OPEN_LOOP)
        assert not rr.isError() and rr.message == 5          # this request is the fifth
        rr = await client.mask_write_register(address=address_of("op_pct"), and_mask=0, or_mask=4000,
                                              device_id=OPEN_LOOP)
        assert not rr.isError()
        assert (await client.read_holding_registers(0, count=1, device_id=OPEN_LOOP)).registers == [4000]
