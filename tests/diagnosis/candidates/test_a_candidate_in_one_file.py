"""A new physics is one class in one file (``tests/stroke_rate.py``): registered, it is searched, named in the
reasons, the JSON (valid against the schema), the Markdown report and the figure, and the twin says what it
cannot carry.
"""

from __future__ import annotations

import json

import jsonschema
import pytest
from stroke_rate import RATE, TOY, StrokeRate, slow_valve

from valve_emulator.cli import main
from valve_emulator.config.writer import dump_loop
from valve_emulator.diagnosis.answers import Reason
from valve_emulator.diagnosis.api import diagnose
from valve_emulator.diagnosis.candidates import base, register
from valve_emulator.diagnosis.report.schema import schema


@pytest.fixture
def toy(monkeypatch):
    """The toy registered for one test, the library as it was afterwards."""
    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))
    return register(StrokeRate())


def test_a_registered_candidate_is_found_and_named_in_every_output(toy, tmp_path):
    rec, model = slow_valve()
    d = diagnose(rec, model, candidates=[TOY])
    assert [f.physics for f in d.findings] == [TOY]
    assert d.findings[0].parameters["rate"] == pytest.approx(RATE, rel=0.1)
    assert d.reasons == ((Reason(TOY), d.findings[0].description),) and str(d.reasons[0][0]) == TOY
    doc = json.loads(json.dumps(d.to_json()))
    jsonschema.validate(doc, schema(), cls=jsonschema.Draft202012Validator)
    assert [r["code"] for r in doc["reasons"]] == [TOY] and doc["findings"][0]["physics"] == TOY
    assert f"`{TOY}`" in d.report() and "stroking at most" in d.report()
    d.plot(tmp_path / "toy.png")
    assert (tmp_path / "toy.png").stat().st_size > 0


def test_a_candidate_registered_after_import_is_a_reason_code_and_an_unknown_word_is_not(toy):
    assert Reason(TOY) is Reason(TOY) and Reason(TOY) == TOY and isinstance(Reason(TOY), Reason)
    with pytest.raises(ValueError, match="not a valid Reason"):
        Reason("stroke_rates")


def test_the_command_line_writes_the_twin_and_json_of_a_registered_candidate(toy, tmp_path, capsys):
    rec, model = slow_valve()
    csv_path, yaml_path = tmp_path / "slow_valve.csv", tmp_path / "slow_valve.yaml"
    rows = zip(rec.t.tolist(), rec.op.tolist(), rec.pv.tolist())
    csv_path.write_text("t,op,pv\n" + "".join(f"{t!r},{o!r},{p!r}\n" for t, o, p in rows), encoding="utf-8")
    yaml_path.write_text(dump_loop(model), encoding="utf-8")
    out_json, out_twin = tmp_path / "d.json", tmp_path / "twin.yaml"
    assert main(["diagnose", str(csv_path), "--model", str(yaml_path), "--json", str(out_json),
                 "--twin", str(out_twin), "--quiet"]) == 0
    doc = json.loads(out_json.read_text(encoding="utf-8"))
    jsonschema.validate(doc, schema(), cls=jsonschema.Draft202012Validator)
    assert TOY in {f["physics"] for f in doc["findings"]}
    assert f"# Left out: the {TOY} finding (valve slot)" in out_twin.read_text(encoding="utf-8")
