"""``valve-emulator diagnose`` and ``prove``: outputs, the exact JSON keys, and clear errors for bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.cli import main
from valve_emulator.recordings.recording import write_csv

CASE = next(c for c in CASES if c.name == "stiction, overshoot")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A concealed stiction recording (CSV, only t/op/pv filled) and its nominal loop config (YAML)."""
    d = tmp_path_factory.mktemp("diag")
    rec, nominal, _ = generate(CASE, duration=2300.0)
    write_csv(rec, d / "rec.csv")
    p = nominal.plant
    cfg = {"name": "nominal", "valve": {"S": 0.0, "J": 0.0},
           "plant": {"num": list(p.num), "den": list(p.den), "delay": p.delay},
           "simulation": {"dt": 1.0}}
    (d / "nominal.yaml").write_text(yaml.safe_dump(cfg), encoding="utf-8")
    return d


@pytest.mark.slow
def test_diagnose_writes_verdict_json_report_and_figure(files, tmp_path, capsys):
    out = {k: tmp_path / f"out.{k}" for k in ("json", "md", "png")}
    code = main(["diagnose", str(files / "rec.csv"), "--model", str(files / "nominal.yaml"),
                 "--json", str(out["json"]), "--report", str(out["md"]), "--plot", str(out["png"])])
    assert code == 0
    captured = capsys.readouterr()
    assert "leaves out valve stiction" in captured.out
    assert "round 1: stiction" in captured.err  # progress on the terminal
    data = json.loads(out["json"].read_text(encoding="utf-8"))
    assert list(data) == ["answer", "strength", "reasons", "friction", "source", "action", "oscillation",
                          "fit_before", "fit_after", "findings", "verdict", "linear_part"]   # linear_part: a model
    assert data["answer"] == "stiction" and data["strength"] in ("strong", "weak")   # graded with a model too
    assert data["action"]["code"] == "stroke_test_valve" and "S ≈" in data["action"]["words"]
    assert data["oscillation"]["words"]
    assert [r["code"] for r in data["reasons"]] == ["stiction"] and data["friction"]["physics"] == "stiction"
    assert [f["physics"] for f in data["findings"]] == ["stiction"]
    finding = data["findings"][0]
    assert list(finding) == ["physics", "parameters", "intervals", "windows", "evidence"]
    assert set(finding["parameters"]) == {"S", "J"}
    assert all(len(w) == 2 and w[0] <= w[1] for w in finding["windows"]) and finding["windows"]
    assert data["fit_after"] > data["fit_before"] + 20
    report = out["md"].read_text(encoding="utf-8")
    assert data["verdict"] in report and "![diagnosis figure](out.png)" in report
    assert f"**Action:** {data['action']['words']}." in report and data["oscillation"]["words"] in report
    assert out["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out["png"].stat().st_size > 20_000


@pytest.mark.slow
def test_diagnose_without_a_model_identifies_the_linear_part(files, tmp_path, capsys):
    out = tmp_path / "out.json"
    assert main(["diagnose", str(files / "rec.csv"), "--json", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    data = json.loads(out.read_text(encoding="utf-8"))
    assert data["verdict"].startswith("the linear model identified from the data leaves out valve stiction")


def _csv(tmp_path, lines: list[str]) -> str:
    p = tmp_path / "bad.csv"
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return str(p)


def _rows(n: int, start: int = 0) -> list[str]:
    return [f"{k:.1f},,{50 + np.sin(k / 7):.4f},,{np.cos(k / 9):.4f}" for k in range(start, start + n)]


BAD = {
    "missing column": (["t,sp,mv,pv"] + [f"{k}.0,,,1.0" for k in range(300)],
                       r"line 1, column 'op': missing required column"),
    "non-numeric cell": (["t,sp,op,mv,pv"] + _rows(3) + ["3.0,,abc,,0.5"] + _rows(300, 4),
                         r"line 5, column 'op' \(3\): not a number: 'abc'"),
    "time goes back": (["t,sp,op,mv,pv"] + _rows(5) + ["2.0,,50.0,,0.1"] + _rows(300, 6),
                       r"line 7, column 't' \(1\): t must increase strictly"),
    "time gap": (["t,sp,op,mv,pv"] + _rows(8) + _rows(300, 20), r"line 10, column 't' \(1\): gap in t"),
    "too few samples": (["t,sp,op,mv,pv"] + _rows(120), r"line 121: 120 data row\(s\), the diagnosis needs at least"),
}


@pytest.mark.parametrize("kind", list(BAD))
def test_bad_recording_is_one_clear_error_and_nothing_written(kind, files, tmp_path, capsys):
    lines, message = BAD[kind]
    path = _csv(tmp_path, lines)
    outs = [tmp_path / "o.json", tmp_path / "o.md", tmp_path / "o.png"]
    code = main(["diagnose", path, "--model", str(files / "nominal.yaml"), "--json", str(outs[0]),
                 "--report", str(outs[1]), "--plot", str(outs[2])])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("valve-emulator diagnose: error: ")
    assert "bad.csv" in err[0]
    import re
    assert re.search(message, err[0]), err[0]
    assert not any(p.exists() for p in outs)


def test_bad_nominal_model_is_named(files, tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nplant:\n  num: [1]\n  den: [1, 0, 0]\n", encoding="utf-8")
    assert main(["diagnose", str(files / "rec.csv"), "--model", str(bad)]) == 2
    assert "2 poles at s = 0" in capsys.readouterr().err


@pytest.mark.slow
def test_prove_runs_a_reduced_set_and_writes_the_table(tmp_path, capsys):
    code = main(["prove", "--out", str(tmp_path), "--case", "control", "--duration", "1500"])
    assert code == 0
    out = capsys.readouterr().out
    assert "control (nothing left out)" in out and "1/1 cases named correctly" in out
    md = (tmp_path / "proof.md").read_text(encoding="utf-8")
    assert "| control (nothing left out) | nothing | nothing |" in md
    assert (tmp_path / "proof" / "control__nothing_left_out.png").exists()
