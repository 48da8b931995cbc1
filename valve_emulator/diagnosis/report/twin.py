r"""The twin: the loop a diagnosis found, written as a loop config that ``simulate`` and ``serve`` read.

:func:`twin` maps a :class:`~valve_emulator.diagnosis.report.diagnosis.Diagnosis` to a
:class:`~valve_emulator.config.LoopConfig` and a header saying where each number came from:

valve
    ``S``, ``J`` of the stiction (or deadband: ``J = 0``) finding, else the nominal valve's; the
    characteristic found, else the nominal one; the valve model and rest criterion of the nominal valve; a found
    actuator lag as ``actuator_lag`` (before the friction, where the diagnosis' chain has it) and a found
    saturation as ``flow_limits`` (the flow clipped after the characteristic, as in the chain). All in
    the twin's travel: the real % travel when OP's travel span is known (the standard format, ``op_units``,
    ``op_range``), and otherwise the diagnosis' unit-free frame (:mod:`~valve_emulator.diagnosis.fit.frame`: the
    recording's robust OP range on 30–70 %). The search always runs in the unit-free frame; :class:`TwinTravel`
    maps every OP quantity from it to the twin's travel exactly (differences scale, levels map affinely, the
    plant's gain per % flow divides by the same ratio). ``valve.op_range`` is the recording's OP at 0 and 100 %
    of that travel (the declared span when known), so a replay (:mod:`~valve_emulator.simulation.replay`) feeds
    the recording's OP exactly as the diagnosis did.
plant
    The final model's linear part as a continuous transfer function (:mod:`~valve_emulator.diagnosis.fit.
    continuous`), in PV units per % flow, with its dead time.
    The operating point ``pv0, u0`` is the fit's (offset, mean flow; for an integrator the balance flow from the
    fitted trend), ``pv0`` then moved so the twin's open-loop replay has the fit's mean PV on the fit part.
    ``noise`` is the RMS of the final model's residual on the fit part; ``pv_range`` the recorded PV's range
    widened by a quarter of it on each side (so the default alarms, at 10 and 90 % of the range, lie 10 % of
    the recorded span outside what was recorded); ``units`` the recording's PV units.
controller
    The model's controller (tuning, action, limits) when a model with one was given; else, when the recording
    has a set point, a PI identified from it (:func:`identify_pi`); else a controller in **manual** holding
    the first OP, tuned by the SIMC rules (Skogestad, *J. Process Control* 13 (2003) 291–309) for the twin's
    own plant, so an operator can switch it to auto. It starts at
    the recording's first OP, with the recorded SP's median (PV's without one) as its set point.
the start
    ``valve.mv0``, ``stuck0``, ``initial_direction`` and ``plant.rest_flow`` carry the state the recording
    starts in, so that ``simulate TWIN --replay REC`` matches from the first sample and ``serve TWIN`` starts at
    the recording's operating point: the valve where the fit's valve starts the record (the start the fit chose,
    :mod:`~valve_emulator.diagnosis.candidates.valve_start`), a self-regulating plant at rest at the PV recorded
    over the first second (:func:`_rest_flow`), an integrating one at rest for the fit's first flow.
simulation, device
    ``dt`` and ``device.tick`` are the recording's sample time, ``duration`` its length.

An external oscillating disturbance found (a sinusoid added to PV) becomes ``plant.disturbance``: the sinusoid
at the plant input that the plant turns into it (amplitude divided by the plant's gain at that frequency, phase
less its phase).

Which finding goes where is what its candidate declares, its
:attr:`~valve_emulator.diagnosis.candidates.base.Candidate.twin_role`
(:class:`~valve_emulator.diagnosis.candidates.base.TwinRole`), read here by role and by parameter name, never by
the candidate's name. A finding without a role (a quantised PV, a valve model the loop config has no keys for)
is left out, and the header says so.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from valve_emulator.config import (
    ControllerConfig,
    DisturbanceConfig,
    LoopConfig,
    PlantConfig,
    SimulationConfig,
    ValveConfig,
)
from valve_emulator.config.schema import CHARACTERISTICS, DeviceConfig
from valve_emulator.config.writer import dump_loop
from valve_emulator.diagnosis.candidates import SLOTS, TwinRole
from valve_emulator.diagnosis.candidates.valve_start import PRE_ROLL
from valve_emulator.diagnosis.fit.chain import Active
from valve_emulator.diagnosis.fit.continuous import continuous_transfer_function
from valve_emulator.diagnosis.fit.data import fit_percent, fold_windows
from valve_emulator.diagnosis.fit.frame import Frame
from valve_emulator.diagnosis.fit.predict import FittedLoop
from valve_emulator.errors import UserError
from valve_emulator.physics.actuator import actuator_response
from valve_emulator.physics.signal_chain import DEFAULT_RANGEABILITY
from valve_emulator.simulation.replay import op_travel, pre_rolled, replay_op

__all__ = ["Twin", "TwinTravel", "twin", "identify_pi", "replay_fit", "PV_MARGIN"]

#: ``pv_range`` is the recorded PV's range widened by this fraction of it on each side.
PV_MARGIN = 0.25
#: Fewest unsaturated samples, and least share of OP's variance explained, for an identified PI to be used.
_PI_MIN_SAMPLES, _PI_MIN_R2 = 20, 0.9
#: An identified integral time beyond this many record lengths counts as no integral action.
_PI_MAX_TI = 100.0
#: A self-regulating twin's plant starts at the PV recorded over this many first seconds.
START_WINDOW = 1.0
#: ... when what its start leaves at the fit part is at most this share of its effect at the start.
_FORGOTTEN = 0.02
#: How far behind OP(0) (beyond J) a valve started moving is put at rest: the fit's value.
_START_EPS = 1e-6
#: OP within this distance (% travel) of 0 or 100 counts as saturated for the PI identification.
_PI_EDGE = 0.5


@dataclass(frozen=True)
class Twin:
    """A twin's config and its provenance (one line per group of numbers, written as the YAML header)."""

    config: LoopConfig
    provenance: tuple[str, ...]

    def text(self) -> str:
        """The YAML file: the provenance as a ``#`` header, then every key of the loop."""
        return dump_loop(self.config, header=self.provenance)


def _g(x: float) -> str:
    return f"{x:.4g}"


def identify_pi(t: np.ndarray, sp: np.ndarray, pv: np.ndarray, op: np.ndarray
                ) -> tuple[float, float | None, str] | None:
    r"""``(kc, ti, action)`` of the PI that wrote ``op`` (% travel) from ``sp`` and ``pv``; None when the data
    do not show one.

    The ISA position form :math:`\mathrm{op} = b + k_c(e + \frac1{T_i}\int e)` in velocity form,
    :math:`\Delta\mathrm{op}_k = k_c\,\Delta e_k + (k_c\Delta t/T_i)\,e_k`, fitted by least squares on the
    samples where OP (now and before) is off its stops — the recorded PV is what the controller read, so the
    regressors carry no error. A negative :math:`k_c` (for ``e = sp − pv``) is direct action; a wrong-signed
    integral term, or an integral time beyond :data:`_PI_MAX_TI` record lengths, means no integral action.
    Refused below :data:`_PI_MIN_R2` of Δop's variance explained.
    """
    dt = float(np.median(np.diff(t)))
    e = np.asarray(sp, dtype=float) - np.asarray(pv, dtype=float)
    op = np.asarray(op, dtype=float)
    inside = (op > _PI_EDGE) & (op < 100.0 - _PI_EDGE)
    use = inside[1:] & inside[:-1] & np.isfinite(e[1:]) & np.isfinite(e[:-1])
    if use.sum() < _PI_MIN_SAMPLES:
        return None
    X = np.column_stack([np.diff(e), e[1:]])[use]
    y = np.diff(op)[use]
    if not np.any(y):
        return None
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    r2 = 1.0 - float(np.sum((y - X @ coef) ** 2) / np.sum((y - y.mean()) ** 2))
    a, b = float(coef[0]), float(coef[1])
    if r2 < _PI_MIN_R2 or a == 0.0:
        return None
    ti = a * dt / b if b != 0.0 and (a > 0) == (b > 0) else None
    if ti is not None and ti > _PI_MAX_TI * (t[-1] - t[0]):
        ti = None   # an integral that would take ages to act is rounding, not a tuning
    return abs(a), ti, "reverse" if a > 0 else "direct"


def _simc(num: tuple[float, ...], den: tuple[float, ...], delay: float, taus: tuple[float, ...],
          integrating: bool, dt: float) -> tuple[float, float, str]:
    """SIMC PI for the plant: the slowest lag kept, the others and the dead time lumped into θ; λ = θ."""
    slow = max(taus, default=0.0)
    theta = max(delay + sum(taus) - slow, dt)
    lam = theta
    if integrating:
        k = num[-1] / den[-2]                    # gain per second of the integrator
        kc, ti = 1.0 / (abs(k) * (lam + theta)), 4.0 * (lam + theta)
    else:
        k = num[-1] / den[-1]
        kc = max(slow, dt) / (abs(k) * (lam + theta))
        ti = min(max(slow, dt), 4.0 * (lam + theta))
    return kc, ti, "reverse" if k > 0 else "direct"


@dataclass(frozen=True)
class TwinTravel:
    r"""The map from the diagnosis' internal OP frame to the twin's travel (0–100 % between ``op_range``).

    The twin's travel is the chain's travel scale (0 and 100 at :attr:`Frame.stops
    <valve_emulator.diagnosis.fit.frame.Frame.stops>`): the real % travel when OP's span is known, else the
    unit-free frame itself (the identity). It is ``travel = 100 (u − s_0)/(s_1 − s_0)``, so OP differences
    (S, J) scale by ``ratio = 100/(s_1 − s_0)``, OP levels (OP, the operating point) map affinely, and a gain per
    unit of internal flow divides by ``ratio``. The saturation limits and the characteristic already act on this
    scale and need no map.
    """

    stops: tuple[float, float]

    @property
    def ratio(self) -> float:
        """Travel units per internal unit."""
        return 100.0 / (self.stops[1] - self.stops[0])

    def level(self, u):
        """Internal OP levels (a float or an array) in the twin's travel."""
        x = (np.asarray(u, dtype=float) - self.stops[0]) * self.ratio
        return float(x) if x.ndim == 0 else x

    def delta(self, du: float) -> float:
        """An internal OP difference (a band S, a jump J) in the twin's travel."""
        return float(du) * self.ratio

    def op_range(self, frame: Frame) -> tuple[float, float]:
        """The recording's OP at 0 and 100 % of the twin's travel (the declared span when it is known)."""
        if frame.span is not None:
            return float(frame.span[0]), float(frame.span[1])
        return frame.op_level(self.stops[0]), frame.op_level(self.stops[1])


def _plant(fitted: FittedLoop, travel: TwinTravel) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The linear part as ``(num, den)`` in PV units per % flow of the twin's travel."""
    ctx, fit = fitted.ctx, fitted.linear
    num, den = continuous_transfer_function(fit.structure, fit.taps, ctx.dt)
    return tuple(c * ctx.y_scale / travel.ratio for c in num), den


def _operating_point(fitted: FittedLoop, travel: TwinTravel) -> tuple[float, float]:
    """``(pv0, u0)``: PV at the operating-point flow, and that flow in the twin's travel (see the module
    docstring)."""
    fit, ctx = fitted.linear, fitted.ctx
    if not fit.structure.integrating:
        return fit.offset * ctx.y_scale + ctx.y_mean, travel.level(fitted.level)
    # y = H(u - level) + offset + trend·k/N: the trend is the integrator fed by (level - u0).
    u0 = fitted.level - fit.trend / (fitted.record_length * ctx.dt * fit.gain)
    y0 = fit.predict(fitted.flow(fitted.op), ctx.dt)[0]
    return float(y0 * ctx.y_scale + ctx.y_mean), travel.level(u0)


def _in_role(fitted: FittedLoop, role: TwinRole) -> Active | None:
    """The physics of the fitted model that the twin writes in ``role`` (None: none)."""
    found = fitted.active.get(role.slot)
    return found if found is not None and found.candidate.twin_role is role else None


def _named(found: Active) -> dict[str, float]:
    """A finding's parameters by name."""
    return {name: float(x) for name, x in zip(found.candidate.param_names, found.params)}


def _left_out(fitted: FittedLoop) -> list[str]:
    """A header line for each finding of the model whose candidate has no twin role, in signal order."""
    lines = []
    for found in sorted(fitted.active.values(), key=lambda a: SLOTS.index(a.slot)):
        if found.candidate.twin_role is not None:
            continue
        if found.slot == "output":
            lines.append(f"Left out: the {found.name} finding acts on the measured PV, which the loop config "
                         "cannot express.")
        else:
            lines.append(f"Left out: the {found.name} finding ({found.slot} slot) has no keys in the loop config, "
                         "so the twin lacks it.")
    return lines


def _input_sine(params: dict[str, float], plant: PlantConfig, dt: float) -> DisturbanceConfig:
    r"""The input sinusoid (% flow) that ``plant`` turns into the output one found, ``A sin(ωt + φ)`` in PV units:
    amplitude ``A/|G(jω)|`` and phase ``φ − arg G(jω)``, the dead time included (steady state; the phase counts
    from the recording's first sample). The simulator holds the disturbance's value at each sample over the
    sample interval, which delays it by ``Δt/2`` and scales it by ``sinc(ωΔt/2)``; the sinusoid written leads by
    as much and is larger by as much, so that the held one is the input found."""
    period, amplitude, phase = params["period"], params["amplitude"], params["phase"]
    w = 2.0 * np.pi / period
    g = np.polyval(plant.num, 1j * w) / np.polyval(plant.den, 1j * w) * np.exp(-1j * w * plant.delay)
    half = 0.5 * w * dt
    hold = np.sin(half) / half if half > 0.0 else 1.0
    return DisturbanceConfig(type="sine", amplitude=amplitude / (abs(g) * hold), period=period,
                             phase=float(np.angle(np.exp(1j * (phase - np.angle(g) + half)))))


def _slug(text: str) -> str:
    stem = Path(text).stem if text else "recording"
    return "twin_" + (re.sub(r"[^A-Za-z0-9]+", "_", stem).strip("_").lower() or "recording")


def _finding_text(diagnosis, physics: str) -> str:
    f = next((f for f in diagnosis.findings if f.physics == physics), None)
    if f is None:
        return ""
    ivs = "; ".join(f"{k} {_g(a)}–{_g(b)}" for k, (a, b) in f.intervals.items())
    return f" (95 % intervals in OP's units: {ivs})" if ivs else ""


def _valve(diagnosis, fitted: FittedLoop, model: LoopConfig | None, op: np.ndarray, travel: TwinTravel
           ) -> tuple[ValveConfig, list[str]]:
    """The valve section of ``fitted`` (``op``: the recorded OP in the twin's travel) and its provenance."""
    rec, frame = diagnosis.recording, diagnosis.frame
    ctx = fitted.ctx
    if frame.known:
        lines = [f"valve.op_range: the recording's OP at 0 and 100 % travel ({frame.span_source}); OP, S, J, "
                 "plant.u0 and the plant's input are in % travel."]
    else:
        lo, hi = frame.to_internal(np.percentile(rec.op, [0.5, 99.5]))
        lines = ["valve.op_range: OP's travel span is unknown; the twin's travel is the diagnosis' unit-free "
                 f"frame (the recording's robust OP range on {_g(lo)}-{_g(hi)} %); op_range maps OP's units to it."]
    found = _in_role(fitted, TwinRole.VALVE_BAND)
    if found is not None:
        band = _named(found)
        S, J = travel.delta(band["S"]), travel.delta(band.get("J", 0.0))
        lines.append(f"valve.S, valve.J: {found.name} found by the diagnosis{_finding_text(diagnosis, found.name)}.")
    else:
        S, J = (travel.delta(x) for x in fitted.nominal_valve)
        keyless = fitted.active.get("valve")   # a valve model the loop config has no keys for
        if keyless is not None:
            lines.append("valve.S, valve.J: " + ("the model's valve" if model is not None else "a free valve")
                         + f" (the {keyless.name} found has no keys in the loop config).")
        else:
            lines.append("valve.S, valve.J: " + ("the model's valve (no valve friction found)." if model is not None
                                                 else "no valve friction found (a free valve)."))
    char = _in_role(fitted, TwinRole.CHARACTERISTIC)
    kind, R = ctx.characteristic
    if char is not None:
        curve = _named(char)
        kind, R = CHARACTERISTICS[int(curve["kind"])], curve["R"]
    lines.append("valve.characteristic: " + ("found by the diagnosis." if char is not None else
                                             "the model's." if model is not None else "linear (assumed)."))
    tau, flow_limits = _actuator_lag(fitted), _flow_limits(fitted)
    if tau:
        lines.append(f"valve.actuator_lag: the actuator lag found by the diagnosis (τ = {_g(tau)} s), before the "
                     "valve's friction as in the diagnosis' chain.")
    if flow_limits != (0.0, 100.0):
        lines.append("valve.flow_limits: the saturation found by the diagnosis (the flow clipped after the "
                     "characteristic, as in the diagnosis' chain).")
    rest = model.valve.rest_time if model is not None else (ctx.rest_samples - 0.5) * ctx.dt
    valve = ValveConfig(model=ctx.valve_model, S=S, J=J, rest_time=rest, op0=float(np.clip(op[0], 0.0, 100.0)),
                        actuator_lag=tau, characteristic=kind, rangeability=R if R > 1.0 else DEFAULT_RANGEABILITY,
                        flow_limits=flow_limits, op_range=travel.op_range(frame),
                        **({"ma_table": model.valve.ma_table} if model is not None else {}))
    return valve, lines


def _actuator_lag(fitted: FittedLoop) -> float:
    """The actuator lag's time constant found (s; 0: none). The lag is unit-free, so no travel map."""
    found = _in_role(fitted, TwinRole.ACTUATOR_LAG)
    return _named(found)["tau"] if found is not None else 0.0


def _flow_limits(fitted: FittedLoop) -> tuple[float, float]:
    """The flow's ``[lo, hi]`` (%) of the saturation found, ``(0, 100)`` without one. The limits are levels on
    the chain's travel scale, which is the twin's travel: no map."""
    found = _in_role(fitted, TwinRole.FLOW_LIMITS)
    if found is None:
        return 0.0, 100.0
    flow = _named(found)
    return max(0.0, flow["lo"]), min(100.0, flow["hi"])


def _plant_section(diagnosis, fitted: FittedLoop, pv_fitted: np.ndarray, model: LoopConfig | None, pv_units: str,
                   travel: TwinTravel) -> tuple[PlantConfig, list[str]]:
    """The plant section of ``fitted`` (``pv_fitted``: its free run on the recording; before the replay's
    operating-point shift) and its provenance."""
    explanation, rec = diagnosis.explanation, diagnosis.recording
    which = ("the final model" if fitted is explanation.fitted else
             "the model the answer rests on (the search's option with the valve, not kept)")
    ctx, st = fitted.ctx, fitted.linear.structure
    num, den = _plant(fitted, travel)
    pv0, u0 = _operating_point(fitted, travel)
    w0 = ctx.window[0]
    noise = float(np.sqrt(np.mean((explanation.traces.pv[w0:] - pv_fitted[w0:]) ** 2)))
    lo, hi = float(np.min(rec.pv)), float(np.max(rec.pv))
    span = hi - lo if hi > lo else max(abs(hi), 1.0)
    units = pv_units or (model.plant.units if model is not None else "")
    plant = PlantConfig(num, den, delay=st.delay, pv0=pv0, u0=u0, units=units, noise=noise,
                        pv_range=(lo - PV_MARGIN * span, hi + PV_MARGIN * span))
    lines = [f"plant.num, den, delay: the linear part of {which}, {_plant_origin(explanation, model)} "
             f"({st.describe()}), as a continuous transfer function in PV units per % flow.",
             f"plant.pv0, u0: the fit's operating point; plant.noise: RMS residual of {which} "
             f"({_g(noise)}); "
             f"pv_range: the recorded PV range widened by {PV_MARGIN:g} of it each side"
             + (f"; units: {units}." if units else ".")]
    sine = _in_role(fitted, TwinRole.DISTURBANCE)
    if sine is not None:
        plant = replace(plant, disturbance=_input_sine(_named(sine), plant, ctx.dt))
        lines.append("plant.disturbance: the external oscillating disturbance found (a sinusoid in PV), as the "
                     "sinusoid at the plant input that the plant turns into it.")
    return plant, lines + _left_out(fitted)


def _plant_origin(explanation, model: LoopConfig | None) -> str:
    """Where the twin's linear plant comes from: the nominal model held as a prior, the parameters the data
    moved (from, to), or, without a model, the identification from the recording."""
    if model is None:
        return "identified from the recording"
    moved = explanation.moved
    if not explanation.linear_tests:
        return "re-fitted by the diagnosis from the model's structure"
    if not moved:
        return "the nominal model's, held as a prior (the data did not demand a move)"
    changes = "; ".join(f"{m.label} moved from {_g(m.nominal)} to {_g(m.proposed)} (penalised BIC "
                        f"{m.delta_bic:.0f} lower)" for m in moved)
    return f"the nominal model's with what the data demanded: {changes}"


def _controller(diagnosis, fitted: FittedLoop, model: LoopConfig | None, op: np.ndarray, plant: PlantConfig
                ) -> tuple[ControllerConfig, list[str]]:
    """The controller section (``op``: the recorded OP in the twin's travel) and its provenance."""
    rec = diagnosis.recording
    st, lines = fitted.linear.structure, []
    limits = (0.0, 100.0)
    has_sp = rec.sp is not None and bool(np.all(np.isfinite(rec.sp)))
    pi = identify_pi(rec.t, rec.sp, rec.pv, op) if has_sp else None
    if model is not None and model.controller is not None:
        c = model.controller
        kc, ti, td, action, mode = c.kc, c.ti, c.td, c.action, "auto"
        limits = (max(0.0, c.op_limits[0]), min(100.0, c.op_limits[1]))
        lines.append("controller: the model's tuning and action.")
    elif pi is not None:
        (kc, ti, action), td, mode = pi, 0.0, "auto"
        lines.append("controller: PI identified from the recorded SP, PV and OP (velocity form, least squares).")
    else:
        kc, ti, action = _simc(plant.num, plant.den, plant.delay, st.taus, st.integrating, fitted.ctx.dt)
        td, mode = 0.0, "manual"
        lines.append("controller: manual at the first OP (the recording shows no controller to copy); tuning by "
                     "the SIMC rules for the twin's plant, for when it is switched to auto.")
    sp = float(np.median(rec.sp if has_sp else rec.pv))   # the loop's usual set point (the served device's)
    controller = ControllerConfig(kc, ti=ti, td=td, sp=sp, bias=float(np.clip(op[0], *limits)), action=action,
                                  op_limits=limits, mode=mode)
    return controller, lines


def twin(diagnosis, *, model: LoopConfig | None = None, pv_units: str = "", name: str | None = None) -> Twin:
    """The twin of ``diagnosis`` (see the module docstring).

    Parameters
    ----------
    diagnosis : a :class:`~valve_emulator.diagnosis.report.diagnosis.Diagnosis` with a fitted model.
    model : the nominal model the diagnosis was run against (its controller and valve model are used).
    pv_units : PV's engineering units (default: the model's ``plant.units``).
    name : the twin's name (default ``twin_<recording stem>``).

    Raises
    ------
    UserError
        The diagnosis has no fitted model (plant data that could not support one).
    """
    explanation = diagnosis.explanation
    if explanation is None or explanation.fitted is None:
        reason = "" if diagnosis.assessment is None else f" ({diagnosis.assessment.reason})"
        raise UserError(f"{diagnosis.source}: no model was fitted, so there is no twin to write{reason}")
    fitted, pv_fitted = _answered(diagnosis)
    rec, dt = diagnosis.recording, fitted.ctx.dt
    travel = TwinTravel(diagnosis.frame.stops)
    op = travel.level(diagnosis.frame.to_internal(rec.op))
    valve, valve_lines = _valve(diagnosis, fitted, model, op, travel)
    plant, plant_lines = _plant_section(diagnosis, fitted, pv_fitted, model, pv_units, travel)
    controller, controller_lines = _controller(diagnosis, fitted, model, op, plant)
    cfg = LoopConfig(name or _slug(diagnosis.source), description=f"twin of {diagnosis.source}", valve=valve,
                     plant=plant, controller=controller,
                     simulation=SimulationConfig(dt=dt, duration=max(float(rec.t[-1] - rec.t[0]), dt)),
                     device=DeviceConfig(tick=dt))
    cfg, start_lines = _with_start(cfg, fitted, rec, travel)
    head = [f"Twin of {diagnosis.source}, written by valve-emulator diagnose --twin: the loop the diagnosis found, "
            "as a loop config.",
            f"Answer: {diagnosis.answer}; held-out fit {_g(explanation.fit_before)} % -> "
            f"{_g(explanation.fit_after)} % ({diagnosis.verdict}).",
            *valve_lines, *plant_lines, *controller_lines, *start_lines,
            f"simulation.dt, device.tick: the recording's sample time ({_g(dt)} s); duration: its length."]
    return Twin(_replay_operating_point(cfg, fitted, pv_fitted, rec), tuple(head))


def _answered(diagnosis) -> tuple[FittedLoop, np.ndarray]:
    """The model the twin is written from (:attr:`Diagnosis.fitted <valve_emulator.diagnosis.report.diagnosis.
    Diagnosis>`: the final model, or the valve option a stiction answer rests on), and its free-run PV on the
    recording."""
    fitted, explanation = diagnosis.fitted, diagnosis.explanation
    if fitted is explanation.fitted:
        return fitted, explanation.traces.pv_after
    return fitted, fitted.predict(diagnosis.recording.op)


@dataclass(frozen=True)
class ValveStart:
    """A valve's state at the recording's first sample, before it reads OP(0), in the twin's travel: its position
    ``mv``, the direction it last moved in, and whether it is stuck there (else still moving)."""

    mv: float
    direction: int
    stuck: bool


def _fitted_start(fitted: FittedLoop) -> int | None:
    """The start the fit chose for its valve, ``+1``/``−1`` (moving up/down at OP(0): see
    :mod:`~valve_emulator.diagnosis.candidates.valve_start`), or None for the mirrored pre-roll (the nominal
    valve's start too)."""
    found = _in_role(fitted, TwinRole.VALVE_BAND)
    start = _named(found).get("start", PRE_ROLL) if found is not None else PRE_ROLL
    return None if start == PRE_ROLL else int(start)


def _valve_start(cfg: LoopConfig, fitted: FittedLoop, op: np.ndarray, travel: TwinTravel) -> ValveStart:
    """The state the fit's valve starts the record in (``op``: the recorded OP in the twin's travel).

    A start moving up or down is the valve at rest ``J + ε`` behind OP(0) in the fit's frame, so that OP(0)
    moves it (an actuator lag starts at rest at OP(0), so the valve reads OP(0) first either way); the pre-roll
    start is whatever the twin's valve reaches through the mirrored pre-roll, which runs the same state machine
    on the same demand as the fit's: the fit's chain lags the whole record first, then pre-rolls the valve on
    the lagged OP.
    """
    d = _fitted_start(fitted)
    if d is None:
        v = cfg.valve
        demand = actuator_response(op, v.actuator_lag, cfg.simulation.dt) if v.actuator_lag else op
        bank = pre_rolled(replace(cfg, valve=replace(v, actuator_lag=0.0)), demand)
        return ValveStart(float(bank.mv[0]), int(bank.direction[0]), bool(bank.stuck[0]))
    v = cfg.valve
    J = v.J / travel.ratio                                          # the fit's frame
    rest = travel.level(float(np.clip(fitted.op[0] - d * (J + _START_EPS), 0.0, 100.0)))
    return ValveStart(float(np.clip(rest - d * 0.5 * (v.S - v.J), 0.0, 100.0)), d, True)


def _with_start(cfg: LoopConfig, fitted: FittedLoop, rec, travel: TwinTravel) -> tuple[LoopConfig, list[str]]:
    """``cfg`` carrying the state the recording starts in: the fit's valve (``mv0``, ``stuck0``,
    ``initial_direction``) and the plant at rest (``rest_flow``), so that a replay or a served twin starts
    where the recording starts."""
    op = np.clip(op_travel(cfg, rec.op), *cfg.controller.op_limits)
    start = _valve_start(cfg, fitted, op, travel)
    valve = replace(cfg.valve, mv0=start.mv, stuck0=start.stuck, initial_direction=start.direction)
    cfg = replace(cfg, valve=valve)
    first = travel.level(float(fitted.flow(fitted.op)[0]))
    moved = None if fitted.linear.structure.integrating else _rest_flow(cfg, rec, first, fitted.ctx.window[0])
    flow = first if moved is None else moved
    line = (f"valve.mv0, stuck0, initial_direction: the state the diagnosis' fit starts the valve in (at "
            f"{_g(start.mv)} %, {'stuck' if start.stuck else 'moving'}, last moving "
            f"{'up' if start.direction > 0 else 'down'}); plant.rest_flow: the plant starts at rest for "
            f"{_g(flow)} % flow, " + ("the fit's first flow." if moved is None else
                                      "the flow whose rest starts at the recorded PV."))
    return replace(cfg, plant=replace(cfg.plant, rest_flow=flow)), [line]


def _rest_flow(cfg: LoopConfig, rec, guess: float, fit_start: int) -> float | None:
    """The flow a self-regulating plant starts at rest for, so that the open-loop replay of ``cfg`` starts at
    the recorded PV: least squares over the recording's first :data:`START_WINDOW` seconds (at least two
    samples).

    A recording starts mid-swing; a plant at rest for the first flow (the fit's start) begins at that flow's
    steady PV, which may lie anywhere in the swing. The replayed PV is affine in the rest flow, so one more
    replay gives its sensitivity and the best value in closed form. Only a plant that has forgotten its start
    by the fit part (sample ``fit_start``; :data:`_FORGOTTEN`) starts elsewhere than at the fit's ``guess``, so
    the fit part replays as the fit; :func:`_replay_operating_point` then moves ``pv0`` by that part's mean.
    None: the start stays the fit's.
    """
    def run(flow: float) -> np.ndarray:
        return replay_op(replace(cfg, plant=replace(cfg.plant, rest_flow=flow)), rec).pv

    dt = cfg.simulation.dt
    n = min(len(rec), max(2, int(math.ceil(START_WINDOW / dt - 1e-9)) + 1))
    base = run(guess)
    sens = run(guess + 1.0) - base
    if not np.any(sens[:n]) or np.max(np.abs(sens[fit_start:])) > _FORGOTTEN * np.max(np.abs(sens[:n])):
        return None   # the plant remembers its start into the fit part: the fit's start is the one it fitted
    err = np.asarray(rec.pv[:n], dtype=float) - base[:n]
    return float(guess + np.dot(sens[:n], err) / np.dot(sens[:n], sens[:n]))


def _replay_operating_point(cfg: LoopConfig, fitted: FittedLoop, pv_fitted: np.ndarray, rec) -> LoopConfig:
    """``cfg`` with ``pv0`` moved so that its open-loop replay has the fit's mean PV (``pv_fitted``, the free run
    of ``fitted``) on the fit part.

    The fit's valve may start differently from the replay's (a start moving up or down at the first sample
    instead of the mirrored pre-roll), and an integrating plant keeps any early difference of flow as a
    permanent offset; a self-regulating one forgets it, and the shift is then only the fit's rounding.
    """
    w0, w1 = fitted.ctx.window
    sim = replay_op(cfg, rec)
    shift = float(np.mean(pv_fitted[w0:w1] - sim.pv[w0:w1]))
    return replace(cfg, plant=replace(cfg.plant, pv0=cfg.plant.pv0 + shift))


def replay_fit(diagnosis, pv: np.ndarray) -> float:
    """The fit (%) of a replayed PV against the recorded one, on the samples ``fit_after`` is measured on:
    the held-out last :data:`~valve_emulator.diagnosis.fit.data.HELD_OUT` of the record (split validation) or the
    two held-out blocks pooled (two-fold)."""
    explanation = diagnosis.explanation
    y, pv = np.asarray(diagnosis.recording.pv, dtype=float), np.asarray(pv, dtype=float)
    if explanation.plant.get("validation", "split") == "split":
        a = explanation.traces.test_start
        return fit_percent(y[a:], pv[a:])
    err = dev = 0.0
    for _, (a, b) in fold_windows(y.size, explanation.fitted.ctx.window[0]):
        err += float(np.sum((y[a:b] - pv[a:b]) ** 2))
        dev += float(np.sum((y[a:b] - np.mean(y[a:b])) ** 2))
    return float("nan") if dev == 0.0 else 100.0 * (1.0 - math.sqrt(err / dev))
