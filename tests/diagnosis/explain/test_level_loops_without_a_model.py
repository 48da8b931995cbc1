"""Level loops diagnosed without a model: the identified plant is never the controller run backwards.

Each loop is drawn from the independent simulator (an integrating plant with or without a lag, a dead time, a
SIMC PI acting one sample late, a sticky valve with S and J drawn, a wandering load, PV noise). About 4–6 s a
diagnosis (a self-regulating first answer is searched again with the plant held integrating): 40 draws take
about four minutes, so the tests are marked slow.
"""

import numpy as np
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.independent import draw

DRAWS = 40


@pytest.fixture(scope="module")
def diagnosed():
    out = []
    for i in range(DRAWS):
        rec, truth, _ = draw("level_sticky", np.random.default_rng([32, i]))
        out.append((truth, ve.diagnose(rec, op_range=(0.0, 100.0))))
    return out


@pytest.mark.slow
def test_the_identified_plant_is_never_the_controllers_inverse(diagnosed):
    """Its gain has the sign the controller's action implies and no time constant is shorter than a sample."""
    wrong = []
    for truth, d in diagnosed:
        plant = d.explanation.plant
        inverse = (np.sign(plant["gain"]) != np.sign(truth["plant"]["gain"])
                   or any(tau < truth["dt"] for tau in plant["taus"]))
        if inverse:
            wrong.append((truth["plant"], plant))
    assert not wrong


@pytest.mark.slow
def test_the_identification_says_which_constraints_it_used(diagnosed):
    for truth, d in diagnosed:
        ident = d.to_json()["identification"]
        assert ident["gain_sign"] == int(np.sign(truth["plant"]["gain"]))
        assert any("controller" in c for c in ident["constraints"])



@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured 22 of 40 (19 before the integrating plant was searched for on "
                   "prefiltered PV; 27 when kept without also predicting PV itself no worse): the held search "
                   "still finds a disturbance, a flow limit or a characteristic instead of the valve on some "
                   "loops, and the search on PV keeps a half-cycle dead time on others")
def test_stiction_is_found_in_nine_loops_of_ten(diagnosed):
    found = sum(d.answer == "stiction" for _, d in diagnosed)
    assert found >= 0.9 * DRAWS, f"stiction found in {found} of {DRAWS}"


@pytest.mark.slow
def test_stiction_is_found_in_most_loops(diagnosed):
    """A floor under the rate measured (22 of 40), so that a change that loses level loops again is seen."""
    found = sum(d.answer == "stiction" for _, d in diagnosed)
    assert found >= 20, f"stiction found in {found} of {DRAWS}"
