"""``--plot`` of ``simulate`` and ``diagnose``: a figure file matplotlib cannot write is refused by flag and file
before anything is computed or written."""

from __future__ import annotations

from pathlib import Path

import pytest

from valve_emulator.cli import main

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "table1"


@pytest.mark.parametrize("name", ["x.pgn", "trend.docx"])
def test_simulate_refuses_an_unknown_figure_format_before_writing_the_csv(tmp_path, capsys, name):
    out, plot = tmp_path / "rec.csv", tmp_path / name
    code = main(["simulate", str(CONFIGS / "concentration_deadband.yaml"), "--duration", "5", "--out", str(out),
                 "--plot", str(plot)])
    err = capsys.readouterr().err
    assert code == 2
    assert f"--plot {plot}: cannot write a {plot.suffix} figure; use one of " in err and ".png" in err
    assert not out.exists() and not plot.exists()


def test_simulate_writes_a_figure_in_an_other_format_matplotlib_knows(tmp_path):
    out, plot = tmp_path / "rec.csv", tmp_path / "fig.svg"
    assert main(["simulate", str(CONFIGS / "concentration_deadband.yaml"), "--duration", "5", "--out", str(out),
                 "--plot", str(plot)]) == 0
    assert out.exists() and plot.read_text(encoding="utf-8").lstrip().startswith("<?xml")


def test_diagnose_names_the_plot_flag_for_an_unknown_figure_format(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main(["simulate", str(CONFIGS / "concentration_deadband.yaml"), "--duration", "5", "--out",
                 str(rec)]) == 0
    json_out = tmp_path / "d.json"
    code = main(["diagnose", str(rec), "--plot", str(tmp_path / "d.pgn"), "--json", str(json_out), "--quiet"])
    assert code == 2
    assert f"error: --plot {tmp_path / 'd.pgn'}: cannot write a .pgn figure" in capsys.readouterr().err
    assert not json_out.exists()


def test_diagnose_names_the_plot_flag_for_a_missing_folder(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main(["simulate", str(CONFIGS / "concentration_deadband.yaml"), "--duration", "5", "--out",
                 str(rec)]) == 0
    plot = tmp_path / "nowhere" / "d.png"
    assert main(["diagnose", str(rec), "--plot", str(plot), "--quiet"]) == 2
    assert f"error: --plot {plot}: folder {plot.parent} does not exist" in capsys.readouterr().err
