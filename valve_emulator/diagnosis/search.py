r"""Forward selection of left-out physics: Hammerstein fits on a global grid, ranked by BIC and held-out fit.

One round
---------
For every candidate not yet in the model (one per chain slot), the whole coarse parameter grid is pushed
through the chain at once (``(T, n)`` signals), filtered once per linear structure, and the linear part is
fitted by least squares for every grid row *and every dead time* of the delay grid in one compiled call
(:func:`~valve_emulator.diagnosis.linear.delay_grid_sse`). The best row is then refined twice on the
candidate's finer grid, each time followed by a Nelder–Mead polish of the poles (and of a free dead time).

The dead time is searched jointly with every candidate's parameters (a wrong dead time passes for less slip
jump, notes §5). While the nominal dead time is still trusted, each candidate yields two options: with θ
held at its nominal value, and together with ``dead_time`` (θ free). ``dead_time`` alone is a third kind of
option.

Significance (defined once, here, for every recording)
------------------------------------------------------
An option is *significant* against a smaller model when both

* BIC falls by at least :data:`DELTA_BIC` (BIC = N ln σ̂² + k ln N on the fit part; 10 is "very strong"
  evidence on the Kass & Raftery (1995) scale, a Bayes factor above about 150), and
* the free-run fit on the held-out part rises by at least :data:`DELTA_FIT` percentage points.

Threshold parameters sit on boundaries, so likelihood-ratio tests do not apply (notes §5); the held-out
free-run test guards against fitting noise. The round accepts the option with the lowest BIC that is
significant against the current model *and* against each of its own sub-options (so "stiction + dead time"
is accepted only if both parts carry weight). Rounds repeat until no option is significant.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainContext
from valve_emulator.diagnosis.chain import Active, run_chain
from valve_emulator.diagnosis.data import Problem
from valve_emulator.diagnosis.linear import (
    LinearFit,
    LinearStructure,
    delay_grid_sse,
    difference,
    filter_inputs,
    fit_one,
    polish,
)
from valve_emulator.diagnosis.nominal import Nominal, bic

__all__ = ["DELTA_BIC", "DELTA_FIT", "Model", "Surface", "Option", "Round", "Search"]

#: Least BIC decrease for an addition to count (see the module docstring).
DELTA_BIC = 10.0
#: Least held-out free-run fit gain, percentage points, for an addition to count.
DELTA_FIT = 0.5
#: Width of a "flat" cost bottom, in units of -2 log-likelihood (the 95 % point of chi-square, 1 dof).
_FLAT = 3.84
#: Grid rows pushed through the chain at once (bounds memory to a few hundred MB at 10^4 samples).
_CHUNK = 512


@dataclass(frozen=True, eq=False)
class Model:
    """A complete model: active physics, the fitted linear part and its scores."""

    active: tuple[Active, ...]
    fit: LinearFit
    delay_free: bool
    k: int
    bic: float
    heldout: float
    y_hat: np.ndarray   # scaled PV prediction over the whole record
    flow: np.ndarray    # chain output (T,)

    def by_slot(self) -> dict[str, Active]:
        return {a.slot: a for a in self.active}

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.active)


@dataclass(frozen=True, eq=False)
class Surface:
    """Fit-part SSE over a candidate's parameter rows (minimised over the delays the option allowed)."""

    candidate: str
    params: np.ndarray
    sse: np.ndarray
    n: int


@dataclass(frozen=True, eq=False)
class Option:
    """One way to extend the current model, fully fitted."""

    added: tuple[str, ...]
    model: Model
    coarse: Surface | None
    scan: Surface | None
    fine: Surface | None

    @property
    def label(self) -> str:
        return " + ".join(self.added)


@dataclass(frozen=True, eq=False)
class Round:
    baseline: Model
    options: tuple[Option, ...]   # sorted by BIC
    chosen: Option | None


def significant(new: Model, old: Model) -> bool:
    """The significance rule of the module docstring."""
    return (old.bic - new.bic >= DELTA_BIC) and (new.heldout - old.heldout >= DELTA_FIT)


def _frac_shift(z: np.ndarray, f: float) -> np.ndarray:
    """Rows of ``z`` delayed by a fraction ``f`` of a sample (linear interpolation)."""
    if f <= 0.0:
        return z
    out = z.copy()
    out[:, 1:] = (1.0 - f) * z[:, 1:] + f * z[:, :-1]
    return out


class Search:
    """Runs the rounds for one problem (a fitting machine; its results are :class:`Round` objects)."""

    def __init__(self, problem: Problem, nominal: Nominal, library: dict[str, Candidate], *,
                 progress: Callable[[str], None] | None = None) -> None:
        self.p = problem
        self.nominal = nominal
        self.library = library
        self.say = progress or (lambda msg: None)
        self.dmax = float(problem.delays.max()) * problem.dt
        self.diff = problem.difference
        self.target = difference(problem.y) if problem.difference else problem.y
        self.prior = nominal.structure.taus if nominal.given else None

    # -- building blocks -------------------------------------------------------------------------------------
    def ctx(self, model: Model | None) -> ChainContext:
        st = model.fit.structure if model else self.nominal.structure
        return ChainContext(dt=self.p.dt, op=self.p.op, op_span=self.p.op_span,
                            valve_model=self.nominal.valve_model, rest_samples=self.nominal.rest_samples,
                            characteristic=self.nominal.characteristic,
                            tau_plant=max(st.taus, default=10.0 * self.p.dt), delay=st.delay)

    def chain(self, active: dict[str, Active], ctx: ChainContext, cand: Candidate | None = None,
              grid: np.ndarray | None = None) -> np.ndarray:
        return run_chain(self.p.op, active, ctx, nominal_valve=(self.nominal.S, self.nominal.J),
                         grid_candidate=cand, grid=grid)

    def model(self, active: dict[str, Active], fit: LinearFit, delay_free: bool, flow: np.ndarray) -> Model:
        """Score a fitted model: BIC from the fit-part SSE of ``fit`` (the search domain, differences when
        the problem says so), the held-out fit from a PV-domain fit at the same structure."""
        acts = []
        for a in active.values():
            if a.slot == "delay":  # the dead-time candidate's parameter is the fitted dead time
                a = Active(a.candidate, np.array([fit.structure.delay]))
            acts.append(a)
        k = fit.structure.n_params() + int(delay_free) + sum(
            a.candidate.n_params for a in acts if a.slot != "delay")
        level = fit_one(flow, self.p.y, self.p.train, fit.structure, self.p.dt) if self.diff else fit
        y_hat = level.predict(flow, self.p.dt)
        return Model(tuple(acts), level, delay_free, k, bic(fit.sse, fit.n, k), self.p.heldout_fit(y_hat),
                     y_hat, flow)

    def _pole_set(self, model: Model) -> list[LinearStructure]:
        """Linear dynamics tried by the coarse stage of every candidate search.

        A missing valve nonlinearity biases the poles re-fitted around the nominal chain (stiction in the
        concentration loop drags the fitted time constant from 10 s to about 80 s), and with wrong poles
        the valve's cost basin disappears. So the coarse stage also tries the nominal poles scaled by
        2^(±1/2), 2^(±1) — or, without a model, first order with time constants from Δt to a tenth of the
        record and an integrator — and later stages use the best.
        """
        st = model.fit.structure
        out = [st]
        if self.nominal.given:
            nom = replace(self.nominal.structure, delay=st.delay)
            for f in (1.0, 0.5, 2 ** -0.5, 2 ** 0.5, 2.0):
                if nom.taus or f == 1.0:
                    out.append(replace(nom, taus=tuple(t * f for t in nom.taus)))
        else:
            dt = self.p.dt
            out += [replace(a, delay=st.delay) for a in self.nominal.alternates]
            out += [LinearStructure(taus=(float(t),), delay=st.delay)
                    for t in np.geomspace(dt, max(2 * dt, self.p.T * dt / 10.0), 8)]
            out.append(LinearStructure(integrating=True, delay=st.delay))
        return out

    def _prior_penalty(self, st: LinearStructure) -> float:
        """The weak prior of :func:`~valve_emulator.diagnosis.linear.polish`, for comparing pole sets."""
        if self.prior is None or len(self.prior) != len(st.taus) or not st.taus:
            return 0.0
        d = np.sort(np.log(st.taus)) - np.sort(np.log(self.prior))
        return float(np.sum((d / np.log(2.0)) ** 2))

    def _polish(self, flow, st, free):
        return polish(flow, self.p.y, self.p.train, st, self.p.dt, free_delay=free,
                      delay_bounds=(0.0, self.dmax), difference_=self.diff, prior=self.prior)

    def _sse_flows(self, flows: np.ndarray, st: LinearStructure, delays: np.ndarray | None) -> tuple:
        """SSE (n, nd) for chain outputs ``flows`` (T, n) and the delays searched (samples).

        ``delays=None`` holds the structure's own (possibly fractional) dead time.
        """
        z = filter_inputs(flows.T, st, self.p.dt)
        if self.diff:
            z = difference(z)
        if delays is None:
            ds = st.delay / self.p.dt
            m = int(np.floor(ds + 1e-9))
            z, delays = _frac_shift(z, ds - m), np.array([m])
        return delay_grid_sse(z, self.target, self.p.train, delays, st, difference=self.diff), delays

    def _sse_grid(self, active, ctx, cand, grid, st, delays) -> tuple:
        """:meth:`_sse_flows` for a parameter grid, in chunks of :data:`_CHUNK` rows (bounded memory)."""
        parts, used = [], None
        for a in range(0, grid.shape[0], _CHUNK):
            flows = self.chain(active, ctx, cand, grid[a:a + _CHUNK])
            sse, used = self._sse_flows(flows, st, delays)
            parts.append(sse)
        return np.vstack(parts), used

    def _near(self, d: float, r: int) -> np.ndarray:
        d0 = int(round(d / self.p.dt))
        lo, hi = int(self.p.delays.min()), int(self.p.delays.max())
        return np.arange(max(lo, d0 - r), min(hi, d0 + r) + 1)

    # -- the base model --------------------------------------------------------------------------------------
    def base(self) -> Model:
        """Nominal chain with the linear part re-fitted (poles; the dead time too when there is no model)."""
        ctx = self.ctx(None)
        flow = self.chain({}, ctx)[:, 0]
        free = not self.nominal.given
        fit = self._polish(flow, self.nominal.structure, free)
        return self.model({}, fit, free, flow)

    # -- one candidate ---------------------------------------------------------------------------------------
    def _refine(self, model: Model, cand: Candidate, best: np.ndarray, st: LinearStructure, free: bool):
        """Two passes of fine grid + polish around ``best``; returns (active, fit, flow, fine Surface)."""
        active = model.by_slot()
        ctx = self.ctx(model)
        for _ in range(2):
            g = cand.refine(ctx, best)
            sse, delays = self._sse_grid(active, ctx, cand, g, st, self._near(st.delay, 2) if free else None)
            i, j = np.unravel_index(int(np.argmin(sse)), sse.shape)
            best = g[i]
            st0 = replace(st, delay=float(delays[j]) * self.p.dt) if free else st
            flow = self.chain(active, ctx, cand, g[i:i + 1])[:, 0]
            fit = self._polish(flow, st0, free)
            st = fit.structure
        fine = Surface(cand.name, g, sse.min(axis=1), self.p.n_fit)
        if cand.threshold_axes:
            best = self._centre(active, ctx, cand, best, st)
            flow = self.chain(active, ctx, cand, best[None, :])[:, 0]
            fit = self._polish(flow, st, free)
        new_active = dict(active)
        new_active[cand.slot] = Active(cand, best)
        return new_active, fit, flow, fine

    def _centre(self, active, ctx, cand, best, st) -> np.ndarray:
        """Move each threshold parameter to the middle of the flat bottom of its cost.

        With noisy OP the fit-part cost is piecewise constant in a threshold (each slip happens at the
        first sample past it), so every value inside the cell that contains the argmin replays the fit
        part equally well, and the argmin may sit at the cell's edge. Events in the held-out part cut the
        cell at uniformly distributed places; its middle is the value least likely to miss one. The
        flat bottom is the contiguous run around the argmin with N·ln(SSE/SSE_min) ≤ :data:`_FLAT`.
        """
        for axis in cand.threshold_axes:
            rows = cand.line(ctx, best, axis)
            sse, _ = self._sse_grid(active, ctx, cand, rows, st, None)
            cost = self.p.n_fit * np.log(np.maximum(sse[:, 0], 1e-300) / max(sse[:, 0].min(), 1e-300))
            i = int(np.argmin(cost))
            lo = hi = i
            while lo > 0 and cost[lo - 1] <= _FLAT:
                lo -= 1
            while hi < cost.size - 1 and cost[hi + 1] <= _FLAT:
                hi += 1
            best = rows[i].copy()
            best[axis] = 0.5 * (rows[lo, axis] + rows[hi, axis])
        return best

    def _delay_option(self, model: Model, cand: Candidate) -> Option:
        flow = model.flow
        sse, delays = self._sse_flows(flow[:, None], model.fit.structure, self.p.delays)
        st = replace(model.fit.structure, delay=float(delays[int(np.argmin(sse[0]))]) * self.p.dt)
        fit = self._polish(flow, st, True)
        active = model.by_slot()
        active["delay"] = Active(cand, np.array([fit.structure.delay]))
        surf = Surface(cand.name, delays[:, None] * self.p.dt, sse[0], self.p.n_fit)
        return Option((cand.name,), self.model(active, fit, True, flow), surf, None, surf)

    def evaluate(self, model: Model, cand: Candidate) -> list[Option]:
        """Options that add ``cand`` to ``model``: coarse grid × pole set, global scan, refinement."""
        if cand.slot == "delay":
            return [self._delay_option(model, cand)]
        ctx = self.ctx(model)
        active = model.by_slot()
        dead_time = self.library.get("dead_time")
        variants = [(model.delay_free, (cand.name,))]
        if not model.delay_free and dead_time is not None:
            variants.append((True, (cand.name, dead_time.name)))
        grid = cand.grid(ctx)
        flows = self.chain(active, ctx, cand, grid)
        best: dict[bool, tuple] = {}
        for st in self._pole_set(model):
            penalty = self._prior_penalty(st)
            for free, _ in variants:
                sse, delays = self._sse_flows(flows, st, self.p.delays if free else None)
                flat = sse.min(axis=1)
                i = int(np.argmin(flat))
                score = self.p.n_fit * np.log(max(flat[i], 1e-300)) + penalty
                if free not in best or score < best[free][0]:
                    st_b = replace(st, delay=float(delays[int(np.argmin(sse[i]))]) * self.p.dt) if free else st
                    best[free] = (score, grid[i], st_b, Surface(cand.name, grid, flat, self.p.n_fit))
        scan = cand.scan(ctx)
        options = []
        for free, added in variants:
            _, p0, st_b, coarse = best[free]
            scan_surface = None
            if scan is not None:
                sse, _ = self._sse_grid(active, ctx, cand, scan, st_b, self._near(st_b.delay, 3) if free else None)
                flat = sse.min(axis=1)
                p0 = scan[int(np.argmin(flat))]
                scan_surface = Surface(cand.name, scan, flat, self.p.n_fit)
            new_active, fit, flow, fine = self._refine(model, cand, p0, st_b, free)
            if free and not model.delay_free:
                new_active["delay"] = Active(dead_time, np.array([fit.structure.delay]))
            options.append(Option(added, self.model(new_active, fit, free, flow), coarse, scan_surface, fine))
        return options

    # -- the rounds ------------------------------------------------------------------------------------------
    def _candidates(self, model: Model) -> list[Candidate]:
        used = set(model.by_slot())
        out = []
        for cand in self.library.values():
            if cand.slot in used:
                continue
            if cand.slot == "delay" and model.delay_free:
                continue
            out.append(cand)
        return out

    def round(self, model: Model, index: int) -> Round:
        options: list[Option] = []
        cands = self._candidates(model)
        for c, cand in enumerate(cands):
            self.say(f"round {index}: {cand.name} ({c + 1}/{len(cands)})")
            options += self.evaluate(model, cand)
        options.sort(key=lambda o: o.model.bic)
        chosen = None
        for o in options:
            subs = [s for s in options if set(s.added) < set(o.added)]
            if significant(o.model, model) and all(significant(o.model, s.model) for s in subs):
                chosen = o
                break
        return Round(model, tuple(options), chosen)

    def run(self) -> tuple[Model, list[Round]]:
        """Base model, then rounds while an option is significant. Returns (final model, rounds)."""
        self.say("fitting the linear part around the nominal chain")
        model = self.base()
        rounds = []
        while self._candidates(model):
            rnd = self.round(model, len(rounds) + 1)
            rounds.append(rnd)
            if rnd.chosen is None:
                break
            self.say(f"round {len(rounds)}: added {rnd.chosen.label} (BIC {model.bic - rnd.chosen.model.bic:.0f} "
                     f"lower, held-out fit {model.heldout:.1f} -> {rnd.chosen.model.heldout:.1f} %)")
            model = self._rerefine(rnd.chosen.model, rnd.chosen.added)
        return model, rounds

    def _rerefine(self, model: Model, just_added: tuple[str, ...]) -> Model:
        """Refine earlier-accepted grid physics again with the new one in place; keep it if BIC improves."""
        for a in model.active:
            if a.name in just_added or a.slot == "delay":
                continue
            rest = Model(tuple(b for b in model.active if b is not a), model.fit, model.delay_free, model.k,
                         model.bic, model.heldout, model.y_hat, model.flow)
            active, fit, flow, _ = self._refine(rest, a.candidate, a.params, model.fit.structure,
                                                model.delay_free)
            if "delay" in model.by_slot():
                active["delay"] = model.by_slot()["delay"]
            new = self.model(active, fit, model.delay_free, flow)
            if new.bic < model.bic:
                model = new
        return model
