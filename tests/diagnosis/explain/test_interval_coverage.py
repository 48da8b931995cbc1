"""The 95 % intervals of a valve's S and J cover the truth on sticky loops the search did not make.

Loops are drawn from the independent simulator (:mod:`~valve_emulator.benchmark.independent`: continuous
plants, a data-driven or Karnopp friction model, actuator lag in either order, a wandering load, a PI acting one
sample late), and diagnosed with the nominal model the family hands out. The search's model matches none of them
exactly, so the residual is coloured and the linear part uncertain; an interval that treated the samples as
independent and held the plant's poles covered S on 3 of 22 such loops.
"""

from __future__ import annotations

import numpy as np
import pytest
from unseen_loops import COVERAGE, Diagnosed, diagnosed_all

pytestmark = pytest.mark.slow  # 40 diagnoses, about 3 minutes on one core

#: Loops drawn per family (seed 7, not the benchmark's 0: tests/unseen_loops.py) and the least share of intervals
#: that must cover.
#: The aim is 0.9; today S is covered on 22 of 26 of these loops and J on 22 of 23, the four misses of S all
#: within 5 % of an end of the interval (a friction law or an actuator lag the search's model does not have).
DRAWS, LEAST = 20, 0.8
#: A jump smaller than this (% travel) is not checked: its relative error says nothing.
MIN_J = 0.5


def _covered(d: Diagnosed) -> dict[str, bool]:
    truth, friction = d.truth, d.doc["friction"]
    if friction is None or friction["travel"] is None:
        return {}
    out = {}
    for key in ("S", "J"):
        if key == "J" and truth["J"] < MIN_J:
            continue
        lo, hi = friction["travel"][key]["interval"]
        out[key] = bool(lo <= truth[key] <= hi)
    return out


def test_the_intervals_of_s_and_j_cover_the_truth_on_most_drawn_sticky_loops():
    hits: dict[str, list[bool]] = {"S": [], "J": []}
    for d in diagnosed_all(COVERAGE):
        for key, ok in _covered(d).items():
            hits[key].append(ok)
    for key, got in hits.items():
        assert len(got) >= DRAWS, f"{key}: only {len(got)} loops with a friction estimate"
        assert np.mean(got) >= LEAST, f"{key} covered on {sum(got)}/{len(got)} loops"
