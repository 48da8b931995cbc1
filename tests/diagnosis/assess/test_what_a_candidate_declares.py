"""What a candidate declares decides how plant data use it: whether it needs OP's travel span to be searched,
and where it ranks among the causes of a "no stiction" answer."""

from __future__ import annotations

from typing import ClassVar

import pytest
from stroke_rate import TOY, StrokeRate, slow_valve

from valve_emulator.diagnosis.answers import Answer, Reason
from valve_emulator.diagnosis.api import diagnose
from valve_emulator.diagnosis.candidates import base, register, registry


class StrokeRateOnTravel(StrokeRate):
    """The toy, declared as acting on travel levels (so it needs OP's travel span)."""

    needs_span: ClassVar[bool] = True


@pytest.fixture
def on_travel(monkeypatch):
    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))
    return register(StrokeRateOnTravel())


def _searched(d) -> set[str]:
    return {row.option for row in d.explanation.ranking}


def test_a_candidate_that_needs_the_span_is_searched_only_once_the_span_is_known(on_travel):
    rec, _ = slow_valve()
    unknown = diagnose(rec)
    assert TOY not in _searched(unknown) and "stiction" in _searched(unknown)
    known = diagnose(rec, op_range=(0.0, 100.0))
    assert TOY in _searched(known)
    assert known.answer is Answer.NO_STICTION and known.assessment.cause == TOY
    assert known.reasons[0] == (Reason(TOY), known.findings[0].description)


def test_the_causes_of_no_stiction_rank_as_the_rule_says():
    """Disturbance first, then a quantised PV, saturation, a characteristic, an actuator lag, a dead time; valve
    friction is the stiction answer itself and tuning is judged on its own, so neither ranks."""
    lib = registry()
    ranked = sorted((c for c in lib.values() if c.cause_rank is not None), key=lambda c: c.cause_rank)
    assert [c.name for c in ranked] == ["disturbance", "quantization", "saturation", "characteristic",
                                        "actuator_lag", "dead_time"]
    assert all(lib[name].cause_rank is None for name in ("stiction", "deadband", "tuning"))
