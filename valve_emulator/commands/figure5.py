"""``valve-emulator figure5 --out DIR``: reproduce the 2003 paper's Figure 5 (PNG + CSV)."""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from valve_emulator.commands._files import user_files

NAME = "figure5"
HELP = "reproduce Figure 5 of Choudhury, Thornhill & Shah (2003) (open-loop stiction cases) as PNG and CSV"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from valve_emulator.physics.stiction import DEFAULT_MODEL, MODELS

    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="folder for figure5.png and figure5.csv")
    p.add_argument("--model", choices=MODELS, default=DEFAULT_MODEL, help="stiction model (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    with user_files({"--out": args.out}):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from valve_emulator.simulation.figure5 import figure5_data
    from valve_emulator.simulation.figures import plot_open_loop_rows

    data = figure5_data(model=args.model)
    args.out.mkdir(parents=True, exist_ok=True)
    png = plot_open_loop_rows(
        data.t, data.op, [(f"{label}   (S = {S:g}, J = {J:g} in the 2005 convention)", mv)
                          for label, S, J, mv in data.rows],
        args.out / "figure5.png",
        title=f"Figure 5 of Choudhury, Thornhill & Shah (2003): open-loop response of the data-driven stiction "
              f"model ({args.model})")
    csv_path = args.out / "figure5.csv"
    names = ["no_stiction", "deadband", "undershoot", "no_offset", "overshoot"]
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "op"] + [f"mv_{n}" for n in names])
        for k in range(data.t.size):
            w.writerow([repr(float(data.t[k])), repr(float(data.op[k]))]
                       + [repr(float(row[3][k])) for row in data.rows])
    print(f"wrote {png} and {csv_path}")
    return 0
