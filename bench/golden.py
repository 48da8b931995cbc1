"""Golden comparison for a restructure with behaviour preserved.

    python bench/golden.py run OUT_DIR [--plant SET_DIR] [--cases-from PREVIOUS_OUT_DIR]
    python bench/golden.py compare BEFORE_DIR AFTER_DIR

``run`` records, through the command line a user runs (``valve-emulator diagnose FILE [--model M] --json``):

* every concealed case of ``valve-emulator prove``: its recording (standard CSV) and nominal model (YAML)
  are written to ``OUT_DIR/cases/`` first, then diagnosed against the model;
* every window of a labelled plant set (``--plant``: a folder with ``index.csv``), diagnosed without a model;
* the register image of a 100-loop fleet over 1,000 ticks, with operator and instructor writes on the way
  (the SHA-256 of every tick's image, chained, and the last image in hex).

``--cases-from`` reuses another run's case files instead of generating them, so that a comparison of two
code versions feeds both exactly the same bytes.

``compare`` checks that two runs give the same findings, the same parameters (exactly, the default; or to
``--tolerance``, relative to max(1, |value|)), the same answers and verdicts, and a byte-identical register
image. An after-run made without ``--plant`` is compared on its cases and image only. Exit code 0 when they
agree, 1 (with every difference listed) when they do not.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import shutil
import sys
from pathlib import Path

TOLERANCE = 0.0  # a restructure keeps every number to the last digit


# ------------------------------------------------------------------------------------------ run

def _cases_module():
    try:  # the proof cases live with the benchmark machinery
        from valve_emulator.benchmark import cases
    except ImportError:  # a checkout from before the restructure, for the "before" run
        from valve_emulator.diagnosis import cases
    return cases


def _write_cases(folder: Path) -> list[tuple[str, Path, Path]]:
    import yaml

    cases = _cases_module()
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for case in cases.CASES:
        slug = "".join(c if c.isalnum() else "_" for c in case.name.lower()).strip("_")
        rec, _nominal, _true = cases.generate(case)
        csv_path, yaml_path = folder / f"{slug}.csv", folder / f"{slug}.yaml"
        with open(csv_path, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["t", "op", "pv"])
            for t, op, pv in zip(rec.t, rec.op, rec.pv):
                w.writerow([repr(float(t)), repr(float(op)), repr(float(pv))])
        nominal = cases.nominal_mapping(case)
        yaml_path.write_text(yaml.safe_dump(json.loads(json.dumps(nominal))), encoding="utf-8")
        out.append((slug, csv_path, yaml_path))
    return out


def _diagnose(path: Path, model: Path | None, out_json: Path) -> dict:
    from valve_emulator.cli import main

    argv = ["diagnose", str(path), "--json", str(out_json), "--quiet"]
    if model is not None:
        argv += ["--model", str(model)]
    code = main(argv)
    if code != 0 or not out_json.exists():
        return {"error": f"exit code {code}"}
    return json.loads(out_json.read_text(encoding="utf-8"))


def _fleet_image() -> dict:
    import numpy as np

    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.tick import Device

    cfg = server_from_mapping({
        "device": {"tick": 0.1, "instructor_writes": True},
        "loops": [
            {"unit": 200, "valve": {"S": 5.0, "J": 2.0},
             "plant": {"fopdt": {"gain": 3.0, "tau": 10.0, "delay": 1.0}, "noise": 0.02},
             "controller": {"kc": 0.2, "ti": 10.0, "sp_steps": [[0.5, 1.0]]}},
            {"unit": 201, "valve": {"S": 3.0, "J": 1.0}, "plant": {"integrator": {"gain": 0.1}, "pv0": 50.0}},
        ],
        "fleet": {"count": 98, "loops_per_unit": 16, "seed": 11,
                  "base": {"valve": {"S": 4.0, "J": 1.0, "op0": 45.0},
                           "plant": {"fopdt": {"gain": 1.0, "tau": 4.0, "delay": 0.3},
                                     "disturbance": {"type": "sine", "amplitude": 4.0, "period": 3.0},
                                     "noise": 0.05}},
                  "vary": {"S": [0.5, 3.0], "J": [0.0, 1.0], "gain": [0.5, 2.0], "delay": [0.0, 1.0]}},
    })
    device = Device.from_config(cfg, time_scale=0)
    chain = hashlib.sha256()
    # Writes on the way (register addresses from the map, values raw): OP of open-loop loops, SP and mode
    # of the controlled loop, instructor S/J and load.
    from valve_emulator.device.registers import address_of
    from valve_emulator.device.roles import INSTRUCTOR
    writes = {
        100: [(2, "op_pct", [6000]), (0, "sp", [1500])],
        300: [(5, "S", [150]), (0, "mode", [0]), (0, "op_pct", [4500])],
        500: [(7, "load", [200]), (0, "mode", [1]), (40, "J", [300])],
        800: [(5, "S", [0]), (99, "op_pct", [100])],
    }
    errors = []
    for k in range(1000):
        for index, name, values in writes.get(k, ()):
            try:
                device.write(index, address_of(name), values, role=INSTRUCTOR)
            except Exception as exc:  # noqa: BLE001 - recorded, must be the same before and after
                errors.append(f"tick {k} loop {index} {name}: {type(exc).__name__}: {exc}")
        device.advance(1)
        chain.update(bytes(device.image))
    return {"ticks": device.ticks, "sha256_chain": chain.hexdigest(), "last_image": bytes(device.image).hex(),
            "write_errors": errors, "n": int(np.asarray(device.offsets).size)}


def run(out: Path, plant: Path | None, cases_from: Path | None) -> int:
    out.mkdir(parents=True, exist_ok=True)
    result: dict = {"cases": {}, "plant": {}, "image": None}
    if cases_from is not None:
        shutil.copytree(cases_from / "cases", out / "cases", dirs_exist_ok=True)
        case_files = [(p.stem, p, p.with_suffix(".yaml")) for p in sorted((out / "cases").glob("*.csv"))]
    else:
        case_files = _write_cases(out / "cases")
    work = out / "json"
    work.mkdir(exist_ok=True)
    for i, (slug, csv_path, yaml_path) in enumerate(case_files, 1):
        print(f"case {i}/{len(case_files)}: {slug}", file=sys.stderr, flush=True)
        result["cases"][slug] = _diagnose(csv_path, yaml_path, work / f"case_{slug}.json")
    if plant is not None:
        with open(plant / "index.csv", newline="", encoding="utf-8") as fh:
            files = [row["file"] for row in csv.DictReader(fh)]
        for i, name in enumerate(files, 1):
            print(f"window {i}/{len(files)}: {name}", file=sys.stderr, flush=True)
            slug = f"w{i:03d}"
            result["plant"][name] = _diagnose(plant / name, None, work / f"plant_{slug}.json")
    print("fleet image: 100 loops x 1000 ticks", file=sys.stderr, flush=True)
    result["image"] = _fleet_image()
    (out / "golden.json").write_text(json.dumps(result, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    print(f"wrote {out / 'golden.json'}: {len(result['cases'])} cases, {len(result['plant'])} windows, "
          f"image {result['image']['sha256_chain'][:16]}")
    return 0


# ------------------------------------------------------------------------------------------ compare

def _diff(a, b, where: str, out: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key in ("seconds", "source"):  # wall time; where the case file was
                continue
            if key not in a or key not in b:
                # a key only in the newer output is an addition, not a change of behaviour
                if key not in a:
                    continue
                out.append(f"{where}.{key}: missing after")
                continue
            _diff(a[key], b[key], f"{where}.{key}", out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{where}: {len(a)} items before, {len(b)} after")
            return
        for i, (x, y) in enumerate(zip(a, b)):
            _diff(x, y, f"{where}[{i}]", out)
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        if math.isnan(a) and math.isnan(b):
            return
        if abs(a - b) > TOLERANCE * max(1.0, abs(a)):
            out.append(f"{where}: {a!r} before, {b!r} after")
    elif a != b:
        out.append(f"{where}: {a!r} before, {b!r} after")


def compare(before: Path, after: Path, tolerance: float = TOLERANCE) -> int:
    global TOLERANCE
    TOLERANCE = tolerance
    a = json.loads((before / "golden.json").read_text(encoding="utf-8"))
    b = json.loads((after / "golden.json").read_text(encoding="utf-8"))
    if not b["plant"]:  # an after-run of the cases alone
        a = {**a, "plant": {}}
    diffs: list[str] = []
    _diff(a, b, "golden", diffs)
    n_cases, n_plant = len(a["cases"]), len(a["plant"])
    if diffs:
        print(f"{len(diffs)} difference(s):")
        for d in diffs[:200]:
            print("  " + d)
        return 1
    print(f"same: {n_cases} cases, {n_plant} plant windows (findings, parameters to {TOLERANCE:g}, answers), "
          f"register image over {a['image']['ticks']} ticks of {a['image']['n']} loops byte-identical")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--plant", type=Path, help="labelled plant set (folder with index.csv)")
    r.add_argument("--cases-from", type=Path, help="reuse the case files of an earlier run")
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    c.add_argument("--tolerance", type=float, default=TOLERANCE,
                   help="relative tolerance on numbers (default %(default)s: exact)")
    args = p.parse_args(argv)
    if args.cmd == "run":
        return run(args.out, args.plant, args.cases_from)
    return compare(args.before, args.after, args.tolerance)


if __name__ == "__main__":
    sys.exit(main())
