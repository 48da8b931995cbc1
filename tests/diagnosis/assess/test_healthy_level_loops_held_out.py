"""Level loops with a healthy valve as plant data, seed 51 (``tests/unseen_loops.py: HEALTHY_LEVEL_HELD``), and no
strong call on a cycle inside its band.

Known truth: the independent simulator's ``healthy_level`` family (a PI on an integrating plant under a wandering
load, the valve without friction). Seed 51 was the held-out figure of the short-time integrator's leak (heal16: 3 of
24 answered stiction, 12.5 %, above the 10 % target); seeds 52 and 53 were diagnosed before being looked at (1 and 5
of 24) and seed 54 only after ``decision.CYCLE_CROSSING`` was fixed (5 of 24; ``docs/diagnosis.md``). That rule
changes strengths, not answers: a regular cycle speaks for a band only when OP's swing in it crosses the band's
lower 95 % bound (by √(2/3), a triangle read as a sine), as a sticky valve's limit cycle does. Slow: each draw is
diagnosed once per test run and shared (``tests/unseen_loops.py``).
"""

from __future__ import annotations

import pytest
from unseen_loops import (
    HEALTHY_LEVEL,
    HEALTHY_LEVEL_FRESH,
    HEALTHY_LEVEL_HELD,
    HEALTHY_LEVEL_MORE,
    answered_stiction,
    diagnosed_all,
)

pytestmark = pytest.mark.slow

#: Stiction answers measured on seed 51 (2026-11-28): 51.7.9, a weak call the healthy-alike rule does not reach (a
#: band from 2112 s whose swings cross 5.6 %), and 51.7.2, whose wandering load cycles regularly (r 1.34) inside a band
#: of 4.6 % — strong before ``CYCLE_CROSSING``, weak with it. 51.7.0 (an integrating plant identified, the band's leak
#: through it ΔBIC 8.5) was a third until ``decision.LEAK_BIC`` (heal19; seed 51 is one the rule was studied on, so
#: this bound is no held-out figure: those are in ``docs/diagnosis.md``). 2 of 24, at the 10 % target.
MEASURED_CALLS = 2
#: Every healthy level loop drawn as plant data: 8 + 24 of the test sets, 24 fresh (seed 50), 24 held out (seed 51).
AS_PLANT_DATA = ([k for k in HEALTHY_LEVEL if k.mode == "plant"] + HEALTHY_LEVEL_MORE + HEALTHY_LEVEL_FRESH
                 + HEALTHY_LEVEL_HELD)
#: Strong calls measured on those 80 with ``CYCLE_CROSSING`` (2026-11-28): 7.7.16 only, whose band's 95 % interval
#: reaches down to 3.0 % of a 5.9 % band, which its cycle's OP swing (2.7 % peak to peak) crosses. Main had 3
#: (with 50.7.8 and 51.7.2, whose cycles swing OP by 0.74 and 0.39 of their bands' lower bounds).
MEASURED_STRONG = 1


def test_a_held_out_healthy_level_loop_is_answered_stiction_no_more_often_than_measured():
    called = answered_stiction(HEALTHY_LEVEL_HELD)
    assert len(called) <= MEASURED_CALLS, f"{len(called)} of {len(HEALTHY_LEVEL_HELD)} answered stiction: {called}"


def test_a_healthy_level_loop_whose_cycle_stays_inside_its_band_gets_no_strong_call():
    """Every strong call on the 80 says why it is strong: a regular cycle whose OP swing crosses the band; calls on a
    cycle inside the band say so among their reasons and are weak."""
    docs = diagnosed_all(AS_PLANT_DATA)
    strong = [d.draw.name for d in docs if d.doc["strength"] == "strong"]
    assert len(strong) <= MEASURED_STRONG, f"strong stiction calls on healthy level loops: {strong}"
    inside = [d for d in docs if d.doc["answer"] == "stiction"
              and any("is not the band's" in r["sentence"] for r in d.doc["reasons"])]
    assert len(inside) >= 2, [d.draw.name for d in inside]             # 50.7.8 and 51.7.2 (measured)
    for d in inside:
        assert d.doc["strength"] == "weak", d.draw.name
        assert any(r["code"] == "weak_evidence" and "peak to peak" in r["sentence"] for r in d.doc["reasons"])
