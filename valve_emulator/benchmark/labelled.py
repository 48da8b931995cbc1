r"""A labelled set of plant recordings: reading its index, and running one window (ours and the detectors).

Index
-----
A CSV file with a header naming at least ``file`` (a path relative to the index's folder) and ``label``;
optional columns are ``tag`` (the valve or loop: windows of one valve are scored together, default the tag
the file itself names, else its stem) and ``loop_type`` (``LIC``… level loops are integrating, which only
the comparison detectors need to be told: Horch's test does not apply to them and He's fits PV there) and
``stick1`` (the plant's own stiction index, when the set ships one: it is scored beside the methods as a
baseline by :mod:`~valve_emulator.benchmark.evaluation`, never shown to the diagnosis).
Labels are case-insensitive: ``stiction``, ``sticky``, ``yes``, ``1`` and ``true`` are stiction;
``no_stiction``, ``non-stiction``, ``no stiction``, ``normal``, ``no``, ``0`` and ``false`` are not.

A folder instead of an index file: its ``index.csv`` if it has one; otherwise every file in its
sub-folders, labelled by the sub-folder's name (one containing ``non`` or starting with ``no`` is "no
stiction", one containing ``stic`` is "stiction"; any other name is an error).

One window
----------
:func:`run_window` reads the file (:func:`~valve_emulator.recordings.read_recording`, format detected), puts it on
a uniform grid (:func:`~valve_emulator.recordings.resample.regularize`), assesses it
(:func:`~valve_emulator.diagnosis.assess.decision.assess_uniform`) and runs the comparison detectors
(:func:`~valve_emulator.detectors.run_detectors`) on the same samples; it returns a plain dict, so that it
can run in a worker process.
"""

from __future__ import annotations

import csv
import os
import time
from dataclasses import dataclass
from pathlib import Path

from valve_emulator.detectors import DETECTORS, Decision, run_detectors
from valve_emulator.diagnosis.answers import Answer, Reason
from valve_emulator.diagnosis.assess.decision import assess_uniform
from valve_emulator.errors import UserError
from valve_emulator.recordings.resample import regularize

__all__ = ["Item", "read_index", "run_window", "parse_label", "INTEGRATING_TYPES"]

_POSITIVE = {"stiction", "sticky", "yes", "1", "true"}
_NEGATIVE = {"no_stiction", "non-stiction", "non_stiction", "nonstiction", "no stiction", "no-stiction", "normal",
             "no", "0", "false"}
#: Loop types (index column ``loop_type``) whose process integrates.
INTEGRATING_TYPES = ("LIC", "LC", "LT")


@dataclass(frozen=True)
class Item:
    """One window of a labelled set."""

    path: str
    label: bool            # True = stiction
    tag: str = ""          # "" = take it from the file
    loop_type: str = ""
    name: str = ""         # as written in the index (for tables)
    index: float | None = None   # the plant's own stiction index (column stick1), a baseline only


def parse_label(text: str, where: str) -> bool:
    """True for a stiction label, False for a no-stiction one; ValueError naming ``where`` otherwise."""
    key = text.strip().lower()
    if key in _POSITIVE:
        return True
    if key in _NEGATIVE:
        return False
    raise UserError(f"{where}: label {text!r} is neither stiction ({', '.join(sorted(_POSITIVE))}) nor "
                    f"no stiction ({', '.join(sorted(_NEGATIVE))})")


def _from_index(path: Path) -> list[Item]:
    base = path.parent
    with open(path, encoding="utf-8-sig", newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise UserError(f"{path}: line 1: the index is empty; expected a header with file,label[,tag,loop_type]")
    head = [c.strip().lower() for c in rows[0]]
    for need in ("file", "label"):
        if need not in head:
            raise UserError(f"{path}: line 1: the index has no {need!r} column (columns: {', '.join(head)}); "
                            "expected a header with file,label[,tag,loop_type]")
    col = {k: head.index(k) for k in ("file", "label", "tag", "loop_type", "stick1") if k in head}
    items = []
    for n, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        if len(row) < len(head):
            raise UserError(f"{path}: line {n}: {len(row)} cells, the header has {len(head)}")
        name = row[col["file"]].strip()
        file = base / name
        if not file.is_file():
            raise UserError(f"{path}: line {n}: file {name!r} not found in {base}")
        index = row[col["stick1"]].strip() if "stick1" in col else ""
        try:
            index_value = float(index) if index else None
        except ValueError:
            raise UserError(f"{path}: line {n}: stick1 {index!r} is not a number") from None
        items.append(Item(str(file), parse_label(row[col["label"]], f"{path}: line {n}"),
                          row[col["tag"]].strip() if "tag" in col else "",
                          row[col["loop_type"]].strip() if "loop_type" in col else "", name, index_value))
    if not items:
        raise UserError(f"{path}: the index lists no files")
    return items


def _from_folders(folder: Path) -> list[Item]:
    items = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        low = sub.name.lower()
        if "non" in low or low.startswith("no"):
            label = False
        elif "stic" in low:
            label = True
        else:
            raise UserError(f"{folder}: sub-folder {sub.name!r} says neither stiction nor no stiction; name it "
                            "like 'stiction_data' / 'non-stiction_data', or give an index.csv")
        for f in sorted(p for p in sub.iterdir() if p.is_file() and not p.name.startswith(".")):
            items.append(Item(str(f), label, name=f"{sub.name}/{f.name}"))
    if not items:
        raise UserError(f"{folder}: no index.csv and no recordings in labelled sub-folders")
    return items


def read_index(path: str | os.PathLike) -> list[Item]:
    """The windows of a labelled set, from an index file or a folder (see the module docstring).

    Raises
    ------
    ValueError
        A missing ``file``/``label`` column, an unknown label, a listed file that does not exist (each naming
        the index and line), or a folder without labelled recordings.
    OSError
        When the index cannot be read at all.
    """
    p = Path(path)
    if p.is_dir():
        return _from_index(p / "index.csv") if (p / "index.csv").is_file() else _from_folders(p)
    if not p.exists():
        raise UserError(f"{p}: no such file or folder; expected a labelled set's index.csv or its folder")
    return _from_index(p)


def run_window(item: Item) -> dict:
    """Read, assess and run the detectors on one window; a plain dict (see the module docstring).

    Keys: ``name``, ``tag``, ``label``, ``loop_type``, ``samples``, ``dt``, ``decision``, ``cause``,
    ``reason``, ``S``, ``J`` and their intervals, ``op_noise``, ``fit_before``, ``fit_after``, ``notes``,
    ``part_of_record`` (answered on a half of the record), ``reasons`` (the answer's reason codes),
    ``detectors`` (name → decision and reason),
    ``seconds``; or ``error`` (the reader's or the diagnosis' message) when the file cannot be used.
    """
    from valve_emulator.recordings import read_recording

    start = time.perf_counter()
    out = {"name": item.name or Path(item.path).name, "path": item.path, "label": item.label,
           "loop_type": item.loop_type, "tag": item.tag, "plant_index": item.index}
    try:
        loaded = read_recording(item.path)
        out["tag"] = item.tag or loaded.tag or Path(item.path).stem
        rec, _ = regularize(loaded.recording)
        a = assess_uniform(rec)
    except (UserError, OSError) as exc:   # an unreadable or unusable file; anything else is a bug
        out.update(error=str(exc), decision=str(Answer.CANNOT_TELL), cause="", reason=f"unusable file: {exc}",
                   detectors={n: {"decision": str(Decision.UNDETERMINED), "reason": "unusable file"}
                              for n in DETECTORS},
                   seconds=time.perf_counter() - start)
        out["tag"] = out["tag"] or Path(item.path).stem
        return out
    out.update(samples=len(rec), dt=rec.dt, op_noise=a.op_noise, notes=list(a.notes) + list(loaded.notes),
               part_of_record=Reason.PART_OF_RECORD in a.codes, reasons=[str(code) for code in a.codes],
               **a.summary())
    integrating = item.loop_type.upper() in INTEGRATING_TYPES
    dets = run_detectors(rec.op, rec.pv, dt=rec.dt, sp=rec.sp if rec.has_sp else None, integrating=integrating)
    out["detectors"] = {n: {"decision": str(r.decision), "reason": r.reason} for n, r in dets.items()}
    out["seconds"] = time.perf_counter() - start
    return out
