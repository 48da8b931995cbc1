"""``valve-emulator diagnose REC.csv [--model NOMINAL.yaml] [--json OUT] [--report OUT.md] [--plot OUT.png]``.

Replays the nominal model on the recorded OP, locates the mismatch, names the physics the model leaves out,
fits it and shows the fit improve (see :mod:`valve_emulator.diagnosis`). The verdict goes to stdout,
progress to stderr. Inputs are checked before anything is written: a bad recording or config is one error
line naming the file and line, exit code 2, and no output file.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

NAME = "diagnose"
HELP = "find where a recording and its simulation differ, name the physics the model leaves out, fit it"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, metavar="REC.csv", help="standard recording (t,sp,op,mv,pv; mv/sp may be empty)")
    p.add_argument("--model", type=Path, metavar="NOMINAL.yaml",
                   help="loop config of the nominal simulation (default: identify a linear model from the data)")
    p.add_argument("--json", type=Path, metavar="OUT.json", help="write fit_before, fit_after, findings, verdict")
    p.add_argument("--report", type=Path, metavar="OUT.md", help="write a Markdown report")
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="write the four-panel figure")
    p.add_argument("--quiet", action="store_true", help="no progress messages on stderr")


def _progress(quiet: bool):
    start = time.perf_counter()

    def say(msg: str) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    return say


def run(args: argparse.Namespace) -> int:
    from valve_emulator.config import load_loop
    from valve_emulator.diagnosis import diagnose
    from valve_emulator.sim.recording import read_csv

    nominal = load_loop(args.model) if args.model is not None else None
    rec = read_csv(args.recording)
    result = diagnose(rec, nominal, progress=_progress(args.quiet))
    written = []
    if args.plot:
        from valve_emulator.diagnosis.plot import plot_diagnosis

        plot_diagnosis(result, args.plot)
        written.append(args.plot)
    if args.json:
        args.json.write_text(json.dumps(result.to_json(), indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
        written.append(args.json)
    if args.report:
        figure = os.path.relpath(args.plot, args.report.parent) if args.plot else None
        args.report.write_text(result.report(figure=figure), encoding="utf-8")
        written.append(args.report)
    print(result.verdict)
    if written:
        print("wrote " + ", ".join(str(p) for p in written))
    return 0
