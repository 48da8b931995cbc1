"""The decisions a diagnosis hands back, as enums whose values are the words of its JSON and verdicts.

:class:`Answer` is the answer to *is this valve sticky?*; :class:`Strength` qualifies a stiction answer by
whether its evidence survives a drifting-load noise model (see :mod:`~valve_emulator.diagnosis.fit.load_check`).
Both are :class:`str` enums, so ``Answer.STICTION == "stiction"`` and they print as their words.
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["Answer", "Strength", "VALVE_FRICTION"]

#: Findings that are valve friction: the stiction of Choudhury, Thornhill & Shah (2005) and its J = 0 case,
#: a deadband.
VALVE_FRICTION = ("stiction", "deadband")


class Answer(StrEnum):
    """The answer for one loop."""

    STICTION = "stiction"
    NO_STICTION = "no stiction"
    CANNOT_TELL = "cannot tell"


class Strength(StrEnum):
    """How strong a stiction answer's evidence is."""

    STRONG = "strong"
    WEAK = "weak"
