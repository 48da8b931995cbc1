"""The bank's one-model kernel (selects, column-major state) against the per-valve kernel (branches).

:class:`~valve_emulator.physics.stiction.StictionBank` steps its valves with ``step_same_model``, a second
formulation of the state machines written for vectorisation; :func:`stiction_step_kernel`, which the diagnosis
and the loop kernel use, keeps the branches. Both must give the same state, every column, bit for bit (compared
as integers, so that -0.0 and 0.0 differ too), after every sample: on input that takes every branch -- repeated
OP (the rest criterion, R > 1), reversals, slip jumps, OP outside 0..100, J = 0, J = S and J > S.
"""

import numpy as np
import pytest

from valve_emulator.physics.stiction import (
    DIR,
    FLAG,
    MODELS,
    MV,
    NSTATE,
    STILL,
    STUCK,
    VECTOR_MIN,
    StictionBank,
    initial_state,
    simulate_many,
    step_same_model,
    stiction_step_kernel,
)

# Enough valves for the vector loop, and not a multiple of any vector width: the scalar remainder runs too.
N = 4 * VECTOR_MIN + 5


def bits(state):
    return np.ascontiguousarray(state).view(np.uint64)


def parameters(rng, n, grid=False):
    """S (some 0), J: 0, below S, = S or above S (overshoot), rest_samples 1..4 (as floats, like the bank).

    With ``grid`` S and J are multiples of 0.5, so that with :func:`op_samples` on its grid the comparisons of
    the state machines meet their thresholds exactly (``>`` against ``>=`` matters)."""
    S = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0.0, 8.0, n))
    kind = rng.integers(0, 4, n)
    J = np.select([kind == 0, kind == 1, kind == 2], [0.0, rng.uniform(0, 1, n) * S, S],
                  S + rng.uniform(0.0, 4.0, n))
    if grid:
        S, J = np.round(2 * S) / 2, np.round(2 * J) / 2
    R = rng.integers(1, 5, n).astype(float)
    return S, J, R


def op_samples(rng, n, T, grid=False):
    """(T, n) OP: a random walk with reversals and slip-sized steps, held values (runs of du == 0), large jumps,
    and values beyond the stops, exactly on them, and -0.0. With ``grid`` every value is a multiple of 0.25."""
    op = np.empty((T, n))
    u = rng.uniform(-10.0, 110.0, n)
    for k in range(T):
        r = rng.random(n)
        u = np.where(r < 0.35, u, u + rng.normal(0.0, 2.5, n))                     # held (35 %) or a step
        u = np.where((r > 0.90) & (r < 0.95), rng.uniform(-30.0, 130.0, n), u)       # a jump, maybe saturating
        if grid:
            u = np.round(4 * u) / 4
        u = np.where(r >= 0.99, rng.choice([-0.0, 0.0, 100.0, -5.0, 105.0], n), u)  # on or beyond the stops
        op[k] = u
    return op


def reference_and_bank(rng, model, n, grid=False):
    S, J, R = parameters(rng, n, grid)
    codes = np.full(n, MODELS.index(model), dtype=np.int64)
    op0 = rng.uniform(-10.0, 110.0, n)
    direction = rng.choice([-1.0, 1.0], n)
    ref = np.zeros((n, NSTATE))          # row-major, as the callers of stiction_step_kernel hold it
    initial_state(ref, op0, direction, S, J, codes)
    bank = StictionBank(n, S=S, J=J, model=model, rest_samples=R.astype(np.int64))
    bank.reset(op0, direction)
    return S, J, R, codes, ref, bank


@pytest.mark.parametrize("seed, grid", [(0, False), (1, False), (2, True), (3, True)])
@pytest.mark.parametrize("model", MODELS)
def test_bank_step_equals_per_valve_kernel_bit_for_bit(model, seed, grid):
    rng = np.random.default_rng(seed)
    S, J, R, codes, ref, bank = reference_and_bank(rng, model, N, grid)
    assert bank._state.flags.f_contiguous          # the layout the one-model loop vectorises over
    np.testing.assert_array_equal(bits(bank._state), bits(ref))
    stuck, moving, still = 0, 0, 0
    for k, u in enumerate(op_samples(rng, N, 400, grid)):
        stiction_step_kernel(u, S, J, R, codes, ref)
        mv = bank.step(u)
        if not np.array_equal(bits(bank._state), bits(ref)):
            bad = np.flatnonzero((bits(bank._state) != bits(ref)).any(axis=1))[0]
            pytest.fail(f"sample {k}, valve {bad}: bank {bank._state[bad]} != reference {ref[bad]} "
                        f"(u={u[bad]!r}, S={S[bad]!r}, J={J[bad]!r}, R={R[bad]!r})")
        assert np.array_equal(mv, ref[:, MV])
        stuck += int((ref[:, STUCK] == 1.0).sum())
        moving += int((ref[:, STUCK] == 0.0).sum())
        still = max(still, ref[:, STILL].max())
    # The input took the valves through both outcomes (and, for Kano, through rests longer than one sample).
    assert stuck > N and moving > N
    if model == "kano":
        assert still >= 4 and set(np.unique(ref[:, DIR])) == {-1.0, 1.0} and set(np.unique(ref[:, FLAG])) == {0.0, 1.0}


@pytest.mark.parametrize("model", MODELS)
def test_one_model_kernel_on_row_major_state(model):
    """Correct whatever the layout: numba compiles the kernel once per layout, and row-major does not vectorise."""
    rng = np.random.default_rng(7)
    S, J, R, codes, ref, _ = reference_and_bank(rng, model, N)
    rows = ref.copy()
    for u in op_samples(rng, N, 200):
        stiction_step_kernel(u, S, J, R, codes, ref)
        step_same_model(u, S, J, R, codes[0], rows)
        assert np.array_equal(bits(rows), bits(ref))


@pytest.mark.parametrize("model", MODELS)
def test_scalar_op_broadcasts(model):
    rng = np.random.default_rng(9)
    S, J, R, codes, ref, bank = reference_and_bank(rng, model, N)
    for x in (50.0, 50.0, 50.0, 52.5, 60.0, -3.0, -3.0, 101.0, 47.0, 47.0, 47.0, 47.0, 30.0):
        stiction_step_kernel(np.full(N, x), S, J, R, codes, ref)
        bank.step(x)
        assert np.array_equal(bits(bank._state), bits(ref))


@pytest.mark.parametrize("model", MODELS)
def test_bank_run_and_simulate_many_equal_stepping_the_per_valve_kernel(model):
    rng = np.random.default_rng(11)
    S, J, R, codes, ref, bank = reference_and_bank(rng, model, N)
    op = op_samples(rng, N, 300)
    expected = np.empty_like(op)
    start = np.zeros_like(ref)
    for k, u in enumerate(op):
        stiction_step_kernel(u, S, J, R, codes, ref)
        expected[k] = ref[:, MV]
    assert np.array_equal(bits(bank.run(op)), bits(expected))
    assert np.array_equal(bits(bank._state), bits(ref))     # and the state carries on from where it ended
    # simulate_many starts at rest at op[0], direction +1: the reference from that state.
    initial_state(start, op[0], np.ones(N), S, J, codes)
    for k, u in enumerate(op):
        stiction_step_kernel(u, S, J, R, codes, start)
        expected[k] = start[:, MV]
    many = simulate_many(op, S, J, model=model, rest_samples=R.astype(np.int64))
    assert np.array_equal(bits(many), bits(expected))


def test_mixed_models_give_each_valve_its_own_model():
    """stiction_step_kernel with models mixed valve by valve equals one bank per model, valve for valve."""
    rng = np.random.default_rng(5)
    per_model = N
    codes = rng.permutation(np.repeat(np.arange(len(MODELS)), per_model)).astype(np.int64)
    n = codes.size
    S, J, R = parameters(rng, n)
    op0, direction = rng.uniform(-10.0, 110.0, n), rng.choice([-1.0, 1.0], n)
    mixed = np.zeros((n, NSTATE))
    initial_state(mixed, op0, direction, S, J, codes)
    banks = []
    for code, model in enumerate(MODELS):
        sel = np.flatnonzero(codes == code)
        bank = StictionBank(sel.size, S=S[sel], J=J[sel], model=model, rest_samples=R[sel].astype(np.int64))
        bank.reset(op0[sel], direction[sel])
        banks.append((sel, bank))
    kano_for_all = mixed.copy()          # what a kernel ignoring the codes would give
    for u in op_samples(rng, n, 300):
        stiction_step_kernel(u, S, J, R, codes, mixed)
        stiction_step_kernel(u, S, J, R, np.full(n, MODELS.index("kano")), kano_for_all)
        for sel, bank in banks:
            bank.step(u[sel])
            assert np.array_equal(bits(bank._state), bits(mixed[sel]))
    # The models really differ on this input, so the comparison above would notice valves given the wrong one.
    for code, model in enumerate(MODELS):
        sel = codes == code
        assert np.array_equal(mixed[sel], kano_for_all[sel]) == (model == "kano")


@pytest.mark.parametrize("n", [1, VECTOR_MIN - 1, VECTOR_MIN, VECTOR_MIN + 1])
def test_either_side_of_the_vector_threshold(n):
    rng = np.random.default_rng(n)
    for model in MODELS:
        S, J, R, codes, ref, bank = reference_and_bank(rng, model, n)
        assert bank._selects == (n >= VECTOR_MIN)
        for u in op_samples(rng, n, 150):
            stiction_step_kernel(u, S, J, R, codes, ref)
            bank.step(u)
            assert np.array_equal(bits(bank._state), bits(ref))
