r"""The answer for one plant loop: stiction, no stiction (and why), no response (inspect it), or cannot tell.

An :class:`Assessment` is the frozen record :func:`~valve_emulator.diagnosis.assess.decision.assess` returns;
it composes the explain step's :class:`~valve_emulator.diagnosis.explain.result.Explanation` (when the data
could support one) with the answer, its cause and reason, and the checks behind it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from valve_emulator.diagnosis.answers import Answer, Reason, Strength
from valve_emulator.diagnosis.assess.adequacy import Adequacy
from valve_emulator.diagnosis.candidates.tuning import TuningAssessment
from valve_emulator.diagnosis.explain.result import Explanation, Finding
from valve_emulator.diagnosis.explain.search import DELTA_BIC
from valve_emulator.diagnosis.fit.frame import Frame

__all__ = ["Assessment"]


@dataclass(frozen=True, eq=False, kw_only=True)
class Assessment:
    """The answer for one loop.

    Attributes
    ----------
    source : the recording's name.
    decision : the :class:`~valve_emulator.diagnosis.answers.Answer`.
    cause : the physics behind the answer (``stiction``, ``deadband``, ``disturbance``, ``tuning``,
        ``linear``, ...; ``""`` for "no response" and "cannot tell").
    reason : one sentence saying why.
    reasons : ``(code, sentence)`` pairs, the answer's own first, then what else was found (a quantised PV
        beside stiction, a weak evidence, a band inside OP noise...).
    S, J : the valve band and slip jump (OP's units, see :attr:`frame`) when the decision is stiction (J = 0
        for a deadband).
    intervals : 95 % intervals of ``S`` and ``J``.
    explanation : what the explain step found without a model (None when the data could not support it).
    adequacy : the checks of step 2.
    tuning : the loop's tuning judgement, when it was made.
    notes : what was done to the data (resampling).
    op_noise : OP noise σ (% travel).
    band : S of the valve friction the diagnosis accepted, whether or not it was called stiction (None:
        none accepted), for sensitivity studies of :data:`NOISE_BANDS`.
    load_delta_bic : that valve friction's ΔBIC under a drifting-load noise model (None: none accepted).
    frame : how OP was mapped into the search's frame, and OP's units and travel span (None when the data
        could not support a model).
    friction : the valve-friction finding a stiction answer rests on when the explanation's final model does not
        hold it (the search's valve alternative on a regularly cycling loop); None otherwise.
    seconds : wall time.
    """

    source: str
    decision: Answer
    cause: str
    reason: str
    reasons: tuple[tuple[Reason, str], ...] = ()
    S: float | None = None
    J: float | None = None
    intervals: dict = field(default_factory=dict)
    explanation: Explanation | None = None
    adequacy: Adequacy | None = None
    tuning: TuningAssessment | None = None
    notes: tuple[str, ...] = ()
    op_noise: float = float("nan")
    band: float | None = None
    load_delta_bic: float | None = None
    frame: Frame | None = None
    friction: Finding | None = None
    seconds: float = 0.0

    @property
    def codes(self) -> tuple[Reason, ...]:
        """The codes of :attr:`reasons`, in order."""
        return tuple(code for code, _ in self.reasons)

    @property
    def statement(self) -> str:
        """``"<decision>: <reason>"``, or the reason alone where it opens with the decision's words (a stiction
        call's reason opens with its kind: ``"stiction, S ≈ …"``, not ``"stiction: stiction, S ≈ …"``)."""
        words = self.decision.words
        if self.reason.startswith(words) and self.reason[len(words):len(words) + 1] in (",", " "):
            return self.reason
        return f"{words}: {self.reason}"

    @property
    def verdict(self) -> str:
        """The diagnosis' verdict (what the identified model leaves out), then the answer."""
        if self.explanation is None:
            return self.statement
        return f"{self.explanation.verdict} — answer: {self.statement}"

    @property
    def stiction(self) -> bool:
        return self.decision is Answer.STICTION

    @property
    def strong(self) -> bool | None:
        """For a stiction answer, whether its evidence survives a drifting-load noise model, on a PV fine enough
        that its steps do not imitate stick-slip (:data:`Reason.WEAK_EVIDENCE` among the reasons otherwise;
        None: no stiction answer or no load check)."""
        if not self.stiction or self.load_delta_bic is None:
            return None
        return self.load_delta_bic >= DELTA_BIC and Reason.WEAK_EVIDENCE not in self.codes

    @property
    def strength(self) -> Strength | None:
        """:attr:`strong` as a :class:`~valve_emulator.diagnosis.answers.Strength` (None: no stiction answer, or
        no load check)."""
        strong = self.strong
        return None if strong is None else (Strength.STRONG if strong else Strength.WEAK)

    def to_json(self) -> dict:
        """The diagnosis JSON (``fit_before``, ``fit_after``, ``findings``, ``verdict``) with this verdict."""
        if self.explanation is None:
            return {"fit_before": None, "fit_after": None, "findings": [], "verdict": self.verdict}
        data = self.explanation.to_json()
        data["verdict"] = self.verdict
        return data

    def summary(self) -> dict:
        """A flat record for tables: decision, cause, S, J and intervals, fits, time."""
        d = self.explanation
        iv = {f"{k}_95": [round(a, 4), round(b, 4)] for k, (a, b) in self.intervals.items()}
        return {"decision": str(self.decision), "cause": self.cause, "reason": self.reason,
                "S": None if self.S is None else round(self.S, 4), "J": None if self.J is None else round(self.J, 4),
                **iv, "fit_before": None if d is None else round(d.fit_before, 2),
                "fit_after": None if d is None else round(d.fit_after, 2), "band": self.band,
                "load_delta_bic": None if self.load_delta_bic is None else round(self.load_delta_bic, 2),
                "seconds": round(self.seconds, 2)}

    def report(self, *, figure: str | None = None) -> str:
        """Markdown: the verdict, then the diagnosis report (when there is one)."""
        head = [f"# Assessment of `{self.source}`", "", f"**Answer — {self.decision.words}:** {self.reason}", ""]
        head += [f"- note: {n}" for n in self.notes]
        if self.tuning is not None:
            head.append(f"- tuning: {self.tuning.reason}")
        if self.explanation is None:
            return "\n".join(head) + "\n"
        body = self.explanation.report(figure=figure).split("\n", 1)[1]
        return "\n".join(head) + "\n" + body
