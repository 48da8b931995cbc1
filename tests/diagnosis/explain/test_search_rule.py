"""The search's significance rule, on canned options: which option a round accepts, and when the rounds stop.

A stub fitter returns fixed options (BIC and held-out fit chosen by hand), so the rule itself is exercised in
milliseconds, without fitting anything."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from valve_emulator.diagnosis.candidates.base import Kind
from valve_emulator.diagnosis.explain.search import DELTA_BIC, DELTA_FIT, Search, significant
from valve_emulator.diagnosis.fit.chain import Active
from valve_emulator.diagnosis.fit.records import Model, Option

STICTION = SimpleNamespace(name="stiction", slot="valve", kind=Kind.CHAIN)
DEAD_TIME = SimpleNamespace(name="dead_time", slot="delay", kind=Kind.DELAY)
LAG = SimpleNamespace(name="actuator_lag", slot="actuator", kind=Kind.CHAIN)
TUNING = SimpleNamespace(name="tuning", slot="loop", kind=Kind.LOOP)
LIBRARY = {c.name: c for c in (STICTION, DEAD_TIME, LAG, TUNING)}


def _model(bic: float, heldout: float, *cands, delay_free: bool = False) -> Model:
    return Model(active=tuple(Active(c, np.zeros(1)) for c in cands), fit=None, delay_free=delay_free, k=1,
                 bic=bic, heldout=heldout, y_hat=np.zeros(1), flow=np.zeros(1))


def _option(bic: float, heldout: float, *cands) -> Option:
    return Option(added=tuple(c.name for c in cands), model=_model(bic, heldout, *cands), coarse=None, scan=None,
                  fine=None)


class _CannedFitter:
    """Returns, for each model and candidate, the options a table names (none for the others)."""

    def __init__(self, base: Model, options: dict[tuple[tuple[str, ...], str], list[Option]]) -> None:
        self.scorer = SimpleNamespace(library=LIBRARY, p=SimpleNamespace(validation="split"), aim=lambda model: None)
        self.nominal = SimpleNamespace(given=False)   # no late onsets are searched without a nominal model
        self._base, self._options, self.asked = base, options, []

    def base(self) -> Model:
        return self._base

    def evaluate(self, model: Model, cand) -> list[Option]:
        self.asked.append((model.names, cand.name))
        return list(self._options.get((model.names, cand.name), []))


def test_significance_needs_both_the_bic_fall_and_the_held_out_gain():
    old = _model(100.0, 50.0)
    assert significant(_model(100.0 - DELTA_BIC, 50.0 + DELTA_FIT), old)
    assert not significant(_model(100.0 - DELTA_BIC + 0.01, 90.0), old)
    assert not significant(_model(0.0, 50.0 + DELTA_FIT - 0.01), old)


def test_a_round_accepts_the_lowest_bic_option_that_counts_not_the_lowest_bic():
    base = _model(1000.0, 60.0)
    lag_overfits = _option(900.0, 60.1, LAG)       # far lower BIC, but no held-out gain
    stiction = _option(950.0, 70.0, STICTION)
    fitter = _CannedFitter(base, {((), "actuator_lag"): [lag_overfits], ((), "stiction"): [stiction]})
    rnd = Search(fitter).round(base, 1)
    assert rnd.chosen.label == "stiction" and rnd.chosen.model is stiction.model
    assert [o.label for o in rnd.options] == ["actuator_lag", "stiction"]   # sorted by BIC
    assert ((), "tuning") not in fitter.asked                                # loop candidates are not searched


def test_a_pair_is_refused_when_one_of_its_parts_carries_no_weight():
    # stiction + dead time is much better than nothing, but barely better than stiction alone: stiction wins.
    base = _model(1000.0, 60.0)
    alone = _option(950.0, 70.0, STICTION)
    pair = _option(945.0, 70.2, STICTION, DEAD_TIME)
    fitter = _CannedFitter(base, {((), "stiction"): [alone, pair]})
    assert Search(fitter).round(base, 1).chosen.label == "stiction"


def test_a_pair_is_accepted_when_it_counts_against_each_of_its_parts():
    base = _model(1000.0, 60.0)
    alone = _option(950.0, 70.0, STICTION)
    pair = _option(900.0, 80.0, STICTION, DEAD_TIME)
    fitter = _CannedFitter(base, {((), "stiction"): [alone, pair]})
    assert Search(fitter).round(base, 1).chosen.label == "stiction + dead_time"


def test_the_rounds_stop_at_the_first_round_without_an_option_that_counts():
    base = _model(1000.0, 60.0)
    stiction = _option(950.0, 70.0, STICTION)
    after = stiction.model
    lag_after = _option(after.bic - 5.0, 75.0, STICTION, LAG)   # a held-out gain, but too small a BIC fall
    fitter = _CannedFitter(base, {((), "stiction"): [stiction], (("stiction",), "actuator_lag"): [lag_after]})
    model, rounds = Search(fitter).run()
    assert [r.chosen and r.chosen.label for r in rounds] == ["stiction", None]
    assert model is after   # no earlier physics to refine again: the accepted option's model is final
    assert rounds[1].baseline is after and rounds[1].options[0].model is lag_after.model


def test_a_model_with_a_free_dead_time_is_not_offered_the_dead_time_again():
    base = _model(1000.0, 60.0, delay_free=True)
    fitter = _CannedFitter(base, {})
    Search(fitter).round(base, 1)
    assert sorted(name for _, name in fitter.asked) == ["actuator_lag", "stiction"]


def _held_integrator(fitter: _CannedFitter, monkeypatch, loads: dict[tuple[str, ...], float]) -> None:
    """``fitter``'s nominal made a held integrating plant, and the drifting-load BIC of each model by its names."""
    fitter.nominal = SimpleNamespace(given=True, structure=SimpleNamespace(integrating=True, gain=0.02))
    monkeypatch.setattr("valve_emulator.diagnosis.explain.search.load_bic",
                        lambda scorer, model: (loads[model.names], 0.9))


def test_on_a_held_integrator_the_round_takes_the_option_lowest_under_the_drifting_load(monkeypatch):
    # The characteristic is lower in BIC and better held out, the valve lower under the drifting-load noise model:
    # on a held integrating plant the noise model decides (docs/diagnosis.md, *A level loop's model is held*).
    base = _model(1000.0, 60.0)
    characteristic = _option(800.0, 82.0, LAG)
    stiction = _option(850.0, 22.0, STICTION)
    fitter = _CannedFitter(base, {((), "actuator_lag"): [characteristic], ((), "stiction"): [stiction]})
    _held_integrator(fitter, monkeypatch, {(): 500.0, ("actuator_lag",): 400.0, ("stiction",): 210.0})
    assert Search(fitter).round(base, 1).chosen.label == "stiction"
    fitter.nominal = SimpleNamespace(given=True, structure=SimpleNamespace(integrating=True, gain=None))
    assert Search(fitter).round(base, 1).chosen.label == "actuator_lag"   # not held: the free run's rule


def test_on_a_held_integrator_an_option_must_lower_both_bics_by_the_threshold(monkeypatch):
    base = _model(1000.0, 60.0)
    stiction = _option(1000.0 - DELTA_BIC + 0.01, 90.0, STICTION)   # the search's BIC falls too little
    lag = _option(900.0, 90.0, LAG)                                  # the drifting-load BIC falls too little
    fitter = _CannedFitter(base, {((), "actuator_lag"): [lag], ((), "stiction"): [stiction]})
    _held_integrator(fitter, monkeypatch, {(): 500.0, ("actuator_lag",): 500.0 - DELTA_BIC + 0.01,
                                           ("stiction",): 100.0})
    assert Search(fitter).round(base, 1).chosen is None
