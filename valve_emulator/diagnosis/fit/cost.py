r"""The numbers a least-squares fit is judged by, each computed in one place.

With Gaussian errors of unknown variance, −2 log-likelihood is :math:`N \ln(\mathrm{SSE}/N)` up to a
constant, so every comparison the search makes is one of three forms of the same quantity:

* :func:`log_sse`, ``N ln SSE``: the cost a polish minimises and a start is ranked by (a prior may be added);
* :func:`bic`, ``N ln(SSE/N) + k ln N``: what an option is accepted by;
* :func:`relative_cost`, ``N ln(SSE/SSE_min)`` over a cost surface: flat bottoms, intervals and the ΔBIC
  picture of the stiction scan.

An SSE of exactly zero (a noiseless simulated record) is floored at 10⁻³⁰⁰, so that the logarithm is finite.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bic", "log_sse", "relative_cost"]

#: Smallest SSE the logarithms see.
_FLOOR = 1e-300


def log_sse(sse: float, n: float) -> float:
    """``n ln SSE``: −2 log-likelihood up to a constant, the cost a polish minimises and starts are ranked by."""
    return n * np.log(max(sse, _FLOOR))


def bic(sse: float, n: int, k: int) -> float:
    """Bayesian information criterion of a Gaussian least-squares fit: ``n ln(sse/n) + k ln n``."""
    return float(n * np.log(max(sse, _FLOOR) / n) + k * np.log(n))


def relative_cost(sse: np.ndarray, n: float) -> np.ndarray:
    """``n ln(SSE/SSE_min)`` of every point of a cost surface: 0 at its best point, the χ² scale elsewhere."""
    return n * np.log(np.maximum(sse, _FLOOR) / max(float(np.min(sse)), _FLOOR))
