r"""What the engineer does next: one recommended action per answer, in words and as a code for the JSON.

The action follows from the answer and its cause (:func:`recommend`): a sticky valve is stroke-tested and its
positioner checked (with the S and J found); a loop that cycles through its own controller is retuned (with a
gain that gives the identified loop a gain margin of :data:`TARGET_GAIN_MARGIN` at the same integral time: the
gain margin scales as 1/Kc); a cycle the loop does not make is looked for upstream at its period; a flat or
coarsely quantised PV sends someone to the transmitter; a PV that does not answer OP, to the loop itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from valve_emulator.diagnosis.answers import Answer, Reason
from valve_emulator.diagnosis.assess.adequacy import Cycle
from valve_emulator.diagnosis.candidates.tuning import TuningAssessment

__all__ = ["Action", "recommend", "TARGET_GAIN_MARGIN"]

#: The gain margin a suggested retune aims at (a common robust choice; Ms about 1.7 for a lag-dominant loop).
TARGET_GAIN_MARGIN = 2.0


@dataclass(frozen=True)
class Action:
    """A recommended action: ``code`` (``stroke_test_valve``, ``retune``, ``find_upstream_source``,
    ``check_transmitter``, ``inspect_loop``, ``check_actuator``, ``check_valve_sizing``, ``update_model``,
    ``collect_data``, ``none``) and the sentence that says it."""

    code: str
    words: str

    def to_json(self) -> dict:
        return {"code": self.code, "words": self.words}


def _retune(tuning: TuningAssessment | None) -> str:
    """The suggested PI, when the controller was identified with a finite gain margin."""
    if tuning is None or not tuning.judged or not np.isfinite(tuning.gain_margin) or not np.isfinite(tuning.kc):
        return ""
    kc = tuning.kc * tuning.gain_margin / TARGET_GAIN_MARGIN
    ti = "" if not np.isfinite(tuning.ti) else f", Ti = {tuning.ti:.3g} s kept"
    return (f": the identified PI (Kc = {tuning.kc:.3g}, gain margin {tuning.gain_margin:.2g}) with Kc ≈ {kc:.3g}"
            f"{ti} gives the identified loop a gain margin of {TARGET_GAIN_MARGIN:g}")


def _upstream(cycle: Cycle) -> Action:
    return Action("find_upstream_source", f"look upstream for a source cycling with a period of about "
                                          f"{cycle.period:.3g} s (another loop, a pump, a cyclic load): the valve "
                                          "and the tuning do not explain the cycle")


def recommend(answer: Answer, cause: str, codes: tuple[Reason, ...], cycle: Cycle, *, friction: str = "",
              tuning: TuningAssessment | None = None) -> Action:
    """The action for an answer (``cause``: its physics, ``codes``: its reason codes, ``friction``: the S and J
    found, in words, for a stiction answer)."""
    if answer is Answer.STICTION:
        return Action("stroke_test_valve", f"stroke-test the valve in small steps and check the positioner: "
                                           f"{friction or 'valve friction was found'}")
    if answer is Answer.NO_RESPONSE:
        return Action("inspect_loop", "inspect the loop: PV does not answer OP (a seized valve, a closed block "
                                      "valve, an open bypass, a dead transmitter or a frozen archive)")
    if answer is Answer.CANNOT_TELL:
        if Reason.FLAT_PV in codes:
            return Action("check_transmitter", "check the transmitter and the archive: PV is flat")
        if Reason.LIMIT_CYCLE in codes:
            return Action("stroke_test_valve", "stroke-test the valve in small steps, or lower the controller's gain "
                                               "for a few periods: a ring of aggressive tuning dies out, a sticky "
                                               "valve's limit cycle goes on (slower), and a cycle from outside the "
                                               "loop goes on unchanged")
        if Reason.WEAK_EVIDENCE in codes and (Reason.STICTION in codes or Reason.DEADBAND in codes):
            return Action("stroke_test_valve", "stroke-test the valve in small steps: only that tells a sticky "
                                               "valve from a slowly drifting load on this record")
        return Action("collect_data", "record a longer window, or one with a set-point step, in which the "
                                      "loop moves")
    if cause == "tuning":
        return Action("retune", f"retune the controller, less aggressively{_retune(tuning)}")
    if cause == "disturbance" or (cycle.oscillating and cause == "linear"):
        return _upstream(cycle)
    if cause == "quantization":
        return Action("check_transmitter", "check the transmitter's and the archive's resolution: PV is coarsely "
                                           "quantised")
    if cause == "saturation":
        return Action("check_valve_sizing", "check the valve's sizing: it runs into a travel or flow limit")
    if cause == "actuator_lag":
        return Action("check_actuator", "check the actuator and the positioner: the valve follows OP with a lag")
    if cause in ("dead_time", "characteristic"):
        return Action("update_model", f"update the loop's model ({cause.replace('_', ' ')}) and check the tuning "
                                      "against it")
    return Action("none", "no action: the loop behaves as a linear valve and plant")
