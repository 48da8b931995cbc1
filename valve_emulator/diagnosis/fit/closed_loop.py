r"""What a closed loop tells the identification of its plant: the controller's action and the plant's family.

A recording of a loop under control holds two relations between OP and PV: the plant's (PV follows OP) and
the controller's (OP follows PV). Fitted without care, "PV from OP" can lock onto the second one run
backwards — for a PI, :math:`\mathrm{PV} \approx \mathrm{SP} - \mathrm{OP}/K_c`, a fast plant whose gain has
the sign opposite to the true one (Ljung, *System Identification*, 2nd ed., §13.4: the direct method is
consistent only when the model cannot represent that inverse). Three things rule it out here:

* **causality**: the plant model answers OP one sample later at the earliest (the regressors are
  :math:`q^{-1}`-filtered OP), as a sampled controller, which computes OP at sample k from PV up to k−1, requires;
* **the sign of the process gain**: a reverse-acting controller (OP rises when PV falls below SP) runs a plant
  whose gain is positive, a direct-acting one a plant whose gain is negative. The action is declared, or
  read from the controller's own law: the velocity-form PI
  :math:`\Delta\mathrm{OP}_k = K_c\,\Delta e_{k-s} + K_c \tfrac{\Delta t}{T_i}\, e_{k-s}` with
  :math:`e = \mathrm{SP} - \mathrm{PV}` (SP as recorded, or constant) is fitted by least squares for
  :math:`s \in \{0, 1\}`, and its proportional gain's sign is the action when the law explains ΔOP
  exactly (:data:`MIN_R2`) and the gain is clearly nonzero (:data:`MIN_T`);
* **no pole faster than a sample**: the identified time constants are at least Δt;
* **an integrating plant's dead time shorter than the controller's integral time**: a PI
  :math:`K_c(1 + 1/(T_i s))` on :math:`K e^{-\theta s}/s` has the loop phase
  :math:`-180° + \arctan(\omega T_i) - \omega\theta\,(180°/\pi)`, below −180° at every frequency when
  :math:`T_i \le \theta` (:math:`\arctan x < x`), so no gain keeps that loop stable: a loop recorded under such
  a PI, which stays bounded, has :math:`\theta < T_i`. When the PI is read exactly (above), the dead time an
  integrating plant is searched over stops at :math:`T_i` (:attr:`Identification.max_delay`); on a sticky level
  loop the unbounded search locks onto a dead time of half the limit cycle's period, which this excludes.

* **the set point's path bounds the dead time**: the set point is independent of the load, and the controller
  answers its steps at once (OP at k uses SP at k), so PV cannot answer them sooner than the plant's dead time
  (a sticky valve only delays that answer). In a regression of PV on its own :data:`SETPOINT_AR` lags and the
  set point's lags 1 … M + :data:`SETPOINT_AR`, PV's answer m samples after a set-point step (the fitted step
  response, with its standard error) is tested against none for m = M, M − 1, …, downward from the dead time
  a search found (M samples), each at :data:`SETPOINT_LEVEL`, stopping at the first that is not refuted
  (:func:`setpoint_delay`): the hypotheses "no answer within m samples" are nested (each implies those of
  every smaller m), so this fixed sequence is a closed test and its family-wise level is
  :data:`SETPOINT_LEVEL` with no correction for the number of lags (Marcus, Peritz & Gabriel 1976): the
  chance that it bounds the dead time below the truth is at most that.
  Where the dead time the first search found is far beyond that bound (twice it, plus as many samples:
  :func:`~valve_emulator.diagnosis.explain.onset.far_beyond`), the search is run again below it: a linear
  OP → PV relation fitted over a sticky limit cycle takes up the shift between OP's triangle and PV's cycle
  in its dead time, a share of the cycle's period, where the set point shows the plant answering in seconds.

The plant's family (integrating or self-regulating) is declared (a loop type: ``level`` integrates; ``flow``,
``pressure``, ``temperature`` do not), or chosen from the data by BIC (:func:`~valve_emulator.diagnosis.fit.
nominal.identify`). :class:`Identification` records which constraints were used; the explanation reports it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import solve_triangular
from scipy.special import stdtr

from valve_emulator.errors import UserError

__all__ = ["ACTIONS", "LOOP_TYPES", "MIN_R2", "MIN_T", "MIN_MOVES", "MAX_TAPS", "Declared", "Identification",
           "controller_action", "identification", "setpoint_moves", "setpoint_part", "SETPOINT_LEVEL", "SETPOINT_AR",
           "setpoint_delay"]

#: Controller actions: reverse (OP rises as PV falls; the process gain is positive) or direct.
ACTIONS = ("reverse", "direct")
#: Loop types and whether their plant integrates (the convention of loop-monitoring tools).
LOOP_TYPES = {"level": True, "flow": False, "pressure": False, "temperature": False}
#: The fitted PI must explain at least this fraction of ΔOP's variance for its action to be used: the law read
#: exactly, as a PI on the recorded SP and PV gives it. A law read loosely (a cascade, a filtered or tracking
#: controller, OP without SP) is not trusted for the sign: on the shared plant windows, level and pressure
#: loops read at R² 0.6–0.95 were then fitted with the half-cycle dead time and called sticky.
MIN_R2 = 0.98
#: ... and its proportional gain must be this many standard errors from zero.
MIN_T = 10.0
#: Least number of set-point moves, each followed by a tenth of the record, for OP's part driven by the set point
#: to be estimated (:func:`setpoint_part`).
MIN_MOVES = 2
#: Longest FIR (samples) of OP on the set point (:func:`setpoint_part`).
MAX_TAPS = 1000
#: Family-wise level of the set point's test of the dead time (:func:`setpoint_delay`): the chance that it
#: bounds a loop's dead time below the truth. 1 %, the level of the other refutations of the identification.
SETPOINT_LEVEL = 0.01
#: PV's own lags in that regression (they stand in for the loop's dynamics and the load's colour; the set
#: point's lags reach as far beyond the tested ones).
SETPOINT_AR = 20


@dataclass(frozen=True)
class Declared:
    """What the user declares about the loop: its type, whether its plant integrates, its controller's action
    (None: not declared).

    Raises
    ------
    UserError
        An unknown loop type or action, or a loop type that contradicts ``integrating``.
    """

    loop_type: str | None = None
    integrating: bool | None = None
    action: str | None = None

    def __post_init__(self) -> None:
        if self.loop_type is not None and self.loop_type not in LOOP_TYPES:
            raise UserError(f"loop_type must be one of {', '.join(LOOP_TYPES)}, got {self.loop_type!r}")
        if self.action is not None and self.action not in ACTIONS:
            raise UserError(f"action must be one of {', '.join(ACTIONS)}, got {self.action!r}")
        if (self.loop_type is not None and self.integrating is not None
                and LOOP_TYPES[self.loop_type] != self.integrating):
            kind = "integrates" if LOOP_TYPES[self.loop_type] else "does not integrate"
            raise UserError(f"loop_type {self.loop_type!r} {kind}, but integrating={self.integrating} was declared")

    @property
    def plant_integrates(self) -> bool | None:
        """Whether the plant integrates, as declared (None: for the data to decide)."""
        if self.integrating is not None:
            return self.integrating
        return None if self.loop_type is None else LOOP_TYPES[self.loop_type]


@dataclass(frozen=True)
class Action:
    """The controller's action read from the data: ``action`` (None when the PI law does not explain OP),
    the proportional gain ``kc`` (OP per PV unit, positive for reverse action), its t statistic, R², the
    sample shift ``lag`` of the better fit and the integral time ``ti`` in samples (inf: no integral action)."""

    action: str | None
    kc: float
    t: float
    r2: float
    lag: int
    ti: float = float("inf")


def controller_action(op: np.ndarray, pv: np.ndarray, sp: np.ndarray | None) -> Action:
    """The controller's action from its own law (see the module docstring)."""
    op, pv = np.asarray(op, dtype=float), np.asarray(pv, dtype=float)
    if sp is not None and not np.all(np.isfinite(sp)):
        sp = None   # no recorded set point: held constant
    best = Action(None, float("nan"), 0.0, -np.inf, 0)
    for lag in (0, 1):
        # e_k = SP_k − PV_{k−lag}: the set point as the controller sees it, PV as it was sampled.
        pv_seen = pv[:pv.size - lag]
        e = (np.asarray(sp, dtype=float)[lag:] - pv_seen) if sp is not None else -pv_seen
        y = np.diff(op[lag:])
        X = np.column_stack([np.diff(e), e[1:], np.ones(y.size)])
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        res = y - X @ coef
        tot = float(np.sum((y - y.mean()) ** 2))
        if tot <= 0.0:
            continue
        r2 = 1.0 - float(res @ res) / tot
        sigma2 = float(res @ res) / max(y.size - 3, 1)
        cov = sigma2 * np.linalg.pinv(X.T @ X)
        t = float(coef[0] / np.sqrt(max(cov[0, 0], 1e-300)))
        if r2 > best.r2:
            # ΔOP = Kc Δe + (Kc/Ti) e per sample: Ti = Kc / coef[1] samples, when both have one sign.
            ti = float(coef[0] / coef[1]) if coef[0] * coef[1] > 0.0 else float("inf")
            best = Action(None, float(coef[0]), t, r2, lag, ti)
    if best.r2 >= MIN_R2 and abs(best.t) >= MIN_T:
        return replace(best, action="reverse" if best.kc > 0 else "direct")
    return best


@dataclass(frozen=True)
class Identification:
    """How the linear part of a loop without a model is identified.

    Attributes
    ----------
    sign : the process gain's sign (+1, −1) implied by the controller's action, 0 when unknown.
    integrating : the plant's family as declared (None: chosen from the data).
    constraints : one sentence per constraint used, for the answer.
    max_delay : the longest dead time (s) an integrating plant may have, the controller's integral time read
        from its law (None: not read).
    """

    sign: int = 0
    integrating: bool | None = None
    constraints: tuple[str, ...] = ()
    max_delay: float | None = None

    def as_dict(self) -> dict:
        return {"constraints": list(self.constraints), "gain_sign": self.sign,
                "integrating": self.integrating, "max_delay": self.max_delay}

    def delay_bound(self, integrating: bool) -> float | None:
        """The longest dead time (s) a plant of this family may have (None: no bound)."""
        return self.max_delay if integrating else None


def identification(op: np.ndarray, pv: np.ndarray, sp: np.ndarray | None, declared: Declared | None = None,
                   dt: float = 1.0) -> Identification:
    """The constraints for identifying the plant of this closed loop, sampled every ``dt`` s (see the module
    docstring)."""
    declared = declared or Declared()
    said = ["causal: the plant answers OP one sample later at the earliest",
            "time constants of at least one sample"]
    found = controller_action(op, pv, sp)
    max_delay = None
    if found.action is not None and np.isfinite(found.ti) and found.ti > 0.0:
        max_delay = found.ti * dt
        said.append(f"an integrating plant's dead time below the controller's integral time ({max_delay:.3g} s, "
                    "read from its law): no PI keeps a loop stable otherwise")
    if declared.action is not None:
        action, how = declared.action, "declared"
    else:
        action = found.action
        how = (f"read from the controller's law (PI fitted to OP{' and SP' if sp is not None else ''}: "
               f"Kc {found.kc:.3g}, R² {found.r2:.2f}, OP at k from PV at k−{found.lag})")
    sign = 0 if action is None else (1 if action == "reverse" else -1)
    if sign:
        said.append(f"process gain {'positive' if sign > 0 else 'negative'}: {action}-acting controller, {how}")
    else:
        said.append("process gain's sign free: OP is not a PI's output of PV, and no action was declared")
    integrating = declared.plant_integrates
    if integrating is not None:
        src = f"loop type {declared.loop_type}" if declared.loop_type is not None else "declared"
        said.append(f"{'integrating' if integrating else 'self-regulating'} plant ({src})")
    else:
        said.append("integrating or self-regulating plant chosen from the data (BIC)")
    return Identification(sign=sign, integrating=integrating, constraints=tuple(said), max_delay=max_delay)


def setpoint_moves(sp: np.ndarray) -> np.ndarray:
    """The samples at which the set point has just moved (the first sample at each new value)."""
    return np.flatnonzero(np.diff(np.asarray(sp, dtype=float)) != 0.0) + 1


def setpoint_part(op: np.ndarray, sp: np.ndarray | None, end: int, start: int = 0) -> np.ndarray | None:
    """OP's part that the set point explains, estimated on samples ``[0, end)``: the first stage of the
    two-stage method of closed-loop identification (Van den Hof & Schrama 1993; Ljung, *System Identification*,
    2nd ed., §13.5). None without a recorded set point, or when it moves fewer than :data:`MIN_MOVES` times in
    ``[start, end)`` a tenth of the record or more before ``end``.

    OP is regressed by least squares on the set point's values over the last tenth of the record (at most
    :data:`MAX_TAPS` samples; a FIR, the closed loop's answer to a set-point move, and a constant), and that
    FIR is run over the whole record. A wandering load moves OP too, through the controller, but it is
    independent of the set point, so this part of OP carries none of it, and PV fitted from it (the second
    stage) is free of the bias the load gives PV fitted from OP itself, where OP is correlated with the load."""
    if sp is None or not np.all(np.isfinite(sp)):
        return None
    op, sp = np.asarray(op, dtype=float), np.asarray(sp, dtype=float)
    taps = min(op.size // 10, MAX_TAPS)
    moves = setpoint_moves(sp)
    if taps < 2 or np.count_nonzero((moves >= start) & (moves <= end - op.size // 10)) < MIN_MOVES:
        return None
    z = sp - sp[0]
    h = np.linalg.lstsq(*_fir_normal_equations(z[:end], op[:end], taps), rcond=None)[0]
    return h[-1] + np.convolve(z, h[:-1])[:op.size]


def _fir_normal_equations(z: np.ndarray, y: np.ndarray, taps: int) -> tuple[np.ndarray, np.ndarray]:
    """``(XᵀX, Xᵀy)`` of the least-squares FIR of ``y`` on ``z`` (columns: ``z`` delayed by 0 … ``taps`` − 1
    samples, zeros before the record, then a constant), computed lag by lag from running sums instead of
    forming ``X`` (a record of ``n`` samples needs ``n`` × ``taps`` numbers as ``X``, ``taps``² as ``XᵀX``)."""
    n = z.size
    A = np.empty((taps + 1, taps + 1))
    for lag in range(taps):
        # Σ_{k=j}^{n−1} z_{k−i} z_{k−j} for j = i + lag: the running sum of z_m z_{m−lag} up to m = n − 1 − i.
        run = np.cumsum(z[lag:] * z[:n - lag])
        i = np.arange(taps - lag)
        A[i, i + lag] = A[i + lag, i] = run[n - 1 - i - lag]
    zsum = np.cumsum(z)
    A[:taps, taps] = A[taps, :taps] = zsum[n - 1 - np.arange(taps)]
    A[taps, taps] = n
    b = np.empty(taps + 1)
    b[:taps] = np.correlate(y, z, mode="full")[n - 1:n - 1 + taps]
    b[taps] = y.sum()
    return A, b


def setpoint_delay(pv: np.ndarray, sp: np.ndarray | None, longest: int) -> int | None:
    r"""The fewest samples within which PV answers the set point, by the closed test of the module docstring run
    downward from ``longest`` samples (a dead time a search found): the least m for which "PV has not answered
    a set-point step m samples after it" is refuted, together with every larger m up to ``longest``. None when
    ``longest`` itself is not refuted, without a recorded set point, or where the set point's lags are not told
    apart (it moves too little in the record).

    The answer m samples after a unit step is the step response of the fitted regression
    (:math:`A(q)\,\mathrm{PV} = B(q)\,\mathrm{SP}`, :math:`s_m = \sum_{i} a_i s_{m-i} + \sum_{l \le m} b_l`),
    tested against 0 with its standard error by the delta method (Student's t, the regression's degrees of
    freedom). A step response is a single number per lag, where an F-test of the lags 1 … m together spreads
    the evidence over m degrees of freedom (measured: the F-test left a sticky level loop's 99 s dead time
    unrefuted by 98 s, p 0.006 → ≥ 0.01, where PV's answer shows from 35 s)."""
    if sp is None or longest < 1 or not np.all(np.isfinite(sp)):
        return None
    pv, sp = np.asarray(pv, dtype=float), np.asarray(sp, dtype=float)
    na, span = SETPOINT_AR, longest + SETPOINT_AR
    n0, n = max(na, span), pv.size
    if n - n0 < 4 * (span + na + 1):
        return None
    y = pv[n0:n]
    lagged = lambda x, lags: np.column_stack([x[n0 - j:n - j] for j in lags])  # noqa: E731
    X = np.column_stack([np.ones(y.size), lagged(pv, range(1, na + 1)), lagged(sp, range(1, span + 1))])
    q, r = np.linalg.qr(X)
    diag = np.abs(np.diag(r))
    if not np.all(diag > 1e-9 * diag.max()):
        return None
    coef = solve_triangular(r, q.T @ y)
    res = y - X @ coef
    dof = y.size - X.shape[1]
    s2 = float(res @ res) / dof
    a, b = coef[1:1 + na], coef[1 + na:]
    # The step response s_1 … s_longest and its gradient in the coefficients (rows), lag by lag.
    step = np.zeros(longest + 1)
    grad = np.zeros((longest + 1, X.shape[1]))
    for j in range(1, longest + 1):
        i = np.arange(1, min(na, j - 1) + 1)
        step[j] = b[:j].sum() + a[i - 1] @ step[j - i]
        grad[j] = a[i - 1] @ grad[j - i]
        grad[j, 1 + na:1 + na + j] += 1.0
        grad[j, i] += step[j - i]
    z = solve_triangular(r.T, grad[1:].T, lower=True)
    t = step[1:] / np.sqrt(np.maximum(s2 * np.sum(z ** 2, axis=0), 1e-300))
    refuted = 2.0 * stdtr(dof, -np.abs(t)) < SETPOINT_LEVEL
    bound = None
    for m in range(longest, 0, -1):
        if not refuted[m - 1]:
            break
        bound = m
    return bound
