"""The coarse stages of a long record's search score windows spread over its fit part, not all of it."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator import diagnose
from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.benchmark.independent import (
    Controller,
    Load,
    Loop,
    Measurement,
    Plant,
    Valve,
    nominal_mapping,
    simulate,
)
from valve_emulator.config import loop_from_mapping
from valve_emulator.diagnosis.candidates import get
from valve_emulator.diagnosis.explain import pipeline
from valve_emulator.diagnosis.fit import windows
from valve_emulator.diagnosis.fit.data import prepare
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.nominal import nominal_from_config
from valve_emulator.diagnosis.fit.scorer import Scorer
from valve_emulator.diagnosis.fit.windows import COUNT, LEAD_IN, LENGTH, LONG, coarse_windows, window_problem


def test_a_fit_part_shorter_than_the_threshold_is_scored_whole():
    assert coarse_windows((300, 300 + LONG - 1)) == ()


@pytest.mark.parametrize("train", [(4902, 70_000), (300, 300 + LONG), (12_345, 99_999)])
def test_the_windows_run_from_the_fit_parts_first_sample_to_its_last_evenly_after_their_lead_in(train):
    w0, w1 = train
    ws = coarse_windows(train)
    assert len(ws) == COUNT
    assert ws[0].start == w0 and ws[-1].stop == w1
    assert all(w.scored == LENGTH for w in ws)
    assert all(a.stop <= b.start for a, b in zip(ws, ws[1:]))           # in order, never overlapping
    gaps = np.diff([w.start for w in ws])
    assert gaps.max() - gaps.min() <= 1                                    # evenly spread
    assert all(w.start - w.lead == min(LEAD_IN, w.start) and w.lead >= 0 for w in ws)


def test_a_windows_lead_in_is_cut_at_the_records_first_sample():
    ws = coarse_windows((100, 100 + LONG))
    assert ws[0].lead == 0 and ws[0].start == 100
    assert ws[1].start - ws[1].lead == LEAD_IN


def _long_problem(samples: int = 40_000):
    case = CASES[0]
    rec, nominal, _ = generate(case, duration=samples - 1 + case.cut)
    nom = nominal_from_config(nominal, float(rec.t[1] - rec.t[0]))
    return prepare(rec, nominal_delay=nom.delay, settle_time=nom.settle_time), nom


def test_a_windows_sub_record_scores_the_windows_samples_of_the_record_on_its_scale():
    problem, _ = _long_problem()
    w = coarse_windows(problem.train)[2]
    sub = window_problem(problem, w)
    assert sub.n_fit == LENGTH and sub.T - sub.n_fit == w.start - w.lead
    a, b = sub.train
    assert np.array_equal(sub.y[a:b], problem.y[w.start:w.stop])
    assert np.array_equal(sub.op, problem.op[w.lead:w.stop])
    assert (sub.y_scale, sub.y_mean, sub.op_span) == (problem.y_scale, problem.y_mean, problem.op_span)
    assert np.array_equal(sub.delays, problem.delays)


def test_a_candidate_whose_grid_is_read_from_the_data_is_scored_on_the_whole_record():
    """Stiction's grids depend on OP's span only, so its windows score the same rows; a saturation's grid is
    OP's percentiles, which differ from window to window, so it is scored on the whole record."""
    problem, nom = _long_problem()
    lib = {"stiction": get("stiction"), "saturation": get("saturation")}
    fitter = Fitter(Scorer(problem, nom, lib))
    base = fitter.base()
    sticky = fitter.coarse_parts(base, lib["stiction"])
    assert len(sticky) == COUNT and sum(p.n_fit for p in sticky) == COUNT * LENGTH
    whole = fitter.coarse_parts(base, lib["saturation"])
    assert len(whole) == 1 and whole[0].scorer is fitter.scorer


def test_a_record_whose_loop_changes_part_way_is_scored_whole():
    """The pipeline's rule for a located onset: a fitter that may not use windows scores the whole record."""
    problem, nom = _long_problem()
    lib = {"stiction": get("stiction")}
    fitter = Fitter(Scorer(problem, nom, lib), windowed=False)
    assert fitter.windows == ()
    parts = fitter.coarse_parts(fitter.base(), lib["stiction"])
    assert len(parts) == 1 and parts[0].n_fit == problem.n_fit


def _answer(doc: dict) -> tuple:
    f = doc["findings"][0]
    return doc["answer"], f["physics"], f["parameters"], f.get("intervals")


@pytest.mark.slow
def test_a_long_record_gets_the_same_answer_s_j_and_intervals_as_when_scored_whole(monkeypatch):
    """The proof cases' concentration loop (S = 5, J = 2) over 40,000 samples, its nominal model given:
    windowed coarse stages end in the same finding, parameters and intervals as the whole record scored."""
    case = CASES[0]
    rec, nominal, _ = generate(case, duration=40_000 - 1 + case.cut)
    windowed = _answer(diagnose(rec, nominal).to_json())
    monkeypatch.setattr(windows, "LONG", 10 ** 12)
    whole = _answer(diagnose(rec, nominal).to_json())
    assert windowed == whole
    assert windowed[1] == "stiction" and windowed[2]["S"] == pytest.approx(5.0, rel=0.05)


@pytest.mark.slow
def test_a_valve_that_starts_to_stick_late_in_a_long_record_is_found_from_its_onset_on():
    """Known truth, from the independent simulator (as the 3,000-sample test of the late onset, over 100,000
    samples): S = 4 %, J = 2 % from t = 70,000 s, the exact nominal linear part. The first finding is stiction
    with S within 25 % and its onset within a tenth of the record, and the fit from the onset on rises (the
    change is located before the search, so its coarse stages score the whole record: on windows, of which one
    falls after the onset, the first finding was a deadband)."""
    rng = np.random.default_rng(2)
    steps = tuple((251.6 + 600.0 * k, float(rng.uniform(48.0, 51.5))) for k in range(166))
    loop = Loop(plant=Plant(kind="fopdt", gain=1.5, tau=20.0, delay=3.0),
                valve=Valve(friction="data_driven", S=4.0, J=2.0, onset=70_000.0),
                controller=Controller(kc=1.3101110124466333, ti=20.0, action="reverse", sp_steps=steps),
                load=(Load("filtered", size=0.3, tau=50.0),), measurement=Measurement(noise=0.05), dt=1.0,
                duration=100_000.0, seed=2)
    rec, _ = simulate(loop)
    doc = diagnose(rec, loop_from_mapping(nominal_mapping(loop, "late"))).to_json()
    assert doc["answer"] == "stiction" and doc["findings"][0]["physics"] == "stiction"
    finding = doc["findings"][0]
    assert finding["parameters"]["S"] == pytest.approx(4.0, rel=0.25)
    onset = finding["onset"]
    assert abs(onset["onset_s"] - 70_000.0) <= 10_000.0
    assert onset["fit_after"] > onset["fit_before"] + 10.0


@pytest.mark.parametrize("with_model", [True, False])
def test_only_a_search_with_a_nominal_model_may_score_windows(monkeypatch, with_model):
    """Without a model the coarse stage also chooses the poles, up to a tenth of the record: longer than a
    window, so plant data are searched on the whole record whatever its length."""
    made = []

    class Recording(Fitter):
        def __init__(self, scorer, *, windowed=True):
            made.append(windowed)
            super().__init__(scorer, windowed=windowed)

    monkeypatch.setattr(pipeline, "Fitter", Recording)
    case = CASES[0]
    rec, nominal, _ = generate(case, duration=800 + case.cut)
    pipeline.explain(rec, nominal if with_model else None)
    assert made and all(w is with_model for w in made)
