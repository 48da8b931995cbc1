r"""Candidate ``disturbance``: an external oscillating disturbance — a cycle in PV that the valve does not cause.

A cycle from outside the loop (a neighbouring loop that oscillates, a compressor, day and night) enters
the process and the controller answers it, so OP and PV both cycle; with a linear valve the cycle in PV is
then *not* explained by replaying OP through the plant. Model (after the plant, ``output`` kind):

.. math::  \mathrm{pv}_k = G(q)\,f(\mathrm{OP})_k + A \sin(2\pi k\,\Delta t / P + \varphi) + e_k ,

a sinusoid of period P added to PV (a disturbance entering at the plant input reaches PV filtered by the
plant, which at one frequency only changes amplitude and phase, so the same term describes it). Three
parameters for BIC: P, A, φ. A and φ enter linearly (``a sin + b cos``), so for each P they are fitted by
least squares jointly with the linear part (:meth:`Disturbance.regressors`; backfitting would converge slowly,
since OP, which answers the disturbance, is strongly correlated with it); P is searched.

Why it must compete with stiction: a limit cycle caused by a sticky valve and a cycle from outside look
alike in PV and OP. They differ in what explains PV: the stuck valve reproduces each cycle from OP,
whatever its period, while an external disturbance is a coherent sinusoid that OP does not explain.

Grid: the periods of the :data:`N_PEAKS` largest peaks of the periodograms of three signals — what the
model being extended leaves unexplained (its residual), PV and OP — each linearly detrended on the fit part
and four-fold zero-padded, between 4 samples and a third of the fit part (at least three cycles: fewer
cannot be told from a drift); :meth:`refine` searches ±1 periodogram bin at a tenth of a bin. All three,
because a controller that answers a load cycle removes most of it from PV while OP carries it, and a
linear part fitted without the cycle is biased by it, so the residual need not show it either.
"""

from __future__ import annotations

import functools
from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainContext, OutputCandidate, TwinRole, register

__all__ = ["Disturbance", "N_PEAKS", "MIN_CYCLES"]

#: Periodogram peaks tried by the coarse grid.
N_PEAKS = 8
#: Fewest whole cycles of a disturbance within the fit part.
MIN_CYCLES = 3


def _window(ctx: ChainContext) -> tuple[int, int]:
    w0, w1 = ctx.window
    return (w0, w1) if w1 > w0 else (0, ctx.op.shape[0])


def _basis(P: float, ctx: ChainContext) -> tuple[np.ndarray, np.ndarray]:
    return _sinusoids(float(P), float(ctx.dt), int(ctx.op.shape[0]))


@functools.lru_cache(maxsize=2)
def _sinusoids(P: float, dt: float, T: int) -> tuple[np.ndarray, np.ndarray]:
    """sin ωk and cos ωk, ω = 2π dt / P, over T samples (read-only): a backfit asks for the same period's
    basis three times in a row (adjust, regressors, predict). Two entries catch those repeats; a larger cache
    caught few more and kept more record-length arrays alive after the diagnosis."""
    w = 2.0 * np.pi * dt / P * np.arange(T)
    s, c = np.sin(w), np.cos(w)
    s.flags.writeable = c.flags.writeable = False
    return s, c


def _peaks(x: np.ndarray, dt: float) -> np.ndarray:
    """Periods (s) of the :data:`N_PEAKS` largest periodogram peaks of ``x`` in the allowed band."""
    n = x.size
    k = np.arange(n)
    x = x - np.polyval(np.polyfit(k, x, 1), k)
    nfft = 4 * (1 << int(np.ceil(np.log2(max(n, 2)))))
    power = np.abs(np.fft.rfft(x, nfft)) ** 2
    f = np.arange(power.size) / nfft                       # cycles per sample
    ok = (f >= MIN_CYCLES / n) & (f <= 0.25)
    peak = np.zeros(power.size, dtype=bool)
    peak[1:-1] = (power[1:-1] >= power[:-2]) & (power[1:-1] >= power[2:])
    idx = np.flatnonzero(ok & peak)
    if idx.size == 0:
        idx = np.flatnonzero(ok)[:1]
    return dt / f[idx[np.argsort(power[idx])[::-1][:N_PEAKS]]]


class Disturbance(OutputCandidate):
    name: ClassVar[str] = "disturbance"
    slot: ClassVar[str] = "output"
    param_names: ClassVar[tuple[str, ...]] = ("period", "amplitude", "phase")
    n_params: ClassVar[int] = 3
    cause_rank: ClassVar[int | None] = 10
    twin_role: ClassVar[TwinRole | None] = TwinRole.DISTURBANCE

    def applicable(self, ctx: ChainContext) -> bool:
        w0, w1 = _window(ctx)
        return ctx.pv is not None and w1 - w0 >= 4 * MIN_CYCLES

    def grid(self, ctx: ChainContext) -> np.ndarray:
        w0, w1 = _window(ctx)
        signals = [ctx.residual, ctx.pv, ctx.op]
        periods = np.unique(np.concatenate([_peaks(np.asarray(x[w0:w1], dtype=float), ctx.dt)
                                            for x in signals if x is not None]))
        return np.column_stack([periods, np.zeros(periods.size), np.zeros(periods.size)])

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        w0, w1 = _window(ctx)
        f0 = ctx.dt / best[0]
        f = f0 + np.linspace(-1.0, 1.0, 21) / (w1 - w0)
        f = f[(f > 0.0) & (f <= 0.5)]
        rows = np.column_stack([ctx.dt / f, np.zeros(f.size), np.zeros(f.size)])
        return np.vstack([best[None, :], rows])


    def adjust(self, y: np.ndarray, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext
               ) -> tuple[np.ndarray, np.ndarray]:
        w0, w1 = _window(ctx)
        s, c = _basis(float(params[0]), ctx)
        X = np.column_stack([s[w0:w1], c[w0:w1]])
        (a, b), *_ = np.linalg.lstsq(X, (y - y_lin)[w0:w1], rcond=None)
        # A sin(ωt + φ) = A cos φ · sin ωt + A sin φ · cos ωt
        out = np.array([params[0], np.hypot(a, b) * ctx.y_scale, np.arctan2(b, a)])
        return y - (a * s + b * c), out

    def regressors(self, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        return np.column_stack(_basis(float(params[0]), ctx))

    def predict(self, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        s, c = _basis(float(params[0]), ctx)
        amp = float(params[1]) / ctx.y_scale
        return y_lin + amp * (np.cos(params[2]) * s + np.sin(params[2]) * c)

    def simulate(self, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        return self.predict(y_lin, params, ctx)  # the sinusoid needs no measurement: it runs on from t = 0

    def parameters(self, p: np.ndarray) -> dict:
        return {"period": round(float(p[0]), 3), "amplitude": float(f"{float(p[1]):.4g}")}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        return (f"an external oscillating disturbance: period ≈ {p[0]:.3g} s, amplitude ≈ {p[1]:.3g} "
                "PV units")


register(Disturbance())
