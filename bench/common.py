"""Helpers shared by the benchmark scripts: repeated timing with medians (this machine is noisy), Markdown
tables, and for bench_scale.py the libmodbus C tools and ``valve-emulator serve`` as a subprocess."""

from __future__ import annotations

import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path


def median_time(fn: Callable[[], object], *, repeats: int = 7, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs, after ``warmup`` untimed runs (JIT, caches)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def table(rows: list[tuple], header: tuple[str, ...]) -> str:
    """A Markdown table."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


# --- helpers for the scale benchmark (bench_scale.py) ------------------------------------------------------

LIBMODBUS_EXAMPLES = Path("/usr/share/doc/libmodbus-dev/examples")
_C_LINE = re.compile(r"requests=(\d+) errors=(\d+) rate=([\d.]+) p50_us=([\d.]+) p99_us=([\d.]+)")
_LISTENING = re.compile(r"listening on (\S+):(\d+),")


def machine() -> str:
    """One line describing where the figures were measured."""
    import numba
    import numpy
    import pymodbus

    try:
        import uvloop
        uv = f", uvloop {uvloop.__version__}"
    except ImportError:
        uv = ", no uvloop"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{os.cpu_count()} CPU ({cpu}), Linux {platform.release()}, Python {platform.python_version()}, "
            f"numpy {numpy.__version__}, numba {numba.__version__}, pymodbus {pymodbus.__version__}{uv}")


def build_c(source: Path, out: Path) -> Path | None:
    """Compile a libmodbus C program with gcc; ``None`` (and a note on stderr) when that is not possible."""
    if shutil.which("gcc") is None or shutil.which("pkg-config") is None or not source.exists():
        print(f"cannot build {source}: needs gcc, pkg-config and libmodbus-dev", file=sys.stderr)
        return None
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "libmodbus"], capture_output=True, text=True)
    if flags.returncode != 0:
        print(f"cannot build {source}: {flags.stderr.strip()}", file=sys.stderr)
        return None
    cmd = ["gcc", "-O2", "-o", str(out), str(source), *flags.stdout.split(), "-lpthread"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        print(f"cannot build {source}: {done.stderr.strip()}", file=sys.stderr)
        return None
    return out


def c_load(binary: Path, port: int, *, unit: int = 1, connections: int = 1, seconds: float = 3.0,
           nregs: int = 10, host: str = "127.0.0.1") -> subprocess.Popen:
    """Start the libmodbus load client (bench/c/modbus_load.c); read its result with :func:`c_result`."""
    return subprocess.Popen([str(binary), host, str(port), str(unit), str(connections), str(seconds), str(nregs)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def c_result(proc: subprocess.Popen, timeout: float = 120.0) -> dict:
    """``{requests, errors, rate, p50_ms, p99_ms}`` printed by a finished load client."""
    out, err = proc.communicate(timeout=timeout)
    m = _C_LINE.search(out)
    if proc.returncode != 0 or not m:
        raise RuntimeError(f"load client failed ({proc.returncode}): {out.strip()} {err.strip()}")
    n, e, rate, p50, p99 = m.groups()
    return {"requests": int(n), "errors": int(e), "rate": float(rate), "p50_ms": float(p50) / 1e3,
            "p99_ms": float(p99) / 1e3}


def start_serve(*args: str, timeout: float = 300.0) -> tuple[subprocess.Popen, list[int]]:
    """Run ``valve-emulator serve ARGS`` (a user's command line); return it and the port of each process."""
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    processes = 1
    if "--processes" in args and "--process-index" not in args:
        processes = int(args[args.index("--processes") + 1])
    ports: list[int] = []
    deadline = time.monotonic() + timeout
    while len(ports) < processes and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        m = _LISTENING.search(line)
        if m:
            ports.append(int(m.group(2)))
    if len(ports) < processes:
        stop(proc)
        raise RuntimeError(f"valve-emulator serve {' '.join(args)} did not start")
    return proc, ports


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM, then kill after 5 s."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
