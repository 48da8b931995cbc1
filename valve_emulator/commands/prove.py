"""``valve-emulator prove [--out DIR]``: the diagnosis on concealed data with a known truth, as one command.

Simulates every case of :data:`valve_emulator.benchmark.proof.CASES` (closed loop, only OP and PV kept, PV
noise), diagnoses each against a nominal model lacking the effect, prints the table and writes
``DIR/proof.md`` with one figure and one JSON document (as ``diagnose --json`` writes) per case under
``DIR/proof/`` (default ``DIR = ./proof``; the published copy in
the documentation is made with ``--out docs``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from valve_emulator.commands._files import user_files
from valve_emulator.errors import UserError

NAME = "prove"
HELP = "run the diagnosis on concealed simulated recordings with a known truth and write DIR/proof.md"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("proof"), metavar="DIR",
                   help="folder for proof.md and proof/*.png (default %(default)s)")
    p.add_argument("--case", action="append", metavar="NAME",
                   help="run only cases whose name contains NAME (repeatable)")
    p.add_argument("--duration", type=float, metavar="S", help="simulate S seconds per case instead of each case's own")


def run(args: argparse.Namespace) -> int:
    with user_files({"--out": args.out}):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from valve_emulator.benchmark.proof import CASES, proof_markdown, run_case, slug, table_text

    cases = [c for c in CASES if not args.case or any(s in c.name for s in args.case)]
    if not cases:
        raise UserError(f"--case {args.case} matches none of: {', '.join(c.name for c in CASES)}")
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration}")
    figures = args.out / "proof"
    figures.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    results = []
    for i, case in enumerate(cases, 1):
        print(f"[{time.perf_counter() - start:6.1f} s] case {i}/{len(cases)}: {case.name}", file=sys.stderr, flush=True)
        r = run_case(case, duration=args.duration, figure_dir=figures)
        (figures / f"{slug(case.name)}.json").write_text(json.dumps(r.document, indent=2, ensure_ascii=False) + "\n",
                                                         encoding="utf-8")
        results.append(r)
    print(table_text(results))
    md = args.out / "proof.md"
    md.write_text(proof_markdown(results, figure_prefix="proof/", seconds=time.perf_counter() - start),
                  encoding="utf-8")
    print(f"wrote {md} and {len(results)} figure(s) and JSON document(s) in {figures}")
    return 0 if all(r.named_ok for r in results) else 1
