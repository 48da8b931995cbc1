"""Work the search shares between steps gives each step its own numbers: the quick backfit's score, the chain's tail
on a travel scale, one grid scored for several cost domains, overlapping grids scored together."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from first_order_staircase import NOMINAL, staircase_problem

from valve_emulator.diagnosis.candidates import get
from valve_emulator.diagnosis.candidates.base import ChainContext
from valve_emulator.diagnosis.candidates.valve_start import valve_output
from valve_emulator.diagnosis.fit.backfit import backfit, backfit_sse
from valve_emulator.diagnosis.fit.chain import run_chain
from valve_emulator.diagnosis.fit.linear import LinearStructure
from valve_emulator.diagnosis.fit.scorer import Scorer, _shared_rows, replay_order, sse_jobs_many, sse_jobs_shared

T = 1200


@pytest.mark.parametrize("name, prefilter, delays", [
    ("disturbance", None, None),
    ("disturbance", 0.97, np.arange(0, 6)),
    ("quantization", None, np.arange(0, 6)),
    ("quantization", 0.97, None),
])
def test_the_quick_backfits_score_is_the_backfits_sse(name, prefilter, delays):
    problem = staircase_problem(T, load=0.8)
    cand = get(name)
    scorer = Scorer(problem, NOMINAL, {})
    flow = scorer.chain({}, scorer.ctx(None))[:, 0]
    st = NOMINAL.structure
    ctx = replace(scorer.ctx(None), residual=problem.y - np.mean(problem.y))
    rows = cand.grid(ctx)
    assert rows.shape[0] > 0
    for row in rows[:4]:
        full = backfit(flow, problem.y, problem.train, st, problem.dt, cand, row, ctx, prefilter=prefilter,
                       iterations=2, delays=delays).fit.sse
        quick = backfit_sse(flow, problem.y, problem.train, st, problem.dt, cand, row, ctx, prefilter=prefilter,
                            iterations=2, delays=delays)
        assert quick == full


def test_the_chains_tail_on_a_travel_scale_is_travel_clip_and_back_bit_for_bit():
    rng = np.random.default_rng(4)
    ctx = ChainContext(dt=1.0, op=np.zeros(10), op_span=40.0, stops=(12.5, 83.0))
    op = np.clip(50.0 + np.cumsum(rng.normal(0.0, 4.0, 500)), 0.0, 100.0)   # both stops crossed: the clip acts
    lo, hi = ctx.stops

    def tail(x):   # ChainContext.travel, the linear characteristic's clip, ChainContext.from_travel
        return lo + np.clip((x - lo) * (100.0 / (hi - lo)), 0.0, 100.0) * ((hi - lo) / 100.0)

    grid = np.column_stack([rng.uniform(0.5, 5.0, 7), rng.uniform(0.0, 2.0, 7), np.full(7, 1.0)])
    mv = valve_output(op, grid[:, 0], grid[:, 1], grid[:, 2], ctx)
    assert run_chain(op, {}, ctx, grid_candidate=get("stiction"), grid=grid).tobytes() == tail(mv).tobytes()
    assert run_chain(op, {}, ctx)[:, 0].tobytes() == tail(op).tobytes()
    assert tail(op).min() == lo and tail(op).max() == hi


def test_one_grid_scored_for_two_cost_domains_has_the_numbers_of_each_alone():
    problem = staircase_problem(T, load=0.8)
    own = Scorer(problem, NOMINAL, {})
    through = Scorer(replace(problem, prefilter=0.97), NOMINAL, {})
    stiction = get("stiction")
    ctx = own.ctx(None)
    grid = stiction.grid(ctx)[:150]   # three chunks, the last one short
    jobs = [(NOMINAL.structure, None), (LinearStructure(taus=(20.0,), delay=2.0), np.arange(0, 5))]
    tasks = [(own, jobs, own.aim(None)), (through, jobs[:1], through.aim(None))]
    shared = sse_jobs_shared({}, ctx, stiction, grid, tasks)
    for (scorer, task_jobs, aim), results in zip(tasks, shared):
        alone = scorer.sse_jobs({}, ctx, stiction, grid, task_jobs, aim)
        assert len(results) == len(alone)
        for (sse, used), (sse_alone, used_alone) in zip(results, alone):
            assert sse.tobytes() == sse_alone.tobytes() and np.array_equal(used, used_alone)
    assert shared[0][0][0].tobytes() != shared[1][0][0].tobytes()   # the two domains do differ


def test_overlapping_grids_scored_together_have_each_rows_numbers_alone():
    # sse_jobs_many: the rows that several requests of one model hold go through the chain once, the rows that differ
    # only in the valve's start side by side (replay_order); each request's SSEs must be, row by row and to the bit,
    # the straightforward computation: the row alone through the chain, its flow scored for the request's jobs.
    problem = staircase_problem(T, load=0.8)
    scorer = Scorer(problem, NOMINAL, {})
    stiction = get("stiction")
    ctx, aim = scorer.ctx(None), scorer.aim(None)
    SJ = [(S, J) for S in (0.6, 1.0, 1.4, 1.8, 2.2) for J in (0.0, 0.4, 0.8)]

    def grid(pairs):   # a refinement's layout: the starts in separate blocks
        return np.array([(S, J, start) for start in (2.0, 1.0, -1.0) for S, J in pairs])

    grids = [grid(SJ[:9]), grid(SJ[5:]), grid(SJ[:9]), grid(SJ[12:])[::-1]]
    jobs = [[(NOMINAL.structure, None)], [(LinearStructure(taus=(20.0,), delay=2.0), np.arange(0, 5))],
            [(NOMINAL.structure, np.arange(1, 4)), (LinearStructure(taus=(8.0,), delay=1.0), None)],
            [(NOMINAL.structure, None)]]
    together = sse_jobs_many([(scorer, {}, ctx, stiction, g, j, aim) for g, j in zip(grids, jobs)])
    for g, request_jobs, results in zip(grids, jobs, together):
        assert len(results) == len(request_jobs)
        for (st, delays), (sse, used) in zip(request_jobs, results):
            for i, row in enumerate(g):
                alone, used_alone = scorer.sse_flows(scorer.chain({}, ctx, stiction, row[None, :]), st, delays, aim)
                assert sse[i].tobytes() == alone[0].tobytes() and np.array_equal(used, used_alone)
    order = replay_order(stiction, grids[0])   # the starts of each (S, J) side by side, in the grid's order
    assert order is not None and [tuple(r) for r in grids[0][order][:3, :2]] == [SJ[0]] * 3
    assert replay_order(stiction, stiction.scan(ctx)) is None   # the scan's grid has them side by side already


@pytest.mark.parametrize("name", ["stiction", "deadband"])
@pytest.mark.parametrize("model", ["kano", "choudhury", "he"])
def test_a_valve_candidates_output_is_within_travel_so_the_chain_skips_the_stops_check(name, model, monkeypatch):
    # output_in_range lets run_chain skip the nominal linear characteristic's check for values beyond 0–100 %: the
    # valve's MV must lie within them (or be NaN) whatever OP does, and the chain's flows must be, to the bit, those
    # of the chain that checks.
    rng = np.random.default_rng(8)
    op = 50.0 + np.cumsum(rng.normal(0.0, 6.0, 800))          # wanders far beyond both stops
    op[[100, 400]] = np.nan
    ctx = ChainContext(dt=1.0, op=op, op_span=40.0, valve_model=model)
    cand = get(name)
    assert cand.output_in_range
    grid = cand.grid(ctx)[::5]
    mv = cand.apply(op, grid, ctx)
    assert np.all(np.isnan(mv) | ((mv >= 0.0) & (mv <= 100.0))) and np.ptp(mv[:90]) > 0.0
    ok = np.clip(np.nan_to_num(op, nan=50.0), -5.0, 105.0)    # no NaN: the stops' check clips OP itself
    skipped = run_chain(ok, {}, ctx, grid_candidate=cand, grid=grid)
    nominal = run_chain(ok, {}, ctx, nominal_valve=(3.0, 1.0))
    monkeypatch.setattr(type(cand), "output_in_range", False)
    assert skipped.tobytes() == run_chain(ok, {}, ctx, grid_candidate=cand, grid=grid).tobytes()
    assert run_chain(ok, {}, ctx, nominal_valve=(3.0, 1.0)).tobytes() == nominal.tobytes()
    assert run_chain(ok, {}, ctx)[:, 0].tobytes() == np.clip(ok, 0.0, 100.0).tobytes()   # OP itself is clipped


def _shared_rows_by_hand(grids: list[np.ndarray]) -> tuple:
    """The straightforward form of _shared_rows: each row's bytes looked up in a dict in order of appearance, a set
    of holders per distinct row, the sets in the order of their first row."""
    index: dict[bytes, int] = {}
    holders: list[set[int]] = []
    rows: list[np.ndarray] = []
    unique = []
    for k, grid in enumerate(grids):
        ids = []
        for row in grid:
            u = index.setdefault(row.tobytes(), len(rows))
            if u == len(rows):
                rows.append(row)
                holders.append(set())
            holders[u].add(k)
            ids.append(u)
        unique.append(ids)
    sets: dict[tuple[int, ...], list[int]] = {}
    for u, h in enumerate(holders):
        sets.setdefault(tuple(sorted(h)), []).append(u)
    return unique, [(m, np.array([rows[u] for u in us])) for m, us in sets.items()]


def test_shared_rows_numbered_and_grouped_as_by_hand():
    # Rows equal to the bit only (-0.0 is not 0.0, a NaN equals itself), numbered in order of first appearance,
    # and each recast request holding the rows of one set of holders with its members' jobs in turn.
    rng = np.random.default_rng(2)
    values = np.array([0.0, -0.0, 1.0, 2.5, np.nan, 3.0])
    for _ in range(100):
        grids = [rng.choice(values, (int(rng.integers(1, 30)), 3)) for _ in range(int(rng.integers(2, 7)))]
        requests = [(None, None, None, None, g, [("job", k, j) for j in range(k % 2 + 1)], None)
                    for k, g in enumerate(grids)]
        shared = _shared_rows(requests)
        unique, sets = _shared_rows_by_hand(grids)
        assert [ids.tolist() for ids in shared.unique] == unique
        assert shared.members == [m for m, _ in sets]
        for (m, rows), recast, offsets in zip(sets, shared.requests, shared.offsets):
            assert recast[4].tobytes() == rows.tobytes() and recast[4].shape == rows.shape
            assert recast[5] == [job for k in m for job in requests[k][5]]
            assert offsets == {k: sum(len(requests[i][5]) for i in m[:m.index(k)]) for k in m}
