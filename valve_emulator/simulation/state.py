"""The complete dynamic state of a stepping object, captured and put back exactly.

An operator-training simulator's snapshot ("initial condition") must hold *everything* that decides the next
samples, or a restore is not exact: for a loop bank that is the valve's position, stuck reference, direction
and rest timer, the plant's states and dead-time buffers (with their ring head), the controller's
integrator, filter, mode and last output, the disturbance generators (random-walk levels and the bit
generators' states), the pending set-point schedule, the instructor's faults and the sample counter.

Rather than a hand-kept list of fields -- which silently goes stale the day a bank grows a field -- the state
is found by walking the object's attributes:

- a writable ``numpy.ndarray`` is state (copied; restored *in place*, because compiled kernels hold
  references to the very arrays, e.g. the argument tuples of :meth:`PlantBank.kernel_args`);
- an ``int``/``float``/``bool`` (counters such as ``k`` or a block position) is state;
- a ``numpy.random.Generator`` is state: its bit generator's ``state`` mapping;
- a list of plain values (set-point schedules) is state;
- an object of one of the ``nested`` classes is walked in turn (sub-banks), ``None`` is recorded as such;
- anything else (configs, immutable characteristics, tuples of references) is not state.

:func:`capture` returns a flat mapping ``path -> value`` with paths like ``_plant/_buf``; :func:`split` and
:func:`join` turn it into arrays plus a JSON-able remainder, so a snapshot can be stored as an ``.npz`` file
without pickle.
"""

from __future__ import annotations

import copy
import json
import numbers
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from valve_emulator.errors import UserError

__all__ = ["StateMismatch", "capture", "restore", "split", "join"]

_GEN = "__generator__"
_NONE = "__none__"


class StateMismatch(UserError):
    """A captured state that does not fit the object (another config): ``path`` names the field."""

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(message)
        self.path = path


def _plain(value: Any) -> bool:
    if isinstance(value, (bool, numbers.Number, str)) or value is None:
        return True
    if isinstance(value, (list, tuple)):
        return all(_plain(v) for v in value)
    return False


def capture(obj: Any, nested: tuple[type, ...], prefix: str = "") -> dict[str, Any]:
    """The dynamic state of ``obj`` as ``{path: value}`` (copies; see the module docstring)."""
    out: dict[str, Any] = {}
    for name, value in vars(obj).items():
        path = prefix + name
        if isinstance(value, np.ndarray):
            if value.flags.writeable:
                out[path] = value.copy()
        elif isinstance(value, np.random.Generator):
            out[path] = {_GEN: copy.deepcopy(value.bit_generator.state)}
        elif isinstance(value, nested):
            out.update(capture(value, nested, path + "/"))
        elif value is None:
            out[path] = _NONE
        elif isinstance(value, list) and any(isinstance(v, (np.random.Generator, nested)) for v in value):
            for i, v in enumerate(value):
                if v is None:
                    out[f"{path}/{i}"] = _NONE
                elif isinstance(v, np.random.Generator):
                    out[f"{path}/{i}"] = {_GEN: copy.deepcopy(v.bit_generator.state)}
                else:
                    out.update(capture(v, nested, f"{path}/{i}/"))
        elif isinstance(value, (bool, numbers.Number)) or (isinstance(value, list) and _plain(value)):
            out[path] = copy.deepcopy(value.item() if isinstance(value, np.generic) else value)
    return out


def restore(obj: Any, state: Mapping[str, Any], nested: tuple[type, ...],
            make: Mapping[str, Callable[[], Any]] | None = None) -> None:
    """Put ``state`` (from :func:`capture` on an object of the same construction) back into ``obj``.

    Arrays are written in place; ``make[path]`` builds a nested object that ``obj`` has not created yet
    (lazily built sub-banks). Raises :class:`StateMismatch` when the shapes or fields differ; the check runs
    over every field before anything is written, so a mismatch changes nothing.
    """
    make = make or {}
    current = capture(obj, nested)
    for path, value in state.items():
        if path in current:
            now = current[path]
            if isinstance(value, np.ndarray) and (not isinstance(now, np.ndarray) or now.shape != value.shape
                                                  or now.dtype != value.dtype):
                raise StateMismatch(f"state field {path}: saved {getattr(value, 'shape', value)!r} does not fit "
                                    f"{getattr(now, 'shape', now)!r}", path=path)
            if not isinstance(value, np.ndarray) and not _fits(now, value):
                raise StateMismatch(f"state field {path}: saved {value!r:.80} is not of the kind of "
                                    f"{now!r:.80}", path=path)
        elif not any(path.startswith(m + "/") for m in make):
            raise StateMismatch(f"state field {path} does not exist here (another configuration?)", path=path)
    for m, build in make.items():
        saved_here = any(p.startswith(m + "/") for p in state)
        parent, _, attr = m.rpartition("/")
        owner = _resolve(obj, parent)
        if saved_here and getattr(owner, attr) is None:
            setattr(owner, attr, build())
        elif state.get(m) == _NONE:
            setattr(owner, attr, None)
    for path, value in state.items():
        parent, _, attr = path.rpartition("/")
        owner = _resolve(obj, parent)
        if isinstance(owner, list):
            index = int(attr)
            if value == _NONE:
                owner[index] = None
            else:
                owner[index].bit_generator.state = copy.deepcopy(value[_GEN])
            continue
        target = getattr(owner, attr)
        if isinstance(value, np.ndarray):
            target[...] = value
        elif isinstance(value, dict) and _GEN in value:
            target.bit_generator.state = copy.deepcopy(value[_GEN])
        elif isinstance(value, str) and value == _NONE:
            if target is not None and path not in make:
                raise StateMismatch(f"state field {path}: saved None, here {type(target).__name__}", path=path)
        else:
            setattr(owner, attr, copy.deepcopy(value))


def _fits(now: Any, value: Any) -> bool:
    """Can ``value`` (e.g. read from a file) stand where the object holds ``now`` (a captured value)?

    Same kind of number (an int may stand for a float, nothing for a bool); a generator state that a bit
    generator of the same kind accepts; a list of the same length with numbers (or None) at its leaves. Checked before
    anything is written, so a damaged snapshot is refused whole instead of failing halfway or in the next step.
    """
    if isinstance(now, np.ndarray):
        return False
    if isinstance(now, bool) or isinstance(value, bool):
        return type(now) is type(value)
    if isinstance(now, int):
        return type(value) is int
    if isinstance(now, float):
        return type(value) in (int, float)
    if isinstance(now, dict) and _GEN in now:
        return isinstance(value, dict) and _GEN in value and _generator_accepts(now[_GEN], value[_GEN])
    if isinstance(now, list):
        return isinstance(value, list) and len(value) == len(now) and _numbers_at_leaves(value)
    return True


def _numbers_at_leaves(value: Any) -> bool:
    if isinstance(value, (list, tuple)):   # tuples in memory (a set-point step's (t, value)), lists from JSON
        return all(_numbers_at_leaves(v) for v in value)
    return value is None or isinstance(value, numbers.Real) and not isinstance(value, bool)


def _generator_accepts(now: Mapping[str, Any], saved: Any) -> bool:
    """Does a fresh bit generator of ``now``'s kind accept the ``saved`` state?"""
    kind = getattr(np.random, str(now.get("bit_generator")), None)
    if not (isinstance(saved, dict) and saved.get("bit_generator") == now.get("bit_generator") and kind):
        return False
    try:
        kind().state = saved
    except (TypeError, ValueError, KeyError, OverflowError):
        return False
    return True


def _resolve(obj: Any, path: str) -> Any:
    for part in filter(None, path.split("/")):
        obj = obj[int(part)] if isinstance(obj, list) else getattr(obj, part)
    return obj


def split(state: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], str]:
    """``state`` as (arrays by path, JSON text of everything else): storable without pickle."""
    arrays = {p: v for p, v in state.items() if isinstance(v, np.ndarray)}
    rest = {p: v for p, v in state.items() if not isinstance(v, np.ndarray)}
    return arrays, json.dumps(rest)


def join(arrays: Mapping[str, np.ndarray], text: str) -> dict[str, Any]:
    """Inverse of :func:`split`."""
    state: dict[str, Any] = {p: np.array(v) for p, v in arrays.items()}
    state.update(json.loads(text))
    return state
