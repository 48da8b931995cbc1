"""The testing kit's clocks: the manual clock's simulated hour, and lockstep steps per second over Modbus TCP.

    python bench/bench_testing.py [--rounds 5] [--steps 3000]

1. Manual clock, the embedded default device (one loop, tick 0.1 s): wall time of ``await emu.advance(3600)``
   (36,000 ticks), medians over ``--rounds``. Once as a test usually runs it (nothing but the loop acts between
   the ticks, so they run in compiled batches) and once with a ramped malfunction running all hour (then every
   tick runs on its own: the ramp sets its quantity each tick). Target: <= 2 s.
2. Lockstep over Modbus TCP against ``valve-emulator serve --lockstep`` in its own process: ``--steps`` scans of a
   client doing write OP + write ``step`` (1 tick) + read PV, one request outstanding at a time; steps per second,
   medians over ``--rounds``. Clients: pymodbus' sync ``ModbusTcpClient``; the same with write ``step`` + read PV
   as one FC23 request (the server writes first, runs the ticks, then reads); a plain-socket client that sends
   the three requests of a scan in one segment (the server answers pipelined requests in order); and the Node program
   tests/node/pi_lockstep.js (npm modbus-serial; needs ``npm ci`` in tests/node). Target (Python): >= 2,000.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STEP = 65296


def manual_hour(rounds: int, ramp: bool) -> float:
    """Median wall seconds of one simulated hour on the manual clock."""
    from valve_emulator.testing import Emulator

    async def run() -> list[float]:
        times = []
        async with Emulator() as emu:
            await emu.advance(1.0)   # compiled kernels warm
            for _ in range(rounds):
                if ramp:
                    emu.inject("load", flow=5.0, ramp=3600.0)
                t0 = time.perf_counter()
                await emu.advance(3600.0)
                times.append(time.perf_counter() - t0)
        return times

    return statistics.median(asyncio.run(run()))


class Serve:
    """``valve-emulator serve --lockstep --port 0`` in a subprocess, for a ``with`` block."""

    def __enter__(self) -> int:
        self.proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", "--lockstep", "--port", "0"],
                                     stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        return int(line.split("listening on ")[1].split(",")[0].rsplit(":", 1)[1])

    def __exit__(self, *exc: object) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=10)
        self.proc.stdout.close()


def pymodbus_steps(port: int, steps: int) -> float:
    from pymodbus.client import ModbusTcpClient

    with ModbusTcpClient("127.0.0.1", port=port) as c:
        t0 = time.perf_counter()
        for k in range(steps):
            c.write_register(0, 4000 + k % 2000, device_id=1)
            c.write_register(STEP, 1, device_id=1)
            c.read_holding_registers(24, count=2, device_id=1)
        return steps / (time.perf_counter() - t0)


def fc23_steps(port: int, steps: int) -> float:
    """Write OP (FC6), then write step and read PV in one FC23 request (written first, read after the ticks)."""
    from pymodbus.client import ModbusTcpClient

    with ModbusTcpClient("127.0.0.1", port=port) as c:
        t0 = time.perf_counter()
        for k in range(steps):
            c.write_register(0, 4000 + k % 2000, device_id=1)
            c.readwrite_registers(read_address=24, read_count=2, write_address=STEP, values=[1], device_id=1)
        return steps / (time.perf_counter() - t0)


def socket_steps(port: int, steps: int) -> float:
    """Write OP, write step, read PV sent together; the three answers (12 + 12 + 13 bytes) read back."""
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        t0 = time.perf_counter()
        for k in range(steps):
            s.sendall(struct.pack(">HHHBBHH", 1, 0, 6, 1, 6, 0, 4000 + k % 2000)
                      + struct.pack(">HHHBBHH", 2, 0, 6, 1, 6, STEP, 1)
                      + struct.pack(">HHHBBHH", 3, 0, 6, 1, 3, 24, 2))
            need = 12 + 12 + 13
            while need:
                need -= len(s.recv(need))
        return steps / (time.perf_counter() - t0)


def node_steps(port: int, steps: int) -> float | None:
    script = ROOT / "tests" / "node" / "pi_lockstep.js"
    if not (ROOT / "tests" / "node" / "node_modules").is_dir():
        print("node: run `npm ci` in tests/node first", file=sys.stderr)
        return None
    out = subprocess.run(["node", str(script), "--port", str(port), "--iterations", str(steps), "--ticks", "1"],
                         capture_output=True, text=True, timeout=600)
    if out.returncode != 0:
        print(out.stderr, file=sys.stderr)
        return None
    return steps / json.loads(out.stdout)["seconds"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--steps", type=int, default=3000)
    args = p.parse_args()
    print(f"Measured on {machine()}; medians of {args.rounds} rounds.\n")
    rows = [("as a test runs it (batched ticks)", f"{manual_hour(args.rounds, ramp=False):.2f}"),
            ("a ramp running all hour (tick by tick)", f"{manual_hour(args.rounds, ramp=True):.2f}")]
    print("Manual clock, one loop, one simulated hour (36,000 ticks of 0.1 s); target <= 2 s:\n")
    print(table(rows, ("case", "wall s")) + "\n")
    clients = (("Python, pymodbus ModbusTcpClient", pymodbus_steps),
               ("Python, pymodbus, write step + read PV as one FC23 request", fc23_steps),
               ("Python, plain socket, the scan's 3 requests in one segment", socket_steps),
               ("Node 20, npm modbus-serial (tests/node/pi_lockstep.js)", node_steps))
    rows = []
    for name, fn in clients:
        figures = []
        for _ in range(args.rounds):
            with Serve() as port:
                fn(port, 200)   # warm: connection, kernels
                figure = fn(port, args.steps)
            if figure is None:
                break
            figures.append(figure)
        rows.append((name, f"{statistics.median(figures):,.0f}" if figures else "n/a"))
    print(f"Lockstep over Modbus TCP (serve --lockstep in its own process), {args.steps} scans of write OP + "
          f"write step (1 tick) + read PV; target >= 2,000 steps/s for Python:\n")
    print(table(rows, ("client", "steps/s")))


if __name__ == "__main__":
    main()
