"""The Modbus TCP adapter: loopback with pymodbus, exception codes, pipelining, mbpoll."""

import asyncio
import logging
import socket
import struct

import pytest
from mbpoll_output import mbpoll_values, run

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import N_REGISTERS, address_of
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

OPEN_LOOP, WITH_PI = 1, 2


def _config(**device):
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [
        {"unit": OPEN_LOOP, "plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]}},
        {"unit": WITH_PI, "plant": {"num": [1.0], "den": [1.0, 0.0], "pv_range": [-10.0, 10.0]},
         "controller": {"kc": 0.4, "ti": 2.0}},
    ]})


@pytest.fixture
def make_server(fake_bank_cls):
    """EmulatorServer on 127.0.0.1:0 with frozen time (tests step it) over the FakeLoopBank double."""
    def make(config=None, **kw):
        config = config or _config()
        kw.setdefault("time_scale", 0)
        return EmulatorServer(config, bank=fake_bank_cls.for_config(config), **kw)
    return make


async def _holding(client, unit, address=0, count=N_REGISTERS):
    rr = await client.read_holding_registers(address, count=count, device_id=unit)
    assert not rr.isError(), rr
    return rr.registers


async def test_write_op_pct_reads_back_op_ma_and_vice_versa(make_server, client_for):
    async with make_server() as srv:
        client = await client_for(srv)
        assert not (await client.write_register(address_of("op_pct"), 2500, device_id=OPEN_LOOP)).isError()
        regs = await _holding(client, OPEN_LOOP)
        assert regs[address_of("op_ma")] == 8000                      # 4 + 0.16·25 mA
        op = client.convert_from_registers(regs[20:22], client.DATATYPE.FLOAT32, word_order="big")
        assert op == pytest.approx(25.0)
        assert not (await client.write_register(address_of("op_ma"), 16000, device_id=OPEN_LOOP)).isError()
        assert (await _holding(client, OPEN_LOOP))[address_of("op_pct")] == 7500
        srv.device.advance(1)                                           # physics sees the last write
        regs = await _holding(client, OPEN_LOOP)
        assert regs[address_of("mv_pct")] == 7500 and regs[address_of("tick")+1] == 1
        assert srv.device.bank.op_external[0] == 75.0


async def test_input_registers_mirror_read_only_values(make_server, client_for):
    async with make_server() as srv:
        srv.device.advance(3)
        client = await client_for(srv)
        a = address_of("status")
        rr = await client.read_input_registers(a, count=N_REGISTERS - a, device_id=WITH_PI)
        assert rr.registers == (await _holding(client, WITH_PI))[a:]


async def test_unknown_unit_gets_0x0b_without_traceback(make_server, client_for, caplog):
    caplog.set_level(logging.DEBUG)
    async with make_server() as srv:
        client = await client_for(srv)
        rr = await client.read_holding_registers(0, count=2, device_id=77)
        assert rr.isError() and rr.exception_code == 0x0B
    assert not any("Traceback" in r.getMessage() or r.exc_info for r in caplog.records)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.parametrize("address, values, code", [
    (address_of("op_pct"), [12000], 0x03),              # out of range
    (address_of("op_pct"), [1000, 3], 0x03),            # second register (op_ma) out of range: none written
    (address_of("mv_pct"), [100], 0x02),                # read-only
    (address_of("S"), [300], 0x02),                     # instructor register without permission
    (address_of("sp"), [5000], 0x02),                   # controller register, loop has no controller
    (N_REGISTERS - 1, [0, 0], 0x02),                    # past the end of the map
])
async def test_refused_writes_change_nothing(make_server, client_for, address, values, code):
    async with make_server() as srv:
        client = await client_for(srv)
        before = await _holding(client, OPEN_LOOP)
        if len(values) == 1:
            rr = await client.write_register(address, values[0], device_id=OPEN_LOOP)
        else:
            rr = await client.write_registers(address, values, device_id=OPEN_LOOP)
        assert rr.isError() and rr.exception_code == code
        assert await _holding(client, OPEN_LOOP) == before
        srv.device.advance(1)
        assert srv.device.bank.op_external[0] == 50.0 and srv.device.bank.calls == []


async def test_op_write_refused_in_auto_accepted_in_manual(make_server, client_for):
    async with make_server() as srv:
        client = await client_for(srv)
        rr = await client.write_register(address_of("op_pct"), 3000, device_id=WITH_PI)
        assert rr.isError() and rr.exception_code == 0x02
        assert not (await client.write_register(address_of("mode"), 0, device_id=WITH_PI)).isError()
        assert not (await client.write_register(address_of("op_pct"), 3000, device_id=WITH_PI)).isError()
        srv.device.advance(1)
        assert srv.device.bank.calls == [("auto", 1, False), ("manual_op", 1, 30.0)]


async def test_reads_past_the_map_and_into_input_holes_get_0x02(make_server, client_for):
    async with make_server() as srv:
        client = await client_for(srv)
        rr = await client.read_holding_registers(N_REGISTERS - 1, count=2, device_id=OPEN_LOOP)
        assert rr.isError() and rr.exception_code == 0x02
        rr = await client.read_input_registers(address_of("op_pct"), count=1, device_id=OPEN_LOOP)
        assert rr.isError() and rr.exception_code == 0x02
        rr = await client.read_coils(1, count=2, device_id=OPEN_LOOP)       # coils are 0..1
        assert rr.isError() and rr.exception_code == 0x02


async def test_read_only_mode_refuses_writes_with_illegal_function(make_server, client_for):
    async with make_server(_config(read_only=True)) as srv:
        client = await client_for(srv)
        before = await _holding(client, OPEN_LOOP)
        rr = await client.write_register(address_of("op_pct"), 1000, device_id=OPEN_LOOP)
        assert rr.isError() and rr.exception_code == 0x01
        assert await _holding(client, OPEN_LOOP) == before


@pytest.mark.parametrize("hosts, allowed", [([], True), (["127.0.0.1"], True), (["10.1.2.3"], False)])
async def test_instructor_writes_follow_the_host_list(make_server, client_for, hosts, allowed):
    async with make_server(_config(instructor_writes=True, instructor_hosts=hosts)) as srv:
        client = await client_for(srv)
        rr = await client.write_registers(address_of("S"), [500, 200], device_id=OPEN_LOOP)
        assert rr.isError() is (not allowed)
        srv.device.advance(1)
        assert list(srv.device.bank.S) == ([5.0, 0.0] if allowed else [0.0, 0.0])
        assert list(srv.device.bank.J) == ([2.0, 0.0] if allowed else [0.0, 0.0])


async def test_read_write_multiple_writes_first_then_reads(make_server, client_for):
    async with make_server() as srv:
        client = await client_for(srv)
        rr = await client.readwrite_registers(read_address=0, read_count=2, write_address=0,
                                              values=[4000], device_id=OPEN_LOOP)
        assert not rr.isError() and rr.registers == [4000, 10400]


def _mbap(tid, unit, pdu):
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


async def _read_frames(reader, n):
    frames = []
    for _ in range(n):
        header = await asyncio.wait_for(reader.readexactly(7), 2)
        frames.append(header + await reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1))
    return frames


async def test_pipelined_requests_are_all_answered_in_order(make_server):
    async with make_server() as srv:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        requests = [(11, OPEN_LOOP, 0, 2), (12, WITH_PI, address_of("status"), 1), (13, OPEN_LOOP, 2, 3)]
        writer.write(b"".join(_mbap(t, u, struct.pack(">BHH", 3, a, c)) for t, u, a, c in requests))
        # ...and one more split across two segments
        tail = _mbap(14, OPEN_LOOP, struct.pack(">BHH", 3, 0, 1))
        writer.write(tail[:5])
        await writer.drain()
        frames = await _read_frames(reader, 3)
        writer.write(tail[5:])
        frames += await _read_frames(reader, 1)
        writer.close()
        await writer.wait_closed()
    image = srv.device.image
    for frame, (tid, unit, a, c) in zip(frames, requests + [(14, OPEN_LOOP, 0, 1)]):
        start = srv.device.unit_index[unit] * srv.device.stride + 2 * a
        assert struct.unpack(">HHHBBB", frame[:9]) == (tid, 0, 3 + 2 * c, unit, 3, 2 * c)
        assert frame[9:] == image[start:start + 2 * c]


async def test_three_reads_in_one_sendall_on_a_raw_socket(make_server):
    async with make_server() as srv:
        def roundtrip():
            with socket.create_connection(("127.0.0.1", srv.port), timeout=2) as sock:
                sock.sendall(b"".join(_mbap(t, OPEN_LOOP, struct.pack(">BHH", 3, 0, t)) for t in (1, 2, 3)))
                data = b""
                while len(data) < sum(9 + 2 * t for t in (1, 2, 3)):
                    data += sock.recv(4096)
                return data
        data = await asyncio.to_thread(roundtrip)
    pos = 0
    for t in (1, 2, 3):
        assert struct.unpack(">HBB", data[pos:pos + 2] + data[pos + 7:pos + 9]) == (t, 3, 2 * t)
        assert data[pos + 9:pos + 9 + 2 * t] == bytes(srv.device.image[:2 * t])
        pos += 9 + 2 * t


async def test_malformed_requests(make_server):
    async with make_server() as srv:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        bad = [_mbap(1, OPEN_LOOP, struct.pack(">BHH", 3, 0, 0)),                      # count 0
               _mbap(2, OPEN_LOOP, struct.pack(">BHHB", 16, 0, 2, 4) + b"\x00\x01"),   # bytes missing
               _mbap(3, OPEN_LOOP, struct.pack(">BHHBH", 16, 0, 1, 2, 100) + b"\x00")]  # byte too many
        writer.write(b"".join(bad))
        frames = await _read_frames(reader, 3)
        assert [(f[7], f[8]) for f in frames] == [(0x83, 3), (0x90, 3), (0x90, 3)]
        assert srv.device.bank.calls == [] and srv.device._pending == {}
        writer.write(b"\x00\x01\x00\x07\x00\x06\x01\x03\x00\x00\x00\x01")          # protocol id 7
        assert await asyncio.wait_for(reader.read(), 2) == b""                    # connection closed
        writer.close()


async def test_bind_failure_raises_and_stops_the_tick(make_server):
    async with make_server(time_scale=1.0) as first:
        second = make_server(port=first.port, time_scale=1.0)
        with pytest.raises(OSError):
            await second.start()
        assert not second.device.running


async def test_fast_time_scale_serves_while_ticking(make_server, client_for):
    async with make_server(time_scale=float("inf")) as srv:
        client = await client_for(srv)
        k = srv.device.ticks
        await client.write_register(address_of("op_pct"), 6000, device_id=OPEN_LOOP)
        await srv.device.wait_for_tick(k + 2)
        assert (await _holding(client, OPEN_LOOP))[address_of("mv_pct")] == 6000


async def test_mbpoll_reads_and_writes(make_server, mbpoll):
    async with make_server() as srv:
        base = [mbpoll, "-m", "tcp", "-p", str(srv.port), "-a", str(OPEN_LOOP), "-0", "-1", "-o", "2"]
        rc, out = await run(*base, "-r", "0", "-t", "4", "127.0.0.1", "7500")
        assert rc == 0, out
        rc, out = await run(*base, "-r", "0", "-c", "3", "-t", "4", "127.0.0.1")
        assert rc == 0, out
        assert mbpoll_values(out) == {0: "7500", 1: "16000", 2: "5000"}
        rc, out = await run(*base, "-r", str(address_of("op_f32")), "-t", "4:float", "-B", "127.0.0.1")
        assert rc == 0 and float(mbpoll_values(out)[address_of("op_f32")]) == pytest.approx(75.0), out
        rc, out = await run(*base, "-r", str(address_of("mv_pct")), "-c", "2", "-t", "3", "127.0.0.1")
        assert rc == 0 and mbpoll_values(out) == {2: "5000", 3: "5000"}, out
        rc, out = await run(*base, "-r", "0", "-t", "4", "127.0.0.1", "12000")       # out of range
        assert rc != 0 and "Illegal data value" in out
        srv.device.advance(1)
        assert srv.device.bank.op_external[0] == 75.0          # the accepted write, not the refused one


async def test_mbpoll_default_word_order_matches_a_cdab_device(make_server, mbpoll):
    async with make_server(_config(word_order="CDAB")) as srv:
        argv = [mbpoll, "-m", "tcp", "-p", str(srv.port), "-a", str(OPEN_LOOP), "-0", "-1", "-o", "2",
                "-r", str(address_of("op_f32")), "-c", "2", "-t", "4:float", "127.0.0.1"]   # no -B: CDAB
        rc, out = await run(*argv)
        assert rc == 0, out
        values = mbpoll_values(out)
        assert float(values[address_of("op_f32")]) == pytest.approx(50.0)
        assert float(values[address_of("mv_f32")]) == pytest.approx(50.0)


def test_register_requests_are_answered_in_the_bytes_pymodbus_encodes():
    """The server decodes FC3/6/16/23 from the raw bytes and frames its answers itself: an answer, an exception
    answer and the MBAP header are the bytes pymodbus' response classes and socket framer give for them."""
    from pymodbus.framer import FramerSocket
    from pymodbus.pdu import DecodePDU, ExceptionResponse
    from pymodbus.pdu.register_message import (
        ReadHoldingRegistersResponse,
        ReadWriteMultipleRegistersResponse,
        WriteMultipleRegistersResponse,
        WriteSingleRegisterResponse,
    )

    from valve_emulator.device.roles import UNAUTHENTICATED

    srv = EmulatorServer(_config(lockstep=True))
    framer = FramerSocket(DecodePDU(is_server=False))

    def ask(pdu, tid):
        return srv.handle(struct.pack(">HHHB", tid, 0, len(pdu) + 1, OPEN_LOOP) + pdu, UNAUTHENTICATED)

    def expected(response, tid):
        return framer.encode(bytes((response.function_code,)) + response.encode(), OPEN_LOOP, tid)

    def words(address, count):
        return list(struct.unpack(f">{count}H", srv.device.served[2 * address:2 * (address + count)]))

    op, op_ma, pv = address_of("op_pct"), address_of("op_ma"), address_of("pv")
    assert ask(struct.pack(">BHH", 6, op, 4321), 0x1234) == expected(
        WriteSingleRegisterResponse(address=op, registers=[4321]), 0x1234)
    assert ask(struct.pack(">BHHBHH", 16, op, 2, 4, 6000, 13600), 0xFFFF) == expected(
        WriteMultipleRegistersResponse(address=op, count=2), 0xFFFF)
    step = struct.pack(">BHHHHBH", 23, pv, 3, 0xFF10, 1, 2, 1)
    answer = ask(step, 7)
    assert srv.device.ticks == 1
    assert answer == expected(ReadWriteMultipleRegistersResponse(registers=words(pv, 3)), 7)
    read = expected(ReadHoldingRegistersResponse(registers=words(op_ma, 2)), 8)
    assert ask(struct.pack(">BHH", 3, op_ma, 2), 8) == read
    refused = ask(struct.pack(">BHH", 6, address_of("mv_pct"), 1), 9)          # read-only: illegal data address
    assert refused == expected(ExceptionResponse(6, 2), 9)
    assert ask(struct.pack(">BHH", 16, op, 0), 10) == expected(ExceptionResponse(16, 3), 10)   # malformed
