r"""Candidate ``quantization``: PV is measured on few levels, a staircase that imitates stick-slip.

A coarse transmitter or A/D resolution, a historian that stores few decimals, or an archive that keeps a
value until it changes by more than a dead band (exception reporting, "compression") all turn a smooth
PV into a staircase. In a flow loop a staircase PV is what a sticky valve produces too, so a quantised PV
must be tested before stiction is called. Unlike stiction, a quantiser has no memory: a PV near
a threshold chatters between two levels, while a stuck valve needs S to reverse.

Model (after the plant, ``output`` kind): the measured PV is the true PV snapped to the recorded levels,
so the true PV lies within ±h of every reading, ``h`` half the typical step between successive levels,

.. math::  h = \tfrac12\,\mathrm{median}\{\,|\Delta\mathrm{pv}_k| : \Delta\mathrm{pv}_k \ne 0\,\}

(``q/2`` for a uniform quantum q; about the dead band for an archive that holds values). The linear part
is fitted to the *interval* readings: its target is the point of :math:`[y_k - h, y_k + h]` nearest to its
own prediction, re-computed by backfitting (:mod:`~valve_emulator.diagnosis.fit.backfit`), which minimises the
dead-zone loss :math:`\sum_k \max(0, |\hat y_k - y_k| - h)^2` (the ε-insensitive loss of support-vector
regression; Vapnik, *The Nature of Statistical Learning Theory*, 1995). The same loss scores the held-out
part: a reading only says that PV lay within ±h, so the model's prediction of a reading is the value inside
that interval nearest to the linear part's prediction, and its error the distance to the interval (zero
when the linear part predicts within the reading's step). A model that misses by more than a step gains
at most h per sample.

``h`` is measured from the data, not searched (a wider interval always lowers the loss): the grid has one
row and the candidate counts one parameter for BIC. It applies only to a PV on few levels: at most
:data:`MAX_LEVEL_SHARE` of the samples hold distinct values, or PV repeats its previous value on at least
:data:`MIN_HOLD_SHARE` of the steps.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainContext, OutputCandidate, register

__all__ = ["Quantization", "quantum", "on_few_levels", "MAX_LEVEL_SHARE", "MIN_HOLD_SHARE"]

#: A PV whose distinct values number at most this share of its samples is on "few levels".
MAX_LEVEL_SHARE = 0.25
#: ... as is one that repeats its previous value on at least this share of the steps.
MIN_HOLD_SHARE = 0.5


def quantum(pv: np.ndarray) -> float:
    """Typical step between successive PV levels: the median non-zero ``|Δpv|`` (0 for a constant PV)."""
    d = np.abs(np.diff(np.asarray(pv, dtype=float)))
    d = d[d > 0.0]
    return float(np.median(d)) if d.size else 0.0


def on_few_levels(pv: np.ndarray) -> bool:
    """True when PV takes few distinct values or mostly holds them (see the module docstring)."""
    pv = np.asarray(pv, dtype=float)
    if pv.size < 3 or quantum(pv) == 0.0:
        return False
    held = float(np.mean(np.diff(pv) == 0.0))
    return np.unique(pv).size <= MAX_LEVEL_SHARE * pv.size or held >= MIN_HOLD_SHARE


class Quantization(OutputCandidate):
    name: ClassVar[str] = "quantization"
    slot: ClassVar[str] = "output"
    param_names: ClassVar[tuple[str, ...]] = ("q",)
    n_params: ClassVar[int] = 1
    cause_rank: ClassVar[int | None] = 20   # no twin role: the loop config has no measured-PV quantiser

    def applicable(self, ctx: ChainContext) -> bool:
        return ctx.pv is not None and on_few_levels(ctx.pv)

    def grid(self, ctx: ChainContext) -> np.ndarray:
        return np.array([[quantum(ctx.pv) if ctx.pv is not None else 0.0]])

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        return best[None, :]


    def adjust(self, y: np.ndarray, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext
               ) -> tuple[np.ndarray, np.ndarray]:
        h = 0.5 * float(params[0]) / ctx.y_scale
        return np.clip(y_lin, y - h, y + h), params

    def predict(self, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        y = (np.asarray(ctx.pv, dtype=float) - ctx.y_mean) / ctx.y_scale
        return self.adjust(y, y_lin, params, ctx)[0]

    def simulate(self, y_lin: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        """The prediction snapped to the nearest of the levels ``q · k`` in PV units (no record to snap to)."""
        q = float(params[0])
        if not q > 0.0:
            return y_lin
        pv = y_lin * ctx.y_scale + ctx.y_mean
        return (q * np.round(pv / q) - ctx.y_mean) / ctx.y_scale

    def parameters(self, p: np.ndarray) -> dict:
        return {"q": float(f"{float(p[0]):.4g}")}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        return f"a quantised PV (steps of about {p[0]:.3g} PV units)"


register(Quantization())
