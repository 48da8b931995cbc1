r"""``diagnose(recording, model=None, **options) -> Diagnosis``: the one call behind ``valve-emulator diagnose``.

>>> import valve_emulator as ve                                                     # doctest: +SKIP
>>> d = ve.diagnose("FIC101.csv", model="loop.yaml")     # what does my model leave out?
>>> d.answer, [f.physics for f in d.findings], d.fit_before, d.fit_after
>>> pv = d.predict(op)                                    # the fitted loop, replayed on another OP
>>> d = ve.diagnose("FIC101.txt", op="OUT", pv="FLOW")    # plant data: is this valve sticky?

The recording is read (a path, with the reader's options passed through), put on a uniform time grid once
(:func:`~valve_emulator.recordings.resample.regularize`), then either explained against the model
(:func:`~valve_emulator.diagnosis.explain.pipeline.explain`, through
:func:`~valve_emulator.diagnosis.assess.margins.explain_with_tuning`, which names an aggressively tuned nominal
loop's ring as tuning) or, without one, assessed
(:func:`~valve_emulator.diagnosis.assess.decision.assess_uniform`).

OP's units (:mod:`~valve_emulator.diagnosis.fit.frame`): the plant-data search always runs in a unit-free
frame of OP, so its answer does not depend on OP's units or offset, nor on PV's units, offset or sign. OP's
travel span is *declared* by ``op_range=(LO, HI)`` (OP's values at 0 and 100 % travel), by the standard
recording format or a reader told ``op_units`` (``"%"`` or ``"mA"``, converted to %), or by a model (its OP
is % travel). A declared span adds S and J in % of travel, and saturation and the flow characteristic as
candidates — unless the data refute it (:meth:`~valve_emulator.diagnosis.fit.frame.Frame.refutation`: OP
below 0 or above 100 % of the span by more than its noise, or clearly moving within less than 0.5 % of it). A
refuted span is dropped and the answer says so (reason ``op_units_refuted``, and a note naming OP's observed
range); with a model, whose OP is % travel by construction, the model is still fitted, with the same reason and
note.
S and J are always also given as fractions of the OP band used (OP's robust range).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence

from valve_emulator.config import LoopConfig, load_loop
from valve_emulator.diagnosis.answers import Reason
from valve_emulator.diagnosis.assess.adequacy import EXCITATION, adequacy
from valve_emulator.diagnosis.assess.decision import assess_uniform
from valve_emulator.diagnosis.assess.margins import explain_with_tuning
from valve_emulator.diagnosis.fit.closed_loop import Declared
from valve_emulator.diagnosis.fit.frame import Frame
from valve_emulator.diagnosis.report.diagnosis import Diagnosis
from valve_emulator.errors import UserError
from valve_emulator.recordings import MAX_GAP, Recording, RecordingError, read_recording, regularize

__all__ = ["diagnose", "ARRAYS"]

#: What a refuted travel span means for plant data (after the refutation's sentence) ...
DROPPED = ("; the declaration was dropped: the answer does not use it, and S and J are in OP's units and as a "
           "fraction of the OP band used")
#: ... and for a model, whose OP is % travel by construction.
DROPPED_MODEL = ("; the model's OP is % of travel, so its fit and findings on this recording are not to be trusted: "
                 "convert OP to % travel, or diagnose without the model")
#: The arrays a mapping may hold: required first, then optional.
ARRAYS = {"t": True, "op": True, "pv": True, "sp": False, "mv": False}


def _from_mapping(data: Mapping) -> Recording:
    missing = [k for k, required in ARRAYS.items() if required and k not in data]
    if missing:
        raise RecordingError(f"recording mapping: no {', '.join(repr(k) for k in missing)} array; it needs "
                             "'t', 'op' and 'pv' ('sp' and 'mv' are optional)")
    unknown = [k for k in data if k not in ARRAYS]
    if unknown:
        raise RecordingError(f"recording mapping: unknown key(s) {', '.join(repr(str(k)) for k in unknown)}; "
                             f"known: {', '.join(ARRAYS)}")
    try:
        return Recording(t=data["t"], sp=data.get("sp"), op=data["op"], mv=data.get("mv"), pv=data["pv"],
                         source="recording")
    except RecordingError:
        raise
    except ValueError as exc:  # names the array (e.g. "op has 10 samples but t has 12")
        raise RecordingError(f"recording mapping: {exc}") from exc


def _recording(recording, reader_options: dict) -> tuple[Recording, tuple[str, ...], str]:
    """The recording, the reader's notes, and how the file declares OP's travel span ("" if it does not)."""
    if isinstance(recording, (str, os.PathLike)):
        options = {k: v for k, v in reader_options.items() if not (k == "op_units" and v is None)}
        loaded = read_recording(recording, **{"gap_factor": MAX_GAP, **options})
        span = ("standard format" if loaded.source_format == "standard" else
                f"op_units {loaded.op_units}" if reader_options.get("op_units") is not None else "")
        return loaded.recording, tuple(loaded.notes), span
    if reader_options:
        raise TypeError(f"reader options ({', '.join(sorted(reader_options))}) apply only to a recording given "
                        "as a path")
    if isinstance(recording, Recording):
        return recording, (), ""
    if isinstance(recording, Mapping):
        return _from_mapping(recording), (), ""
    raise TypeError(f"recording must be a path, a Recording or a mapping of arrays, got {type(recording).__name__}")


def diagnose(recording, model: LoopConfig | str | os.PathLike | None = None, *,
             candidates: Sequence[str] | None = None, validation: str | None = None,
             progress: Callable[[str], None] | None = None, op_range: Sequence[float] | None = None,
             loop_type: str | None = None, integrating: bool | None = None, action: str | None = None,
             **reader_options) -> Diagnosis:
    """Diagnose one loop's recording (see the module docstring).

    Parameters
    ----------
    recording : a path (read by :func:`~valve_emulator.recordings.read_recording`; ``reader_options`` such as
        ``fmt``, ``op``, ``pv``, ``ts``, ``decimal`` are passed to it), a
        :class:`~valve_emulator.recordings.Recording`, or a mapping of arrays ``t``, ``op``, ``pv`` and
        optionally ``sp``, ``mv``.
    model : the loop the user believes in (a loop config: a YAML path or a
        :class:`~valve_emulator.config.LoopConfig`); None for plant data (the linear part is identified and the
        answer is stiction / no stiction / cannot tell).
    candidates : candidate physics to search (default: all); only with a model.
    validation : ``"split"`` or ``"twofold"`` (default: split with a model); only with a model.
    progress : called with a short message at each stage.
    op_range : OP's values at 0 and 100 % of travel, in OP's units (e.g. ``(0, 27648)`` for raw analog
        counts), when known (see the module docstring); plant data only.
    loop_type, integrating, action : plant data only: the loop's type (``level`` integrates; ``flow``,
        ``pressure``, ``temperature`` do not), whether its plant integrates, and the controller's action
        (``reverse``: OP rises as PV falls, so the process gain is positive; ``direct``), when known. The
        plant is identified under these (:mod:`~valve_emulator.diagnosis.fit.closed_loop`); without them
        the family is chosen from the data and the action read from the controller's law.

    Raises
    ------
    RecordingError
        An unreadable file, a missing array or key (named), a gap in time, too few samples with a model.
    ConfigError
        A model file that is not a valid loop config.
    """
    if model is None and (candidates is not None or validation is not None):
        raise TypeError("candidates and validation apply only with a model (plant data use the fixed rule)")
    if model is not None and op_range is not None:
        raise TypeError("op_range applies only to plant data: with a model OP is % travel")
    if model is not None and (loop_type, integrating, action) != (None, None, None):
        raise TypeError("loop_type, integrating and action apply only to plant data: a model has its own plant")
    loop = Declared(loop_type=loop_type, integrating=integrating, action=action)
    declared = _declared_span(op_range)
    cfg = load_loop(model) if isinstance(model, (str, os.PathLike)) else model
    pv_units = reader_options.get("pv_units", "")
    rec, notes, known = _recording(recording, reader_options)
    rec, note = regularize(rec)
    notes += (note,) if note else ()
    if cfg is not None:
        declared = Frame(span_source="model")
    elif declared is None and known:
        declared = Frame.travel_percent(source=known)
    refuted = "" if declared is None else declared.refutation(rec.op, moving=_moving(rec))
    if refuted:
        refuted += (DROPPED_MODEL if cfg is not None else DROPPED)
    caveats = ((Reason.OP_UNITS_REFUTED, refuted),) if refuted else ()
    notes += (refuted,) if refuted else ()
    if cfg is not None:
        explained = explain_with_tuning(rec, cfg, candidates=candidates, validation=validation, progress=progress)
        return Diagnosis(recording=rec, explanation=explained, notes=notes, caveats=caveats, model=cfg,
                         pv_units=pv_units)
    a = assess_uniform(rec, progress=progress, frame=None if refuted else declared, declared=loop)
    return Diagnosis(recording=rec, explanation=a.explanation, assessment=a, notes=notes, caveats=caveats,
                     pv_units=pv_units)


def _declared_span(op_range: Sequence[float] | None) -> Frame | None:
    """The travel span ``op_range`` declares (None without one)."""
    if op_range is None:
        return None
    if len(op_range) != 2:
        raise UserError(f"op_range must be (LO, HI), OP's values at 0 and 100 % travel; got {op_range!r}")
    return Frame.travel_percent((float(op_range[0]), float(op_range[1])), source="op_range")


def _moving(rec: Recording) -> bool:
    """Whether OP moves clearly beyond its noise: its robust range reaches :data:`EXCITATION` noise σ (the
    adequacy check's excitation by OP)."""
    return adequacy(rec).facts.get("op_range_in_noise", 0.0) >= EXCITATION
