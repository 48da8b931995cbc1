r"""The unknown state of a sticky valve at the first sample of a recording, and when it stops mattering.

A recording starts mid-cycle. A model valve started in the wrong state can stay wrong for long:
with OP swinging only a little more than S — common, because the controller reverses as soon as the valve
moves — a valve put at rest at OP(0) mid-swing may never reach S (to reverse) nor J (to go on), and its
replay explains nothing. Which start synchronises soonest with the real valve depends on the data, so the
start is a nuisance parameter of every valve candidate (not counted by BIC), with three values:

``PRE_ROLL`` (2)
    The valve first runs through the first fifth of the record (at least 100 samples) mirrored in time,
    ``OP[K], …, OP[1]``, which joins the record continuously at OP(0) and has its excursions; by OP(0) it
    is in a state a valve cycling on this OP reaches — stuck at a recent extreme, or moving. It starts the
    pre-roll moving upwards.
``+1`` / ``−1``
    The valve is moving up / down at OP(0): put at rest at ``OP(0) ∓ (J + ε)`` having last moved that way,
    so the first sample overcomes J. These are the most eager states in each direction.

Burn-in: the three starts are very different states; once their replays agree, the valve's true initial
state (which lies among such states) has almost always been forgotten too. :func:`sync_burn_in` returns the
sample by which the three agree for good, the 90th percentile over a grid of (S, J); the search scores every
model only after the largest such burn-in (capped), so that no candidate is rewarded for a lucky start.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numba
import numpy as np

from valve_emulator.diagnosis._threads import run_split, workers_for
from valve_emulator.diagnosis.candidates.base import ChainContext
from valve_emulator.physics._arrays import kernel_array
from valve_emulator.physics.stiction import (
    CHOUDHURY,
    DIR,
    FLAG,
    KANO,
    MODELS,
    MV,
    NSTATE,
    REF,
    STILL,
    STUCK,
    U_PREV,
    choudhury_update,
    he_update,
    initial_state,
    kano_update,
    stiction_step_kernel,
)

__all__ = ["PRE_ROLL", "STARTS", "valve_burn_in", "valve_output", "sync_burn_in"]

PRE_ROLL: Final = 2.0
#: The start values, in the order grids use them.
STARTS: Final = (PRE_ROLL, 1.0, -1.0)
_EPS = 1e-6


def _pre_roll(T: int) -> int:
    return min(T - 1, max(100, T // 5))


#: From this many valves of one model a thread's share steps the branch-free formulation of the state machines
#: (:func:`~valve_emulator.physics.stiction.kano_update` and its siblings: the same state bit for bit), written
#: out in the time loop below so that LLVM vectorises the loop over the valves. Measured (10⁴ samples, Kano):
#: 1.0–1.2 ns per valve-sample from 24 valves on, against 2.3–3.4 for the branches; at 21 and fewer LLVM's
#: vector loop is not entered and the selects take 7 ns.
_VECTOR_FROM = 24
#: Up to this many valves of one model step the same selects too, one valve at a time: the branches' kernel,
#: called once per sample with the bank's arrays, costs more in that call than a few valves' updates (a joint
#: polish replays one valve at a time). Measured on the 2-core machine of 2026-11-28 (2,400 samples, load 6):
#: one Kano valve 23 → 9.6 ns per valve-sample, two 13 → 9.0, four 8.3 → 7.3 (He: 23 → 8.0, 8.2 → 4.9); from
#: eight on the branches were as fast or faster (Kano 5.4 against 7.1).
_SELECTS_UPTO = 4


@numba.njit(cache=True, nogil=True)
def _run_valves(op, K, first, last, cols, S, J, R, codes, st, out, out_first):  # pragma: no cover - compiled
    # The physics layer's state machines in a compiled time loop over samples first..last-1 of the record preceded
    # by its mirrored pre-roll: sample kk < K is op[K - kk] (op[K], ..., op[1]), sample kk >= K is op[kk - K].
    # Valve i reads OP column cols[i] and, from kk = K on, writes MV into row kk - out_first, column cols[i] of out
    # (out_first = K: out is the record's MV, (T, n)). The state is column-major. At least _VECTOR_FROM valves of
    # one model step the selects inline, one loop over the valves per sample: a call per sample to the physics
    # layer's step_same_model (arrays as arguments, reference counts updated at every call) cost more than the
    # valves' own work at these sizes (64 valves: 3 ns per valve-sample against 1.0 inline), and than one valve's
    # (_SELECTS_UPTO). Those in between keep the branches of stiction_step_kernel.
    m = cols.shape[0]
    u = np.empty(m)
    same = m >= _VECTOR_FROM or m <= _SELECTS_UPTO
    for i in range(m):
        same = same and codes[i] == codes[0]
    code = codes[0] if m else KANO
    for kk in range(first, last):
        k = K - kk if kk < K else kk - K
        if op.shape[1] > 1:
            for i in range(m):
                u[i] = min(max(op[k, cols[i]], 0.0), 100.0)
        else:
            v = min(max(op[k, 0], 0.0), 100.0)
            for i in range(m):
                u[i] = v
        if not same:
            stiction_step_kernel(u, S, J, R, codes, st)
        elif code == KANO:
            for i in range(m):
                st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR], st[i, FLAG], st[i, STILL], st[i, STUCK] = \
                    kano_update(u[i], S[i], J[i], R[i], st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR],
                                st[i, FLAG], st[i, STILL])
        elif code == CHOUDHURY:
            for i in range(m):
                st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR], st[i, FLAG], st[i, STUCK] = \
                    choudhury_update(u[i], S[i], J[i], st[i, MV], st[i, U_PREV], st[i, REF], st[i, DIR],
                                     st[i, FLAG])
        else:
            for i in range(m):
                st[i, MV], st[i, U_PREV], st[i, REF], st[i, STUCK] = \
                    he_update(u[i], S[i], J[i], st[i, MV], st[i, U_PREV], st[i, REF])
        if kk >= K:
            for i in range(m):
                out[kk - out_first, cols[i]] = st[i, MV]


#: Samples between the checks of :func:`_run_merging` for valves that have caught up with their group's first.
_MERGE_EVERY = 256
#: Fewest valves :func:`_run_merging` keeps stepping when it was given at least as many: on the 2-core machine of
#: 2026-11-27 (AMD EPYC) the vector loop cost 3.6–4.0 ns per valve-sample from 28 valves on and 9.5 ns at 24 (the
#: branches 8.5–8.8 ns at 16–20), so a bank that steps the vector loop keeps this many going (all of them below
#: it); a smaller bank, which takes the branches at the same cost per valve however few, stops any that catch up.
_KEEP_STEPPING = 32


@numba.njit(cache=True, nogil=True)
def _run_merging(op, K, T, cols, S, J, R, codes, st, out, leader, keep):  # pragma: no cover - compiled
    # _run_valves over the record (samples K..K+T-1 of the pre-rolled time axis, all m valves from their states st at
    # the record's first sample, column-major), OP shared by all (op (., 1)), for valves in groups of equal
    # parameters: leader[i] is the first valve of i's group (the same S and J to the bit; R and the model are the
    # bank's), i itself for the first. Every _MERGE_EVERY samples a valve whose state equals its leader's to the bit
    # (NaN never equal, -0.0 not 0.0) stops stepping: from there it would step exactly as its leader (the same
    # numbers through the same operations), so its column of out is its leader's from that sample on, copied segment
    # by segment. Leaders never stop; at least ``keep`` valves keep stepping (_KEEP_STEPPING). Returns how many
    # valve-samples were stepped.
    m = cols.shape[0]
    since = np.full(m, T, dtype=np.int64)
    act = np.arange(m)
    pos = np.arange(m)
    a_cols, a_S, a_J, a_R, a_codes = cols.copy(), S.copy(), J.copy(), R.copy(), codes.copy()
    a_st = np.empty((NSTATE, m)).T
    for i in range(m):
        for s in range(NSTATE):
            a_st[i, s] = st[i, s]
    stepped = 0
    f_cols = l_cols = cols[:0].copy()   # the columns of the valves that stopped, and of their leaders
    for k0 in range(0, T, _MERGE_EVERY):
        n_act = act.shape[0]
        going = np.ones(n_act, dtype=np.bool_)
        n_going = n_act
        for p in range(n_act):
            i = act[p]
            if leader[i] == i or n_going <= keep:
                continue
            q = pos[leader[i]]
            same = True
            for s in range(NSTATE):
                a, b = a_st[p, s], a_st[q, s]
                if not (a == b and (a != 0.0 or np.signbit(a) == np.signbit(b))):
                    same = False
                    break
            if same:
                going[p] = False
                n_going -= 1
                since[i] = k0
        if n_going < n_act:
            idx = np.flatnonzero(going)
            act, a_cols, a_S, a_J, a_R, a_codes = act[idx], a_cols[idx], a_S[idx], a_J[idx], a_R[idx], a_codes[idx]
            new_st = np.empty((NSTATE, n_going)).T
            for p in range(n_going):
                for s in range(NSTATE):
                    new_st[p, s] = a_st[idx[p], s]
            a_st = new_st
            for p in range(n_going):
                pos[act[p]] = p
            stopped = np.flatnonzero(since < T)
            f_cols, l_cols = cols[stopped], cols[leader[stopped]]
        k1 = min(T, k0 + _MERGE_EVERY)
        _run_valves(op, K, K + k0, K + k1, a_cols, a_S, a_J, a_R, a_codes, a_st, out, K)
        stepped += n_going * (k1 - k0)
        for k in range(k0, k1):   # the segment's rows, still in cache
            for f in range(f_cols.shape[0]):
                out[k, f_cols[f]] = out[k, l_cols[f]]
    return stepped


def _leaders(S: np.ndarray, J: np.ndarray) -> np.ndarray:
    """For each valve, the first valve with the same ``S`` and ``J`` to the bit (itself for the first of each)."""
    return _first_equal(np.ascontiguousarray(S).view(np.int64), np.ascontiguousarray(J).view(np.int64))


@numba.njit(cache=True, nogil=True)
def _first_equal(s, j):  # pragma: no cover - compiled
    # For each i, the first k <= i with s[k] == s[i] and j[k] == j[i] (the bits of S and J as integers): a bank holds
    # a few dozen valves, so the pairs are compared directly rather than hashed.
    n = s.shape[0]
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        out[i] = i
        for k in range(i):
            if s[k] == s[i] and j[k] == j[i]:
                out[i] = k
                break
    return out


@dataclass(frozen=True, eq=False)
class _Bank:
    """Valves ready to run (:func:`_bank`): OP (T, 1 or n) as the kernel reads it, the pre-roll's length ``K``,
    which valves start with the pre-roll, their parameters, model codes and initial state (n, NSTATE)."""

    x: np.ndarray
    K: int
    pre: np.ndarray
    S: np.ndarray
    J: np.ndarray
    R: np.ndarray
    codes: np.ndarray
    state: np.ndarray


def _bank(x: np.ndarray, S: np.ndarray, J: np.ndarray, start: np.ndarray, ctx: ChainContext) -> _Bank:
    """The valves of :func:`valve_output` in their initial states."""
    x = np.asarray(x, dtype=float)
    x2 = kernel_array(x[:, None] if x.ndim == 1 else x)
    S, J, start = (np.asarray(a, dtype=float) for a in (S, J, start))
    n = max(S.size, J.size, start.size, x2.shape[1])
    S, J, start = (_per_valve(a, n) for a in (S, J, start))
    K = _pre_roll(x2.shape[0])
    pre = start == PRE_ROLL
    d = np.where(pre, 1.0, start)
    cols = np.zeros(n, dtype=np.int64) if x2.shape[1] == 1 else np.arange(n)
    first = np.where(pre, x2[K, cols], x2[0, cols])   # the OP each valve starts from
    codes = np.full(n, MODELS.index(ctx.valve_model), dtype=np.int64)
    state = np.zeros((n, NSTATE))
    initial_state(state, np.clip(first - d * (J + _EPS), 0.0, 100.0), d, S, J, codes)
    return _Bank(x=x2, K=K, pre=pre, S=S, J=J, R=np.full(n, float(ctx.rest_samples)), codes=codes,
                 state=state)


def _per_valve(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` (one value, or one per valve) as a new C-contiguous, writable array of ``n`` values. Writable:
    ``np.ascontiguousarray`` passes a broadcast view through read-only, and numba compiled the valves' kernel (and
    the physics' step within it) once more for every read-only mix of S and J (:func:`~valve_emulator.physics.
    _arrays.kernel_array`). A grid's column, n values already, is copied without the broadcast's set-up."""
    if a.shape == (n,):
        return a.copy()
    return kernel_array(np.broadcast_to(np.atleast_1d(a), (n,)))


def _pre_rolled(bank: _Bank, valves: np.ndarray) -> np.ndarray:
    """The state (column-major) of ``valves`` at the record's first sample: those that start with the pre-roll
    run through the mirrored pre-roll first."""
    st = np.asfortranarray(bank.state[valves])
    rolled = np.flatnonzero(bank.pre[valves])
    if rolled.size:
        i = valves[rolled]
        st_pre = np.asfortranarray(st[rolled])
        _run_valves(bank.x, bank.K, 0, bank.K, i, bank.S[i], bank.J[i], bank.R[i], bank.codes[i], st_pre,
                    np.empty((0, 0)), bank.K)
        st[rolled] = st_pre
    return st


def valve_output(x: np.ndarray, S: np.ndarray, J: np.ndarray, start: np.ndarray, ctx: ChainContext) -> np.ndarray:
    """MV (T, n) of valves with parameters ``S, J`` and initial state ``start`` (see the module docstring).

    ``x`` is OP (T,) shared by all, or (T, n) one column per valve.
    """
    bank = _bank(x, S, J, start, ctx)
    n, T, K = bank.S.size, bank.x.shape[0], bank.K
    out = np.empty((T, n))

    def part(a: int, b: int) -> None:
        # Valves a..b-1 (a thread's share; the valves are independent and the kernel releases the GIL): those that
        # start with the pre-roll first run through the mirrored pre-roll, then all of them through the record
        # together, in column order (whole vectors, and each sample's MV written as one contiguous row).
        valves = np.arange(a, b)
        st = _pre_rolled(bank, valves)
        leader = _leaders(bank.S[a:b], bank.J[a:b]) if bank.x.shape[1] == 1 and b - a > 1 else None
        if leader is None or (leader == np.arange(b - a)).all():
            _run_valves(bank.x, K, K, K + T, valves, bank.S[a:b], bank.J[a:b], bank.R[a:b], bank.codes[a:b], st,
                        out, K)
        else:   # valves of equal parameters, different starts: those that catch up stop stepping (_run_merging)
            _run_merging(bank.x, K, T, valves, bank.S[a:b], bank.J[a:b], bank.R[a:b], bank.codes[a:b], st, out,
                         leader, min(b - a, _KEEP_STEPPING) if b - a >= _VECTOR_FROM else 0)

    workers = workers_for(n)
    run_split(part, [n * w // workers for w in range(workers + 1)])
    return out


def sync_burn_in(mv: np.ndarray, n_starts: int = len(STARTS)) -> int:
    """Samples until valves with different starts agree for good (columns in groups of ``n_starts``).

    For each group, the sample after which all its columns give the same MV to the end of the record; the
    90th percentile over the groups that do agree over at least the last tenth of the record.
    """
    T = mv.shape[0]
    last = _last_differing(kernel_array(mv), n_starts)
    merged = last < T - 1 - T // 10
    return int(np.percentile(last[merged] + 1, 90)) if merged.any() else 0


#: Samples a bank of valves runs between the burn-in's checks of which groups have merged (:func:`valve_burn_in`).
_SEGMENT = 1024


def valve_burn_in(x: np.ndarray, S: np.ndarray, J: np.ndarray, start: np.ndarray, ctx: ChainContext,
                  n_starts: int = len(STARTS)) -> int:
    """``sync_burn_in(valve_output(x, S, J, start, ctx), n_starts)``, without the record's MV.

    The valves run through the record :data:`_SEGMENT` samples at a time; after each segment a group whose
    valves have the same parameters and, to the bit, the same state is dropped: from there its valves step alike
    for good, so its columns never differ again and the sample at which they last differed is already known. On
    a long record most groups merge early and the rest of the record is replayed for the few that have not
    (stiction's coarse grid at 10^5 samples: (T, 396) MV, 317 MB, no longer written and read back).
    """
    bank = _bank(x, S, J, start, ctx)
    n, T, K = bank.S.size, bank.x.shape[0], bank.K
    groups = np.arange(n // n_starts)
    last = np.full(groups.size, -1, dtype=np.int64)
    valves = np.arange(groups.size * n_starts)
    st = _pre_rolled(bank, valves)
    same_params = _same_within_groups(bank.S, n_starts) & _same_within_groups(bank.J, n_starts)
    buf = np.empty((_SEGMENT, valves.size))
    for k0 in range(0, T, _SEGMENT):
        k1 = min(T, k0 + _SEGMENT)
        cols = np.arange(valves.size)
        _run_valves(bank.x, K, K + k0, K + k1, cols, bank.S[valves], bank.J[valves], bank.R[valves],
                    bank.codes[valves], st, buf, K + k0)
        seen = _last_differing(buf[:k1 - k0], n_starts)
        last[groups[seen >= 0]] = k0 + seen[seen >= 0]
        going = ~(same_params[groups] & _merged(st, n_starts))
        if not going.all():
            groups = groups[going]
            keep = np.repeat(going, n_starts)
            valves, st = valves[keep], np.asfortranarray(st[keep])
            buf = np.empty((_SEGMENT, valves.size))   # contiguous, as the kernels were compiled for
        if groups.size == 0:
            break
    merged = last < T - 1 - T // 10
    return int(np.percentile(last[merged] + 1, 90)) if merged.any() else 0


def _same_within_groups(a: np.ndarray, n_starts: int) -> np.ndarray:
    """Per group of ``n_starts`` consecutive entries of ``a``, whether they are equal to the bit."""
    bits = np.ascontiguousarray(a[:a.size // n_starts * n_starts]).view(np.int64).reshape(-1, n_starts)
    return (bits == bits[:, :1]).all(axis=1)


def _merged(st: np.ndarray, n_starts: int) -> np.ndarray:
    """Per group of ``n_starts`` consecutive rows of the state ``st`` (n, NSTATE), whether they are equal to the
    bit."""
    bits = np.ascontiguousarray(st).view(np.int64).reshape(-1, n_starts, st.shape[1])
    return (bits == bits[:, :1]).all(axis=(1, 2))


@numba.njit(cache=True, nogil=True)
def _last_differing(mv, n_starts):  # pragma: no cover - compiled
    # Per group of n_starts columns of mv (T, n), the last sample at which its columns differ by more than 1e-9
    # (-1: never), read from the end of the record back to it: a group that agrees over most of the record is
    # read over the part where it agrees only, and none is copied out. Its spread at a sample is numpy's
    # np.maximum / np.minimum over the columns in order (a NaN propagates, and a NaN spread does not differ),
    # then the difference: the numbers the whole-array reduction compared.
    T = mv.shape[0]
    n_groups = mv.shape[1] // n_starts
    last = np.full(n_groups, -1, dtype=np.int64)
    for g in range(n_groups):
        c = g * n_starts
        for k in range(T - 1, -1, -1):
            top = bottom = mv[k, c]
            for j in range(1, n_starts):
                x = mv[k, c + j]
                if x != x or top != top:
                    top = np.nan
                elif x > top:
                    top = x
                if x != x or bottom != bottom:
                    bottom = np.nan
                elif x < bottom:
                    bottom = x
            if top - bottom > 1e-9:
                last[g] = k
                break
    return last
