r"""The numbers a least-squares fit is judged by, each computed in one place.

With Gaussian errors of unknown variance, −2 log-likelihood is :math:`N \ln(\mathrm{SSE}/N)` up to a
constant, so every comparison the search makes is one of three forms of the same quantity:

* :func:`log_sse`, ``N ln SSE``: the cost a polish minimises and a start is ranked by (a prior may be added);
* :func:`bic`, ``N ln(SSE/N) + k ln N``: what an option is accepted by (:func:`ar1_bic` that of a residual
  whose samples are correlated, under an AR(1) error);
* :func:`relative_cost`, ``N ln(SSE/SSE_min)`` over a cost surface: flat bottoms, intervals and the ΔBIC
  picture of the stiction scan.

An SSE of exactly zero (a noiseless simulated record) is floored at 10⁻³⁰⁰, so that the logarithm is finite.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ar1_bic", "bic", "log_sse", "relative_cost"]

#: Smallest SSE the logarithms see.
_FLOOR = 1e-300


def log_sse(sse: float, n: float) -> float:
    """``n ln SSE``: −2 log-likelihood up to a constant, the cost a polish minimises and starts are ranked by."""
    return n * np.log(max(sse, _FLOOR))


def bic(sse: float, n: int, k: int) -> float:
    """Bayesian information criterion of a Gaussian least-squares fit: ``n ln(sse/n) + k ln n``."""
    return float(n * np.log(max(sse, _FLOOR) / n) + k * np.log(n))


def ar1_bic(residual: np.ndarray, k: int) -> float:
    """:func:`bic` of ``residual`` under an AR(1) error :math:`e_k = \\rho e_{k-1} + w_k`, ρ fitted by least
    squares (within ±0.999) and counted as one more parameter than the model's ``k``: the BIC of the
    whitened residual ``w``, which treats correlated samples as the evidence they are."""
    r = np.asarray(residual, dtype=float)
    den = float(r[:-1] @ r[:-1])
    rho = float(np.clip(r[1:] @ r[:-1] / den, -0.999, 0.999)) if den > 0 else 0.0
    w = r[1:] - rho * r[:-1]
    return bic(float(w @ w), w.size, k + 1)


def relative_cost(sse: np.ndarray, n: float) -> np.ndarray:
    """``n ln(SSE/SSE_min)`` of every point of a cost surface: 0 at its best point, the χ² scale elsewhere."""
    return n * np.log(np.maximum(sse, _FLOOR) / max(float(np.min(sse)), _FLOOR))
