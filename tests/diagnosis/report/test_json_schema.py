"""The JSON a diagnosis writes is valid against the schema shipped with the package, for every kind of
answer (stiction, no stiction, no response, cannot tell and each refusal), with and without a model, and for `prove`."""

from __future__ import annotations

import functools
import json

import jsonschema
import numpy as np
import pytest
from historian import STEPS_300, simulate
from stroke_rate import TOY, StrokeRate

import valve_emulator as ve
from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.cli import main
from valve_emulator.diagnosis.candidates import base, register
from valve_emulator.diagnosis.report.schema import SCHEMA_PATH, schema

RNG = np.random.default_rng(14)


def _validate(doc: dict) -> None:
    jsonschema.validate(json.loads(json.dumps(doc)), schema(), cls=jsonschema.Draft202012Validator)


def test_the_schema_ships_with_the_package_and_is_itself_valid():
    assert SCHEMA_PATH.is_file() and SCHEMA_PATH.parent.name == "report"
    jsonschema.Draft202012Validator.check_schema(schema())


def _flat_pv():
    t = np.arange(600.0)
    return {"t": t, "op": np.linspace(20.0, 70.0, 600) + 0.1 * RNG.normal(size=600), "pv": np.full(600, 3.0)}


PLANT = {
    "stiction": lambda: simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, S=4.0, J=1.0, duration=900.0, sp_steps=STEPS_300),
    "linear": lambda: simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, duration=900.0, sp_steps=STEPS_300),
    "too short": lambda: {"t": np.arange(150.0), "op": 50 + RNG.normal(size=150), "pv": RNG.normal(size=150)},
    "no response": _flat_pv,
    "no excitation": lambda: {"t": np.arange(800.0), "op": 40 + 0.1 * RNG.normal(size=800),
                              "pv": 50 + RNG.normal(size=800), "sp": np.full(800, 50.0)},
}
EXPECTED = {"stiction": ("stiction", "stiction"), "linear": ("no_stiction", "linear"),
            "too short": ("cannot_tell", "too_short"), "no response": ("no_response", "no_response"),
            "no excitation": ("cannot_tell", "no_excitation")}


@pytest.mark.parametrize("name", list(PLANT))
def test_plant_data_documents_are_valid_and_carry_the_answer_as_codes(name):
    doc = ve.diagnose(PLANT[name]()).to_json()
    _validate(doc)
    answer, first = EXPECTED[name]
    assert doc["answer"] == answer, doc["verdict"]
    assert doc["reasons"][0]["code"] in ((first, "deadband") if first == "stiction" else (first,)), doc["reasons"]
    assert (doc["friction"] is not None) == (answer == "stiction")
    assert (doc["strength"] is not None) == (answer == "stiction")


@pytest.mark.slow
def test_a_document_with_a_model_is_valid_and_its_friction_has_intervals_and_units():
    rec, nominal, _ = generate(CASES[0])     # stiction, undershoot
    doc = ve.diagnose(rec, nominal).to_json()
    _validate(doc)
    assert doc["answer"] == "stiction" and doc["strength"] in ("strong", "weak")   # graded with a model too
    S = doc["friction"]["S"]
    assert S["interval"][0] <= S["value"] <= S["interval"][1] and S["units"]


@pytest.mark.slow
def test_prove_writes_one_valid_document_per_case(tmp_path, capsys):
    assert main(["prove", "--out", str(tmp_path), "--case", "control", "--case", "actuator lag",
                 "--duration", "900"]) in (0, 1)
    docs = sorted((tmp_path / "proof").glob("*.json"))
    assert [p.stem for p in docs] == ["actuator_lag", "control__nothing_left_out"]
    for p in docs:
        _validate(json.loads(p.read_text(encoding="utf-8")))


@functools.cache
def _linear_text() -> str:
    """The document of the linear plant's diagnosis, diagnosed once for the tests below."""
    return json.dumps(ve.diagnose(PLANT["linear"]()).to_json())


def _linear_document() -> dict:
    """A copy of its own of the linear plant's document, for a test that breaks or extends it."""
    return json.loads(_linear_text())


@pytest.mark.parametrize("breakage", [
    lambda d: d.update(answer="no stiction"),                 # words, not the code
    lambda d: d.update(strength="weak"),                      # a strength without a stiction answer
    lambda d: d["reasons"].append({"code": "gremlins", "sentence": "x"}),
    lambda d: d.pop("friction"),
])
def test_the_schema_rejects_a_broken_document(breakage):
    doc = _linear_document()
    breakage(doc)
    with pytest.raises(jsonschema.ValidationError):
        _validate(doc)


def test_the_schema_takes_its_vocabulary_from_the_candidates_registered(monkeypatch):
    """A reason code of a candidate registered later is refused before its registration and valid after."""
    doc = _linear_document()
    doc["reasons"].append({"code": TOY, "sentence": "a valve stroking slowly"})
    with pytest.raises(jsonschema.ValidationError, match=TOY):
        _validate(doc)
    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))
    register(StrokeRate())
    _validate(doc)
    assert TOY in schema()["$defs"]["physics"]["enum"]
