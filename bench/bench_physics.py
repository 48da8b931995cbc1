"""Speed of the physics core. Run: ``python bench/bench_physics.py``.

Prints medians of several runs:
- ``simulate`` samples/s for one valve over 10^6 samples, per model, against a plain per-sample Python loop
  of the same Kano algorithm measured in the same run;
- valve-samples/s stepping 1, 1,000 and 10,000 valves at once (``StictionBank.step`` per sample, the way the
  emulator's tick calls it, and ``simulate_many`` over a whole array, the way the diagnosis does);
- simulated seconds per wall second of the concentration loop (valve + plant + PI) at dt = 0.1 s;
- loop-steps/s for 1,000 loops stepped together.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import median_time, table  # noqa: E402

from valve_emulator.config import load_loop  # noqa: E402
from valve_emulator.simulation.loop import LoopBank, simulate_loop  # noqa: E402
from valve_emulator.stiction import MODELS, StictionBank, simulate, simulate_many  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def kano_python(op, S, J):
    """The Kano algorithm as a plain per-sample Python loop: the baseline."""
    out = np.empty(len(op))
    u_prev = min(max(op[0], 0.0), 100.0)
    us, d, stp, du_prev = u_prev, 1.0, 1, 0.0
    half = (S - J) / 2
    mv = u_prev - half
    for k, x in enumerate(op):
        u = min(max(x, 0.0), 100.0)
        du = u - u_prev
        if du * du_prev <= 0 and stp == 0:
            us, stp = u_prev, 1
        if stp == 0:
            mv = u - d * half
        elif -d * (u - us) > S:
            d = -d
            mv, stp = u - d * half, 0
        elif d * (u - us) > J:
            mv, stp = u - d * half, 0
        out[k] = mv
        u_prev, du_prev = u, du
    return out


def main() -> None:
    rng = np.random.default_rng(0)
    n = 10 ** 6
    op = 50 + 10 * np.sin(np.arange(n) * 2 * np.pi / 5000) + rng.normal(0, 0.3, n)
    rows = []
    base = median_time(lambda: kano_python(op[:100_000], 5.0, 2.0), repeats=3) * 10
    rows.append(("plain Python loop (kano), 1 valve", f"{n / base:,.0f}", "1.0×"))
    np.testing.assert_allclose(kano_python(op[:20000], 5.0, 2.0), simulate(op[:20000], S=5.0, J=2.0))
    for model in MODELS:
        t = median_time(lambda: simulate(op, S=5.0, J=2.0, model=model))
        rows.append((f"simulate, {model}, 1 valve × 10^6 samples", f"{n / t:,.0f}", f"{base / t:,.0f}×"))
    for nv in (1, 1000, 10_000):
        bank = StictionBank(nv, S=rng.uniform(1, 8, nv), J=rng.uniform(0, 6, nv))
        bank.reset(50.0)
        steps = 2000 if nv > 1 else 20000
        ops = 50 + rng.normal(0, 3, (steps, nv))

        def tick_loop():
            for k in range(steps):
                bank.step(ops[k])

        t = median_time(tick_loop, repeats=5)
        rows.append((f"StictionBank.step per sample, {nv:,} valves", f"{nv * steps / t:,.0f}",
                     f"{base * nv * steps / n / t:,.0f}×"))
        t = median_time(lambda: simulate_many(ops, np.full(nv, 5.0), np.full(nv, 2.0)), repeats=5)
        rows.append((f"simulate_many over the array, {nv:,} valves", f"{nv * steps / t:,.0f}",
                     f"{base * nv * steps / n / t:,.0f}×"))
    print("## Stiction kernel (valve-samples/s, median)\n")
    print(table(rows, ("case", "valve-samples/s", "vs plain Python")))

    cfg = load_loop(ROOT / "configs" / "table1" / "concentration_undershoot.yaml")
    t = median_time(lambda: simulate_loop(cfg, 3600.0), repeats=7)
    rows = [("concentration loop, 1 h at dt = 0.1 s (valve + plant + PI)", f"{t * 1000:.1f} ms",
             f"{3600 / t:,.0f} simulated s / wall s")]
    cfgs = [replace(cfg, valve=replace(cfg.valve, S=float(s), J=float(j), seed_form=None))
            for s, j in zip(rng.uniform(2, 6, 1000), rng.uniform(0, 4, 1000))]
    bank = LoopBank(cfgs)
    steps = 3000
    t = median_time(lambda: bank.run(steps), repeats=5)
    rows.append(("1,000 loops stepped together (compiled run)", f"{t * 1000:.1f} ms / {steps} steps",
                 f"{1000 * steps / t:,.0f} loop-steps/s"))

    def ticks():
        for _ in range(200):
            bank.step()

    t = median_time(ticks, repeats=5)
    rows.append(("1,000 loops, one `LoopBank.step()` per tick", f"{t / 200 * 1e6:.0f} µs / tick",
                 f"{1000 * 200 / t:,.0f} loop-steps/s"))
    print("\n## Closed loop (median)\n")
    print(table(rows, ("case", "time", "rate")))


if __name__ == "__main__":
    main()
