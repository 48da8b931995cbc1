"""Modbus RTU on a real pseudo serial line (a ``socat`` pty pair) and RTU frames over TCP.

mbpoll (libmodbus) polls over the pty at 19200 8E1 and 9600 8N2; raw frames show that a wrong CRC gets no
reply while the next good frame is answered, and that a broadcast write is carried out by every unit
without a reply; a pymodbus client configured with the RTU framer talks to ``framer="rtu"`` over TCP.
"""

import asyncio
import struct
import subprocess
import time

import pytest
import serial
from mbpoll_output import mbpoll_values, run
from required import tool

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import COMM_BASE, address_of
from valve_emulator.device.rtu import SerialSettings, crc16, with_crc
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")


def _config(**device):
    plant = {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]}
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [
        {"name": "FV-1", "unit": 1, "plant": plant}, {"name": "FV-2", "unit": 2, "plant": plant}]})


@pytest.fixture
def pty_pair(tmp_path):
    """Two linked pseudo terminals ``(server end, client end)`` made by socat (stopped after the test)."""
    socat = tool("socat", "apt-get install socat")
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    proc = subprocess.Popen([socat, f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 5
    while not (a.exists() and b.exists()):
        assert time.monotonic() < deadline and proc.poll() is None, "socat did not create the pty pair"
        time.sleep(0.02)
    yield str(a), str(b)
    proc.terminate()
    proc.wait(5)


@pytest.fixture
def make_server(fake_bank_cls):
    def make(config=None, **kw):
        config = config or _config()
        return EmulatorServer(config, bank=fake_bank_cls.for_config(config), time_scale=0, **kw)
    return make


async def _mbpoll(mbpoll, *argv):
    return await run(mbpoll, "-m", "rtu", "-0", "-1", "-o", "1", *argv, timeout=20)


@pytest.mark.parametrize(("settings", "flags"), [
    (SerialSettings(), ["-b", "19200", "-P", "even", "-s", "1"]),
    (SerialSettings(baud=9600, parity="N", stopbits=2), ["-b", "9600", "-P", "none", "-s", "2"]),
])
async def test_mbpoll_reads_and_writes_over_a_serial_line(make_server, pty_pair, mbpoll, settings, flags):
    server_end, client_end = pty_pair
    async with make_server() as srv:
        link = srv.open_serial(server_end, settings)
        rc, out = await _mbpoll(mbpoll, *flags, "-a", "1", "-r", "0", "-t", "4", client_end, "7500")
        assert rc == 0, out
        rc, out = await _mbpoll(mbpoll, *flags, "-a", "1", "-r", "0", "-c", "3", "-t", "4", client_end)
        assert rc == 0 and mbpoll_values(out) == {0: "7500", 1: "16000", 2: "5000"}, out
        rc, out = await _mbpoll(mbpoll, *flags, "-a", "2", "-r", "0", "-c", "7", "-t", "1", client_end)
        assert rc == 0 and mbpoll_values(out) == {0: "1", 1: "0", 2: "0", 3: "0", 4: "0", 5: "0", 6: "0"}, out
        rc, out = await _mbpoll(mbpoll, *flags, "-a", "3", "-r", "0", "-t", "4", client_end)   # no unit 3
        assert rc != 0 and "timed out" in out.lower(), out
        assert link.frames >= 4 and link.dropped == 0


def _exchange(port, settings, frames, *, wait=0.3):
    """Send each frame (with a pause longer than t3.5 between them) and return what came back after each."""
    parity = {"E": serial.PARITY_EVEN, "O": serial.PARITY_ODD, "N": serial.PARITY_NONE}[settings.parity]
    answers = []
    with serial.Serial(port, baudrate=settings.baud, parity=parity, stopbits=settings.stopbits,
                       timeout=wait) as line:
        for frame in frames:
            line.write(frame)
            time.sleep(wait)
            answers.append(line.read(line.in_waiting or 1) if line.in_waiting else b"")
    return answers


async def test_a_wrong_crc_gets_no_reply_and_the_next_good_frame_is_answered(make_server, pty_pair):
    server_end, client_end = pty_pair
    async with make_server() as srv:
        srv.open_serial(server_end)
        good = with_crc(struct.pack(">BBHH", 1, 3, address_of("op_pct"), 1))
        bad = good[:-1] + bytes((good[-1] ^ 0x5A,))
        answers = await asyncio.to_thread(_exchange, client_end, SerialSettings(), [bad, good])
        assert answers[0] == b""
        assert answers[1] == with_crc(b"\x01\x03\x02\x13\x88") and crc16(answers[1]) == 0
        assert srv.diagnostics.comm_errors == 1


async def test_broadcast_write_is_carried_out_by_every_unit_without_a_reply(make_server, pty_pair):
    server_end, client_end = pty_pair
    async with make_server() as srv:
        srv.open_serial(server_end)
        op = address_of("op_pct")
        frames = [with_crc(struct.pack(">BBHH", 0, 6, op, 2500)),                   # broadcast: silence
                  with_crc(struct.pack(">BBHH", 2, 3, op, 1))]
        answers = await asyncio.to_thread(_exchange, client_end, SerialSettings(), frames)
        assert answers == [b"", with_crc(b"\x02\x03\x02\x09\xc4")]                # 2500 on unit 2 too
        srv.device.advance(1)
        assert list(srv.device.bank.op_external) == [25.0, 25.0]


async def test_comm_fault_bad_crc_corrupts_the_answer_on_the_line(make_server, pty_pair):
    server_end, client_end = pty_pair
    async with make_server(_config(instructor_writes=True)) as srv:
        srv.open_serial(server_end)
        read = with_crc(struct.pack(">BBHH", 1, 3, address_of("op_pct"), 1))
        frames = [with_crc(struct.pack(">BBHH", 1, 6, COMM_BASE, 5)), read,
                  with_crc(struct.pack(">BBHH", 1, 6, COMM_BASE, 0)), read]
        answers = await asyncio.to_thread(_exchange, client_end, SerialSettings(), frames)
        assert answers[0] == frames[0]                                              # FC6 echo, good CRC
        assert answers[1][:-2] == b"\x01\x03\x02\x13\x88" and crc16(answers[1]) != 0
        assert answers[3] == with_crc(b"\x01\x03\x02\x13\x88")


async def test_rtu_over_tcp_answers_a_pymodbus_client_with_the_rtu_framer(make_server):
    from pymodbus.client import AsyncModbusTcpClient
    from pymodbus.framer import FramerType

    async with make_server(framer="rtu") as srv:
        client = AsyncModbusTcpClient("127.0.0.1", port=srv.port, framer=FramerType.RTU, timeout=2, retries=0)
        assert await client.connect()
        try:
            assert not (await client.write_register(address_of("op_pct"), 6000, device_id=1)).isError()
            rr = await client.read_holding_registers(0, count=3, device_id=1)
            assert rr.registers == [6000, 13600, 5000]
            rr = await client.read_discrete_inputs(0, count=2, device_id=2)
            assert rr.bits[:2] == [True, False]
            rr = await client.read_holding_registers(0, count=1, device_id=9)            # no unit 9
            assert rr.isError() and rr.exception_code == 0x0B
            rr = await client.read_device_information(read_code=4, object_id=5, device_id=2)
            assert rr.information[5] == b"FV-2"
        finally:
            client.close()


async def test_serve_command_runs_tcp_and_rtu_from_one_process_on_one_tick(pty_pair, mbpoll):
    import sys

    server_end, client_end = pty_pair
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "valve_emulator", "serve", "--port", "0", "--rtu", server_end, "--baud", "9600",
        "--parity", "N", "--stopbits", "2", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT)
    try:
        line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
        assert f"Modbus RTU on {server_end} at 9600 8N2" in line, line
        port = line.split("listening on 127.0.0.1:")[1].split(",")[0]
        tick = address_of("tick")
        rc, out = await _mbpoll(mbpoll, "-b", "9600", "-P", "none", "-s", "2", "-a", "1", "-r", str(tick),
                                "-c", "2", "-t", "4", client_end)
        assert rc == 0, out
        rtu_tick = int(mbpoll_values(out)[tick]) << 16 | int(mbpoll_values(out)[tick + 1])
        tcp = await asyncio.create_subprocess_exec(
            mbpoll, "-m", "tcp", "-p", port, "-a", "1", "-0", "-1", "-r", str(tick), "-c", "2", "-t", "4",
            "127.0.0.1", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT)
        out = (await asyncio.wait_for(tcp.communicate(), 20))[0].decode()
        assert tcp.returncode == 0, out
        tcp_tick = int(mbpoll_values(out)[tick]) << 16 | int(mbpoll_values(out)[tick + 1])
        assert 0 <= tcp_tick - rtu_tick <= 20        # the same tick counter, read a moment apart
    finally:
        proc.terminate()
        await asyncio.wait_for(proc.wait(), 20)


@pytest.mark.parametrize(("argv", "message"), [
    (["--baud", "9600"], "--baud, --parity and --stopbits set up the serial line of --rtu DEVICE"),
    (["--rtu", "/nonexistent/ttyX"], "--rtu /nonexistent/ttyX: no such file or directory"),
])
def test_serve_refuses_bad_serial_flags(argv, message, capsys):
    from valve_emulator.cli import main

    assert main(["serve", "--port", "0", *argv]) != 0
    assert message in capsys.readouterr().err


def _send_in_two_parts(port, gaps):
    """Send a read of op_pct at 1200 8E1 in two parts ``gap`` s apart, for each gap; return the answers
    (one open: socat ends the pty pair when one side closes)."""
    frame = with_crc(struct.pack(">BBHH", 1, 3, address_of("op_pct"), 1))
    answers = []
    with serial.Serial(port, baudrate=1200, parity=serial.PARITY_EVEN, timeout=0.5) as line:
        for gap in gaps:
            line.write(frame[:3])
            time.sleep(gap)
            line.write(frame[3:])
            answers.append(line.read(7))
    return answers


@pytest.mark.realtime   # a 22 ms silence between t1.5 and t3.5: 8 ms either side, which a loaded machine eats
async def test_a_silence_inside_a_frame_discards_it(make_server, pty_pair):
    server_end, client_end = pty_pair
    settings = SerialSettings(baud=1200)                # t1.5 = 13.75 ms, t3.5 = 32.1 ms
    async with make_server() as srv:
        link = srv.open_serial(server_end, settings)
        answers = await asyncio.to_thread(_send_in_two_parts, client_end, [0.022, 0.0])
        assert answers == [b"", with_crc(b"\x01\x03\x02\x13\x88")]
        assert link.dropped == 1


async def test_rtu_over_tcp_survives_garbage_and_answers_the_next_good_frame(make_server):
    import random

    rng = random.Random(16)
    good = with_crc(struct.pack(">BBHH", 1, 3, address_of("op_pct"), 1))
    async with make_server(framer="rtu") as srv:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        try:
            for size in (1, 3, 7, 40, 300):
                junk = bytes(rng.randrange(256) for _ in range(size))
                writer.write(junk)
                await asyncio.sleep(0.1)                      # > STREAM_GAP: the partial frame is abandoned
                writer.write(good)
                answer = await asyncio.wait_for(reader.readexactly(7), 2)
                assert answer == with_crc(b"\x01\x03\x02\x13\x88"), (size, answer)
                await asyncio.sleep(0.05)
                assert not reader._buffer                     # noqa: SLF001 - nothing else was answered
        finally:
            writer.close()
        assert srv.crc_errors >= 4
