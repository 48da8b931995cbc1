"""The decisions a diagnosis hands back, as enums whose values are the codes of its JSON.

:class:`Answer` is the answer to *is this valve sticky?*; :class:`Strength` qualifies a stiction answer by
whether its evidence survives a drifting-load noise model (see :mod:`~valve_emulator.diagnosis.fit.load_check`);
:class:`Reason` names why, one short code per cause (each with a sentence in the output): one per registered
candidate physics, then the codes that are no physics. All are
:class:`str` enums, so ``Answer.NO_STICTION == "no_stiction"``; :attr:`Answer.words` is the phrase the verdict
sentences use ("no stiction").
"""

from __future__ import annotations

from enum import StrEnum

from valve_emulator.diagnosis.candidates import registry

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


class _ReasonCode(StrEnum):
    """The behaviour of :class:`Reason`, whose members are made below from the registry."""

    @classmethod
    def _missing_(cls, value: object) -> _ReasonCode | None:
        """A candidate registered after this module was imported (``valve_emulator.diagnosis.register``) is a
        reason code too: its name joins as a member, the same object on every later lookup."""
        if not (isinstance(value, str) and value in registry()):
            return None
        member = str.__new__(cls, value)
        member._name_, member._value_ = value.upper(), value
        return cls._value2member_map_.setdefault(value, member)


#: The reason codes that are no physics: why the data could not decide, or what qualifies the answer.
_OTHER_CODES = {
    "weak_evidence": "the friction does not survive a drifting-load noise model",
    "linear": "a linear valve and plant explain the loop",
    "small_band": "a band fits, but inside OP's own noise",
    "too_short": "the record is too short",
    "flat_pv": "PV flat while OP barely moves",
    "no_response": "PV flat while OP travels far",
    "flat_op": "OP flat: the valve was never asked to move",
    "no_excitation": "no oscillation and no excitation",
    "not_explained": "no model predicts held-out PV better than their mean",
    "uninformative": "the fit part carries no information",
    "part_of_record": "answered on one half: one linear model explains neither whole",
    "op_units_refuted": "OP's declared travel span does not fit OP: it was dropped",
    "limit_cycle": "the record cycles more regularly than the identified loop rings: a limit cycle it does not make",
}

Reason = _ReasonCode("Reason", [(code.upper(), code) for code in (*registry(), *_OTHER_CODES)], module=__name__)
Reason.__doc__ = """Why a loop got its answer: the codes of the JSON's ``reasons`` (each paired with a sentence).

The physics of the findings come first, one code per registered candidate, named after it (valve friction,
``stiction`` and ``deadband``, and what imitates it: ``disturbance``, ``tuning``, ``quantization``, ...;
a candidate registered later joins when first looked up, ``Reason("its_name")``); then the codes that say
why the data could not decide or what qualifies the answer:

""" + "\n".join(f"``{code}``\n    {meaning}." for code, meaning in _OTHER_CODES.items())
