"""Hostile protocol input over real sockets: 10^5 malformed frames, then the device is unharmed.

A seeded generator builds batches of malformed requests whose specified answer is known (an oracle), sends
each batch in one ``sendall`` (sometimes cut into many small segments) and checks every answer; a batch may
end with a frame that cannot be resynchronised (wrong protocol id, a length of 0, 1 or > 254, random bytes,
a truncated frame followed by end of stream), after which the server must have answered everything before
it and closed the connection. The client runs in another process with blocking sockets, as an attacker
would: in a thread of this one it would hold the GIL for about a third of the CPU time, and the tick would
measure the test, not the server. The server and its tick (real physics, time-scale 1, 100 ms) run on the
test's event loop.
"""

from __future__ import annotations

import asyncio
import gc
import multiprocessing
import random
import socket
import struct
import time
import tracemalloc
from concurrent.futures import ProcessPoolExecutor

import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import (
    INPUT_REGISTERS,
    MAP_VERSION,
    N_REGISTERS,
    RegisterError,
    address_of,
    check_read,
)
from valve_emulator.device.registers.bits import BitTable, check_bits
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

UNITS = (1, 2)
N_FRAMES = 100_000
TICK = 0.1


def _config():
    plant = {"num": [3.0], "den": [10.0, 1.0], "delay": 1.0, "pv_range": [-10.0, 10.0]}
    # error_rate: this test answers 10^5 malformed frames on a few connections; the error budget that
    # would slow them down is tested on its own (test_robustness_flood.py)
    return server_from_mapping({"device": {"tick": TICK, "error_rate": 1.0e+9}, "loops": [
        {"unit": 1, "valve": {"S": 5.0, "J": 2.0}, "plant": plant},
        {"unit": 2, "valve": {"S": 3.0, "J": 3.0}, "plant": plant, "controller": {"kc": 0.2, "ti": 10.0}},
    ]})


def _mbap(tid: int, unit: int, pdu: bytes, *, length: int | None = None, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1 if length is None else length, unit) + pdu


def _read_outcome(table: str, address: int, count: int) -> int | None:
    """Expected exception code of a read (None: a normal answer)."""
    if not 1 <= count <= 125:
        return 3
    try:
        check_read(table, address, count)
    except RegisterError:
        return 2
    return None


_READ_ONLY = [r.address for r in INPUT_REGISTERS if r.access == "R"]
_INSTRUCTOR = [r.address for r in INPUT_REGISTERS if r.access == "RW-instructor"]


def _answerable(rng: random.Random, tid: int) -> tuple[bytes, tuple]:
    """One malformed (or harmless) request and its expected answer ``(tid, unit, fc byte, code | -bytes)``."""
    unit = rng.choice(UNITS)
    kind = rng.randrange(19)
    if kind >= 13:
        return _answerable_beyond_registers(rng, tid, unit, kind)
    if kind == 0:                                           # unit without a loop: 0x0B before anything else
        bad = rng.choice([u for u in range(256) if u not in UNITS])
        fc = rng.randrange(256)
        pdu = bytes([fc]) + rng.randbytes(rng.randrange(0, 12))
        return _mbap(tid, bad, pdu), (tid, bad, fc | 0x80, 0x0B)
    if kind == 1:                                           # unknown function code (incl. >= 0x80)
        fc = rng.choice([f for f in range(256) if f not in _SUPPORTED])
        pdu = bytes([fc]) + rng.randbytes(rng.randrange(0, 40))
        return _mbap(tid, unit, pdu), (tid, unit, fc | 0x80, 0x01)
    if kind == 2:                                           # read count 0 or above 125
        fc, count = rng.choice((3, 4)), rng.choice([0, 126, 127, 2000, 65535, rng.randrange(126, 65536)])
        return _mbap(tid, unit, struct.pack(">BHH", fc, rng.randrange(65536), count)), (tid, unit, fc | 0x80, 3)
    if kind == 3:                                           # FC16: count 0 / > 123 / byte count lies
        count = rng.choice([0, 124, 125, 200, rng.randrange(1, 124)])
        nbytes = rng.choice([2 * count, 2 * count + 2, max(0, 2 * count - 2), rng.randrange(256)]) & 0xFF
        data = rng.randbytes(rng.choice([2 * count, nbytes, rng.randrange(0, 200)]) % 240)
        pdu = struct.pack(">BHHB", 16, rng.randrange(65536), count, nbytes) + data
        if 1 <= count <= 123 and nbytes == 2 * count == len(data):
            pdu += b"\x00\x00"                              # keep it malformed: two bytes too many
        return _mbap(tid, unit, pdu), (tid, unit, 0x90, 3)
    if kind == 4:                                           # FC23 limits and byte counts
        rc = rng.choice([0, 126, rng.randrange(1, 126)])
        wc = rng.choice([0, 122, rng.randrange(1, 122)])
        nbytes = rng.choice([2 * wc, 2 * wc + 1, 0]) & 0xFF
        data = rng.randbytes(min(rng.choice([2 * wc, nbytes, 3]), 240))
        pdu = struct.pack(">BHHHHB", 23, 0, rc, address_of("op_pct"), wc, nbytes) + data
        if 1 <= rc <= 125 and 1 <= wc <= 121 and nbytes == 2 * wc == len(data):
            pdu += b"\x00"
        return _mbap(tid, unit, pdu), (tid, unit, 0x97, 3)
    if kind == 5:                                           # truncated PDU (MBAP length matches the cut)
        fc = rng.choice((3, 4, 6, 16, 23))
        full = {3: struct.pack(">BHH", 3, 0, 2), 4: struct.pack(">BHH", 4, 12, 1),
                6: struct.pack(">BHH", 6, 0, 100), 16: struct.pack(">BHHBH", 16, 0, 1, 2, 100),
                23: struct.pack(">BHHHHBH", 23, 0, 1, 0, 1, 2, 100)}[fc]
        return _mbap(tid, unit, full[:rng.randrange(1, len(full))]), (tid, unit, fc | 0x80, 3)
    if kind == 6:                                           # MBAP length longer than the request (<= 254)
        fc = rng.choice((3, 4, 6))
        pdu = struct.pack(">BHH", fc, 0, 1) + rng.randbytes(rng.randrange(1, 200))
        return _mbap(tid, unit, pdu), (tid, unit, fc | 0x80, 3)
    if kind == 7:                                           # a read spanning past the end of the map
        fc, count = rng.choice((3, 4)), rng.randrange(1, 126)
        address = rng.randrange(max(0, N_REGISTERS - count + 1), 65536)
        return _mbap(tid, unit, struct.pack(">BHH", fc, address, count)), (tid, unit, fc | 0x80, 2)
    if kind == 8:                                           # FC6 refused: read-only, instructor, outside map
        address = rng.choice(_READ_ONLY + _INSTRUCTOR + [N_REGISTERS, rng.randrange(N_REGISTERS, 65536)])
        return _mbap(tid, unit, struct.pack(">BHH", 6, address, rng.randrange(65536))), (tid, unit, 0x86, 2)
    if kind == 9:                                           # FC6 value out of range
        pdu = struct.pack(">BHH", 6, address_of("op_pct"), rng.randrange(10001, 65536))
        code = 2 if unit == 2 else 3                        # unit 2's controller is in auto: OP not writable
        return _mbap(tid, unit, pdu), (tid, unit, 0x86, code)
    if kind == 10:                                          # FC16 starting on a read-only register
        address, count = rng.choice(_READ_ONLY), rng.randrange(1, 5)
        pdu = struct.pack(">BHHB", 16, address, count, 2 * count) + rng.randbytes(2 * count)
        return _mbap(tid, unit, pdu), (tid, unit, 0x90, 2 if address + count <= N_REGISTERS else 2)
    # kinds 11, 12: random read request (any address/count): either data or the specified exception
    fc, address, count = rng.choice((3, 4)), rng.randrange(0, 40), rng.randrange(0, 130)
    code = _read_outcome({3: "holding", 4: "input"}[fc], address, count)
    return (_mbap(tid, unit, struct.pack(">BHH", fc, address, count)),
            (tid, unit, fc | 0x80, code) if code else (tid, unit, fc, -2 * count))


_SUPPORTED = (1, 2, 3, 4, 5, 6, 8, 15, 16, 22, 23, 43)


def _answerable_beyond_registers(rng: random.Random, tid: int, unit: int, kind: int) -> tuple[bytes, tuple]:
    """Kinds 13..18: malformed requests of the bit, diagnostics, mask write and identification codes, each
    answered 0x03 by the same structural check, before any address; and random bit reads."""
    if kind == 13:                                          # FC1/FC2: bit count 0 or above 2000
        fc, count = rng.choice((1, 2)), rng.choice([0, 2001, rng.randrange(2001, 65536)])
        return _mbap(tid, unit, struct.pack(">BHH", fc, rng.randrange(65536), count)), (tid, unit, fc | 0x80, 3)
    if kind == 14:                                          # FC5 value neither 0xFF00 nor 0; fixed lengths cut
        fc = rng.choice((5, 5, 1, 2, 22, 43))
        if fc == 5:
            value = rng.choice([1, 0x00FF, 0xFFFF, 0xFF01, rng.randrange(1, 0xFF00)])
            return _mbap(tid, unit, struct.pack(">BHH", 5, rng.randrange(65536), value)), (tid, unit, 0x85, 3)
        full = {1: struct.pack(">BHH", 1, 0, 1), 2: struct.pack(">BHH", 2, 0, 1),
                22: struct.pack(">BHHH", 22, 0, 0xFFFF, 0), 43: b"\x2b\x0e\x01\x00"}[fc]
        pdu = full[:rng.randrange(1, len(full))] if rng.random() < 0.5 else full + rng.randbytes(rng.randrange(1, 9))
        if fc == 43 and len(pdu) == 1:
            pdu = b"\x2b"                                   # MEI type missing
        return _mbap(tid, unit, pdu), (tid, unit, fc | 0x80, 3)
    if kind == 15:                                          # FC15: count 0 / > 1968 / byte count lies
        count = rng.choice([0, 1969, rng.randrange(1, 1969)])
        right = (count + 7) // 8
        nbytes = rng.choice([right + 1, max(0, right - 1), rng.randrange(256)]) & 0xFF
        data = rng.randbytes(rng.choice([right, nbytes, rng.randrange(0, 200)]) % 240)
        pdu = struct.pack(">BHHB", 15, rng.randrange(65536), count, nbytes) + data
        if 1 <= count <= 1968 and nbytes == right == len(data):
            pdu += b"\x00"                                  # keep it malformed: one byte too many
        return _mbap(tid, unit, pdu), (tid, unit, 0x8F, 3)
    if kind == 16:                                          # FC8: counter sub-function with data, or too short
        if rng.random() < 0.3:
            return _mbap(tid, unit, b"\x08" + rng.randbytes(rng.randrange(0, 2))), (tid, unit, 0x88, 3)
        sub = rng.randrange(0x0A, 0x0F)
        data = rng.choice([rng.randbytes(rng.choice((0, 1, 3, 4))), struct.pack(">H", rng.randrange(1, 65536))])
        return _mbap(tid, unit, struct.pack(">BH", 8, sub) + data), (tid, unit, 0x88, 3)
    if kind == 17:                                          # FC43/0x0E: read device id code 0 or 5..255
        code = rng.choice([0, rng.randrange(5, 256)])
        return _mbap(tid, unit, bytes((43, 0x0E, code, rng.randrange(256)))), (tid, unit, 0xAB, 3)
    # kind 18: random bit read (any address/count): either data or the specified exception
    fc, address, count = rng.choice((1, 2)), rng.randrange(0, 40), rng.randrange(1, 12)
    try:
        check_bits(BitTable.COIL if fc == 1 else BitTable.DISCRETE_INPUT, address, count)
    except RegisterError:
        return _mbap(tid, unit, struct.pack(">BHH", fc, address, count)), (tid, unit, fc | 0x80, 2)
    return _mbap(tid, unit, struct.pack(">BHH", fc, address, count)), (tid, unit, fc, -((count + 7) // 8))


def _fatal(rng: random.Random, tid: int) -> tuple[bytes, bool, tuple | None]:
    """A frame after which the server must close: ``(bytes, send EOF after it, answer expected before)``."""
    kind = rng.randrange(6)
    read = struct.pack(">BHH", 3, 0, 1)
    if kind == 0:
        return _mbap(tid, 1, read, protocol=rng.randrange(1, 65536)), False, None
    if kind == 1:
        return _mbap(tid, 1, read, length=rng.choice([0, 1])), False, None
    if kind == 2:
        return _mbap(tid, 1, read, length=rng.choice([255, 256, 1000, 65535, rng.randrange(255, 65536)])), False, None
    if kind == 3:                                           # random bytes (protocol id forced non-zero)
        junk = bytearray(rng.randbytes(rng.randrange(7, 64)))
        junk[2] |= 1
        return bytes(junk), False, None
    if kind == 4:                                           # truncated frame, then end of stream
        frame = _mbap(tid, 1, read)
        return frame[:rng.randrange(1, len(frame))], True, None
    # MBAP length too short: the request is answered as malformed, its rest becomes a partial header
    return _mbap(tid, 1, read, length=rng.randrange(2, 5)), True, (tid, 1, 0x83, 3)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError(f"closed after {len(data)} of {n} bytes")
        data += chunk
    return bytes(data)


def _check_answers(sock: socket.socket, expected: list[tuple]) -> None:
    for tid, unit, fc, code in expected:
        header = _recv_exact(sock, 7)
        rtid, proto, length, runit = struct.unpack(">HHHB", header)
        body = _recv_exact(sock, length - 1)
        got = (rtid, proto, runit, body[0])
        assert got == (tid, 0, unit, fc), f"answer {header.hex()} {body.hex()} for expected {(tid, unit, fc, code)}"
        if code is not None and code > 0:
            assert body[1] == code and len(body) == 2, (body.hex(), code)
        else:
            assert body[1] == -code == len(body) - 2


def _expect_closed(sock: socket.socket) -> None:
    """The server closes the connection (after its short tarpit delay): EOF or reset, nothing more."""
    try:
        assert sock.recv(1) == b""
    except ConnectionResetError:
        pass
    sock.close()


def _fuzz(port: int, n_frames: int, seed: int) -> dict[str, int]:
    """Send at least ``n_frames`` malformed frames; returns counters."""
    rng = random.Random(seed)
    stats = {"frames": 0, "connections": 0, "split": 0, "closed": 0}
    sock, closing = None, []   # connections the server must close; checked later, not waited for
    tid = 0
    while stats["frames"] < n_frames:
        if sock is None:
            sock = socket.create_connection(("127.0.0.1", port), timeout=10)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            stats["connections"] += 1
        frames, expected = [], []
        for _ in range(rng.randrange(20, 400)):
            tid = (tid + 1) & 0xFFFF
            frame, answer = _answerable(rng, tid)
            frames.append(frame)
            expected.append(answer)
        fatal = rng.random() < 0.3
        payload = b"".join(frames)
        if rng.random() < 0.05:                     # the same bytes in many small segments
            stats["split"] += 1
            pos = 0
            while pos < len(payload):
                step = rng.choice((1, 2, 3, 7, 11, 50))
                sock.sendall(payload[pos:pos + step])
                pos += step
        else:
            sock.sendall(payload)
        stats["frames"] += len(frames)
        if fatal:
            tid = (tid + 1) & 0xFFFF
            tail, eof, answer = _fatal(rng, tid)
            sock.sendall(tail)
            if eof:
                sock.shutdown(socket.SHUT_WR)
            expected += [answer] if answer else []
            stats["frames"] += 1
        _check_answers(sock, expected)
        if fatal:
            closing.append(sock)
            sock = None
            if len(closing) > 20:
                _expect_closed(closing.pop(0))
                stats["closed"] += 1
    if sock is not None:
        sock.close()
    for sock in closing:
        _expect_closed(sock)
        stats["closed"] += 1
    return stats


def _read_holding(port: int, unit: int, address: int, count: int) -> list[int]:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(_mbap(77, unit, struct.pack(">BHH", 3, address, count)))
        header = _recv_exact(sock, 7)
        body = _recv_exact(sock, struct.unpack(">H", header[4:6])[0] - 1)
    assert body[:2] == bytes((3, 2 * count)), body.hex()
    return list(struct.unpack(f">{count}H", body[2:]))


async def _until(predicate, timeout: float = 5.0) -> None:
    """Bounded polling on observable state (not a synchronising sleep)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)


async def test_fuzz_1e5_malformed_frames_leave_the_device_unharmed():
    loop = asyncio.get_running_loop()
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as attacker:
        async with EmulatorServer(_config(), time_scale=1.0) as srv:
            # the wall time each tick ran at (this coroutine resumes after a tick, later on a busy event loop)
            tick_at: dict[int, float] = {}
            srv.device.on_tick.append(lambda device: tick_at.__setitem__(device.ticks, time.monotonic()))
            await srv.device.wait_for_tick(2)
            # warm-up: the attacker process starts, the server's code paths and caches fill
            stats = await loop.run_in_executor(attacker, _fuzz, srv.port, 3000, 1)
            await _until(lambda: srv.connections == 0)
            before_op = await asyncio.to_thread(_read_holding, srv.port, 1, 0, 2)
            gc.collect()
            tasks_before = len(asyncio.all_tasks())
            tracemalloc.start()
            mem_before = tracemalloc.get_traced_memory()[0]
            ticks0 = await srv.device.wait_for_tick(srv.device.ticks + 1)   # measure from a tick instant
            t0, overruns0 = tick_at[ticks0], srv.device.overruns

            stats = await loop.run_in_executor(attacker, _fuzz, srv.port, N_FRAMES, 9)

            ticks1 = await srv.device.wait_for_tick(srv.device.ticks + 1)
            t1 = tick_at[ticks1]
            await _until(lambda: srv.connections == 0)
            gc.collect()
            mem_after = tracemalloc.get_traced_memory()[0]
            tracemalloc.stop()
            assert stats["frames"] >= N_FRAMES and stats["closed"] > 100 and stats["split"] > 10, stats
            # the tick kept its schedule: ticks advanced at the nominal rate (±1 %), none overran
            rate = (ticks1 - ticks0) / (t1 - t0)
            assert rate == pytest.approx(1 / TICK, rel=0.01), (ticks1 - ticks0, t1 - t0)
            assert srv.device.overruns == overruns0
            # tasks and memory back to the baseline
            assert len(asyncio.all_tasks()) == tasks_before
            assert mem_after - mem_before < 512 * 1024, f"{(mem_after - mem_before) / 1024:.0f} KiB retained"
            # nothing was written, and a normal read answers correctly
            assert await asyncio.to_thread(_read_holding, srv.port, 1, 0, 2) == before_op
            regs = await asyncio.to_thread(_read_holding, srv.port, 2, address_of("map_version"), 1)
            assert regs == [MAP_VERSION]
            assert srv.device._pending == {}
            print(f"fuzz: {stats}, {t1 - t0:.1f} s, requests {srv.requests}, violations {srv.violations}, "
                  f"retained {(mem_after - mem_before) / 1024:.0f} KiB, tick p99 {srv.device.jitter.p99 * 1e3:.2f} ms")
