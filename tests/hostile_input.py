"""Hostile input on every interface of one running emulator: HTTP station, RTU serial line, snapshot files,
SIGHUP with a broken config. Zero crashes, the tick on schedule, normal reads correct afterwards.

The stress is run at full size by ``python bench/bench_interfaces_under_attack.py [--size full|ci]`` (about
ten minutes; it prints the figures) and at :data:`CI` size by ``tests/system/test_hostile_input.py``, which
asserts them; :func:`rewrite_snapshot` also makes the broken files of ``tests/station/test_snapshot_files.py``.

``valve-emulator serve`` runs as a user starts it (its own process; a two-loop config, tick 0.1 s, time-scale
1, ``--web`` with a token, ``--snapshots``, ``--rtu`` on one end of a ``socat`` pty pair at 4,000,000 baud, the
highest rate ``--baud`` takes). This process attacks it, one phase after the other, while a monitor thread
reads the tick register over Modbus TCP every 0.2 s and counts ticks per one-second window:

- ``http``: malformed JSON, wrong types, values no register carries, unknown paths, wrong methods, path tricks
  in snapshot names, wrong tokens -- each must get a 4xx JSON error naming the expected field; 10 MB bodies
  (413); ``slow`` half-open connections (a request line cut short, then silence) held open meanwhile and
  counted when the server closes them. The instructor's view of the state (everything but the moving
  values) must be the same afterwards.
- ``rtu``: frames with a bad CRC, truncated, for a unit not served here, longer than any frame, random bytes,
  in bursts (1 frame, or up to 64 back to back without a silence) each followed by the 3.5-character silence
  and a good request: nothing may answer a corrupted frame, the good request must get the right answer.
- ``snapshots``: files truncated, of another format version, with NaN or infinite numbers, a ring-buffer
  index out of range, of a device with another number of loops or other units, dropped into the snapshot
  folder: each restore must be refused (409) naming the file and what is wrong, and simulated time must not
  jump.
- ``hup``: 10 clients (5 Modbus TCP, 5 HTTP) poll while the config file is replaced by broken versions and
  SIGHUP is sent: the error must name the file, line and key, no request may fail, the running config stays.

"""

from __future__ import annotations

import http.client
import json
import queue
import random
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import serial

from valve_emulator.device.registers import address_of
from valve_emulator.device.rtu import crc16, request_length, with_crc

TOKEN = "hostile-bench-token"
BAUD = 4_000_000
SILENCE = 0.003          # > t3.5 = 1.75 ms above 19200 baud
CONFIG = """\
device:
  tick: 0.1
  max_connections: 64
  instructor_writes: true
loops:
  - unit: 1
    name: FIC101
    valve: {S: 5.0, J: 2.0}
    plant: {num: [3.0], den: [10.0, 1.0], delay: 2.0, pv_range: [-10.0, 10.0]}
    controller: {kc: 0.2, ti: 10.0, sp: 0.0}
  - unit: 2
    name: HIC102
    valve: {S: 3.0, J: 1.0}
    plant: {num: [3.0], den: [10.0, 1.0], pv_range: [-10.0, 10.0]}
"""


@dataclass(frozen=True)
class Sizes:
    """How much of each attack one run sends."""

    http_rounds: int          # rounds of the list of bad requests
    big_bodies: int           # 10 MB bodies
    slow: int                 # slow half-open connections
    slow_hold: float          # seconds they are held (the server's idle timeout is 15 s)
    wrong_tokens: int
    rtu_frames: int           # corrupted RTU frames
    hup_rounds: int           # broken configs sent with SIGHUP (each variant once per round)
    hup_clients: int = 10


FULL = Sizes(http_rounds=200, big_bodies=20, slow=500, slow_hold=20.0, wrong_tokens=1000, rtu_frames=1_000_000,
             hup_rounds=20)
CI = Sizes(http_rounds=2, big_bodies=2, slow=20, slow_hold=0.5, wrong_tokens=20, rtu_frames=1500, hup_rounds=1)


# --- the emulator under attack ------------------------------------------------------------------------------

class Emulator:
    """``valve-emulator serve`` with Modbus TCP, the station and an RTU line; stderr collected line by line."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.config = folder / "plant.yaml"
        self.config.write_text(CONFIG)
        self.snapshots = folder / "snapshots"
        server_end, self.tty = folder / "ttyS", folder / "ttyM"
        self.socat = subprocess.Popen([shutil.which("socat") or "socat", f"pty,raw,echo=0,link={server_end}",
                                       f"pty,raw,echo=0,link={self.tty}"], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL)
        _wait_for(lambda: server_end.exists() and self.tty.exists(), "socat's pty pair")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "valve_emulator", "serve", str(self.config), "--port", "0", "--web", "0",
             "--web-token", TOKEN, "--snapshots", str(self.snapshots), "--rtu", str(server_end), "--baud",
             str(BAUD), "--log-level", "INFO"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.stdout: queue.Queue[str] = queue.Queue()
        self.stderr: list[str] = []
        threading.Thread(target=self._collect, args=(self.proc.stderr, self.stderr), daemon=True).start()
        first = self.proc.stdout.readline() + self.proc.stdout.readline()
        threading.Thread(target=self._collect, args=(self.proc.stdout, self.stdout), daemon=True).start()
        ports = re.findall(r"(?:listening on [\d.]+:|http://127\.0\.0\.1:)(\d+)", first)
        if len(ports) < 2:
            self.close()
            raise RuntimeError(f"serve did not start: {first} {''.join(self.stderr)}")
        self.modbus, self.web = int(ports[0]), int(ports[1])
        # the master's end of the serial line, open for the whole run (socat ends when a side closes)
        self.line = serial.Serial(str(self.tty), baudrate=BAUD, parity=serial.PARITY_EVEN, timeout=0.1)

    @staticmethod
    def _collect(stream, sink) -> None:
        for line in stream:
            (sink.put if isinstance(sink, queue.Queue) else sink.append)(line)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def crashes(self) -> list[str]:
        """stderr lines that mean an unhandled error (a traceback, aiohttp's 'Error handling request')."""
        return [line for line in self.stderr if "Traceback" in line or "Error handling request" in line]

    def close(self) -> None:
        if getattr(self, "line", None) is not None:
            self.line.close()
        for proc in (self.proc, self.socat):
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def _wait_for(ready, what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} did not come up")
        time.sleep(0.02)


class Modbus:
    """A blocking raw Modbus TCP client: ``read(unit, address, count)`` -> register values."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.tid = 0

    def read(self, unit: int, address: int, count: int) -> list[int]:
        self.tid = (self.tid + 1) & 0xFFFF
        self.sock.sendall(struct.pack(">HHHBBHH", self.tid, 0, 6, unit, 3, address, count))
        head = _recv(self.sock, 7)
        body = _recv(self.sock, struct.unpack(">H", head[4:6])[0] - 1)
        if body[0] != 3 or struct.unpack(">H", head[:2])[0] != self.tid:
            raise RuntimeError(f"Modbus read answered {body.hex()}")
        return list(struct.unpack(f">{count}H", body[2:]))

    def close(self) -> None:
        self.sock.close()


def _recv(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed by the server")
        data += chunk
    return data


class TickMonitor:
    """Reads the tick counter every 0.2 s; :meth:`rates` gives the ticks of each one-second window."""

    def __init__(self, port: int) -> None:
        self.samples: list[tuple[float, int]] = []
        self.errors = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(port,), daemon=True)
        self._thread.start()

    def _run(self, port: int) -> None:
        client = Modbus(port)
        while not self._stop.wait(0.2):
            try:
                hi, lo = client.read(1, address_of("tick"), 2)
                self.samples.append((time.monotonic(), hi << 16 | lo))
            except (OSError, RuntimeError):
                self.errors += 1
                client = Modbus(port)
        client.close()

    def stop(self) -> list[float]:
        self._stop.set()
        self._thread.join()
        return self.rates()

    def rates(self) -> list[float]:
        """Ticks per second over consecutive one-second windows (each between two samples ~1 s apart)."""
        out, start = [], self.samples[0] if self.samples else None
        for t, tick in self.samples[1:]:
            if t - start[0] >= 1.0:
                out.append((tick - start[1]) / (t - start[0]))
                start = (t, tick)
        return out


@contextmanager
def monitored(emu: Emulator, figures: dict, *, at_least: float = 2.5):
    """Run the block under the tick monitor, for ``at_least`` seconds (so that even a short phase has tick
    windows); put the tick figures into ``figures``."""
    monitor = TickMonitor(emu.modbus)
    t0 = time.monotonic()
    try:
        yield
    finally:
        time.sleep(max(0.0, at_least - (time.monotonic() - t0)))
        rates = monitor.stop()
        figures.update(seconds=round(time.monotonic() - t0, 1), tick_min=min(rates, default=float("nan")),
                       tick_max=max(rates, default=float("nan")), tick_windows=len(rates),
                       tick_off=sum(not 9.0 <= r <= 11.0 for r in rates), monitor_errors=monitor.errors)


# --- HTTP ----------------------------------------------------------------------------------------------------

J = {"Content-Type": "application/json", "Authorization": f"Bearer {TOKEN}"}
#: (method, path, body, expected status, expected field); body bytes or a JSON-able value
BAD_REQUESTS = [
    ("POST", "/api/loops/2", {"op": 1e308}, 409, "op"),
    ("POST", "/api/loops/1", {"sp": -1e308}, 409, "sp"),
    ("POST", "/api/loops/1", {"op": "50"}, 400, "op"),
    ("POST", "/api/loops/1", {"mode": ["auto"]}, 400, "mode"),
    ("POST", "/api/loops/1", {"sp": 1, "op": 2}, 400, "body"),
    ("POST", "/api/loops/1", {"valve": 1}, 400, "valve"),
    ("POST", "/api/loops/abc", {"mode": "auto"}, 400, "unit"),
    ("POST", "/api/loops/99", {"mode": "auto"}, 404, "unit"),
    ("POST", "/api/speed", {"time_scale": "fast"}, 400, "time_scale"),
    ("POST", "/api/speed", {"time_scale": -1}, 400, "time_scale"),
    ("POST", "/api/malfunctions", {"unit": 1, "kind": "stiction", "S": -1}, 400, "S"),
    ("POST", "/api/malfunctions", {"unit": 1, "kind": "noise", "std": 1e308}, 400, "std"),
    ("POST", "/api/malfunctions", {"unit": True, "kind": "seize"}, 400, "unit"),
    ("POST", "/api/malfunctions", {"unit": 1, "kind": "meltdown"}, 400, "kind"),
    ("POST", "/api/reveal", {"unit": 1, "mv": "yes"}, 400, "mv"),
    ("POST", "/api/scenario", {"yaml": "[" * 100_000}, 400, "scenario"),
    ("POST", "/api/scenario", {"yaml": 5}, 400, "yaml"),
    ("POST", "/api/snapshots", {"name": "../../etc/passwd"}, 400, "name"),
    ("POST", "/api/snapshots", {"name": "/etc/passwd"}, 400, "name"),
    ("POST", "/api/snapshots", {"name": "a\x00b"}, 400, "name"),
    ("POST", "/api/snapshots", {"name": 7}, 400, "name"),
    ("POST", "/api/snapshots/..%2F..%2Fetc%2Fpasswd/restore", {}, 400, "name"),
    ("POST", "/api/snapshots/%2Fetc%2Fpasswd/restore", {}, 400, "name"),
    ("POST", "/api/snapshots/a%00b/restore", {}, 400, "name"),
    ("DELETE", "/api/snapshots/..%2Fplant.yaml", None, 400, "name"),
    ("DELETE", "/api/snapshots/%2Ftmp%2Fx", None, 400, "name"),
    ("POST", "/api/freeze", b"{", 400, "body"),
    ("POST", "/api/freeze", b"[" * 100_000 + b"]" * 100_000, 400, "body"),
    ("POST", "/api/speed", b'{"time_scale": NaN}', 400, "body"),
    ("POST", "/api/speed", b'{"time_scale": Infinity}', 400, "body"),
    ("POST", "/api/session", b"\xff\xfe\x00", 400, "body"),
    ("POST", "/api/run", b"[]", 400, "body"),
    ("GET", "/api/nope", None, 404, "path"),
    ("GET", "/../../etc/passwd", None, 404, "path"),
    ("GET", "/static/..%2F..%2Fapp.py", None, 404, "path"),
    ("POST", "/api/state", {}, 405, "method"),
    ("GET", "/api/state?units=1e308", None, 400, "units"),
    ("GET", "/api/stream?rate=nan", None, 400, "rate"),
]


def _request(port: int, method: str, path: str, body=None, headers=J, timeout: float = 30.0):
    """``(status, parsed JSON or None)`` of one request on a fresh connection."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        data = body if isinstance(body, bytes) or body is None else json.dumps(body).encode()
        conn.request(method, path, body=data, headers=headers)
        resp = conn.getresponse()
        raw = resp.read()
        is_json = resp.getheader("Content-Type", "").startswith("application/json")
        return resp.status, json.loads(raw) if is_json else None
    finally:
        conn.close()


def _steady(port: int) -> dict:
    """The instructor's state less what moves by itself (PV, OP, MV, time, tick, score ...)."""
    state = _request(port, "GET", "/api/state")[1]
    keep = ("unit", "mode", "sp", "S", "J", "load", "noise", "sensor_bias", "sensor_stuck", "mv_revealed")
    snaps = _request(port, "GET", "/api/snapshots")[1]
    return {"loops": [{**{k: lp[k] for k in keep}, "fault": lp["status"]["fault"]} for lp in state["loops"]],
            "time_scale": state["time_scale"],
            "running": state["running"], "malfunctions": state["malfunctions"],
            "snapshots": sorted(s["name"] for s in snaps["snapshots"])}


def _slow_connections(port: int, n: int) -> list[socket.socket]:
    """``n`` connections that send half a request line and then nothing."""
    socks = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.sendall(b"POST /api/speed HTTP/1.1\r\nHost: x\r\nContent-Ty")
        s.setblocking(False)
        socks.append(s)
    return socks


def _closed_by_server(socks: list[socket.socket]) -> int:
    closed = 0
    for s in socks:
        try:
            closed += s.recv(1) == b""
        except BlockingIOError:
            pass
        except OSError:
            closed += 1
    return closed


def http_phase(emu: Emulator, sizes: Sizes) -> dict:
    port = emu.web
    figures: dict = {"phase": "http"}
    before = _steady(port)
    wrong_status, not_json, wrong_field, normal, normal_failed, requests = 0, 0, 0, 0, 0, 0
    with monitored(emu, figures):
        slow = _slow_connections(port, sizes.slow)
        t_slow = time.monotonic()
        rng = random.Random(3)
        checks = [*BAD_REQUESTS * sizes.http_rounds,
                  *[("POST", "/api/snapshots", b'{"name": "' + b"a" * (10 << 20) + b'"}', 413, "body")]
                  * sizes.big_bodies]
        rng.shuffle(checks)
        for k, (method, path, body, status, field) in enumerate(checks):
            got, answer = _request(port, method, path, body)
            requests += 1
            wrong_status += got != status
            not_json += answer is None
            wrong_field += answer is not None and answer.get("field") != field
            if (got, (answer or {}).get("field")) != (status, field):
                figures.setdefault("unexpected", []).append((method, path[:60], got, answer))
            if k % 50 == 0:   # a normal client meanwhile
                normal += 1
                normal_failed += _request(port, "GET", "/api/state?view=trainee")[0] != 200
        for k in range(sizes.wrong_tokens):
            given = TOKEN[:-1] + chr(ord("A") + k % 26) if k % 2 else TOKEN[: k % len(TOKEN)]
            got, answer = _request(port, "POST", "/api/malfunctions", {"unit": 1, "kind": "seize"},
                                   headers={**J, "Authorization": f"Bearer {given}"})
            requests += 1
            wrong_status += got != 401
            wrong_field += answer is None or answer.get("field") != "token"
            if (got, (answer or {}).get("field")) != (401, "token"):
                figures.setdefault("unexpected", []).append(("token", given, got, answer))
        time.sleep(max(0.0, sizes.slow_hold - (time.monotonic() - t_slow)))
        normal += 1
        normal_failed += _request(port, "GET", "/api/state?view=trainee")[0] != 200
        figures["slow_closed_by_server"] = _closed_by_server(slow)
        for s in slow:
            s.close()
    figures.update(requests=requests, wrong_status=wrong_status, not_json=not_json, wrong_field=wrong_field,
                   normal=normal, normal_failed=normal_failed, slow=sizes.slow, big_bodies=sizes.big_bodies,
                   unchanged=_steady(port) == before)
    return figures


# --- RTU -----------------------------------------------------------------------------------------------------

GOOD = with_crc(struct.pack(">BBHH", 1, 3, address_of("S"), 2))   # S and J of unit 1: they do not move
#: A master that gets no answer within the line's timeout (0.1 s) waits this long and asks again. On a pty the
#: silence before the good request exists only in time: when socat or the server is not scheduled for longer
#: than SILENCE (this machine is shared), the burst and the request arrive in one read, as one frame with a
#: bad CRC, and are rightly dropped; and an answer can come after the timeout. ``good_retried`` counts the
#: retries, ``good_late`` answers that came after it, ``good_wrong`` wrong or missing answers (1 s after the
#: retry), ``answered_corrupted`` anything else the line carried back.
RETRY = 0.02


def _copies(data: bytes, answer: bytes) -> bool:
    """Is ``data`` one or more copies of ``answer``?"""
    return bool(data) and len(data) % len(answer) == 0 and data == answer * (len(data) // len(answer))


def _ask_good(line: serial.Serial, expected: bytes, figures: dict) -> None:
    """Send the good request and check its answer (see RETRY)."""
    line.write(GOOD)
    got = line.read(len(expected))
    if got == expected:
        return
    figures["good_retried"] += 1
    time.sleep(RETRY)
    line.write(GOOD)
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline and not _copies(got, expected):
        got += line.read(max(1, line.in_waiting))
    figures["good_wrong"] += not _copies(got, expected)


def _stray_bytes(line: serial.Serial, expected: bytes, figures: dict) -> None:
    """Whatever came back after a burst of corrupted frames: a late answer to a good request, or a reply to
    a corrupted frame (which must never happen)."""
    if not line.in_waiting:
        return
    got = line.read(line.in_waiting)
    time.sleep(RETRY)
    got += line.read(line.in_waiting)
    if _copies(got, expected):
        figures["good_late"] += 1
    else:
        figures["answered_corrupted"] += 1
        figures.setdefault("stray", []).append(got.hex()[:80])


def corrupted_frames(rng: random.Random):
    """Endless corrupted frames: (kind, bytes); none is a frame this server may answer."""
    kinds = ("bad_crc", "truncated", "wrong_unit", "overlong", "random")
    while True:
        kind = rng.choice(kinds)
        request = with_crc(struct.pack(">BBHH", rng.choice((1, 2)), rng.choice((3, 4, 6)), rng.randrange(64),
                                       rng.randrange(1, 10)))
        if kind == "bad_crc":
            frame = request[:-1] + bytes((request[-1] ^ rng.randrange(1, 256),))
        elif kind == "truncated":
            frame = request[: rng.randrange(1, len(request))]
        elif kind == "wrong_unit":   # a good frame for a unit not on this line: a slave stays silent
            frame = with_crc(bytes((rng.randrange(3, 248),)) + request[1:-2])
        elif kind == "overlong":
            frame = rng.randbytes(rng.randrange(257, 600))
        else:
            frame = rng.randbytes(rng.randrange(1, 40))
        if kind != "wrong_unit" and len(frame) >= 4 and crc16(frame) == 0:
            frame = frame[:-1] + bytes((frame[-1] ^ 1,))
        yield kind, frame


def _burst(frames, size: int) -> bytes:
    burst = b"".join(next(frames)[1] for _ in range(size))
    if request_length(burst) == len(burst) and crc16(burst) == 0 and burst[0] in (1, 2):
        burst += b"\x00"   # the concatenation happens to be a good frame: spoil it
    return burst


def rtu_phase(emu: Emulator, sizes: Sizes, *, max_burst: int = 64) -> dict:
    figures: dict = {"phase": "rtu", "frames": 0, "bytes": 0, "bursts": 0, "answered_corrupted": 0,
                     "good_retried": 0, "good_late": 0, "good_wrong": 0}
    rng = random.Random(11)
    frames = corrupted_frames(rng)
    line = emu.line
    with monitored(emu, figures):
        time.sleep(SILENCE)
        line.write(GOOD)
        expected = line.read(9)
        figures["good_reference"] = expected.hex()
        while figures["frames"] < sizes.rtu_frames:
            size = 1 if rng.random() < 0.5 else rng.randrange(2, max_burst + 1)
            size = min(size, sizes.rtu_frames - figures["frames"])
            burst = _burst(frames, size)
            line.write(burst)
            time.sleep(SILENCE)
            figures["frames"] += size
            figures["bytes"] += len(burst)
            figures["bursts"] += 1
            _stray_bytes(line, expected, figures)
            _ask_good(line, expected, figures)
            time.sleep(SILENCE / 2)
    figures["good_ok"] = len(expected) == 9 and crc16(expected) == 0
    return figures


# --- snapshot files ----------------------------------------------------------------------------------------

def rewrite_snapshot(src: Path, dst: Path, *, header=None, arrays=None, edit=lambda text: text) -> None:
    """A copy of snapshot file ``src`` at ``dst`` with header fields and arrays replaced, the header's JSON
    text passed through ``edit``."""
    with np.load(src) as data:
        head = json.loads(str(data["__header__"]))
        saved = {k: data[k] for k in data.files if k != "__header__"}
    head.update(header or {})
    saved.update(arrays or {})
    with dst.open("wb") as f:
        np.savez(f, __header__=np.array(edit(json.dumps(head))), **saved)


def broken_snapshots(good: Path, folder: Path) -> dict[str, str]:
    """Write broken copies of ``good`` into ``folder``: name -> what the refusal must say."""
    (folder / "truncated.npz").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    rewrite_snapshot(good, folder / "version.npz", header={"format": 2})
    rewrite_snapshot(good, folder / "infinite.npz", header={"time": 12345.5},
                     edit=lambda t: t.replace("12345.5", "1e999"))
    with np.load(good) as data:
        x = data["bank:_plant/_x"]
        head = json.loads(str(data["__header__"]))
    rewrite_snapshot(good, folder / "nan.npz", arrays={"bank:_plant/_x": np.full_like(x, np.nan)})
    rewrite_snapshot(good, folder / "inf.npz", arrays={"bank:_plant/_x": np.full_like(x, np.inf)})
    rewrite_snapshot(good, folder / "head.npz", arrays={"bank:_plant/_head": np.array([10**9])})
    config = head["device"]["config"]
    more = {**config, "units": [*config["units"], 3], "n": config["n"] + 1}
    rewrite_snapshot(good, folder / "loops.npz", header={"device": {**head["device"], "config": more}})
    rewrite_snapshot(good, folder / "units.npz", header={"device": {**head["device"],
                                                            "config": {**config, "units": [7, 8]}}})
    return {"truncated": "not a readable snapshot file", "version": "snapshot format 2",
            "infinite": "'time' is inf", "nan": "state field _plant/_x holds nan",
            "inf": "state field _plant/_x holds inf", "head": "state field _plant/_head",
            "loops": "another configuration", "units": "another configuration"}


def snapshot_phase(emu: Emulator, sizes: Sizes) -> dict:
    port = emu.web
    figures: dict = {"phase": "snapshots", "refused": 0, "wrong": 0, "time_jumped": 0}
    with monitored(emu, figures):
        assert _request(port, "POST", "/api/snapshots", {"name": "good"})[0] == 201
        expected = broken_snapshots(emu.snapshots / "good.npz", emu.snapshots)
        before = {k: v for k, v in _steady(port).items() if k != "snapshots"}   # the files are listed once read
        for name, what in expected.items():
            t0 = _request(port, "GET", "/api/state")[1]["time"]
            status, answer = _request(port, "POST", f"/api/snapshots/{name}/restore", {})
            t1 = _request(port, "GET", "/api/state")[1]["time"]
            ok = status == 409 and answer and str(emu.snapshots / f"{name}.npz") in answer["error"] \
                and what in answer["error"]
            figures["refused"] += bool(ok)
            figures["wrong"] += not ok
            figures["time_jumped"] += t1 < t0
            if not ok:
                figures.setdefault("answers", []).append((name, status, answer))
        figures["files"] = len(expected)
        figures["unchanged"] = {k: v for k, v in _steady(port).items() if k != "snapshots"} == before
        for name in (*expected, "good"):
            _request(port, "DELETE", f"/api/snapshots/{name}")
    return figures


# --- SIGHUP with a broken config ---------------------------------------------------------------------------

#: (text replaced, replacement, line and key the error must name)
BROKEN_CONFIGS = [
    ("max_connections: 64", "max_connections: 0", 3, "device.max_connections"),
    ("tick: 0.1", "tick: -1", 2, "device.tick"),
    ("S: 5.0", "S: fast", 8, "loops[0].valve.S"),
    ("instructor_writes: true", "instructor_writes: true\n  colour: red", 5, "device.colour"),
]


def _poller(emu: Emulator, kind: str, stop: threading.Event, counts: dict) -> None:
    modbus = Modbus(emu.modbus) if kind == "modbus" else None
    expected = None
    while not stop.is_set():
        try:
            if modbus is not None:
                value = modbus.read(1, address_of("S"), 2)
            else:
                status, state = _request(emu.web, "GET", "/api/state?view=trainee")
                value = (status, state["n_loops"])
            expected = expected or value
            counts["ok" if value == expected else "wrong"] += 1
        except (OSError, RuntimeError, KeyError, TypeError):
            counts["failed"] += 1
        time.sleep(0.01)
    if modbus is not None:
        modbus.close()


def _next_stderr(emu: Emulator, start: int, needle: str, timeout: float = 10.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for line in emu.stderr[start:]:
            if needle in line:
                return line
        time.sleep(0.02)
    return ""


def hup_phase(emu: Emulator, sizes: Sizes) -> dict:
    figures: dict = {"phase": "hup", "reloads": 0, "named": 0, "kept": 0}
    counts = {"ok": 0, "wrong": 0, "failed": 0}
    stop = threading.Event()
    kinds = ["modbus", "http"] * (sizes.hup_clients // 2)
    pollers = [threading.Thread(target=_poller, args=(emu, kind, stop, counts)) for kind in kinds]
    with monitored(emu, figures):
        for t in pollers:
            t.start()
        for _ in range(sizes.hup_rounds):
            for old, new, line_no, key in BROKEN_CONFIGS:
                emu.config.write_text(CONFIG.replace(old, new))
                start = len(emu.stderr)
                emu.proc.send_signal(signal.SIGHUP)
                line = _next_stderr(emu, start, "config reload failed")
                named = f"{emu.config}:{line_no}: " in line and key in line
                figures["reloads"] += 1
                figures["named"] += named
                figures["kept"] += "keeping the running config" in line
                if not named:
                    figures.setdefault("messages", []).append(line.strip())
        emu.config.write_text(CONFIG)
        emu.proc.send_signal(signal.SIGHUP)
        figures["good_reload"] = _reloaded(emu)
        stop.set()
        for t in pollers:
            t.join()
    figures.update(clients=len(pollers), requests=sum(counts.values()), **counts)
    return figures


def _reloaded(emu: Emulator, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if "reloaded" in emu.stdout.get(timeout=0.1):
                return True
        except queue.Empty:
            pass
    return False


# --- afterwards --------------------------------------------------------------------------------------------

def normal_reads(emu: Emulator) -> dict:
    """Modbus, HTTP and RTU reads of values that do not move: S and J as configured."""
    client = Modbus(emu.modbus)
    s_j = client.read(1, address_of("S"), 2)
    client.close()
    status, state = _request(emu.web, "GET", "/api/state")
    time.sleep(SILENCE)
    emu.line.write(GOOD)
    rtu = emu.line.read(9)
    return {"modbus_ok": s_j == [500, 200], "http_ok": status == 200 and state["loops"][0]["S"] == 5.0,
            "rtu_ok": rtu == with_crc(bytes((1, 3, 4)) + struct.pack(">HH", 500, 200))}


PHASES = {"http": http_phase, "rtu": rtu_phase, "snapshots": snapshot_phase, "hup": hup_phase}


def run(sizes: Sizes, phases=tuple(PHASES), *, progress=lambda figures: None) -> list[dict]:
    """Start the emulator, run ``phases`` at ``sizes``, check it afterwards; one figures dict per phase plus
    a last one (``phase: after``) with the crash check and the normal reads. ``progress(figures)`` is called
    as each phase ends."""
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        emu = Emulator(Path(tmp))
        try:
            for name in phases:
                out.append(PHASES[name](emu, sizes))
                progress(out[-1])
            out.append({"phase": "after", "alive": emu.alive(), "crashes": len(emu.crashes()), **normal_reads(emu)})
        finally:
            emu.close()
    return out
