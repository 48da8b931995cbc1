#!/usr/bin/env bash
# The benchmarks of docs/benchmarks.md §11 in one run, one after the other, each stamped with the time and the
# load average (run it on an otherwise idle machine). Usage: bench/run_limits.sh PLANT_DATA_DIR
# (PLANT_DATA_DIR: the labelled plant windows that `valve-emulator evaluate` sweeps, e.g. ../shared/data/stictiongpt_plant)
set -euo pipefail
cd "$(dirname "$0")/.."
data="${1:?usage: bench/run_limits.sh PLANT_DATA_DIR}"
stamp() { echo "=== $1: $(date -u +%Y-%m-%dT%H:%M:%SZ) load $(cut -d' ' -f1-3 /proc/loadavg)"; }
stamp start
python bench/bench_modbus_c.py --rounds 3;                                  stamp "11.1 Modbus against C"
python bench/bench_tick_parts.py;                                           stamp "11.2 tick parts"
python bench/bench_plant_jitter.py;                                         stamp "11.2 plant jitter"
python bench/bench_physics.py;                                              stamp "11.2 stiction kernel"
python bench/bench_diagnose.py --samples 10000 100000 --repeat 3;           stamp "11.3 diagnose"
python - "$data" <<'PY'
import subprocess, sys, time
t = time.perf_counter()
subprocess.run([sys.executable, "-m", "valve_emulator", "evaluate", sys.argv[1], "--jobs", "2"], check=True,
               stdout=subprocess.DEVNULL)
print(f"evaluate --jobs 2: {time.perf_counter() - t:.1f} s wall")
PY
stamp "11.3 plant sweep"
python bench/bench_interfaces_under_attack.py;                              stamp "11.4 hostile input"
