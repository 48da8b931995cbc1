"""The candidate physics: registry, parameter vocabulary, grids, and each batched transform against physics."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest

from valve_emulator.diagnosis.candidates import (
    SLOTS,
    Candidate,
    ChainContext,
    TwinRole,
    get,
    register,
    registry,
    valve_start,
)
from valve_emulator.diagnosis.candidates.actuator_lag import first_order_lag
from valve_emulator.diagnosis.candidates.stiction import stiction_kind
from valve_emulator.diagnosis.candidates.valve_start import (
    PRE_ROLL,
    STARTS,
    sync_burn_in,
    valve_burn_in,
    valve_output,
)
from valve_emulator.diagnosis.fit.chain import Active, run_chain
from valve_emulator.physics.signal_chain import Characteristic
from valve_emulator.physics.stiction import StictionBank


def simulate(op, *, S, J, model="kano", direction=1.0, op0=None):
    """The physics layer's valve stepped sample by sample (an independent path to the same kernels)."""
    bank = StictionBank(1, S=S, J=J, model=model)
    bank.reset(op[0] if op0 is None else op0, direction)
    return np.array([bank.step(np.array([x]))[0] for x in op])

T = 400
OP = 50.0 + 8.0 * np.sin(np.linspace(0.0, 6 * np.pi, T))
CTX = ChainContext(dt=1.0, op=OP, op_span=16.0, tau_plant=10.0, delay=5.0)

VOCABULARY = {
    "stiction": ("valve", {"S", "J"}),
    "deadband": ("valve", {"S"}),
    "dead_time": ("delay", {"theta"}),
    "characteristic": ("characteristic", {"type", "R"}),
    "actuator_lag": ("actuator", {"tau"}),
}


def test_registry_holds_every_physics_with_its_json_parameter_keys():
    lib = registry()
    assert set(VOCABULARY) <= set(lib)
    for name, (slot, keys) in VOCABULARY.items():
        cand = lib[name]
        assert cand.slot == slot and slot in SLOTS
        grid = cand.grid(CTX)
        assert grid.ndim == 2 and grid.shape[1] == len(cand.param_names) and grid.shape[0] >= 1
        assert set(cand.parameters(grid[0])) == keys
        fine = cand.refine(CTX, grid[0])
        np.testing.assert_array_equal(fine[0], grid[0])  # a refinement contains its centre


def test_unknown_candidate_names_the_known_ones():
    with pytest.raises(ValueError, match="unknown candidate physics 'friction'.*stiction"):
        get("friction")


def test_a_new_candidate_slots_in_by_registration():
    class Offset(Candidate):  # a toy: adds a constant to OP
        name: ClassVar[str] = "toy_offset"
        slot: ClassVar[str] = "actuator"
        param_names: ClassVar[tuple[str, ...]] = ("c",)
        n_params: ClassVar[int] = 1

        def grid(self, ctx):
            return np.array([[0.0], [1.0]])

        def refine(self, ctx, best):
            return best[None, :]

        def apply(self, x, params, ctx):
            x = np.asarray(x, dtype=float)
            return (x[:, None] if x.ndim == 1 else x) + params[:, 0]

        def parameters(self, p):
            return {"c": float(p[0])}

        def describe(self, p, nominal=None, units=" %", edges=None):
            return f"an offset {p[0]}"

    try:
        register(Offset())
        assert get("toy_offset").apply(OP, np.array([[2.0]]), CTX)[:, 0] == pytest.approx(OP + 2.0)
        with pytest.raises(ValueError, match="slot must be one of"):
            bad = Offset()
            bad.slot = "nowhere"
            register(bad)
    finally:
        from valve_emulator.diagnosis.candidates import base
        base._REGISTRY.pop("toy_offset", None)
    assert "toy_offset" not in registry()


def test_pre_rolled_valve_breaks_free_where_a_valve_stuck_at_op0_never_does():
    # OP swings 3.6 % peak to peak around its start; with S = J = 3 a valve at rest at OP(0) never moves
    # (it needs 3 % either way), while a valve that has lived through such swings cycles with them.
    op = 50.0 + 1.8 * np.sin(np.linspace(0.0, 12 * np.pi, 1200))
    assert np.ptp(simulate(op, S=3.0, J=3.0)) == 0.0
    mv = valve_output(op, np.full(3, 3.0), np.full(3, 3.0), np.array(STARTS), CTX)
    assert np.ptp(mv[:, 0]) > 3.0
    # starting to move up at OP(0) also cycles and agrees with the pre-rolled valve after the first swing;
    # starting to move down does not (OP rises at once, the valve sticks mid-swing for good): no single
    # start is safe, hence three of them on every grid
    assert np.allclose(mv[200:, 0], mv[200:, 1])
    assert np.ptp(mv[:, 2]) == 0.0


def test_burn_in_is_when_different_starts_merge():
    mv = np.zeros((1000, 6))
    mv[:100, 1] = 1.0     # group 1 agrees from sample 100 on
    mv[:300, 5] = 1.0     # group 2 from sample 300 on
    assert sync_burn_in(mv) == int(np.percentile([100, 300], 90))
    mv[-1, 4] = 1.0       # a group that never agrees does not count
    assert sync_burn_in(mv) == 100
    assert sync_burn_in(mv[:, :4], n_starts=2) == int(np.percentile([100, 0], 90))
    assert get("stiction").burn_in(CTX) >= 0


@pytest.mark.parametrize("model", ["kano", "choudhury", "he"])
def test_the_burn_in_replayed_until_the_starts_merge_is_the_one_read_from_the_whole_record(model):
    # valve_burn_in drops a group once its valves' states agree to the bit; what it returns must be what the
    # whole record's MV gives, over several of its segments, for groups that merge early, late or never.
    rng = np.random.default_rng(3)
    op = 50.0 + 6.0 * np.sin(np.arange(5000) / 40.0) + np.cumsum(rng.normal(size=5000)) * 0.05
    ctx = ChainContext(dt=1.0, op=op, op_span=float(np.ptp(op)), valve_model=model)
    grid = get("stiction").grid(ctx)
    S, J, start = grid[:, 0], grid[:, 1], grid[:, 2]
    assert valve_burn_in(op, S, J, start, ctx) == sync_burn_in(valve_output(op, S, J, start, ctx))
    # a "group" whose valves differ in S is never taken for merged
    S2 = S.copy()
    S2[1::3] *= 1.0001
    assert valve_burn_in(op, S2, J, start, ctx) == sync_burn_in(valve_output(op, S2, J, start, ctx))
    assert get("stiction").burn_in(ctx) == sync_burn_in(get("stiction").apply(op, grid, ctx))


@pytest.mark.parametrize("model", ["kano", "choudhury", "he"])
def test_moving_starts_are_the_physics_valve_started_just_below_its_jump(model):
    rng = np.random.default_rng(0)
    op = 50.0 + np.cumsum(rng.normal(size=600)) * 0.3
    ctx = ChainContext(dt=1.0, op=op, op_span=10.0, valve_model=model)
    for start in (1.0, -1.0):
        mv = valve_output(op, [4.0], [1.5], [start], ctx)[:, 0]
        ref = simulate(op, S=4.0, J=1.5, model=model, direction=start, op0=op[0] - start * (1.5 + 1e-6))
        np.testing.assert_array_equal(mv, ref)


def test_stiction_candidate_is_the_physics_model_and_deadband_is_j_zero():
    st, db = get("stiction"), get("deadband")
    mv = st.apply(OP, np.array([[4.0, 1.5, 1.0]]), CTX)[:, 0]
    # the physics model, started at rest as if it had moved up, synchronises at the first reversal
    ref = simulate(OP, S=4.0, J=1.5)
    assert np.allclose(mv[T // 3:], ref[T // 3:])
    np.testing.assert_allclose(db.apply(OP, np.array([[4.0, 1.0]]), CTX),
                               st.apply(OP, np.array([[4.0, 0.0, 1.0]]), CTX))
    assert stiction_kind(5, 2) == "undershoot" and stiction_kind(5, 5.2) == "no offset"
    assert stiction_kind(5, 7) == "overshoot"


def test_stiction_scan_is_fine_in_s_and_the_line_is_finer_still():
    st = get("stiction")
    coarse, scan = st.grid(CTX), st.scan(CTX)
    ds = lambda g: np.min(np.diff(np.unique(g[:, 0])))  # noqa: E731
    assert ds(scan) < ds(coarse) / 5
    line = st.line(CTX, np.array([5.0, 2.0, 1.0]), 0)
    assert ds(line) < ds(scan) / 10 and np.all(line[:, 1] == 2.0)


def test_actuator_lag_follows_the_exact_zoh_state_and_vanishes_at_zero():
    step = np.concatenate([np.zeros(5), np.ones(60)])
    tau = 4.0
    out = first_order_lag(step, np.array([tau, 0.0]), 1.0)
    a = np.exp(-1.0 / tau)
    state = 1.0 - a ** np.arange(0, 60)          # exact ZOH lag state after k samples of the step
    w = 1.0 - tau * (1.0 - a)                      # weight of the sample average toward the input
    np.testing.assert_allclose(out[5:, 0], state + (1.0 - state) * w, rtol=1e-12)
    np.testing.assert_array_equal(out[:, 1], step)
    # the sample average of the continuous lag response is what the ZOH plant integrates
    tt = np.linspace(0.0, 1.0, 10001)
    k = 7
    cont = 1.0 - np.exp(-(k + tt) / tau)
    assert out[5 + k, 0] == pytest.approx(np.trapezoid(cont, tt), rel=1e-6)


def test_characteristic_candidate_is_the_physics_characteristic():
    ch = get("characteristic")
    grid = ch.grid(CTX)
    kinds = {ch.parameters(g)["type"] for g in grid}
    assert kinds == {"equal_percentage", "quick_opening"}  # the nominal (linear) is not a candidate
    rows = np.array([[1.0, 30.0], [2.0, 0.0]])
    out = ch.apply(OP, rows, CTX)
    np.testing.assert_allclose(out[:, 0], Characteristic("equal_percentage", 30.0).flow(OP))
    np.testing.assert_allclose(out[:, 1], Characteristic("quick_opening").flow(OP))
    assert ch.parameters(rows[1]) == {"type": "quick_opening", "R": None}


def test_chain_applies_slots_in_signal_order_with_the_grid_in_between():
    lag = Active(get("actuator_lag"), np.array([3.0]))
    grid = np.array([[4.0, 1.5, 1.0], [2.0, 0.0, -1.0]])
    flows = run_chain(OP, {"actuator": lag}, CTX, grid_candidate=get("stiction"), grid=grid)
    lagged = first_order_lag(OP, np.array([3.0]), 1.0)[:, 0]
    expect = valve_output(lagged, grid[:, 0], grid[:, 1], grid[:, 2], CTX)
    np.testing.assert_allclose(flows, np.clip(expect, 0, 100))
    nominal_valve = run_chain(OP, {}, CTX, nominal_valve=(4.0, 1.5))[:, 0]
    np.testing.assert_allclose(nominal_valve, valve_output(OP, [4.0], [1.5], [PRE_ROLL], CTX)[:, 0])


@pytest.mark.parametrize("model", ["kano", "choudhury", "he"])
@pytest.mark.parametrize("n", [5, 48, 200])
@pytest.mark.parametrize("shared_op", [True, False])
def test_a_grid_of_valves_replays_each_valve_as_it_would_alone(model, n, shared_op):
    # A grid is replayed together (branch-free vector code from 24 valves of a thread's share on: 48 valves are
    # two shares of 24 or one of 48, the pre-roll valves first, then all in column order); each column must be bit
    # for bit the valve replayed on its own, which takes the branches.
    rng = np.random.default_rng(5)
    ctx = ChainContext(dt=1.0, op=OP, op_span=16.0, valve_model=model, rest_samples=2)
    S, J = rng.uniform(0.5, 8.0, n), rng.uniform(0.0, 6.0, n)
    start = rng.choice(np.array(STARTS), n)
    noisy = OP + rng.normal(0.0, 0.3, OP.size)   # reversals at random: both ways through every branch
    op = noisy if shared_op else noisy[:, None] + rng.normal(0.0, 0.5, (OP.size, n))
    together = valve_output(op, S, J, start, ctx)
    for i in range(n):
        alone = valve_output(op if shared_op else op[:, i], S[i:i + 1], J[i:i + 1], start[i:i + 1], ctx)
        assert np.array_equal(together[:, i], alone[:, 0]), i


def _bank_by_broadcast(x, S, J, start, ctx):
    """The valve bank as written before a grid's columns were copied as they are: every parameter broadcast to the
    bank's size and made contiguous and writable, OP likewise (the straightforward set-up)."""
    x2 = np.array(np.asarray(x, dtype=float)[:, None] if np.ndim(x) == 1 else x, dtype=float)
    S, J, start = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (S, J, start))
    n = max(S.size, J.size, start.size, x2.shape[1])
    S, J, start = (np.array(np.broadcast_to(a, (n,))) for a in (S, J, start))
    K = valve_start._pre_roll(x2.shape[0])
    pre = start == PRE_ROLL
    d = np.where(pre, 1.0, start)
    cols = np.zeros(n, dtype=np.int64) if x2.shape[1] == 1 else np.arange(n)
    first = np.where(pre, x2[K, cols], x2[0, cols])
    codes = np.full(n, valve_start.MODELS.index(ctx.valve_model), dtype=np.int64)
    state = np.zeros((n, valve_start.NSTATE))
    valve_start.initial_state(state, np.clip(first - d * (J + valve_start._EPS), 0.0, 100.0), d, S, J, codes)
    return x2, K, pre, S, J, np.full(n, float(ctx.rest_samples)), codes, state


@pytest.mark.parametrize("form", ["grid-columns", "scalars", "one-of-each", "per-valve-op"])
def test_a_valve_bank_is_the_one_every_parameter_broadcast_makes(form):
    """valve_start._bank copies a grid's columns as they are: the same arrays, to the bit, as broadcasting every
    parameter to the bank's size; each contiguous and writable (the kernels' one compiled signature)."""
    rng = np.random.default_rng(8)
    n = 30
    grid = np.column_stack([rng.uniform(0.5, 8.0, n), rng.uniform(0.0, 6.0, n), rng.choice(np.array(STARTS), n)])
    op = OP.copy()
    op.flags.writeable = False                          # a recording's OP is read-only
    S, J, start, x = grid[:, 0], grid[:, 1], grid[:, 2], op   # columns of a grid: strided views
    if form == "scalars":
        S, J, start = 4.0, 1.5, PRE_ROLL
    elif form == "one-of-each":
        S, J, start = np.array([4.0]), grid[:, 1], np.array(-1.0)
    elif form == "per-valve-op":
        x = op[:, None] + rng.normal(0.0, 0.5, (op.size, n))
    ctx = ChainContext(dt=1.0, op=OP, op_span=16.0, valve_model="choudhury", rest_samples=3)
    bank = valve_start._bank(x, S, J, start, ctx)
    want = _bank_by_broadcast(x, S, J, start, ctx)
    got = (bank.x, bank.K, bank.pre, bank.S, bank.J, bank.R, bank.codes, bank.state)
    assert got[1] == want[1]
    for a, b in zip(got[:1] + got[2:], want[:1] + want[2:]):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8))
    for a in (bank.x, bank.S, bank.J):
        assert a.flags.c_contiguous and a.flags.writeable
    assert not np.shares_memory(bank.S, grid) and not np.shares_memory(bank.x, op)


@pytest.mark.parametrize("model", ["kano", "choudhury", "he"])
@pytest.mark.parametrize("groups", [4, 40])
def test_valves_of_equal_parameters_that_catch_up_replay_each_valve_as_it_would_alone(model, groups):
    # A grid's rows that differ only in the start are replayed together and a valve whose state has caught up
    # with its group's first stops stepping (its column copied from there on): every column must still be bit
    # for bit the valve replayed on its own. Groups that merge at once (a start repeated), early, late and never,
    # over several of the checks' segments; 4 groups (12 valves: the branches) and 40 (120: the vector loop,
    # which keeps at least valve_start._KEEP_STEPPING valves going).
    rng = np.random.default_rng(11)
    n_op = 3000
    op = 50.0 + 5.0 * np.sin(np.arange(n_op) / 37.0) + np.cumsum(rng.normal(size=n_op)) * 0.04
    op[n_op // 2:] += 3.0 * np.sin(np.arange(n_op - n_op // 2) / 9.0)   # reversals late in the record as well
    ctx = ChainContext(dt=1.0, op=op, op_span=float(np.ptp(op)), valve_model=model, rest_samples=2)
    S, J = rng.uniform(0.3, 9.0, groups), rng.uniform(0.0, 6.0, groups)
    rows = [(S[g], J[g], start) for g in range(groups) for start in (*STARTS, STARTS[g % 3])]
    order = rng.permutation(len(rows))                     # the members of a group need not be side by side
    S_rows, J_rows, start = (np.array([rows[i][c] for i in order]) for c in range(3))
    together = valve_output(op, S_rows, J_rows, start, ctx)
    for i in range(len(rows)):
        alone = valve_output(op, S_rows[i:i + 1], J_rows[i:i + 1], start[i:i + 1], ctx)
        assert np.array_equal(together[:, i], alone[:, 0]), i
    # and the valves that caught up did stop stepping
    bank = valve_start._bank(op, S_rows, J_rows, start, ctx)
    m = S_rows.size
    keep = 0 if m < 24 else valve_start._KEEP_STEPPING
    stepped = valve_start._run_merging(bank.x, bank.K, n_op, np.arange(m), bank.S, bank.J, bank.R, bank.codes,
                                       valve_start._pre_rolled(bank, np.arange(m)), np.empty((n_op, m)),
                                       valve_start._leaders(bank.S, bank.J), keep)
    assert stepped < m * n_op


def test_importing_the_package_registers_every_candidate_its_modules_define():
    """No list of modules is kept by hand: in a fresh interpreter, importing the package alone fills the library
    with each candidate class that a module of the package defines."""
    import importlib
    import inspect
    import pkgutil
    import subprocess
    import sys

    from valve_emulator.diagnosis import candidates

    fresh = subprocess.run([sys.executable, "-c", "from valve_emulator.diagnosis.candidates import registry; "
                            "print(' '.join(registry()))"], capture_output=True, text=True, check=True)
    defined = set()
    for info in pkgutil.iter_modules(candidates.__path__):
        module = importlib.import_module(f"{candidates.__name__}.{info.name}")
        defined |= {cls.name for _, cls in inspect.getmembers(module, inspect.isclass)
                    if issubclass(cls, Candidate) and not inspect.isabstract(cls) and cls.__module__ == module.__name__}
    assert len(defined) >= 9 and set(fresh.stdout.split()) == defined


def _toy(slot: str, params: tuple[str, ...], role, name: str = "toy_declared"):
    class Toy(Candidate):
        def grid(self, ctx):
            return np.zeros((1, len(params)))

        def refine(self, ctx, best):
            return best[None, :]

        def apply(self, x, p, ctx):
            return x

        def parameters(self, p):
            return {}

        def describe(self, p, nominal=None, units=" %", edges=None):
            return "a toy"

    Toy.name, Toy.slot, Toy.param_names, Toy.n_params, Toy.twin_role = name, slot, params, len(params), role
    return Toy()


@pytest.mark.parametrize("slot, params, role, name, message", [
    ("actuator", ("S",), TwinRole.VALVE_BAND, "toy_declared", "twin role VALVE_BAND needs slot 'valve'"),
    ("valve", ("band",), TwinRole.VALVE_BAND, "toy_declared", "the parameters S"),
    ("limit", ("lo",), TwinRole.FLOW_LIMITS, "toy_declared", "the parameters lo, hi"),
    ("valve", ("S",), None, "Toy Band", "lower-case identifier"),
])
def test_registration_refuses_a_declaration_the_package_could_not_act_on(slot, params, role, name, message):
    with pytest.raises(ValueError, match=message):
        register(_toy(slot, params, role, name))
    assert name not in registry()


def test_registration_refuses_a_describe_that_cannot_be_handed_the_search_edges():
    toy = _toy("valve", ("S",), None, "toy_old_describe")
    type(toy).describe = lambda self, p, nominal=None, units=" %": "a toy"
    with pytest.raises(ValueError, match="must take edges"):
        register(toy)
    assert "toy_old_describe" not in registry()
