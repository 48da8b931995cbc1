"""The decisions a diagnosis hands back, as enums whose values are the codes of its JSON.

:class:`Answer` is the answer to *is this valve sticky?*; :class:`Strength` qualifies a stiction answer by
whether its evidence survives a drifting-load noise model (see :mod:`~valve_emulator.diagnosis.fit.load_check`);
:class:`Reason` names why, one short code per cause (each with a sentence in the output). All are
:class:`str` enums, so ``Answer.NO_STICTION == "no_stiction"``; :attr:`Answer.words` is the phrase the verdict
sentences use ("no stiction").
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["Answer", "Strength", "Reason", "VALVE_FRICTION"]

#: Findings that are valve friction: the stiction of Choudhury, Thornhill & Shah (2005) and its J = 0 case,
#: a deadband.
VALVE_FRICTION = ("stiction", "deadband")


class Answer(StrEnum):
    """The answer for one loop (deadband, friction with J = 0, counts as stiction).

    ``no_response`` is a finding, not an abstention: PV holds one value while OP travels far, so the valve is not
    moving or the loop is open (a seized valve, a closed block valve, an open bypass, a dead transmitter, a
    frozen archive) — the loop needs inspecting, though the record cannot say which of these it is.
    ``cannot_tell`` is kept for records that cannot decide.
    """

    STICTION = "stiction"
    NO_STICTION = "no_stiction"
    NO_RESPONSE = "no_response"
    CANNOT_TELL = "cannot_tell"

    @property
    def needs_attention(self) -> bool:
        """Whether the answer asks someone to look at the valve (stiction, or a PV that does not respond)."""
        return self in (Answer.STICTION, Answer.NO_RESPONSE)

    @property
    def words(self) -> str:
        """The answer in words, for sentences: ``"no stiction"``."""
        return self.value.replace("_", " ")

    @classmethod
    def parse(cls, text: str) -> Answer:
        """The answer from its code or its words (``"no stiction"``, ``"no_stiction"``)."""
        return cls(str(text).strip().lower().replace(" ", "_"))


class Strength(StrEnum):
    """How strong a stiction answer's evidence is."""

    STRONG = "strong"
    WEAK = "weak"


class Reason(StrEnum):
    """Why a loop got its answer: the codes of the JSON's ``reasons`` (each paired with a sentence).

    Valve friction (``stiction``, ``deadband``) and what imitates it (``disturbance``, ``tuning``,
    ``quantization``, ``saturation``, ``characteristic``, ``actuator_lag``, ``dead_time``) are the physics of
    the findings; the others say why the data could not decide or what qualifies the answer.
    """

    STICTION = "stiction"
    DEADBAND = "deadband"
    WEAK_EVIDENCE = "weak_evidence"          # the friction does not survive a drifting-load noise model
    DISTURBANCE = "disturbance"
    TUNING = "tuning"
    QUANTIZATION = "quantization"
    SATURATION = "saturation"
    CHARACTERISTIC = "characteristic"
    ACTUATOR_LAG = "actuator_lag"
    DEAD_TIME = "dead_time"
    LINEAR = "linear"                        # a linear valve and plant explain the loop
    SMALL_BAND = "small_band"                # a band fits, but inside OP's own noise
    TOO_SHORT = "too_short"
    FLAT_PV = "flat_pv"                      # PV flat while OP barely moves
    NO_RESPONSE = "no_response"              # PV flat while OP travels far
    FLAT_OP = "flat_op"
    NO_EXCITATION = "no_excitation"
    NOT_EXPLAINED = "not_explained"          # no model predicts held-out PV better than its mean
    UNINFORMATIVE = "uninformative"          # the fit part carries no information
    PART_OF_RECORD = "part_of_record"        # answered on one half: one linear model explains neither whole
    OP_UNITS_REFUTED = "op_units_refuted"    # OP's declared travel span does not fit OP: it was dropped
