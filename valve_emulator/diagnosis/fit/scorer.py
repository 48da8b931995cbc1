r"""Scoring parameter grids: the chain, the batched linear fit and the bookkeeping every candidate search uses.

:class:`Scorer` holds one problem (data, nominal model, candidate library) and answers "what is the fit-part
SSE of every row of this parameter grid, for these linear structures and dead times?" — pushing the grid
through the chain in chunks of :data:`_CHUNK` rows (the valve simulation is the costly part, so each chunk is
scored for every requested structure before the next is simulated; the chunks are shared out over the kernels'
threads), filtering each chunk once per structure and solving the least-squares problems of all rows and all
dead times in one compiled call.

It also owns the choices that must be the same for every model of a problem:

* the scored samples: the fit part starts after the largest burn-in the candidates claim (a valve's unknown
  initial state must be forgotten before it is scored; capped at
  :data:`~valve_emulator.diagnosis.fit.data.BURN_CAP` of the record): :func:`library_burn_in`, applied to the
  problem before a scorer is made;
* the cost domain: PV, or high-pass prefiltered PV for an integrating plant
  (:func:`~valve_emulator.diagnosis.fit.linear.highpass`);
* the weak prior that ties re-fitted time constants to the nominal ones
  (:data:`~valve_emulator.diagnosis.fit.linear.PRIOR_WIDTH`);
* the target of the linear fits: the scaled PV, or — once a model holds an ``output`` candidate — the
  target that candidate made of it, held while the model is extended (:meth:`Scorer.aim`: an :class:`Aim`
  passed to every call that fits, never state set from outside);
* the error model BIC assumes. With a nominal model (``validation="split"``) it is white noise,
  ``BIC = N ln(SSE/N) + k ln N``. Without one (``"twofold"``, plant data) the residual of even the best
  model is strongly autocorrelated (unmeasured load disturbances are slow), and white-noise BIC would count
  every one of N correlated samples as independent evidence; there BIC is that of an AR(1) error,
  :math:`e_k = \rho e_{k-1} + w_k`, with ρ fitted per model (one more parameter):
  ``BIC = N ln(SSE_w/N) + (k+1) ln N`` with ``SSE_w = Σ (r_k − ρ r_{k−1})²`` the prewhitened residual
  (the Cochrane–Orcutt transformation; Box, Jenkins & Reinsel, *Time Series Analysis*, §9: a regression
  with autocorrelated errors scored by its innovations). A slow mismatch the error model already
  predicts from its own past then counts little; a mismatch at the instants a valve slips counts fully.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from valve_emulator.diagnosis._threads import run_each, workers_for
from valve_emulator.diagnosis.candidates.base import Candidate, ChainContext
from valve_emulator.diagnosis.fit.chain import Active, run_chain
from valve_emulator.diagnosis.fit.cost import ar1_bic, bic
from valve_emulator.diagnosis.fit.data import Problem
from valve_emulator.diagnosis.fit.linear import (
    LinearFit,
    LinearStructure,
    highpass,
    input_grid_sse,
    on_pv,
    polish,
    prior_term,
    split_delay,
)
from valve_emulator.diagnosis.fit.linear_kernels import column_means
from valve_emulator.diagnosis.fit.nominal import Nominal
from valve_emulator.diagnosis.fit.records import Model
from valve_emulator.physics._arrays import kernel_array

__all__ = ["Aim", "Scorer", "chain_context", "library_burn_in", "replay_order", "sse_jobs_many", "sse_jobs_shared"]

#: Most grid rows pushed through the chain at once. Bounds memory (5 MB per array at 10^4 samples), and the
#: chain's output is then a contiguous block that the linear kernel reads from cache for every job (structure)
#: scored on it: with 256 rows the kernel's strided reads of the wider array took twice the time.
_CHUNK = 64
#: Fewest rows in a chunk of a grid cut for the threads: a valve grid's chunk of fewer valves steps the valves'
#: branches, two to three times slower per valve (``valve_start._VECTOR_FROM``).
_CHUNK_MIN = 24


@dataclass(frozen=True, eq=False)
class Aim:
    """What the linear part is fitted to while one model is extended or profiled.

    ``y`` is in scaled PV units: the scaled PV, or the target an ``output`` candidate of the model made of it
    (:mod:`~valve_emulator.diagnosis.fit.backfit`); ``cost`` is the same in the search's cost domain (``y``
    itself, or high-pass prefiltered for an integrating plant), contiguous and writable as the compiled kernels
    take it (the record's arrays are read-only, and the kernels' callers copied them at every call).
    """

    y: np.ndarray
    cost: np.ndarray


def chain_context(problem: Problem, nominal: Nominal, structure: LinearStructure) -> ChainContext:
    """What every candidate of ``problem`` sees: the data, the nominal valve and the linear part ``structure``."""
    return ChainContext(dt=problem.dt, op=problem.op, op_span=problem.op_span,
                        valve_model=nominal.valve_model, rest_samples=nominal.rest_samples,
                        characteristic=nominal.characteristic,
                        tau_plant=max(structure.taus, default=10.0 * problem.dt), delay=structure.delay,
                        pv=problem.pv, y_scale=problem.y_scale, y_mean=problem.y_mean, window=problem.train,
                        stops=problem.stops)


def library_burn_in(problem: Problem, nominal: Nominal, library: dict[str, Candidate]) -> int:
    """The largest burn-in the candidates of ``library`` claim on ``problem`` (samples; 0 for none), which
    :func:`~valve_emulator.diagnosis.fit.data.with_burn_in` turns into the problem every model is scored on."""
    ctx = chain_context(problem, nominal, nominal.structure)
    return max((c.burn_in(ctx) for c in library.values()), default=0)


def _kernel_job(st: LinearStructure, delays: np.ndarray | None) -> tuple:
    """What the SSE of :meth:`Scorer.sse_flows` depends on besides the flows: the poles (the denominator and the
    regressors' number follow from them), the gain's sign, a held gain and the dead times searched (the
    structure's own when ``delays`` is None; a held gain is scored at that gain,
    :func:`~valve_emulator.diagnosis.fit.linear.input_grid_sse`). Its held time constants and bounds are for the
    polish, not this fit."""
    return (st.taus, st.fixed_poles, st.integrating, st.sign, st.gain,
            ("own", st.delay) if delays is None else ("grid", np.asarray(delays, dtype=np.int64).tobytes()))


class Scorer:
    """Grid scoring for one problem (see the module docstring).

    ``problem`` is scored as given: its fit part already starts after the library's burn-in
    (:func:`library_burn_in`, :func:`~valve_emulator.diagnosis.fit.data.with_burn_in`).
    """

    def __init__(self, problem: Problem, nominal: Nominal, library: dict[str, Candidate]) -> None:
        self.p = problem
        self.nominal = nominal
        self.library = library
        self.dmax = float(problem.delays.max()) * problem.dt
        self.lam = problem.prefilter
        self.prior = nominal.structure.taus if nominal.given else None
        self._prior_sorted = sorted(np.log(self.prior).tolist()) if self.prior else None
        #: Scores derived from a model that later stages ask for again (see ``load_check.load_bic``), by the
        #: model's ``id`` with the model itself kept, so that an id is never reused while it is remembered.
        self.memo: dict[int, tuple[Model, object]] = {}

    def aim(self, model: Model | None) -> Aim:
        """What the linear part is fitted to while ``model`` is extended or profiled (the scaled PV unless the
        model holds an output candidate, see :mod:`~valve_emulator.diagnosis.fit.backfit`)."""
        y = self.p.y if model is None or model.target is None else model.target
        return Aim(y, kernel_array(y if self.lam is None else highpass(y, self.lam)))

    def ctx(self, model: Model | None) -> ChainContext:
        """The chain context of ``model`` (its linear part; the nominal one for None)."""
        return chain_context(self.p, self.nominal, model.fit.structure if model else self.nominal.structure)

    def chain(self, active: dict[str, Active], ctx: ChainContext, cand: Candidate | None = None,
              grid: np.ndarray | None = None) -> np.ndarray:
        """Flow (T, n) of the chain with ``active`` in place and ``cand`` over ``grid`` (see :func:`run_chain`)."""
        return run_chain(self.p.op, active, ctx, nominal_valve=(self.nominal.S, self.nominal.J),
                         grid_candidate=cand, grid=grid)

    def model(self, active: dict[str, Active], fit: LinearFit, delay_free: bool, flow: np.ndarray, *,
              target: np.ndarray) -> Model:
        """Score a fitted model: BIC from the fit-part SSE of ``fit`` (the search domain: prefiltered PV
        when the problem says so), the held-out fit from a PV-domain fit at the same structure.

        ``target`` is what ``fit`` was fitted to (scaled PV units, e.g. ``aim.y``); with an ``output``
        candidate in ``active`` the prediction is the candidate's of the linear part's. Without a held-out
        part (two-fold validation) ``heldout`` is NaN until :mod:`~valve_emulator.diagnosis.fit.crossval` fills it.
        """
        acts = []
        for a in active.values():
            if a.slot == "delay":  # the dead-time candidate's parameter is the fitted dead time
                a = Active(a.candidate, np.array([fit.structure.delay]))
            acts.append(a)
        k = fit.structure.n_params() + int(delay_free) + sum(
            a.candidate.n_params for a in acts if a.slot != "delay")
        level = fit if self.lam is None else on_pv(fit, flow, target, self.p.train, self.p.dt)
        y_hat = level.predict(flow, self.p.dt)
        out = active.get("output")
        if out is not None:
            y_hat = out.candidate.predict(y_hat, out.params, self.ctx(None))
        if self.p.validation == "split":
            score, heldout = bic(fit.sse, fit.n, k), self.p.heldout_fit(y_hat)
        else:
            score, heldout = self._ar1_bic(target - level.predict(flow, self.p.dt), k), float("nan")
        return Model(active=tuple(acts), fit=level, delay_free=delay_free, k=k, bic=score, heldout=heldout,
                     y_hat=y_hat, flow=flow, target=target if out is not None else None)

    def _ar1_bic(self, residual: np.ndarray, k: int) -> float:
        """BIC under an AR(1) error (see the module docstring), on the fit part, in the search's domain."""
        r = residual if self.lam is None else highpass(residual, self.lam)
        w0, w1 = self.p.train
        return ar1_bic(r[w0:w1], k)

    def prior_penalty(self, st: LinearStructure) -> float:
        """The weak prior of :func:`~valve_emulator.diagnosis.fit.linear.polish`, for comparing pole sets."""
        if self.prior is None or len(self.prior) != len(st.taus) or not st.taus:
            return 0.0
        return prior_term(np.log(st.taus), self._prior_sorted)

    def polish(self, flow: np.ndarray, st: LinearStructure, free: bool, aim: Aim) -> LinearFit:
        """The linear part driven by ``flow`` polished from ``st`` (a free dead time too when ``free``)."""
        return polish(flow, aim.y, self.p.train, st, self.p.dt, **self.polish_kw(free))

    def polish_kw(self, free: bool) -> dict:
        """The keyword arguments of every polish of this problem (dead-time bounds, prefilter, prior)."""
        return dict(free_delay=free, delay_bounds=(0.0, self.dmax), prefilter=self.lam, prior=self.prior)

    def sse_flows(self, flows: np.ndarray, st: LinearStructure, delays: np.ndarray | None, aim: Aim, *,
                  means: np.ndarray | None = None) -> tuple:
        """SSE (n, nd) for chain outputs ``flows`` (T, n) and the delays searched (samples).

        ``delays=None`` holds the structure's own (possibly fractional) dead time. ``means``: the flows' column
        means (:func:`~valve_emulator.diagnosis.fit.linear_kernels.column_means`) when known.
        """
        frac = 0.0
        if delays is None:
            m, frac = split_delay(st.delay / self.p.dt)
            delays = np.array([m])
        return input_grid_sse(flows, aim.cost, self.p.train, delays, st, self.p.dt, prefilter=self.lam,
                              frac=frac, means=means), delays

    def sse_grid(self, active, ctx, cand, grid, st, delays, aim: Aim) -> tuple:
        """:meth:`sse_flows` for a parameter grid, in chunks of :data:`_CHUNK` rows (bounded memory)."""
        return self.sse_jobs(active, ctx, cand, grid, [(st, delays)], aim)[0]

    def sse_jobs(self, active, ctx, cand, grid, jobs, aim: Aim) -> list[tuple]:
        """Several ``(structure, delays)`` evaluations of one grid in one pass: each chunk of rows is pushed
        through the chain once (the valve simulation is the costly part) and scored for every job."""
        rows, order = _in_replay_order(cand, grid)
        return _unordered(self._score_chunks(lambda a, b: self.chain(active, ctx, cand, rows[a:b]), grid.shape[0],
                                             jobs, aim), order)

    def sse_flows_all(self, flows: np.ndarray, jobs: list[tuple], aim: Aim) -> list[tuple]:
        """:meth:`sse_flows` of ``flows`` (T, n) for every ``(structure, delays)`` of ``jobs``, at most
        :data:`_CHUNK` columns at a time (copied contiguous, then scored for every job while they are in cache): the
        same numbers as job by job over the whole array."""
        return self._score_chunks(lambda a, b: np.ascontiguousarray(flows[:, a:b]), flows.shape[1], jobs, aim)

    def _score_chunks(self, chunk: Callable[[int, int], np.ndarray], n: int, jobs: list[tuple], aim: Aim
                      ) -> list[tuple]:
        """The flows of ``n`` grid rows, made a chunk at a time by ``chunk(first row, end row)``, each chunk scored
        for every job as it is made (:func:`_chunks_scored`, :meth:`_score_block`); per job the SSE rows of all
        chunks stacked, and the delays it searched."""
        return _stacked(_chunks_scored(chunk, n, lambda flows: self._score_block(flows, jobs, aim)))

    def _score_block(self, flows: np.ndarray, jobs: list[tuple], aim: Aim) -> list[tuple]:
        """:meth:`sse_flows` of one block of flows for every job. Jobs the linear kernel cannot tell apart
        (:func:`_kernel_job`, e.g. an integrator that is both an identified alternate and a pole hypothesis of its
        own) are scored once and share the numbers."""
        first: dict[tuple, int] = {}
        same = [first.setdefault(_kernel_job(st, delays), i) for i, (st, delays) in enumerate(jobs)]
        # The flows' means once for every job (reading a long record's block for them costs a pass of the fit).
        means = column_means(flows) if len(first) > 1 else None
        done = {i: self.sse_flows(flows, *jobs[i], aim, means=means) for i in first.values()}
        return [done[i] for i in same]

    def near(self, d: float, r: int) -> np.ndarray:
        """Whole-sample dead times of the problem's grid within ``r`` samples of ``d`` (s)."""
        d0 = int(round(d / self.p.dt))
        lo, hi = int(self.p.delays.min()), int(self.p.delays.max())
        return np.arange(max(lo, d0 - r), min(hi, d0 + r) + 1)


def sse_jobs_many(requests: list[tuple]) -> list[list[tuple]]:
    """:meth:`Scorer.sse_jobs` of several grids, each request ``(scorer, active, ctx, cand, grid, jobs, aim)``:
    the chunks of all of them shared out over the threads together. Per request, the numbers of its own
    ``sse_jobs``.

    Requests that differ only in their grid and jobs (the same scorer, model, context, candidate and aim: the
    refinement's starts) often hold the same rows (neighbouring grids overlap; at 10^5 samples stiction's three
    starts held 2,910 rows of which 1,479 distinct). Each distinct row goes through the chain once
    (:func:`_shared_rows`) and is scored for the jobs of every request that holds it. A row's numbers depend on the
    row and the job only (:func:`_chunks_scored`), so they are those of each request's own ``sse_jobs``."""
    groups: dict[tuple, list[int]] = {}
    for r, (scorer, active, ctx, cand, _, _, aim) in enumerate(requests):
        groups.setdefault((id(scorer), id(active), id(ctx), id(cand), id(aim)), []).append(r)
    parts, put_back = [], []
    for rs in groups.values():
        if len(rs) > 1 and all(requests[r][4].shape[0] for r in rs):
            split = _shared_rows([requests[r] for r in rs])
            put_back.append((rs, len(parts), split))
            parts += split.requests
        else:
            put_back += [([r], len(parts) + i, None) for i, r in enumerate(rs)]
            parts += [requests[r] for r in rs]
    scored = _sse_jobs_each(parts)
    out: list[list[tuple]] = [None] * len(requests)   # type: ignore[list-item]
    for rs, first, split in put_back:
        if split is None:
            out[rs[0]] = scored[first]
            continue
        for r, result in zip(rs, split.results(scored[first:first + len(split.requests)])):
            out[r] = result
    return out


@dataclass(frozen=True, eq=False)
class _SharedRows:
    """Requests of one model (:func:`sse_jobs_many`) recast as one request per set of requests that hold a row:
    ``requests`` are the recast ones, each with the distinct rows held by exactly that set (``members``) and the
    jobs of its members one after the other (``offsets``: where each member's start). ``unique`` (per original
    request, for each of its rows) is the row's index among the distinct rows, ``part`` and ``at`` (per distinct
    row) its recast request and its place there."""

    requests: list[tuple]
    members: list[tuple[int, ...]]
    offsets: list[dict[int, int]]
    unique: list[np.ndarray]
    part: np.ndarray
    at: np.ndarray
    n_jobs: list[int]

    def results(self, scored: list[list[tuple]]) -> list[list[tuple]]:
        """Per original request, per job, ``(sse, delays)`` with the rows of its grid, from the recast requests'
        results ``scored``."""
        out = []
        for k, rows in enumerate(self.unique):
            parts = self.part[rows]
            per_job = []
            first = next(p for p, m in enumerate(self.members) if k in m)
            for j in range(self.n_jobs[k]):
                nd = scored[first][self.offsets[first][k] + j][0].shape[1]
                sse = np.empty((rows.size, nd))
                for p, m in enumerate(self.members):
                    if k in m:
                        mine = parts == p
                        sse[mine] = scored[p][self.offsets[p][k] + j][0][self.at[rows[mine]]]
                per_job.append((sse, scored[first][self.offsets[first][k] + j][1]))
            out.append(per_job)
        return out


def _shared_rows(requests: list[tuple]) -> _SharedRows:
    """:class:`_SharedRows` of ``requests`` (one model's; see :func:`sse_jobs_many`).

    The distinct rows are numbered in the order they first appear (request by request, row by row), rows equal
    when their bytes are (a row's bits, as ``row.tobytes()`` compares them: -0.0 is not 0.0, a NaN equals the same
    NaN); each one's holders are the requests that hold it, and the sets of holders are taken in the order of
    their first row."""
    grids = [np.ascontiguousarray(req[4], dtype=float) for req in requests]
    whole = np.concatenate(grids)
    as_bytes = whole.view(np.dtype((np.void, whole.dtype.itemsize * whole.shape[1]))).ravel()
    _, first, inverse = np.unique(as_bytes, return_index=True, return_inverse=True)
    by_first = np.argsort(first, kind="stable")             # distinct rows in the order they first appear
    number = np.empty(by_first.size, dtype=np.int64)
    number[by_first] = np.arange(by_first.size)
    ids = number[inverse.ravel()]
    sizes = [g.shape[0] for g in grids]
    unique = np.split(ids, np.cumsum(sizes)[:-1])
    rows = whole[first[by_first]]
    # Each distinct row's holders, as the sorted tuple of the requests that hold it.
    holder_of = np.repeat(np.arange(len(requests)), sizes)
    held = np.zeros((rows.shape[0], len(requests)), dtype=bool)
    held[ids, holder_of] = True
    packed = np.packbits(held, axis=1)   # equal rows exactly when the holder sets are
    _, set_first, set_of = np.unique(packed.view(np.dtype((np.void, packed.shape[1]))).ravel(), return_index=True,
                                     return_inverse=True)
    set_of = set_of.ravel()
    part, at = np.empty(len(rows), dtype=np.int64), np.empty(len(rows), dtype=np.int64)
    recast, members, offsets = [], [], []
    for p, s in enumerate(np.argsort(set_first, kind="stable")):   # the sets in the order of their first row
        us = np.flatnonzero(set_of == s)
        m = tuple(np.flatnonzero(held[us[0]]).tolist())
        part[us], at[us] = p, np.arange(len(us))
        scorer, active, ctx, cand, _, _, aim = requests[m[0]]
        jobs, offset = [], {}
        for k in m:
            offset[k] = len(jobs)
            jobs += list(requests[k][5])
        recast.append((scorer, active, ctx, cand, rows[us], jobs, aim))
        members.append(m)
        offsets.append(offset)
    return _SharedRows(requests=recast, members=members, offsets=offsets, unique=unique, part=part, at=at,
                       n_jobs=[len(req[5]) for req in requests])


def _sse_jobs_each(requests: list[tuple]) -> list[list[tuple]]:
    """:func:`sse_jobs_many` without looking for rows the requests share: each grid's chunks as they are."""
    ordered = [_in_replay_order(cand, grid) for _, _, _, cand, grid, _, _ in requests]
    orders = [order for _, order in ordered]
    grids = [(functools.partial(_grid_chunk, scorer, active, ctx, cand, rows), grid.shape[0],
              functools.partial(scorer._score_block, jobs=jobs, aim=aim))
             for (scorer, active, ctx, cand, grid, jobs, aim), (rows, _) in zip(requests, ordered)]
    return [_unordered(_stacked(blocks), order) for blocks, order in zip(_grids_chunks_scored(grids), orders)]


def replay_order(cand: Candidate | None, grid: np.ndarray) -> np.ndarray | None:
    """The order in which a grid's rows go through the chain: rows that differ only in a valve's initial state
    (the nuisance parameter ``start`` of :mod:`~valve_emulator.diagnosis.candidates.valve_start`) side by side, in
    the order of each group's first row, so that they share a chunk and the valves of a group that catch up with
    each other are stepped once (``valve_start._run_merging``). None: the grid's own order (no such parameter, or
    the groups are side by side already, as in the scan's grids). A row's numbers do not depend on the rows that
    share its chunk (:func:`_chunks_scored`), so the order changes no number."""
    if cand is None or "start" not in cand.param_names or grid.shape[0] < 2:
        return None
    rest = np.delete(grid, cand.param_names.index("start"), axis=1)
    _, first, group = np.unique(rest, axis=0, return_index=True, return_inverse=True)
    order = np.lexsort((np.arange(grid.shape[0]), first[group.ravel()]))
    return None if (order == np.arange(grid.shape[0])).all() else order


def _in_replay_order(cand: Candidate | None, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``grid``'s rows in :func:`replay_order` and that order (None: the grid as it is), for :func:`_unordered`."""
    order = replay_order(cand, grid)
    return (grid if order is None else grid[order]), order


def _unordered(scored: list[tuple], order: np.ndarray | None) -> list[tuple]:
    """Per job ``(sse, delays)`` with the SSE rows of a grid scored in ``order`` (:func:`replay_order`) put back in
    the grid's own order."""
    if order is None:
        return scored
    back = np.empty_like(order)
    back[order] = np.arange(order.size)
    return [(sse[back], delays) for sse, delays in scored]


def _grid_chunk(scorer: Scorer, active, ctx, cand, grid: np.ndarray, a: int, b: int) -> np.ndarray:
    """The chain's flows of rows ``a:b`` of ``grid``."""
    return scorer.chain(active, ctx, cand, grid[a:b])


def sse_jobs_shared(active, ctx, cand, grid: np.ndarray, tasks: list[tuple[Scorer, list[tuple], Aim]]
                    ) -> list[list[tuple]]:
    """:meth:`Scorer.sse_jobs` of one grid for several scorers of one problem that differ only in the cost domain
    (the same data, nominal model and library; e.g. the search's own and one through a noise model's prefilter):
    ``tasks`` holds ``(scorer, jobs, aim)``. Each chunk of rows goes through the chain once (the first scorer's;
    the chain does not depend on the cost domain) and is scored for every task: per task, the numbers of its own
    ``sse_jobs``."""
    first = tasks[0][0]
    rows, order = _in_replay_order(cand, grid)
    blocks = _chunks_scored(lambda a, b: first.chain(active, ctx, cand, rows[a:b]), grid.shape[0],
                            lambda flows: [scorer._score_block(flows, jobs, aim) for scorer, jobs, aim in tasks])
    return [_unordered(_stacked([block[t] for block in blocks]), order) for t in range(len(tasks))]


def _chunks_scored(chunk: Callable[[int, int], np.ndarray], n: int, score: Callable[[np.ndarray], list]
                   ) -> list[list]:
    """``score(chunk(a, b))`` for the chunks ``a:b`` of ``n`` grid rows (:func:`_chunk_bounds`), in order.

    The chunks are independent, so the kernels' threads take them one after another as each finishes one
    (:func:`~valve_emulator.diagnosis._threads.run_each`), each thread making and scoring its chunk: both cores
    busy with the chain and the linear kernel alike. The splits inside a chunk (its valves, its columns) then run
    in the thread that makes it. Every row's numbers are those of its chunk alone: the valves, the filters and the
    fits of a grid's rows are column by column the same whatever rows share a chunk."""
    return _grids_chunks_scored([(chunk, n, score)])[0]


def _grids_chunks_scored(grids: list[tuple[Callable[[int, int], np.ndarray], int, Callable[[np.ndarray], list]]]
                         ) -> list[list[list]]:
    """:func:`_chunks_scored` of several grids, ``(chunk, n, score)`` each, their chunks taken by the threads
    from one list: a grid of one chunk no longer leaves the other cores idle while it is scored."""
    tasks, owner = [], []
    for g, (chunk, n, score) in enumerate(grids):
        bounds = _chunk_bounds(n)
        tasks += [functools.partial(_scored, chunk, score, a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        owner += [g] * (len(bounds) - 1)
    out: list[list[list]] = [[] for _ in grids]
    for g, result in zip(owner, run_each(tasks)):
        out[g].append(result)
    return out


def _scored(chunk: Callable[[int, int], np.ndarray], score: Callable[[np.ndarray], list], a: int, b: int) -> list:
    return score(chunk(a, b))


def _chunk_bounds(n: int) -> list[int]:
    """Where the chunks of ``n`` grid rows start and end: as few as :data:`_CHUNK` rows allow, at least one per
    thread of :data:`_CHUNK_MIN` rows or more, of even sizes (the threads take them in turn, so an odd short
    chunk would leave a core idle while the others finish)."""
    count = max(-(-n // _CHUNK), workers_for(n, _CHUNK_MIN))
    return [n * i // count for i in range(count + 1)]


def _stacked(blocks: list[list[tuple]]) -> list[tuple]:
    """Per job, its ``(sse, delays)`` of every block with the SSE rows stacked in block order."""
    return [(np.vstack([block[j][0] for block in blocks]), blocks[0][j][1]) for j in range(len(blocks[0]))]
