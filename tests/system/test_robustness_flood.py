"""Floods and slow clients: connection limit, idle / slow / half-open timeouts, the tick on time.

The server and its tick run here (real physics, time-scale 1, 100 ms tick); the hostile and normal clients
run in a separate process (``_flood_client.py``) so that their work does not share this event loop or GIL.
This scenario inherently takes real time; short timeouts keep it to a few seconds.
"""

from __future__ import annotations

import asyncio
import gc
import json
import logging
import socket
import struct
import sys
import time
from pathlib import Path

import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.guard import ConnectionGuard, LogLimiter
from valve_emulator.device.registers import N_REGISTERS
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.tick import JitterBuffer

pytestmark = pytest.mark.usefixtures("no_task_leak")

CLIENT = Path(__file__).with_name("_flood_client.py")
FRAME_TIMEOUT, IDLE_TIMEOUT = 0.5, 1.0
WAVES = 3   # 3 × (10 slow clients + 200 connection attempts at once), 3 s apart: about 100 ticks measured


def _config(**device):
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [
        {"unit": 1, "valve": {"S": 5.0, "J": 2.0},
         "plant": {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0, "pv_range": [-10.0, 10.0]}}]})


async def _until(predicate, timeout: float = 5.0) -> None:
    """Bounded polling on observable state (not a synchronising sleep)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)


def _read(port: int) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=2) as sock:
        sock.sendall(struct.pack(">HHHBBHH", 5, 0, 6, 1, 3, 0, 2))
        data = b""
        while len(data) < 13:
            chunk = sock.recv(64)
            if not chunk:
                break
            data += chunk
        return data


@pytest.mark.realtime
async def test_200_connections_and_10_slow_clients_keep_the_tick_and_the_normal_clients(caplog):
    caplog.set_level(logging.INFO, logger="valve_emulator.device.server")
    cfg = _config(frame_timeout=FRAME_TIMEOUT, idle_timeout=IDLE_TIMEOUT)   # max_connections: default 64
    async with EmulatorServer(cfg, time_scale=1.0) as srv:
        await srv.device.wait_for_tick(3)
        srv.device.jitter = JitterBuffer(4096)   # only the ticks of this scenario (not start-up compilation)
        overruns = srv.device.overruns
        gc.freeze()   # as `serve` does once started: no full collection rescans the start-up objects
        try:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, str(CLIENT), str(srv.port), "--normal", "4", "--slow", "10", "--flood", "200",
                "--waves", str(WAVES), "--wave-period", "3", stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE)
            out, err = await asyncio.wait_for(proc.communicate(), 60)
        finally:
            gc.unfreeze()
        assert proc.returncode == 0, err.decode()
        result = json.loads(out)
        jitter = srv.device.jitter
        await _until(lambda: srv.connections == 0)
        # slots are free again: a new client gets answers
        answer = await asyncio.to_thread(_read, srv.port)
        assert answer[7:9] == b"\x03\x04"

    # the tick stayed on schedule
    assert len(jitter) >= 95 and srv.device.overruns == overruns
    worst = [f"{x * 1e3:.1f}" for x in sorted(jitter.values())[-5:]]
    # No systematic lateness under the flood (95 % of ticks within 5 ms), and no tick pushed anywhere near the
    # next one (every tick within half a period). With about 100 ticks a p99 is the second-worst tick, which one
    # scheduling hiccup of a shared 2-core machine decides; the flood's own effect would delay many ticks.
    p95 = jitter.percentile(95)
    assert p95 <= 0.005, f"tick lateness p95 {p95 * 1e3:.2f} ms; worst {worst} ms"
    assert max(jitter.values()) < 0.05, f"a tick {max(jitter.values()) * 1e3:.1f} ms late; worst {worst} ms"
    # normal clients were answered in every window, without errors
    for client in result["normal"]:
        assert client["errors"] == []
        assert min(client["counts"][:-1]) > 0, client["counts"]
    # each flood hit the limit: 4 normal + 10 slow + 50 flood connections fit in 64, the rest was refused
    guard = srv.guard
    assert guard.refused >= WAVES * 100             # (exact counts depend on when idle ones expired)
    assert [f["closed"] for f in result["flood"]] == [200] * WAVES
    assert guard.expired["idle"] >= WAVES * 40      # accepted flood connections that never sent anything
    refusals = [r for r in caplog.records if "refused connection from" in r.getMessage()]
    assert refusals and "device.max_connections = 64" in refusals[0].getMessage()
    assert len(refusals) <= 2 * WAVES               # rate-limited: one line, then a count
    # every slow client lost its connection after the frame timeout, unanswered
    assert guard.expired["slow"] >= WAVES * 10
    for client in result["slow"]:
        assert "answered" not in client, client
        assert FRAME_TIMEOUT <= client["closed_after"] <= FRAME_TIMEOUT + 0.5, client
        assert client["bytes_sent"] < 12          # one byte per 0.2 s: never a whole 12-byte request
    print(f"tick p50 {jitter.p50 * 1e3:.2f} ms p99 {jitter.p99 * 1e3:.2f} ms, worst {worst} ms; "
          f"normal answers/window {[min(c['counts'][:-1]) for c in result['normal']]}; refused {guard.refused}; "
          f"expired {guard.expired}")


async def test_a_client_that_does_not_read_is_closed_and_costs_bounded_memory():
    """Pipelined requests without reading the answers: reading stops, the idle timeout ends it."""
    async with EmulatorServer(_config(idle_timeout=0.3, frame_timeout=0.3), time_scale=0) as srv:
        def hog():
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)   # before connecting: a small window
            sock.connect(("127.0.0.1", srv.port))
            sock.setblocking(False)
            request = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, N_REGISTERS) * 1000   # 71-byte answers
            sent, seen = 0, False
            start = time.monotonic()
            while time.monotonic() - start < 3:
                try:
                    sent += sock.send(request)
                except BlockingIOError:
                    time.sleep(0.01)   # our send buffer is full: the server stopped reading us
                except OSError:
                    break
                seen = seen or srv.connections == 1
                if seen and srv.connections == 0:
                    break
            sock.close()
            return sent
        sent = await asyncio.to_thread(hog)
        await _until(lambda: srv.connections == 0)
        assert sum(srv.guard.expired.values()) == 1   # idle, or slow: the frame left in the paused buffer
        # the server answered only what the socket buffers could hold, not everything that was sent
        assert srv.requests * 12 < sent


async def test_eof_after_pipelined_requests_still_answers_them_all():
    async with EmulatorServer(_config(), time_scale=0) as srv:
        def client():
            with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as sock:
                sock.sendall(b"".join(struct.pack(">HHHBBHH", t, 0, 6, 1, 3, 0, 1) for t in range(200)))
                sock.shutdown(socket.SHUT_WR)
                data = b""
                while chunk := sock.recv(65536):
                    data += chunk
                return data
        data = await asyncio.to_thread(client)
        assert len(data) == 200 * 11
        assert [struct.unpack(">H", data[i:i + 2])[0] for i in range(0, len(data), 11)] == list(range(200))


def test_guard_deadlines_on_a_fake_clock():
    now = [100.0]
    aborted = []
    guard = ConnectionGuard(max_connections=2, idle_timeout=10.0, frame_timeout=2.0, clock=lambda: now[0])
    a = guard.admit("a", lambda: aborted.append("a"))
    b = guard.admit("b", lambda: aborted.append("b"))
    assert guard.admit("c", lambda: aborted.append("c")) is None and guard.refused == 1
    b.partial_since = 101.0
    now[0] = 103.5                                   # b's frame is 2.5 s old
    assert guard.sweep() == 1 and aborted == ["b"] and guard.open == 1
    assert guard.admit("d", lambda: None) is not None  # b's slot is free
    a.last_request = 103.0
    now[0] = 112.0
    assert guard.sweep() == 0
    now[0] = 114.0
    assert guard.sweep() == 2 and aborted == ["b", "a"]  # a and d idle
    assert guard.expired == {"idle": 2, "slow": 1, "closing": 0}


def test_connections_being_closed_leave_the_limit_and_are_capped():
    now = [0.0]
    aborted = []
    guard = ConnectionGuard(max_connections=2, idle_timeout=10.0, frame_timeout=1.0, clock=lambda: now[0])
    slots = [guard.admit(name, lambda name=name: aborted.append(name)) for name in "ab"]
    guard.closing(slots[0])
    assert guard.open == 1 and guard.admit("c", lambda: aborted.append("c")) is not None
    guard.closing(slots[1])
    now[0] = 0.5
    guard.closing(guard.slots[next(iter(guard.slots))])      # c: a third one being closed
    assert aborted == ["a"] and len(guard.leaving) == 2        # the oldest went at once
    now[0] = 1.2
    assert guard.sweep() == 1 and aborted == ["a", "b"]        # b: closing for longer than frame_timeout
    guard.release(slots[1])
    assert guard.expired["closing"] == 2


def test_log_limiter_counts_what_it_suppresses(caplog):
    caplog.set_level(logging.INFO)
    now = [0.0]
    limiter = LogLimiter(logging.getLogger("test.limiter"), interval=10.0, clock=lambda: now[0])
    assert limiter.log("k", logging.WARNING, "refused %d", 1)
    assert not any(limiter.log("k", logging.WARNING, "refused %d", i) for i in range(2, 6))
    now[0] = 10.5
    limiter.flush()
    assert [r.getMessage() for r in caplog.records] == [
        "refused 1", "4 more 'k' events in the last 10 s were not logged"]
    now[0] = 11.0
    assert not limiter.log("k", logging.WARNING, "refused %d", 7)
    now[0] = 21.0
    assert limiter.log("k", logging.WARNING, "refused %d", 8)
    assert caplog.records[-1].getMessage() == "refused 8 (1 more like this in the last 10 s were not logged)"


# --- the connection's own defences ---------------------------------------------------------------------

def _frames(n: int, pdu: bytes, unit: int = 1) -> bytes:
    return b"".join(struct.pack(">HHHB", t & 0xFFFF, 0, len(pdu) + 1, unit) + pdu for t in range(n))


@pytest.mark.realtime
async def test_garbage_is_tarpitted_then_closed_without_holding_a_connection_slot(fake_bank_cls):
    from valve_emulator.device.connection import VIOLATION_DELAY

    cfg = _config(max_connections=2)   # also keeps at most 2 connections that are being closed
    async with EmulatorServer(cfg, bank=fake_bank_cls.for_config(cfg), time_scale=0) as srv:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        writer.write(_frames(1, struct.pack(">BHH", 3, 0, 2)) + b"\x00\x01\x00\x07garbage")
        answer = await asyncio.wait_for(reader.readexactly(13), 2)   # the read before the garbage: answered
        assert answer[7:9] == b"\x03\x04"
        t0 = time.monotonic()
        await _until(lambda: srv.violations == 1)
        assert srv.guard.open == 0 and len(srv.guard.leaving) == 1   # its slot is free at once ...
        other = await asyncio.to_thread(_read, srv.port)              # ... for another client
        assert other[7:9] == b"\x03\x04"
        assert await asyncio.wait_for(reader.read(), 5) == b""       # ... and it is closed a little later
        assert VIOLATION_DELAY - 0.05 <= time.monotonic() - t0 <= VIOLATION_DELAY + 1.0
        writer.close()


@pytest.mark.realtime
async def test_error_budget_slows_a_garbage_stream_and_nobody_else(fake_bank_cls):
    cfg = _config(error_rate=200.0)
    async with EmulatorServer(cfg, bank=fake_bank_cls.for_config(cfg), time_scale=0) as srv:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        t0 = time.monotonic()
        writer.write(_frames(400, struct.pack(">BHH", 3, 0, 0)))     # 400 reads of 0 registers: 0x03 each
        first = await asyncio.wait_for(reader.readexactly(9 * 150), 2)   # the burst comes at once
        burst = time.monotonic() - t0
        good = await asyncio.to_thread(_read, srv.port)              # meanwhile another client is served
        assert good[7:9] == b"\x03\x04"
        await asyncio.wait_for(reader.readexactly(9 * 250), 5)
        elapsed = time.monotonic() - t0
        writer.close()
        assert first[7:9] == b"\x83\x03" and burst < 0.5
        assert srv.throttled >= 1
        assert elapsed >= (400 - 200 - 32) / 200 * 0.8             # about 200 answers per second after the burst


@pytest.mark.realtime
async def test_a_pipelining_client_does_not_hold_up_another(fake_bank_cls):
    cfg = _config()
    async with EmulatorServer(cfg, bank=fake_bank_cls.for_config(cfg), time_scale=0) as srv:
        heavy_r, heavy_w = await asyncio.open_connection("127.0.0.1", srv.port)
        light_r, light_w = await asyncio.open_connection("127.0.0.1", srv.port)
        n = 20_000
        heavy_w.write(_frames(n, struct.pack(">BHH", 3, 0, 10)))    # about 0.2 s of work for the server
        heavy = asyncio.ensure_future(heavy_r.readexactly(n * 29))
        for _t in range(20):                                          # one request at a time, like a SCADA
            light_w.write(_frames(1, struct.pack(">BHH", 3, 0, 1)))
            await asyncio.wait_for(light_r.readexactly(11), 2)
        assert not heavy.done(), "the light client waited for the heavy one's backlog"
        await asyncio.wait_for(heavy, 20)
        for w in (heavy_w, light_w):
            w.close()
