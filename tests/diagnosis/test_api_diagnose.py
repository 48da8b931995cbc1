"""The public API, ``valve_emulator.diagnose``: one answer whatever the input form, a fitted model that predicts.

Known truth: a closed loop with a sticky valve (S = 5 %, J = 2 %) is simulated and concealed (OP and PV only,
noise in PV, the record starting mid-cycle); its nominal model has a valve without friction.
"""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis.fit.data import HELD_OUT, fit_percent
from valve_emulator.recordings import RecordingError, write_csv
from valve_emulator.simulation.loop import LoopBank

CASE = CASES[0]  # stiction, undershoot: concentration loop, dt = 1 s
ONLY = ["stiction"]  # the search restricted to the hidden physics keeps the test short


@pytest.fixture(scope="module")
def case():
    return generate(CASE, duration=1200.0)


@pytest.fixture(scope="module")
def diagnosis(case):
    rec, nominal, _ = case
    return ve.diagnose(rec, nominal, candidates=ONLY)


def _open_loop(cfg, op: np.ndarray) -> np.ndarray:
    """PV of ``cfg``'s valve and plant driven by ``op`` (the controller in manual, no noise), sample by sample."""
    cfg = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, noise=0.0))
    bank = LoopBank([cfg])
    bank.set_auto(0, False)
    pv = np.empty(op.size)
    for k, u in enumerate(op):
        bank.set_manual_op(0, float(u))
        pv[k] = bank.run(1)["pv"][0, 0]
    return pv


def test_the_hidden_stiction_is_the_answer_with_its_parameters(diagnosis):
    assert diagnosis.answer is ve.Answer.STICTION and diagnosis.answer == "stiction"
    (finding,) = diagnosis.findings
    assert finding.physics == "stiction"
    assert finding.parameters["S"] == pytest.approx(5.0, abs=0.5)
    assert finding.parameters["J"] == pytest.approx(2.0, abs=1.0)
    assert diagnosis.fit_after > 80.0 > diagnosis.fit_before


def test_a_path_a_recording_and_a_mapping_give_the_same_diagnosis(case, diagnosis, tmp_path):
    rec, nominal, _ = case
    path = tmp_path / "loop.csv"
    write_csv(rec, path)
    from_path = ve.diagnose(path, nominal, candidates=ONLY)
    from_arrays = ve.diagnose({"t": rec.t, "op": rec.op, "pv": rec.pv}, nominal, candidates=ONLY)
    for other in (from_path, from_arrays):
        assert other.answer == diagnosis.answer
        mine, theirs = diagnosis.to_json(), other.to_json()
        assert [f["physics"] for f in theirs["findings"]] == [f["physics"] for f in mine["findings"]]
        for a, b in zip(theirs["findings"], mine["findings"]):
            assert a["parameters"] == pytest.approx(b["parameters"], abs=1e-6)
        assert theirs["fit_after"] == pytest.approx(mine["fit_after"], abs=1e-6)


def test_predict_on_the_recorded_op_reproduces_the_reported_fit(case, diagnosis):
    rec = case[0]
    pv = diagnosis.predict(rec.op)
    a = int(round((1.0 - HELD_OUT) * len(rec)))  # the held-out last 30 %
    assert fit_percent(rec.pv[a:], pv[a:]) == pytest.approx(diagnosis.fit_after, abs=1e-6)


def test_predict_on_a_new_op_follows_the_true_loop_where_the_nominal_model_does_not(case, diagnosis):
    rec, nominal, true_cfg = case
    k = np.arange(700)
    lo, hi = np.percentile(rec.op, [10, 90])
    op = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.sin(2 * np.pi * k / 350.0) \
        + 0.15 * (hi - lo) * np.sign(np.sin(2 * np.pi * k / 97.0))
    truth = _open_loop(true_cfg, op)
    settled = slice(250, None)  # after the initial states have been forgotten; levels compared as deviations

    def rms(pv):
        d = (pv[settled] - pv[settled].mean()) - (truth[settled] - truth[settled].mean())
        return float(np.sqrt(np.mean(d ** 2)))

    fitted, nominal_only = rms(diagnosis.predict(op)), rms(_open_loop(nominal, op))
    assert fitted < 0.1 * nominal_only
    assert fitted < 0.05 * float(np.std(truth[settled]))


def test_to_json_round_trips_with_the_documented_keys(diagnosis):
    data = diagnosis.to_json()
    assert json.loads(json.dumps(data)) == data
    assert list(data) == ["answer", "strength", "reasons", "friction", "source", "action", "oscillation",
                          "fit_before", "fit_after", "findings", "verdict", "linear_part"]   # linear_part: with a model
    assert set(data["findings"][0]) == {"physics", "parameters", "intervals", "windows", "evidence"}
    assert diagnosis.report().startswith("# Diagnosis of ")


def test_the_figure_is_written(diagnosis, tmp_path):
    diagnosis.plot(tmp_path / "d.png")
    assert (tmp_path / "d.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plant_data_that_cannot_tell_keep_no_model_and_say_why():
    rng = np.random.default_rng(3)
    d = ve.diagnose({"t": np.arange(150.0), "op": 50 + rng.normal(size=150), "pv": rng.normal(size=150)})
    assert d.answer is ve.Answer.CANNOT_TELL and d.assessment is not None
    assert d.fit_before is None and d.findings == ()
    data = d.to_json()
    assert data["fit_before"] is None and data["verdict"].startswith("cannot tell: ")
    assert data["answer"] == "cannot_tell" and [r["code"] for r in data["reasons"]] == ["too_short"]
    with pytest.raises(ValueError, match="no model was fitted"):
        d.predict(np.zeros(10))


@pytest.mark.parametrize("data, message", [
    ({"t": [0.0, 1.0], "op": [1.0, 2.0]}, r"no 'pv' array"),
    ({"t": [0.0, 1.0], "pv": [1.0, 2.0]}, r"no 'op' array"),
    ({"t": [0.0, 1.0], "op": [1.0, 2.0], "pv": [1.0, 2.0], "flow": [0.0, 0.0]}, r"unknown key\(s\) 'flow'"),
    ({"t": [0.0, 1.0, 2.0], "op": [1.0, 2.0], "pv": [1.0, 2.0, 3.0]}, r"op has 2 samples but t has 3"),
])
def test_a_bad_mapping_names_the_array(data, message):
    with pytest.raises(RecordingError, match=message):
        ve.diagnose(data)


def test_bad_arguments_are_named(case, diagnosis):
    rec, nominal, _ = case
    with pytest.raises(TypeError, match="reader options \\(op\\) apply only to a recording given as a path"):
        ve.diagnose(rec, nominal, op="OUT")
    with pytest.raises(TypeError, match="only with a model"):
        ve.diagnose(rec, candidates=ONLY)
    with pytest.raises(TypeError, match="got int"):
        ve.diagnose(3)
    op = np.array(rec.op)
    op[7] = np.nan
    with pytest.raises(ValueError, match="op must be finite, got nan at index 7"):
        diagnosis.predict(op)


def test_import_stays_light_and_exports_the_public_surface():
    code = ("import sys, valve_emulator as ve; assert 'numpy' not in sys.modules, 'numpy imported'; "
            "names = ['diagnose', 'Diagnosis', 'Recording', 'read_recording', 'simulate_loop', 'load_loop', "
            "'Strength', 'UserError', 'ConfigError', '__version__']; "
            "assert set(names) <= set(dir(ve)), 'missing exports'")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert ve.Recording.__name__ == "Recording" and issubclass(ve.ConfigError, ve.UserError)
    assert not hasattr(ve, "load_config")


def test_the_diagnosis_package_imports_its_names_on_first_use_and_keeps_them():
    # valve_emulator._lazy: a name's module is imported only when the name is first asked for; the name is then
    # the package's own attribute; an unknown name is an AttributeError naming the package.
    code = ("import sys, valve_emulator.diagnosis as d\n"
            "assert 'valve_emulator.diagnosis.api' not in sys.modules, 'imported early'\n"
            "assert 'diagnose' not in vars(d)\n"
            "from valve_emulator.diagnosis.api import diagnose\n"
            "assert d.diagnose is diagnose and vars(d)['diagnose'] is diagnose\n"
            "try:\n    d.nope\nexcept AttributeError as exc:\n"
            "    assert str(exc) == \"module 'valve_emulator.diagnosis' has no attribute 'nope'\", exc\n"
            "else:\n    raise AssertionError('no AttributeError')\n")
    subprocess.run([sys.executable, "-c", code], check=True)
