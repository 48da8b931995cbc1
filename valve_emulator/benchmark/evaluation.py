r"""The result of ``valve-emulator evaluate``: every method scored per window and per valve, as text or Markdown.

Built from the per-window dicts of :func:`~valve_emulator.benchmark.labelled.run_window`, scored by
:mod:`~valve_emulator.benchmark.scorecard`. Methods: ``diagnosis`` (this project's assessment,
:mod:`~valve_emulator.diagnosis.assess.decision`) and the comparison detectors side by side, on the same windows.

The assessment answers *no response* where PV does not respond to OP (the valve is not moving or the loop is
open: someone must inspect it). The headline (``diagnosis``) counts that answer as flagging the valve — it
needs attention, as a sticky valve does; the strict figure beside it (``diagnosis, strict``) counts it as not
called stiction, like an abstention.

The one threshold of the assessment that was not taken from the literature or from a convention used
elsewhere in the package, :data:`~valve_emulator.diagnosis.assess.decision.NOISE_BANDS`, is also checked:
the valve-level balanced accuracy for other values, and a leave-one-valve-out estimate in which each
valve is called with the value that scores best on the other valves. So is the qualifier of a stiction call
(:mod:`~valve_emulator.diagnosis.fit.load_check`): the figures had a *weak* call (one that a drifting-load noise
model explains about as well) been answered "cannot tell".
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass, field

from valve_emulator.benchmark.scorecard import (
    ABSTAIN,
    NEGATIVE,
    POSITIVE,
    Confusion,
    call,
    confusion,
    leave_one_valve_out,
    markdown_table,
    text_table,
    valve_calls,
    window_calls,
)
from valve_emulator.detectors import DETECTORS, Decision
from valve_emulator.diagnosis.answers import Answer, Reason
from valve_emulator.diagnosis.assess.decision import NOISE_BANDS
from valve_emulator.diagnosis.explain.search import DELTA_BIC

__all__ = ["Evaluation", "METHOD", "STRICT", "PLANT_INDEX", "INDEX_THRESHOLD", "NOISE_GRID", "decision_of",
           "misclassified"]

#: Name of this project's method in the tables: the headline, where *no response* flags the valve.
METHOD = "diagnosis"
#: The same answers scored strictly: *no response* counts as not called stiction.
STRICT = "diagnosis, strict"
#: Name of the plant's own stiction index (the index file's ``stick1``) in the tables: a baseline.
PLANT_INDEX = "plant index"
#: The plant index calls stiction at or above this value (it abstains where the index has no value).
INDEX_THRESHOLD = 0.5
#: Values of NOISE_BANDS tried by the threshold check.
NOISE_GRID = (0.0, 1.0, 2.0, 3.0, 5.0, 10.0)
_LABEL = {True: POSITIVE, False: NEGATIVE}


def decision_of(method: str) -> Callable[[dict], str]:
    """Reads ``method``'s decision from a window result."""
    if method == METHOD:
        return lambda r: _headline(r["decision"])
    if method == STRICT:
        return lambda r: r["decision"]
    if method == PLANT_INDEX:
        return _index_call
    return lambda r: r["detectors"][method]["decision"]


def _headline(decision: str) -> str:
    """Our decision as the headline scores it: *no response* (inspect the valve) flags it, as stiction does."""
    return POSITIVE if decision == Answer.NO_RESPONSE else decision


def _index_call(r: dict) -> str:
    """The plant index thresholded at :data:`INDEX_THRESHOLD` (abstains where there is none)."""
    x = r.get("plant_index")
    if x is None:
        return ABSTAIN
    return POSITIVE if x >= INDEX_THRESHOLD else NEGATIVE


def _with_bands(k: float) -> Callable[[dict], str]:
    """Our binary decision had NOISE_BANDS been ``k`` (only the valve band against OP noise changes)."""
    def decide(r: dict) -> str:
        other = r["decision"] if call(r["decision"]) != POSITIVE else Answer.NO_STICTION
        if r.get("band") is None or r.get("op_noise") is None:
            return other
        return Answer.STICTION if r["band"] >= k * r["op_noise"] else other
    return decide


def _strong_only(r: dict) -> str:
    """Our decision had a weak stiction call (not surviving a drifting-load noise model) been "cannot tell"."""
    load = r.get("load_delta_bic")
    if call(r["decision"]) == POSITIVE and load is not None and load < DELTA_BIC:
        return Answer.CANNOT_TELL
    return r["decision"]


def _without_halves(r: dict) -> str:
    """Our decision had a record not explained as a whole stayed "cannot tell" (no answer from its halves)."""
    return Answer.CANNOT_TELL if r.get("part_of_record") else r["decision"]


#: Reason codes of a record whose PV does not respond: no method can tell a sticky valve from those data.
_NO_RESPONSE = frozenset({str(Reason.FLAT_PV), str(Reason.NO_RESPONSE)})


def _flat(r: dict) -> bool:
    """The window's PV is flat (our answer's reasons say so): the record holds no evidence either way."""
    return bool(_NO_RESPONSE & set(r.get("reasons", ())))


def misclassified(results: list[dict], method: str = METHOD) -> list[tuple[str, dict, dict]]:
    """``(tag, valve, representative window)`` for each valve whose call disagrees with its label.

    The representative window is the first whose own call disagrees (a missed stiction valve: the first
    window not called stiction, preferring a "no stiction" answer to an abstention, which says less).
    """
    dec = decision_of(method)
    out = []
    for tag, v in valve_calls(results, dec).items():
        if (v["call"] == POSITIVE) == v["label"]:
            continue
        wins = [r for r in results if r["tag"] == tag]
        if v["label"]:
            wrong = ([r for r in wins if call(dec(r)) == NEGATIVE]
                     or [r for r in wins if call(dec(r)) != POSITIVE])
        else:
            wrong = [r for r in wins if call(dec(r)) == POSITIVE]
        out.append((tag, v, (wrong or wins)[0]))
    return out


@dataclass
class Evaluation:
    """All scores of one evaluation run (see the module docstring)."""

    results: list[dict]
    seconds: float = 0.0
    jobs: int = 1
    source: str = ""
    figures: dict = field(default_factory=dict)   # tag -> figure path (relative to the report)

    @property
    def methods(self) -> list[str]:
        index = [PLANT_INDEX] if any(r.get("plant_index") is not None for r in self.results) else []
        return [METHOD, STRICT] + index + list(DETECTORS)

    def windows(self, method: str) -> Confusion:
        return self._windows_by(decision_of(method))

    def valves(self, method: str) -> Confusion:
        return self._valves_by(decision_of(method))

    def _windows_by(self, decide: Callable[[dict], str]) -> Confusion:
        return confusion(window_calls(self.results, decide))

    def _valves_by(self, decide: Callable[[dict], str]) -> Confusion:
        return confusion((v["label"], v["call"]) for v in valve_calls(self.results, decide).values())

    def threshold_check(self) -> tuple[list[tuple], Confusion]:
        rows = []
        for k in NOISE_GRID:
            c = self._valves_by(lambda r, k=k: _headline(_with_bands(k)(r)))
            rows.append((f"{k:g}" + (" (used)" if k == NOISE_BANDS else ""), c.sensitivity, c.specificity,
                         c.balanced_accuracy))
        lovo, _ = leave_one_valve_out(self.results, NOISE_GRID, lambda r, k: _headline(_with_bands(k)(r)))
        return rows, lovo

    def load_check(self) -> list[tuple]:
        """Per valve and per window: the answers as given, and had weak stiction calls been "cannot tell"."""
        return self._against(("strong calls only", _strong_only), coverage=False)

    def halves_check(self) -> list[tuple]:
        """Per valve and per window: the answers as given, and had no record been answered by its halves."""
        return self._against(("without answers from halves", _without_halves), coverage=True)

    def flat_check(self) -> list[tuple]:
        """Ours and the plant index per valve and per window: on every window, and on the windows whose PV
        responds (not flat: ``flat_pv``/``no_response``), where a record can show stiction at all."""
        rows = []
        responding = Evaluation([r for r in self.results if not _flat(r)])
        methods = [m for m in self.methods if m in (METHOD, PLANT_INDEX)]
        for where, ev in (("all windows", self), ("PV not flat", responding)):
            for m in methods:
                for unit, c in (("valve", ev.valves(m)), ("window", ev.windows(m))):
                    rows.append((where, m, unit, c.sensitivity, c.specificity, c.balanced_accuracy, c.tp, c.fn,
                                 c.fp, c.tn))
        return rows

    def _against(self, other: tuple[str, Callable[[dict], str]], *, coverage: bool) -> list[tuple]:
        """Rows (rule, unit, sensitivity, specificity, balanced accuracy[, coverage], TP, FN, FP, TN) of our
        answers as given and under the ``other`` (name, decision) rule, per valve and per window."""
        rows = []
        other_name, rule = other
        for name, decide in (("as answered", decision_of(METHOD)), (other_name, lambda r: _headline(rule(r)))):
            for unit, c in (("valve", self._valves_by(decide)), ("window", self._windows_by(decide))):
                rows.append((name, unit, c.sensitivity, c.specificity, c.balanced_accuracy,
                             *((c.coverage,) if coverage else ()), c.tp, c.fn, c.fp, c.tn))
        return rows

    # -- tables ---------------------------------------------------------------------------------------------
    def _summary_rows(self, unit: str) -> list[tuple]:
        rows = []
        for m in self.methods:
            c = self.valves(m) if unit == "valve" else self.windows(m)
            rows.append((m, c.sensitivity, c.specificity, c.balanced_accuracy, c.coverage, c.tp, c.fn, c.fp, c.tn))
        return rows

    _SUMMARY = ("method", "sensitivity", "specificity", "balanced accuracy", "coverage", "TP", "FN", "FP", "TN")

    def _matrix_rows(self, unit: str) -> list[tuple]:
        rows = []
        for m in self.methods:
            c = self.valves(m) if unit == "valve" else self.windows(m)
            for label, called, denied, abstained in c.rows():
                rows.append((m, label, called, denied, abstained))
        return rows

    _MATRIX = ("method", "label", "called stiction", "called no stiction", "abstained")

    def _loop_rows(self) -> list[tuple]:
        ours = valve_calls(self.results, decision_of(METHOD))
        dets = {d: valve_calls(self.results, decision_of(d)) for d in DETECTORS}
        rows = []
        for tag, v in ours.items():
            wins = [r for r in self.results if r["tag"] == tag]
            S = [r["S"] for r in wins if r.get("S") is not None]
            s_text = f"{statistics.median(S):.3g}" if S else "—"
            mark = "" if (v["call"] == POSITIVE) == v["label"] else " ✗"
            rows.append((tag, wins[0].get("loop_type", ""), _LABEL[v["label"]], len(wins),
                         "/".join(str(n) for n in _answer_counts(wins).values()), _valve_words(v, wins) + mark,
                         s_text, *(_call(dets[d][tag]["call"], ours=False) for d in DETECTORS)))
        return rows

    def _loop_header(self) -> tuple:
        return ("tag", "type", "label", "windows", "ours: stiction/no/no response/cannot tell", "ours (valve)",
                "median S %", *DETECTORS)

    def _stiction_rows(self) -> list[tuple]:
        rows = []
        for r in self.results:
            if call(r["decision"]) != POSITIVE:
                continue
            s95, j95 = r.get("S_95"), r.get("J_95")
            load = r.get("load_delta_bic")
            rows.append((r["name"], r["tag"], _LABEL[r["label"]], r["cause"], f"{r['S']:.3g}",
                         f"{s95[0]:.3g}–{s95[1]:.3g}" if s95 else "—", f"{r['J']:.3g}",
                         f"{j95[0]:.3g}–{j95[1]:.3g}" if j95 else "—",
                         "—" if load is None else f"{load:.1f} ({'strong' if load >= DELTA_BIC else 'weak'})"))
        return rows

    _STICTION = ("window", "tag", "label", "physics", "S %", "S 95 %", "J %", "J 95 %", "ΔBIC, drifting load")

    def text(self) -> str:
        """Plain-text tables for the terminal."""
        parts = [f"{len(self.results)} windows, {len(valve_calls(self.results, decision_of(METHOD)))} valves, "
                 f"{self.seconds:.0f} s with {self.jobs} job(s)", "",
                 "Per valve (stiction vs not; an abstention counts as not called stiction; 'diagnosis' counts 'no "
                 "response' as flagged, 'diagnosis, strict' as not called stiction):",
                 text_table(self._SUMMARY, self._summary_rows("valve")), "",
                 "Per window:", text_table(self._SUMMARY, self._summary_rows("window")), "",
                 "Confusion per valve (label x answer):", text_table(self._MATRIX, self._matrix_rows("valve")), "",
                 "Confusion per window:", text_table(self._MATRIX, self._matrix_rows("window")), "",
                 "Per loop:", text_table(self._loop_header(), self._loop_rows())]
        return "\n".join(parts)

    def markdown(self) -> str:
        """The results section of ``docs/real-data.md`` (generated; see ``valve-emulator evaluate``)."""
        rows, lovo = self.threshold_check()
        n_valves = len(valve_calls(self.results, decision_of(METHOD)))
        out = [f"_Generated by `valve-emulator evaluate {self.source}`: {len(self.results)} windows, {n_valves} "
               f"valves, {self.seconds:.0f} s with {self.jobs} job(s). Do not edit by hand._", "",
               "### Per valve (the headline: windows of one valve are not independent)", "",
               f"`{METHOD}` is the headline: it counts the answer *no response* (PV does not respond to OP: the valve "
               "is not moving or the loop is open, inspect it) as flagging the valve, since it needs attention as "
               f"a sticky one does; `{STRICT}` counts it as not called stiction (a miss on a sticky valve). In the "
               "confusion matrices, *called stiction* holds the flagged ones.", "",
               f"`{PLANT_INDEX}` is the plant's own stiction index (the index file's `stick1`, a grid search of a "
               f"Kano model) thresholded at {INDEX_THRESHOLD:g}: a baseline computed here by the report, never "
               "shown to the diagnosis.", "",
               markdown_table(self._SUMMARY, self._summary_rows("valve")), "",
               "### Per window", "", markdown_table(self._SUMMARY, self._summary_rows("window")), "",
               "### Confusion matrices: label × answer", "",
               "Per valve:", "", markdown_table(self._MATRIX, self._matrix_rows("valve")), "",
               "Per window:", "", markdown_table(self._MATRIX, self._matrix_rows("window")), "",
               "### Per loop", "",
               "Our window answers (stiction / no stiction / no response / cannot tell), the valve's call by the "
               "valve rule (headline: *no response* flags the valve), the "
               "median S of the windows called stiction, and each detector's valve call (undetermined: all its "
               "windows were undetermined or not applicable; ✗: our call disagrees with the label).", "",
               markdown_table(self._loop_header(), self._loop_rows()), "",
               "### Windows called stiction: S and J with 95 % intervals", "",
               markdown_table(self._STICTION, self._stiction_rows()), "",
               "### Threshold check: the OP-noise bound on S", "",
               f"Valve-level figures had `NOISE_BANDS` (S ≥ k · OP noise σ) been another k; leave-one-valve-out "
               f"(each valve called with the k of {', '.join(f'{k:g}' for k in NOISE_GRID)} that scores best on the "
               f"other valves): sensitivity {_pct(lovo.sensitivity)}, specificity {_pct(lovo.specificity)}, "
               f"balanced accuracy **{_pct(lovo.balanced_accuracy)}**.", "",
               markdown_table(("k", "sensitivity", "specificity", "balanced accuracy"), rows), "",
               "### Qualifier check: stiction calls that a drifting load explains as well", "",
               f"A stiction call is *strong* when the valve still lowers BIC by at least {DELTA_BIC:g} under a "
               "random-walk load noise model (`valve_emulator.diagnosis.fit.load_check`), *weak* otherwise. The "
               "answers count both; here is what answering \"cannot tell\" to the weak ones would give.", "",
               markdown_table(("rule", "unit", "sensitivity", "specificity", "balanced accuracy", "TP", "FN", "FP",
                               "TN"), self.load_check()), "",
               "### Halves check: records answered on a half", "",
               f"{sum(bool(r.get('part_of_record')) for r in self.results)} window(s) were not explained by one "
               "linear model as a whole and were answered on their halves (reason `part_of_record`). Had they "
               "stayed \"cannot tell\":", "",
               markdown_table(("rule", "unit", "sensitivity", "specificity", "balanced accuracy", "coverage", "TP",
                               "FN", "FP", "TN"), self.halves_check()), "",
               "### Flat-PV check: the windows a record can answer", "",
               f"{sum(_flat(r) for r in self.results)} window(s) have a flat PV (reason `flat_pv` or "
               "`no_response`): a seized valve, a closed block valve, a dead transmitter and a frozen archive "
               "give the same record. Where OP travelled far the answer is *no response* (flagged in the "
               "headline, a miss in the strict figure), where it barely moved *cannot tell* (a miss). The same "
               "scores on the other windows, for the diagnosis and the plant index alike (a secondary figure: "
               "the headline is the one above).", "",
               markdown_table(("windows", "method", "unit", "sensitivity", "specificity", "balanced accuracy",
                               "TP", "FN", "FP", "TN"), self.flat_check()), "",
               "### Misclassified valves", ""]
        wrong = misclassified(self.results)
        if not wrong:
            out.append("None.")
        for tag, v, r in wrong:
            wins = [w for w in self.results if w["tag"] == tag]
            c = _answer_counts(wins)
            out += [f"#### {tag} — labelled {_LABEL[v['label']]}, called {_valve_words(v, wins)}", "",
                    f"{len(v['windows'])} window(s): "
                    + ", ".join(f"{n} {a.words}" for a, n in c.items())
                    + f". Window shown: `{r['name']}` — "
                    f"**{Answer.parse(r['decision']).words}**: {r['reason']}", ""]
            if tag in self.figures:
                out += [f"![{tag}]({self.figures[tag]})", ""]
        return "\n".join(out)


def _answer_counts(windows: list[dict]) -> dict[Answer, int]:
    """How many of these windows got each of our answers (stiction, no stiction, no response, cannot tell)."""
    counts = dict.fromkeys((Answer.STICTION, Answer.NO_STICTION, Answer.NO_RESPONSE, Answer.CANNOT_TELL), 0)
    for r in windows:
        counts[Answer.parse(r["decision"])] += 1
    return counts


def _valve_words(v: dict, windows: list[dict]) -> str:
    """Our valve call in words: a valve flagged only by *no response* answers is "no response"."""
    if v["call"] == POSITIVE and not any(call(r["decision"]) == POSITIVE for r in windows):
        return Answer.NO_RESPONSE.words
    return _call(v["call"])


def _call(c: str, *, ours: bool = True) -> str:
    """A call in the method's own words (our abstention is "cannot tell", a detector's "undetermined")."""
    return (Answer.CANNOT_TELL.words if ours else str(Decision.UNDETERMINED)) if c == ABSTAIN else str(c)


def _pct(x: float) -> str:
    return "—" if x != x else f"{100 * x:.0f} %"
