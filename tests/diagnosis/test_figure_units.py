"""The figures label OP, MV, S and J in the units the answer is in: % travel only when the travel span is known.

Known truth: the proof cases' sticky concentration loop (S = 5 %, J = 2 % of travel), concealed (OP and PV
only). Given with its travel span, the figures say "% travel"; exported mean-centred without a span, the
answer is in OP's own units and so are the axes — a "%" there would claim a span nobody gave.
"""

import matplotlib.figure
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis.report.plot_loop import plot_loop


@pytest.fixture(scope="module")
def loop():
    rec, _, _ = generate(CASES[0], duration=1200.0)
    return rec


def _labels(monkeypatch, draw) -> set[str]:
    """Every axis label of the figures that ``draw`` saves."""
    seen: set[str] = set()
    save = matplotlib.figure.Figure.savefig

    def capture(fig, *args, **kwargs):
        for ax in fig.axes:
            seen.update((ax.get_xlabel(), ax.get_ylabel()))
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    draw()
    return seen - {""}


@pytest.mark.parametrize("known_span", [True, False])
def test_op_s_and_j_axes_carry_the_answer_s_units(loop, tmp_path, monkeypatch, known_span):
    data = {"t": loop.t, "op": loop.op if known_span else loop.op - loop.op.mean(), "pv": loop.pv}
    d = ve.diagnose(data, op_range=(0.0, 100.0) if known_span else None)
    assert d.answer == "stiction"
    units = "% travel" if known_span else "its own units"

    diagnosis = _labels(monkeypatch, lambda: d.plot(tmp_path / "d.png"))
    assert {f"S ({units})", f"J ({units})", f"OP ({units})", f"MV ({units})"} <= diagnosis
    loop_figure = _labels(monkeypatch, lambda: plot_loop(d.recording, d.assessment, tmp_path / "l.png"))
    assert f"OP ({units})" in loop_figure
    if not known_span:
        assert not any("%" in label for label in diagnosis | loop_figure)
