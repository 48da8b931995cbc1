"""``valve-emulator simulate CONFIG [--duration S] --out REC.csv [--plot FIG.png]``: one loop, offline."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "simulate"
HELP = "simulate one loop offline (deterministic) and write the standard recording CSV"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, metavar="CONFIG", help="loop config (YAML, see docs/config.md)")
    p.add_argument("--duration", type=float, metavar="S", help="simulated seconds (default: simulation.duration)")
    p.add_argument("--out", required=True, type=Path, metavar="REC.csv", help="recording to write (t,sp,op,mv,pv,...)")
    p.add_argument("--plot", type=Path, metavar="FIG.png",
                   help="also plot trends and MV-OP / PV-OP like Figures 6-8 of Choudhury, Thornhill & Shah (2003)")


def run(args: argparse.Namespace) -> int:
    from valve_emulator.config import load_loop
    from valve_emulator.recordings.recording import write_csv
    from valve_emulator.simulation.loop import simulate_loop

    cfg = load_loop(args.config)
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be > 0 s, got {args.duration}")
    rec = simulate_loop(cfg, args.duration)
    write_csv(rec, args.out)
    msg = f"wrote {args.out} ({len(rec)} samples, {rec.t[-1]:g} s of {cfg.name})"
    if args.plot:
        from valve_emulator.simulation.figures import plot_closed_loop

        v = cfg.valve
        plot_closed_loop(rec, args.plot, title=f"{cfg.name}: {v.model}, S = {v.S:g} %, J = {v.J:g} %")
        msg += f" and {args.plot}"
    print(msg)
    return 0
