r"""Closed loops as a real plant makes them: an independent simulator for testing the diagnosis.

The diagnosis searches a sampled model (a valve state machine stepped once per sample, a zero-order-hold
plant). Handed data from the package's own simulator, whose discretisation is exactly the search's, it is
right; that proves little about a real plant, which is continuous. This module makes recordings the search did
not make. It shares no code with the searched model: it imports only numpy, scipy and the
:class:`~valve_emulator.recordings.Recording` record, never ``valve_emulator.physics`` or ``.simulation``.

What it models (every sample interval ``dt`` is integrated in ``substeps`` fixed steps, RK4 for the plant):

* **Plants** in continuous time with a dead time that need not be a multiple of ``dt``: first order
  ``K/(τs+1)``, second order ``K/((τ₁s+1)(τs+1))``, integrating ``K/s`` (a level: dh/dt = k·(flow in − flow
  out)) and integrating with a lag ``K/(s(τ₁s+1))``, each ``e^{−θs}``. The plant input is the valve's flow
  plus the load, in % flow, as a deviation from the operating point.
* **The valve**: an actuator first-order lag and a friction element, in either order (``lag_first``: the
  actuator pressure lags OP and the stem sticks on it; ``friction_first``: the stem sticks on OP and the
  travel lags behind). Friction is either the data-driven model of Choudhury, Thornhill & Shah (deadband +
  stickband ``S``, slip jump ``J``, % travel; Control Engineering Practice 13 (2005) 641–658), written here
  from its definition, or a Karnopp force balance (a stem of mass on a spring with static friction above
  kinetic friction, integrated at ``dt/200``) whose static and kinetic bands are ``(S+J)/2`` and ``(S−J)/2``.
  Friction may start at ``onset`` (a healthy valve until then). The flow characteristic is linear or equal
  percentage.
* **The controller**: a positional PI with anti-windup (conditional integration), reverse or direct acting,
  that computes OP at sample ``k`` from the PV sampled at ``k−1``, as a DCS does, and holds it for one sample;
  set-point steps.
* **Loads**: filtered noise, a random walk, a sinusoid; **measurement**: PV noise and A/D quantisation.

:func:`simulate` runs one :class:`Loop` and returns the :class:`~valve_emulator.recordings.Recording` and a
dict of the truth; :func:`draw` draws a loop of a named family (:data:`FAMILIES`) and returns the recording,
the truth and the nominal model a user would believe in (a mapping that
``valve_emulator.config.loop_from_mapping`` accepts: the linear part, the tuning, an ideal valve).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.signal import lfilter

from valve_emulator.recordings import Recording

__all__ = ["FAMILIES", "MATERIAL_S", "Controller", "Load", "Loop", "Measurement", "Plant", "Valve", "draw", "draw_loop",
           "loop_margins", "nominal_mapping", "simulate"]

#: Friction below this S (% travel) is not what a loop's owner calls a sticky valve: a family whose valve has
#: less is expected to be answered "no stiction".
MATERIAL_S = 1.0
PLANT_KINDS = ("fopdt", "sopdt", "integrating", "integrating_lag")
FRICTIONS = ("none", "data_driven", "karnopp")
ORDERS = ("lag_first", "friction_first")


# --- the loop, as frozen records ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Plant:
    """A continuous plant with dead time; PV = ``pv0`` + response to the plant input (% flow deviation).

    ``fopdt``: K/(τs+1); ``sopdt``: K/((τ₁s+1)(τs+1)); ``integrating``: K/s; ``integrating_lag``:
    K/(s(τ₁s+1)); all times e^{−θs} with θ = ``delay`` (s, any real value).
    """

    kind: str
    gain: float
    tau: float = 0.0     # s, the output lag of a self-regulating plant
    lag: float = 0.0     # s, τ₁: the first lag of sopdt and integrating_lag
    delay: float = 0.0   # s
    pv0: float = 50.0

    def __post_init__(self) -> None:
        if self.kind not in PLANT_KINDS:
            raise ValueError(f"plant kind must be one of {PLANT_KINDS}, got {self.kind!r}")
        if self.kind in ("fopdt", "sopdt") and self.tau <= 0:
            raise ValueError("a self-regulating plant needs tau > 0")
        if self.kind in ("sopdt", "integrating_lag") and self.lag <= 0:
            raise ValueError(f"a {self.kind} plant needs lag > 0")

    @property
    def integrating(self) -> bool:
        return self.kind.startswith("integrating")

    @property
    def first_lag(self) -> float:
        """τ₁ when the plant has one, else 0 (the input passes straight to the output stage)."""
        return self.lag if self.kind in ("sopdt", "integrating_lag") else 0.0

    def transfer_function(self) -> tuple[list[float], list[float]]:
        """(num, den), highest power first, without the dead time."""
        out = [1.0, 0.0] if self.integrating else [self.tau, 1.0]   # s  or  τs + 1
        den = np.polymul(out, [self.first_lag, 1.0]) if self.first_lag else np.array(out)
        return [self.gain], [float(c) for c in den]

    def frequency_response(self, w: np.ndarray) -> np.ndarray:
        """G(jω) including the dead time."""
        num, den = self.transfer_function()
        s = 1j * w
        return np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * self.delay)


@dataclass(frozen=True)
class Valve:
    """Actuator lag, friction and flow characteristic. S and J in % travel (2005 convention).

    ``rest_time``: for the data-driven friction, an input that has not changed for longer than this has come
    to rest and the valve sticks (the 2003 paper's "slope zero for two consecutive instants"); None = 1.5 dt.
    ``initial_direction``: the valve starts at rest as if it had just moved this way.
    """

    friction: str = "none"
    S: float = 0.0
    J: float = 0.0
    actuator_lag: float = 0.0       # s, 0 = none
    order: str = "lag_first"
    onset: float = 0.0              # s: healthy before, sticky from then on
    characteristic: str = "linear"  # linear | equal_percentage
    rangeability: float = 50.0
    rest_time: float | None = None
    initial_direction: int = 1

    def __post_init__(self) -> None:
        if self.friction not in FRICTIONS:
            raise ValueError(f"friction must be one of {FRICTIONS}, got {self.friction!r}")
        if self.order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {self.order!r}")
        if self.characteristic not in ("linear", "equal_percentage"):
            raise ValueError(f"characteristic must be linear or equal_percentage, got {self.characteristic!r}")
        if self.S < 0 or self.J < 0 or self.actuator_lag < 0:
            raise ValueError("S, J and actuator_lag must be >= 0")

    @property
    def sticky(self) -> bool:
        return self.friction != "none" and self.S > 0

    def flow(self, travel: float) -> float:
        """Flow, % of full flow, at a travel in %."""
        if self.characteristic == "linear":
            return travel
        return 100.0 * self.rangeability ** (travel / 100.0 - 1.0)


@dataclass(frozen=True)
class Controller:
    """Positional PI, ``op = bias + kc·(e + Σe·dt/ti)``, e = sp − pv (reverse) or pv − sp (direct)."""

    kc: float
    ti: float
    action: str = "reverse"
    sp_steps: tuple[tuple[float, float], ...] = ()   # (time s, new set point)
    op_limits: tuple[float, float] = (0.0, 100.0)


@dataclass(frozen=True)
class Load:
    """A load at the plant input, % flow: ``filtered`` (first-order filtered white noise of standard deviation
    ``size`` and time constant ``tau``), ``random_walk`` (``size`` % per √s), ``sine`` (amplitude ``size``,
    ``period`` s)."""

    kind: str = "none"
    size: float = 0.0
    tau: float = 0.0
    period: float = 0.0


@dataclass(frozen=True)
class Measurement:
    """PV as the A/D converter gives it: Gaussian noise of standard deviation ``noise``, then rounded to a
    multiple of ``quantum`` (0 = no quantisation). PV units."""

    noise: float = 0.0
    quantum: float = 0.0


@dataclass(frozen=True)
class Loop:
    """One closed (or, with ``manual_op``, open) loop. ``op0``: the operating point's travel, where the valve
    and the plant start at rest. ``manual_op``: OP per sample instead of the controller (an open loop)."""

    plant: Plant
    valve: Valve = Valve()
    controller: Controller | None = None
    load: tuple[Load, ...] = ()
    measurement: Measurement = Measurement()
    dt: float = 1.0
    duration: float = 1000.0
    op0: float = 50.0
    sp0: float | None = None        # None: the plant's pv0
    substeps: int = 20
    seed: int = 0
    manual_op: tuple[float, ...] | None = field(default=None, repr=False)

    @property
    def samples(self) -> int:
        return int(round(self.duration / self.dt)) + 1


# --- the valve's friction, from its definitions -------------------------------------------------------------

def _clip(u: float) -> float:
    """``u`` limited to 0..100 % travel (``min(max(u, 0), 100)``)."""
    return 0.0 if u < 0.0 else 100.0 if u > 100.0 else u


class DataDrivenFriction:
    """The stiction of Choudhury, Thornhill & Shah, from its definition, on an input sampled at any rate.

    The valve sticks when its input comes to rest (unchanged for longer than ``rest_time``) or reverses; it
    keeps the input ``u_s`` where it stuck and the direction ``d`` it last moved. Stuck, it slips back when the
    input has moved more than S (deadband + stickband) against ``d``, or on when it has moved more than J
    further along ``d`` (the static friction less the kinetic friction still pushing it). Slipping and moving,
    the output is ``u − d·(S − J)/2``: the slip jump is J. ``u_s`` changes only when it sticks, so noise and a
    held input do not reset it. Before ``onset`` the valve is healthy: output = input.
    """

    def __init__(self, S: float, J: float, u0: float, *, rest_time: float, onset: float, direction: int = 1):
        self.S, self.J, self.rest_time, self.onset = S, J, rest_time, onset
        self.d, self.u_s, self.u_prev = direction, u0, u0
        self.out = u0 if onset > 0 else u0 - direction * (S - J) / 2.0   # where a motion along d left it
        self.stuck, self.rest = True, 0.0

    def __call__(self, u: float, t: float, h: float) -> float:
        u = _clip(u)
        du = u - self.u_prev
        if t < self.onset:
            if du:
                self.d = 1 if du > 0 else -1
            self.u_s = self.out = self.u_prev = u
            return u
        self.rest = self.rest + h if du == 0.0 else 0.0
        if not self.stuck and (self.d * du < 0 or self.rest > self.rest_time):
            self.stuck, self.u_s = True, self.u_prev   # stops or reverses where the input was
        if self.stuck:
            if -self.d * (u - self.u_s) > self.S:
                self.stuck, self.d = False, -self.d    # static friction overcome against the last motion
            elif self.d * (u - self.u_s) > self.J:
                self.stuck = False                     # along it: only the difference to kinetic friction
        if not self.stuck:
            self.out = _clip(u - self.d * (self.S - self.J) / 2.0)
        self.u_prev = u
        return self.out


class KarnoppFriction:
    """A stem of mass on the actuator's spring with Karnopp friction: static band ``fs = (S+J)/2`` above the
    kinetic band ``fc = (S−J)/2`` (forces over the spring rate, % travel), critically damped by viscous
    friction, natural period ``period`` s, integrated by semi-implicit Euler in ``inner`` steps per call.

    Stuck, the stem moves when the spring force ``u − x`` exceeds ``fs``; moving, kinetic friction ``fc``
    opposes the velocity, and the stem sticks again when the velocity changes sign, or falls inside Karnopp's
    zero-velocity band while the force is within ``fs``. Reversing from rest needs the input to change by
    fs + fc = S, continuing by fs − fc = J, and a slip settles at ``u ∓ fc``. (Needs J <= S: kinetic friction
    cannot be negative.)
    """

    def __init__(self, S: float, J: float, u0: float, *, period: float, onset: float, direction: int = 1,
                 inner: int = 10):
        self.fs, self.fc, self.onset, self.inner = (S + J) / 2.0, max(S - J, 0.0) / 2.0, onset, inner
        self.w = 2.0 * math.pi / period
        self.v_zero = 1e-3 * self.w * max(S, 1e-6)     # Karnopp's band of "zero" velocity
        self.x = u0 if onset > 0 else u0 - direction * self.fc
        self.v, self.stuck = 0.0, True

    @property
    def out(self) -> float:
        return self.x

    def __call__(self, u: float, t: float, h: float) -> float:
        u = _clip(u)
        if t < self.onset:
            self.x, self.v, self.stuck = u, 0.0, True
            return u
        if self.stuck and abs(u - self.x) <= self.fs:
            return self.x                             # held by static friction for the whole step
        w2, c, dh = self.w * self.w, 2.0 * self.w, h / self.inner
        x, v_now, stuck, fs, fc, v_zero = self.x, self.v, self.stuck, self.fs, self.fc, self.v_zero   # local names
        for _ in range(self.inner):
            force = u - x
            if stuck:
                if abs(force) <= fs:
                    continue
                stuck = False
                direction = 1.0 if force > 0 else -1.0
            else:
                direction = 1.0 if v_now > 0 else -1.0
            v = v_now + dh * (w2 * (force - fc * direction) - c * v_now)
            if v * direction <= 0.0 or (abs(v) < v_zero and abs(force) <= fs):
                v_now, stuck = 0.0, True          # the velocity reached zero: it sticks
                continue
            v_now = v
            x += dh * v
        self.x, self.v, self.stuck = _clip(x), v_now, stuck
        return self.x


class Pass:
    """A healthy valve stem: travel = input."""

    def __init__(self, u0: float):
        self.out = u0

    def __call__(self, u: float, t: float, h: float) -> float:
        return _clip(u)


def _friction(valve: Valve, u0: float, dt: float) -> DataDrivenFriction | KarnoppFriction | Pass:
    """The valve's friction element, at rest with its input at ``u0``; a Karnopp stem swings with a period of
    half a sample (it settles well within one), a data-driven valve comes to rest after 1.5 samples of a held
    input unless told otherwise."""
    if not valve.sticky:
        return Pass(u0)
    if valve.friction == "karnopp":
        return KarnoppFriction(valve.S, valve.J, u0, period=dt / 2.0, onset=valve.onset,
                               direction=valve.initial_direction)
    rest = 1.5 * dt if valve.rest_time is None else valve.rest_time
    return DataDrivenFriction(valve.S, valve.J, u0, rest_time=rest, onset=valve.onset,
                              direction=valve.initial_direction)


@dataclass(frozen=True)
class _Stem:
    """The valve from OP to stem travel: the friction element and the actuator's first-order lag (time constant
    ``lag``, 0 = none, output ``lag_start`` at first), the lag first or second (the valve's ``order``);
    ``start`` the stem's travel at rest with OP at its starting value. :func:`simulate` steps the lag, exactly
    for an input held over each substep."""

    friction: DataDrivenFriction | KarnoppFriction | Pass
    lag: float
    lag_start: float
    lag_first: bool
    start: float


def _stem(valve: Valve, u0: float, dt: float) -> _Stem:
    """The valve's stem at rest with OP at ``u0``."""
    friction = _friction(valve, u0, dt)
    lag_first = valve.order == "lag_first"
    return _Stem(friction, valve.actuator_lag, u0 if lag_first else friction.out, lag_first, friction.out)


# --- the plant: RK4 over a delayed, piecewise-linear input ---------------------------------------------------

class PlantState:
    """States z = (x₁, y): x₁ the first lag's output (the input itself without one), y the PV deviation;
    ż = A z + B u. One RK4 step of length h is linear in z and in the input at its start, middle and end, so
    its matrices are worked out once (the classical RK4 formula applied to unit vectors) and each step is a
    few multiplications (:func:`simulate`: ``z ← m·z + b_start·u_start + b_mid·u_mid + b_end·u_end``)."""

    def __init__(self, plant: Plant, h: float):
        tau1 = plant.first_lag
        # ẏ = K·x₁ (integrating) or (K·x₁ − y)/τ; without a first lag x₁ is the input u
        drive, leak = (plant.gain, 0.0) if plant.integrating else (plant.gain / plant.tau, 1.0 / plant.tau)
        if tau1:
            A, B = np.array([[-1.0 / tau1, 0.0], [drive, -leak]]), np.array([1.0 / tau1, 0.0])
        else:
            A, B = np.array([[0.0, 0.0], [0.0, -leak]]), np.array([0.0, drive])
        M = np.column_stack([_rk4(A, B, e, h, 0.0, 0.0, 0.0) for e in np.eye(2)])
        inputs = [_rk4(A, B, np.zeros(2), h, *e) for e in np.eye(3)]
        self.m = [float(v) for v in M.ravel()]
        self.b = [[float(v) for v in col] for col in inputs]   # start, middle, end


def _rk4(A: np.ndarray, B: np.ndarray, z: np.ndarray, h: float, u0: float, um: float, u1: float) -> np.ndarray:
    """One classical Runge–Kutta step of ż = A z + B u, the input given at the step's start, middle and end."""
    k1 = A @ z + B * u0
    k2 = A @ (z + h / 2 * k1) + B * um
    k3 = A @ (z + h / 2 * k2) + B * um
    k4 = A @ (z + h * k3) + B * u1
    return z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def _delayed(line: list[float], pos: float, newest: int) -> float:
    """The plant input read θ late: at substep position ``pos`` (fractional: the reading's position less θ in
    substeps) on ``line``, the input's history on the substep grid pushed up to index ``newest``, interpolated
    linearly; the input before the start is the starting value, 0, and none is read beyond the newest."""
    pos = newest if newest < pos else pos
    if pos < 0:
        return 0.0
    i = int(pos)
    frac = pos - i
    return line[i] if frac == 0 or i >= newest else line[i] * (1 - frac) + line[i + 1] * frac


# --- loads, measurement, controller --------------------------------------------------------------------------

def _load_series(loads: tuple[Load, ...], t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The summed load on the substep times ``t`` (% flow)."""
    total = np.zeros_like(t)
    h = t[1] - t[0]
    for load in loads:
        if load.kind == "sine":
            total += load.size * np.sin(2 * math.pi * t / load.period + rng.uniform(0, 2 * math.pi))
        elif load.kind == "random_walk":
            total += np.concatenate([[0.0], np.cumsum(rng.normal(0, load.size * math.sqrt(h), t.size - 1))])
        elif load.kind == "filtered":
            a = math.exp(-h / load.tau)
            e = rng.normal(0, load.size * math.sqrt(1 - a * a), t.size)
            e[0] = 0.0
            total += lfilter([1.0], [1.0, -a], e)   # an AR(1) at the substep rate: a first-order filter, exact
        elif load.kind != "none":
            raise ValueError(f"load kind must be none, filtered, random_walk or sine, got {load.kind!r}")
    return total


class PI:
    """Positional PI with anti-windup: at a limit, with the error pushing further, the integral grows only up
    to where OP reaches the limit (never beyond), so OP leaves the limit as soon as the error turns."""

    def __init__(self, c: Controller, bias: float, dt: float):
        self.c, self.bias, self.dt, self.integral = c, bias, dt, 0.0
        self.sign = 1.0 if c.action == "reverse" else -1.0

    def __call__(self, sp: float, pv: float) -> float:
        lo, hi = self.c.op_limits
        e = self.sign * (sp - pv)
        integral = self.integral + e * self.dt / self.c.ti
        raw = self.bias + self.c.kc * (e + integral)
        if raw > hi and e > 0:
            integral = max(self.integral, (hi - self.bias) / self.c.kc - e)
        elif raw < lo and e < 0:
            integral = min(self.integral, (lo - self.bias) / self.c.kc - e)
        raw = self.bias + self.c.kc * (e + integral)
        self.integral = integral
        return min(max(raw, lo), hi)


def set_point(loop: Loop, t: np.ndarray) -> np.ndarray:
    """The set point at the sample times: ``sp0`` (or the plant's ``pv0``), then each step from its time on."""
    sp = np.full(t.size, loop.plant.pv0 if loop.sp0 is None else loop.sp0)
    for when, value in loop.controller.sp_steps if loop.controller else ():
        sp[t >= when] = value
    return sp


# --- the simulation ------------------------------------------------------------------------------------------

def simulate(loop: Loop, *, record_mv: bool = False) -> tuple[Recording, dict]:
    """Run the loop; returns the recording (``t, sp, op, pv``, and ``mv`` when ``record_mv``) and the truth.

    At sample k: PV is measured (noise, quantisation); OP is the controller's answer to the PV measured at
    k−1 (``op0`` at k = 0), or ``manual_op[k]``; OP is then held while valve and plant run ``substeps``
    fixed steps to the next sample. ``mv`` is the stem travel at the sample instant, after the valve has
    seen that sample's OP. The truth: ``sticky`` (friction of at least :data:`MATERIAL_S`), ``S`` and ``J``
    (0 for a healthy valve), every parameter of the loop (``valve``, ``plant``, ``controller``, ``load``,
    ``measurement``, ``dt``), and per sample the stem travel ``mv`` and the load ``load_series``.
    """
    n, m, dt = loop.samples, loop.substeps, loop.dt
    h = dt / m
    rng = np.random.default_rng(loop.seed)
    t = np.arange(n) * dt
    load = _load_series(loop.load, np.arange(n * m + 1) * h, rng)
    noise = rng.normal(0.0, loop.measurement.noise, n) if loop.measurement.noise else np.zeros(n)
    sp = set_point(loop, t)
    stem = _stem(loop.valve, loop.op0, dt)
    u_eq = loop.valve.flow(stem.start)   # the plant starts at rest at the stem's starting travel
    pi = PI(loop.controller, loop.op0, dt) if loop.controller and loop.manual_op is None else None
    op, pv, mv = np.empty(n), np.empty(n), np.empty(n)
    q = loop.measurement.quantum
    # The substep loop is most of a draw's time (48,000 substeps for 2,400 samples): it runs on local names,
    # the actuator's lag and the plant's step written out.
    friction, lag_first, tau = stem.friction, stem.lag_first, stem.lag
    pull = 1.0 - math.exp(-h / tau) if tau > 0 else 0.0   # the lag's step: the same h every substep
    y_lag = stem.lag_start
    linear, flow = loop.valve.characteristic == "linear", loop.valve.flow
    plant = PlantState(loop.plant, h)
    (m00, m01, m10, m11), ((b00, b01), (bm0, bm1), (b10, b11)) = plant.m, plant.b
    x1 = y = 0.0
    line, late, last = [0.0] * (n * m + 1), loop.plant.delay / h, n * m
    # With θ over one substep, the input at i + 1 that step i reads is the one step i + 1 reads at its start:
    # the same position, i + 1 - θ < i, between values pushed before either step.
    carry = late > 1
    u1 = 0.0
    loads = load.tolist()
    pv0 = loop.plant.pv0
    for k in range(n):
        value = pv0 + y + noise[k]
        pv[k] = q * round(value / q) if q else value
        if loop.manual_op is not None:
            op[k] = loop.manual_op[k]
        else:
            op[k] = loop.op0 if k == 0 or pi is None else pi(sp[k], pv[k - 1])
        u = float(op[k])
        for j in range(m):
            i = k * m + j
            ti = i * h
            if lag_first:
                y_lag = y_lag + (u - y_lag) * pull if tau > 0 else u
                x = friction(y_lag, ti, h)
            else:
                y_lag = y_lag + (friction(u, ti, h) - y_lag) * pull if tau > 0 else friction(u, ti, h)
                x = y_lag
            if j == 0:
                mv[k] = x
            line[i] = (x if linear else flow(x)) - u_eq + loads[i]
            if i + 1 >= last:
                break
            # one RK4 step over the input at substeps i, i + 1/2 and i + 1, read θ late
            u0 = u1 if carry and i else _delayed(line, i - late, i)
            um = _delayed(line, i + 0.5 - late, i)
            u1 = _delayed(line, i + 1 - late, i)
            x1, y = (m00 * x1 + m01 * y + b00 * u0 + bm0 * um + b10 * u1,
                     m10 * x1 + m11 * y + b01 * u0 + bm1 * um + b11 * u1)
    recording = Recording(t=t, sp=sp, op=op, mv=mv if record_mv else None, pv=pv, source="independent")
    truth = {"sticky": loop.valve.sticky and loop.valve.S >= MATERIAL_S, "S": loop.valve.S if loop.valve.sticky
             else 0.0, "J": loop.valve.J if loop.valve.sticky else 0.0, "valve": asdict(loop.valve),
             "plant": asdict(loop.plant), "controller": None if loop.controller is None else asdict(loop.controller),
             "load": [asdict(x) for x in loop.load], "measurement": asdict(loop.measurement), "dt": dt,
             "mv": mv, "load_series": load[::m][:n]}
    return recording, truth


# --- margins of the nominal loop -----------------------------------------------------------------------------

def _pi_response(kc: float, ti: float, w: np.ndarray) -> np.ndarray:
    return kc * (1.0 + 1.0 / (1j * w * ti))


def loop_margins(plant: Plant, kc: float, ti: float, extra_delay: float) -> dict:
    """Ms, gain margin and phase margin (deg) of the continuous loop PI·G·e^{−s·extra_delay}.

    ``extra_delay`` is what sampling adds to the plant's own dead time: 1.5 dt for a PI that acts one sample
    late and holds its output (one sample, plus half a sample of hold).
    """
    w = np.logspace(-5, 2, 200_000) / max(plant.delay + extra_delay, plant.tau, plant.lag, 1e-3)
    loop = _pi_response(kc, ti, w) * plant.frequency_response(w) * np.exp(-1j * w * extra_delay)
    loop = loop * (1.0 if plant.gain > 0 else -1.0)
    phase = np.unwrap(np.angle(loop))
    cross = np.flatnonzero((phase[:-1] > -math.pi) & (phase[1:] <= -math.pi))
    gm = 1.0 / abs(loop[cross[0]]) if cross.size else math.inf
    unit = np.flatnonzero((abs(loop[:-1]) >= 1.0) & (abs(loop[1:]) < 1.0))
    pm = math.degrees(math.pi + phase[unit[0]]) if unit.size else math.inf
    return {"Ms": float(np.max(1.0 / np.abs(1.0 + loop))), "GM": float(gm), "PM": float(pm)}


def _kc_for_gain_margin(plant: Plant, ti: float, extra_delay: float, gm: float) -> float:
    """The Kc that gives the loop the gain margin ``gm`` (Ti fixed: the phase does not depend on Kc)."""
    margins = loop_margins(plant, 1.0, ti, extra_delay)
    return margins["GM"] / gm


# --- the families ---------------------------------------------------------------------------------------------

def _simc(plant: Plant, dt: float, rng: np.random.Generator, speed: tuple[float, float] = (1.0, 2.0)) -> tuple:
    """SIMC PI (Skogestad 2003) for the plant seen through a sampled PI (1.5 dt more dead time); the closed-loop
    time constant τc is drawn as a multiple of the effective dead time."""
    theta = plant.delay + 1.5 * dt
    if plant.kind == "sopdt":
        theta += plant.lag / 2.0             # the half rule
    if plant.kind == "integrating_lag":
        theta += plant.lag
    tc = rng.uniform(*speed) * theta
    k = abs(plant.gain)
    if plant.integrating:
        return 1.0 / (k * (tc + theta)), 4.0 * (tc + theta)
    tau = plant.tau + (plant.lag / 2.0 if plant.kind == "sopdt" else 0.0)
    return tau / (k * (tc + theta)), min(tau, 4.0 * (tc + theta))


def _controller(plant: Plant, kc: float, ti: float, steps: tuple) -> Controller:
    return Controller(kc=kc, ti=ti, action="reverse" if plant.gain > 0 else "direct", sp_steps=steps)


def _sp_steps(rng: np.random.Generator, duration: float, size: float, every: float) -> tuple:
    times = np.arange(every * rng.uniform(0.3, 0.7), duration * 0.95, every)
    levels = 50.0 + size * rng.choice([-1.0, 1.0], times.size) * rng.uniform(0.5, 1.0, times.size)
    return tuple((float(a), float(b)) for a, b in zip(times, levels))


def _sign(rng: np.random.Generator) -> float:
    return float(rng.choice([-1.0, 1.0]))


def _friction_draw(rng: np.random.Generator, S: tuple[float, float], jr: tuple[float, float], dt: float,
                   *, lag: float | None = None, onset: float = 0.0) -> Valve:
    S_ = float(rng.uniform(*S))
    tau = float(rng.uniform(0.3, 1.5) * dt) if lag is None else lag
    friction = str(rng.choice(["data_driven", "karnopp"]))
    J = float(S_ * rng.uniform(*jr))
    return Valve(friction=friction, S=S_, J=min(J, S_) if friction == "karnopp" else J,  # Karnopp: J <= S
                 actuator_lag=tau if rng.random() < 0.5 or lag is not None else 0.0,
                 order=str(rng.choice(ORDERS)), onset=onset)


def _level(rng: np.random.Generator, dt: float) -> Plant:
    kind = str(rng.choice(["integrating", "integrating_lag"]))
    return Plant(kind=kind, gain=_sign(rng) * float(rng.uniform(0.01, 0.05)),
                 lag=float(rng.uniform(2.0, 10.0)) if kind == "integrating_lag" else 0.0,
                 delay=float(rng.uniform(0.0, 4.0)))


def _self_regulating(rng: np.random.Generator, tau: tuple[float, float], delay: tuple[float, float]) -> Plant:
    kind = str(rng.choice(["fopdt", "sopdt"]))
    t = float(rng.uniform(*tau))
    return Plant(kind=kind, gain=_sign(rng) * float(rng.uniform(0.5, 2.5)), tau=t,
                 lag=float(rng.uniform(0.1, 0.5) * t) if kind == "sopdt" else 0.0, delay=float(rng.uniform(*delay)))


def _level_sticky(rng):
    dt, duration = 1.0, 2400.0
    plant = _level(rng, dt)
    kc, ti = _simc(plant, dt, rng)
    loop = Loop(plant=plant, valve=_friction_draw(rng, (1.0, 6.0), (0.0, 1.2), dt),
                controller=_controller(plant, kc, ti, _sp_steps(rng, duration, 2.0, 800.0)),
                load=(Load("random_walk", size=0.02),), measurement=Measurement(noise=float(rng.uniform(0.02, 0.1))),
                dt=dt, duration=duration)
    return loop, {"expected": "stiction"}


def _late_onset(rng):
    dt, duration = 1.0, 3000.0
    plant = _level(rng, dt) if rng.random() < 0.5 else _self_regulating(rng, (5.0, 30.0), (1.0, 8.0))
    kc, ti = _simc(plant, dt, rng)
    onset = float(rng.uniform(0.2, 0.8) * duration)
    loop = Loop(plant=plant, valve=_friction_draw(rng, (2.0, 6.0), (0.2, 1.0), dt, onset=onset),
                controller=_controller(plant, kc, ti, _sp_steps(rng, duration, 2.0, 600.0)),
                load=(Load("filtered", size=0.5, tau=50.0),),
                measurement=Measurement(noise=float(rng.uniform(0.02, 0.1))), dt=dt, duration=duration)
    return loop, {"expected": "stiction", "onset": onset}


def _aggressive_pi(rng):
    dt, duration = 1.0, 2400.0
    plant = _self_regulating(rng, (10.0, 40.0), (2.0, 10.0))
    ti = float(rng.uniform(0.5, 1.0) * (plant.tau + plant.first_lag))
    gm = float(rng.uniform(1.2, 1.6))
    kc = _kc_for_gain_margin(plant, ti, 1.5 * dt, gm)
    loop = Loop(plant=plant, valve=Valve(), controller=_controller(plant, kc, ti, _sp_steps(rng, duration, 2.0, 400.0)),
                load=(Load("filtered", size=1.0, tau=30.0),),
                measurement=Measurement(noise=float(rng.uniform(0.01, 0.05))), dt=dt, duration=duration)
    return loop, {"expected": "no_stiction", "tuning": True, "margins": loop_margins(plant, kc, ti, 1.5 * dt),
                  "margins_extra_delay": 1.5 * dt}


def _slow_noisy_valve(rng):
    dt, duration = 1.0, 2400.0
    plant = _self_regulating(rng, (5.0, 30.0), (1.0, 6.0))
    kc, ti = _simc(plant, dt, rng, speed=(1.5, 3.0))
    valve = _friction_draw(rng, (0.2, 0.6), (0.0, 0.5), dt, lag=float(rng.uniform(3.0, 10.0)))
    loop = Loop(plant=plant, valve=valve, controller=_controller(plant, kc, ti, _sp_steps(rng, duration, 3.0, 400.0)),
                load=(Load("filtered", size=1.0, tau=40.0),),
                measurement=Measurement(noise=float(rng.uniform(0.1, 0.3))), dt=dt, duration=duration)
    return loop, {"expected": "no_stiction"}


def _coarse_ad(rng):
    dt, duration = 1.0, 2400.0
    plant = _level(rng, dt) if rng.random() < 0.5 else _self_regulating(rng, (5.0, 30.0), (1.0, 6.0))
    kc, ti = _simc(plant, dt, rng)
    loop = Loop(plant=plant, controller=_controller(plant, kc, ti, _sp_steps(rng, duration, 3.0, 600.0)),
                load=(Load("random_walk", size=0.05),),
                measurement=Measurement(noise=0.02, quantum=float(rng.uniform(0.2, 0.5))), dt=dt, duration=duration)
    return loop, {"expected": "no_stiction"}


def _flow(rng):
    return Plant(kind="fopdt", gain=_sign(rng) * float(rng.uniform(0.5, 2.0)), tau=float(rng.uniform(1.0, 4.0)),
                 delay=float(rng.uniform(0.0, 1.5)))


def _flow_sticky(rng):
    dt, duration = 0.5, 1500.0
    plant = _flow(rng)
    kc, ti = _simc(plant, dt, rng)
    loop = Loop(plant=plant, valve=_friction_draw(rng, (1.0, 5.0), (0.2, 1.2), dt),
                controller=_controller(plant, kc, ti, _sp_steps(rng, duration, 3.0, 300.0)),
                load=(Load("filtered", size=0.5, tau=20.0),),
                measurement=Measurement(noise=float(rng.uniform(0.02, 0.1))), dt=dt, duration=duration)
    return loop, {"expected": "stiction"}


def _healthy_flow(rng):
    dt, duration = 0.5, 1500.0
    plant = _flow(rng)
    kc, ti = _simc(plant, dt, rng)
    loop = Loop(plant=plant, controller=_controller(plant, kc, ti, _sp_steps(rng, duration, 3.0, 300.0)),
                load=(Load("sine", size=float(rng.uniform(1.0, 5.0)), period=float(rng.uniform(10.0, 60.0))),),
                measurement=Measurement(noise=float(rng.uniform(0.02, 0.1))), dt=dt, duration=duration)
    return loop, {"expected": "no_stiction"}


def _healthy_level(rng):
    loop, _ = _level_sticky(rng)
    return replace(loop, valve=Valve()), {"expected": "no_stiction"}


FAMILIES: dict[str, Callable] = {
    "level_sticky": _level_sticky, "late_onset": _late_onset, "aggressive_pi": _aggressive_pi,
    "slow_noisy_valve": _slow_noisy_valve, "coarse_ad": _coarse_ad, "flow_sticky": _flow_sticky,
    "healthy_flow": _healthy_flow, "healthy_level": _healthy_level,   # a new family goes last: draws keep their entropy
}
"""Named families of loops; :func:`draw` documents what each holds."""


def nominal_mapping(loop: Loop, name: str) -> dict:
    """The loop a user believes in, as a loop-config mapping: the plant's linear part (its transfer function,
    dead time and operating point), the tuning, and an ideal linear valve — no friction, no actuator lag."""
    num, den = loop.plant.transfer_function()
    c = loop.controller
    return {
        "name": name,
        "description": f"nominal model of an independent {name} loop: the linear part, an ideal valve",
        "valve": {"S": 0.0, "J": 0.0, "op0": loop.op0},
        "plant": {"num": num, "den": den, "delay": loop.plant.delay, "pv0": loop.plant.pv0, "u0": loop.op0,
                  "pv_range": [loop.plant.pv0 - 100.0, loop.plant.pv0 + 100.0], "noise": loop.measurement.noise},
        "controller": {"kc": c.kc, "ti": c.ti, "sp": loop.plant.pv0, "bias": loop.op0, "action": c.action,
                       "sp_steps": [list(s) for s in c.sp_steps]},
        "simulation": {"dt": loop.dt, "duration": loop.duration, "seed": 0},
    }


def draw_loop(family: str, rng: np.random.Generator) -> tuple[Loop, dict]:
    """The loop :func:`draw` simulates, with its seed, and the family's extra truth (``expected``, ``onset``, ...):
    the same loop can be run again changed in one part (a valve healthy throughout, to see what its friction
    changes in the recording)."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; known: {', '.join(FAMILIES)}")
    loop, extra = FAMILIES[family](rng)
    return replace(loop, seed=int(rng.integers(2**31))), extra


def draw(family: str, rng: np.random.Generator) -> tuple[Recording, dict, dict]:
    """One loop of ``family``: (recording, truth, nominal model mapping).

    Families: ``level_sticky`` (an integrating plant, with or without a lag, dead time, SIMC PI, sticky valve:
    S 1–6 %, J 0–1.2 S); ``late_onset`` (stiction S 2–6 % starting in the middle 60 % of the record);
    ``aggressive_pi`` (a healthy valve, a PI tuned to a gain margin of 1.2–1.6; the truth's ``margins`` are
    Ms, GM and PM of the continuous loop with the sampling's 1.5 dt of dead time); ``slow_noisy_valve``
    (actuator lag 3–10 s, friction S 0.2–0.6 %, noisy PV; expected "no stiction": S below
    :data:`MATERIAL_S`); ``coarse_ad`` (a healthy valve, PV quantised to 0.2–0.5, a drifting load);
    ``flow_sticky`` (a fast first-order flow loop, S 1–5 %, J 0.2–1.2 S); ``healthy_flow`` (the same
    loop, a healthy valve, a load oscillating with a 10–60 s period); ``healthy_level`` (a ``level_sticky``
    loop with a healthy valve: a PI on an integrating plant under a wandering load). Friction is data-driven or
    Karnopp, with or without an actuator lag, in either order, drawn. The truth has ``expected`` (``stiction`` or
    ``no_stiction``), ``tuning`` (True where aggressive tuning is the cause), S, J and every parameter.
    """
    loop, extra = draw_loop(family, rng)
    recording, truth = simulate(loop)
    truth = {**truth, "family": family, "tuning": False, **extra}
    return replace(recording, source=f"independent:{family}"), truth, nominal_mapping(loop, family)
