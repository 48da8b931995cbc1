"""The 95 % intervals of a valve's S and J, and of an actuator lag, cover the truth on sticky loops the search did
not make.

Loops are drawn from the independent simulator (:mod:`~valve_emulator.benchmark.independent`: continuous
plants, a data-driven or Karnopp friction model, actuator lag in either order, a wandering load, a PI acting one
sample late), and diagnosed with the nominal model the family hands out. The search's model matches none of them
exactly, so the residual is coloured, the linear part uncertain and the estimate biased by a friction law the
search does not have; an interval that treated the samples as independent and held the plant's poles covered S
on 3 of 22 such loops, one that ended half a grid step beyond its region and ignored how the record's blocks
disagree on 27 of 32 (:mod:`~valve_emulator.diagnosis.fit.uncertainty`).
"""

from __future__ import annotations

import numpy as np
import pytest
from unseen_loops import COVERAGE, Diagnosed, diagnosed_all

pytestmark = pytest.mark.slow  # 40 diagnoses, about 3 minutes on one core

#: Loops drawn per family (seed 7, not the benchmark's 0: tests/unseen_loops.py) and the least share of intervals
#: that must cover. Today S is covered on 29 of 32 of these loops (two deadbands whose valve slips by half its
#: band, the truth 1.5 % beyond the interval's end; a level loop whose plant gain the search put five times too
#: low), J on 28 of 29, a lag on 4 of 4: one more miss of S fails the test.
DRAWS, LEAST = 20, 0.9
#: A jump smaller than this (% travel) is not checked: its relative error says nothing.
MIN_J = 0.5
#: Lag findings reported as a value (with a closed interval) there must be at least this many of.
LAGS = 3


def _covered(d: Diagnosed) -> dict[str, bool]:
    truth, friction = d.truth, d.doc["friction"]
    out = {}
    if friction is not None and friction["travel"] is not None:
        for key in ("S", "J"):
            if key == "J" and truth["J"] < MIN_J:
                continue
            lo, hi = friction["travel"][key]["interval"]
            out[key] = bool(lo <= truth[key] <= hi)
    lags = [f["intervals"].get("tau", [None, None]) for f in d.doc["findings"] if f["physics"] == "actuator_lag"]
    for lo, hi in lags:
        if None not in (lo, hi):     # an open end is a bound (tau on an edge of the range searched), no value
            out["lag"] = bool(lo <= truth["valve"]["actuator_lag"] <= hi)
    return out


def test_the_intervals_of_s_j_and_a_lag_cover_the_truth_on_most_drawn_sticky_loops():
    hits: dict[str, list[bool]] = {"S": [], "J": [], "lag": []}
    for d in diagnosed_all(COVERAGE):
        for key, ok in _covered(d).items():
            hits[key].append(ok)
    for key, got in hits.items():
        least = LAGS if key == "lag" else DRAWS
        assert len(got) >= least, f"{key}: only {len(got)} loops with an estimate"
        assert np.mean(got) >= LEAST, f"{key} covered on {sum(got)}/{len(got)} loops"
