"""Writing up findings: the stiction scan's ΔBIC picture, the effective sample size of the intervals and the
parameter text of an option."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from valve_emulator.diagnosis.candidates.base import Kind
from valve_emulator.diagnosis.explain.findings import _n_scale, param_text, stiction_surface
from valve_emulator.diagnosis.explain.search import Round
from valve_emulator.diagnosis.fit.chain import Active
from valve_emulator.diagnosis.fit.records import Model, Option, Surface

STICTION = SimpleNamespace(name="stiction", slot="valve", kind=Kind.CHAIN,
                           parameters=lambda p: {"S": float(p[0]), "J": float(p[1]), "start": None})
LAG = SimpleNamespace(name="actuator_lag", slot="actuator", kind=Kind.CHAIN, parameters=lambda p: {"tau": float(p[0])})


def _model(*actives: Active, y_hat: np.ndarray | None = None) -> Model:
    return Model(active=actives, fit=None, delay_free=False, k=1, bic=0.0, heldout=0.0,
                 y_hat=np.zeros(1) if y_hat is None else y_hat, flow=np.zeros(1))


def _stiction_option(sse: np.ndarray, best=(2.0, 1.0), load_model: bool = False) -> Option:
    # Rows (S, J, start): two starts for each (S, J) on a 2 × 3 grid.
    rows = np.array([(s, j, st) for st in (0.0, 1.0) for j in (0.0, 1.0) for s in (1.0, 2.0, 3.0)])
    model = _model(Active(STICTION, np.array([*best, 0.0])))
    return Option(added=("stiction",), model=model, coarse=None,
                  scan=Surface(candidate="stiction", params=rows, sse=sse, n=100, load_model=load_model), fine=None)


def test_the_stiction_picture_is_the_delta_bic_over_s_and_j_of_the_best_start():
    sse = np.full(12, 4.0)
    sse[4] = 1.0            # S = 2, J = 1, start 0: the best
    sse[4 + 6] = 0.5 * 4.0  # the same (S, J) from start 1: worse, not shown
    sse[0 + 6] = 2.0        # S = 1, J = 0, start 1: better than start 0's 4.0
    option = _stiction_option(sse)
    rounds = [Round(baseline=_model(), options=(option,), chosen=option)]
    (S, J, grid), best, load_model = stiction_surface(rounds)
    assert not load_model
    assert S.tolist() == [1.0, 2.0, 3.0] and J.tolist() == [0.0, 1.0] and best == (2.0, 1.0)
    assert grid[1, 1] == 0.0
    assert grid[0, 0] == pytest.approx(100 * np.log(2.0))
    assert grid[0, 1] == pytest.approx(100 * np.log(4.0))


def test_the_stiction_picture_comes_from_the_round_that_accepted_stiction():
    first = _stiction_option(np.full(12, 1.0), best=(1.0, 0.0))
    other = Option(added=("actuator_lag",), model=_model(Active(LAG, np.array([3.0]))), coarse=None, scan=None,
                   fine=None)
    accepted = _stiction_option(np.linspace(1.0, 2.0, 12), best=(3.0, 1.0))
    rounds = [Round(baseline=_model(), options=(first, other), chosen=other),
              Round(baseline=_model(), options=(accepted,), chosen=accepted)]
    assert stiction_surface(rounds)[1] == (3.0, 1.0)
    assert stiction_surface(rounds[:1] + [Round(baseline=_model(), options=(), chosen=None)])[1] == (1.0, 0.0)
    assert stiction_surface([Round(baseline=_model(), options=(other,), chosen=None)]) == (None, None, False)


def test_the_stiction_picture_says_when_its_scan_was_scored_through_the_drifting_load_noise_model():
    """A late valve's second fit scores its scan through the noise model's prefilter: the figure must say so,
    since its ΔBIC are not the free run's."""
    late = _stiction_option(np.linspace(1.0, 2.0, 12), load_model=True)
    assert stiction_surface([Round(baseline=_model(), options=(late,), chosen=late)])[2] is True


def test_an_autocorrelated_residual_counts_fewer_effective_samples_with_and_without_a_model():
    rng = np.random.default_rng(0)
    e = np.zeros(20000)
    w = rng.normal(size=e.size)
    for k in range(1, e.size):
        e[k] = 0.8 * e[k - 1] + w[k]
    for validation in ("twofold", "split"):
        problem = SimpleNamespace(validation=validation, train=(0, e.size), y=e)
        assert _n_scale(problem, _model(y_hat=np.zeros(e.size))) == pytest.approx((1 - 0.8) / (1 + 0.8), rel=0.2)
    white = SimpleNamespace(validation="split", train=(0, w.size), y=w)
    assert _n_scale(white, _model(y_hat=np.zeros(w.size))) > 0.9


def test_the_parameter_text_names_only_the_added_physics_and_skips_unset_parameters():
    model = _model(Active(STICTION, np.array([2.5, 0.5, 0.0])), Active(LAG, np.array([3.0])))
    assert param_text(model, ("stiction",)) == "S=2.5, J=0.5"
    assert param_text(model, ("stiction", "actuator_lag")) == "S=2.5, J=0.5; tau=3"
