"""Figures and reports speak the answer's units: % travel only when the travel span is known.

Known truth: the proof cases' sticky concentration loop (S = 5 %, J = 2 % of travel), concealed (OP and PV
only). Given with its travel span, the figures say "% travel"; exported mean-centred without a span, the
answer is in OP's own units and so are the axes, the candidate ranking and the linear part's gain — a "%"
there would claim a span nobody gave.
"""

import matplotlib.figure
import numpy as np
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.detectors.base import oscillation
from valve_emulator.diagnosis.report.plot_loop import plot_loop


@pytest.fixture(scope="module")
def loop():
    rec, _, _ = generate(CASES[0], duration=1200.0)
    return rec


@pytest.fixture(scope="module")
def scaled(loop):
    """The loop exported mean-centred and in tenths of a per cent (S = 50, J = 20 in OP's units)."""
    return ve.diagnose({"t": loop.t, "op": 10.0 * (loop.op - loop.op.mean()), "pv": loop.pv})


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


def test_a_plant_figure_names_the_identified_model_not_a_nominal_one(scaled, monkeypatch, tmp_path):
    titles: list[str] = []
    save = matplotlib.figure.Figure.savefig

    def capture(fig, *args, **kwargs):
        titles.extend(ax.get_title() for ax in fig.axes)
        titles.extend(t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts())
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    scaled.plot(tmp_path / "d.png")
    assert "Residual of the linear model identified from the data (windows shaded)" in titles
    assert not any("nominal model" in t for t in titles)


def test_the_candidate_ranking_gives_parameters_in_op_s_units(scaled):
    friction = next(f for f in scaled.explanation.findings if f.physics in ("stiction", "deadband"))
    assert friction.parameters["S"] == pytest.approx(50.0, rel=0.1)             # 10 × 5 % travel
    chosen = next(r for r in scaled.explanation.ranking if r.chosen and r.option == friction.physics)
    assert f"S={friction.parameters['S']:.4g}" in chosen.parameters


def test_the_linear_part_states_its_gain_per_op_unit_and_what_was_identified(scaled):
    linear = scaled.explanation.linear
    assert "gain, PV per OP unit" in linear                                     # not "per % flow"
    assert linear["integrating"] == ("—", "no")                                 # no nominal; a self-regulating plant
    gain_given = ve.diagnose({"t": scaled.recording.t, "op": scaled.recording.op / 10.0 + 50.0,
                              "pv": scaled.recording.pv}, op_range=(0.0, 100.0)).explanation.linear
    assert float(linear["gain, PV per OP unit"][1]) == pytest.approx(
        float(gain_given["gain, PV per % flow"][1]) / 10.0, rel=0.05)          # the map's scale, inverted


def test_options_the_two_fold_rule_did_not_cross_validate_show_no_fit(scaled):
    rows = [line for line in scaled.report().splitlines() if line.startswith("| 1 |")]
    assert rows and not any("nan" in line for line in rows)
    unchosen = [r for r in scaled.explanation.ranking if r.heldout != r.heldout]
    assert unchosen, "the two-fold rule leaves some options without a held-out fit"
    assert any("| — |" in line for line in rows)


def test_the_figure_shows_whole_cycles_of_a_finely_sampled_record(monkeypatch, tmp_path):
    # The concentration loop with S = 5 %, J = 2 % sampled at 0.1 s: its cycle (about 140 s) is 1,400
    # samples, so a fixed number of samples would show a fraction of one.
    truth = ve.load_loop("configs/table1/concentration_undershoot.yaml")
    rec = ve.simulate_loop(truth, duration=1500.0)                # held out: the last 450 s, three cycles
    d = ve.diagnose(rec, model="configs/table1/concentration_no_stiction.yaml", candidates=["stiction"])
    assert d.explanation.findings[0].physics == "stiction"
    spans = {}
    save = matplotlib.figure.Figure.savefig

    def capture(fig, *args, **kwargs):
        held_out, valve = fig.axes[1], fig.axes[2]
        spans["pv"] = np.ptp(held_out.get_lines()[0].get_xdata())
        spans["op"] = valve.get_lines()[0].get_xdata()
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    d.plot(tmp_path / "d.png")
    period = oscillation(rec.op).period * rec.dt
    assert 130.0 < period < 160.0
    assert spans["pv"] >= 3 * period                      # the held-out panel: at least three whole cycles
    op = spans["op"]                                      # the valve panel: OP's whole swing, both ways
    assert np.ptp(op) >= 0.9 * np.ptp(rec.op[-len(op):]) and len(op) * rec.dt >= 1.5 * period
