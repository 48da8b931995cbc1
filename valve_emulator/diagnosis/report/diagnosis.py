r"""The public result of :func:`valve_emulator.diagnose`: the answer, the findings and the fitted model.

One type for both questions. With a model, a :class:`Diagnosis` wraps the explain step's
:class:`~valve_emulator.diagnosis.explain.result.Explanation` (*what does my model leave out?*); on plant
data without one it also holds the :class:`~valve_emulator.diagnosis.assess.result.Assessment` (*is this
valve sticky?*), whose explanation is the same object. Everything else is read through: the
:class:`~valve_emulator.diagnosis.answers.Answer`, the findings, the held-out fits, the JSON, the Markdown
report, the figure and :meth:`Diagnosis.predict`, a free run of the fitted loop on any OP.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from valve_emulator.config import LoopConfig
from valve_emulator.diagnosis.answers import VALVE_FRICTION, Answer, Reason, Strength
from valve_emulator.diagnosis.assess.action import Action, recommend
from valve_emulator.diagnosis.assess.adequacy import Cycle, adequacy, cycle
from valve_emulator.diagnosis.assess.decision import Decision, answer_with_model, strength_with_model
from valve_emulator.diagnosis.assess.result import Assessment
from valve_emulator.diagnosis.explain.result import Explanation, Finding
from valve_emulator.diagnosis.fit.frame import TRAVEL, Frame, robust_range
from valve_emulator.diagnosis.fit.predict import FittedLoop
from valve_emulator.diagnosis.report.twin import Twin, twin
from valve_emulator.recordings.recording import Recording

__all__ = ["Diagnosis"]


def _sig(x: float) -> float:
    return float(f"{float(x):.6g}")


#: The units of S and J as fractions of the OP band used.
BAND = "fraction of the OP band"


def _friction_json(f: Finding | None, frame: Frame) -> dict | None:
    """The valve-friction estimate: S and J, each with its 95 % interval and units (J = 0 for a deadband), in
    OP's units, when OP's travel span is known in % of travel (``travel``; null otherwise), and as fractions of
    the OP band used, OP's robust range (``band``: the same figures whatever OP's units)."""
    if f is None:
        return None

    def value(key: str, scale, units: str) -> dict:
        x = float(f.parameters.get(key, 0.0))
        lo, hi = f.intervals.get(key, (x, x))
        return {"value": _sig(scale(x)), "interval": [_sig(scale(lo)), _sig(scale(hi))], "units": units}

    same = lambda x: x  # noqa: E731
    out = {"physics": f.physics, "S": value("S", same, frame.units), "J": value("J", same, frame.units)}
    out["travel"] = None if not frame.known else {
        "S": value("S", frame.travel, TRAVEL), "J": value("J", frame.travel, TRAVEL), "span": list(frame.span),
        "span_source": frame.span_source}
    out["band"] = None if frame.band_range is None else {
        "S": value("S", frame.band, BAND), "J": value("J", frame.band, BAND), "op_band": list(frame.band_range)}
    return out


@dataclass(frozen=True, eq=False, kw_only=True)
class Diagnosis:
    """What :func:`valve_emulator.diagnose` found (see the module docstring).

    Attributes
    ----------
    recording : the recording diagnosed (on a uniform grid).
    explanation : the explain step's record (None when plant data could not support a model at all).
    assessment : the plant-data answer (None when a model was given).
    notes : what was done to the data on the way in (reader notes, resampling, a refuted OP span).
    caveats : ``(code, sentence)`` pairs that qualify any answer, after its own reasons (``op_units_refuted``).
    model : the nominal model it was run against (None for plant data); the twin takes its controller.
    pv_units : PV's engineering units, as the reader was told (for the twin).
    """

    recording: Recording
    explanation: Explanation | None
    assessment: Assessment | None = None
    notes: tuple[str, ...] = ()
    caveats: tuple[tuple[Reason, str], ...] = ()
    model: LoopConfig | None = None
    pv_units: str = ""

    # -- the answer ---------------------------------------------------------------------------------------
    @property
    def source(self) -> str:
        return self.recording.source or "recording"

    @property
    def answer(self) -> Answer:
        """Stiction, no stiction or cannot tell. Without a model: the plant-data rule's answer. With one:
        :func:`~valve_emulator.diagnosis.assess.decision.answer_with_model` (stiction when a valve-friction finding,
        :data:`VALVE_FRICTION`, was accepted, unless a healthy valve fits the record too, by plant data's rule:
        then cannot tell; else no stiction)."""
        if self.assessment is not None:
            return self.assessment.decision
        return self._with_model.answer

    @cached_property
    def _with_model(self) -> Decision:
        """The answer's decision against the nominal model (only with one)."""
        return answer_with_model(self.recording, self.explanation, self.frame)

    @cached_property
    def strength(self) -> Strength | None:
        """How strong a stiction answer is (None for other answers): on plant data, whether it survives a
        drifting-load noise model; with a model, :func:`~valve_emulator.diagnosis.assess.decision.
        strength_with_model`."""
        if self.assessment is not None:
            return self.assessment.strength
        if self.friction is None:
            return None
        return strength_with_model(self.friction, adequacy(self.recording).facts, self.fit_before, self.fit_after,
                                   self.recording)

    @property
    def findings(self) -> tuple[Finding, ...]:
        """What the model leaves out, in agreement with the answer: a valve-friction finding only under a
        stiction answer (a band inside OP noise, or a call the record cannot tell, is said in the reasons); where
        the answer rests on a valve the final model does not hold (the search's valve alternative,
        :attr:`Assessment.friction <valve_emulator.diagnosis.assess.result.Assessment>`), that one first and the
        only one (a band of the final model inside OP noise is said in the reasons)."""
        found = () if self.explanation is None else self.explanation.findings
        alternative = None if self.assessment is None else self.assessment.friction
        if self.answer is Answer.STICTION and alternative is None:
            return found
        others = tuple(f for f in found if f.physics not in VALVE_FRICTION)
        return (alternative,) + others if self.answer is Answer.STICTION else others

    @property
    def cause(self) -> str:
        """The physics behind the answer: on plant data the assessment's; with a model the valve friction, else
        the first finding, else ``linear``."""
        if self.assessment is not None:
            return self.assessment.cause
        if self.answer is Answer.CANNOT_TELL:
            return self._with_model.cause
        first = self.friction or next(iter(self.findings), None)
        return "linear" if first is None else first.physics

    @cached_property
    def oscillation(self) -> Cycle:
        """The loop's oscillation summary (period, PV and OP swings, regularity), or no oscillation."""
        return cycle(self.recording)

    @cached_property
    def action(self) -> Action:
        """What to do next (:func:`~valve_emulator.diagnosis.assess.action.recommend`)."""
        codes = tuple(code for code, _ in self.reasons)
        tuning = None if self.assessment is None else self.assessment.tuning
        return recommend(self.answer, self.cause, codes, self.oscillation, friction=self._friction_words(),
                         tuning=tuning)

    def _friction_words(self) -> str:
        """S and J with their intervals, in % of travel when known, else in OP's units."""
        doc = _friction_json(self.friction, self.frame)
        if doc is None:
            return ""
        figures = doc["travel"] or doc
        return "; ".join(f"{k} ≈ {figures[k]['value']:.3g} {figures[k]['units']} (95 % "
                         f"{figures[k]['interval'][0]:.3g}–{figures[k]['interval'][1]:.3g})" for k in ("S", "J"))

    @property
    def fit_before(self) -> float | None:
        """Held-out free-run fit (%) of the nominal (or identified linear) model; None without an explanation."""
        return None if self.explanation is None else self.explanation.fit_before

    @property
    def fit_after(self) -> float | None:
        """Held-out free-run fit (%) of the final model; None without an explanation."""
        return None if self.explanation is None else self.explanation.fit_after

    @property
    def verdict(self) -> str:
        """The sentence the command line prints (with a model and a call the record cannot tell, the answer after
        the explain step's verdict, as on plant data)."""
        if self.assessment is not None:
            return self.assessment.verdict
        if self.answer is Answer.CANNOT_TELL:
            return f"{self.explanation.verdict} — answer: {self.answer.words}: {self._with_model.reason}"
        return self.explanation.verdict

    @property
    def reasons(self) -> tuple[tuple[Reason, str], ...]:
        """``(code, sentence)`` pairs saying why: on plant data the assessment's; with a model, one per finding
        (``linear`` when there is none), after the sticky and the healthy valve a call the record cannot tell
        names; then the :attr:`caveats`."""
        if self.assessment is not None:
            return self.assessment.reasons + self.caveats
        if self.answer is Answer.CANNOT_TELL:
            return (self._with_model.reasons + tuple((Reason(f.physics), f.description) for f in self.findings)
                    + self.caveats)
        if not self.findings:
            return ((Reason.LINEAR, "no candidate physics improves the model significantly"),) + self.caveats
        return tuple((Reason(f.physics), f.description) for f in self.findings) + self.caveats

    @property
    def frame(self) -> Frame:
        """OP's units and travel span (with a model: % travel, the model's), and the OP band used."""
        if self.assessment is not None and self.assessment.frame is not None:
            return self.assessment.frame
        return Frame(span_source="model" if self.assessment is None else "assumed",
                     band_range=robust_range(self.recording.op))

    @property
    def friction(self) -> Finding | None:
        """The valve-friction finding (stiction, or a deadband: friction with J = 0), None when none was found."""
        return next((f for f in self.findings if f.physics in VALVE_FRICTION), None)

    # -- the fitted model -----------------------------------------------------------------------------------
    @property
    def fitted(self) -> FittedLoop | None:
        """The model the answer rests on, as a loop that replays any OP: the search's final model, or, where a
        stiction answer rests on the valve the search tried and did not keep (a regularly cycling loop whose
        final model has no friction: :attr:`Assessment.friction <valve_emulator.diagnosis.assess.result.
        Assessment>`), that option's model, so that :meth:`predict` and the :meth:`twin` stick as the answer
        says. None when no model was fitted."""
        e = self.explanation
        if e is None:
            return None
        alternative = e.valve_alternative
        if self.answer is Answer.STICTION and self.assessment is not None and self.assessment.friction is not None \
                and alternative is not None and alternative.fitted is not None:
            return alternative.fitted
        return e.fitted

    def predict(self, op) -> np.ndarray:
        """Free-run PV (engineering units) of :attr:`fitted` — linear part plus the found physics — for the
        controller output ``op`` (% travel, sampled at the recording's step).

        On the recorded OP it is the prediction whose held-out fit is :attr:`fit_after`, unless the answer rests
        on a valve the search did not keep (:attr:`fitted`; the report says so).
        """
        fitted = self.fitted
        if fitted is None:
            reason = "" if self.assessment is None else f" ({self.assessment.reason})"
            raise ValueError(f"{self.source}: no model was fitted: the data could not support one{reason}")
        return fitted.predict(op)

    def twin(self, *, name: str | None = None) -> Twin:
        """The loop this diagnosis found as a loop config, with a header saying where each number came from
        (:mod:`~valve_emulator.diagnosis.report.twin`); ``Twin.text()`` is the YAML file."""
        return twin(self, model=self.model, pv_units=self.pv_units, name=name)

    def to_config(self, *, name: str | None = None) -> LoopConfig:
        """The twin's :class:`~valve_emulator.config.LoopConfig`: what ``simulate`` and ``serve`` read
        (see :meth:`twin`). Raises ValueError when no model was fitted."""
        return self.twin(name=name).config

    # -- output ---------------------------------------------------------------------------------------------
    def to_json(self) -> dict:
        """The ``diagnose --json`` document, valid against :data:`~valve_emulator.diagnosis.report.schema.SCHEMA`:
        ``answer``, ``strength``, ``reasons`` (``code``, ``sentence``), ``friction`` (the valve-friction
        estimate with 95 % intervals and units, or null), ``source``, ``action`` (``code``, ``words``),
        ``oscillation`` (the summary, :class:`~valve_emulator.diagnosis.assess.adequacy.Cycle`), then
        ``fit_before``, ``fit_after``, ``findings`` (each with its parameters' 95 % ``intervals``,
        :meth:`~valve_emulator.diagnosis.explain.result.Finding.to_json`) and ``verdict``."""
        base = self.assessment.to_json() if self.assessment is not None else self.explanation.to_json()
        base["findings"] = [f.to_json() for f in self.findings]
        base["verdict"] = self.verdict
        strength = self.strength
        head = {"answer": str(self.answer), "strength": None if strength is None else str(strength),
                "reasons": [{"code": str(c), "sentence": s} for c, s in self.reasons],
                "friction": _friction_json(self.friction, self.frame), "source": self.source,
                "action": self.action.to_json(), "oscillation": self.oscillation.to_json()}
        return {**head, **base}

    def report(self, *, figure: str | None = None) -> str:
        """A Markdown report (``figure``: a path to link, relative to the report), with the notes on the data."""
        text = (self.assessment or self.explanation).report(figure=figure)
        strength = "" if self.strength is None else f" ({self.strength} evidence)"
        lines = [f"**Action:** {self.action.words}.", "", f"- answer: {self.answer.words}{strength}",
                 f"- {self.oscillation.words}", *self._left_valve(), *(f"- note: {n}" for n in self.notes)]
        head, sep, rest = text.partition("\n\n")         # the title, then the answer's (or verdict's) paragraph
        answer, sep2, rest = rest.partition("\n\n")
        return head + sep + answer + sep2 + "\n".join(lines) + "\n\n" + rest

    def _left_valve(self) -> tuple[str, ...]:
        """The report's line for a friction finding the answer rests on that the search's final model does not
        hold (the model, fits and findings below are the search's, without it)."""
        f = None if self.assessment is None else self.assessment.friction
        if f is None or self.answer is not Answer.STICTION:
            return ()
        ivs = "; ".join(f"{k} 95 % {a:.3g}–{b:.3g}" for k, (a, b) in f.intervals.items())
        return (f"- friction: {f.description} ({ivs}); the model, fits and findings below are the search's, "
                "without it",)

    def plot(self, path: str | os.PathLike, *, title: str | None = None) -> None:
        """Write the figure (PNG): the raw OP/PV trend, the phase plot, the answer with its oscillation summary
        and action, then the diagnosis' four panels; or, when the data could not support a model, the loop's
        data and the reason."""
        strength = "" if self.strength is None else f" ({self.strength} evidence)"
        words = self.oscillation.words
        summary = (words[0].upper() + words[1:], f"Action: {self.action.words}")
        title = self.source if title is None else title
        if self.explanation is not None:
            from valve_emulator.diagnosis.report.plot import plot_diagnosis

            plot_diagnosis(self.explanation, path, recording=self.recording,
                           summary=(f"Answer: {self.answer.words}{strength}", *summary), title=title)
        else:
            from valve_emulator.diagnosis.report.plot_loop import plot_loop

            plot_loop(self.recording, self.assessment, path, title=title, summary=summary)
