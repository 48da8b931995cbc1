"""Benchmark: a whole plant on two cores — 100,000 loops ticking at 10 Hz while ten C clients poll.

``bench_scale.py``'s tick-jitter measurement (§2 of docs/benchmarks.md) for one fleet size, in one and in two
processes, without the rest of that report. Run::

    python bench/bench_plant_jitter.py [--loops 100000] [--seconds 10] [--windows 3]

Needs gcc, pkg-config and libmodbus-dev (the C load client).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_scale import _jitter_section, _warm_up, jitter  # noqa: E402
from common import build_c, machine  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=100_000)
    ap.add_argument("--seconds", type=float, default=10.0, help="seconds per window (10)")
    ap.add_argument("--windows", type=int, default=3, help="windows per configuration (3)")
    args = ap.parse_args(argv)
    print(machine())
    with tempfile.TemporaryDirectory() as tmp:
        client = build_c(HERE / "c" / "modbus_load.c", Path(tmp) / "modbus_load")
        if client is None:
            print("the C load client could not be built (gcc, pkg-config, libmodbus-dev)", file=sys.stderr)
            return 1
        _warm_up()
        results = [jitter(client, args.loops, p, args.seconds, args.windows) for p in (1, 2)]
    print(_jitter_section(results, args.seconds, args.windows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
