"""Control loops -- sticky valve, plant and optional internal PI(D) -- stepped together as a bank.

One loop is a bank of one. Both the offline simulator (:meth:`LoopBank.run`, :func:`simulate_loop`) and the
emulator's tick (:meth:`LoopBank.step`) call the same compiled kernel, :func:`loop_step_kernel`, so an
emulated device and an offline run of the same config give the same trajectory sample for sample.

Order inside one sample k, for every loop at once (see ``docs/design.md``):

1. ``pv_k``  = plant output at ``t_k`` + measurement noise;
2. ``op_k``  = PI(D)(sp_k, pv_k) where the loop has an internal controller, else the external OP held since
   the last write (``op_external``);
3. ``mv_k``  = stiction(saturate(actuator(op_k))), ``flow_k`` = clip(characteristic(mv_k), flow limits): the
   actuator's lag (``valve.actuator_lag``, :mod:`~valve_emulator.physics.actuator`) acts before the friction,
   the flow limits (``valve.flow_limits``) after the characteristic — the order of the diagnosis' chain; a
   loop without them passes OP and flow unchanged;
4. the plant integrates ``flow_k`` + load disturbance over ``[t_k, t_k + dt)``, giving ``pv_{k+1}``.

The initial state is an equilibrium: the valve at rest at its initial OP (controller bias, or ``valve.op0``
without a controller), the plant's operating-point flow ``u0`` equal to the valve's initial flow unless the
config sets it, so PV starts at ``pv0`` and nothing moves until something is changed.

A config may instead carry the state a recording starts in (a twin's, :mod:`valve_emulator.diagnosis.report.twin`):
``valve.mv0`` and ``valve.stuck0`` put the valve at that position, stuck or still moving in
``valve.initial_direction``, and ``plant.rest_flow`` starts the plant at rest for that flow instead of the
valve's. Without those keys the loop starts exactly as before.
"""

from __future__ import annotations

import math
from collections import namedtuple
from collections.abc import Sequence
from typing import ClassVar, NamedTuple

import numba
import numpy as np

from valve_emulator.config import LoopConfig, ValveConfig
from valve_emulator.physics._arrays import kernel_array
from valve_emulator.physics.actuator import actuator_output, lag_coefficients
from valve_emulator.physics.controller import DERIVATIVE_FILTER, PIDBank, pid_step_kernel
from valve_emulator.physics.disturbance import BLOCK as NORMALS_BLOCK
from valve_emulator.physics.disturbance import DisturbanceBank, NoiseBank
from valve_emulator.physics.plant import PlantBank, plant_step_kernel, transfer_functions_to_zoh
from valve_emulator.physics.signal_chain import CHARACTERISTICS, Characteristic, LookupTable
from valve_emulator.physics.stiction import (
    DIR,
    FLAG,
    MODELS,
    MV,
    NSTATE,
    REF,
    STILL,
    STUCK,
    U_PREV,
    initial_state,
    rest_samples_for,
    stiction_step_kernel,
    validate_parameters,
)
from valve_emulator.recordings.recording import Recording
from valve_emulator.simulation import state as _state

__all__ = ["LoopBank", "PackedState", "simulate_loop", "loop_step_kernel", "sensed_step_kernel", "packed_step_kernel",
           "ROWS", "BOOL_ROWS", "INT_ROWS"]

_LINEAR, _EQUAL_PERCENTAGE, _QUICK_OPENING = (CHARACTERISTICS.index(k) for k in CHARACTERISTICS)


@numba.njit(cache=True, inline="always")
def _flow(mv, kind, rangeability):  # pragma: no cover - compiled
    x = min(max(mv, 0.0), 100.0) / 100.0
    if kind == _EQUAL_PERCENTAGE:
        return 100.0 * rangeability ** (x - 1.0)
    if kind == _QUICK_OPENING:
        return 100.0 * math.sqrt(x)
    return 100.0 * x


@numba.njit(cache=True)
def loop_step_kernel(sp, noise, dist, op_ext, has_ctrl, frozen, pid, pid_op, actuator, valve, char_kind, char_r,
                     flow_limits, plant, plant_pv, pv_meas, op, flow, u_in):  # pragma: no cover - compiled
    """Advance every loop one sample in place (see the module docstring for the order).

    ``pid`` and ``plant`` are the argument tuples of ``pid_step_kernel`` and ``plant_step_kernel`` after
    their inputs, ``pid_op`` and ``plant_pv`` the output arrays inside them (their banks' ``kernel_output``);
    ``actuator`` is ``(tau, a, w, state)`` of :func:`~valve_emulator.physics.actuator.actuator_output`;
    ``valve`` is ``(S, J, R, codes, state)`` of ``stiction_step_kernel``; ``flow_limits`` (n, 2) the flow's
    ``[lo, hi]``. Outputs: ``pv_meas`` (PV measured
    at t_k), ``op``, ``flow``; ``u_in`` is scratch. Returns 0, or a nonzero code when an input was not
    finite (the controller or plant kernel refused it).
    """
    n = sp.shape[0]
    for i in range(n):
        pv_meas[i] = plant_pv[i] + noise[i]
    code = pid_step_kernel(sp, pv_meas, *pid)
    if code != 0:
        return code
    st = valve[4]
    for i in range(n):
        op[i] = pid_op[i] if has_ctrl[i] else op_ext[i]
        demand = actuator_output(i, op[i], actuator[0], actuator[1], actuator[2], actuator[3])
        u_in[i] = st[i, U_PREV] if frozen[i] else demand
    stiction_step_kernel(u_in, valve[0], valve[1], valve[2], valve[3], valve[4])
    for i in range(n):
        flow[i] = min(max(_flow(st[i, MV], char_kind[i], char_r[i]), flow_limits[i, 0]), flow_limits[i, 1])
        u_in[i] = flow[i] + dist[i]
    bad = plant_step_kernel(u_in, *plant)
    if bad >= 0:
        return 10 + bad
    return 0


#: :func:`sensed_step_kernel`'s answers when it has not stepped: the set-point schedule has a step due, or a loop
#: has measurement noise and the noise streams do not exist yet (both handled in Python, then the call repeated).
SP_DUE, NOISE_DUE = -1, -2


@numba.njit(cache=True)
def sensed_step_kernel(sp_next, due_by, noise_missing, unit_noise, noise_std, pv_bias, pv_stuck, load, disturbance,
                       sp, op_ext, has_ctrl, frozen, pid, pid_op, actuator, valve, char_kind, char_r, flow_limits,
                       plant, plant_pv, pv_meas, op, flow, u_in):  # pragma: no cover - compiled
    """One sample of :meth:`LoopBank.step`: :func:`loop_step_kernel` with the measurement noise
    ``unit_noise·noise_std + pv_bias`` (or a stuck transmitter's value) and the plant input's ``load +
    disturbance`` composed here, element by element as numpy would.

    Before anything changes it returns :data:`SP_DUE` when a set-point step is due (``sp_next <= due_by``)
    and :data:`NOISE_DUE` when ``noise_missing`` and a loop is noisy; otherwise the step's code (0: done).
    """
    n = sp.shape[0]
    for i in range(n):
        if sp_next[i] <= due_by:
            return SP_DUE
        if noise_missing and noise_std[i] != 0.0:
            return NOISE_DUE
    noise = np.empty(n)
    dist = np.empty(n)
    for i in range(n):
        noise[i] = unit_noise[i] * noise_std[i] + pv_bias[i]
        if np.isfinite(pv_stuck[i]):
            noise[i] = pv_stuck[i] - plant_pv[i]
        dist[i] = load[i] + disturbance[i]
    return loop_step_kernel(sp, noise, dist, op_ext, has_ctrl, frozen, pid, pid_op, actuator, valve, char_kind,
                            char_r, flow_limits, plant, plant_pv, pv_meas, op, flow, u_in)


#: The bank's float state, one row each of :attr:`PackedState.floats` (n loops wide): row name -> (the sub-bank
#: that names it, ``""`` for the bank itself, and its attribute there). The attributes are views of their rows,
#: so the sub-banks, :meth:`LoopBank.run` and the snapshots (which find state by attribute) see one storage.
_FLOAT_ATTRS: dict[str, tuple[str, str]] = {
    "sp_next": ("", "_sp_next"), "noise_std": ("", "noise_std"), "pv_bias": ("", "pv_bias"),
    "pv_stuck": ("", "pv_stuck"), "load": ("", "load"), "sp": ("", "_sp"), "op_external": ("", "op_external"),
    "S": ("", "_S"), "J": ("", "_J"), "R": ("", "_R"), "char_r": ("", "_char_r"), "act_tau": ("", "_act_tau"),
    "act_a": ("", "_act_a"), "act_w": ("", "_act_w"), "act_state": ("", "_act_state"), "pv": ("", "pv"),
    "op": ("", "op"), "flow": ("", "flow"), "u_in": ("", "_u_in"),
    "kc": ("_pid", "_kc"), "ti_inv": ("_pid", "_ti_inv"), "td": ("_pid", "_td"), "bias": ("_pid", "_bias"),
    "sign": ("_pid", "_sign"), "op_min": ("_pid", "_op_min"), "op_max": ("_pid", "_op_max"),
    "integral": ("_pid", "_integral"), "deriv": ("_pid", "_deriv"), "pv_last": ("_pid", "_pv_last"),
    "e_last": ("_pid", "_e_last"), "u_last": ("_pid", "_u_last"), "pid_op": ("_pid", "_op"),
    "man_op": ("_pid", "_man_op"),
    "u0": ("_plant", "_u0"), "pv0": ("_plant", "_pv0"), "D": ("_plant", "_D"), "ud": ("_plant", "_ud"),
    "plant_pv": ("_plant", "_pv"),
}
#: Rows of no attribute: this sample's disturbance and unit normals (inputs :meth:`LoopBank.step` fills when a
#: loop has them), and the PV measured by a step, kept until the step is known to have succeeded.
_SCRATCH_ROWS = ("dist", "unit", "pv_new")
_BOOL_ATTRS = {"has_controller": ("", "has_controller"), "frozen": ("", "frozen"), "auto": ("_pid", "_auto"),
              "init": ("_pid", "_init")}
#: Integer rows; the plant's ring head is the first element of its row (``_plant._head`` a view of shape (1,)).
_INT_ATTRS = {"codes": ("", "_codes"), "char_kind": ("", "_char_kind"), "m": ("_plant", "_m"),
             "head": ("_plant", "_head")}
#: The plant's (n, order) arrays, one plane each of :attr:`PackedState.plant_vectors`.
_PLANT_PLANES = ("_B0", "_B1", "_C", "_x")

#: Row numbers by name: ``ROWS.kc`` is the row of the controller gains in :attr:`PackedState.floats`
#: (a tuple of ints: compiled code reads them as constants).
#: (Classes of their own names, so that a kernel holding them in a closure can be cached.)
FloatRows = namedtuple("FloatRows", [*_FLOAT_ATTRS, *_SCRATCH_ROWS])
BoolRows = namedtuple("BoolRows", list(_BOOL_ATTRS))
IntRows = namedtuple("IntRows", list(_INT_ATTRS))
ROWS = FloatRows(*range(len(FloatRows._fields)))
BOOL_ROWS = BoolRows(*range(len(BoolRows._fields)))
INT_ROWS = IntRows(*range(len(IntRows._fields)))


class PackedState(NamedTuple):
    """A loop bank's whole state in nine arrays -- the arguments of :func:`packed_step_kernel` before its
    scalars. At one loop a compiled call's cost is mostly numba unboxing its array arguments (about 50 ns
    each): a step from these costs a fifth of one given every array of the bank (some 60)."""

    floats: np.ndarray         # (len(ROWS), n): the rows of ROWS
    bools: np.ndarray          # (len(BOOL_ROWS), n)
    ints: np.ndarray           # (len(INT_ROWS), n): stiction model codes, characteristic kinds, plant delays, ring head
    valve: np.ndarray          # (n, NSTATE): the stiction state machines
    flow_limits: np.ndarray    # (n, 2)
    plant_A: np.ndarray        # (n, order, order)
    plant_vectors: np.ndarray  # (4, n, order): B0, B1, C and the state x
    plant_buf: np.ndarray      # (n, ring length): the dead-time ring buffers
    plant_work: np.ndarray     # (order,) scratch


@numba.njit(cache=True)
def packed_step_kernel(floats, bools, ints, valve, flow_limits, plant_A, plant_vectors, plant_buf, plant_work, t, dt,
                       noise_missing):  # pragma: no cover - compiled
    """:func:`sensed_step_kernel` on a bank's :class:`PackedState` at time ``t``: the same codes, the same
    arithmetic. The rows ``dist`` and ``unit`` hold this sample's disturbance and unit normals (``unit`` is
    zeroed here while ``noise_missing``); the measured PV lands in row ``pv`` only once the step succeeded."""
    F, B, P = floats, bools, plant_vectors
    if noise_missing:
        F[ROWS.unit, :] = 0.0
    pid = (F[ROWS.kc], F[ROWS.ti_inv], F[ROWS.td], F[ROWS.bias], F[ROWS.sign], F[ROWS.op_min], F[ROWS.op_max], dt,
           DERIVATIVE_FILTER, F[ROWS.integral], F[ROWS.deriv], F[ROWS.pv_last], F[ROWS.e_last], F[ROWS.u_last],
           F[ROWS.pid_op], B[BOOL_ROWS.auto], F[ROWS.man_op], B[BOOL_ROWS.init])
    actuator = (F[ROWS.act_tau], F[ROWS.act_a], F[ROWS.act_w], F[ROWS.act_state])
    valve_args = (F[ROWS.S], F[ROWS.J], F[ROWS.R], ints[INT_ROWS.codes], valve)
    plant = (F[ROWS.u0], F[ROWS.pv0], plant_A, P[0], P[1], P[2], F[ROWS.D], ints[INT_ROWS.m], plant_buf,
             ints[INT_ROWS.head], P[3], F[ROWS.ud], F[ROWS.plant_pv], plant_work)
    code = sensed_step_kernel(F[ROWS.sp_next], t + 1e-9 * dt, noise_missing, F[ROWS.unit], F[ROWS.noise_std],
                              F[ROWS.pv_bias], F[ROWS.pv_stuck], F[ROWS.load], F[ROWS.dist], F[ROWS.sp],
                              F[ROWS.op_external], B[BOOL_ROWS.has_controller], B[BOOL_ROWS.frozen], pid,
                              F[ROWS.pid_op], actuator, valve_args, ints[INT_ROWS.char_kind], F[ROWS.char_r],
                              flow_limits, plant, F[ROWS.plant_pv], F[ROWS.pv_new], F[ROWS.op], F[ROWS.flow],
                              F[ROWS.u_in])
    if code == 0:
        F[ROWS.pv, :] = F[ROWS.pv_new]
    return code


def _pack(bank: LoopBank) -> PackedState:
    """Move the bank's state arrays (and its controller's and plant's) into the rows of a :class:`PackedState`,
    each attribute becoming a view of its row: one storage, reached by name or by one compiled call."""
    n, plant = bank.n, bank._plant

    def adopt(rows: np.ndarray, table: dict[str, tuple[str, str]]) -> None:
        for r, (owner_name, attr) in enumerate(table.values()):
            owner = getattr(bank, owner_name) if owner_name else bank
            old = getattr(owner, attr)
            view = rows[r, :old.size]   # the ring head is one number: the first of its row
            view[:] = old
            setattr(owner, attr, view)

    floats = np.zeros((len(ROWS), n))
    adopt(floats, _FLOAT_ATTRS)
    bools = np.zeros((len(BOOL_ROWS), n), dtype=np.bool_)
    adopt(bools, _BOOL_ATTRS)
    ints = np.zeros((len(INT_ROWS), n), dtype=np.int64)
    adopt(ints, _INT_ATTRS)
    vectors = np.stack([getattr(plant, name) for name in _PLANT_PLANES])
    for j, name in enumerate(_PLANT_PLANES):
        setattr(plant, name, vectors[j])
    return PackedState(floats, bools, ints, bank._vstate, bank._flow_limits, plant._A, vectors, plant._buf,
                       plant._work)


@numba.njit(cache=True)
def _run_kernel(sp, noise, dist, op_ext, has_ctrl, frozen, pid, pid_op, actuator, valve, char_kind, char_r,
                flow_limits, plant, plant_pv, pv_meas, op, flow, u_in, out_pv, out_op, out_mv, out_flow,
                out_stuck):  # pragma: no cover
    st = valve[4]
    for k in range(sp.shape[0]):
        code = loop_step_kernel(sp[k], noise[k], dist[k], op_ext[k], has_ctrl, frozen, pid, pid_op, actuator,
                                valve, char_kind, char_r, flow_limits, plant, plant_pv, pv_meas, op, flow, u_in)
        if code != 0:
            return k
        for i in range(sp.shape[1]):
            out_pv[k, i] = pv_meas[i]
            out_op[k, i] = op[i]
            out_mv[k, i] = st[i, MV]
            out_flow[k, i] = flow[i]
            out_stuck[k, i] = st[i, STUCK] == 1.0
    return -1


class LoopBank:
    """``n`` control loops stepped together, built from :class:`~valve_emulator.config.LoopConfig` objects.

    Parameters
    ----------
    loops : the loops' configs.
    dt : sample time (s); default the first loop's ``simulation.dt`` (the device passes its tick).
    """

    def __init__(self, loops: Sequence[LoopConfig], *, dt: float | None = None) -> None:
        loops = tuple(loops)
        if not loops:
            raise ValueError("loops must contain at least one LoopConfig")
        self.loops = loops
        self.n = n = len(loops)
        self.dt = float(loops[0].simulation.dt if dt is None else dt)
        self.k = 0
        valves = [c.valve for c in loops]

        # valve: stiction state machines and characteristics
        self._S = np.array([v.S for v in valves], dtype=float)
        self._J = np.array([v.J for v in valves], dtype=float)
        self._R = np.array(_shared(rest_samples_for, [(v.rest_time, self.dt) for v in valves]), dtype=float)
        self._codes = np.array([MODELS.index(v.model) for v in valves], dtype=np.int64)
        self._vstate = np.zeros((n, NSTATE))
        self._char_kind = np.array([CHARACTERISTICS.index(v.characteristic) for v in valves], dtype=np.int64)
        self._char_r = np.array([v.rangeability for v in valves], dtype=float)
        self._flow_limits = np.array([v.flow_limits for v in valves], dtype=float).reshape(n, 2)
        # Fleets repeat these: build each distinct one once (they are immutable, sharing is safe).
        self.characteristics = _shared(Characteristic, [(v.characteristic, v.rangeability) for v in valves])
        self.tables = _shared(LookupTable, [(v.ma_table,) for v in valves])

        # controller (a dummy P controller where a loop has none; its output is not used there)
        ctrls = [c.controller for c in loops]
        self.has_controller = np.array([c is not None for c in ctrls])
        self._pid = PIDBank(
            n,
            kc=[c.kc if c else 1.0 for c in ctrls],
            ti=[c.ti if (c and c.ti is not None) else math.inf for c in ctrls],
            td=[c.td if c else 0.0 for c in ctrls],
            bias=[c.bias if c else 50.0 for c in ctrls],
            direct=[bool(c and c.action == "direct") for c in ctrls],
            op_min=[c.op_limits[0] if c else 0.0 for c in ctrls],
            op_max=[c.op_limits[1] if c else 100.0 for c in ctrls],
            dt=self.dt,
        )
        op_init = np.array([
            min(max(c.bias, c.op_limits[0]), c.op_limits[1]) if c else v.op0 for c, v in zip(ctrls, valves)
        ])
        self.op_external = np.array([v.op0 for v in valves], dtype=float)

        # actuator at rest at the initial OP, valve at rest there; plant in equilibrium at the resulting flow
        self._act_tau = np.array([v.actuator_lag for v in valves], dtype=float)
        self._act_a, self._act_w = lag_coefficients(self._act_tau, self.dt)
        self._act_state = op_init.astype(float)
        initial_state(self._vstate, op_init, np.array([v.initial_direction for v in valves], dtype=float),
                      self._S, self._J, self._codes)
        for i, v in enumerate(valves):
            if v.mv0 is not None or not v.stuck0:
                _place_valve(self._vstate[i], v, self._S[i], self._J[i])
        mv0 = self._vstate[:, MV]
        flow0 = np.clip(_flows(self.characteristics, mv0), self._flow_limits[:, 0], self._flow_limits[:, 1])
        # The exact discretisation (three matrix exponentials) dominates building a large bank: loops with the
        # same transfer function and delay share one (same inputs, same result: nothing is approximated), and
        # the distinct ones are discretised in batches of one order.
        plants = _shared_batch(transfer_functions_to_zoh, [(c.plant.num, c.plant.den, c.plant.delay, self.dt)
                                                           for c in loops])
        u0 = np.array([c.plant.u0 if c.plant.u0 is not None else f for c, f in zip(loops, flow0)])
        self._plant = PlantBank(plants, u0=u0, pv0=[c.plant.pv0 for c in loops])
        rest = [c.plant.rest_flow for c in loops]
        self._plant.reset(flow0 if all(r is None for r in rest) else
                          np.array([f if r is None else r for r, f in zip(rest, flow0)]))

        # set points, modes
        self._sp = np.array([c.sp if c else c_l.plant.pv0 for c, c_l in zip(ctrls, loops)], dtype=float)
        self._sp_steps = [list(c.sp_steps) if c else [] for c in ctrls]
        # time of each loop's next scheduled set-point step (inf: none), so a tick finds the due ones
        # with one vectorised comparison instead of a Python pass over every loop
        self._sp_next = np.array([s[0][0] if s else math.inf for s in self._sp_steps], dtype=float)
        self._pid.reset(self._plant.pv, self._sp, op_init)
        self._controlled = self.has_controller.copy()
        self._op_limits = np.array([c.op_limits if c else (0.0, 100.0) for c in ctrls], dtype=float)
        for i, c in enumerate(ctrls):
            if c is not None and c.mode == "manual":
                self._pid.set_manual(i, op_init[i])

        # disturbances and noise: each loop's streams depend only on its own simulation.seed
        dist = [c.plant.disturbance for c in loops]
        seeds = [c.simulation.seed for c in loops]
        self._dist = DisturbanceBank([d.type for d in dist], dt=self.dt, seed=0, index=seeds,
                                     amplitude=[d.amplitude for d in dist], time=[d.time for d in dist],
                                     period=[d.period if d.period > 0 else 1.0 for d in dist],
                                     phase=[d.phase for d in dist], std=[d.std for d in dist])
        # measurement noise = noise_std * unit normals; the generator exists once any loop has noise
        self.noise_std = np.array([c.plant.noise for c in loops], dtype=float)
        self._seeds = seeds
        self._noise: NoiseBank | None = None
        # the disturbances' step, None when no loop has one (the kinds are fixed by the configs); a bound
        # method, so not part of the bank's state (a snapshot holds the generators themselves)
        self._disturbance = None if all(d.type == "none" for d in dist) else self._dist.step
        #: instructor faults: extra load (% flow added to the plant input) and a valve stuck completely
        self.load = np.zeros(n)
        self.frozen = np.zeros(n, dtype=np.bool_)
        #: sensor faults: a bias added to the measured PV (PV units), and the value a stuck transmitter
        #: shows (NaN: not stuck)
        self.pv_bias = np.zeros(n)
        self.pv_stuck = np.full(n, np.nan)

        # outputs of the current sample
        self.pv = self._plant.pv.copy()           # measured PV at t_k (before the first step: noise-free)
        self.op = op_init.astype(float)
        self.flow = flow0.copy()
        self._u_in = np.zeros(n)
        #: the state above as a few arrays (its attributes are views of their rows): what one compiled call of
        #: :func:`packed_step_kernel` steps; a tuple, which the snapshots do not walk (they find the views)
        self.packed = _pack(self)
        self._valve_args = (self._S, self._J, self._R, self._codes, self._vstate)

    # -- read-only views ------------------------------------------------------------------------------------
    @property
    def t(self) -> float:
        """Simulated time of the next sample to be computed, ``k·dt`` (s)."""
        return self.k * self.dt

    @property
    def sample_time(self) -> float:
        """Simulated time of the values ``op``, ``mv``, ``pv`` now hold (s): the sample last computed."""
        return max(self.k - 1, 0) * self.dt

    @property
    def mv(self) -> np.ndarray:
        return self._vstate[:, MV].copy()

    @property
    def direction(self) -> np.ndarray:
        """The direction each valve last moved in (+1 opening, −1 closing; +1 before any move): the meaning of
        ``valve.initial_direction``, so that ``mv``, ``stuck`` and this are a start ``valve.mv0``,
        ``valve.stuck0`` and ``valve.initial_direction`` reproduce."""
        st = self._vstate
        lag = np.sign((st[:, U_PREV] - st[:, MV]) * (self._S - self._J))   # OP − MV = d(S − J)/2 (Choudhury, He)
        d = np.where(self._codes == MODELS.index("kano"), st[:, DIR], lag)
        return np.where(d == 0.0, 1, d).astype(int)

    @property
    def sp(self) -> np.ndarray:
        return self._sp.copy()

    @property
    def stuck(self) -> np.ndarray:
        return self._vstate[:, STUCK] == 1.0

    @property
    def sat_low(self) -> np.ndarray:
        return self.op <= 0.0

    @property
    def sat_high(self) -> np.ndarray:
        return self.op >= 100.0

    @property
    def auto(self) -> np.ndarray:
        return self._pid.auto & self.has_controller

    @property
    def S(self) -> np.ndarray:
        return self._S.copy()

    @property
    def J(self) -> np.ndarray:
        return self._J.copy()

    @property
    def kc(self) -> np.ndarray:
        return self._pid.kc

    @property
    def ti(self) -> np.ndarray:
        """Integral time (s); inf where there is no integral action."""
        return self._pid.ti

    @property
    def td(self) -> np.ndarray:
        return self._pid.td

    def image_arrays(self) -> tuple[np.ndarray, ...]:
        """What the device's register image shows, as the bank's own arrays (no copies; read only):
        ``op, valve state (n, NSTATE), flow, pv, sp, kc, 1/ti, td, S, J, load, noise_std, controller auto,
        has_controller, frozen``.

        The compiled encoder derives ``mv``, ``stuck``, ``ti``, the saturation flags and ``auto`` from them itself:
        at one loop the properties' copies and numpy expressions cost several times the encoding. They are arrays
        of :attr:`packed` (most of them its rows), changed in place as the bank runs."""
        kc, ti_inv, td, auto = self._pid.live_settings()
        return (self.op, self._vstate, self.flow, self.pv, self._sp, kc, ti_inv, td, self._S, self._J, self.load,
                self.noise_std, auto, self.has_controller, self.frozen)

    # -- commands (the device's instructor and operator writes) -----------------------------------------------
    def set_valve(self, i: int, *, S: float | None = None, J: float | None = None) -> None:
        """Change stiction of loop ``i``; it takes effect at the next sample."""
        newS = self._S[i] if S is None else float(S)
        newJ = self._J[i] if J is None else float(J)
        validate_parameters(newS, newJ, MODELS[self._codes[i]])
        self._S[i], self._J[i] = newS, newJ

    def set_sp(self, i: int, value: float) -> None:
        if not math.isfinite(value):
            raise ValueError(f"sp must be finite, got {value!r}")
        self._sp[i] = value
        self._sp_steps[i] = [s for s in self._sp_steps[i] if s[0] > self.t]
        self._sp_next[i] = self._sp_steps[i][0][0] if self._sp_steps[i] else math.inf

    def set_auto(self, i: int, auto: bool) -> None:
        if auto:
            self._pid.set_auto(i)
        else:
            self._pid.set_manual(i, float(self.op[i]))

    def set_manual_op(self, i: int, op: float) -> None:
        self._pid.set_manual(i, op)

    def set_tuning(self, i: int, *, kc: float | None = None, ti: float | None = None,
                   td: float | None = None) -> None:
        self._pid.set_tuning(i, kc=kc, ti=ti, td=td)

    # -- stepping ---------------------------------------------------------------------------------------------
    def _apply_sp_schedule(self, t: float) -> None:
        for i in np.flatnonzero(self._sp_next <= t + 1e-9 * self.dt):
            steps = self._sp_steps[i]
            while steps and steps[0][0] <= t + 1e-9 * self.dt:
                self._sp[i] = steps.pop(0)[1]
            self._sp_next[i] = steps[0][0] if steps else math.inf

    def _sp_table(self, steps: int) -> np.ndarray:
        """Set point of every loop at each of the next ``steps`` samples (consumes the schedule)."""
        sp = np.empty((steps, self.n))
        sp[:] = self._sp
        times = (self.k + np.arange(steps)) * self.dt
        for i in np.flatnonzero(np.isfinite(self._sp_next)):
            for t_s, value in self._sp_steps[i]:
                sp[times >= t_s - 1e-9 * self.dt, i] = value
            if self._sp_steps[i]:
                done = [s for s in self._sp_steps[i] if s[0] <= times[-1] + 1e-9 * self.dt]
                if done:
                    self._sp[i] = done[-1][1]
                self._sp_steps[i] = [s for s in self._sp_steps[i] if s[0] > times[-1] + 1e-9 * self.dt]
                self._sp_next[i] = self._sp_steps[i][0][0] if self._sp_steps[i] else math.inf
        return sp

    def _unit_noise(self, steps: int) -> np.ndarray:
        """Standard normals of shape (steps, n), from each loop's own stream (zeros while no loop is noisy)."""
        if self._noise is None:
            if not np.any(self.noise_std > 0):
                return np.zeros((steps, self.n))
            self._noise = NoiseBank(np.ones(self.n), 0, index=self._seeds)
        return np.asarray(self._noise.step_many(steps)).reshape(steps, self.n)

    def set_noise(self, i: int, std: float) -> None:
        """Measurement noise of loop ``i`` (PV units); takes effect at the next sample."""
        if not (math.isfinite(std) and std >= 0):
            raise ValueError(f"noise must be >= 0 (PV units), got {std!r}")
        self.noise_std[i] = std

    def set_load(self, i: int, load: float) -> None:
        """Extra load disturbance of loop ``i`` (% flow added to the plant input)."""
        if not math.isfinite(load):
            raise ValueError(f"load must be finite (% flow), got {load!r}")
        self.load[i] = load

    def set_frozen(self, i: int, frozen: bool) -> None:
        """Make valve ``i`` stick completely (``True``) or release it (``False``)."""
        self.frozen[i] = bool(frozen)

    def set_sensor(self, i: int, *, bias: float | None = None, stuck: float | None = None,
                   release: bool = False) -> None:
        """Sensor faults of loop ``i``: measured PV = plant PV + noise + ``bias``, or ``stuck`` (PV units)
        whatever the process does; ``release`` un-sticks the transmitter."""
        if bias is not None:
            if not math.isfinite(bias):
                raise ValueError(f"sensor bias must be finite (PV units), got {bias!r}")
            self.pv_bias[i] = bias
        if stuck is not None:
            if not math.isfinite(stuck):
                raise ValueError(f"sensor stuck value must be finite (PV units), got {stuck!r}")
            self.pv_stuck[i] = stuck
        if release:
            self.pv_stuck[i] = math.nan

    def follow_external(self, external: bool) -> None:
        """Let every valve follow the external OP (``op_external``, :meth:`run`'s ``op``) instead of its
        controller (``True``), or hand the valves back to their controllers (``False``): in auto, continuing
        bumplessly from the OP, PV and set point they have now.

        A closed-loop replay leads in open loop on the recorded OP, then lets the controller take over
        (:mod:`~valve_emulator.simulation.replay`).
        """
        if external:
            self.has_controller[:] = False
            return
        self.has_controller[:] = self._controlled
        self._pid.reset(self.pv, self._sp, np.clip(self.op, self._op_limits[:, 0], self._op_limits[:, 1]))

    def settle_plants(self) -> None:
        """Put every plant at rest for the flow it now receives (valves and controllers keep their state).

        A replay that first runs the valves through a pre-roll (:mod:`~valve_emulator.simulation.replay`)
        starts the plants afresh: an integrating plant would otherwise carry what the pre-roll fed it.
        """
        self._plant.reset(self.flow + self.load)
        self.pv[:] = self._plant.pv

    # -- snapshots --------------------------------------------------------------------------------------------
    #: The fields of :meth:`state` that may hold a non-finite number, and what it means there. Every other
    #: number in the state is finite, so a snapshot holding NaN or infinity elsewhere (a damaged or edited
    #: file) is refused before it is restored rather than stopping the next step.
    NON_FINITE_STATE: ClassVar[dict[str, str]] = {"_sp_next": "inf: no set-point step pending",
                               "pv_stuck": "NaN: the transmitter is not stuck"}

    def dynamic_int_state(self) -> dict[str, tuple[int, int]]:
        """The integer fields of :meth:`state` that change as the bank runs, each with its valid range
        (inclusive). Every other integer field is set by the configuration, so a snapshot must hold the bank's
        own value there. The compiled step indexes its arrays with these without bounds checks: an edited
        snapshot with a ring head of 10**9 would crash the process, so restores check them first."""
        return {"k": (0, 2**62), "_plant/_head": (0, self._plant._buf.shape[1] - 1),
                "_dist/_normals/_pos": (0, NORMALS_BLOCK), "_noise/_normals/_pos": (0, NORMALS_BLOCK)}

    def _nested(self) -> tuple[type, ...]:
        return (PIDBank, PlantBank, DisturbanceBank, NoiseBank, type(self._dist._normals))

    def state(self) -> dict:
        """The complete dynamic state (:func:`valve_emulator.simulation.state.capture`): after
        :meth:`set_state` with it, the bank continues sample for sample as it did from here."""
        return _state.capture(self, self._nested())

    def set_state(self, state: dict) -> None:
        """Restore a :meth:`state` of a bank built from the same configs (``StateMismatch`` otherwise,
        with nothing changed)."""
        _state.restore(self, state, self._nested(),
                       make={"_noise": lambda: NoiseBank(np.ones(self.n), 0, index=self._seeds)})

    def _kernel_args(self) -> tuple:
        pid, plant = self._pid.kernel_args(), self._plant.kernel_args()
        actuator = (self._act_tau, self._act_a, self._act_w, self._act_state)
        return (pid, self._pid.kernel_output(), actuator, self._valve_args, self._char_kind, self._char_r,
                self._flow_limits, plant, self._plant.kernel_output())

    def step(self) -> None:
        """Advance every loop one sample ``dt``; afterwards ``pv``, ``op``, ``mv`` … describe sample k.

        The emulator's lockstep runs one of these per client request, so the work around the compiled step is
        kept to one compiled call of a dozen arguments (:func:`packed_step_kernel` on :attr:`packed`): it
        composes the noise, the sensor faults and the load itself and tells when the set-point schedule or the
        noise streams need Python first; the disturbance generators run only when a loop has a disturbance (as
        :meth:`run` does).
        """
        self.step_by(packed_step_kernel)

    def step_by(self, kernel, *args) -> None:
        """:meth:`step` by the compiled ``kernel(*packed, t, dt, noise_missing, *args)``: :func:`packed_step_kernel`
        itself, or a kernel that calls it first and, only where it returned 0, does more in the same call (the
        device's tick encodes its register image there). It answers as :func:`packed_step_kernel` does."""
        t = self.k * self.dt
        floats = self.packed.floats
        if self._disturbance is not None:
            floats[ROWS.dist] = self._disturbance(t)
        missing = self._noise is None
        if not missing:
            floats[ROWS.unit] = self._unit_noise(1)[0]
        code = kernel(*self.packed, t, self.dt, missing, *args)
        while code in (SP_DUE, NOISE_DUE):   # rare: a set-point step, the first sample of a noisy loop
            if code == SP_DUE:
                self._apply_sp_schedule(t)
            else:
                floats[ROWS.unit] = self._unit_noise(1)[0]   # creates the noise streams
                missing = False
            code = kernel(*self.packed, t, self.dt, missing, *args)
        if code != 0:
            raise ValueError(f"non-finite value in loop step at t = {t} s (code {code})")
        self.k += 1

    def run(self, steps: int, *, sp: np.ndarray | None = None, op: np.ndarray | None = None
            ) -> dict[str, np.ndarray]:
        """Advance ``steps`` samples in one compiled loop; return arrays of shape (steps, n).

        Keys: ``t`` (steps,), ``sp``, ``op``, ``mv``, ``flow``, ``pv``, ``stuck``. The bank's state carries on,
        so ``run(a)`` then ``run(b)`` equals ``run(a + b)`` and equals ``a + b`` calls of :meth:`step`.

        ``sp`` and ``op`` (steps, n), when given, are the set point at every sample (instead of the schedule)
        and the external OP at every sample (instead of the one held since the last write): a recording
        replayed through the loops (:mod:`~valve_emulator.simulation.replay`). Afterwards the bank holds
        their last rows.
        """
        steps = int(steps)
        if (sp is not None or op is not None) and np.isfinite(self.pv_stuck).any():
            raise ValueError("a replayed sp or op cannot be combined with a stuck transmitter")
        if np.isfinite(self.pv_stuck).any():   # a stuck transmitter depends on the plant sample by sample
            return self._run_stepwise(steps)
        times = (self.k + np.arange(steps)) * self.dt
        if sp is None:
            sp = self._sp_table(steps)
        else:
            sp = self._replayed("sp", sp, steps)
            if steps:   # a replayed set point replaces the schedule
                self._sp[:] = sp[-1]
                self._sp_steps = [[] for _ in range(self.n)]
                self._sp_next[:] = math.inf
        if op is not None:
            op = self._replayed("op", op, steps)
            if steps:
                self.op_external[:] = op[-1]
        # loops without disturbance or noise need no per-sample generator calls
        dist = np.zeros((steps, self.n)) if self._disturbance is None else np.ascontiguousarray(
            self._dist.step_many(times)).reshape(steps, self.n)
        dist += self.load
        noise = np.ascontiguousarray(self._unit_noise(steps) * self.noise_std + self.pv_bias)
        # kernel_array, not np.ascontiguousarray: at one step the broadcast view counts as contiguous and would
        # reach the kernel read-only (another argument type, see _replayed)
        op_ext = kernel_array(np.broadcast_to(self.op_external, (steps, self.n))) if op is None else op
        out = {name: np.empty((steps, self.n)) for name in ("pv", "op", "mv", "flow")}
        stuck = np.empty((steps, self.n), dtype=np.bool_)
        pv_meas = np.empty(self.n)
        bad = _run_kernel(sp, noise, dist, op_ext, self.has_controller, self.frozen, *self._kernel_args(),
                          pv_meas, self.op, self.flow, self._u_in, out["pv"], out["op"], out["mv"], out["flow"],
                          stuck)
        if bad >= 0:
            raise ValueError(f"non-finite value in loop step at t = {times[bad]} s")
        self.k += steps
        if steps:
            self.pv[:] = pv_meas
        return {"t": times, "sp": sp, **out, "stuck": stuck}

    def _replayed(self, name: str, values: np.ndarray, steps: int) -> np.ndarray:
        """A replayed input of :meth:`run` as a contiguous, writable (steps, n) float array of finite values.

        Writable: a read-only array (a recording's) is another argument type to numba, which compiled the
        whole time loop (:func:`_run_kernel`, the loop's step and the controller's within it) a second time
        for it (seconds of compiling), for the same numbers."""
        a = np.asarray(values, dtype=float)
        a = a.reshape(-1, 1) if a.ndim == 1 and self.n == 1 else a
        if a.shape != (steps, self.n):
            raise ValueError(f"{name} must have shape ({steps}, {self.n}), got {np.shape(values)}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite")
        return kernel_array(a)

    def _run_stepwise(self, steps: int) -> dict[str, np.ndarray]:
        """:meth:`run` by calls of :meth:`step` (same keys and shapes)."""
        times = (self.k + np.arange(steps)) * self.dt
        rows = {name: np.empty((steps, self.n)) for name in ("sp", "pv", "op", "mv", "flow")}
        stuck = np.empty((steps, self.n), dtype=np.bool_)
        for j in range(steps):
            self.step()
            rows["sp"][j], rows["pv"][j], rows["op"][j] = self._sp, self.pv, self.op
            rows["mv"][j], rows["flow"][j], stuck[j] = self._vstate[:, MV], self.flow, self.stuck
        return {"t": times, **rows, "stuck": stuck}


def _place_valve(state: np.ndarray, valve: ValveConfig, S: float, J: float) -> None:
    """Put one valve's state row (:data:`~valve_emulator.physics.stiction.NSTATE` values) at ``valve.mv0`` (when
    set; else where :func:`~valve_emulator.physics.stiction.initial_state` put it), having last moved in
    ``valve.initial_direction``, stuck or still moving by ``valve.stuck0``.

    Stuck, it is the state :func:`~valve_emulator.physics.stiction.initial_state` gives a valve at rest at the OP
    ``mv0 + d(S − J)/2`` (where it stopped); moving, the valve follows OP at that offset, so OP going on in
    direction ``d`` moves it at once (the Kano and Choudhury machines) instead of after J.
    """
    d = float(valve.initial_direction)
    half = 0.5 * (S - J)
    mv = state[MV] if valve.mv0 is None else valve.mv0
    u = min(max(mv + d * half, 0.0), 100.0)
    model = valve.model
    state[MV], state[U_PREV], state[STILL] = mv, u, 0.0
    state[STUCK] = 1.0 if valve.stuck0 else 0.0
    if model == "he":
        state[REF] = u - mv                     # the residual OP − MV
    elif model == "kano":
        state[REF], state[DIR], state[FLAG] = u, d, 1.0 if valve.stuck0 else 0.0
    else:                                       # choudhury: stuck at u, or sliding with slope d
        state[REF] = u if valve.stuck0 else u - d * S
        state[DIR], state[FLAG] = (0.0, 1.0) if valve.stuck0 else (d, 0.0)


def _flows(characteristics: list[Characteristic], travel: np.ndarray) -> np.ndarray:
    """``characteristics[i].flow(travel[i])`` for every loop: the linear ones (a fleet's usual case) in one
    expression, the others one by one (a power of an array may differ from that of a scalar in the last bit)."""
    linear = np.array([ch.kind == "linear" for ch in characteristics], dtype=bool)
    flow = np.empty(travel.size)
    if linear.any():
        flow[linear] = Characteristic("linear").flow(travel[linear])
    for i in np.flatnonzero(~linear).tolist():
        flow[i] = characteristics[i].flow(travel[i])
    return flow


def _shared(make, args: list[tuple]) -> list:
    """``[make(*a) for a in args]``, calling ``make`` once per distinct ``a`` (hashable, immutable results)."""
    made: dict[tuple, object] = {}
    return [made[a] if a in made else made.setdefault(a, make(*a)) for a in args]


def _shared_batch(make_many, args: list[tuple]) -> list:
    """``make_many(args)``, called once on the distinct ``args`` (hashable, immutable results)."""
    distinct = list(dict.fromkeys(args))
    made = dict(zip(distinct, make_many(distinct)))
    return [made[a] for a in args]


def simulate_loop(config: LoopConfig, duration: float | None = None) -> Recording:
    """Run one loop offline for ``duration`` s (default ``simulation.duration``); deterministic.

    Returns a :class:`~valve_emulator.recordings.recording.Recording` with columns ``t, sp, op, mv, pv`` and the
    extras ``flow`` (%), ``op_ma`` (controller output through the valve's mA table) and ``stuck`` (0/1).
    """
    duration = config.simulation.duration if duration is None else float(duration)
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be > 0 s, got {duration!r}")
    bank = LoopBank([config])
    steps = int(round(duration / bank.dt)) + 1
    out = bank.run(steps)
    table = bank.tables[0]
    return Recording(
        t=out["t"], sp=out["sp"][:, 0], op=out["op"][:, 0], mv=out["mv"][:, 0], pv=out["pv"][:, 0],
        extra={"flow": out["flow"][:, 0], "op_ma": table.to_ma(out["op"][:, 0]),
               "stuck": out["stuck"][:, 0].astype(float)},
        source=config.source or config.name,
    )
