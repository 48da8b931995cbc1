"""Data-driven valve stiction: three published state machines sharing the parameters (S, J).

All quantities are in % of valve travel and follow the 2005 convention of Choudhury, Thornhill & Shah
("Modelling valve stiction", Control Engineering Practice 13 (2005) 641-658):

* ``S`` -- deadband plus stickband, measured on the input (OP) axis;
* ``J`` -- slip jump, measured on the output (MV, valve position) axis.

While the valve moves in direction ``d`` (+1 opening, -1 closing) its position lags the input by a constant
offset, ``MV = OP - d*(S - J)/2``: ``J = 0`` is a pure deadband, ``0 < J < S`` undershoot, ``J = S`` no offset
and ``J > S`` overshoot. The 2003 paper (Choudhury, Thornhill & Shah, ADCHEM 2003) prints a slip jump ``j``
that is half of this ``J``; :func:`seed_to_2005` converts.

Models
------
``"choudhury"``
    The 2005 flow chart, literally. Known to freeze on held (zero-order-hold) or noisy input and to need only
    J, not S, to restart in the opposite direction after a stop; kept for comparison with the paper.
``"kano"`` (default)
    Kano, Maruta, Kugemoto & Shimizu, "Practical model and detection algorithm for valve stiction",
    IFAC DYCOPS 2004. The same cycles as ``"choudhury"`` on clean input, but the stuck reference ``us`` only
    changes while the valve moves, so held or noisy input does not reset it. This is why it is the default.
    One addition of ours, ``rest_samples``: the valve counts as come to rest only after OP has stayed
    unchanged for that many consecutive samples (the literal model is ``rest_samples = 1``); a reversal of OP
    stops it at once whatever the setting. See :func:`rest_samples_for`.
``"he"``
    He, Wang, Pottmann & Qin, "A curve fitting method for detecting valve stiction in oscillating control
    loops", Ind. Eng. Chem. Res. 46 (2007). A residual force with static band ``fs = (S + J)/2`` and kinetic
    band ``fd = (S - J)/2``. For J > 0 it re-sticks during slow one-directional motion, so its cycles depend
    on the sample time.

Initial state (no paper fixes it; ours is deliberate): the valve is at rest at ``OP(0)`` *as if it had just
stopped after moving in direction* ``direction`` (default +1). So ``MV(0) = OP(0) - direction*(S - J)/2``, a
further move in the same direction needs J of input, a reversal needs S.

Saturation: OP is clipped to [0, 100] before the model, and MV to [0, 100] after it (the travel stops). The
literal ``"choudhury"`` chart additionally puts MV at 0/100 whenever OP is outside [0, 100].

Implementation: every model keeps its state in one ``(n, NSTATE)`` float array, one row per valve, and one
numba kernel, :func:`stiction_step_kernel` ``(u, S, J, R, codes, state)``, advances ``n`` valves (of any mix
of models, ``codes`` indexing :data:`MODELS`) one sample in place. It serves the loop kernel of
:mod:`valve_emulator.simulation.loop` and small groups of the diagnosis' candidate valves.

:class:`StictionBank` (and through it :func:`simulate`, :func:`simulate_many` and the emulator's tick) holds
valves of one model, and from :data:`VECTOR_MIN` valves on steps them with a second formulation of the same
state machines (:func:`step_same_model`). With a random OP the branches of a state machine go one way or the
other at random, and a mispredicted branch costs more than the whole update of a valve; so there each update
computes both outcomes and selects one, which LLVM compiles to blends, and the bank keeps its state
column-major (``order="F"``), each column contiguous, so that the loop over valves becomes vector code. The
selects keep exactly the floating-point expressions of the branches, in the same order and without
``fastmath`` (which would allow reassociation and fused multiply-adds), so both formulations give the same
state bit for bit; ``tests/physics/test_stiction_bank_kernel.py`` holds them to it. A few valves, and one
valve over a long array (:func:`simulate`), keep the branches: they do not fill a vector, and on a smooth OP
the branches are well predicted. The diagnosis steps its grids of candidate valves (hundreds of one model on
one OP) with the same selects on column-major state, :func:`kano_update` and its siblings written out in its own
compiled time loop (a call per sample to :func:`step_same_model` costs more than a few dozen valves' work there:
numba updates the reference counts of a call's array arguments); :func:`stiction_step_kernel` keeps the
branches for the loop kernel, whose state is row-major, where the loop does not vectorise and the selects
alone are slower than the branches.
"""

from __future__ import annotations

from typing import Final

import numba
import numpy as np
from numpy.typing import ArrayLike

from valve_emulator.physics._arrays import vector

__all__ = [
    "MODELS",
    "DEFAULT_MODEL",
    "StictionBank",
    "Valve",
    "simulate",
    "simulate_many",
    "seed_to_2005",
    "rest_samples_for",
    "validate_parameters",
    "stiction_step_kernel",
    "step_same_model",
    "VECTOR_MIN",
    "initial_state",
    "NSTATE",
    "KANO",
    "CHOUDHURY",
    "HE",
    "kano_update",
    "choudhury_update",
    "he_update",
]

MODELS: Final = ("choudhury", "kano", "he")
DEFAULT_MODEL: Final = "kano"

# Columns of the state array (one row per valve).
MV, U_PREV, REF, DIR, FLAG, STILL, STUCK = range(7)
NSTATE: Final = 7
# REF:  kano -> stuck input us;  choudhury -> xss;  he -> residual ur
# DIR:  kano -> friction direction d (+-1);  choudhury -> sign of the previous slope (-1, 0, +1)
# FLAG: kano -> stp (1 stopped);  choudhury -> I (1 after a stop with zero slope)
# STILL: kano -> samples since OP last changed (the rest criterion);  STUCK: 1 when MV is held this sample


@numba.njit(cache=True, inline="always")
def _clip(x: float) -> float:
    return min(max(x, 0.0), 100.0)


@numba.njit(cache=True, inline="always")
def _kano_valve(i, u_raw, S, J, R, st):  # pragma: no cover - compiled
    u = _clip(u_raw)
    du = u - st[i, U_PREV]
    if du == 0.0:
        st[i, STILL] += 1.0
    else:
        st[i, STILL] = 0.0
    half = 0.5 * (S - J)
    # Moving: it stops on a reversal of OP, or when OP has been still for R samples.
    if st[i, FLAG] == 0.0 and (du * st[i, DIR] < 0.0 or st[i, STILL] >= R):
        st[i, REF] = st[i, U_PREV]
        st[i, FLAG] = 1.0
    if st[i, FLAG] == 0.0:
        st[i, MV] = _clip(u - st[i, DIR] * half)
        st[i, STUCK] = 0.0
    else:
        d = st[i, DIR]
        if -d * (u - st[i, REF]) > S:  # reversal that overcomes deadband + stickband
            d = -d
            st[i, DIR] = d
            st[i, MV] = _clip(u - d * half)
            st[i, FLAG] = 0.0
            st[i, STUCK] = 0.0
        elif d * (u - st[i, REF]) > J:  # same direction again: only the slip jump to overcome
            st[i, MV] = _clip(u - d * half)
            st[i, FLAG] = 0.0
            st[i, STUCK] = 0.0
        else:
            st[i, STUCK] = 1.0
    st[i, U_PREV] = u


@numba.njit(cache=True, inline="always")
def _choudhury_valve(i, x, S, J, R, st):  # pragma: no cover - compiled
    if x < 0.0 or x > 100.0:  # saturated: the valve sits on its stop
        x = _clip(x)
        st[i, MV] = x
        st[i, REF] = x
        st[i, DIR] = np.sign(x - st[i, U_PREV])
        st[i, STUCK] = 0.0
        st[i, U_PREV] = x
        return
    v = x - st[i, U_PREV]
    sv = np.sign(v)
    if sv != st[i, DIR]:  # the slope changed sign, or became zero: the valve sticks
        st[i, REF] = st[i, U_PREV]
        if v == 0.0:
            st[i, FLAG] = 1.0
        st[i, STUCK] = 1.0
    else:
        band = J if st[i, FLAG] == 1.0 else S
        if abs(x - st[i, REF]) > band:
            st[i, FLAG] = 0.0
            st[i, MV] = _clip(x - sv * 0.5 * (S - J))
            st[i, STUCK] = 0.0
        else:
            st[i, STUCK] = 1.0
    st[i, DIR] = sv
    st[i, U_PREV] = x


@numba.njit(cache=True, inline="always")
def _he_valve(i, u_raw, S, J, R, st):  # pragma: no cover - compiled
    u = _clip(u_raw)
    fs = 0.5 * (S + J)
    fd = 0.5 * (S - J)
    tmp = st[i, REF] + (u - st[i, U_PREV])
    if abs(tmp) > fs:
        st[i, REF] = np.sign(tmp) * fd
        st[i, MV] = _clip(u - st[i, REF])
        st[i, STUCK] = 0.0
    else:
        st[i, REF] = tmp  # MV = u - ur is unchanged in exact arithmetic: hold it exactly
        st[i, STUCK] = 1.0
    st[i, U_PREV] = u


@numba.njit(cache=True, inline="always")
def _valve(i, u, S, J, R, code, st):  # pragma: no cover - compiled
    if code == 1:
        _kano_valve(i, u, S, J, R, st)
    elif code == 0:
        _choudhury_valve(i, u, S, J, R, st)
    else:
        _he_valve(i, u, S, J, R, st)


@numba.njit(cache=True)
def _run(op, S, J, R, codes, st, out):  # pragma: no cover - compiled
    for k in range(op.shape[0]):
        for i in range(st.shape[0]):
            _valve(i, op[k, i], S[i], J[i], R[i], codes[i], st)
            out[k, i] = st[i, MV]


@numba.njit(cache=True)
def stiction_step_kernel(u, S, J, R, codes, st):  # pragma: no cover - compiled
    """Advance valves of mixed models one sample: ``codes[i]`` indexes :data:`MODELS`."""
    for i in range(u.shape[0]):
        _valve(i, u[i], S[i], J[i], R[i], codes[i], st)


# --- One model for every valve: the same state machines as selects (see the module docstring) -------------
# Each ``*_update`` takes and returns the state as scalars: an array handed to an inlined function inside the
# loop leaves reference-counting calls in the loop, and LLVM does not vectorise a loop that calls. Every
# ``a if c else b`` below has two operands without side effects, both computed, so that LLVM can make it a
# select (a blend in the vector loop) rather than a branch; conditions combine with ``&`` and ``|``, which do
# not short-circuit, for the same reason.

#: A bank of fewer valves takes the branching per-valve loop. LLVM checks at run time that the arrays do not
#: overlap and enters the vector loop only above a trip count that pays for those checks (about 40 valves with
#: AVX-512); below it the selects run one valve at a time, slower than branches, which on a smooth OP are
#: well predicted. At 64 valves the selects beat the branches on smooth and on random OP for every model.
VECTOR_MIN: Final = 64
CHOUDHURY, KANO, HE = (MODELS.index(m) for m in ("choudhury", "kano", "he"))


@numba.njit(cache=True, inline="always")
def kano_update(u_raw, S, J, R, mv, u_prev, ref, d, flag, still):  # pragma: no cover - compiled
    """:func:`_kano_valve` as selects; returns the new ``(MV, U_PREV, REF, DIR, FLAG, STILL, STUCK)``."""
    u = _clip(u_raw)
    du = u - u_prev
    still = still + 1.0 if du == 0.0 else 0.0
    half = 0.5 * (S - J)
    stop = (flag == 0.0) & ((du * d < 0.0) | (still >= R))     # moving, and a reversal or R still samples
    ref = u_prev if stop else ref
    stopped = stop | (flag != 0.0)
    rev = stopped & (-d * (u - ref) > S)                        # overcomes deadband + stickband backwards
    jump = rev | (stopped & (d * (u - ref) > J))                # ... or the slip jump forwards: it moves
    held = stopped & (not jump)
    d = -d if rev else d
    mv = mv if held else _clip(u - d * half)
    flag = 0.0 if jump else (1.0 if stop else flag)
    return mv, u, ref, d, flag, still, 1.0 if held else 0.0


@numba.njit(cache=True, inline="always")
def choudhury_update(x, S, J, mv, u_prev, ref, slope, flag):  # pragma: no cover - compiled
    """:func:`_choudhury_valve` as selects; returns the new ``(MV, U_PREV, REF, DIR, FLAG, STUCK)``."""
    sat = (x < 0.0) | (x > 100.0)                               # saturated: the valve sits on its stop
    x = _clip(x) if sat else x
    v = x - u_prev
    sv = np.sign(v)
    turn = (not sat) & (sv != slope)                            # the slope changed sign or became zero: sticks
    band = J if flag == 1.0 else S
    go = (not sat) & (not turn) & (abs(x - ref) > band)
    mv = x if sat else (_clip(x - sv * 0.5 * (S - J)) if go else mv)
    ref = x if sat else (u_prev if turn else ref)
    flag = 1.0 if turn & (v == 0.0) else (0.0 if go else flag)
    return mv, x, ref, sv, flag, 0.0 if sat | go else 1.0


@numba.njit(cache=True, inline="always")
def he_update(u_raw, S, J, mv, u_prev, ref):  # pragma: no cover - compiled
    """:func:`_he_valve` as selects; returns the new ``(MV, U_PREV, REF, STUCK)``."""
    u = _clip(u_raw)
    fs = 0.5 * (S + J)
    fd = 0.5 * (S - J)
    tmp = ref + (u - u_prev)
    slip = abs(tmp) > fs
    ref = np.sign(tmp) * fd if slip else tmp
    mv = _clip(u - ref) if slip else mv
    return mv, u, ref, 0.0 if slip else 1.0


@numba.njit(cache=True)
def _kano_columns(u, S, J, R, st):  # pragma: no cover - compiled
    for i in range(u.shape[0]):
        st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR], st[i, FLAG], st[i, STILL], st[i, STUCK] = \
            kano_update(u[i], S[i], J[i], R[i], st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR], st[i, FLAG],
                        st[i, STILL])


@numba.njit(cache=True)
def _choudhury_columns(u, S, J, st):  # pragma: no cover - compiled
    for i in range(u.shape[0]):
        st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR], st[i, FLAG], st[i, STUCK] = \
            choudhury_update(u[i], S[i], J[i], st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR], st[i, FLAG])


@numba.njit(cache=True)
def _he_columns(u, S, J, st):  # pragma: no cover - compiled
    for i in range(u.shape[0]):
        st[i, MV], st[i, U_PREV], st[i, REF], st[i, STUCK] = \
            he_update(u[i], S[i], J[i], st[i, MV], st[i, U_PREV], st[i, REF])


@numba.njit(cache=True)
def step_same_model(u, S, J, R, code, st):  # pragma: no cover - compiled
    """Advance valves that all use model ``code`` one sample: the same state as :func:`stiction_step_kernel`."""
    if code == KANO:
        _kano_columns(u, S, J, R, st)
    elif code == CHOUDHURY:
        _choudhury_columns(u, S, J, st)
    else:
        _he_columns(u, S, J, st)


@numba.njit(cache=True)
def _run_same_model(op, S, J, R, code, st, out):  # pragma: no cover - compiled
    for k in range(op.shape[0]):
        step_same_model(op[k], S, J, R, code, st)   # run() checked that op has one column per valve
        for i in range(st.shape[0]):
            out[k, i] = st[i, MV]


def seed_to_2005(s: float, j: float) -> tuple[float, float]:
    """Convert the 2003 paper's ``(s, j)`` to the 2005 convention ``(S, J)``.

    The 2003 paper (ADCHEM 2003) states that there is no offset at ``j = s/2``, undershoot below and overshoot above.
    With ``MV = OP - d*(S - J)/2`` no offset means ``J = S``; hence ``S = s`` and ``J = 2*j``.
    """
    return float(s), 2.0 * float(j)


def rest_samples_for(rest_time: float, dt: float) -> int:
    """Samples of unchanged OP after which a valve counts as at rest: ``max(1, ceil(rest_time/dt))``.

    A real valve comes to rest when its input stops changing. A controller that writes every 100 ms to an
    emulator that ticks every 10 ms leaves OP unchanged for nine ticks out of ten; with the literal model
    (one sample) each of those pauses would stop the valve and make it overcome J again, turning smooth
    motion into stick-slip that depends on the tick. Choose ``rest_time`` longer than the writer's period.
    """
    if not np.isfinite(rest_time) or rest_time < 0:
        raise ValueError(f"rest_time must be a finite number >= 0, got {rest_time!r}")
    if not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt must be > 0, got {dt!r}")
    return max(1, int(np.ceil(rest_time / dt - 1e-9)))


def validate_parameters(S: ArrayLike, J: ArrayLike, model: str, rest_samples: ArrayLike = 1) -> None:
    """Raise ValueError naming the offending parameter."""
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}; got {model!r}")
    for name, value in (("S", S), ("J", J)):
        arr = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite, got {value!r}")
        if np.any(arr < 0):
            raise ValueError(f"{name} must be >= 0 (% of valve travel), got {value!r}")
    r = np.asarray(rest_samples)
    if not np.issubdtype(r.dtype, np.integer) or np.any(r < 1):
        raise ValueError(f"rest_samples must be an integer >= 1, got {rest_samples!r}")


def _check_op(op: np.ndarray) -> None:
    bad = ~np.isfinite(op)
    if bad.any():
        k = np.argwhere(bad)[0]
        where = ", ".join(str(int(i)) for i in k)
        raise ValueError(f"op[{where}] is {op[tuple(k)]!r}; OP must be finite (% of valve travel)")


def initial_state(state: np.ndarray, op0: np.ndarray, direction: np.ndarray, S: np.ndarray, J: np.ndarray,
                  codes: np.ndarray) -> None:
    """Fill ``state`` (n, NSTATE): valves at rest at ``op0`` as if just stopped after moving in ``direction``.

    ``codes[i]`` indexes :data:`MODELS`. See the module docstring for why this initial state.
    """
    d = np.asarray(direction, dtype=float)
    if not np.all(np.abs(d) == 1):
        raise ValueError(f"direction must be +1 or -1, got {direction!r}")
    u0 = np.clip(np.asarray(op0, dtype=float), 0.0, 100.0)
    half = 0.5 * (S - J)
    kano, choudhury = codes == MODELS.index("kano"), codes == MODELS.index("choudhury")
    state[:, MV] = np.clip(u0 - d * half, 0.0, 100.0)
    state[:, U_PREV] = u0
    state[:, STILL] = 0.0
    state[:, STUCK] = 1.0
    state[:, REF] = np.where(kano | choudhury, u0, d * half)        # us / xss / residual ur
    state[:, DIR] = np.where(kano, d, 0.0)                          # d / previous slope sign / unused
    state[:, FLAG] = np.where(kano | choudhury, 1.0, 0.0)           # stopped / I flag / unused


class StictionBank:
    """``n`` sticky valves stepped together, one sample per :meth:`step`.

    Parameters
    ----------
    n : number of valves.
    S, J : deadband+stickband and slip jump, % travel, scalars or arrays of length ``n``.
    model : ``"kano"`` (default), ``"choudhury"`` or ``"he"``.
    rest_samples : rest criterion of the ``"kano"`` model (samples of unchanged OP), scalar or per valve.
    """

    def __init__(self, n: int, *, S: ArrayLike, J: ArrayLike, model: str = DEFAULT_MODEL,
                 rest_samples: ArrayLike = 1) -> None:
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n!r}")
        validate_parameters(S, J, model, np.asarray(rest_samples))
        self.n = int(n)
        self.model = model
        self._code = MODELS.index(model)
        self._codes = np.full(self.n, self._code, dtype=np.int64)
        self._S = vector("S", S, self.n)
        self._J = vector("J", J, self.n)
        self._R = vector("rest_samples", rest_samples, self.n, dtype=np.int64).astype(float)
        # Column-major for the vector loop (see the module docstring), which needs a few valves to pay off.
        self._selects = self.n >= VECTOR_MIN
        self._state = np.zeros((self.n, NSTATE), order="F" if self._selects else "C")
        self.reset(0.0)

    def reset(self, op0: ArrayLike, direction: ArrayLike = 1) -> None:
        """Put every valve at rest at ``op0`` as if it had just stopped moving in ``direction`` (+1/-1)."""
        initial_state(self._state, vector("op0", op0, self.n), vector("direction", direction, self.n),
                      self._S, self._J, self._codes)

    def step(self, op: ArrayLike) -> np.ndarray:
        """Advance every valve one sample with input ``op`` (% travel); return MV (a view, do not keep)."""
        u = np.asarray(op, dtype=float)
        if u.ndim == 0:
            u = np.full(self.n, float(u))
        elif u.shape != (self.n,):   # the compiled step does not check bounds: a longer op would write past the state
            raise ValueError(f"op must be a scalar or have shape ({self.n},), got shape {u.shape}")
        if self._selects:
            step_same_model(u, self._S, self._J, self._R, self._code, self._state)
        else:
            stiction_step_kernel(u, self._S, self._J, self._R, self._codes, self._state)
        return self._state[:, MV]

    def set_parameters(self, *, S: ArrayLike | None = None, J: ArrayLike | None = None,
                       index: int | slice | np.ndarray | None = None) -> None:
        """Change S and/or J (for all valves, or those at ``index``); takes effect at the next step."""
        newS = self._S.copy()
        newJ = self._J.copy()
        sel = slice(None) if index is None else index
        if S is not None:
            newS[sel] = S
        if J is not None:
            newJ[sel] = J
        validate_parameters(newS, newJ, self.model)
        self._S[:], self._J[:] = newS, newJ

    @property
    def S(self) -> np.ndarray:
        return self._S.copy()

    @property
    def J(self) -> np.ndarray:
        return self._J.copy()

    @property
    def mv(self) -> np.ndarray:
        """Valve position, % travel (read-only copy)."""
        return self._state[:, MV].copy()

    @property
    def stuck(self) -> np.ndarray:
        """True where the valve held its position at the last step."""
        return self._state[:, STUCK] == 1.0

    def run(self, op: np.ndarray) -> np.ndarray:
        """Step through ``op`` of shape ``(T, n)``; return MV of shape ``(T, n)``; state carries on."""
        op = np.ascontiguousarray(op, dtype=float)
        if op.ndim != 2 or op.shape[1] != self.n:
            raise ValueError(f"op must have shape (T, {self.n}), got shape {op.shape}")
        out = np.empty_like(op)
        if self._selects:
            _run_same_model(op, self._S, self._J, self._R, self._code, self._state, out)
        else:
            _run(op, self._S, self._J, self._R, self._codes, self._state, out)
        return out


class Valve:
    """One sticky valve for per-sample use (a bank of one): ``mv = valve.step(op)``."""

    def __init__(self, *, S: float, J: float, model: str = DEFAULT_MODEL, rest_samples: int = 1,
                 op0: float = 0.0, direction: int = 1) -> None:
        self._bank = StictionBank(1, S=S, J=J, model=model, rest_samples=rest_samples)
        self._bank.reset(op0, direction)
        self._u = np.zeros(1)

    def step(self, op: float) -> float:
        self._u[0] = op
        return float(self._bank.step(self._u)[0])

    @property
    def mv(self) -> float:
        return float(self._bank.mv[0])

    @property
    def stuck(self) -> bool:
        return bool(self._bank.stuck[0])


def simulate_many(op: ArrayLike, S: ArrayLike, J: ArrayLike, *, model: str = DEFAULT_MODEL,
                  rest_samples: ArrayLike = 1, direction: ArrayLike = 1,
                  op0: ArrayLike | None = None) -> np.ndarray:
    """MV of many valves, shape ``(T, n)``, for OP of shape ``(T,)`` (shared) or ``(T, n)``.

    ``S`` and ``J`` have shape ``(n,)`` (or are scalars with a 2-D ``op``); the valves start at rest at
    ``op0`` (default ``op[0]``) as described in the module docstring.
    """
    op = np.asarray(op, dtype=float)
    _check_op(op)
    S_arr, J_arr = np.atleast_1d(np.asarray(S, dtype=float)), np.atleast_1d(np.asarray(J, dtype=float))
    n = max(S_arr.shape[0], J_arr.shape[0], op.shape[1] if op.ndim == 2 else 1)
    if op.ndim == 1:
        op2 = np.ascontiguousarray(np.broadcast_to(op[:, None], (op.shape[0], n)))
    elif op.ndim == 2 and op.shape[1] == n:
        op2 = np.ascontiguousarray(op)
    else:
        raise ValueError(f"op must have shape (T,) or (T, {n}), got {op.shape}")
    bank = StictionBank(n, S=np.broadcast_to(S_arr, (n,)), J=np.broadcast_to(J_arr, (n,)), model=model,
                        rest_samples=np.broadcast_to(np.asarray(rest_samples), (n,)))
    if op2.shape[0] == 0:
        return np.empty((0, n))
    bank.reset(op2[0] if op0 is None else op0, direction)
    return bank.run(op2)


def simulate(op: ArrayLike, *, S: float, J: float, model: str = DEFAULT_MODEL, rest_samples: int = 1,
             direction: int = 1) -> np.ndarray:
    """Valve position MV (% travel) of one sticky valve driven by ``op`` (% travel), same length.

    Examples
    --------
    >>> import numpy as np
    >>> op = 50 + 10 * np.sin(np.linspace(0, 4 * np.pi, 2000))
    >>> mv = simulate(op, S=5.0, J=2.0)   # undershoot: MV lags OP by (S - J)/2 = 1.5 % while moving
    """
    op = np.asarray(op, dtype=float)
    if op.ndim != 1:
        raise ValueError(f"op must be one-dimensional, got shape {op.shape}")
    validate_parameters(S, J, model, np.asarray(rest_samples))
    return simulate_many(op, [S], [J], model=model, rest_samples=rest_samples, direction=direction)[:, 0]
