r"""Scoring answers against labels: per window and per valve, confusion matrices, balanced accuracy.

Every method — the project's assessment and each comparison detector — is scored by the same rules on the
same windows.

Calls
-----
A window's answer is a *positive call* (stiction), a *negative call* (no stiction) or an *abstention*
(our "cannot tell", a detector's "undetermined" or "not applicable"). A **valve** (all windows of one tag)
is called stiction when at least half of its windows that were not abstentions are (:data:`VALVE_SHARE`),
no stiction when fewer are, and abstains when all its windows did. Windows of one valve are not
independent (one valve may contribute many windows), so the valve is the unit the headline figures use.

Figures
-------
In the two-way ("stiction vs not") matrix an abstention counts as *not called stiction*: a method that
will not say stiction has not found it. With TP, FN, FP, TN so counted,

.. math::  \mathrm{sensitivity} = \frac{TP}{TP + FN}, \quad \mathrm{specificity} = \frac{TN}{TN + FP}, \quad
           \mathrm{balanced\ accuracy} = \tfrac12(\mathrm{sensitivity} + \mathrm{specificity}),

the mean of the per-class recalls, which does not reward a method for the larger class (35 stiction
windows against 45 others; 7 valves against 27). The three-way matrix (label × called stiction / called
no stiction / abstained) and the coverage (share of answers that are not abstentions) are reported too.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

__all__ = ["VALVE_SHARE", "Confusion", "call", "confusion", "valve_calls", "window_calls", "leave_one_valve_out",
           "markdown_table", "text_table"]

#: Share of a valve's non-abstaining windows that must call stiction for the valve to be called stiction.
VALVE_SHARE = 0.5

#: The three calls: stiction, no stiction and an abstention of any kind.
POSITIVE, NEGATIVE, ABSTAIN = "stiction", "no stiction", "abstain"


def call(decision: str) -> str:
    """Map a method's decision — an answer's code (``no_stiction``) or a detector's words (``no stiction``) —
    to a call: ``stiction``, ``no stiction`` or ``abstain``."""
    words = str(decision).replace("_", " ")
    if words == POSITIVE:
        return POSITIVE
    if words == NEGATIVE:
        return NEGATIVE
    return ABSTAIN


@dataclass(frozen=True)
class Confusion:
    """Counts of one method on one set of units (windows or valves): label × call."""

    pos_called: int = 0     # stiction, called stiction (TP)
    pos_denied: int = 0     # stiction, called no stiction
    pos_abstained: int = 0  # stiction, abstained
    neg_called: int = 0     # no stiction, called stiction (FP)
    neg_denied: int = 0     # no stiction, called no stiction
    neg_abstained: int = 0  # no stiction, abstained

    @property
    def tp(self) -> int:
        return self.pos_called

    @property
    def fn(self) -> int:
        return self.pos_denied + self.pos_abstained

    @property
    def fp(self) -> int:
        return self.neg_called

    @property
    def tn(self) -> int:
        return self.neg_denied + self.neg_abstained

    @property
    def sensitivity(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else float("nan")

    @property
    def specificity(self) -> float:
        return self.tn / (self.tn + self.fp) if self.tn + self.fp else float("nan")

    @property
    def balanced_accuracy(self) -> float:
        return 0.5 * (self.sensitivity + self.specificity)

    @property
    def coverage(self) -> float:
        n = self.tp + self.fn + self.fp + self.tn
        return 1.0 - (self.pos_abstained + self.neg_abstained) / n if n else float("nan")

    def rows(self) -> list[tuple[str, int, int, int]]:
        """The three-way matrix: (label, called stiction, called no stiction, abstained)."""
        return [(str(POSITIVE), self.pos_called, self.pos_denied, self.pos_abstained),
                (str(NEGATIVE), self.neg_called, self.neg_denied, self.neg_abstained)]


def confusion(pairs: Iterable[tuple[bool, str]]) -> Confusion:
    """Confusion of ``(label, call)`` pairs (label True = stiction; calls from :func:`call`)."""
    c = dict.fromkeys(("pos_called", "pos_denied", "pos_abstained", "neg_called", "neg_denied", "neg_abstained"), 0)
    for label, verdict in pairs:
        key = ("pos_" if label else "neg_") + {POSITIVE: "called", NEGATIVE: "denied", ABSTAIN: "abstained"}[verdict]
        c[key] += 1
    return Confusion(**c)


def window_calls(results: Sequence[dict], decision: Callable[[dict], str]) -> list[tuple[bool, str]]:
    """``(label, call)`` of every window; ``decision`` reads the method's decision from a result dict."""
    return [(r["label"], call(decision(r))) for r in results]


def valve_calls(results: Sequence[dict], decision: Callable[[dict], str]) -> OrderedDict[str, dict]:
    """Per tag: ``label``, ``call`` (the valve rule of the module docstring), ``windows`` and ``counts``.

    Raises
    ------
    ValueError
        When windows of one tag carry different labels (the valve rule needs one label per valve).
    """
    out: OrderedDict[str, dict] = OrderedDict()
    for r in results:
        v = out.setdefault(r["tag"], {"label": r["label"], "windows": [], "counts": {POSITIVE: 0, NEGATIVE: 0,
                                                                                   ABSTAIN: 0}})
        if v["label"] != r["label"]:
            raise ValueError(f"valve {r['tag']!r} has windows labelled both stiction and no stiction "
                             f"({r['name']}); score per window only, or fix the labels")
        v["windows"].append(r["name"])
        v["counts"][call(decision(r))] += 1
    for v in out.values():
        n = v["counts"][POSITIVE] + v["counts"][NEGATIVE]
        v["call"] = ABSTAIN if n == 0 else (POSITIVE if v["counts"][POSITIVE] >= VALVE_SHARE * n else NEGATIVE)
    return out


def leave_one_valve_out(results: Sequence[dict], grid: Sequence[float],
                        decide: Callable[[dict, float], str]) -> tuple[Confusion, dict[str, float]]:
    """Held-out check of a threshold chosen from the data.

    For each valve, the threshold of ``grid`` with the best valve-level balanced accuracy on all *other*
    valves is chosen (ties: the first in ``grid``), and that valve is called with it. Returns the confusion
    of those held-out calls and the threshold each valve got. ``decide(result, threshold)`` is a window's
    decision under a threshold.
    """
    tags = list(OrderedDict.fromkeys(r["tag"] for r in results))
    per = {k: valve_calls(results, lambda r, k=k: decide(r, k)) for k in grid}
    pairs, chosen = [], {}
    for tag in tags:
        def ba(k: float, tag: str = tag) -> float:
            c = confusion((v["label"], v["call"]) for t, v in per[k].items() if t != tag)
            b = c.balanced_accuracy
            return -1.0 if b != b else b
        best = max(grid, key=ba)
        chosen[tag] = best
        v = per[best][tag]
        pairs.append((v["label"], v["call"]))
    return confusion(pairs), chosen


def _fmt(cell) -> str:
    if isinstance(cell, float):
        return "—" if cell != cell else f"{100 * cell:.0f} %"
    return str(cell)


def markdown_table(header: Sequence[str], rows: Iterable[Sequence]) -> str:
    """A Markdown table; floats are shown as percentages."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(_fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def text_table(header: Sequence[str], rows: Iterable[Sequence]) -> str:
    """The same table as aligned plain text."""
    cells = [list(header)] + [[_fmt(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
