"""Sticky level loops diagnosed with their exact nominal model: the valve is found, at about its size.

Each loop is drawn from the independent simulator (an integrating plant with or without a lag, a dead time, a
SIMC PI acting one sample late, a sticky valve with S and J drawn, a wandering load at the plant's input, PV
noise) and diagnosed with the nominal model the simulator states: the plant exactly, the valve ideal. The seed
(14) is used by no other set; the rule these tests judge (the integrating plant held as given, each round decided
under the drifting-load noise model: docs/diagnosis.md, *A level loop's model is held*) was found on the level
loops of the coverage and calibration sets (seed 7 and 32). About 5–15 s a diagnosis; marked slow, each draw
shared with the other property tests (tests/unseen_loops.py).
"""

import pytest
from unseen_loops import LEVEL_MODEL, diagnosed_all

pytestmark = pytest.mark.slow


def _found() -> list:
    return [d for d in diagnosed_all(LEVEL_MODEL) if d.doc["answer"] == "stiction"]


def test_stiction_is_found_in_nine_loops_of_ten():
    """Measured 2026-11-28: 18 of 20 (misses 14.0.15, a saturation and a dead time; 14.0.19, cannot tell; the
    set was not diagnosed with main's code). On the 42 level loops of the coverage and calibration sets, where the
    rule was found, 40 of 42 against 29 before; held out (bench/bench_unseen_loops.py --seed 0), 8 of 8 against
    3 of 8."""
    found = len(_found())
    assert found >= 0.9 * len(LEVEL_MODEL), f"stiction found in {found} of {len(LEVEL_MODEL)}"


def test_the_given_integrating_plant_is_not_moved_to_stand_in_for_the_valve():
    """Where the valve is found, the plant's gain and lag stay the user's: a gain moved beside a found valve is
    the free run's answer to the wandering load, which the drifting-load noise model does not confirm."""
    moved = {d.draw.name: m for d in _found() for m in d.doc["linear_part"]
             if m["moved"] and m["parameter"] in ("gain", "time_constant")}
    assert not moved, moved


def test_the_band_found_is_near_the_truth():
    """S within 25 % of the truth in at least 80 % of the loops where the valve is found (measured 2026-11-28:
    16 of 18; 19 of 20 and 18 of 20 on the coverage and calibration sets' level loops)."""
    found = _found()
    near = [d for d in found if d.doc["friction"] is not None
            and abs(d.doc["friction"]["S"]["value"] - d.truth["S"]) <= 0.25 * d.truth["S"]]
    assert len(near) >= 0.8 * len(found), [(d.truth["S"], d.doc["friction"]) for d in found]
