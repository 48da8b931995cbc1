"""Drawing the package's figures leaves matplotlib's backend alone: a notebook user who chose one keeps it.

Every figure (the paper-style figures, the diagnosis figure, one loop's assessment figure) is drawn on a
``matplotlib.figure.Figure`` of its own and written straight to a PNG, without pyplot."""

from __future__ import annotations

import subprocess
import sys

_SCRIPT = """
import sys
import matplotlib
matplotlib.use("svg")   # what a user chose; any backend but Agg shows a switch

import numpy as np
from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis.api import diagnose
from valve_emulator.diagnosis.assess.decision import assess_uniform
from valve_emulator.diagnosis.report.plot_loop import plot_loop
from valve_emulator.simulation.figures import plot_closed_loop, plot_open_loop_rows
from valve_emulator.simulation.loop import simulate_loop
assert matplotlib.get_backend() == "svg", ("import", matplotlib.get_backend())

out = sys.argv[1]
rec, nominal, true = generate(CASES[0], duration=900.0)
plot_closed_loop(simulate_loop(true, 300.0), f"{out}/closed_loop.png", title="closed loop")
t = np.linspace(0.0, 10.0, 101)
plot_open_loop_rows(t, 50 + 10 * np.sin(t), [("a", 50 + 9 * np.sin(t))], f"{out}/open_loop.png")
diagnose(rec, nominal).plot(f"{out}/diagnosis.png")
plot_loop(rec, assess_uniform(rec), f"{out}/loop.png", title="plant data")
print(matplotlib.get_backend())
"""


def test_importing_and_drawing_every_figure_keeps_the_users_backend(tmp_path):
    done = subprocess.run([sys.executable, "-c", _SCRIPT, str(tmp_path)], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "svg"
    for name in ("closed_loop", "open_loop", "diagnosis", "loop"):
        assert (tmp_path / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
