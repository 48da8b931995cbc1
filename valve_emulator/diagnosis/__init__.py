"""Diagnosis (layer 3): where a simulation and a recording differ, which physics the model leaves out.

Subpackages, in the order a diagnosis runs:

``fit``
    one model against one recording: data preparation, the linear part (output-error identification), the
    nominal model, the signal chain, grid scoring, fitting one candidate, cross-validation, intervals.
``candidates``
    the physics the search may add, one module each, by kind (valve chain, plant, after the plant, loop).
``explain``
    *what does my model leave out?* — locate the residual, search the candidates round by round under one
    significance rule, write up the findings.
``assess``
    *is this valve sticky?* — for plant data without a model: can the data tell, and one rule from the
    findings to an :class:`~valve_emulator.diagnosis.answers.Answer`.
``report``
    the result records, JSON, Markdown and figures.

The entry point is :func:`~valve_emulator.diagnosis.api.diagnose` (also ``valve_emulator.diagnose``), which
returns a :class:`~valve_emulator.diagnosis.report.diagnosis.Diagnosis`;
:func:`~valve_emulator.diagnosis.explain.pipeline.explain` and
:func:`~valve_emulator.diagnosis.assess.decision.assess` are the two steps behind it. The names below are
imported on first use (``import valve_emulator.diagnosis`` stays light).
"""

from __future__ import annotations

from valve_emulator import _lazy

_EXPORTS = {
    "diagnose": "valve_emulator.diagnosis.api",
    "Diagnosis": "valve_emulator.diagnosis.report.diagnosis",
    "Answer": "valve_emulator.diagnosis.answers",
    "Strength": "valve_emulator.diagnosis.answers",
    "Explanation": "valve_emulator.diagnosis.explain.result",
    "Finding": "valve_emulator.diagnosis.explain.result",
    "Assessment": "valve_emulator.diagnosis.assess.result",
    "RULE": "valve_emulator.diagnosis.explain.pipeline",
    "RULE_TWOFOLD": "valve_emulator.diagnosis.explain.pipeline",
    "DELTA_BIC": "valve_emulator.diagnosis.explain.search",
    "DELTA_FIT": "valve_emulator.diagnosis.explain.search",
    "Candidate": "valve_emulator.diagnosis.candidates",
    "ChainContext": "valve_emulator.diagnosis.candidates",
    "get": "valve_emulator.diagnosis.candidates",
    "register": "valve_emulator.diagnosis.candidates",
    "registry": "valve_emulator.diagnosis.candidates",
}

__all__ = sorted(_EXPORTS)


__getattr__ = _lazy.exports(__name__, _EXPORTS, globals())
