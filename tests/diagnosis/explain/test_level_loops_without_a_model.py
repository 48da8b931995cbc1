"""Level loops diagnosed without a model: the identified plant is never the controller run backwards.

Each loop is drawn from the independent simulator (an integrating plant with or without a lag, a dead time, a
SIMC PI acting one sample late, a sticky valve with S and J drawn, a wandering load, PV noise). About 4–6 s a
diagnosis (a self-regulating first answer is searched again with the plant held integrating): 40 draws take
about four minutes on one core, so the tests are marked slow; each draw is diagnosed once per test run and shared
with the other property tests (tests/unseen_loops.py).
"""

import numpy as np
import pytest
from unseen_loops import LEVEL, diagnosed, diagnosed_all

pytestmark = pytest.mark.slow
_EACH = pytest.mark.parametrize("key", LEVEL, ids=lambda d: d.name)


@_EACH
def test_the_identified_plant_is_never_the_controllers_inverse(key):
    """Its gain has the sign the controller's action implies and no time constant is shorter than a sample."""
    d = diagnosed(key)
    truth = d.truth
    assert np.sign(d.plant["gain"]) == np.sign(truth["plant"]["gain"]), (truth["plant"], d.plant)
    assert all(tau >= truth["dt"] for tau in d.plant["taus"]), (truth["plant"], d.plant)


@_EACH
def test_the_identification_says_which_constraints_it_used(key):
    d = diagnosed(key)
    ident = d.doc["identification"]
    assert ident["gain_sign"] == int(np.sign(d.truth["plant"]["gain"]))
    assert any("controller" in c for c in ident["constraints"])


def _found() -> int:
    return sum(d.doc["answer"] == "stiction" for d in diagnosed_all(LEVEL))


def test_stiction_is_found_in_nine_loops_of_ten():
    """Measured 36 of 40 (2026-11-27: 34 before the set point's path bounded the dead time, which reached 32.9 and
    32.14, answered tuning through a first-order plant whose dead time, 99 s and 69 s, stood in for a fraction of
    the limit cycle where the set point shows PV answering within 35 s and 11 s; 32 before a loop that does not
    cycle regularly, whose valve alternative explains PV better under the drifting-load model, shows its band's
    memory and has OP's swings crossing it, was called on that valve; 19 before the search holding an
    integrator). Of the 4 misses, 1 (32.22) is a characteristic whose true band (1.63 %) lies inside 3 OP noise
    σ; 32.32's 126 s dead time is not far beyond the set point's bound (81 s); 32.19 names the periodic load the
    search fitted to its limit cycle (its 35 s dead time against a bound of 25 s); 32.25's band the drifting load
    explains better."""
    found = _found()
    assert found >= 0.9 * len(LEVEL), f"stiction found in {found} of {len(LEVEL)}"


def test_a_cycle_beyond_the_identified_loops_ring_is_not_answered_tuning():
    """A sticky valve's limit cycle repeats itself; an aggressive loop's ring wanders with its load. Where the
    record cycles more regularly than the loop identified on it rings (the tuning test's ring check), tuning is
    not the answer (measured 2026-11-27: one of the 40, 32.19, r 81 against at most 22 simulated, answered
    tuning before; now named by the periodic load the search accepted at the cycle's period)."""
    beyond = [d for d in diagnosed_all(LEVEL) if any(r["code"] == "limit_cycle" for r in d.doc["reasons"])]
    assert beyond, "no sticky level loop's cycle found beyond its identified loop's ring"
    for d in beyond:
        assert d.doc["reasons"][0]["code"] != "tuning" or d.doc["answer"] == "cannot_tell", d.doc["verdict"]
        assert d.doc["action"]["code"] != "retune", d.doc["action"]
