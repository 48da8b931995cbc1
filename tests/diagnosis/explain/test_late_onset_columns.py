"""A late candidate's columns, whatever the order of their onsets: the input before each row's onset, the inner
candidate started at it from then on, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator.diagnosis.candidates import ChainContext, get
from valve_emulator.diagnosis.explain.onset import LateOnset

T = 400
OP = 50.0 + 6.0 * np.sin(np.linspace(0.0, 9 * np.pi, T)) + 0.3 * np.cos(np.arange(T) / 3.0)
CTX = ChainContext(dt=0.5, op=OP, op_span=12.0)


def _expected(late: LateOnset, x: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Each row on its own: x up to its onset sample, the inner candidate on the rest (when two samples are left)."""
    cols = []
    for i, row in enumerate(params):
        xi = x if x.ndim == 1 else x[:, i]
        k0 = int(np.clip(np.round(row[-1] / CTX.dt), 0, T))
        col = xi.copy()
        if T - k0 >= 2:
            col[k0:] = late.inner.apply(xi[k0:].copy(), row[None, :-1], CTX)[:, 0]
        cols.append(col)
    return np.column_stack(cols)


@pytest.mark.parametrize("name", ["stiction", "deadband"])
@pytest.mark.parametrize("two_d", [False, True])
def test_rows_with_interleaved_onsets_match_each_row_alone(name, two_d):
    late = LateOnset(get(name))
    rng = np.random.default_rng(3)
    inner = late.inner.grid(CTX)[:12]
    onsets = np.array([30.0, 80.0, 30.0, 199.6, 0.0, 80.0, 30.0, 250.0, 199.6, 0.0, 80.0, 30.0])  # s; T·dt = 200
    params = LateOnset.with_onset(inner, onsets)
    x = OP if not two_d else OP[:, None] + rng.normal(0.0, 0.5, (T, params.shape[0]))
    got = late.apply(x, params, CTX)
    np.testing.assert_array_equal(got, _expected(late, x, params))
    np.testing.assert_array_equal(got[:, 7], x if x.ndim == 1 else x[:, 7])   # onset after the record: healthy


def test_rows_sharing_one_onset_match_each_row_alone():
    late = LateOnset(get("stiction"))
    params = LateOnset.with_onset(late.inner.grid(CTX), 55.0)
    np.testing.assert_array_equal(late.apply(OP, params, CTX), _expected(late, OP, params))
