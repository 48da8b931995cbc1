"""A valve that holds OP's moves inside a band, written for the tests independently of the package's physics."""

from __future__ import annotations

import numpy as np


def held(op: np.ndarray, width: float) -> np.ndarray:
    """The travel of a valve that holds until OP has moved ``width / 2`` beyond it either way (a play operator:
    a dead band of total width ``width``), starting at OP's first value."""
    out = np.empty_like(op)
    x = op[0]
    for k, u in enumerate(op):
        x = min(max(x, u - width / 2), u + width / 2)
        out[k] = x
    return out
