"""Modbus RTU throughput against the line's theoretical transaction rate.

    python bench/bench_rtu.py [--seconds 5] [--rounds 3] [--bauds 19200 115200]

``valve-emulator serve --rtu`` runs in its own process on one end of a ``socat`` pty pair (default
config, real physics at time-scale 1); this process is the master on the other end and polls one holding
register (an 8-byte request, a 7-byte answer) back to back, leaving the 3.5-character silence the serial
line specification requires before each request.

The line's limit for that transaction (*MODBUS over Serial Line V1.02* §2.5.1.1): ``T = 15 bytes × 11 bits
/ baud + 2 × t3.5`` (t3.5 = 3.5 characters up to 19200 baud, 1.75 ms above), i.e. 79.4 transactions/s at
19200 8E1 and 203 at 115200. A pty moves bytes instantly, so the time the 15 bytes would spend on a real
wire is added to the measured time of every transaction; the ratio ``T / (measured + wire)`` then says
whether the emulator's frame detection and answer fit in the line's own timing: 1.0 is a device that
waits the t3.5 silence after a request and then answers in zero time. Target: >= 0.9. The emulator
answers a request whose length and CRC are complete without waiting for that silence (as libmodbus does),
so it can exceed 1. Medians over ``--rounds``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import serial

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, table  # noqa: E402

from valve_emulator.device.rtu import SerialSettings, with_crc  # noqa: E402

REQUEST = with_crc(struct.pack(">BBHH", 1, 3, 0, 1))   # read op_pct of unit 1
ANSWER_BYTES = 7


def _pty_pair(folder: Path) -> tuple[subprocess.Popen, str, str]:
    a, b = folder / "ttyA", folder / "ttyB"
    proc = subprocess.Popen([shutil.which("socat") or "socat", f"pty,raw,echo=0,link={a}",
                             f"pty,raw,echo=0,link={b}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 5
    while not (a.exists() and b.exists()):
        if time.monotonic() > deadline:
            raise RuntimeError("socat did not create the pty pair")
        time.sleep(0.02)
    return proc, str(a), str(b)


def _poll(line: serial.Serial, settings: SerialSettings, seconds: float) -> tuple[int, float]:
    """Transactions completed and the time they took (s), polling back to back for ``seconds``."""
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        time.sleep(settings.t35)                          # the master's silence before a request
        line.write(REQUEST)
        answer = line.read(ANSWER_BYTES)
        if len(answer) != ANSWER_BYTES:
            raise RuntimeError(f"no answer at {settings} (got {answer!r})")
        n += 1
    return n, time.perf_counter() - t0


def measure(settings: SerialSettings, seconds: float, rounds: int) -> dict:
    wire = (len(REQUEST) + ANSWER_BYTES) * settings.bits_per_char / settings.baud
    theory = wire + 2 * settings.t35
    ratios, rates = [], []
    with tempfile.TemporaryDirectory() as folder:
        socat, server_end, client_end = _pty_pair(Path(folder))
        server = subprocess.Popen(
            [sys.executable, "-m", "valve_emulator", "serve", "--port", "0", "--rtu", server_end, "--baud",
             str(settings.baud), "--parity", settings.parity, "--stopbits", str(settings.stopbits)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ})
        try:
            line = server.stdout.readline()
            if "listening" not in line:
                raise RuntimeError(f"serve did not start: {line}")
            parity = {"E": serial.PARITY_EVEN, "O": serial.PARITY_ODD, "N": serial.PARITY_NONE}[settings.parity]
            with serial.Serial(client_end, baudrate=settings.baud, parity=parity, stopbits=settings.stopbits,
                               timeout=1.0) as port:   # one open: socat ends the pair when a side closes
                _poll(port, settings, 0.5)                # warm-up
                for _ in range(rounds):
                    n, elapsed = _poll(port, settings, seconds)
                    per = elapsed / n + wire              # the wire time a real line would add
                    rates.append(1 / per)
                    ratios.append(theory / per)
        finally:
            server.terminate()
            server.wait(20)
            socat.terminate()
            socat.wait(5)
    return {"line": str(settings), "theory": 1 / theory, "rate": statistics.median(rates),
            "ratio": statistics.median(ratios), "min ratio": min(ratios)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--bauds", type=int, nargs="+", default=[19200, 115200])
    args = p.parse_args(argv)
    rows = []
    for baud in args.bauds:
        r = measure(SerialSettings(baud=baud), args.seconds, args.rounds)
        rows.append((r["line"], f"{r['theory']:.1f}", f"{r['rate']:.1f}", f"{r['ratio']:.3f}",
                     f"{r['min ratio']:.3f}", "yes" if r["ratio"] >= 0.9 else "NO"))
    print(f"## Modbus RTU throughput (1-register reads, {machine()})\n")
    print(table(rows, ("line", "line limit (transactions/s)", "emulator (median)", "ratio (median)",
                       "ratio (worst round)", ">= 0.9")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
