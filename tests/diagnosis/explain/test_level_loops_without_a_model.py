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


@pytest.mark.xfail(strict=True, reason="measured 29 of 40 (27 before a dead time on the grid's end widened the grid; "
                   "22 while the search holding an integrator also had to predict held-out PV itself no worse; 19 "
                   "before that search existed): on the rest no search finds the valve (a disturbance, a flow limit or "
                   "a characteristic instead, or nothing), or a valve alternative explains PV better under the "
                   "drifting-load model and the answer is cannot tell; three of the 11 misses have a plant lag of "
                   "7-10 s, which a first-order plant with a dead time of half the cycle stands in for)")
def test_stiction_is_found_in_nine_loops_of_ten():
    found = _found()
    assert found >= 0.9 * len(LEVEL), f"stiction found in {found} of {len(LEVEL)}"


def test_stiction_is_found_in_most_loops():
    """A floor under the rate measured (29 of 40), so that a change that loses level loops again is seen."""
    found = _found()
    assert found >= 27, f"stiction found in {found} of {len(LEVEL)}"
