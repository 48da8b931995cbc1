"""``diagnose --loop-type/--integrating/--action``: what the user knows about a loop reaches the identification
of its plant, and is refused where it cannot apply."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

import valve_emulator as ve
from valve_emulator.benchmark.independent import draw
from valve_emulator.cli import main
from valve_emulator.recordings.recording import write_csv


@pytest.fixture(scope="module")
def level_loop(tmp_path_factory):
    d = tmp_path_factory.mktemp("level")
    rec, truth, nominal = draw("level_sticky", np.random.default_rng([5, 1]))
    write_csv(rec, d / "rec.csv")
    (d / "nominal.yaml").write_text(yaml.safe_dump(nominal), encoding="utf-8")
    return d, truth


def test_a_declared_loop_type_and_action_are_the_identifications_constraints(level_loop, tmp_path):
    d, truth = level_loop
    action = truth["controller"]["action"]
    out = tmp_path / "d.json"
    assert main(["diagnose", str(d / "rec.csv"), "--loop-type", "level", "--action", action, "--json", str(out),
                 "--quiet"]) == 0
    ident = json.loads(out.read_text())["identification"]
    assert ident["integrating"] is True
    assert ident["gain_sign"] == (1 if action == "reverse" else -1)
    assert any("loop type level" in c for c in ident["constraints"])
    assert any(f"{action}-acting controller, declared" in c for c in ident["constraints"])


def test_declaring_the_loop_with_a_model_is_one_error_line_naming_the_flags(level_loop, capsys):
    d, _ = level_loop
    assert main(["diagnose", str(d / "rec.csv"), "--model", str(d / "nominal.yaml"), "--loop-type", "level"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--loop-type" in err[0] and "--model" in err[0]


def test_the_python_call_refuses_an_unknown_loop_type_and_a_declaration_with_a_model(level_loop):
    d, _ = level_loop
    with pytest.raises(ValueError, match="loop_type must be one of"):
        ve.diagnose(d / "rec.csv", loop_type="tank")
    with pytest.raises(TypeError, match="only to plant data"):
        ve.diagnose(d / "rec.csv", d / "nominal.yaml", action="reverse")
