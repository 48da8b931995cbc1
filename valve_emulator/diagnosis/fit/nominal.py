r"""The nominal model: the simulation the user believes in, or, without one, a linear model from the data.

From a loop config (:class:`~valve_emulator.config.LoopConfig`) we take the plant ``num/den·e^{−θs}``, the
valve (its stiction model, rest criterion, and S, J — usually 0) and its flow characteristic. The
controller is not needed: the diagnosis replays the *recorded* OP, so the loop is cut at the valve.

Replay (``fit_before``): the nominal chain driven by the recorded OP, the plant simulated exactly by the
physics layer's ZOH kernel. Only the operating point is fitted, on the fit part: the PV offset and, for an
integrating plant, the operating-point flow ``u0`` (a ramp); a recording's operating point is not physics.

Without a model (:func:`identify`) the linear part is chosen from data between first order plus dead
time and integrator plus dead time (the two low-order families of process control; Seborg et al.,
*Process Dynamics and Control*, ch. 7), each with its time constant and dead time searched on a grid and
refined by output error; BIC picks the family, unless it was declared. Both are fitted under the closed
loop's constraints (:mod:`~valve_emulator.diagnosis.fit.closed_loop`: the gain's sign from the controller's
action, time constants of at least a sample), so the controller's inverse is never the plant.
The other family is kept as an alternative that every candidate search also tries, because a missing valve
nonlinearity can make the wrong family look better on OP → PV (stiction turns a triangular OP into a
square-wave flow).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numba
import numpy as np

from valve_emulator.config import LoopConfig
from valve_emulator.diagnosis.fit.closed_loop import Identification, setpoint_part
from valve_emulator.diagnosis.fit.cost import bic
from valve_emulator.diagnosis.fit.data import Problem
from valve_emulator.diagnosis.fit.linear import (
    LinearFit,
    LinearStructure,
    highpass,
    input_grid_sse,
    polish,
)
from valve_emulator.errors import UserError
from valve_emulator.physics.plant import PlantBank, plant_step_kernel, transfer_function_to_zoh
from valve_emulator.physics.signal_chain import DEFAULT_RANGEABILITY
from valve_emulator.physics.stiction import rest_samples_for

__all__ = ["Nominal", "nominal_from_config", "identify", "identify_before", "replay_plant"]


@dataclass(frozen=True)
class Nominal:
    """What the diagnosis starts from.

    Attributes
    ----------
    structure : linear structure (poles, integrator, dead time) of the nominal plant.
    given : True when it came from a loop config; False when identified from the data.
    num, den : the nominal transfer function (config only), for the exact replay.
    valve_model, rest_samples, S, J : the nominal valve.
    characteristic : ``(kind, rangeability)`` of the nominal valve.
    alternates : other linear structures every candidate search also tries (identified models only).
    identification : the closed-loop constraints the linear part was identified under (identified models only).
    """

    structure: LinearStructure
    given: bool
    num: tuple[float, ...] = ()
    den: tuple[float, ...] = ()
    valve_model: str = "kano"
    rest_samples: int = 1
    S: float = 0.0
    J: float = 0.0
    characteristic: tuple[str, float] = ("linear", DEFAULT_RANGEABILITY)
    alternates: tuple[LinearStructure, ...] = field(default=())
    identification: Identification | None = None

    @property
    def delay(self) -> float:
        return self.structure.delay

    @property
    def settle_time(self) -> float:
        """About four times the slowest time constant (s)."""
        slow = max(self.structure.taus, default=0.0)
        for p in self.structure.fixed_poles:
            slow = max(slow, -1.0 / min(np.real(p), -1e-12))
        return 4.0 * slow


def nominal_from_config(cfg: LoopConfig, dt: float) -> Nominal:
    """The nominal model of a loop config, for a recording sampled every ``dt`` s.

    Raises
    ------
    UserError
        A plant the linear part cannot represent: more than one pole at the origin, or an unstable pole.
    """
    den = np.trim_zeros(np.asarray(cfg.plant.den, dtype=float), "f")
    zeros = 0
    while den.size > 1 and den[-1] == 0.0:
        den = den[:-1]
        zeros += 1
    if zeros > 1:
        raise UserError(f"{cfg.source or cfg.name}: plant.den has {zeros} poles at s = 0; the diagnosis "
                        "handles at most one integrator")
    roots = np.roots(den) if den.size > 1 else np.array([])
    if np.any(np.real(roots) >= 0):
        raise UserError(f"{cfg.source or cfg.name}: plant.den has an unstable pole "
                        f"{roots[np.real(roots) >= 0][0]:.4g}; the diagnosis needs a stable plant")
    real = roots[np.abs(np.imag(roots)) < 1e-9 * np.maximum(1.0, np.abs(roots))]
    cplx = roots[np.abs(np.imag(roots)) >= 1e-9 * np.maximum(1.0, np.abs(roots))]
    structure = LinearStructure(taus=tuple(sorted(float(-1.0 / np.real(r)) for r in real)),
                                integrating=zeros == 1, fixed_poles=tuple(complex(r) for r in cplx),
                                delay=float(cfg.plant.delay))
    v = cfg.valve
    return Nominal(structure, True, tuple(cfg.plant.num), tuple(cfg.plant.den), v.model,
                   rest_samples_for(v.rest_time, dt), v.S, v.J, (v.characteristic, v.rangeability))


@numba.njit(cache=True)
def _run_plant(u, u0, pv0, A, B0, B1, C, D, m, buf, head, x, ud, pv, work, out):  # pragma: no cover
    one = np.empty(1)
    out[0] = pv[0]
    for k in range(u.shape[0] - 1):
        one[0] = u[k]
        plant_step_kernel(one, u0, pv0, A, B0, B1, C, D, m, buf, head, x, ud, pv, work)
        out[k + 1] = pv[0]


def replay_plant(nominal: Nominal, flow: np.ndarray, dt: float) -> np.ndarray:
    """Deviation PV of the nominal plant for the flow sequence, started at rest at ``flow[0]``.

    Uses the physics layer's exact ZOH discretisation and its compiled step kernel, so this is the same
    plant the simulator runs.
    """
    plant = transfer_function_to_zoh(nominal.num, nominal.den, nominal.delay, dt)
    bank = PlantBank([plant], u0=float(flow[0]), pv0=0.0)
    out = np.empty(flow.shape[0])
    _run_plant(np.ascontiguousarray(flow, dtype=float), *bank.kernel_args(), out)
    return out


def _family_fits(problem: Problem, u: np.ndarray, integrating: bool, sign: int) -> LinearFit:
    """Best fit of one family over a time-constant grid × the dead-time grid, then polished (the gain's
    sign held to ``sign`` when nonzero, time constants at least a sample)."""
    dt = problem.dt
    if integrating:
        taus_grid = [()]
    else:
        taus_grid = [(float(t),) for t in np.geomspace(dt, max(2 * dt, problem.T * dt / 10.0), 28)]
    best = (np.inf, None, 0)
    lam = problem.prefilter
    target = problem.y if lam is None else highpass(problem.y, lam)
    for taus in taus_grid:
        st = LinearStructure(taus=taus, integrating=integrating, sign=sign, min_tau=dt)
        sse = input_grid_sse(u, target, problem.train, problem.delays, st, dt, prefilter=lam)[0]
        i = int(np.argmin(sse))
        if sse[i] < best[0]:
            best = (float(sse[i]), st, int(problem.delays[i]))
    st = LinearStructure(taus=best[1].taus, integrating=integrating, delay=best[2] * dt, sign=sign, min_tau=dt)
    return polish(u, problem.y, problem.train, st, dt, free_delay=True,
                  delay_bounds=(0.0, float(problem.delays.max()) * dt), prefilter=lam)


def identify(problem: Problem, *, valve_model: str = "kano", rest_samples: int = 1,
             constraints: Identification | None = None) -> Nominal:
    """Linear model (FOPDT or IPDT, chosen by BIC unless ``constraints`` declare the family) from OP to PV,
    with a linear, stiction-free valve, under the closed loop's ``constraints`` (default: none but causality)."""
    constraints = constraints or Identification()
    u = np.asarray(problem.op, dtype=float)
    families = (False, True) if constraints.integrating is None else (constraints.integrating,)
    fits = [_family_fits(problem, u, integrating, constraints.sign) for integrating in families]
    n = problem.n_fit
    scores = [bic(f.sse, n, f.structure.n_params() + 1) for f in fits]  # + 1: the dead time
    order = np.argsort(scores)
    best = fits[order[0]]
    alternates = tuple(fits[i].structure for i in order[1:])
    return Nominal(best.structure, False, valve_model=valve_model, rest_samples=rest_samples,
                   alternates=alternates, identification=constraints)


def identify_before(problem: Problem, sp: np.ndarray | None, end: int, *,
                    constraints: Identification | None = None) -> Nominal | None:
    """The linear model of :func:`identify` fitted on the fit part before sample ``end`` (where the loop is
    still linear: a valve that starts to stick there is healthy before it), from OP's part that the set point
    explains (:func:`~valve_emulator.diagnosis.fit.closed_loop.setpoint_part`, the two-stage method); None where
    the set point does not move enough before ``end`` to tell.

    Why not from OP itself: under a wandering load the controller moves OP to cancel the load while PV holds
    its set point, so PV fitted from OP by output error is biased (on the independent ``late_onset`` loops
    the dead time of the healthy part came out 10–44 s for 1–7 s behind a lag); the set point is independent
    of the load, and so is OP's part that it drives."""
    w0 = problem.train[0]
    driven = setpoint_part(problem.op, sp, end, start=w0)
    if driven is None:
        return None
    healthy = replace(problem, op=driven, train=(w0, min(end, problem.train[1])))
    return identify(healthy, constraints=constraints)
