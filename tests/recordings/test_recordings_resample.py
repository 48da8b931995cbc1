"""``regularize``: a uniform record comes back as it is (same object, no note), so calling it twice is harmless."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from valve_emulator.recordings import Recording, regularize


def _record(t: np.ndarray) -> Recording:
    k = np.arange(t.size)
    return Recording(t, np.full(t.size, 50.0), 40.0 + (k // 7 % 2) * 5.0, np.sin(k / 5.0), np.cos(k / 9.0),
                     extra={"mode": np.ones(t.size)}, source="mem.csv")


def test_a_uniform_record_is_returned_unchanged_without_a_note():
    rec = _record(1.7e9 + 0.1 * np.arange(200_000))        # POSIX-like times, 0.1 s steps
    out, note = regularize(rec)
    assert out is rec and note is None


@settings(max_examples=60, deadline=None)
@given(n=st.integers(5, 400), dt=st.floats(1e-3, 100.0), t0=st.floats(0.0, 1e6),
       seed=st.integers(0, 2**32 - 1), late=st.floats(0.05, 0.4))
def test_regularize_is_idempotent(n, dt, t0, seed, late):
    """Polling jitter (some rows up to ``late`` × dt late) is resampled once; the result is then uniform."""
    rng = np.random.default_rng(seed)
    t = t0 + dt * (np.arange(n) + late * (rng.random(n) < 0.3))
    first, note = regularize(_record(t))
    again, note2 = regularize(first)
    assert again is first and note2 is None
    steps = np.diff(first.t)
    assert np.allclose(steps, steps[0], rtol=1e-6, atol=0.0)
    if note is None:                                        # nothing was late: the record itself came back
        assert np.array_equal(first.t, t)
