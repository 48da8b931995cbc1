"""An estimate on an edge of the range searched is a bound, not a value: candidates declare their search edges,
never search beyond them, and a finding on one says so."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis import diagnose
from valve_emulator.diagnosis.candidates import get, registry
from valve_emulator.diagnosis.candidates.base import ChainContext
from valve_emulator.diagnosis.candidates.characteristic import R_MAX
from valve_emulator.diagnosis.explain.findings import _as_bounds, _edge_text, _on_edges
from valve_emulator.diagnosis.explain.onset import LateOnset
from valve_emulator.physics.signal_chain import CHARACTERISTICS

EQP = CHARACTERISTICS.index("equal_percentage")


def _ctx() -> ChainContext:
    t = np.arange(2000.0)
    op = 50.0 + 20.0 * np.sin(2 * np.pi * t / 200.0)
    return ChainContext(dt=1.0, op=op, op_span=40.0, tau_plant=12.0, window=(0, t.size))


def _declared():
    ctx = _ctx()
    return [(c, ctx) for c in registry().values() if c.bounds(ctx)]


def test_some_candidates_declare_search_edges():
    assert {c.name for c, _ in _declared()} >= {"characteristic", "actuator_lag"}


@pytest.mark.parametrize("cand, ctx", _declared(), ids=lambda x: getattr(x, "name", ""))
def test_no_grid_or_refinement_goes_beyond_a_declared_edge(cand, ctx):
    rows = cand.grid(ctx)
    for _ in range(3):  # refinement repeated from its own top and bottom rows, as the search repeats it
        for name, (lo, hi) in cand.bounds(ctx).items():
            col = rows[:, cand.param_names.index(name)]
            assert hi is None or col.max() <= hi * (1 + 1e-12), (name, col.max(), hi)
            assert lo is None or col.min() >= lo * (1 - 1e-12), (name, col.min(), lo)
        ax = cand.param_names.index(next(iter(cand.bounds(ctx))))
        top, bottom = rows[int(np.argmax(rows[:, ax]))], rows[int(np.argmin(rows[:, ax]))]
        rows = np.vstack([cand.refine(ctx, top), cand.refine(ctx, bottom)])


def test_an_estimate_on_the_top_edge_becomes_a_lower_bound_with_an_open_interval():
    cand, ctx = get("characteristic"), _ctx()
    edges = _on_edges(cand, ctx, np.array([EQP, R_MAX]))
    assert edges == {"R": ("≥", R_MAX)}
    assert _on_edges(cand, ctx, np.array([EQP, 30.0])) == {}
    assert _as_bounds({"R": (300.0, R_MAX)}, edges) == {"R": (R_MAX, np.inf)}
    assert _edge_text(edges) == " (R at the edge of the range searched: a bound, not a value)"
    assert _edge_text({}) == ""


def test_a_parameter_on_an_edge_is_said_as_the_bound_and_never_as_a_value():
    eqp = get("characteristic").describe(np.array([EQP, R_MAX]), {"theta": 1.0}, edges={"R": ("≥", R_MAX)})
    assert eqp.startswith(f"an equal-percentage flow characteristic: R ≥ {R_MAX:.0f}, steeper than any valve's")
    assert "≈" not in eqp
    assert get("characteristic").describe(np.array([EQP, 57.4]), {"theta": 1.0}) == (
        "an equal-percentage flow characteristic: R ≈ 57")
    lag = get("actuator_lag")
    top = lag.describe(np.array([30.0]), {"theta": 1.0}, edges={"tau": ("≥", 30.0)})
    assert top.startswith("an actuator lag: τ ≥ 30.0 s, longer than the range searched") and "≈" not in top
    assert "τ ≥ 30.0 s" in lag.describe(np.array([30.0]), None, edges={"tau": ("≥", 30.0)})
    assert lag.describe(np.array([4.25]), {"theta": 1.0}) == "an actuator lag: τ ≈ 4.2 s"


def test_a_late_finding_keeps_its_physics_edges():
    """A finding that starts part-way is its inner physics from the onset on: the inner candidate's search edges
    are its own (the onset's range, the record, is no edge of the physics), and its phrase says the bound."""
    inner = get("characteristic")
    late = LateOnset(inner)
    ctx = _ctx()
    assert late.bounds(ctx) == inner.bounds(ctx)
    assert _on_edges(late, ctx, np.array([EQP, R_MAX, 800.0])) == {"R": ("≥", R_MAX)}
    said = late.describe(np.array([EQP, R_MAX, 800.0]), {"theta": 1.0}, edges={"R": ("≥", R_MAX)})
    assert said.startswith(f"an equal-percentage flow characteristic: R ≥ {R_MAX:.0f}, steeper")
    assert said.endswith(", from t ≈ 800 s on")


def test_the_joint_polish_keeps_a_candidate_inside_the_range_searched():
    """The joint polish (a Nelder–Mead on log τ with the poles) is bounded by the candidate's declared edges, as
    its grids are: unbounded, it once walked an actuator lag on a held integrating plant to 2·10⁹ s."""
    lag, ctx = get("actuator_lag"), _ctx()
    lo, hi = lag.search_range(ctx)
    assert hi.tolist() == [lag.bounds(ctx)["tau"][1]] and lo.tolist() == [-np.inf]
    lo, hi = get("stiction").search_range(ctx)
    assert np.all(np.isinf(lo)) and np.all(np.isinf(hi))   # no declared edge: nothing clipped


@pytest.mark.slow  # a whole diagnosis (about 20 s)
def test_a_curve_steeper_than_any_searched_is_reported_as_a_bound():
    case = next(c for c in CASES if c.name == "equal-percentage characteristic")
    case = dataclasses.replace(case, loop={**case.loop, "valve": {**case.loop["valve"], "rangeability": 3000.0}})
    rec, nominal, _ = generate(case, duration=2600.0)
    found = {f.physics: f for f in diagnose(rec, nominal).findings}
    f = found["characteristic"]
    assert f.edges == {"R": ("≥", R_MAX)}
    assert f.intervals["R"] == (R_MAX, np.inf)
    assert f"R ≥ {R_MAX:.4g}" in f.description and f"R ≥ {R_MAX:.4g}" in f.evidence
