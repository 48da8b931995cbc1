"""A chain candidate acting from an onset on: healthy before it, the candidate's own physics started there."""

from __future__ import annotations

from types import SimpleNamespace

import jsonschema
import numpy as np
import pytest

from valve_emulator import diagnose
from valve_emulator.benchmark.independent import (
    Controller,
    Load,
    Loop,
    Measurement,
    Plant,
    Valve,
    draw,
    nominal_mapping,
    simulate,
)
from valve_emulator.config import loop_from_mapping
from valve_emulator.diagnosis.candidates import ChainContext, get, registry
from valve_emulator.diagnosis.explain.onset import (
    BLOCKS,
    LateOnset,
    Onset,
    Suspected,
    before_part,
    bic_after,
    bic_on,
    late_options,
    post_onset_split,
    suspect_onset,
)
from valve_emulator.diagnosis.explain.search import DELTA_BIC, Search, significant
from valve_emulator.diagnosis.fit.data import HELD_OUT, prepare, with_burn_in
from valve_emulator.diagnosis.fit.fitter import Fitter
from valve_emulator.diagnosis.fit.nominal import nominal_from_config
from valve_emulator.diagnosis.fit.scorer import Scorer, library_burn_in
from valve_emulator.diagnosis.report.schema import schema
from valve_emulator.recordings import Recording

T = 600
OP = 50.0 + 6.0 * np.sin(np.linspace(0.0, 12 * np.pi, T))
CTX = ChainContext(dt=0.5, op=OP, op_span=12.0)
STICTION = get("stiction")


def test_before_the_onset_the_slot_passes_op_through_and_from_it_the_valve_sticks():
    late = LateOnset(STICTION)
    rows = LateOnset.with_onset(np.array([[3.0, 1.0, 2.0]]), 100.0)   # onset at 100 s = sample 200
    mv = late.apply(OP, rows, CTX)[:, 0]
    np.testing.assert_array_equal(mv[:200], OP[:200])
    inner = STICTION.apply(OP[200:], np.array([[3.0, 1.0, 2.0]]), CTX)[:, 0]
    np.testing.assert_array_equal(mv[200:], inner)
    assert np.abs(mv[200:] - OP[200:]).max() > 1.0   # it does stick after the onset


def test_rows_with_different_onsets_each_start_their_own_valve():
    late = LateOnset(STICTION)
    rows = LateOnset.with_onset(np.array([[3.0, 1.0, 2.0]] * 3), np.array([0.0, 50.0, 300.0]))
    mv = late.apply(OP, rows, CTX)
    np.testing.assert_array_equal(mv[:, 0], STICTION.apply(OP, rows[:1, :3], CTX)[:, 0])
    np.testing.assert_array_equal(mv[:100, 1], OP[:100])
    np.testing.assert_array_equal(mv[:, 2], OP)   # an onset at the record's end: a healthy valve throughout


def test_a_late_finding_reports_its_onset_and_counts_it_as_a_parameter():
    late = LateOnset(STICTION)
    p = np.array([3.0, 1.0, 2.0, 812.34])
    assert late.name == "stiction" and late.slot == "valve" and late.twin_role is STICTION.twin_role
    assert late.n_params == STICTION.n_params + 1
    assert late.parameters(p) == {"S": 3.0, "J": 1.0, "onset_s": 812.3}
    assert "from t ≈ 812.3 s" in late.describe(p)


def test_the_refinement_moves_the_onset_and_keeps_its_centre():
    late = LateOnset(STICTION)
    best = np.array([3.0, 1.0, 2.0, 120.0])
    fine = late.refine(CTX, best)
    assert fine.shape[1] == 4
    assert np.any(np.all(fine == best, axis=1))
    onsets = np.unique(fine[:, 3])
    assert onsets.min() < 120.0 < onsets.max() and np.all(onsets >= 0.0)


def test_an_onset_reads_as_its_time_and_the_fits_where_the_finding_acts():
    onset = Onset(onset_s=1541.23, fit_before=12.345, fit_after=56.78)
    assert onset.to_json() == {"onset_s": 1541.2, "fit_before": 12.35, "fit_after": 56.78}
    line = onset.sentence()
    assert "t ≈ 1541 s" in line and "12.3 % without" in line and "56.8 % with" in line


def _loop_error(n: int, onset: int | None, *, first_move: int = 150, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(SP, PV) of a loop: set-point steps from ``first_move`` on, PV following them with a small noise and a
    slow load, and from ``onset`` on a stick-slip cycle (a square wave of period 80 samples, amplitude 1)."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    sp = 50.0 + np.where(k >= first_move, 2.0 * ((k - first_move) // 400 % 2 * 2 - 1), 0.0)
    load = np.convolve(rng.normal(0.0, 0.05, n), np.ones(50) / 50, mode="same")
    pv = sp + 0.05 * rng.normal(size=n) + load
    if onset is not None:
        pv = pv + np.where(k >= onset, np.sign(np.sin(2 * np.pi * (k - onset) / 80.0 + 0.1)), 0.0)
    return sp, pv


@pytest.mark.parametrize("onset", [700, 1500, 2300])
def test_a_loop_that_starts_to_cycle_part_way_is_located_within_a_block(onset):
    sp, pv = _loop_error(3000, onset)
    found = suspect_onset(pv, sp)
    assert isinstance(found, Suspected) and found.signal == "SP − PV"
    assert abs(found.sample - onset) <= 2 * 3000 // BLOCKS
    assert found.rise > 1.0 and found.share > 0.5


def test_without_a_set_point_the_fast_part_of_pv_locates_the_onset():
    """A regulating loop (the set point never moves) recorded without its set point."""
    _, pv = _loop_error(3000, 1800, first_move=3000, seed=1)
    found = suspect_onset(pv, None)
    assert found is not None and found.signal == "PV" and abs(found.sample - 1800) <= 2 * 3000 // BLOCKS


def test_a_loop_that_cycles_throughout_or_never_has_no_onset():
    sp, pv = _loop_error(3000, 0, seed=2)
    assert suspect_onset(pv, sp) is None
    sp, pv = _loop_error(3000, None, seed=3)
    assert suspect_onset(pv, sp) is None


def test_a_cycle_that_starts_with_the_first_set_point_move_is_not_an_onset():
    """Before the set point first moves a loop is quiet whether its valve sticks or not."""
    sp, pv = _loop_error(3000, 600, first_move=600, seed=4)
    assert suspect_onset(pv, sp) is None


def _problem(validation: str):
    n = 3000
    t = np.arange(n, dtype=float)
    op = 50.0 + np.sin(t / 30.0)
    rec = Recording(t=t, sp=None, op=op, mv=None, pv=op + 0.01 * np.cos(t / 7.0))
    return prepare(rec, validation=validation)


def _suspected(sample: int) -> Suspected:
    return Suspected(sample=sample, rise=2.0, share=0.5, signal="SP − PV")


def test_after_a_late_onset_the_held_out_part_is_the_tail_of_the_part_after_it():
    """The usual split holds out the last 30 % (from sample 2100 of 3000): an onset after 60 % of the record
    would leave less than a tenth of it to fit."""
    problem = _problem("split")
    for onset in (1900, 2400):
        late = post_onset_split(problem, _suspected(onset))
        assert late.train == (problem.train[0], onset + round((1 - HELD_OUT) * (3000 - onset)))
        assert late.test == (late.train[1], problem.T)


def test_an_onset_that_leaves_a_tenth_of_the_record_to_fit_keeps_the_usual_split():
    problem = _problem("split")
    for onset in (0, 1500, 1800):
        assert post_onset_split(problem, _suspected(onset)) is problem
    assert post_onset_split(problem, None) is problem


def test_two_fold_validation_keeps_its_folds_after_an_onset():
    problem = _problem("twofold")
    assert post_onset_split(problem, Suspected(sample=2400, rise=2.0, share=0.5, signal="PV")) is problem


@pytest.mark.slow
def test_a_valve_that_starts_to_stick_part_way_is_found_from_its_onset_on():
    """Known truth, from the independent simulator (a continuous FOPDT plant, a data-driven sticky valve, a SIMC PI
    one sample late, a wandering load): S = 4 %, J = 2 % from t = 1500 s of a 3000 s record, the exact nominal
    linear part. The first finding is stiction with S within 25 % and its onset within a tenth of the record,
    and the fit from the onset on rises."""
    steps = ((251.63787441938956, 48.2714394731882), (851.6378744193896, 51.187901073366604),
             (1451.6378744193896, 48.944853372666934), (2051.6378744193894, 48.72503063209396),
             (2651.6378744193894, 48.34256698512441))
    loop = Loop(plant=Plant(kind="fopdt", gain=1.5, tau=20.0, delay=3.0),
                valve=Valve(friction="data_driven", S=4.0, J=2.0, onset=1500.0),
                controller=Controller(kc=1.3101110124466333, ti=20.0, action="reverse", sp_steps=steps),
                load=(Load("filtered", size=0.3, tau=50.0),), measurement=Measurement(noise=0.05), dt=1.0,
                duration=3000.0, seed=2)
    rec, _ = simulate(loop)
    doc = diagnose(rec, loop_from_mapping(nominal_mapping(loop, "late"))).to_json()
    jsonschema.validate(doc, schema())
    assert doc["answer"] == "stiction" and doc["findings"][0]["physics"] == "stiction"
    finding = doc["findings"][0]
    assert finding["parameters"]["S"] == pytest.approx(4.0, rel=0.25)
    onset = finding["onset"]
    assert abs(onset["onset_s"] - 1500.0) <= 300.0
    assert onset["fit_after"] > onset["fit_before"] + 10.0


def _predicting(pred: np.ndarray, k: int):
    """A stand-in for a search model: its linear part predicts ``pred`` (nothing else is read)."""
    return SimpleNamespace(target=None, fit=SimpleNamespace(predict=lambda flow, dt: pred), flow=None, k=k)


def test_an_addition_is_judged_on_the_part_after_an_onset_not_credited_with_the_part_before():
    """``bic_after``: an addition that mends only the part before a late finding's onset gains nothing there,
    one that mends the part after it gains what it mends."""
    T, onset = 2000, 1000
    t = np.arange(T)
    swing = 2.0 * np.sin(2 * np.pi * t / 200.0)
    before, after = np.where(t < onset, swing, 0.0), np.where(t >= onset, swing, 0.0)
    noise = np.random.default_rng(3).normal(0.0, 0.5, T)
    problem = SimpleNamespace(y=before + after + noise, train=(0, T), dt=1.0, prefilter=None)
    old = _predicting(np.zeros(T), k=3)
    gain_before = bic_after(problem, old, onset) - bic_after(problem, _predicting(before, k=4), onset)
    gain_after = bic_after(problem, old, onset) - bic_after(problem, _predicting(after, k=4), onset)
    assert gain_before < 0.0 < DELTA_BIC < gain_after


def _late_model(pred: np.ndarray, k: int, onset_s: float | None, *, taus: tuple = (), delay: float = 0.0):
    """A stand-in for a search model predicting ``pred``, with a valve that starts at ``onset_s`` (s; None: no
    late finding) and a linear part of time constants ``taus`` and dead time ``delay``."""
    model = _predicting(pred, k)
    model.fit.structure = SimpleNamespace(taus=taus, fixed_poles=(), delay=delay)
    model.active = () if onset_s is None else (
        SimpleNamespace(name="stiction", candidate=LateOnset(STICTION), params=np.array([3.0, 1.0, 2.0, onset_s])),)
    return model


def test_an_addition_beside_a_late_valve_must_also_fit_the_healthy_part_before_its_onset():
    """``Search.holds_before_onset``: an addition that mends the cycles after the onset but spoils the healthy
    part before it, or does not pay for its parameter there, does not hold; one no worse there does; a part
    before the onset shorter than a tenth of the record, or a model in which nothing starts late, is not
    judged."""
    T, onset = 2000, 1000
    t = np.arange(T)
    swing = 2.0 * np.sin(2 * np.pi * t / 200.0)
    after = np.where(t >= onset, swing, 0.0)
    noise = np.random.default_rng(4).normal(0.0, 0.5, T)
    problem = SimpleNamespace(y=after + noise, train=(0, T), T=T, dt=1.0, prefilter=None)
    search = Search.__new__(Search)
    search.scorer = SimpleNamespace(p=problem)
    old = _late_model(np.zeros(T), k=3, onset_s=onset)
    after_only = _late_model(after, k=4, onset_s=onset)   # mends after, leaves before: a parameter for nothing
    spoiling = _late_model(swing, k=4, onset_s=onset)     # mends after, spoils before
    window = before_part(problem, onset, old, spoiling)
    assert window == (0, onset)
    assert bic_on(problem, old, window) - bic_on(problem, spoiling, window) < -DELTA_BIC
    assert search.holds_before_onset(_late_model(after, k=3, onset_s=onset), old)
    assert not search.holds_before_onset(spoiling, old)
    assert not search.holds_before_onset(after_only, old)
    assert before_part(problem, 150, old) is None
    assert search.holds_before_onset(_late_model(swing, k=4, onset_s=150.0), _late_model(np.zeros(T), 3, 150.0))
    assert search.holds_before_onset(spoiling, _late_model(swing, k=4, onset_s=None))


def test_the_part_before_an_onset_starts_where_the_linear_part_has_settled_not_after_the_valves_burn_in():
    """A valve that starts late is healthy before its onset, so the part before it is judged from where the
    linear part has forgotten its initial state (its dead time and five time constants), even where the fit
    part starts later (after the valve candidates' burn-in)."""
    T = 3000
    problem = SimpleNamespace(train=(1050, T), T=T, dt=1.0)
    slow = _late_model(np.zeros(T), 3, 1100.0, taus=(30.0,), delay=5.0)
    fast = _late_model(np.zeros(T), 3, 1100.0, taus=(2.0,))
    assert before_part(problem, 1100, fast, slow) == (159, 1100)
    assert before_part(problem, 1100, fast) == (14, 1100)
    assert before_part(problem, 3500, fast) == (14, T)
    assert before_part(SimpleNamespace(train=(10, T), T=T, dt=1.0), 1100, slow) == (10, 1100)


@pytest.mark.slow
def test_under_a_wandering_load_a_late_valve_counts_by_the_drifting_load_noise_model_not_the_free_run():
    """Draw 6 of the ``late_onset`` property test (a continuous second-order plant, a data-driven valve of S 3.4 %
    from t = 634 s, a wandering load; its nominal model): before the onset the controller cancels the load with
    OP, the free run replays those moves, and the linear part fitted around a healthy valve shrinks its gain.
    Fitted in the free run, the late valve's band is too small to be one; fitted through the drifting-load noise
    model's prefilter it is the drawn valve (S within 25 %, onset within a tenth of the record), and it counts
    against the healthy valve by that noise model's BIC, though not by the free run's significance rule."""
    rec, truth, mapping = draw("late_onset", np.random.default_rng([32, 6]))
    nom = nominal_from_config(loop_from_mapping(mapping), rec.dt)
    lib = registry()
    problem = prepare(rec, nominal_delay=nom.delay, settle_time=nom.settle_time, validation="split")
    problem = with_burn_in(problem, library_burn_in(problem, nom, lib))
    suspected = suspect_onset(problem.pv, rec.sp)
    problem = post_onset_split(problem, suspected)
    fitter = Fitter(Scorer(problem, nom, lib))
    search = Search(fitter, suspected=suspected)
    healthy = search.validated(fitter.base())
    whole = next(o for o in fitter.evaluate(healthy, STICTION) if o.added == ("stiction",))
    free_run, late = late_options(fitter, healthy, STICTION, whole, suspected)
    assert free_run is None
    S, onset = late.model.by_slot()["valve"].params[[0, -1]]
    assert abs(S - truth["S"]) <= 0.25 * truth["S"]
    assert abs(onset - truth["onset"]) <= 0.1 * (rec.t[-1] - rec.t[0])
    assert not significant(late.model, healthy) and search.late_counts(late.model, healthy)


def test_a_valve_that_sticks_from_the_start_of_a_loop_at_rest_is_reported_without_an_onset():
    """Known truth, from the independent simulator: the README's concentration loop (3 e^(-10 s)/(10 s + 1), PI
    kc 0.2, Ti 10 s, Choudhury, Thornhill & Shah 2003 Table 1) with a valve that sticks from the first sample
    (S = 5 %, J = 2 %), at rest until its set point steps at t = 10 s. The loop starts to cycle only at the first
    slip, once the integral has moved OP through the band; the part before it is shorter than the linear part
    takes to settle plus a tenth of the record, so it cannot show a healthy valve: stiction, with no onset."""
    loop = Loop(plant=Plant(kind="fopdt", gain=3.0, tau=10.0, delay=10.0, pv0=0.0),
                valve=Valve(friction="data_driven", S=5.0, J=2.0),
                controller=Controller(kc=0.2, ti=10.0, action="reverse", sp_steps=((10.0, 1.0),)),
                measurement=Measurement(noise=0.01), dt=0.5, duration=1500.0, seed=5)
    rec, _ = simulate(loop)
    doc = diagnose(rec, loop_from_mapping(nominal_mapping(loop, "from_the_start"))).to_json()
    assert doc["answer"] == "stiction" and doc["findings"][0]["physics"] == "stiction"
    finding = doc["findings"][0]
    assert finding["parameters"]["S"] == pytest.approx(5.0, rel=0.25)
    assert finding["parameters"]["J"] == pytest.approx(2.0, rel=0.25)
    assert "onset_s" not in finding["parameters"] and finding.get("onset") is None
    assert "from t ≈" not in doc["verdict"]


@pytest.mark.slow
def test_a_valve_that_sticks_throughout_is_not_reported_as_starting_part_way():
    """Known truth, from the independent simulator: a flow loop whose data-driven valve sticks from the first sample
    (S 4.03 %, J 2.55 %; draw ``flow_sticky`` (7, 5, 17) of ``tests/unseen_loops.py``), diagnosed as plant data.
    A change point is located in its control error near 330 s, and the late valve there led: the search's fit part
    starts at 525 s (after the valve candidates' burn-in), where a valve sticking from 332 s on and the
    whole-record one are the same model (the late one 6 higher in BIC for its onset). The part before the onset
    does not show a healthy valve (a valve sticking there fits it better under both noise models), so it is
    answered stiction without an onset (before: "from t ≈ 331.9 s on"), S within 25 % (J 3.80 for 2.55, as
    before: not judged here)."""
    rec, truth, _ = draw("flow_sticky", np.random.default_rng([7, 5, 17]))
    assert truth["valve"]["onset"] == 0.0 and truth["sticky"]
    doc = diagnose(rec, op_range=(0.0, 100.0)).to_json()
    assert doc["answer"] == "stiction"
    friction = [f for f in doc["findings"] if f["physics"] in ("stiction", "deadband")]
    assert len(friction) == 1 and friction[0].get("onset") is None
    assert "onset_s" not in friction[0]["parameters"] and "from t ≈" not in doc["verdict"]
    assert friction[0]["parameters"]["S"] == pytest.approx(truth["S"], rel=0.25)
