"""``valve-emulator diagnose FILE`` on plant-style files, bad input through the CLI, and ``evaluate`` end to end.

All data are made here (the project's simulator, written as the recorder's CSV, a generic CSV and the DCS
text export); nothing is read from the shared plant data.
"""

from __future__ import annotations

import csv
import json
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
from historian import STEPS_300, simulate

from valve_emulator.cli import main
from valve_emulator.recordings.recording import Recording, write_csv


def _sticky(seed: int = 1, duration: float = 1000.0) -> Recording:
    """A self-regulating loop with a sticky valve (S = 5 %, J = 2 %)."""
    return simulate([3.0], [10.0, 1.0], 10.0, 0.2, 10.0, S=5.0, J=2.0, duration=duration, seed=seed)


def _jittered(rec: Recording, *, late_every: int = 5, late: float = 0.2, gap_at: int | None = None) -> Recording:
    """As the Modbus recorder writes it: some rows a tick late (and, if asked, rows missing)."""
    t = np.array(rec.t, dtype=float)
    t[1::late_every] += late
    keep = np.ones(t.size, dtype=bool)
    if gap_at is not None:
        keep[gap_at:gap_at + 5] = False
    return Recording(t[keep], rec.sp[keep], rec.op[keep], None, rec.pv[keep], source=rec.source)


def _dcs(path, rec: Recording, tag: str = "FIC101") -> None:
    """The DCS text export of the shared plant data (5 header lines, tab separated, .MV is OP)."""
    start = datetime(2024, 6, 27, 21, 55)
    lines = [f"PROCESSDATA\t{tag} Data\tyyyy-MM-dd HH:mm:ss", f"8\t{rec.dt:g}\t{start:%Y-%m-%d %H:%M:%S}\t{len(rec)}",
             "tagname\t" + "\t".join(f"{tag}.{c}" for c in ("MV", "PV", "SV", "MODE"))
             + "\tbOpOFL\tbPvOFL\tbSpOFL\tbAutOFL",
             "desc\t阀位输出\t流量\t设定\tAut\t\t\t\t", "fsMax=1\tfsMin=0\tL=24"]
    for k in range(len(rec)):
        stamp = start + timedelta(seconds=float(rec.t[k]))
        lines.append(f"{stamp:%Y-%m-%d %H:%M:%S}\t{rec.op[k]:.6f}\t{rec.pv[k]:.6f}\t{rec.sp[k]:.3f}\t1\t0\t0\t0\t0")
    path.write_text("\r\n".join(lines) + "\r\n", encoding="utf-8")


# ------------------------------------------------------------------------------------------------- diagnose

@pytest.mark.slow
def test_diagnose_a_jittered_recorder_file_resamples_says_so_and_finds_stiction(tmp_path, capsys):
    path = tmp_path / "rec.csv"
    write_csv(_jittered(_sticky()), path)
    out = tmp_path / "out.json"
    assert main(["diagnose", str(path), "--json", str(out), "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("note: resampled onto a uniform 1 s grid: ") and "OP and SP held" in lines[0]
    assert "— answer: stiction, S ≈" in lines[1] or "— answer: stiction without slip jump (deadband), S ≈" in lines[1]
    assert "stiction: stiction" not in lines[1]
    data = json.loads(out.read_text(encoding="utf-8"))
    assert list(data) == ["answer", "strength", "reasons", "friction", "source", "action", "oscillation",
                          "fit_before", "fit_after", "findings", "verdict", "identification"]
    assert data["answer"] == "stiction" and data["strength"] in ("strong", "weak")
    S = data["friction"]["S"]
    assert S["interval"][0] <= S["value"] <= S["interval"][1]
    assert data["findings"][0]["physics"] in ("stiction", "deadband")   # the slip timing is blurred a little


def test_diagnose_refuses_a_real_gap_naming_the_line(tmp_path, capsys):
    path = tmp_path / "gap.csv"
    write_csv(_jittered(_sticky(duration=700.0), gap_at=300), path)
    assert main(["diagnose", str(path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gap.csv: line 302" in err[0] and "gap" in err[0]


@pytest.mark.slow
def test_diagnose_reads_a_generic_export_with_the_reader_flags(tmp_path, capsys):
    rec = _sticky(duration=800.0)
    rows = ["Export from historian", "unit;%;m3/h;m3/h"]
    rows.append("OUT;FLOW;FLOW.SP")
    rows += [f"{o:.4f};{p:.4f};{s:.2f}".replace(".", ",") for o, p, s in zip(rec.op, rec.pv, rec.sp)]
    path = tmp_path / "export.csv"
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    report = tmp_path / "r.md"
    code = main(["diagnose", str(path), "--op", "OUT", "--pv", "FLOW", "--sp", "FLOW.SP", "--ts", "1", "--skip", "2",
                 "--decimal", ",", "--pv-units", "m3/h", "--report", str(report), "--quiet"])
    assert code == 0
    assert "answer: stiction" in capsys.readouterr().out
    assert report.read_text(encoding="utf-8").startswith("# Assessment of ")


def test_diagnose_reads_a_dcs_export_and_answers_no_response_to_a_flat_pv(tmp_path, capsys):
    rec = simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, duration=600.0, sp_steps=STEPS_300)
    flat = Recording(rec.t, rec.sp, rec.op, None, np.zeros(len(rec)), source="flat")
    path = tmp_path / "FIC101.txt"
    _dcs(path, flat)
    plot = tmp_path / "flat.png"
    assert main(["diagnose", str(path), "--plot", str(plot), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("no response: PV is flat: it holds one value over 100 % of the record")
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


BAD_INPUT = {
    "unknown format": (b"\x00\x01\x02binary junk without columns\n" * 5, [], r"cannot detect the format"),
    "column that does not exist": (b"t,op,pv\n" + b"".join(f"{k},50,{k % 7}\n".encode() for k in range(300)),
                                   ["--format", "csv", "--op", "VALVE"],
                                   r"op='VALVE': no such column; the columns are 1: 't', 2: 'op', 3: 'pv'"),
    "mixed encodings": ("t;op;pv;备注\n".encode() + b"0;50;1;ok\n1;50;1;caf\xe9\n", ["--ts", "1"],
                        r"line 3: not UTF-8 text at byte offset .*mixes encodings"),
}


@pytest.mark.parametrize("kind", list(BAD_INPUT))
def test_bad_input_is_one_clear_error_naming_the_file_and_nothing_is_written(kind, tmp_path, capsys):
    data, flags, message = BAD_INPUT[kind]
    path = tmp_path / "bad.dat"
    path.write_bytes(data)
    outs = [tmp_path / "o.json", tmp_path / "o.md", tmp_path / "o.png"]
    code = main(["diagnose", str(path), *flags, "--json", str(outs[0]), "--report", str(outs[1]),
                 "--plot", str(outs[2]), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("valve-emulator diagnose: error: ") and "bad.dat" in err[0]
    import re
    assert re.search(message, err[0]), err[0]
    assert not any(p.exists() for p in outs)


# ------------------------------------------------------------------------------------------------- evaluate

@pytest.fixture(scope="module")
def labelled_set(tmp_path_factory):
    """Three valves: V1 sticky (two windows), V2 a linear loop, V3 labelled sticky but with a flat PV."""
    d = tmp_path_factory.mktemp("set")
    write_csv(_sticky(seed=1, duration=900.0), d / "v1a.csv")
    write_csv(_sticky(seed=2, duration=900.0), d / "v1b.csv")
    write_csv(simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, duration=900.0, sp_steps=STEPS_300), d / "v2.csv")
    rec = simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, duration=600.0, sp_steps=STEPS_300)
    _dcs(d / "v3.txt", Recording(rec.t, rec.sp, rec.op, None, np.zeros(len(rec))), tag="V3")
    (d / "index.csv").write_text("file,label,tag,loop_type\nv1a.csv,stiction,V1,FIC\nv1b.csv,stiction,V1,FIC\n"
                                 "v2.csv,no_stiction,V2,FIC\nv3.txt,stiction,V3,FIC\n", encoding="utf-8")
    return d


@pytest.mark.slow
def test_evaluate_scores_per_valve_and_window_with_the_detectors_and_writes_the_report(labelled_set, tmp_path,
                                                                                         capsys):
    report = tmp_path / "real.md"
    report.write_text("# Intro kept\n\n<!-- valve-emulator evaluate: begin -->\nold\n"
                      "<!-- valve-emulator evaluate: end -->\n\nOutro kept.\n", encoding="utf-8")
    out = tmp_path / "all.json"
    code = main(["evaluate", str(labelled_set), "--jobs", "2", "--report", str(report), "--figures",
                 str(tmp_path / "fig"), "--json", str(out), "--quiet"])
    assert code == 0
    text = capsys.readouterr().out
    assert "4 windows, 3 valves" in text and "2 job(s)" in text
    for method in ("diagnosis", "horch", "he", "bicoherence"):
        assert method in text
    results = json.loads(out.read_text(encoding="utf-8"))
    assert [r["decision"] for r in results] == ["stiction", "stiction", "no_stiction", "no_response"]
    assert all(set(r["detectors"]) == {"horch", "he", "bicoherence"} for r in results)
    md = report.read_text(encoding="utf-8")
    assert md.startswith("# Intro kept") and md.rstrip().endswith("Outro kept.") and "\nold\n" not in md
    # per valve: V1 found, V2 rightly not, V3 (flat PV while OP travels) answered no response: flagged in the
    # headline (sensitivity 2/2), a miss in the strict figure (sensitivity 1/2, specificity 1)
    assert "| diagnosis | 100 % | 100 % | 100 % |" in md
    assert "| diagnosis, strict | 50 % | 100 % | 75 % |" in md
    assert "### Misclassified valves\n\nNone." in md


def test_evaluate_refuses_a_bad_index_before_running(tmp_path, capsys):
    (tmp_path / "index.csv").write_text("file,verdict\nx.csv,stiction\n", encoding="utf-8")
    assert main(["evaluate", str(tmp_path)]) == 2
    assert "index.csv: line 1: the index has no 'label' column" in capsys.readouterr().err


def _counts_csv(path, rec: Recording) -> None:
    """A generic CSV whose OP is in raw analog counts (0..27648 = 0..100 % travel)."""
    rows = [f"{t:g},{276.48 * op:.3f},{pv:.6f}" for t, op, pv in zip(rec.t, rec.op, rec.pv)]
    path.write_text("seconds,OUT,FLOW\n" + "\n".join(rows) + "\n", encoding="utf-8")


@pytest.mark.slow
def test_diagnose_op_in_raw_counts_reports_s_and_j_in_counts_and_with_op_range_in_travel(tmp_path, capsys):
    path, out, ranged = tmp_path / "counts.csv", tmp_path / "a.json", tmp_path / "b.json"
    _counts_csv(path, _sticky())
    flags = [str(path), "--format", "csv", "--time", "seconds", "--op", "OUT", "--pv", "FLOW", "--quiet"]
    assert main(["diagnose", *flags, "--json", str(out)]) == 0
    assert main(["diagnose", *flags, "--json", str(ranged), "--op-range", "0", "27648"]) == 0
    capsys.readouterr()
    plain, known = (json.loads(p.read_text(encoding="utf-8")) for p in (out, ranged))
    assert plain["answer"] == known["answer"] == "stiction"
    assert plain["friction"]["S"]["units"] == "OP units" and plain["friction"]["travel"] is None
    assert 3.5 * 276.48 < plain["friction"]["S"]["value"] < 6.5 * 276.48     # S = 5 % travel, in counts
    travel = known["friction"]["travel"]
    assert travel["S"]["units"] == "% travel" and travel["span"] == [0, 27648] and travel["span_source"] == "op_range"
    assert travel["S"]["value"] == pytest.approx(known["friction"]["S"]["value"] / 276.48, rel=1e-3)


@pytest.mark.slow
def test_diagnose_says_when_the_data_refute_the_declared_op_units_and_answers_as_without_them(tmp_path, capsys):
    rec = _sticky()
    fraction = Recording(rec.t, rec.sp, rec.op / 100.0, None, rec.pv, source="fraction")   # OP 0..1, as % travel
    path, standard, generic = tmp_path / "FIC101.csv", tmp_path / "standard.json", tmp_path / "generic.json"
    write_csv(fraction, path)
    assert main(["diagnose", str(path), "--quiet", "--json", str(standard)]) == 0
    out = capsys.readouterr().out
    assert "note: OP ran from" in out and "(standard format)" in out and "declaration was dropped" in out
    flags = ["--format", "csv", "--time", "t", "--op", "op", "--pv", "pv", "--sp", "sp", "--quiet"]
    assert main(["diagnose", str(path), *flags, "--op-units", "%", "--json", str(generic)]) == 0
    assert "(op_units %)" in capsys.readouterr().out
    a, b = (json.loads(p.read_text(encoding="utf-8")) for p in (standard, generic))
    assert a["answer"] == b["answer"] == "stiction"
    assert [r["code"] for r in a["reasons"]] == [r["code"] for r in b["reasons"]]
    assert a["reasons"][-1]["code"] == "op_units_refuted" and a["friction"]["travel"] is None
    assert a["friction"]["band"]["S"]["value"] == pytest.approx(b["friction"]["band"]["S"]["value"], rel=1e-6)
    ranged = tmp_path / "ranged.json"                  # the span said right: kept, S in % travel
    assert main(["diagnose", str(path), *flags, "--op-range", "0", "1", "--json", str(ranged)]) == 0
    capsys.readouterr()
    c = json.loads(ranged.read_text(encoding="utf-8"))
    assert "op_units_refuted" not in [r["code"] for r in c["reasons"]]
    assert 3.5 < c["friction"]["travel"]["S"]["value"] < 6.5                     # S = 5 % travel


def test_diagnose_refuses_a_reversed_op_range_naming_it(tmp_path, capsys):
    path = tmp_path / "counts.csv"
    _counts_csv(path, _sticky(duration=400.0))
    flags = [str(path), "--format", "csv", "--time", "seconds", "--op", "OUT", "--pv", "FLOW", "--quiet"]
    assert main(["diagnose", *flags, "--op-range", "100", "0"]) == 2
    assert "must exceed" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------ plant-wide sweep

def _plant_folder(tmp_path):
    folder = tmp_path / "plant"
    folder.mkdir()
    write_csv(_sticky(duration=700.0), folder / "FIC101.csv")
    write_csv(simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, duration=900.0, sp_steps=STEPS_300), folder / "FIC102.csv")
    (folder / "FIC103.csv").write_text("t,op\n0,1\n", encoding="utf-8")        # unusable: no PV column
    (folder / "notes.md").write_text("not a recording\n", encoding="utf-8")  # skipped
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("jobs", [1, 2])
def test_diagnose_a_folder_sweeps_it_one_line_each_and_writes_the_summary(tmp_path, capsys, jobs):
    folder = _plant_folder(tmp_path)
    table, doc = tmp_path / "sweep.csv", tmp_path / "sweep.json"
    assert main(["diagnose", str(folder), "--jobs", str(jobs), "--csv", str(table), "--json", str(doc)]) == 0
    out = capsys.readouterr().out.splitlines()
    lines = [ln for ln in out if ln.startswith("[")]
    assert len(lines) == 3 and lines[-1].startswith("[####################] 3/3")
    assert any("FIC101.csv: stiction" in ln for ln in lines) and any("FIC103.csv: error:" in ln for ln in lines)
    assert "answers: error 1, no_stiction 1, stiction 1" in out
    rows = list(csv.DictReader(table.open(encoding="utf-8")))
    assert [Path(r["file"]).name for r in rows] == ["FIC101.csv", "FIC102.csv", "FIC103.csv"]
    assert [r["answer"] for r in rows] == ["stiction", "no_stiction", ""]
    assert 3.5 < float(rows[0]["S"]) < 6.5 and rows[0]["units"] == "% travel" and rows[0]["S_travel"] == rows[0]["S"]
    data = json.loads(doc.read_text(encoding="utf-8"))
    band = data[0]["document"]["friction"]["band"]["S"]["value"]             # S as a fraction of the OP band used
    assert band > 0 and float(rows[0]["S_band"]) == pytest.approx(band)
    assert data[0]["document"]["answer"] == "stiction"
    assert "FIC103.csv" in data[2]["error"] and data[2]["document"] is None


def test_a_sweep_refuses_the_flags_of_one_file(tmp_path, capsys):
    folder = _plant_folder(tmp_path)
    assert main(["diagnose", str(folder), "--plot", str(tmp_path / "x.png")]) == 2
    assert "apply to one file" in capsys.readouterr().err
    assert main(["diagnose", str(folder / "FIC101.csv"), "--jobs", "2"]) == 2
    assert "apply to a sweep" in capsys.readouterr().err
