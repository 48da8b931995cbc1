"""Client side of the flood test, run in its own process: ``python _flood_client.py PORT [options]``.

Normal clients poll a 10-register read (each in a thread, blocking sockets) the whole time; after
``--warmup`` s, in each of ``--waves`` waves ``--wave-period`` s apart, ``--slow`` clients start trickling a
valid request one byte every ``--byte-period`` s and ``--flood`` connections are attempted at once
(non-blocking connects, then held open without sending).
Prints one JSON object: per-window answer counts of the normal clients, errors, when the server closed each
slow client, how many flood connections were accepted / refused.
"""

from __future__ import annotations

import argparse
import json
import selectors
import socket
import struct
import threading
import time

READ = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, 10)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed by the server")
        data += chunk
    return bytes(data)


def normal(port: int, t0: float, duration: float, window: float, out: dict) -> None:
    counts = [0] * int(duration / window + 1)
    errors = []
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=2) as sock:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            tid = 0
            while (now := time.monotonic() - t0) < duration:
                tid = (tid + 1) & 0xFFFF
                sock.sendall(struct.pack(">H", tid) + READ[2:])
                answer = _recv_exact(sock, 9 + 20)
                if answer[:2] != struct.pack(">H", tid) or answer[7:9] != b"\x03\x14":
                    errors.append(answer.hex())
                counts[int(now / window)] += 1
                time.sleep(0.01)  # a fast SCADA poll (100 per s), not a benchmark
    except OSError as exc:
        errors.append(repr(exc))
    out["counts"], out["errors"] = counts, errors


def slow(port: int, byte_period: float, out: dict, connected: threading.Event) -> None:
    """Send a valid request one byte at a time; note when the server hangs up."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            connected.set()
            start = time.monotonic()
            sent = 0
            try:
                for byte in READ * 10:
                    sock.sendall(bytes([byte]))
                    sent += 1
                    sock.settimeout(byte_period)
                    try:
                        data = sock.recv(100)
                    except TimeoutError:
                        continue
                    if data:
                        out["answered"] = data.hex()
                    break
            except OSError:
                pass
            out["closed_after"] = time.monotonic() - start
            out["bytes_sent"] = sent
    except OSError as exc:
        out["error"] = repr(exc)
        connected.set()


def flood(port: int, n: int, hold: float) -> dict:
    """``n`` non-blocking connects at once; count those the server keeps vs. resets/closes within ``hold``."""
    sel = selectors.DefaultSelector()
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", port))
        socks.append(s)
        sel.register(s, selectors.EVENT_READ)
    closed = set()
    deadline = time.monotonic() + hold
    while time.monotonic() < deadline and len(closed) < n:
        for key, _ in sel.select(timeout=0.05):
            s = key.fileobj
            try:
                data = s.recv(1)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            if not data:
                closed.add(s)
                sel.unregister(s)
    result = {"closed": len(closed), "open": n - len(closed)}
    for s in socks:
        s.close()
    return result


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("port", type=int)
    ap.add_argument("--normal", type=int, default=4)
    ap.add_argument("--slow", type=int, default=10)
    ap.add_argument("--flood", type=int, default=200)
    ap.add_argument("--waves", type=int, default=1, help="slow clients + flood, this many times in a row")
    ap.add_argument("--wave-period", type=float, default=3.0)
    ap.add_argument("--warmup", type=float, default=0.5)
    ap.add_argument("--window", type=float, default=0.25)
    ap.add_argument("--byte-period", type=float, default=0.2)
    args = ap.parse_args()
    duration = args.warmup + args.waves * args.wave_period + 0.5
    t0 = time.monotonic()
    normals = [{} for _ in range(args.normal)]
    threads = [threading.Thread(target=normal, args=(args.port, t0, duration, args.window, o)) for o in normals]
    for t in threads:
        t.start()
    time.sleep(args.warmup)
    slows, floods = [], []
    for _wave in range(args.waves):
        start = time.monotonic()
        wave_slows = [{} for _ in range(args.slow)]
        connected = [threading.Event() for _ in wave_slows]
        slow_threads = [threading.Thread(target=slow, args=(args.port, args.byte_period, o, c))
                        for o, c in zip(wave_slows, connected)]
        for t in slow_threads:
            t.start()
        for c in connected:   # the slow clients hold their slots before the flood arrives
            c.wait(5)
        floods.append(flood(args.port, args.flood, args.wave_period - 0.5))
        for t in slow_threads:
            t.join()
        slows += wave_slows
        time.sleep(max(0.0, args.wave_period - (time.monotonic() - start)))
    for t in threads:
        t.join()
    print(json.dumps({"normal": normals, "slow": slows, "flood": floods}))


if __name__ == "__main__":
    main()
