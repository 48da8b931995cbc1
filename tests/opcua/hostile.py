"""Malformed OPC UA traffic for the hostile-input test and ``bench/bench_opcua.py``: seeded, loopback only.

Every message goes over a fresh TCP connection (the server ends a connection at its first error, as OPC UA
Part 6 asks), and the sender reads until the server closes or a short time passes. The kinds:

- ``random``: random bytes;
- ``huge``: a Hello chunk whose MessageSize is absurd (up to 4 GiB), then a few bytes;
- ``tiny``: a chunk header whose MessageSize is smaller than the header itself;
- ``after_hello``: a valid Hello, then garbage;
- ``truncated``: a chunk header promising more than is sent, then end of stream;
- ``bad_sequence``: a valid Hello, then a MSG chunk on a channel that does not exist, with a random sequence
  number;
- ``open_junk``: an OpenSecureChannel chunk with a junk body;
- ``tls``: a TLS ClientHello (what a client configured for another protocol sends).
"""

from __future__ import annotations

import random
import socket
import struct
import threading
import time

KINDS = ("random", "huge", "tiny", "after_hello", "truncated", "bad_sequence", "open_junk", "tls")
# A TLS 1.2 ClientHello's first bytes (record header, handshake header, version, part of the random).
TLS_HELLO = bytes.fromhex("16030100c4010000c00303") + bytes(32)


def hello(url: str) -> bytes:
    """A well-formed OPC UA Hello chunk for ``url`` (Part 6, 7.1.2.3)."""
    body = struct.pack("<IIIII", 0, 65536, 65536, 0, 0) + struct.pack("<i", len(url)) + url.encode()
    return b"HELF" + struct.pack("<I", 8 + len(body)) + body


def message(kind: str, rng: random.Random, url: str) -> bytes:
    """One malformed message of ``kind``."""
    junk = rng.randbytes(rng.randint(1, 200))
    if kind == "random":
        return junk
    if kind == "huge":
        return b"HELF" + struct.pack("<I", rng.randint(2**24, 2**32 - 1)) + junk[:16]
    if kind == "tiny":
        return rng.choice([b"HELF", b"MSGF", b"OPNF"]) + struct.pack("<I", rng.randint(0, 7)) + junk[:8]
    if kind == "after_hello":
        return hello(url) + junk
    if kind == "truncated":
        return rng.choice([b"HELF", b"MSGF", b"OPNF"]) + struct.pack("<I", 1000 + len(junk)) + junk
    if kind == "bad_sequence":
        body = struct.pack("<IIII", rng.getrandbits(32), rng.getrandbits(32), rng.getrandbits(32), rng.randint(1, 9))
        return hello(url) + b"MSGF" + struct.pack("<I", 8 + len(body) + len(junk)) + body + junk
    if kind == "open_junk":
        return b"OPNF" + struct.pack("<I", 8 + len(junk)) + junk
    if kind == "tls":
        return TLS_HELLO
    raise ValueError(f"unknown kind {kind!r}")


def send_one(host: str, port: int, data: bytes, *, linger: float = 0.5) -> bool:
    """Send ``data`` on a new connection and read until the server closes (True) or ``linger`` passes."""
    with socket.create_connection((host, port), timeout=5) as sock:
        sock.settimeout(linger)
        try:
            sock.sendall(data)
            sock.shutdown(socket.SHUT_WR)
            while sock.recv(4096):
                pass
            return True
        except TimeoutError:
            return False
        except OSError:       # reset by the server: it closed the connection
            return True


def attack(host: str, port: int, url: str, count: int, *, seed: int = 802, threads: int = 4) -> dict[str, int]:
    """Send ``count`` malformed messages (kinds in turn) from ``threads`` threads; per-kind counts and how many
    connections the server closed itself."""
    sent = {k: 0 for k in KINDS}
    closed = [0]
    lock = threading.Lock()

    def worker(index: int) -> None:
        rng = random.Random(seed * 1000 + index)
        for n in range(index, count, threads):
            kind = KINDS[n % len(KINDS)]
            ok = send_one(host, port, message(kind, rng, url))
            with lock:
                sent[kind] += 1
                closed[0] += ok

    workers = [threading.Thread(target=worker, args=(i,)) for i in range(threads)]
    start = time.monotonic()
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    return {**sent, "closed_by_server": closed[0], "seconds": time.monotonic() - start}
