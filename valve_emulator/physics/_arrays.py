"""Argument checking shared by the physics banks: one parameter per element of a bank."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["vector"]


def vector(name: str, value: ArrayLike, n: int, *, dtype=float, finite: bool = False) -> np.ndarray:
    """``value`` as a new array of length ``n`` (a scalar is repeated); ValueError naming ``name`` otherwise.

    With ``finite=True`` non-finite elements are refused too.
    """
    try:
        arr = np.array(np.broadcast_to(np.asarray(value, dtype=dtype), (n,)))
    except (ValueError, TypeError):
        raise ValueError(f"{name} must be a scalar or have length {n}, got {value!r}") from None
    if finite and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr
