"""Over every drawn loop the property tests diagnose (``unseen_loops.ALL``, shared with them under pytest-xdist):
a finding's parameters lie inside their own 95 % intervals, and a parameter on an edge of the range searched is
the edge itself, said as a bound — never a point value beyond the range (issue 32 §5: "a parameter at the edge of
its search range is never reported as a value")."""

from __future__ import annotations

import pytest
from unseen_loops import ALL, diagnosed_all


def _numeric(parameters: dict) -> dict:
    return {k: v for k, v in parameters.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def _outside(finding: dict) -> list[str]:
    """What a finding of the JSON document reports outside its own intervals, or as a value past an edge."""
    out = []
    for name, v in _numeric(finding["parameters"]).items():
        if name not in finding["intervals"]:
            continue
        lo, hi = finding["intervals"][name]
        tol = 1e-6 * max(1.0, abs(v))
        if (lo is not None and v < lo - tol) or (hi is not None and v > hi + tol):
            out.append(f"{finding['physics']} {name} {v} outside [{lo}, {hi}]")
        if (lo is None) != (hi is None):   # a bound: the value is the edge, and the evidence says the bound
            edge, sign = (lo, "≥") if hi is None else (hi, "≤")
            if abs(v - edge) > tol:
                out.append(f"{finding['physics']} {name} {v} given for the bound {sign} {edge}")
            if f"{name} {sign}" not in finding["evidence"]:
                out.append(f"{finding['physics']} {name}: the evidence does not say the bound {sign} {edge}")
    return out


@pytest.mark.slow  # every drawn loop (shared with the property tests in one run)
def test_no_finding_reports_a_value_outside_its_interval_or_past_an_edge_of_the_range_searched():
    wrong = {d.draw.name: w for d in diagnosed_all(ALL) for f in d.doc["findings"] if (w := _outside(f))}
    assert not wrong, wrong


def test_the_check_sees_a_value_past_an_edge():
    """The check itself, on the finding the held integrator once gave a healthy level loop (healthy_level 2032.7.5
    with its model, main 3bd02d0): an actuator lag of 2·10⁹ s reported for the bound τ ≥ 30 s."""
    found = {"physics": "actuator_lag", "parameters": {"tau": 2176911503.267}, "intervals": {"tau": [30.0, None]},
             "evidence": "95 % interval tau ≥ 30"}
    assert _outside(found) == ["actuator_lag tau 2176911503.267 given for the bound ≥ 30.0"]
    assert _outside({**found, "parameters": {"tau": 30.0}}) == []
    assert _outside({"physics": "stiction", "parameters": {"S": 2.0, "J": 1.0}, "intervals": {"S": [2.1, 3.0]},
                     "evidence": ""}) == ["stiction S 2.0 outside [2.1, 3.0]"]
