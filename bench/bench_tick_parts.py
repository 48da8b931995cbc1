"""Where a tick of a whole plant goes: building it, and each part of one tick, for a fleet of loops.

The fleet is ``bench_scale.py``'s (varied S, J, gain and dead time, first-order plants under PI, 500 loops per
unit id). Printed, medians of ``--repeat`` calls: loading the configuration (expanding the fleet), building the
server (loop bank, register image, units), and of one tick: the stiction kernel, the controllers, the plants,
the whole bank step (those three, plus the set points, disturbances and noise), and encoding every register
into the image. Run::

    python bench/bench_tick_parts.py [--loops 100000] [--repeat 51]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scale import _warm_up, fleet_mapping  # noqa: E402
from common import machine, median_time, table  # noqa: E402

from valve_emulator.config import server_from_mapping  # noqa: E402
from valve_emulator.device.server import EmulatorServer  # noqa: E402
from valve_emulator.physics.controller import pid_step_kernel  # noqa: E402
from valve_emulator.physics.plant import plant_step_kernel  # noqa: E402
from valve_emulator.physics.stiction import stiction_step_kernel  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=51)
    args = ap.parse_args(argv)
    print(machine())
    _warm_up()   # compile (or load) the kernels first: building is then building
    n = args.loops
    builds = []
    for _ in range(3):
        t0 = time.perf_counter()
        cfg = server_from_mapping(fleet_mapping(n))
        t1 = time.perf_counter()
        srv = EmulatorServer(cfg, time_scale=0)
        builds.append((t1 - t0, time.perf_counter() - t1))
    config_s, server_s = (float(np.median([b[i] for b in builds])) for i in (0, 1))
    dev = srv.device
    bank = dev.bank
    for _ in range(5):
        dev.tick()
    plant, pid = bank._plant, bank._pid
    u = bank.flow.copy()
    plant_args = plant.kernel_args()
    rows = [("load the configuration (fleet expanded)", f"{config_s * 1e3:,.0f}"),
            ("build the server (bank, image, units)", f"{server_s * 1e3:,.0f}")]
    parts = {
        "stiction kernel (every valve)": lambda: stiction_step_kernel(bank.op.copy(), bank._S, bank._J, bank._R,
                                                                      bank._codes, bank._vstate),
        "controllers (PI kernel)": lambda: pid_step_kernel(bank._sp, bank.pv, *pid.kernel_args()),
        "plants (kernel)": lambda: plant_step_kernel(u, *plant_args),
        "whole bank step (the above, set points, disturbances, noise)": bank.step,
        "encode every register into the image": dev._refresh,
    }
    for name, fn in parts.items():
        rows.append((name, f"{median_time(fn, repeats=args.repeat, warmup=3) * 1e3:.2f}"))
    print(f"\n{n:,} loops; build: median of 3, tick parts: median of {args.repeat} calls (ms)\n")
    print(table(rows, ("part", "ms")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
