r"""Fitting one candidate: coarse grid × pole hypotheses, a global scan, refinement, a polish of the poles.

Stages, for every candidate and every dead-time variant (θ held at its current value, or freed together with
``dead_time`` while the nominal dead time is still trusted):

1. **coarse**: the candidate's coarse grid through the chain at once, scored for every pole hypothesis of
   :meth:`Fitter.pole_set` and every dead time of the grid; the best row of each hypothesis is a start,
   ranked by ``N ln SSE`` plus the prior on the poles;
2. **scan** (candidates that define one, e.g. stiction): a global grid fine along the rough directions,
   scored at the top :data:`_STARTS` starts' poles and nearby dead times;

   on a long record these two stages score windows spread over the fit part instead of all of it
   (:mod:`~valve_emulator.diagnosis.fit.windows`: they only choose the starts);
3. **refine**, twice: the candidate's fine local grid (dead time ±2 samples when free), then a Nelder–Mead
   polish of the poles (and of a free dead time, to a fraction of a sample);
4. **centre** threshold parameters in their flat cost bottom (:meth:`Fitter.centre`).

The start that ends with the lowest BIC (plus prior) is the option. Why several starts: a continuous
parameter trades off against the poles (an actuator lag against the plant's time constant) and stiction's
coarse cost is rough, so the coarse winner can be an artefact of grid placement.

``output`` candidates (after the plant) are fitted by backfitting instead (:meth:`Fitter.output_options`,
:mod:`~valve_emulator.diagnosis.fit.backfit`): their coarse grid and refinement are scored with the poles held,
then the best is polished. ``loop`` candidates are not searched.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from valve_emulator.diagnosis._threads import run_each
from valve_emulator.diagnosis.candidates.base import Candidate, Kind
from valve_emulator.diagnosis.fit.backfit import Filtered, backfit, backfit_sse
from valve_emulator.diagnosis.fit.chain import Active
from valve_emulator.diagnosis.fit.cost import log_sse, relative_cost
from valve_emulator.diagnosis.fit.linear import LinearFit, LinearStructure, split_delay, sse_one
from valve_emulator.diagnosis.fit.records import Model, Option, Surface
from valve_emulator.diagnosis.fit.scorer import Aim, Scorer, sse_jobs_many
from valve_emulator.diagnosis.fit.simplex import nelder_mead
from valve_emulator.diagnosis.fit.windows import Part, Window, coarse_parts, coarse_windows, window_scorer

__all__ = ["Fitter", "Refined", "Result", "Start", "Variant"]

#: Pole hypotheses whose best coarse start is scanned and refined.
_STARTS = 2
#: Cost evaluations of a joint polish of a candidate's parameters with the poles (:meth:`Fitter.joint_polish`).
_JOINT_EVALS = 200
#: Refined starts further than this behind the best (in −2 log posterior) are not polished jointly: the valley
#: along which a joint polish moves a start is shallower than that (a few units between the lag orders).
_JOINT_MARGIN = 10.0
#: Width of a "flat" cost bottom, in units of -2 log-likelihood (the 95 % point of chi-square, 1 dof).
_FLAT = 3.84


@dataclass(frozen=True, eq=False)
class Variant:
    """One way a candidate is added: with the dead time held or ``free``; ``added`` names the option."""

    free: bool
    added: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class Start:
    """Where a refinement starts: the best coarse row for one pole hypothesis.

    ``score`` is ``N ln SSE`` plus the prior on the poles, ``params`` the coarse grid's best row, ``structure``
    the pole hypothesis (its dead time the best of the grid when free), ``coarse`` the coarse surface.
    """

    score: float
    params: np.ndarray
    structure: LinearStructure
    coarse: Surface


@dataclass(frozen=True, eq=False)
class Refined:
    """A candidate refined into a model: the physics in place by slot, the linear fit, the chain's output
    and the fine grid's surface."""

    active: dict[str, Active]
    fit: LinearFit
    flow: np.ndarray
    fine: Surface


@dataclass(frozen=True, eq=False)
class Result:
    """What one start ended as: its penalised score (BIC plus the prior on the poles), the model and the
    surfaces it was found on (``scan`` None for a candidate without a scan)."""

    score: float
    model: Model
    scan: Surface | None
    fine: Surface


class Fitter:
    """Fits candidates into a model (see the module docstring); its results are :class:`Option` objects.

    It *has* a :class:`~valve_emulator.diagnosis.fit.scorer.Scorer` (the problem, the nominal model, the
    library and the grid scoring); what the linear part is fitted to comes from the model being extended
    (:meth:`~valve_emulator.diagnosis.fit.scorer.Scorer.aim`), never from state set beforehand.
    """

    def __init__(self, scorer: Scorer, *, windowed: bool = True) -> None:
        #: Whether a long record's coarse stages may score windows (:mod:`.windows`); False for a record whose
        #: physics changes part-way (a located onset), which windows would weigh by how many fall after it, and
        #: without a nominal model (the poles the coarse stage chooses from are longer than a window).
        self.windowed = windowed
        self.scorer = scorer

    def surface(self, name: str, params: np.ndarray, sse: np.ndarray, n: int | None = None) -> Surface:
        """A cost surface of candidate ``name`` on the problem's fit part (or on ``n`` samples of it)."""
        return Surface(candidate=name, params=params, sse=sse, n=self.p.n_fit if n is None else n)

    @property
    def windows(self) -> tuple[Window, ...]:
        """The windows the coarse stages score (none: the whole fit part; :mod:`.windows`)."""
        return coarse_windows(self.p.train) if self.windowed else ()

    @cached_property
    def _window_scorers(self) -> tuple[Scorer, ...]:
        return tuple(window_scorer(self.scorer, w) for w in self.windows)

    def coarse_parts(self, model: Model, cand: Candidate) -> tuple[Part, ...]:
        """What the coarse stages of ``cand`` added to ``model`` score: the windows, or the whole record."""
        windows = self.windows
        return coarse_parts(self.scorer, windows, self._window_scorers if windows else (), model, cand)

    @property
    def p(self):
        """The problem (:class:`~valve_emulator.diagnosis.fit.data.Problem`) being fitted."""
        return self.scorer.p

    @property
    def nominal(self):
        return self.scorer.nominal

    @property
    def library(self):
        return self.scorer.library

    def pole_set(self, model: Model) -> list[LinearStructure]:
        """Linear dynamics tried by the coarse stage of every candidate search.

        A missing valve nonlinearity biases the poles re-fitted around the nominal chain (stiction in the
        concentration loop drags the fitted time constant from 10 s to about 80 s), and with wrong poles
        the valve's cost basin disappears. So the coarse stage also tries the nominal poles scaled by
        2^(±1/2), 2^(±1) — or, without a model, first order with time constants from Δt to a tenth of the
        record and an integrator (only the declared family when the plant's was declared), under the
        identification's constraints (the gain's sign, time constants of a sample or more) — and later stages
        use the best.
        """
        st = model.fit.structure
        out = [st]
        if self.nominal.given:
            nom = replace(self.nominal.structure, delay=st.delay)
            for f in (1.0, 0.5, 2 ** -0.5, 2 ** 0.5, 2.0):
                if (nom.taus and not nom.taus_held) or f == 1.0:
                    out.append(replace(nom, taus=tuple(t * f for t in nom.taus)))
        else:
            dt = self.p.dt
            out += [replace(a, delay=st.delay) for a in self.nominal.alternates]
            family = None if self.nominal.identification is None else self.nominal.identification.integrating
            plain = replace(st, taus=(), integrating=False, fixed_poles=())
            if family is not True:
                out += [replace(plain, taus=(float(t),))
                        for t in np.geomspace(dt, max(2 * dt, self.p.T * dt / 10.0), 8)]
            if family is not False:
                out.append(replace(plain, integrating=True))
        return out

    def base(self) -> Model:
        """Nominal chain with the linear part re-fitted (poles; the dead time too when there is no model).

        Without a nominal model the identified structure is only a start: the base also tries every pole
        hypothesis of :meth:`pole_set` (with the dead-time grid) and keeps the best after polishing, so
        that no candidate earns its ΔBIC merely by giving the search a second chance at the linear part.
        """
        ctx, aim = self.scorer.ctx(None), self.scorer.aim(None)
        flow = self.scorer.chain({}, ctx)[:, 0]
        free = not self.nominal.given
        fit = self.scorer.polish(flow, self.nominal.structure, free, aim)
        model = self.scorer.model({}, fit, free, flow, target=aim.y)
        if self.nominal.given:
            return model
        best = None
        for st in self.pole_set(model):
            sse, delays = self.scorer.sse_flows(flow[:, None], st, self.p.delays, aim)
            j = int(np.argmin(sse[0]))
            if best is None or sse[0, j] < best[0]:
                best = (float(sse[0, j]), replace(st, delay=float(delays[j]) * self.p.dt))
        other = self.scorer.model({}, self.scorer.polish(flow, best[1], free, aim), free, flow, target=aim.y)
        return other if other.bic < model.bic else model

    def refine(self, model: Model, cand: Candidate, best: np.ndarray, st: LinearStructure, free: bool, *,
               joint: bool = True) -> Refined:
        """Two passes of fine grid + polish around ``best`` (then, for a candidate that trades off against the
        poles and ``joint``, :meth:`joint_polish`), threshold parameters centred: ``cand`` refined into
        ``model``."""
        return self.refine_all(model, cand, [(best, st, free)], joint=joint)[0]

    def refine_all(self, model: Model, cand: Candidate, starts: list[tuple[np.ndarray, LinearStructure, bool]], *,
                   joint: bool = True) -> list[Refined]:
        """:meth:`refine` of ``cand`` from each ``(best, structure, free)`` of ``starts``, stage by stage.

        The chain's output depends only on the grid, never on the linear structure or the dead time, and starts
        often share their grids (the θ-held and θ-free variants start from the same scan row, and refinements
        converge): at each stage every distinct grid is pushed through the chain once and scored for every start
        that uses it (:meth:`_score_grids`). Each start's numbers are those of refining it alone, and equal starts
        (same row, structure and variant) are refined once.
        """
        keys = [(best.tobytes(), repr(st), free) for best, st, free in starts]
        first: dict[tuple, int] = {}
        for k, key in enumerate(keys):
            first.setdefault(key, k)
        if len(first) < len(starts):
            done = dict(zip(first, self.refine_all(model, cand, [starts[k] for k in first.values()], joint=joint)))
            return [done[key] for key in keys]
        active = model.by_slot()
        ctx, aim = self.scorer.ctx(model), self.scorer.aim(model)
        bests = [b for b, _, _ in starts]
        sts = [s for _, s, _ in starts]
        frees = [f for _, _, f in starts]
        fits: list[LinearFit] = [None] * len(starts)   # type: ignore[list-item]
        flows: list[np.ndarray] = [None] * len(starts)  # type: ignore[list-item]
        grids: list[np.ndarray] = []
        scored: list[tuple] = []
        for _ in range(2):
            grids = [cand.refine(ctx, b) for b in bests]
            jobs = [(st, self.scorer.near(st.delay, 2) if free else None) for st, free in zip(sts, frees)]
            scored = self._score_grids(active, ctx, cand, grids, jobs, aim)
            rows = {}
            for k, (g, (sse, delays)) in enumerate(zip(grids, scored)):
                i, j = np.unravel_index(int(np.argmin(sse)), sse.shape)
                bests[k] = g[i]
                sts[k] = replace(sts[k], delay=float(delays[j]) * self.p.dt) if frees[k] else sts[k]
                flows[k] = self._row_flow(rows, active, ctx, cand, g[i])
            fits = self._polish_all(flows, sts, frees, aim)
            sts = [fit.structure for fit in fits]
        fines = [self.surface(cand.name, g, sse.min(axis=1)) for g, (sse, _) in zip(grids, scored)]
        if joint and self.trades_with_prior(cand):
            for k in range(len(starts)):
                bests[k], sts[k] = self.joint_polish(active, ctx, cand, bests[k], sts[k], frees[k], aim)
                flows[k] = self.scorer.chain(active, ctx, cand, bests[k][None, :])[:, 0]
            fits = self._polish_all(flows, sts, frees, aim)
        if cand.threshold_axes:
            bests = self.centre_all(active, ctx, cand, bests, sts, aim)
            rows = {}
            for k in range(len(starts)):
                flows[k] = self._row_flow(rows, active, ctx, cand, bests[k])
            fits = self._polish_all(flows, sts, frees, aim)
        out = []
        for best, fit, flow, fine in zip(bests, fits, flows, fines):
            new_active = dict(active)
            new_active[cand.slot] = Active(cand, best)
            out.append(Refined(active=new_active, fit=fit, flow=flow, fine=fine))
        return out

    def _polish_all(self, flows: list[np.ndarray], sts: list[LinearStructure], frees: list[bool], aim: Aim
                    ) -> list[LinearFit]:
        """:meth:`~valve_emulator.diagnosis.fit.scorer.Scorer.polish` of each start (its flow, structure and
        variant): independent polishes, shared out over the kernels' threads (:func:`~valve_emulator.diagnosis.
        _threads.run_each`); on a long record a polish is mostly its compiled column fit, which releases the GIL."""
        return run_each([functools.partial(self.scorer.polish, flow, st, free, aim)
                         for flow, st, free in zip(flows, sts, frees)])

    def _score_grids(self, active, ctx, cand, grids: list[np.ndarray], jobs: list[tuple], aim: Aim) -> list[tuple]:
        """``sse_grid`` of ``grids[k]`` for ``jobs[k]`` (structure, delays), every distinct grid through the chain
        once with all its jobs, the grids' chunks shared out over the threads together
        (:func:`~valve_emulator.diagnosis.fit.scorer.sse_jobs_many`)."""
        groups: dict[tuple, dict[tuple, list[int]]] = {}
        for k, (g, (st, delays)) in enumerate(zip(grids, jobs)):
            job = (repr(st), None if delays is None else delays.tobytes())
            groups.setdefault((g.shape, g.tobytes()), {}).setdefault(job, []).append(k)
        out: list[tuple] = [None] * len(grids)   # type: ignore[list-item]
        requests = []
        for same_grid in groups.values():
            ks = [k[0] for k in same_grid.values()]
            requests.append((self.scorer, active, ctx, cand, grids[ks[0]], [jobs[k] for k in ks], aim))
        for same_grid, scored in zip(groups.values(), sse_jobs_many(requests)):
            for r, same_job in zip(scored, same_grid.values()):
                for k in same_job:
                    out[k] = r
        return out

    def _row_flow(self, memo: dict, active, ctx, cand, row: np.ndarray) -> np.ndarray:
        """The chain's output (T,) for one parameter row, computed once per distinct row in ``memo``."""
        key = row.tobytes()
        if key not in memo:
            memo[key] = self.scorer.chain(active, ctx, cand, row[None, :])[:, 0]
        return memo[key]

    def trades_with_prior(self, cand: Candidate) -> bool:
        """Whether ``cand`` trades off against the poles and a nominal model's prior must choose between the
        fits (without a model there is no prior, and the two orderings of two lags are one answer)."""
        return bool(getattr(cand, "joint_with_poles", False)) and self.nominal.given

    def joint_polish(self, active, ctx, cand, best: np.ndarray, st: LinearStructure, free: bool, aim: Aim
                     ) -> tuple[np.ndarray, LinearStructure]:
        """Nelder–Mead on the candidate's parameters and the poles (and a free dead time) together.

        The cost is the polish's, ``N ln SSE`` plus the prior on the poles (:meth:`Scorer.prior_penalty`), the
        parameters and time constants on a log scale. Why jointly: an actuator lag and a plant time constant
        trade off along a narrow diagonal valley (their sum and product are what the data fix), where the
        refinement's alternation — the candidate's grid with the poles held, then the poles with the
        candidate held — creeps and stops short of the bottom, leaving a cost difference between the two
        orderings of the lags larger than the prior that should decide between them.

        The candidate's parameters stay inside the range searched (``Candidate.search_range``), as its grids and
        refinement do: unbounded, the simplex walked an actuator lag on a held integrating plant to 2·10⁹ s (a
        valve that never moves, reported as a lag), where the grids stop at their top.
        """
        n, k, nt = self.p.n_fit, best.size, 0 if st.taus_held else len(st.taus)
        lo_d, hi_d = 0.0, self.scorer.dmax
        lo_p, hi_p = cand.search_range(ctx)

        def make(x: np.ndarray) -> tuple[np.ndarray, LinearStructure]:
            taus = tuple(float(np.exp(v)) for v in x[k:k + nt]) or st.taus
            delay = float(np.clip(x[-1], lo_d, hi_d)) if free else st.delay
            return np.clip(np.exp(x[:k]), lo_p, hi_p), replace(st, taus=taus, delay=delay)

        def cost(x: np.ndarray) -> float:
            params, s = make(x)
            flow = self.scorer.chain(active, ctx, cand, params[None, :])[:, 0]
            sse = sse_one(flow, aim.y, self.p.train, s, self.p.dt, prefilter=self.scorer.lam, y_cost=aim.cost)
            return log_sse(sse, n) + self.scorer.prior_penalty(s)

        x0 = np.concatenate([np.log(np.maximum(best, 1e-12)), np.log(st.taus[:nt]), [st.delay] if free else []])
        step = np.concatenate([np.full(k + nt, 0.1), [max(self.p.dt, 0.1 * st.delay)] if free else []])
        simplex = np.vstack([x0] + [x0 + np.eye(x0.size)[i] * step[i] for i in range(x0.size)])
        res = nelder_mead(cost, simplex, maxfev=_JOINT_EVALS, xatol=1e-2, fatol=0.05)
        return make(res.x) if res.fun <= res.start else (best, st)

    def centre(self, active, ctx, cand, best, st, aim: Aim) -> np.ndarray:
        """Move each threshold parameter to the middle of the flat bottom of its cost.

        With noisy OP the fit-part cost is piecewise constant in a threshold (each slip happens at the
        first sample past it), so every value inside the cell that contains the argmin replays the fit
        part equally well, and the argmin may sit at the cell's edge. Events in the held-out part cut the
        cell at uniformly distributed places; its middle is the value least likely to miss one. The
        flat bottom is the contiguous run around the argmin with N·ln(SSE/SSE_min) ≤ :data:`_FLAT`.
        """
        return self.centre_all(active, ctx, cand, [best], [st], aim)[0]

    def centre_all(self, active, ctx, cand, bests: list[np.ndarray], sts: list[LinearStructure], aim: Aim
                   ) -> list[np.ndarray]:
        """:meth:`centre` of each of ``bests`` (with its structure), axis by axis, a line shared by several
        through the chain once."""
        bests = list(bests)
        for axis in cand.threshold_axes:
            lines = [cand.line(ctx, best, axis) for best in bests]
            scored = self._score_grids(active, ctx, cand, lines, [(st, None) for st in sts], aim)
            for k, (rows, (sse, _)) in enumerate(zip(lines, scored)):
                cost = relative_cost(sse[:, 0], self.p.n_fit)
                i = int(np.argmin(cost))
                lo = hi = i
                while lo > 0 and cost[lo - 1] <= _FLAT:
                    lo -= 1
                while hi < cost.size - 1 and cost[hi + 1] <= _FLAT:
                    hi += 1
                best = rows[i].copy()
                best[axis] = 0.5 * (rows[lo, axis] + rows[hi, axis])
                bests[k] = best
        return bests

    def delay_option(self, model: Model, cand: Candidate) -> Option:
        flow, aim = model.flow, self.scorer.aim(model)
        sse, delays = self.scorer.sse_flows(flow[:, None], model.fit.structure, self.p.delays, aim)
        st = replace(model.fit.structure, delay=float(delays[int(np.argmin(sse[0]))]) * self.p.dt)
        fit = self.scorer.polish(flow, st, True, aim)
        active = model.by_slot()
        active["delay"] = Active(cand, np.array([fit.structure.delay]))
        surf = self.surface(cand.name, delays[:, None] * self.p.dt, sse[0])
        model = self.scorer.model(active, fit, True, flow, target=aim.y)
        return Option(added=(cand.name,), model=model, coarse=surf, scan=None, fine=surf)

    def output_sse(self, model: Model, cand: Candidate, rows: np.ndarray, st: LinearStructure | None = None,
                    delays: np.ndarray | None = None) -> np.ndarray:
        """Fit-part SSE of each output-candidate row by a quick backfit (structure ``st``, default the model's;
        the dead time re-chosen from ``delays`` when given)."""
        ctx = replace(self.scorer.ctx(model), residual=self.p.y - model.y_hat)
        st = model.fit.structure if st is None else st
        # The rows' backfits are independent, and on a long record mostly numpy's and the kernels' work on whole
        # columns (which release the GIL): they share the kernels' threads.
        # The flow and PV filtered for ``st`` once for every row (a row with regressors of its own asks for them).
        shared = Filtered(model.flow, self.p.y, st, self.p.dt, self.scorer.lam)
        return np.array(run_each([functools.partial(backfit_sse, model.flow, self.p.y, self.p.train, st, self.p.dt,
                                                    cand, r, ctx, prefilter=self.scorer.lam, iterations=2,
                                                    delays=delays, filtered=shared) for r in rows]))

    def output_options(self, model: Model, cand: Candidate) -> list[Option]:
        """The option that adds an ``output`` candidate: its grid by quick backfits with the model's linear
        structure, the :data:`_STARTS` + 1 best rows again from every pole hypothesis (dead time on the grid
        when free), the refinement at the best structure, then the best row polished (see
        :mod:`~valve_emulator.diagnosis.fit.backfit`)."""
        ctx = replace(self.scorer.ctx(model), residual=self.p.y - model.y_hat)
        if not cand.applicable(ctx):
            return []
        grid = cand.grid(ctx)
        if grid.shape[0] == 0:
            return []
        delays = self.p.delays if model.delay_free else None
        sse = self.output_sse(model, cand, grid, None, delays)
        top = grid[np.argsort(sse)[:_STARTS + 1]]
        best = None
        for st in self.pole_set(model):
            s_top = self.output_sse(model, cand, top, st, delays)
            score = log_sse(float(s_top.min()), self.p.n_fit) + self.scorer.prior_penalty(st)
            if best is None or score < best[0]:
                best = (score, st, top[int(np.argmin(s_top))])
        _, st, row0 = best
        fine = cand.refine(ctx, row0)
        sse_fine = self.output_sse(model, cand, fine, st, delays)
        row = fine[int(np.argmin(sse_fine))]
        bf = backfit(model.flow, self.p.y, self.p.train, st, self.p.dt, cand, row, ctx, prefilter=self.scorer.lam,
                     polish_kw=self.scorer.polish_kw(model.delay_free), delays=delays)
        active = model.by_slot()
        active[cand.slot] = Active(cand, bf.params)
        m = self.scorer.model(active, bf.fit, model.delay_free, model.flow, target=bf.target)
        return [Option(added=(cand.name,), model=m, coarse=self.surface(cand.name, grid, sse), scan=None,
                       fine=self.surface(cand.name, fine, sse_fine))]

    def evaluate(self, model: Model, cand: Candidate) -> list[Option]:
        """Options that add ``cand`` to ``model``: coarse grid × pole set, global scan, refinement."""
        if cand.kind is Kind.LOOP:
            return []
        if cand.kind is Kind.OUTPUT:
            return self.output_options(model, cand)
        if cand.slot == "delay":
            return [self.delay_option(model, cand)]
        aim = self.scorer.aim(model)
        variants = self.variants(model, cand)
        parts = self.coarse_parts(model, cand)
        starts = self.coarse_starts(model, cand, variants, parts)
        # The coarse winner can be an artefact of grid placement — a continuous parameter trades off
        # against the poles (an actuator lag against the plant's time constant), and stiction's coarse
        # cost is rough — so the best start of each of the top pole hypotheses is scanned and refined, and
        # the choice is made afterwards.
        ranked = {v.free: self._ranked(starts[v.free], cand) for v in variants}
        scan = cand.scan(self.scorer.ctx(model))
        scanned = self.scan_surfaces(model.by_slot(), cand, scan, ranked, parts) if scan is not None else {}
        todo = [(v.free, i, start) for v in variants for i, start in enumerate(ranked[v.free])]
        p0s = [start.params if scanned.get((free, i)) is None else scan[int(np.argmin(scanned[(free, i)].sse))]
               for free, i, start in todo]
        refined = self.refine_all(model, cand, [(p0, start.structure, free)
                                                for p0, (free, _, start) in zip(p0s, todo)], joint=False)
        by_start = {(free, i): self._result(model, r, free, aim, scanned.get((free, i)))
                    for r, (free, i, _) in zip(refined, todo)}
        options = []
        for v in variants:
            results = [by_start[(v.free, i)] for i in range(len(ranked[v.free]))]
            if self.trades_with_prior(cand):
                results = self._joint_results(model, cand, v.free, results)
            best = min(results, key=lambda r: r.score)
            options.append(Option(added=v.added, model=best.model, coarse=ranked[v.free][0].coarse, scan=best.scan,
                                  fine=best.fine))
        return options

    def variants(self, model: Model, cand: Candidate) -> list[Variant]:
        """The dead time as ``model`` has it, and — while the nominal dead time is still trusted and the library
        has ``dead_time`` — freed together with ``cand``."""
        out = [Variant(model.delay_free, (cand.name,))]
        dead_time = self.library.get("dead_time")
        if not model.delay_free and dead_time is not None:
            out.append(Variant(True, (cand.name, dead_time.name)))
        return out

    def coarse_starts(self, model: Model, cand: Candidate, variants: list[Variant], parts: tuple[Part, ...]
                      ) -> dict[bool, list[Start]]:
        """Stage 1: the candidate's coarse grid through the chain once per part of the record scored
        (:meth:`coarse_parts`), scored for every pole hypothesis and every variant, the SSEs summed over the
        parts; the best row of each is a :class:`Start`, by variant (θ free or held)."""
        grid = cand.grid(self.scorer.ctx(model))
        poles = self.pole_set(model)
        free = any(v.free for v in variants)
        held = not all(v.free for v in variants)
        on_grid: list = [None] * len(poles)
        at_own: list = [None] * len(poles)
        # The parts (windows) are independent: they share the kernels' threads; their SSEs are summed in order.
        scored = run_each([functools.partial(self._coarse_part, part, model.by_slot(), cand, grid, poles, free, held)
                           for part in parts])
        for g, h in scored:
            on_grid, at_own = _summed(on_grid, g), _summed(at_own, h)
        n = sum(part.n_fit for part in parts)
        starts: dict[bool, list[Start]] = {v.free: [] for v in variants}
        for st, grid_delays, own_delay in zip(poles, on_grid, at_own):
            penalty = self.scorer.prior_penalty(st)
            for v in sorted(variants, key=lambda v: not v.free):
                sse, delays = grid_delays if v.free else own_delay
                flat = sse.min(axis=1)
                i = int(np.argmin(flat))
                score = log_sse(flat[i], n) + penalty
                st_b = replace(st, delay=float(delays[int(np.argmin(sse[i]))]) * self.p.dt) if v.free else st
                starts[v.free].append(Start(score=score, params=grid[i], structure=st_b,
                                            coarse=self.surface(cand.name, grid, flat, n)))
        return starts

    def _coarse_part(self, part: Part, active, cand: Candidate, grid: np.ndarray, poles: list[LinearStructure],
                     free: bool, held: bool) -> tuple[list, list]:
        """Stage 1 on one part of the record: per pole hypothesis, ``(sse, delays)`` over the dead-time grid (θ
        free) and at its own dead time (θ held), or None where that variant is not asked for."""
        flows = part.scorer.chain(active, part.ctx, cand, grid)
        # θ free: every pole hypothesis over the dead-time grid, in one pass over the flows.
        g = (part.scorer.sse_flows_all(flows, [(st, self.p.delays) for st in poles], part.aim) if free else
             [None] * len(poles))
        # θ held: its column of the θ-free result when it has one.
        h = ([_held_delay(part.scorer, flows, st, part.aim, gd) for st, gd in zip(poles, g)] if held else
             [None] * len(poles))
        return g, h

    def _result(self, model: Model, r: Refined, free: bool, aim: Aim, scan: Surface | None) -> Result:
        """Stage 3 from one start: ``r``, the candidate refined into ``model`` from it, scored (a dead time freed
        with it becomes the ``dead_time`` candidate of the model)."""
        active = dict(r.active)
        if free and not model.delay_free:
            active["delay"] = Active(self.library["dead_time"], np.array([r.fit.structure.delay]))
        m = self.scorer.model(active, r.fit, free, r.flow, target=aim.y)
        return Result(score=m.bic + self.scorer.prior_penalty(m.fit.structure), model=m, scan=scan, fine=r.fine)

    def _ranked(self, starts: list[Start], cand: Candidate) -> list[Start]:
        """The :data:`_STARTS` best starts, and for a candidate that trades off against the poles the best one at
        the nominal poles when it is not among them.

        With a nominal model the prior's mode must then always be refined: two lags in series fit the data
        equally well in either order (an actuator lag of 14 s before a 7.5 s plant is the same transfer function
        as 7.5 s before 15 s), so which of the two the coarse grid happens to place better says nothing, and
        only a start at the nominal poles lets the prior (:meth:`Scorer.prior_penalty`) choose between them.
        """
        ranked = sorted(starts, key=lambda r: r.score)
        top = ranked[:_STARTS]
        if self.trades_with_prior(cand) and self.nominal.structure.taus:
            nominal = self.nominal.structure.taus
            at_nominal = [r for r in ranked if r.structure.taus == nominal]
            if at_nominal and not any(r.structure.taus == nominal for r in top):
                top.append(at_nominal[0])
        return top

    def _joint_results(self, model: Model, cand: Candidate, free: bool, results: list[Result]) -> list[Result]:
        """The refined starts within :data:`_JOINT_MARGIN` of the best polished again by :meth:`joint_polish`
        (the others cannot overtake it), scored again.

        Only when the best start lowers the penalised BIC of ``model`` at all: an option that does not is far
        from the fall of 10 that it would need to count, and which of its starts wins does not matter.
        """
        best = min(r.score for r in results)
        if best >= model.bic + self.scorer.prior_penalty(model.fit.structure):
            return results
        ctx, aim = self.scorer.ctx(model), self.scorer.aim(model)
        out = []
        for r in results:
            if r.score - best > _JOINT_MARGIN:
                out.append(r)
                continue
            m = r.model
            active = m.by_slot()
            params, st = self.joint_polish(model.by_slot(), ctx, cand, active[cand.slot].params, m.fit.structure,
                                           free, aim)
            flow = self.scorer.chain(model.by_slot(), ctx, cand, params[None, :])[:, 0]
            fit = self.scorer.polish(flow, st, free, aim)
            active[cand.slot] = Active(cand, params)
            if "delay" in active and free and not model.delay_free:
                active["delay"] = Active(active["delay"].candidate, np.array([fit.structure.delay]))
            m = self.scorer.model(active, fit, free, flow, target=aim.y)
            out.append(Result(score=m.bic + self.scorer.prior_penalty(m.fit.structure), model=m, scan=r.scan,
                              fine=r.fine))
        return out

    def scan_surfaces(self, active, cand, scan, ranked: dict[bool, list[Start]], parts: tuple[Part, ...]
                      ) -> dict[tuple[bool, int], Surface]:
        """Stage 2: the scan's surface for every (θ free, start index) on the parts of the record the coarse
        stage scored (their SSEs summed), merging starts that share their poles into one job.

        A θ-free start needs the integer delays near its coarse best; a θ-fixed start its own delay (its
        column, when that delay is a whole number of samples; a separate job otherwise).
        """
        jobs: dict[tuple, set] = {}
        need = {}
        for free, starts in ranked.items():
            for i, st_b in enumerate(s.structure for s in starts):
                key = (st_b.taus, st_b.integrating, st_b.fixed_poles)
                ds = st_b.delay / self.p.dt
                if free:
                    want = set(self.scorer.near(st_b.delay, 3).tolist())
                elif abs(ds - round(ds)) < 1e-9:
                    want = {int(round(ds))}
                else:
                    key, want = key + (ds,), None  # fractional: its own job
                if want is None:
                    jobs[key] = None
                else:
                    jobs.setdefault(key, set()).update(want)
                need[(free, i)] = (key, want, st_b)
        keys = list(jobs)
        job_list = []
        for key in keys:
            st = next(v[2] for v in need.values() if v[0] == key)
            job_list.append((st, None if jobs[key] is None else np.array(sorted(jobs[key]))))
        scored: list = [None] * len(job_list)
        for part_scored in sse_jobs_many([(part.scorer, active, part.ctx, cand, scan, job_list, part.aim)
                                          for part in parts]):
            scored = _summed(scored, part_scored)
        results = dict(zip(keys, scored))
        n = sum(part.n_fit for part in parts)
        out = {}
        for vi, (key, want, _) in need.items():
            sse, delays = results[key]
            cols = slice(None) if want is None else np.isin(delays, sorted(want))
            out[vi] = self.surface(cand.name, scan, sse[:, cols].min(axis=1), n)
        return out

    def profile(self, model: Model, name: str) -> Surface:
        """Cost surface of one active candidate around its final value, the others held (for intervals).

        The dead time is profiled over integer samples around its value; other candidates over their
        :meth:`~valve_emulator.diagnosis.candidates.base.Candidate.profile_grid`, with a free dead time
        re-chosen within ±3 samples at every row (a profile, not a slice, of the likelihood) and a held one
        held.
        """
        a = next(x for x in model.active if x.name == name)
        st, aim = model.fit.structure, self.scorer.aim(model)
        if a.candidate.kind is Kind.OUTPUT:
            rest = replace(model, active=tuple(x for x in model.active if x is not a), target=None)
            g = a.candidate.refine(self.scorer.ctx(model), a.params)
            return self.surface(name, g, self.output_sse(rest, a.candidate, g))
        if a.slot == "delay":
            sse, delays = self.scorer.sse_flows(model.flow[:, None], st, self.scorer.near(st.delay, 6), aim)
            return self.surface(name, delays[:, None] * self.p.dt, sse[0])
        rest = {k: v for k, v in model.by_slot().items() if k != a.slot}
        ctx = self.scorer.ctx(model)
        g = a.candidate.profile_grid(ctx, a.params)
        delays = self.scorer.near(st.delay, 3) if model.delay_free else None
        sse, _ = self.scorer.sse_grid(rest, ctx, a.candidate, g, st, delays, aim)
        return self.surface(name, g, sse.min(axis=1))


def _held_delay(scorer: Scorer, flows: np.ndarray, st: LinearStructure, aim: Aim, grid: tuple | None) -> tuple:
    """SSE (n, 1) of ``flows`` at the structure's own dead time on ``scorer``'s record: the column of the
    dead-time grid's result ``grid`` when that dead time is a whole number of samples on the grid (the one-pass
    fit computes every dead time's normal equations from the same running sums, so the column is the same
    numbers), else a pass of its own."""
    if grid is not None:
        m, frac = split_delay(st.delay / scorer.p.dt)
        sse, delays = grid
        hit = np.flatnonzero(delays == m)
        if frac == 0.0 and hit.size:
            return sse[:, hit[:1]], delays[hit[:1]]
    return scorer.sse_flows(flows, st, None, aim)


def _summed(total: list, part: list) -> list:
    """Per job the ``(sse, delays)`` of ``total`` plus those of ``part`` (None in ``total``: not yet scored, or
    not asked for when ``part``'s is None too): the SSE of a job summed over the parts of the record scored."""
    return [p if t is None else (t[0] + p[0], t[1]) for t, p in zip(total, part)]
