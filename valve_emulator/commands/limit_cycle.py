"""``valve-emulator limit-cycle CONFIG``: describing-function prediction beside the simulated limit cycle."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from valve_emulator.errors import UserError

NAME = "limit-cycle"
HELP = "predict the limit cycle with the describing function and compare with simulation"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, nargs="+", metavar="CONFIG", help="loop config(s) with a controller")
    p.add_argument("--duration", type=float, metavar="S", help="simulated seconds (default: simulation.duration)")


def compare(cfg, duration=None) -> dict:
    """Predicted and simulated OP amplitude (% travel) and period (s) of one loop config."""
    from valve_emulator.physics.signal_chain import Characteristic
    from valve_emulator.simulation.limit_cycle import measure_limit_cycle, predict_limit_cycle
    from valve_emulator.simulation.loop import simulate_loop

    if cfg.controller is None:
        raise UserError(f"{cfg.source or cfg.name}: controller is required for a limit-cycle prediction")
    gain = float(Characteristic(cfg.valve.characteristic, cfg.valve.rangeability).gain(cfg.controller.bias))
    pred = predict_limit_cycle(cfg.valve.S, cfg.valve.J, cfg.controller, cfg.plant, characteristic_gain=gain)
    rec = simulate_loop(cfg, duration)
    meas = measure_limit_cycle(rec.t, rec.op)
    return {"name": cfg.name, "S": cfg.valve.S, "J": cfg.valve.J, "predicted": pred, "measured": meas}


def _fmt(x: float, spec: str = ".2f") -> str:
    return "-" if not math.isfinite(x) else format(x, spec)


def run(args: argparse.Namespace) -> int:
    from valve_emulator.config import load_loop

    cfgs = [load_loop(p) for p in args.config]  # validate every file before simulating anything
    print(f"{'loop':28s} {'S':>5s} {'J':>5s} | {'DF amp':>7s} {'DF period':>9s} | {'sim amp':>7s} "
          f"{'sim period':>10s} {'sustained':>9s} | {'period err':>10s}")
    for cfg in cfgs:
        r = compare(cfg, args.duration)
        p, m = r["predicted"], r["measured"]
        err = (p.period - m.period) / m.period * 100 if p.found and m.sustained else math.nan
        print(f"{r['name']:28s} {r['S']:5.2f} {r['J']:5.2f} | {_fmt(p.amplitude):>7s} {_fmt(p.period, '.1f'):>9s} | "
              f"{_fmt(m.amplitude if m.sustained else 0.0):>7s} "
              f"{_fmt(m.period if m.sustained else math.nan, '.1f'):>10s} "
              f"{'yes' if m.sustained else 'no':>9s} | {_fmt(err, '+.1f') + (' %' if math.isfinite(err) else ''):>10s}")
    return 0
