"""Array handling shared by the compiled kernels' callers: one parameter per element of a bank, and arrays in
the one layout the kernels are compiled for."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["kernel_array", "vector"]


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


def kernel_array(a: ArrayLike, dtype=np.float64) -> np.ndarray:
    """``a`` as a C-contiguous, writable array of ``dtype``, copied only when it is not one already.

    numba compiles (and caches) one specialisation per array layout *and* per read-only flag; frozen recordings
    and broadcast views are read-only, so without this a first run would compile a kernel twice.
    """
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()
