"""``valve-emulator simulate CONFIG [--duration S] --out REC.csv [--plot FIG.png]``: one loop, offline.

``--replay REC`` drives the loop with a recording instead (:mod:`valve_emulator.simulation.replay`): its OP,
open loop, as the diagnosis' fit does (the recording's OP is mapped to % travel by ``valve.op_range``), or with
``--replay-sp`` its set point through the loop's own controller. The output is on the recording's time grid
and the open-loop replay prints the replayed PV's fit against the recorded one on the last 30 % (the part a
diagnosis with a model holds out: compare it with that diagnosis' ``fit_after``). REC is read like ``diagnose`` reads
a recording (the same reader flags). A bad recording, or one without a set point for ``--replay-sp``, is one
error line naming the file, exit code 2, and nothing written; so is a ``--plot`` file matplotlib cannot write
(``fig.pgn``), refused before the CSV is written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from valve_emulator.commands._files import check_figure, user_files
from valve_emulator.commands._reader import add_reader_arguments, reader_options
from valve_emulator.errors import UserError

NAME = "simulate"
HELP = "simulate one loop offline (deterministic) and write the standard recording CSV; or replay a recording"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, metavar="CONFIG", help="loop config (YAML, see docs/config.md)")
    p.add_argument("--duration", type=float, metavar="S", help="simulated seconds (default: simulation.duration)")
    p.add_argument("--out", required=True, type=Path, metavar="REC.csv", help="recording to write (t,sp,op,mv,pv,...)")
    p.add_argument("--plot", type=Path, metavar="FIG.png",
                   help="also plot trends and MV-OP / PV-OP like Figures 6-8 of Choudhury, Thornhill & Shah (2003)")
    r = p.add_argument_group("replaying a recording (a twin from diagnose --twin against its recording)")
    r.add_argument("--replay", type=Path, metavar="REC",
                   help="drive the loop with this recording's OP, open loop (the controller cut out, no noise)")
    r.add_argument("--replay-sp", action="store_true",
                   help="with --replay: drive it with the recorded SP through the loop's controller instead")
    add_reader_arguments(p, op_range=False)


def _replay(cfg, args: argparse.Namespace):
    """The replayed recording and the line to print about it."""
    import numpy as np

    from valve_emulator.diagnosis.fit.data import HELD_OUT, fit_percent, held_out_start
    from valve_emulator.recordings import read_recording
    from valve_emulator.simulation.replay import replay_op, replay_sp

    options = {k: v for k, v in reader_options(args).items() if not (k == "op_units" and v is None)}
    rec = read_recording(args.replay, **options).recording
    if args.replay_sp:
        sim = replay_sp(cfg, rec)
        return sim, f"closed loop on the recorded SP of {args.replay}"
    sim = replay_op(cfg, rec)
    a = held_out_start(len(rec))
    fit = fit_percent(np.asarray(rec.pv[a:]), sim.pv[a:])
    return sim, f"open loop on the recorded OP of {args.replay}; PV fit {fit:.1f} % on the last {HELD_OUT:.0%}"


def run(args: argparse.Namespace) -> int:
    with user_files({"--out": args.out, "--plot": args.plot, "--replay": args.replay}):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from valve_emulator.config import load_loop
    from valve_emulator.recordings.recording import write_csv
    from valve_emulator.simulation.loop import simulate_loop

    cfg = load_loop(args.config)
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration}")
    if args.replay_sp and args.replay is None:
        raise UserError("--replay-sp needs --replay REC (the recording whose set point drives the loop)")
    if args.replay is not None and args.duration is not None:
        raise UserError("--duration does not apply to --replay (the recording sets the length)")
    for flag, p in (("--out", args.out), ("--plot", args.plot)):
        if p is not None and not p.parent.is_dir():
            raise UserError(f"{flag} {p}: folder {p.parent} does not exist")
    check_figure("--plot", args.plot)
    if args.replay is not None:
        rec, how = _replay(cfg, args)
    else:
        rec, how = simulate_loop(cfg, args.duration), ""
    write_csv(rec, args.out)
    msg = f"wrote {args.out} ({len(rec)} samples, {rec.t[-1]:g} s of {cfg.name}" + (f", {how})" if how else ")")
    if args.plot:
        from valve_emulator.simulation.figures import plot_closed_loop

        v = cfg.valve
        plot_closed_loop(rec, args.plot, title=f"{cfg.name}: {v.model}, S = {v.S:g} %, J = {v.J:g} %")
        msg += f" and {args.plot}"
    print(msg)
    return 0
