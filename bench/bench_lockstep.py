"""Lockstep at the wire's speed: what a ``step`` write costs against a plain write and a read, over Modbus TCP.

Run: ``python bench/bench_lockstep.py [--rounds 3] [--requests 2000] [--before /path/to/other/checkout]``.

``valve-emulator serve --lockstep`` runs in its own process (the embedded default device: one loop, no internal
controller, so OP is writable); one raw-socket client in this process (blocking socket, ``TCP_NODELAY``, one
request outstanding, no Modbus library) measures, one request at a time:

- the time to an answer of an FC8 echo (the floor: the wire, the event loop and the client, the server doing
  nothing), of a 10-register read (FC3), of a write of OP (FC6), of ``step`` = 1, 5 and 10 (their ticks run
  before the write is answered) and of FC23 (``step`` = 1 and read PV), each sent back to back, medians per
  round, and the ratios write / read and step / write *of the same round*;
- the steps/s of a scan of read PV + write OP + ``step`` = 1 (three round trips; 1 / the median scan, and over
  the whole run), the time to each of its three answers, the same scan with FC23 (write OP, then one FC23
  request that writes ``step`` and reads PV after the tick: two round trips) and with pymodbus' client, and the
  ticks/s of a client that writes ``step`` = 10 back to back;
- in-process, without socket or client, the server's own work per request (``EmulatorServer.handle``): until the
  answer, and until what the request changes is done; and the two parts of a tick, the loop bank's step and the
  image refresh.

``--before`` serves a second device from another checkout of the project (its code on ``PYTHONPATH``), and each
round measures both servers one after the other, so that a before/after comparison shares the machine's load.
Figures are medians over the rounds with their spread (min–max).

``--answers N [--before CHECKOUT]``: instead of timing, N random request frames (every function code, refused
and malformed ones, steps of 0 to 300 ticks, two roles) answered in-process by a lockstep device of 10 loops on
4 units (a unit without a loop asked too), with and without a custom mA table (without one, a tick steps and
encodes in one compiled call), and by one serving the Modbus float32 CDAB and S7 counts profiles;
prints the SHA-256 of every answer and of both register images after every request, for each checkout: a
faster request path must give the same digest.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))
from common import machine, table  # noqa: E402

STEP = 0xFF10        # the clock's step register (holding 65296)
OP, PV_F32 = 0, 24   # op_pct, pv_f32 of the register map
UNIT = 1


class Serve:
    """``valve-emulator serve --lockstep --port 0`` from checkout ``root``, in a subprocess, for a ``with`` block."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def __enter__(self) -> int:
        env = dict(os.environ, PYTHONPATH=str(self.root))
        self.proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", "--lockstep", "--port", "0"],
                                     stdout=subprocess.PIPE, text=True, env=env, cwd=self.root)
        line = self.proc.stdout.readline()
        if "listening on " not in line:
            self.proc.kill()
            raise RuntimeError(f"serve from {self.root} did not start: {line!r}")
        return int(line.split("listening on ")[1].split(",")[0].rsplit(":", 1)[1])

    def __exit__(self, *exc: object) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=10)
        self.proc.stdout.close()


class Client:
    """One raw Modbus TCP client: a request frame out, its whole answer back, nothing else."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.tid = 0

    def close(self) -> None:
        self.sock.close()

    def request(self, pdu: bytes) -> bytes:
        """Send ``pdu`` to unit 1, return the answer's PDU; an exception answer raises."""
        self.tid = (self.tid + 1) & 0xFFFF
        sock = self.sock
        sock.sendall(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, UNIT) + pdu)
        head = _recv(sock, 7)
        body = _recv(sock, ((head[4] << 8) | head[5]) - 1)
        if body[0] & 0x80:
            raise RuntimeError(f"exception 0x{body[1]:02X} to {pdu.hex()}")
        return body


def _recv(sock: socket.socket, n: int) -> bytes:
    data = sock.recv(n)
    while len(data) < n:
        more = sock.recv(n - len(data))
        if not more:
            raise ConnectionError("server closed the connection")
        data += more
    return data


def read_pdu(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, address, count)


def write_pdu(address: int, value: int) -> bytes:
    return struct.pack(">BHH", 6, address, value)


def fc23_pdu(read_address: int, read_count: int, write_address: int, value: int) -> bytes:
    return struct.pack(">BHHHHBH", 23, read_address, read_count, write_address, 1, 2, value)


def echo_pdu(k: int) -> bytes:
    """FC8 sub-function 0 (return query data): the server answers with the request, changing nothing."""
    return struct.pack(">BHH", 8, 0, k & 0xFFFF)


def op_value(k: int) -> int:
    """An OP write that changes at every scan (40.00 .. 59.99 %), as a controller's output would."""
    return 4000 + k % 2000


def latency(client: Client, pdu_of: Callable[[int], bytes], n: int) -> float:
    """Median seconds from sending a request to its whole answer, over ``n`` requests."""
    times = []
    for k in range(n):
        pdu = pdu_of(k)
        t0 = time.perf_counter()
        client.request(pdu)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def rate(client: Client, scan: Callable[[Client, int], None], n: int) -> float:
    """Scans per second over ``n`` scans: 1 / the median scan's duration (on a machine shared with other jobs
    the mean is mostly the time this process waited for a core)."""
    times = []
    for k in range(n):
        t0 = time.perf_counter()
        scan(client, k)
        times.append(time.perf_counter() - t0)
    return 1.0 / statistics.median(times)


def whole_run_rate(client: Client, scan: Callable[[Client, int], None], n: int) -> float:
    """Scans per second over ``n`` scans: ``n`` / the whole run's duration, waits for a core included."""
    t0 = time.perf_counter()
    for k in range(n):
        scan(client, k)
    return n / (time.perf_counter() - t0)


def scan_three(c: Client, k: int) -> None:
    c.request(read_pdu(PV_F32, 2))
    c.request(write_pdu(OP, op_value(k)))
    c.request(write_pdu(STEP, 1))


def scan_latencies(c: Client, n: int) -> tuple[float, float, float]:
    """Median seconds to the answer of each request of the scan (read PV, write OP, step = 1) over ``n`` scans:
    where a scan's time goes when the requests follow one another as a controller sends them."""
    times: tuple[list[float], list[float], list[float]] = ([], [], [])
    for k in range(n):
        for pdu, out in zip((read_pdu(PV_F32, 2), write_pdu(OP, op_value(k)), write_pdu(STEP, 1)), times):
            t0 = time.perf_counter()
            c.request(pdu)
            out.append(time.perf_counter() - t0)
    return tuple(statistics.median(t) for t in times)


def scan_fc23(c: Client, k: int) -> None:
    c.request(write_pdu(OP, op_value(k)))
    c.request(fc23_pdu(PV_F32, 2, STEP, 1))


def step_ten(c: Client, k: int) -> None:
    c.request(write_pdu(STEP, 10))


def pymodbus_scans(c: Client, n: int) -> float:
    """Scans per second of read PV + write OP + step = 1 with pymodbus' synchronous client (a client that takes
    longer than the raw one to turn an answer into its next request)."""
    from pymodbus.client import ModbusTcpClient

    port = c.sock.getpeername()[1]
    with ModbusTcpClient("127.0.0.1", port=port) as mc:
        times = []
        for k in range(n):
            t0 = time.perf_counter()
            mc.read_holding_registers(PV_F32, count=2, device_id=UNIT)
            mc.write_register(OP, op_value(k), device_id=UNIT)
            mc.write_register(STEP, 1, device_id=UNIT)
            times.append(time.perf_counter() - t0)
        return 1.0 / statistics.median(times)


#: name, unit, ``fn(client, n) -> figure``
CASES: tuple[tuple[str, str, Callable[[Client, int], float]], ...] = (
    ("FC8 echo (the floor: an answer that does nothing)", "µs", lambda c, n: 1e6 * latency(c, echo_pdu, n)),
    ("read 10 registers (FC3)", "µs", lambda c, n: 1e6 * latency(c, lambda k: read_pdu(0, 10), n)),
    ("write OP (FC6)", "µs", lambda c, n: 1e6 * latency(c, lambda k: write_pdu(OP, op_value(k)), n)),
    ("write step = 1 (FC6)", "µs", lambda c, n: 1e6 * latency(c, lambda k: write_pdu(STEP, 1), n)),
    ("write step = 5 (FC6)", "µs", lambda c, n: 1e6 * latency(c, lambda k: write_pdu(STEP, 5), n)),
    ("write step = 10 (FC6)", "µs", lambda c, n: 1e6 * latency(c, lambda k: write_pdu(STEP, 10), n)),
    ("FC23: step = 1 and read PV", "µs", lambda c, n: 1e6 * latency(c, lambda k: fc23_pdu(PV_F32, 2, STEP, 1), n)),
    ("scan: read PV + write OP + step = 1", "steps/s", lambda c, n: rate(c, scan_three, n)),
    ("the same scan, n / the whole run's time", "steps/s", lambda c, n: whole_run_rate(c, scan_three, n)),
    ("scan: write OP + FC23 (step = 1, read PV)", "steps/s", lambda c, n: rate(c, scan_fc23, n)),
    ("step = 10 back to back", "ticks/s", lambda c, n: 10 * rate(c, step_ten, n)),
    ("scan: read PV + write OP + step = 1, pymodbus client", "steps/s", pymodbus_scans),
)


SCAN_PARTS = ("in a scan: read PV", "in a scan: write OP", "in a scan: step = 1")


def measure(port: int, requests: int) -> dict[str, float]:
    """One round of every case against the server on ``port`` (after a short warm-up)."""
    client = Client(port)
    try:
        for _, _, fn in CASES:
            fn(client, 100)
        figures = {name: fn(client, requests) for name, _, fn in CASES}
        figures.update(zip(SCAN_PARTS, (1e6 * t for t in scan_latencies(client, requests))))
        return figures
    finally:
        client.close()


def server_cpu(number: int, repeats: int = 5) -> dict[str, float]:
    """The server's own work per request, µs, in this process (no socket, no client): the best of ``repeats``
    runs of ``number`` requests through ``EmulatorServer.handle``, and the parts of a tick. ``answered`` is
    the time to the answer, ``done`` includes any work a server carries out after it (``settle``, where it has one).
    """
    from valve_emulator.device.runtime import load_server_or_default, with_device
    from valve_emulator.device.server import EmulatorServer
    try:   # a client without credentials: a role since the permission table, ``instructor=False`` before it
        from valve_emulator.device.roles import UNAUTHENTICATED as plain
    except ImportError:
        plain = False

    srv = EmulatorServer(with_device(load_server_or_default(None), lockstep=True))
    settle = getattr(srv, "settle", lambda: None)
    clock = time.perf_counter

    def best(frames: list[bytes], answered: bool) -> float:
        runs = []
        for _ in range(repeats):
            total = 0.0
            for k in range(number):
                t0 = clock()
                srv.handle(frames[k % len(frames)], plain)
                t1 = clock()
                settle()
                total += (t1 if answered else clock()) - t0
            runs.append(total / number)
        return 1e6 * min(runs)

    def frame(pdu: bytes) -> bytes:
        return struct.pack(">HHHB", 1, 0, len(pdu) + 1, UNIT) + pdu

    cases = {"FC8 echo": [frame(echo_pdu(k)) for k in range(100)], "read 10 registers": [frame(read_pdu(0, 10))],
             "write OP": [frame(write_pdu(OP, op_value(k))) for k in range(100)],
             "step = 1": [frame(write_pdu(STEP, 1))], "step = 5": [frame(write_pdu(STEP, 5))],
             "step = 10": [frame(write_pdu(STEP, 10))],
             "FC23 step = 1 + read PV": [frame(fc23_pdu(PV_F32, 2, STEP, 1))]}
    out = {}
    for name, frames in cases.items():
        out[f"{name}: answered"] = best(frames, True)
        out[f"{name}: done"] = best(frames, False)
    device = srv.device
    for name, fn in (("tick: bank.step()", device.bank.step), ("tick: image refresh", device._refresh)):
        out[name] = 1e6 * min(timeit_runs(fn, repeats, number))
    return out


def timeit_runs(fn: Callable[[], object], repeats: int, number: int) -> list[float]:
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        runs.append((time.perf_counter() - t0) / number)
    return runs


def _answers_servers() -> list:
    """The lockstep servers :func:`answers_digest` asks: 10 loops on 4 units, one with a custom mA table, the
    same fleet without it (a tick is then one compiled call that steps and encodes), then the two profiles' maps."""
    from valve_emulator.device.runtime import load_server_or_default, with_device
    from valve_emulator.device.server import EmulatorServer

    servers = [EmulatorServer(_fleet(ma_table)) for ma_table in (True, False)]
    for profile in ("modicon_float_cdab", "s7_analog"):
        config = load_server_or_default(ROOT / "configs" / "profiles" / f"{profile}.yaml")
        servers.append(EmulatorServer(with_device(config, lockstep=True)))
    return servers


def _fleet(ma_table: bool) -> Any:
    """A lockstep fleet of 10 loops on 4 units: noise, a sine disturbance, set-point steps, an integrating plant,
    manual controllers; with ``ma_table`` the second loop has a custom mA table."""
    from valve_emulator.config import server_from_mapping

    table = {"ma_table": [[4.0, 0.0], [12.0, 40.0], [20.0, 100.0]]} if ma_table else {}
    return server_from_mapping({
        "device": {"tick": 0.1, "instructor_writes": True, "lockstep": True},
        "loops": [
            {"unit": 1, "valve": {"S": 5.0, "J": 2.0},
             "plant": {"fopdt": {"gain": 3.0, "tau": 10.0, "delay": 1.0}, "noise": 0.02,
                       "disturbance": {"type": "sine", "amplitude": 2.0, "period": 5.0}},
             "controller": {"kc": 0.2, "ti": 10.0, "sp_steps": [[0.5, 1.0], [3.0, 2.0]]}},
            {"unit": 2, "valve": {"S": 3.0, "J": 1.0, **table},
             "plant": {"integrator": {"gain": 0.1}, "pv0": 50.0}},
        ],
        "fleet": {"count": 8, "loops_per_unit": 4, "seed": 3,
                  "base": {"valve": {"S": 4.0, "J": 1.0, "op0": 45.0},
                           "plant": {"fopdt": {"gain": 1.0, "tau": 4.0, "delay": 0.3}},
                           "controller": {"kc": 0.5, "ti": 5.0, "mode": "manual"}},
                  "vary": {"S": [0.5, 3.0], "gain": [0.5, 2.0]}}})


def _random_pdu(rng: Any, step_heavy: bool) -> bytes:
    """One request PDU: mostly the lockstep path's function codes at addresses near the map, some refused,
    some malformed (a byte cut off or added)."""
    def address() -> int:
        kind = rng.random()
        if kind < 0.3:
            return int(rng.choice([0, 0, 0, 1, 5, 6, 24]))
        if kind < 0.6:
            return int(rng.integers(0, 40))
        if kind < 0.8:
            return int(32 * rng.integers(0, 4) + rng.integers(0, 33))
        return int(rng.choice([STEP, STEP - 1, 0xFF00, 0xFF01, 0xFF02, int(rng.integers(0, 65536))]))

    def value() -> int:
        return int(rng.choice([rng.integers(0, 65536), rng.integers(0, 10001), rng.integers(0, 30000),
                               rng.integers(0, 2), rng.integers(4000, 20001)]))

    fc = int(rng.choice([3, 4, 6, 16, 23, 1, 2, 5, 8, 15, 22, 43, 7, 0x2B],
                        p=[.2, .08, .3, .1, .1, .03, .03, .03, .02, .03, .03, .02, .02, .01]))
    if fc == 6 and step_heavy and rng.random() < 0.4:
        pdu = struct.pack(">BHH", 6, STEP, int(rng.choice([0, 1, 1, 1, 2, 3, 5, 10, int(rng.integers(0, 300))])))
    elif fc in (3, 4, 1, 2):
        pdu = struct.pack(">BHH", fc, address(), int(rng.choice([1, 2, 4, 10, int(rng.integers(0, 130))])))
    elif fc in (6, 5):
        pdu = struct.pack(">BHH", fc, address(), value() if fc == 6 else int(rng.choice([0, 0xFF00, 1])))
    elif fc == 16:
        n = int(rng.integers(1, 5))
        pdu = struct.pack(f">BHHB{n}H", 16, address(), n, 2 * n, *(value() for _ in range(n)))
    elif fc == 23:
        pdu = struct.pack(">BHHHHBH", 23, address(), int(rng.integers(1, 4)), STEP if rng.random() < 0.4
                          else address(), 1, 2, int(rng.integers(0, 4)) if rng.random() < 0.5 else value())
    elif fc == 15:
        pdu = struct.pack(">BHHBB", 15, address(), 2, 1, int(rng.integers(0, 4)))
    elif fc == 22:
        pdu = struct.pack(">BHHH", 22, address(), int(rng.integers(0, 65536)), int(rng.integers(0, 65536)))
    elif fc == 8:
        pdu = struct.pack(">BHH", 8, int(rng.choice([0, 0x0A, 0x0B, 0x0D, 0x0E, 3])), 0)
    elif fc == 43:
        pdu = bytes((43, 14, int(rng.integers(1, 5)), int(rng.integers(0, 8))))
    else:
        pdu = bytes((fc,)) + bytes(rng.integers(0, 256, int(rng.integers(0, 6)), dtype=np.uint8))
    cut = rng.random()
    if cut < 0.03:
        return pdu[:-1] or pdu
    if cut < 0.05:
        return pdu + b"\x00"
    return pdu


def answers_digest(n: int, seed: int = 34) -> dict[str, Any]:
    """SHA-256 of the answers to ``n`` random frames and of the register images after each (see the module doc)."""
    import hashlib

    from valve_emulator.device.roles import INSTRUCTOR, UNAUTHENTICATED

    rng = np.random.default_rng(seed)
    digest = hashlib.sha256()
    codes: dict[str, int] = {}
    for srv in _answers_servers():
        units = sorted(set(srv.units))
        for tid in range(n // 3):
            unit = int(rng.choice(units)) if rng.random() < 0.95 else int(rng.choice([0, 77]))
            frame = struct.pack(">HHHB", tid & 0xFFFF, 0, 0, unit)
            pdu = _random_pdu(rng, step_heavy=True)
            frame = frame[:4] + struct.pack(">HB", len(pdu) + 1, unit) + pdu
            answer = srv.handle(frame, INSTRUCTOR if rng.random() < 0.3 else UNAUTHENTICATED)
            digest.update(answer)
            digest.update(bytes(srv.device.image))
            if srv.device.served is not srv.device.image:
                digest.update(bytes(srv.device.served))
            key = f"0x{answer[8]:02X}" if answer[7] & 0x80 else "answered"
            codes[key] = codes.get(key, 0) + 1
        digest.update(str(srv.device.ticks).encode())
    return {"sha256": digest.hexdigest(), "answers": dict(sorted(codes.items()))}


def answers_digest_of(root: Path, n: int) -> dict[str, Any]:
    """:func:`answers_digest` with checkout ``root``'s code, in a process of its own."""
    env = dict(os.environ, PYTHONPATH=str(root))
    done = subprocess.run([sys.executable, __file__, "--answers-json", str(n)], capture_output=True, text=True,
                          env=env, cwd=root, check=True)
    return json.loads(done.stdout)


def server_cpu_of(root: Path, number: int) -> dict[str, float]:
    """:func:`server_cpu` of checkout ``root``: in this process for this checkout, else in a process of its own
    with that checkout's code."""
    if root == ROOT:
        sys.path.insert(0, str(ROOT))   # this checkout's code, whatever PYTHONPATH says
        return server_cpu(number)
    env = dict(os.environ, PYTHONPATH=str(root))
    done = subprocess.run([sys.executable, __file__, "--server-cpu", str(number)], capture_output=True, text=True,
                          env=env, cwd=root, check=True)
    return json.loads(done.stdout)


def summary(values: list[float]) -> str:
    """Median and spread: ``123 (110–130)``."""
    fmt = "{:,.0f}" if statistics.median(values) >= 100 else "{:.2f}"
    lo, hi = min(values), max(values)
    return f"{fmt.format(statistics.median(values))} ({fmt.format(lo)}–{fmt.format(hi)})"


def ratios(rounds: list[dict[str, float]]) -> list[tuple[str, str]]:
    """The issue's two ratios and the read's and write's over the floor, each taken within one round, then
    summarised over the rounds."""
    def ratio(over: str, under: str) -> str:
        return summary([r[over] / r[under] for r in rounds])

    floor = "FC8 echo (the floor: an answer that does nothing)"
    return [("write OP / read", ratio("write OP (FC6)", "read 10 registers (FC3)")),
            ("step = 1 / write OP", ratio("write step = 1 (FC6)", "write OP (FC6)")),
            ("read / FC8 echo", ratio("read 10 registers (FC3)", floor)),
            ("write OP / FC8 echo", ratio("write OP (FC6)", floor))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="rounds per server (default 3)")
    ap.add_argument("--requests", type=int, default=2000, help="requests (or scans) per case and round")
    ap.add_argument("--before", type=Path, help="another checkout to measure alongside this one, alternately")
    ap.add_argument("--answers", type=int, help="compare the answers to this many random frames instead of timing")
    ap.add_argument("--server-cpu", type=int, help=argparse.SUPPRESS)   # one checkout's, as JSON
    ap.add_argument("--answers-json", type=int, help=argparse.SUPPRESS)   # one checkout's, as JSON
    args = ap.parse_args(argv)
    if args.server_cpu:
        print(json.dumps(server_cpu(args.server_cpu)))
        return 0
    if args.answers_json:
        print(json.dumps(answers_digest(args.answers_json)))
        return 0
    if args.answers:
        roots = {"this checkout": ROOT} if args.before is None else {"before": args.before.resolve(), "after": ROOT}
        digests = {name: answers_digest_of(root, args.answers) for name, root in roots.items()}
        for name, d in digests.items():
            print(f"{name}: {d['sha256']} {d['answers']}")
        same = len({d["sha256"] for d in digests.values()}) == 1
        print("the same answers and images" if same else "ANSWERS OR IMAGES DIFFER")
        return 0 if same else 1
    roots = {"this checkout": ROOT}
    if args.before is not None:
        roots = {"before": args.before.resolve(), "after": ROOT}
    results: dict[str, list[dict[str, float]]] = {name: [] for name in roots}
    print(f"Measured on {machine()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; load average "
          f"{os.getloadavg()[0]:.1f}; {args.rounds} rounds of {args.requests} requests per case.\n")
    cpu: dict[str, list[dict[str, float]]] = {name: [] for name in roots}
    for _ in range(args.rounds):
        for name, root in roots.items():
            with Serve(root) as port:
                results[name].append(measure(port, args.requests))
            cpu[name].append(server_cpu_of(root, min(args.requests, 1000)))
    names = list(roots)
    cases = [(case, unit) for case, unit, _ in CASES] + [(part, "µs") for part in SCAN_PARTS]
    rows = [(case, unit, *(summary([r[case] for r in results[n]]) for n in names)) for case, unit in cases]
    by_server = [ratios(results[n]) for n in names]
    rows += [(label, "ratio", *(r[i][1] for r in by_server)) for i, (label, _) in enumerate(by_server[0])]
    print("## Over Modbus TCP: one raw client, `serve --lockstep` in its own process\n")
    print(table(rows, ("case", "unit", *names)))
    print("\n## The server's own work per request, µs (in-process, best of 5 runs; median over the rounds)\n")
    parts = list(cpu[names[0]][0])
    print(table([(part, *(summary([r[part] for r in cpu[n]]) for n in names)) for part in parts],
                ("request", *names)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
