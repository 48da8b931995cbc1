"""``valve-emulator evaluate DIR_OR_INDEX [--jobs N] [--report OUT.md] [--figures DIR] [--json OUT.json]``.

Runs the plant-data assessment (:mod:`valve_emulator.diagnosis.assess.decision`) and the comparison detectors on
every window of a labelled set (:mod:`valve_emulator.benchmark.labelled`: an ``index.csv`` with ``file`` and
``label`` columns, or a folder of labelled sub-folders) and prints, for this project's method and each
detector side by side, the confusion matrices and balanced accuracy per valve and per window, and a per-loop
table (:mod:`valve_emulator.benchmark.evaluation`). Progress goes to stderr.

``--jobs N`` runs N windows at a time in worker processes (each with single-threaded compiled kernels, so
N workers use N cores without oversubscribing them). ``--report`` writes the results as Markdown: into an
existing file between the markers ``<!-- valve-emulator evaluate: begin -->`` and ``<!-- ... end -->``
(the text around them is kept), else as a new file. ``--figures`` draws one figure per misclassified valve.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from valve_emulator.commands._files import user_files
from valve_emulator.errors import UserError

NAME = "evaluate"
HELP = ("assess every window of a labelled set of plant recordings, with the comparison detectors, and score "
        "them per window and per valve")

BEGIN = "<!-- valve-emulator evaluate: begin -->"
END = "<!-- valve-emulator evaluate: end -->"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("set", metavar="DIR_OR_INDEX",
                   help="a labelled set: its index.csv (columns file,label[,tag,loop_type]) or its folder")
    p.add_argument("--jobs", type=int, default=1, metavar="N", help="windows assessed at once (default %(default)s)")
    p.add_argument("--report", type=Path, metavar="OUT.md",
                   help="write the results as Markdown: between the file's '<!-- valve-emulator evaluate: begin/end "
                        "-->' markers when it has them (the rest is kept), else a new file")
    p.add_argument("--figures", type=Path, metavar="DIR", help="one PNG per misclassified valve (linked from --report)")
    p.add_argument("--json", type=Path, metavar="OUT.json", help="write every window's result")
    p.add_argument("--quiet", action="store_true", help="no progress messages on stderr")


def _run_all(items, jobs: int, say) -> list[dict]:
    from valve_emulator.batch.pool import run_ordered
    from valve_emulator.benchmark.labelled import run_window

    finished = 0

    def done(_: int, r: dict) -> None:
        nonlocal finished
        finished += 1
        say(f"{finished}/{len(items)} {r['name']}: {r['decision']}")

    return run_ordered(run_window, items, jobs=jobs, done=done)


def _figures(ev, folder: Path, report: Path | None, say) -> None:
    from valve_emulator.benchmark.evaluation import misclassified
    from valve_emulator.diagnosis.assess.decision import assess_uniform
    from valve_emulator.diagnosis.report.plot_loop import plot_loop
    from valve_emulator.recordings import read_recording, regularize

    folder.mkdir(parents=True, exist_ok=True)
    for tag, v, r in misclassified(ev.results):
        say(f"figure for {tag}")
        rec, _ = regularize(read_recording(r["path"]).recording)
        a = assess_uniform(rec)
        name = "".join(c if c.isalnum() else "_" for c in tag) + ".png"
        label = "stiction" if v["label"] else "no stiction"
        plot_loop(rec, a, folder / name, title=f"{tag} — labelled {label}; window {r['name']}")
        path = folder / name
        ev.figures[tag] = os.path.relpath(path, report.parent) if report else str(path)


def _write_report(path: Path, section: str, source: str) -> None:
    body = f"{BEGIN}\n{section}\n{END}"
    if path.exists():
        text = path.read_text(encoding="utf-8")
        if BEGIN in text and END in text:
            head, rest = text.split(BEGIN, 1)
            tail = rest.split(END, 1)[1]
            path.write_text(head + body + tail, encoding="utf-8")
            return
    path.write_text(f"# Evaluation on `{source}`\n\n{body}\n", encoding="utf-8")


def run(args: argparse.Namespace) -> int:
    with user_files({"": Path(args.set), "--report": args.report, "--figures": args.figures, "--json": args.json}):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from valve_emulator.benchmark.evaluation import Evaluation
    from valve_emulator.benchmark.labelled import read_index

    if args.jobs < 1:
        raise UserError(f"--jobs must be a whole number >= 1, got {args.jobs}")
    for flag, p in (("--report", args.report), ("--json", args.json)):
        if p is not None and not p.parent.is_dir():
            raise UserError(f"{flag} {p}: folder {p.parent} does not exist")
    items = read_index(args.set)
    start = time.perf_counter()

    def say(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    jobs = min(args.jobs, len(items))
    say(f"{len(items)} windows, {jobs} job(s)")
    results = _run_all(items, jobs, say)
    ev = Evaluation(results, seconds=time.perf_counter() - start, jobs=jobs, source=str(args.set))
    if args.figures is not None:
        _figures(ev, args.figures, args.report, say)
    print(ev.text())
    written = []
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1, ensure_ascii=False, default=float) + "\n",
                             encoding="utf-8")
        written.append(args.json)
    if args.report is not None:
        _write_report(args.report, ev.markdown(), str(args.set))
        written.append(args.report)
    if written:
        print("wrote " + ", ".join(str(p) for p in written))
    return 0
