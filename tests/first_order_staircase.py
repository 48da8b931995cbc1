"""A first-order plant under a random OP staircase, prepared as the diagnosis' fit stages see it: a small problem
for tests of the scorer and of the work the search shares, with the nominal model that made it."""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from valve_emulator.diagnosis.fit.data import Problem, prepare
from valve_emulator.diagnosis.fit.linear import LinearStructure
from valve_emulator.diagnosis.fit.nominal import Nominal
from valve_emulator.recordings.recording import Recording

#: The plant's nominal model: gain 2, time constant 10 s, dead time 2 s.
NOMINAL = Nominal(structure=LinearStructure(taus=(10.0,), delay=2.0), given=True, num=(2.0,), den=(10.0, 1.0))


def staircase_problem(T: int, load: float = 0.0) -> Problem:
    """``T`` samples (1 s) of the plant driven by a random staircase (steps of 25 s between 30 and 70 %), plus a
    sinusoidal load of amplitude ``load`` (period 90 s) and a little noise, prepared around the nominal dead time."""
    rng = np.random.default_rng(3)
    op = np.repeat(rng.uniform(30.0, 70.0, T // 25), 25)
    a = np.exp(-0.1)
    pv = lfilter([0.0, 0.0, 0.0, 2.0 * (1.0 - a)], [1.0, -a], op - 50.0)
    if load:
        pv = pv + load * np.sin(2.0 * np.pi * np.arange(T) / 90.0)
    pv = pv + rng.normal(0.0, 0.05, T)
    rec = Recording(np.arange(T, dtype=float), None, op, None, pv, source="mem.csv")
    return prepare(rec, nominal_delay=2.0, settle_time=40.0)
