r"""What the explain step found: findings, the JSON, the verdict sentence and the Markdown report.

An :class:`Explanation` is a frozen record (the fitting machine is
:class:`~valve_emulator.diagnosis.explain.search.Search`) that keeps the fitted model
(:class:`~valve_emulator.diagnosis.fit.predict.FittedLoop`). :meth:`Explanation.to_json` returns exactly the
keys ``fit_before``, ``fit_after``, ``findings`` (each ``physics``, ``parameters``, ``windows``, ``evidence``, and
``onset`` for physics that starts part-way),
``verdict`` and, with a model, ``linear_part`` (whether each parameter of the nominal linear part moved:
:class:`LinearMove`); everything else (intervals, rankings, the linear part's table) goes to
:meth:`Explanation.report`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from valve_emulator.diagnosis.explain.locate import Located
from valve_emulator.diagnosis.explain.onset import Onset
from valve_emulator.diagnosis.fit.load_check import Memory
from valve_emulator.diagnosis.fit.predict import FittedLoop

__all__ = ["Finding", "LinearMove", "RankRow", "Traces", "ValveAlternative", "Explanation", "verdict"]


@dataclass(frozen=True, kw_only=True)
class Finding:
    """One piece of physics the nominal model leaves out, fitted.

    Attributes
    ----------
    physics : vocabulary word (``stiction``, ``deadband``, ``dead_time``, ``characteristic``,
        ``actuator_lag``).
    parameters : the JSON parameters (their keys are part of the JSON output).
    windows : ``(t_start, t_end)`` (s) where adding it reduces the residual most.
    evidence : one sentence: BIC, held-out fit, interval, where the improvement lies.
    description : phrase for the verdict.
    intervals : 95 % profile intervals per parameter name.
    delta_bic, fit_without, fit_with : the test it passed.
    load_delta_bic : for a valve finding on plant data (no nominal model), ΔBIC again under a drifting-load
        noise model (:mod:`~valve_emulator.diagnosis.fit.load_check`); None otherwise.
    edges : the parameters whose estimate sits on an edge of the range searched
        (:meth:`~valve_emulator.diagnosis.candidates.base.Candidate.bounds`): name → (``"≥"`` or ``"≤"``, the
        edge). Such a parameter is a bound, not a value; its interval is open on the far side.
    onset : for physics that starts part-way, when it starts and the fits where it acts
        (:class:`~valve_emulator.diagnosis.explain.onset.Onset`); None when it acts from the start.
    """

    physics: str
    parameters: dict
    windows: tuple[tuple[float, float], ...]
    evidence: str
    description: str
    intervals: dict = field(default_factory=dict)
    delta_bic: float = 0.0
    fit_without: float = 0.0
    fit_with: float = 0.0
    load_delta_bic: float | None = None
    edges: dict = field(default_factory=dict)
    onset: Onset | None = None

    def to_json(self) -> dict:
        """The finding in the diagnosis document: ``physics``, ``parameters``, ``intervals`` (the 95 % interval
        of each numeric parameter that has one, in the units of its value, :func:`_interval_json`),
        ``windows``, ``evidence`` and, for physics that starts part-way, ``onset``."""
        numeric = {k: v for k, v in self.parameters.items() if isinstance(v, (int, float)) and np.isfinite(v)}
        intervals = {k: _interval_json(*self.intervals[k], numeric[k]) for k in numeric if k in self.intervals}
        out = {"physics": self.physics, "parameters": dict(self.parameters), "intervals": intervals,
               "windows": [[round(a, 6), round(b, 6)] for a, b in self.windows], "evidence": self.evidence}
        if self.onset is not None:
            out["onset"] = self.onset.to_json()
        return out


@dataclass(frozen=True, kw_only=True)
class LinearMove:
    """Whether one parameter of the nominal model's linear part moved (see
    :mod:`~valve_emulator.diagnosis.explain.prior`).

    Attributes
    ----------
    parameter : ``"gain"`` (PV per % flow; per second for an integrating plant), ``"time_constant"`` (s) or
        ``"dead_time"`` (s).
    index : which time constant (position in the nominal model's ascending list); None for the others.
    nominal : the nominal model's value.
    proposed : the value the data move it to when it is freed (the MAP estimate under the prior).
    moved : whether the data demand the move (penalised BIC falls by at least 10); the final model then has
        ``proposed``, else ``nominal``.
    delta_bic : penalised BIC of the model with it held minus that with it moved (≥ 10 when moved).
    fit_held, fit_moved : held-out free-run fit (%) with it held and with it moved.
    """

    parameter: str
    index: int | None
    nominal: float
    proposed: float
    moved: bool
    delta_bic: float
    fit_held: float
    fit_moved: float

    @property
    def fitted(self) -> float:
        """The value in the final model."""
        return self.proposed if self.moved else self.nominal

    @property
    def label(self) -> str:
        return {"gain": "gain", "dead_time": "dead time (s)"}.get(
            self.parameter, f"time constant {(self.index or 0) + 1} (s)")

    def sentence(self) -> str:
        """One line for the report: from, to, and what the move bought (or why it was not made)."""
        if self.moved:
            return (f"{self.label} moved from {self.nominal:.4g} to {self.proposed:.4g}: penalised BIC "
                    f"{self.delta_bic:.0f} lower, held-out fit {self.fit_held:.1f} % → {self.fit_moved:.1f} %")
        return (f"{self.label} held at {self.nominal:.4g}: moving it to {self.proposed:.4g} lowers the penalised "
                f"BIC by {self.delta_bic:.1f}, less than the 10 a move needs (held-out fit {self.fit_held:.1f} % "
                f"held, {self.fit_moved:.1f} % moved)")

    def to_json(self) -> dict:
        return {"parameter": self.parameter, "index": self.index, "nominal": _num(self.nominal),
                "fitted": _num(self.fitted), "proposed": _num(self.proposed), "moved": self.moved,
                "delta_bic": round(self.delta_bic, 2), "fit_held": _num(self.fit_held, 2),
                "fit_moved": _num(self.fit_moved, 2)}


def _interval_json(lo: float, hi: float, value: float) -> list:
    """A 95 % interval for the JSON: each end to 6 significant digits (as ``friction``'s), never rounded past the
    ``value`` it holds, and an infinite end (the far side of a parameter on an edge of the range searched: a
    bound, not a value) null."""
    low = min(float(f"{lo:.6g}"), value) if np.isfinite(lo) else None
    high = max(float(f"{hi:.6g}"), value) if np.isfinite(hi) else None
    return [low, high]


def _num(x: float, digits: int = 6) -> float | None:
    """A JSON number (None for NaN, e.g. a held-out fit two-fold validation did not compute)."""
    return None if x != x else round(float(x), digits)


@dataclass(frozen=True, kw_only=True)
class RankRow:
    """One option of one round of the search, for the ranking table."""

    round: int
    option: str
    parameters: str
    delta_bic: float
    heldout: float
    chosen: bool


@dataclass(frozen=True, eq=False, kw_only=True)
class Traces:
    """Signals for the figure (PV units, % travel, s)."""

    t: np.ndarray
    op: np.ndarray
    pv: np.ndarray
    pv_before: np.ndarray
    pv_base: np.ndarray
    pv_after: np.ndarray
    mv_after: np.ndarray
    flow_after: np.ndarray
    test_start: int
    surface: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None   # S, J, ΔBIC over (S, J)
    surface_best: tuple[float, float] | None = None
    surface_load_model: bool = False   # the surface scored through the drifting-load noise model (a late fit's)


@dataclass(frozen=True)
class ValveAlternative:
    """The valve the search tried and did not keep, as an alternative explanation (plant data only).

    The option of the search with the lowest BIC that adds valve friction with a band of at least the least
    band asked for (a band that could matter), scored against the final model under the drifting-load noise
    model (:func:`~valve_emulator.diagnosis.fit.load_check.load_delta_bic`): ``load_delta_bic`` is the final
    model's BIC minus the option's, so positive when the valve explains PV *better*.

    Attributes
    ----------
    physics : ``stiction`` or ``deadband``.
    S, J : the band and jump in OP's units (J = 0 for a deadband).
    load_delta_bic : BIC of the final model minus BIC of the option, under the drifting-load noise model.
    intervals : 95 % intervals of ``S`` and ``J`` (OP's units), made as an accepted finding's are (the profile of
        the option's cost over its band and jump, jackknifed over blocks of the record), when the option explains
        PV better than the final model (``load_delta_bic`` ≥ the findings' ΔBIC) and the final model has no valve
        friction: the only case in which the answer can rest on it; empty otherwise.
    fitted : the option's model as a loop that replays any OP, in that same case (the twin of an answer resting
        on it is written from it); None otherwise.
    memory : in that same case, whether PV shows the band's memory beyond any single-valued map of OP (what no
        flow characteristic can make: :func:`~valve_emulator.diagnosis.fit.load_check.remembered`); None
        otherwise.
    """

    physics: str
    S: float
    J: float
    load_delta_bic: float
    intervals: dict = field(default_factory=dict)
    fitted: FittedLoop | None = None
    memory: Memory | None = None


def verdict(findings: tuple[Finding, ...], fit_before: float, fit_after: float, *, given: bool) -> str:
    """The plain-language verdict (see the module docstring of :mod:`valve_emulator.diagnosis`)."""
    subject = "the model" if given else "the linear model identified from the data"
    if not findings:
        return (f"no significant mismatch: no candidate physics improves {subject} significantly "
                f"(held-out fit {fit_after:.0f} %)")
    parts = [f.description for f in findings]
    what = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
    return f"{subject} leaves out {what}; fit {fit_before:.0f} % → {fit_after:.0f} %"


def _fmt(x: float) -> str:
    return f"{x:.4g}"


@dataclass(frozen=True, eq=False, kw_only=True)
class Explanation:
    """Everything the explain step found (see the module docstring).

    Attributes
    ----------
    source : the recording's name.
    given : whether a nominal model was given (else the linear part was identified from the data).
    fit_before, fit_base, fit_after : held-out free-run fits (%) of the nominal model, of the nominal chain
        with the linear part re-fitted, and of the final model.
    findings : the accepted physics, in the order accepted.
    located : where the nominal model's residual concentrates.
    linear : the linear part's table for the report, nominal against re-fitted.
    ranking : every option of every round.
    traces : signals for the figure.
    rule : the significance rule, in words.
    seconds : wall time.
    plant : the fitted linear part, numerically: gain (PV/%), taus, delay, integrating, validation.
    fitted : the final model, replayable on any OP (:meth:`predict`).
    input_delta_bic : plant data only (two-fold validation): how much the final model explains PV under the
        drifting-load noise model, against that noise model alone
        (:func:`~valve_emulator.diagnosis.fit.load_check.input_delta_bic`); None with a nominal model.
    linear_tests : with a nominal model, one :class:`LinearMove` per parameter of its linear part that was
        tested (gain, time constants, and the dead time when the search freed it); :attr:`moved` are those
        the data moved.
    identification : without a model, how the linear part was identified: ``constraints`` (one sentence each:
        causality, the gain's sign and where it came from, the plant's family), ``gain_sign``, ``integrating``
        (as declared, or None), ``max_delay`` (an integrating plant's dead-time bound, or None),
        ``delay_searched`` (the longest dead time tried, s) and ``delay_is_bound`` (the dead time sits on that
        end: a bound, not a value); None with a model.
    valve_alternative : plant data, when asked for (``least_band`` of
        :func:`~valve_emulator.diagnosis.explain.pipeline.explain`) and the search tried one: the best valve
        option with a band that could matter (:class:`ValveAlternative`).
    """

    source: str
    given: bool
    fit_before: float
    fit_base: float
    fit_after: float
    findings: tuple[Finding, ...]
    located: Located
    linear: dict
    ranking: tuple[RankRow, ...]
    traces: Traces
    rule: str
    seconds: float = 0.0
    plant: dict = field(default_factory=dict)
    fitted: FittedLoop | None = None
    input_delta_bic: float | None = None
    linear_tests: tuple[LinearMove, ...] = ()
    identification: dict | None = None
    valve_alternative: ValveAlternative | None = None

    @property
    def moved(self) -> tuple[LinearMove, ...]:
        """The parameters of the nominal linear part the data moved (empty without a model or when it held)."""
        return tuple(m for m in self.linear_tests if m.moved)

    @property
    def verdict(self) -> str:
        return verdict(self.findings, self.fit_before, self.fit_after, given=self.given)

    def predict(self, op) -> np.ndarray:
        """Free-run PV of the fitted loop for ``op`` (see
        :meth:`~valve_emulator.diagnosis.fit.predict.FittedLoop.predict`)."""
        if self.fitted is None:
            raise ValueError(f"{self.source}: this explanation keeps no fitted model")
        return self.fitted.predict(op)

    def to_json(self) -> dict:
        """The JSON: ``fit_before``, ``fit_after``, ``findings``, ``verdict``, and with a model ``linear_part``
        (one :meth:`LinearMove.to_json` per parameter of the nominal linear part tested)."""
        out = {"fit_before": round(self.fit_before, 2), "fit_after": round(self.fit_after, 2),
               "findings": [f.to_json() for f in self.findings], "verdict": self.verdict}
        if self.given:
            out["linear_part"] = [m.to_json() for m in self.linear_tests]
        if self.identification is not None:
            out["identification"] = self.identification
        return out

    def report(self, *, figure: str | None = None) -> str:
        """A Markdown report; ``figure`` is a path to link (relative to the report)."""
        out = [f"# Diagnosis of `{self.source}`", "", f"**Verdict:** {self.verdict}.", ""]
        nominal = "nominal model as given (operating point fitted)" if self.given else \
            "linear model identified from the data (linear valve)"
        out += ["| model | free-run fit on the held-out part |", "|---|---|",
                f"| {nominal} | {self.fit_before:.1f} % |",
                f"| nominal chain, linear part re-fitted | {self.fit_base:.1f} % |",
                f"| with the findings | {self.fit_after:.1f} % |", ""]
        out += ["## Findings", ""]
        if not self.findings:
            out += ["None: no candidate passed the significance rule below.", ""]
        for i, f in enumerate(self.findings, 1):
            params = ", ".join(f"{k} = {v}" for k, v in f.parameters.items())
            ivs = "; ".join(f"{k} {_fmt(a)} – {_fmt(b)}" for k, (a, b) in f.intervals.items())
            shown = ", ".join(f"[{a:.5g}, {b:.5g}]" for a, b in f.windows[:6])
            more = f" and {len(f.windows) - 6} more" if len(f.windows) > 6 else ""
            out += [f"### {i}. `{f.physics}`", "", f"- parameters: {params}"]
            if ivs:
                out.append(f"- 95 % intervals (profile of the cost surface): {ivs}")
            if f.onset is not None:
                out.append(f"- acts {f.onset.sentence()}")
            out += [f"- evidence: {f.evidence}", f"- windows (s): {shown or 'none'}{more}", ""]
        loc = self.located
        out += ["## Where the nominal model's residual concentrates", "",
                f"The {len(loc.windows)} strongest window(s) hold {100 * loc.energy_share:.0f} % of the residual "
                f"energy in {100 * loc.time_share:.0f} % of the time: "
                + ", ".join(f"[{a:.5g}, {b:.5g}]" for a, b in loc.windows) + " s.", "",
                "| condition | share of residual energy | share of time | lift |", "|---|---|---|---|"]
        out += [f"| {a.condition} | {100 * a.energy_share:.0f} % | {100 * a.time_share:.0f} % | {a.lift:.2f} |"
                for a in loc.alignments]
        out += ["", "## Linear part", "", "| | nominal | re-fitted |", "|---|---|---|"]
        out += [f"| {k} | {v[0]} | {v[1]} |" for k, v in self.linear.items()]
        if self.given:
            out += ["", "The nominal model is a prior: a parameter moves only when the penalised BIC falls by at "
                    "least 10.", ""]
            out += [f"- {m.sentence()}" for m in self.linear_tests] or ["- nothing to test"]
        out += ["", "## Candidate ranking", "", self.rule, "",
                "| round | option | parameters | ΔBIC | held-out fit | chosen |", "|---|---|---|---|---|---|"]
        # Two-fold validation cross-validates only the options it compares; the others show "—".
        out += [f"| {r.round} | {r.option} | {r.parameters} | {r.delta_bic:.0f} | "
                f"{'—' if r.heldout != r.heldout else f'{r.heldout:.1f} %'} | {'yes' if r.chosen else ''} |"
                for r in self.ranking]
        if figure:
            out += ["", f"![diagnosis figure]({figure})"]
        out += ["", f"_Computed in {self.seconds:.1f} s._", ""]
        return "\n".join(out)
