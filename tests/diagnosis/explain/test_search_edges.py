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
    assert f"R ≥ {R_MAX:.4g}" in _edge_text(edges) and _edge_text({}) == ""


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
