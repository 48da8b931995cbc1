"""The measuring subscriber ``bench/bench_opcua.py --client node`` runs (``tests/opcua/node/subscriber.mjs``,
node-opcua) against ``valve-emulator serve --opcua`` on a small fleet: it receives and counts every tick's pv and op
value of every loop, by the bench's definition and tick by tick."""

from __future__ import annotations

import json
import subprocess

import yaml

from .test_opcua_interop import start_serve, stop
from .test_opcua_node import NODE_DIR, node  # noqa: F401  (the fixture)

LOOPS = 20
TICK = 0.1
SECONDS = 4.0
#: A fleet whose PV and OP change at every tick: measurement noise on every PV, a PI controller on every loop.
FLEET = {"device": {"tick": TICK},
         "fleet": {"count": LOOPS, "loops_per_unit": 10, "seed": 3,
                   "base": {"valve": {"S": 4.0, "J": 1.0},
                            "plant": {"fopdt": {"gain": 1.0, "tau": 15.0, "delay": 2.0}, "noise": 0.05},
                            "controller": {"kc": 0.5, "ti": 15.0}},
                   "vary": {"S": [2.0, 6.0], "J": [0.0, 3.0]}}}


def run_subscriber(binary: str, settings: dict) -> dict:
    """subscriber.mjs with ``settings``, told to go at once; its last JSON line (the counts, or the failure)."""
    done = subprocess.run([binary, str(NODE_DIR / "subscriber.mjs")], input=json.dumps(settings) + "\ngo\n",
                          capture_output=True, text=True, timeout=120, cwd=NODE_DIR)
    lines = [json.loads(ln) for ln in done.stdout.splitlines() if ln.startswith("{")]
    assert lines and "counts" in lines[-1], done.stdout[-2000:] + done.stderr[-2000:]
    assert [next(iter(ln)) for ln in lines] == ["ready", "start", "counts"], lines
    return lines[-1]["counts"]


def test_node_subscriber_counts_every_pv_and_op_value_of_every_tick(node, tmp_path):  # noqa: F811
    """20 loops at time-scale 1 (a tick every 0.1 s), pv, op and the simulated ``time`` of every loop sampled every
    tick and published every tick, as the bench's 1-client row; the subscriber counts pv/op (the bench's counts) and
    also ``time``, whose values number the ticks. A queue of 10 per item, so that a stall of the loaded test machine
    (a server that hands two ticks' samples within one publishing interval) cannot make the server replace a value
    the subscriber should count: this tests the subscriber's counting, not the server's timing (the bench's rows do).
    Every item gets its publishing intervals' share (the bench's definition, within the window's edge), each loop's
    ``time`` advances by exactly one tick from value to value (no tick lost), and each loop's pv and op carry a value
    stamped with every one of those ticks' SourceTimestamps (every value of every tick)."""
    (tmp_path / "fleet.yaml").write_text(yaml.safe_dump(FLEET))
    from valve_emulator.config import load_server

    loops = [f"Unit{lp.device.unit}.{lp.name}" for lp in load_server(tmp_path / "fleet.yaml").loops]
    assert len(loops) == LOOPS
    proc, url, _ = start_serve(str(tmp_path / "fleet.yaml"), "--opcua", "0", "--time-scale", "1")
    try:
        counts = run_subscriber(node, {"url": url, "loops": loops, "variables": ["pv", "op", "time"],
                                       "counted": ["pv", "op", "time"], "publish_ms": 1000 * TICK,
                                       "sampling_ms": 1000 * TICK, "queue": 10, "requests": 3, "settle": 1.0,
                                       "seconds": SECONDS, "trace": True})
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]
    assert counts["lost"] == [] and counts["items"] == 3 * LOOPS
    per_item = SECONDS / TICK
    assert counts["fewest"] >= per_item - 2, counts["fewest"]   # the bench's count, one tick either edge
    assert counts["capped"] >= 3 * LOOPS * (per_item - 2)
    start, end = counts["window"]
    trace = counts["trace"]
    for path in loops:
        # the ticks inside the window, from the loop's simulated time (each tick adds 0.1 s)
        times = [(stamp, value) for at, stamp, value in trace[f"{path}.time"] if start <= at <= end]
        assert len(times) >= per_item - 2, (path, len(times))
        steps = [round((b[1] - a[1]) / TICK, 6) for a, b in zip(times, times[1:])]
        assert steps == [1.0] * len(steps), (path, steps)
        ticks = {stamp for stamp, _ in times[1:-1]}   # the window's edge ticks may fall either side
        for var in ("pv", "op"):
            stamps = [stamp for _, stamp, _ in trace[f"{path}.{var}"]]
            assert len(stamps) == len(set(stamps)), (path, var)   # no value counted twice
            missing = ticks - set(stamps)
            assert not missing, (path, var, sorted(missing))
