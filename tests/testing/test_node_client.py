"""A JavaScript PLC program (tests/node/pi_lockstep.js, npm package modbus-serial) closes the loop in lockstep."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from required import node_with

NODE_DIR = Path(__file__).resolve().parents[1] / "node"
#: A loop without stiction, so the PI settles: first order, gain 3, 10 s lag, 5 s dead time.
PLANT = """\
device: {tick: 0.1}
loops:
  - unit: 1
    valve: {S: 0.0, J: 0.0}
    plant: {num: [3.0], den: [10.0, 1.0], delay: 5.0, pv_range: [-10.0, 10.0]}
"""


@pytest.fixture
def node() -> str:
    """The node binary with tests/node's packages installed (``npm ci`` there, which ``.ci/run`` does)."""
    return node_with(NODE_DIR, "modbus-serial")


def _run(node: str, port: int) -> dict:
    out = subprocess.run([node, str(NODE_DIR / "pi_lockstep.js"), "--port", str(port), "--iterations", "600",
                          "--ticks", "5", "--sp", "2.0", "--kc", "0.5", "--ti", "10"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_node_pi_settles_the_loop_and_two_runs_agree(node, serve, tmp_path):
    config = tmp_path / "plant.yaml"
    config.write_text(PLANT)
    runs = []
    for _ in range(2):
        with serve(str(config), "--lockstep") as port:
            runs.append(_run(node, port))
    first, second = runs
    assert first["pv"] == second["pv"] and first["op"] == second["op"]       # to the last digit
    settled = first["pv"][-100:]                                             # the last 50 simulated seconds
    assert max(abs(pv - 2.0) for pv in settled) < 0.05
    assert first["pv"][0] == 0.0 and len(first["pv"]) == 600
