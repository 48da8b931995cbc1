"""Scoring against labels: calls, the valve rule, confusion, balanced accuracy, leave-one-valve-out; the index."""

from __future__ import annotations

import pytest

from valve_emulator.benchmark.evaluation import Evaluation, misclassified
from valve_emulator.benchmark.labelled import read_index
from valve_emulator.benchmark.scorecard import (
    call,
    confusion,
    leave_one_valve_out,
    markdown_table,
    valve_calls,
    window_calls,
)


def _w(tag, label, decision, name=None, **kw):
    return {"tag": tag, "label": label, "decision": decision, "name": name or f"{tag}-{decision}",
            "detectors": {d: {"decision": kw.get(d, "undetermined"), "reason": ""}
                          for d in ("horch", "he", "bicoherence")}, **kw}


def test_calls_map_every_methods_answers():
    assert [call(d) for d in ("stiction", "no stiction", "cannot tell", "undetermined", "not applicable")] == \
        ["stiction", "no stiction", "abstain", "abstain", "abstain"]
    assert call("no_response") == "abstain"      # strictly, "no response" is not a stiction call


def test_the_headline_flags_no_response_and_the_strict_figure_counts_it_a_miss():
    # A: sticky, its windows no response and cannot tell (PV flat while OP travels; then OP barely moved);
    # B: sticky, called stiction; C: not sticky, no response (a closed block valve on a healthy valve);
    # D: not sticky, no stiction.
    res = [_w("A", True, "no_response", "a1", reasons=["no_response"], reason="r"),
           _w("A", True, "cannot_tell", "a2", reasons=["flat_pv"], reason="r"),
           _w("B", True, "stiction", "b1", S=1.0, J=0.0, cause="deadband", reason="r"),
           _w("C", False, "no_response", "c1", reasons=["no_response"], reason="r"),
           _w("D", False, "no_stiction", "d1", cause="linear", reason="r")]
    ev = Evaluation(res, source="set")
    head, strict = ev.valves("diagnosis"), ev.valves("diagnosis, strict")
    assert (head.tp, head.fn, head.fp, head.tn) == (2, 0, 1, 1) and head.coverage == 1.0
    assert (strict.tp, strict.fn, strict.fp, strict.tn) == (1, 1, 0, 2) and strict.coverage == 0.5
    wh, ws = ev.windows("diagnosis"), ev.windows("diagnosis, strict")
    assert (wh.tp, wh.fn, wh.fp, wh.tn) == (2, 1, 1, 1) and wh.balanced_accuracy == pytest.approx(0.5 * (2 / 3 + 0.5))
    assert (ws.tp, ws.fn, ws.fp, ws.tn) == (1, 2, 0, 2) and ws.coverage == pytest.approx(0.4)
    assert {tag for tag, _, _ in misclassified(res)} == {"C"}
    md = ev.markdown()
    assert "| diagnosis | 100 % | 50 % | 75 % | 100 % | 2 | 0 | 1 | 1 |" in md
    assert "| diagnosis, strict | 50 % | 100 % | 75 % | 50 % | 1 | 1 | 0 | 2 |" in md
    assert "| A |  | stiction | 2 | 0/0/1/1 | no response |" in md
    assert "#### C — labelled no stiction, called no response" in md


def test_confusion_counts_abstentions_as_not_called_and_balanced_accuracy_known_truth():
    pairs = [(True, "stiction")] * 3 + [(True, "abstain")] + [(False, "no stiction")] * 5 + [(False, "stiction")]
    c = confusion(pairs)
    assert (c.tp, c.fn, c.fp, c.tn) == (3, 1, 1, 5)
    assert c.sensitivity == 0.75 and c.specificity == pytest.approx(5 / 6)
    assert c.balanced_accuracy == pytest.approx(0.5 * (0.75 + 5 / 6))
    assert c.coverage == pytest.approx(0.9)
    assert c.rows() == [("stiction", 3, 0, 1), ("no stiction", 1, 5, 0)]


def test_the_valve_rule_half_of_the_answered_windows_and_abstentions_left_out():
    res = [_w("A", True, "stiction"), _w("A", True, "no stiction"), _w("A", True, "cannot tell"),   # 1 of 2
           _w("B", False, "stiction"), _w("B", False, "no stiction"), _w("B", False, "no stiction"),  # 1 of 3
           _w("C", False, "cannot tell")]                                                          # none
    v = valve_calls(res, lambda r: r["decision"])
    assert [v[t]["call"] for t in "ABC"] == ["stiction", "no stiction", "abstain"]
    assert v["A"]["counts"] == {"stiction": 1, "no stiction": 1, "abstain": 1}
    assert len(window_calls(res, lambda r: r["decision"])) == 7


def test_a_valve_with_two_labels_is_refused():
    with pytest.raises(ValueError, match="valve 'A' has windows labelled both"):
        valve_calls([_w("A", True, "stiction"), _w("A", False, "stiction")], lambda r: r["decision"])


def test_leave_one_valve_out_chooses_the_threshold_on_the_other_valves():
    # Each window carries a score; a threshold k calls stiction when score >= k. Valves A, B sticky (scores
    # 5, 4), C, D not (1, 6). Without D, k = 2 separates A, B from C perfectly, so D is called with k = 2 (a
    # false positive); without C, k = 2 and k = 7 tie at 50 % and the first of the grid is taken.
    res = [_w(t, lab, "", score=s) for t, lab, s in (("A", True, 5), ("B", True, 4), ("C", False, 1), ("D", False, 6))]
    c, chosen = leave_one_valve_out(res, (2.0, 5.0, 7.0), lambda r, k: "stiction" if r["score"] >= k else "no stiction")
    assert chosen == {"A": 2.0, "B": 2.0, "C": 2.0, "D": 2.0}
    assert (c.tp, c.fn, c.fp, c.tn) == (2, 0, 1, 1)


def test_misclassified_valves_and_their_representative_window():
    res = [_w("A", True, "cannot tell", "a1"), _w("A", True, "no stiction", "a2"), _w("B", False, "stiction", "b1"),
           _w("C", False, "no stiction", "c1")]
    wrong = {tag: r["name"] for tag, _, r in misclassified(res)}
    assert wrong == {"A": "a2", "B": "b1"}   # a "no stiction" answer says more than an abstention


def test_evaluation_tables_put_the_detectors_side_by_side():
    res = [_w("A", True, "stiction", horch="stiction", S=2.0, J=0.5, S_95=[1.8, 2.2], J_95=[0.3, 0.7],
              cause="stiction", reason="r"),
           _w("B", False, "no stiction", he="stiction", cause="linear", reason="r")]
    ev = Evaluation(res, seconds=3.0, jobs=2, source="set")
    text = ev.text()
    for m in ("diagnosis", "horch", "he", "bicoherence"):
        assert m in text
    md = ev.markdown()
    assert "| diagnosis | 100 % | 100 % | 100 % |" in md and "| he | 0 % | 0 % | 0 % |" in md
    assert "| A-stiction | A | stiction | stiction | 2 | 1.8–2.2 | 0.5 | 0.3–0.7 |" in md
    assert markdown_table(("a", "b"), [(0.5, 3)]) == "| a | b |\n|---|---|\n| 50 % | 3 |"


def test_the_load_check_answers_weak_stiction_calls_cannot_tell():
    # A: sticky, one strong and one weak call; B: not sticky, one weak call (a false positive as answered).
    kw = dict(cause="deadband", S=1.0, J=0.0, reason="r")
    res = [_w("A", True, "stiction", "a1", load_delta_bic=40.0, **kw),
           _w("A", True, "stiction", "a2", load_delta_bic=3.0, **kw),
           _w("B", False, "stiction", "b1", load_delta_bic=-20.0, **kw), _w("C", False, "no stiction", "c1", **kw)]
    rows = {(r[0], r[1]): r[2:] for r in Evaluation(res).load_check()}
    assert rows["as answered", "valve"][3:] == (1, 0, 1, 1)          # TP FN FP TN
    assert rows["strong calls only", "valve"][3:] == (1, 0, 0, 2)    # A still sticky (1 of 1 answered), B abstains
    assert rows["strong calls only", "window"][3:] == (1, 1, 0, 2)   # a2 becomes an abstention
    md = Evaluation(res).markdown()
    assert "| 40.0 (strong) |" in md and "| 3.0 (weak) |" in md


def test_an_index_names_its_errors_with_file_and_line(tmp_path):
    (tmp_path / "w1.csv").write_text("t,op,pv\n", encoding="utf-8")
    idx = tmp_path / "index.csv"
    idx.write_text("file,label,tag\nw1.csv,stiction,V1\n", encoding="utf-8")
    items = read_index(tmp_path)
    assert [(i.label, i.tag, i.name) for i in items] == [(True, "V1", "w1.csv")]
    idx.write_text("file,label\nw1.csv,maybe\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"index.csv: line 2: label 'maybe' is neither stiction"):
        read_index(idx)
    idx.write_text("file,label\nnope.csv,stiction\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"index.csv: line 2: file 'nope.csv' not found"):
        read_index(idx)
    idx.write_text("name,label\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"index.csv: line 1: the index has no 'file' column"):
        read_index(idx)


def test_a_folder_without_index_is_labelled_by_its_sub_folders(tmp_path):
    for sub, name in (("stiction_data", "a.txt"), ("non-stiction_data", "b.txt")):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / name).write_text("x", encoding="utf-8")
    items = read_index(tmp_path)
    assert [(i.name, i.label) for i in items] == [("non-stiction_data/b.txt", False), ("stiction_data/a.txt", True)]
    (tmp_path / "misc").mkdir()
    with pytest.raises(ValueError, match="sub-folder 'misc' says neither"):
        read_index(tmp_path)


def test_the_plant_index_is_scored_beside_the_methods_as_a_baseline(tmp_path):
    sticky = dict(S=2.0, J=0.5, cause="stiction", reason="r")
    res = [_w("A", True, "no_stiction", plant_index=0.9, cause="linear", reason="r"),
           _w("B", False, "no_stiction", plant_index=0.7, cause="linear", reason="r"),
           _w("C", False, "stiction", plant_index=0.1, **sticky), _w("D", True, "stiction", plant_index=None, **sticky)]
    ev = Evaluation(res, source="set")
    assert ev.methods[:3] == ["diagnosis", "diagnosis, strict", "plant index"]
    c = ev.valves("plant index")
    assert (c.tp, c.fn, c.fp, c.tn) == (1, 1, 1, 1) and c.coverage == pytest.approx(0.75)
    assert "plant index" in ev.markdown() and "never shown to the diagnosis" in ev.markdown()
    (tmp_path / "a.txt").write_text("x", encoding="utf-8")
    (tmp_path / "index.csv").write_text("file,label,stick1\na.txt,stiction,0.42\n", encoding="utf-8")
    assert read_index(tmp_path)[0].index == pytest.approx(0.42)
    (tmp_path / "index.csv").write_text("file,label,stick1\na.txt,stiction,high\n", encoding="utf-8")
    with pytest.raises(ValueError, match="line 2: stick1 'high' is not a number"):
        read_index(tmp_path)


def test_the_halves_check_shows_the_figures_without_answers_from_halves():
    # A: sticky, one window answered stiction on a half, one no stiction as a whole; B: not sticky, answered no
    # stiction on a half; C: not sticky, answered as a whole.
    kw = dict(cause="x", S=1.0, J=0.0, reason="r")
    res = [_w("A", True, "stiction", "a1", part_of_record=True, **kw),
           _w("A", True, "no stiction", "a2", **kw),
           _w("B", False, "no stiction", "b1", part_of_record=True, **kw),
           _w("C", False, "no stiction", "c1", **kw)]
    rows = {(r[0], r[1]): r[2:] for r in Evaluation(res).halves_check()}
    assert rows["as answered", "valve"][3:] == (1.0, 1, 0, 0, 2)       # coverage, TP FN FP TN
    assert rows["without answers from halves", "valve"][3:] == (pytest.approx(2 / 3), 0, 1, 0, 2)
    assert rows["without answers from halves", "window"][3:] == (0.5, 0, 2, 0, 2)
    assert "2 window(s) were not explained by one linear model as a whole" in Evaluation(res).markdown()


def test_the_flat_pv_check_scores_both_methods_without_the_flat_windows():
    # A: sticky, one window flat (cannot tell; the index says 0.9), one called stiction (index 0.2);
    # B: sticky, its only window flat while OP travels (no response, flagged; index 1.0); C: not sticky, answered
    # no stiction (index 0.6).
    kw = dict(cause="x", S=1.0, J=0.0, reason="r")
    res = [_w("A", True, "cannot tell", "a1", reasons=["flat_pv"], plant_index=0.9, **kw),
           _w("A", True, "stiction", "a2", reasons=["stiction"], plant_index=0.2, **kw),
           _w("B", True, "no_response", "b1", reasons=["no_response"], plant_index=1.0, **kw),
           _w("C", False, "no stiction", "c1", reasons=["linear"], plant_index=0.6, **kw)]
    rows = {r[:3]: r[3:] for r in Evaluation(res).flat_check()}
    assert rows["all windows", "diagnosis", "window"][3:] == (2, 1, 0, 1)              # TP FN FP TN
    assert rows["all windows", "plant index", "window"][3:] == (2, 1, 1, 0)
    assert rows["PV not flat", "diagnosis", "window"][3:] == (1, 0, 0, 1)
    assert rows["PV not flat", "plant index", "window"][3:] == (0, 1, 1, 0)
    assert rows["PV not flat", "diagnosis", "valve"][3:] == (1, 0, 0, 1)               # B has no window left
    md = Evaluation(res).markdown()
    assert "2 window(s) have a flat PV" in md
