"""The 2003 paper's Figure 5: the stiction model in open loop under a sinusoidal input.

Five rows (Choudhury, Thornhill & Shah, ADCHEM 2003, Section 4.2): no stiction, pure deadband (j = 0),
undershoot (j < s/2), no offset (j = s/2), overshoot (j > s/2). The paper does not print the values it used for
Figure 5; we use s = 5 % with the j of its Table 1 concentration loop, typed in the 2003 paper's form and converted
with J = 2 j, and an input of amplitude 10 % around 50 % with a 100 s period.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from valve_emulator.physics.stiction import DEFAULT_MODEL, seed_to_2005, simulate

__all__ = ["FIGURE5_CASES", "Figure5Data", "figure5_data"]

#: (label, s, j as the 2003 paper prints them)
FIGURE5_CASES = (
    ("no stiction", 0.0, 0.0),
    ("pure deadband: s = 5, j = 0", 5.0, 0.0),
    ("undershoot: s = 5, j = 1 (j < s/2)", 5.0, 1.0),
    ("no offset: s = 5, j = 2.5 (j = s/2)", 5.0, 2.5),
    ("overshoot: s = 5, j = 3.5 (j > s/2)", 5.0, 3.5),
)


@dataclass(frozen=True)
class Figure5Data:
    t: np.ndarray
    op: np.ndarray
    rows: tuple[tuple[str, float, float, np.ndarray], ...]  # (label, S, J, mv), 2005 convention


def figure5_data(*, model: str = DEFAULT_MODEL, dt: float = 0.1, duration: float = 200.0,
                 amplitude: float = 10.0, period: float = 100.0, level: float = 50.0) -> Figure5Data:
    t = np.arange(0.0, duration + dt / 2, dt)
    op = level + amplitude * np.sin(2 * np.pi * t / period)
    rows = []
    for label, s, j in FIGURE5_CASES:
        S, J = seed_to_2005(s, j)
        rows.append((label, S, J, simulate(op, S=S, J=J, model=model)))
    return Figure5Data(t=t, op=op, rows=tuple(rows))
