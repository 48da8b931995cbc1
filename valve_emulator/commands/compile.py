"""``valve-emulator compile [--only PART ...]``: compile the numba kernels ahead, into the kernel cache.

Every command compiles the kernels it uses on its first run and caches them (see :mod:`valve_emulator._cache`):
about 10 s before the first ``diagnose`` gets going. Run this once after installing (or while building a
container image) and the first ``diagnose``, ``simulate`` or ``serve`` loads its kernels from the cache like
every later run.

It compiles by running each part's own code on small inputs — a short simulated loop written to a CSV file
and diagnosed from it with and without a model, a simulation, a few device ticks — so the kernels are compiled
for exactly the argument types a real run passes them, and a new kernel is covered without a list to keep.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

NAME = "compile"
HELP = "compile the numba kernels ahead into the kernel cache, so the first diagnose/simulate/serve does not"

PARTS = ("diagnose", "simulate", "serve")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--only", action="append", choices=PARTS, metavar="PART",
                   help=f"compile only what PART uses ({', '.join(PARTS)}; repeatable; default: all)")


def _diagnose() -> None:
    """A short concealed-stiction loop, read back from CSV and diagnosed as plant data and against a model."""
    import valve_emulator as ve
    from valve_emulator.benchmark.cases import CASES, generate
    from valve_emulator.recordings.recording import write_csv

    case = CASES[0]
    rec, nominal, _ = generate(case, duration=600 + case.cut)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "loop.csv"
        write_csv(rec, path)
        ve.diagnose(path)
        ve.diagnose(path, nominal)


def _simulate() -> None:
    """The default device's first loop, simulated offline for a minute, and the valve alone on a ramp."""
    import numpy as np

    from valve_emulator.device.runtime import load_server_or_default
    from valve_emulator.physics import stiction
    from valve_emulator.simulation.loop import simulate_loop

    simulate_loop(load_server_or_default(None).loops[0], 60.0)
    stiction.simulate(np.linspace(0.0, 50.0, 200), S=3.0, J=1.0)


def _serve() -> None:
    """The default device (its loop bank and register image), advanced a few ticks without a network: some in
    one compiled run, as a quiet ``advance`` runs them, and one on its own, as a tick or a lockstep ``step`` = 1;
    then the register codec's plain pass (:func:`~valve_emulator.device.registers.encode`), which encodes any
    state that is not a loop bank (the testing kit's doubles, a caller's own arrays) from the same values."""
    from types import SimpleNamespace

    from valve_emulator.device.registers import encode
    from valve_emulator.device.runtime import load_server_or_default
    from valve_emulator.device.tick import QUIET_MIN, Device

    device = Device.from_config(load_server_or_default(None), time_scale=0.0)
    device.advance(QUIET_MIN)
    device.advance(1)
    bank = device.bank
    names = ("op", "mv", "flow", "pv", "sp", "kc", "ti", "td", "S", "J", "load", "noise_std", "stuck", "sat_low",
             "sat_high", "has_controller", "auto", "frozen")
    encode(SimpleNamespace(**{name: getattr(bank, name) for name in names}), device.scaling, tick=1, overruns=0,
           time=0.1)


_WORK = {"diagnose": _diagnose, "simulate": _simulate, "serve": _serve}


def kernel_cache_stats() -> dict[str, tuple[int, int]]:
    """``module.name`` → (loaded from the cache, compiled) of every compiled kernel of the package imported in
    this process (numba's cache hits and misses), each kernel once however many modules import it."""
    from numba.core.registry import CPUDispatcher

    kernels = {id(k): k for m in list(sys.modules.values())
               if (getattr(m, "__name__", "") or "").startswith("valve_emulator")
               for k in vars(m).values() if isinstance(k, CPUDispatcher)}
    return {f"{k.py_func.__module__}.{k.py_func.__qualname__}": (sum(k.stats.cache_hits.values()),
                                                                  sum(k.stats.cache_misses.values()))
            for k in kernels.values()}


def run(args: argparse.Namespace) -> int:
    from valve_emulator._cache import cache_dir

    parts = [p for p in PARTS if not args.only or p in args.only]
    start = time.perf_counter()
    for part in parts:
        t = time.perf_counter()
        _WORK[part]()
        print(f"{part}: {time.perf_counter() - t:.1f} s", file=sys.stderr, flush=True)
    n, seconds = sum(m for _, m in kernel_cache_stats().values()), time.perf_counter() - start
    if n:
        print(f"compiled {n} kernel(s) of {', '.join(parts)} in {seconds:.1f} s into {cache_dir()}")
    else:
        print(f"nothing to compile: the kernels of {', '.join(parts)} were already in {cache_dir()} ({seconds:.1f} s)")
    return 0
