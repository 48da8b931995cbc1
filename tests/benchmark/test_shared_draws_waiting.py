"""tests/unseen_loops.py: a worker that waits for a draw another worker claimed diagnoses the next unclaimed draw the
run's tests need meanwhile (not one they do not name), and a draw that fails there is left to the test that reads
it. The diagnosis is replaced by a stand-in that records what it was asked; the other worker is played by files."""

from __future__ import annotations

import json

import pytest
import unseen_loops as shared
from unseen_loops import Draw

A, B, C, UNNAMED = (Draw("level_sticky", (32, i), "plant") for i in range(4))


@pytest.fixture
def run(tmp_path, monkeypatch):
    """This worker's view of a run: A claimed by the other worker, the tests naming A, B and C."""
    monkeypatch.setattr(shared, "_folder", lambda: tmp_path)
    monkeypatch.setattr(shared, "_memory", {})
    monkeypatch.setattr(shared, "NEEDED", [A, B, C])
    monkeypatch.setattr(shared, "_none_left", False)
    monkeypatch.setattr(shared, "_failed", set())
    monkeypatch.setattr(shared, "PATIENCE", 2.0)   # a worker that only waited would take A over after 2 s
    shared._files(A, tmp_path)[1].touch()
    return tmp_path


def _other_worker_finishes_a(folder):
    shared._files(A, folder)[0].write_text(json.dumps({"doc": {"draw": A.name}, "plant": {}}))


def test_a_waiting_worker_diagnoses_the_next_needed_draw_then_takes_the_awaited_one(run, monkeypatch):
    asked = []

    def diagnose(key):
        asked.append(key)
        if key == B:                       # while this worker diagnoses B, the other one finishes A
            _other_worker_finishes_a(run)
        return {"doc": {"draw": key.name}, "plant": {}}

    monkeypatch.setattr(shared, "_diagnose", diagnose)
    assert shared._record(A) == {"doc": {"draw": A.name}, "plant": {}}
    assert asked == [B]                    # one draw at a time, the next after A; C is left to whoever needs it
    assert json.loads(shared._files(B, run)[0].read_text())["doc"] == {"draw": B.name}   # shared with the other
    assert shared._record(B)["doc"] == {"draw": B.name} and asked == [B]                  # and kept here


def test_only_the_draws_the_tests_name_are_diagnosed_while_waiting(run, monkeypatch):
    asked = []
    monkeypatch.setattr(shared, "_diagnose", lambda key: asked.append(key) or {"doc": {}, "plant": {}})
    for key in (B, C):
        shared._files(key, run)[1].touch()  # the other worker has claimed every other named draw too
    sleeps = []
    monkeypatch.setattr(shared.time, "sleep", lambda s: sleeps.append(s) or _other_worker_finishes_a(run))
    assert shared._record(A)["doc"] == {"draw": A.name}
    assert asked == [] and sleeps == [0.1]   # nothing left to do but wait: UNNAMED is never diagnosed


def test_a_draw_that_fails_while_waiting_is_left_to_its_own_test(run, monkeypatch):
    asked = []

    def diagnose(key):
        asked.append(key)
        if key == B:
            _other_worker_finishes_a(run)
            raise ValueError("B cannot be diagnosed")
        return {"doc": {"draw": key.name}, "plant": {}}

    monkeypatch.setattr(shared, "_diagnose", diagnose)
    assert shared._record(A)["doc"] == {"draw": A.name}   # the wait for A does not fail for B
    assert asked == [B, C]                                # B's error set aside, the next one taken instead
    assert not shared._files(B, run)[1].exists()          # B's claim released
    with pytest.raises(ValueError, match="B cannot be diagnosed"):
        shared._record(B)                                 # B's own test meets the error
