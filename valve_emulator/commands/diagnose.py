"""``valve-emulator diagnose FILE [--model NOMINAL.yaml] [reader flags] [--json OUT] [--report OUT.md] [--plot PNG]
[--twin TWIN.yaml]``,
or a plant-wide sweep: ``valve-emulator diagnose FOLDER_OR_FILES... [--jobs N | --scheduler ADDRESS] [--csv OUT.csv]
[--json OUT.json]``.

With ``--model``: replays the nominal model on the recorded OP, locates the mismatch, names the physics the
model leaves out, fits it and shows the fit improve (see :mod:`valve_emulator.diagnosis`). Without it — plant
data — identifies the linear part from the data and answers *stiction*, *no stiction* (and why) or *cannot
tell* (and why) (:mod:`valve_emulator.diagnosis.assess.decision`). The work is
:func:`valve_emulator.diagnose`; this module only maps flags to its arguments and writes its outputs.

FILE is read by :func:`valve_emulator.recordings.read_recording`: the standard recording CSV, a generic CSV/TSV with
a column mapping (``--op --pv --sp --time`` or ``--ts``, ``--skip``, ``--decimal``...), or the DCS text export.
A recording whose time steps jitter (the Modbus recorder's rows can come a tick late) is put on a uniform
grid — OP held, PV interpolated — and the output says so; a real gap (more than
:data:`~valve_emulator.recordings.resample.MAX_GAP` samples) is refused.

Given a folder or several files, it diagnoses each recording as plant data
(:mod:`valve_emulator.batch.sweep`): one line per recording with a progress bar as they finish, then a
count per answer; ``--csv`` and ``--json`` write the summary table (answers, reason codes, S, J, fits).
``--jobs N`` uses N processes of this machine, ``--scheduler ADDRESS`` an existing Dask distributed cluster.

``--twin`` writes the loop the diagnosis found as a loop config (:mod:`valve_emulator.diagnosis.report.twin`),
which ``simulate`` replays against the recording and ``serve`` serves as a device.

The verdict goes to stdout (after any note on what was done to the data), progress to stderr. Inputs are
checked before anything is written: a bad file, flag or config is one error line naming the file (and line),
exit code 2, and no output file.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from valve_emulator.commands._files import check_figure, user_files
from valve_emulator.commands._reader import add_reader_arguments, reader_options
from valve_emulator.errors import UserError

NAME = "diagnose"
HELP = ("find what a recording's model leaves out (with --model), or whether a plant loop's valve sticks (without): "
        "name the physics, fit it")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, metavar="FILE", nargs="+",
                   help="recording: standard CSV (t,sp,op,mv,pv), generic CSV/TSV (map columns below) or DCS export; "
                        "a folder or several files: a plant-wide sweep")
    p.add_argument("--model", type=Path, metavar="NOMINAL.yaml",
                   help="loop config of the nominal simulation (default: plant data, identify the linear part)")
    p.add_argument("--json", type=Path, metavar="OUT.json", help="write fit_before, fit_after, findings, verdict")
    p.add_argument("--report", type=Path, metavar="OUT.md", help="write a Markdown report")
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="write the figure")
    p.add_argument("--twin", type=Path, metavar="TWIN.yaml",
                   help="write the twin: the loop the diagnosis found as a loop config (simulate, serve)")
    p.add_argument("--quiet", action="store_true", help="no progress messages on stderr")
    loop = p.add_argument_group("the loop, when known (plant data only)")
    loop.add_argument("--loop-type", choices=("level", "flow", "pressure", "temperature"),
                      help="level: an integrating plant; flow, pressure, temperature: self-regulating")
    loop.add_argument("--integrating", action="store_true", default=None,
                      help="the plant integrates (default: recognised from the data)")
    loop.add_argument("--action", choices=("reverse", "direct"),
                      help="the controller's action: reverse (OP rises as PV falls; positive process gain) or "
                           "direct (default: read from the controller's law in the data)")
    s = p.add_argument_group("a plant-wide sweep (a folder or several files)")
    s.add_argument("--jobs", type=int, default=1, metavar="N", help="recordings diagnosed at once (default 1)")
    s.add_argument("--scheduler", metavar="ADDRESS",
                   help="submit the recordings to this Dask distributed scheduler (e.g. tcp://10.0.0.5:8786; "
                        "needs the extra valve_emulator[cluster])")
    s.add_argument("--csv", type=Path, metavar="OUT.csv", help="write the summary table (one line per recording)")
    add_reader_arguments(p)


def _progress(quiet: bool):
    start = time.perf_counter()

    def say(msg: str) -> None:
        if not quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    return say


def _bar(done: int, total: int, width: int = 20) -> str:
    full = int(round(width * done / total))
    return "[" + "#" * full + "." * (width - full) + f"] {done}/{total}"


def _line(row: dict) -> str:
    if row["error"]:
        return f"{row['file']}: error: {row['error']}"
    what = f"{row['answer']}" + (f" ({row['strength']})" if row["strength"] else "")
    if row["S"] is not None:
        what += f", S {row['S']:.4g}, J {row['J']:.4g} {row['units']}"
    return f"{row['file']}: {what} [{row['reasons']}] ({row['seconds']:.1f} s)"


def _sweep(args: argparse.Namespace) -> int:
    from valve_emulator.batch.sweep import SweepTable, sweep

    if any(p is not None for p in (args.model, args.report, args.plot, args.twin)):
        raise UserError("a sweep (a folder or several files) diagnoses plant data: --model, --report, --plot and "
                        "--twin apply to one file")
    if any(v is not None for v in (args.loop_type, args.integrating, args.action)):
        raise UserError("--loop-type, --integrating and --action describe one loop: they apply to one file")
    if args.scheduler is not None and args.jobs != 1:
        raise UserError("--jobs and --scheduler exclude each other (the cluster decides how many at once)")
    options = {k: v for k, v in reader_options(args).items() if v is not None}
    if args.op_range is not None:
        options["op_range"] = tuple(args.op_range)

    def progress(done: int, total: int, row: dict) -> None:
        print(f"{_bar(done, total)} {_line(row)}", flush=True)

    table = SweepTable(sweep(args.recording, jobs=args.jobs, scheduler=args.scheduler, progress=progress, **options))
    print("answers: " + ", ".join(f"{k} {n}" for k, n in sorted(table.counts().items())))
    written = []
    if args.csv:
        args.csv.write_text(table.csv(), encoding="utf-8")
        written.append(args.csv)
    if args.json:
        args.json.write_text(json.dumps(table.json(), indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
        written.append(args.json)
    if written:
        print("wrote " + ", ".join(str(p) for p in written))
    return 0


def run(args: argparse.Namespace) -> int:
    files = {"": args.recording[0] if len(args.recording) == 1 else None, "--model": args.model, "--json": args.json,
             "--report": args.report, "--plot": args.plot, "--csv": args.csv, "--twin": args.twin}
    with user_files(files):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from valve_emulator.config import load_loop
    from valve_emulator.diagnosis.api import diagnose

    for flag, p in (("--json", args.json), ("--report", args.report), ("--plot", args.plot), ("--csv", args.csv),
                    ("--twin", args.twin)):
        if p is not None and not p.parent.is_dir():
            raise UserError(f"{flag} {p}: folder {p.parent} does not exist")
    check_figure("--plot", args.plot)
    if args.jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {args.jobs}")
    if len(args.recording) > 1 or args.recording[0].is_dir():
        return _sweep(args)
    if args.jobs != 1 or args.scheduler is not None or args.csv is not None:
        raise UserError("--jobs, --scheduler and --csv apply to a sweep (a folder or several files)")
    args.recording = args.recording[0]
    nominal = load_loop(args.model) if args.model is not None else None
    if nominal is not None and args.op_range is not None:
        raise UserError("--op-range applies only to plant data (without --model): a model's OP is % travel")
    extra = {} if args.op_range is None else {"op_range": tuple(args.op_range)}
    loop = {k: v for k, v in (("loop_type", args.loop_type), ("integrating", args.integrating),
                              ("action", args.action)) if v is not None}
    if nominal is not None and loop:
        raise UserError("--loop-type, --integrating and --action apply only to plant data (without --model): "
                        "a model has its own plant")
    extra.update(loop)
    d = diagnose(args.recording, nominal, progress=_progress(args.quiet), **extra, **reader_options(args))
    twin = d.twin().text() if args.twin else None   # before anything is written: no model, no twin
    written = []
    if twin is not None:
        args.twin.write_text(twin, encoding="utf-8")
        written.append(args.twin)
    if args.plot:
        d.plot(args.plot, title=str(args.recording))
        written.append(args.plot)
    if args.json:
        args.json.write_text(json.dumps(d.to_json(), indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
        written.append(args.json)
    if args.report:
        figure = os.path.relpath(args.plot, args.report.parent) if args.plot else None
        args.report.write_text(d.report(figure=figure), encoding="utf-8")
        written.append(args.report)
    for n in dict.fromkeys(d.notes):
        print(f"note: {n}")
    print(d.verdict)
    if written:
        print("wrote " + ", ".join(str(p) for p in written))
    return 0
