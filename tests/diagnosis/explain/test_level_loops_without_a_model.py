"""Level loops diagnosed without a model: the identified plant is never the controller run backwards.

Each loop is drawn from the independent simulator (an integrating plant with or without a lag, a dead time, a
SIMC PI acting one sample late, a sticky valve with S and J drawn, a wandering load, PV noise). About 6 s a
diagnosis: 40 draws take about four minutes, so the test is marked slow.
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

