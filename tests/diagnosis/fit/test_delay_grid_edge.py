"""A dead time on the end of the grid searched is an edge, not a value: the grid is widened, or it is a bound."""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from valve_emulator.diagnosis.explain.pipeline import explain
from valve_emulator.diagnosis.fit.data import WIDEN, delay_at_end, prepare, widens
from valve_emulator.recordings.recording import Recording


def _open_loop(delay: int, T: int = 5000, tau: float = 20.0, seed: int = 3) -> Recording:
    """A first-order plant (τ = ``tau`` samples, gain 0.8) with ``delay`` samples of dead time, driven by a
    random square wave, and measured in white noise: no controller, so no inverse to lock onto."""
    rng = np.random.default_rng(seed)
    op = 50.0 + 10.0 * np.repeat(rng.choice([-1.0, 1.0], T // 60 + 1), 60)[:T]
    a = np.exp(-1.0 / tau)
    y = lfilter([0.0, 0.8 * (1.0 - a)], [1.0, -a], op - 50.0)
    pv = 20.0 + np.concatenate([np.zeros(delay), y[:T - delay]]) + 0.05 * rng.standard_normal(T)
    return Recording(np.arange(T, dtype=float), None, op, None, pv, source="long dead time")


def test_the_dead_time_grid_widens_past_its_100_sample_cap_as_far_as_the_record_allows_and_not_past_t_over_20():
    usual = prepare(_open_loop(10), validation="twofold")
    wide = prepare(_open_loop(10), validation="twofold", reach=WIDEN)
    assert usual.delays.max() == 100 and widens(usual)
    assert wide.delays.max() == 200 and not widens(wide)
    middling = prepare(_open_loop(10, T=2400), validation="twofold", reach=WIDEN)
    assert middling.delays.max() == 200 and 10 * (middling.delays.max() + 1) <= middling.T
    short = prepare(_open_loop(10, T=1000), validation="twofold")
    assert short.delays.max() == 50 and not widens(short)   # T/20, not the cap: a dead time there is a bound


def test_a_dead_time_is_on_the_grids_end_only_within_one_sample_of_its_last_point():
    p = prepare(_open_loop(10), validation="twofold")
    assert delay_at_end(p, 100.0) and delay_at_end(p, 99.0)
    assert not delay_at_end(p, 98.9) and not delay_at_end(p, 0.0)


def test_a_dead_time_beyond_the_usual_grid_is_found_by_widening_it_not_reported_at_its_end():
    e = explain(_open_loop(150), candidates=[], validation="twofold")
    assert abs(e.plant["delay"] - 150.0) < 3.0
    assert not e.plant["delay_is_bound"] and not e.identification["delay_is_bound"]
    assert e.identification["delay_searched"] == 200.0


def test_a_dead_time_beyond_even_the_widened_grid_is_reported_as_a_bound():
    e = explain(_open_loop(230), candidates=[], validation="twofold")
    assert e.plant["delay_is_bound"] and e.identification["delay_is_bound"] and e.plant["delay"] >= 199.0
    assert e.linear["dead time (s)"][1].startswith("≥ ")
