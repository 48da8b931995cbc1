r"""A plant-wide sweep: the plant-data diagnosis of many recordings, on one machine or on a Dask cluster.

:func:`sweep` diagnoses every recording of a list of files and folders (a folder stands for the recording
files in it, :func:`recordings_in`) and returns one flat row per recording (:func:`diagnose_file`): the
answer, its strength and reason codes, S and J in OP's units, as fractions of the OP band used, and in % travel
when the span is known, the held-out fits, the time, and the whole JSON document. It runs them one after the
other, in ``jobs`` worker processes of this machine (:func:`~valve_emulator.batch.pool.run_ordered`), or on an
existing Dask distributed cluster (``scheduler``: its address, or a ``distributed`` client or cluster object; the
optional extra ``valve_emulator[cluster]``). A file that cannot be read or diagnosed is a row with its
``error``, not the end of the sweep.

:class:`SweepTable` writes the rows as CSV (one line per recording) and JSON.
"""

from __future__ import annotations

import csv
import io
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from valve_emulator.batch.pool import run_ordered
from valve_emulator.errors import UserError

__all__ = ["RECORDING_SUFFIXES", "recordings_in", "diagnose_file", "sweep", "SweepTable", "COLUMNS"]

#: File suffixes a folder's recordings may have (others, e.g. reports and figures, are skipped).
RECORDING_SUFFIXES = (".csv", ".txt", ".tsv", ".dat")
#: The summary table's columns.
COLUMNS = ("file", "answer", "strength", "reasons", "S", "J", "units", "S_band", "J_band", "S_travel", "J_travel",
           "fit_before", "fit_after", "seconds", "error")


def recordings_in(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """The recording files named by ``paths``: files as given, folders as their recording files (sorted, hidden
    files and other suffixes skipped). Raises UserError for a path that does not exist or an empty result."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.is_file() and not f.name.startswith(".")
                          and f.suffix.lower() in RECORDING_SUFFIXES)
        elif p.is_file():
            out.append(p)
        else:
            raise UserError(f"{p}: no such file or folder")
    if not out:
        raise UserError(f"no recording files ({', '.join(RECORDING_SUFFIXES)}) in {', '.join(map(str, paths))}")
    return out


def _value(doc: dict, key: str, scale: str = ""):
    """S or J from the document's friction: in OP's units, or on ``scale`` (``"band"``, ``"travel"``)."""
    fr = doc.get("friction")
    if fr is None or (scale and fr.get(scale) is None):
        return None
    return (fr[scale] if scale else fr)[key]["value"]


def diagnose_file(path: str | os.PathLike, options: dict | None = None) -> dict:
    """Diagnose one recording file without a model; a flat row (see :data:`COLUMNS`) plus ``document``, the
    JSON of :meth:`~valve_emulator.diagnosis.report.diagnosis.Diagnosis.to_json`. ``options`` are
    :func:`~valve_emulator.diagnosis.api.diagnose`'s (reader options, ``op_range``)."""
    from valve_emulator.diagnosis.api import diagnose

    start = time.perf_counter()
    row: dict = dict.fromkeys(COLUMNS)
    row["file"] = str(path)
    try:
        doc = diagnose(path, **(options or {})).to_json()
    except (UserError, OSError) as exc:   # an unreadable or unusable file; anything else is a bug
        row.update(error=str(exc), seconds=round(time.perf_counter() - start, 2), document=None)
        return row
    row.update(answer=doc["answer"], strength=doc["strength"], reasons=" ".join(r["code"] for r in doc["reasons"]),
               S=_value(doc, "S"), J=_value(doc, "J"), S_band=_value(doc, "S", "band"),
               J_band=_value(doc, "J", "band"), S_travel=_value(doc, "S", "travel"),
               J_travel=_value(doc, "J", "travel"),
               units=None if doc["friction"] is None else doc["friction"]["S"]["units"],
               fit_before=doc["fit_before"], fit_after=doc["fit_after"],
               seconds=round(time.perf_counter() - start, 2), document=doc)
    return row


def _dask_results(files: Sequence[Path], options: dict, scheduler):
    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ModuleNotFoundError as exc:  # the optional extra is missing
        raise UserError("--scheduler needs Dask distributed: pip install 'dask[distributed]' (the extra "
                        "'cluster' of valve_emulator)") from exc
    client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
    try:
        futures = {client.submit(diagnose_file, str(f), options, pure=False): i for i, f in enumerate(files)}
        for fut in dask_completed(list(futures)):
            yield futures[fut], fut.result()
    finally:
        if client is not scheduler:
            client.close()


def sweep(paths: Iterable[str | os.PathLike], *, jobs: int = 1, scheduler=None,
          progress: Callable[[int, int, dict], None] | None = None, **options) -> list[dict]:
    """Diagnose every recording of ``paths`` (see the module docstring); rows in the order of the files.

    ``progress(done, total, row)`` is called as each recording finishes (in completion order).
    """
    if jobs < 1:
        raise UserError(f"jobs must be at least 1, got {jobs}")
    files = recordings_in(paths)
    finished = 0

    def done(_: int, row: dict) -> None:
        nonlocal finished
        finished += 1
        if progress is not None:
            progress(finished, len(files), row)

    if scheduler is None:
        return run_ordered(partial(diagnose_file, options=options), [str(f) for f in files], jobs=jobs, done=done)
    rows: list[dict] = [{}] * len(files)
    for i, row in _dask_results(files, options, scheduler):
        rows[i] = row
        done(i, row)
    return rows


@dataclass(frozen=True)
class SweepTable:
    """The rows of a sweep, as CSV (:data:`COLUMNS`) and JSON (a list of rows, each with its document)."""

    rows: list[dict]

    def csv(self) -> str:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for r in self.rows:
            w.writerow({k: "" if r.get(k) is None else r[k] for k in COLUMNS})
        return buf.getvalue()

    def json(self) -> list[dict]:
        return [dict(r) for r in self.rows]

    def counts(self) -> dict[str, int]:
        """Recordings per answer (``error`` for those that could not be diagnosed)."""
        out: dict[str, int] = {}
        for r in self.rows:
            key = r["answer"] or "error"
            out[key] = out.get(key, 0) + 1
        return out
