"""Snapshots of a running device: named initial conditions, persisted as files, and the backtrack ring.

A :class:`Snapshot` holds the complete dynamic state of the device's loop bank
(:meth:`~valve_emulator.simulation.loop.LoopBank.state`: valve, plant and dead-time buffers, controller,
disturbance and noise generators, sample counter), the device's tick count and the running malfunction ramps,
so that restoring it makes the device continue sample for sample as it did after the save.

:class:`SnapshotStore` keeps named snapshots, in memory and -- with a directory -- as one ``NAME.npz`` file
each (numpy arrays plus a JSON header, no pickle: loading a file runs no code), so a lesson's initial
conditions survive a restart. A snapshot only fits a device built from the same configuration: the header
carries the unit ids, the number of loops and the tick, and :meth:`Device.restore
<valve_emulator.device.tick.Device.restore>` refuses a snapshot of another configuration.

A file is checked completely when it is read, and again against the device before anything is restored;
every refusal is a :class:`SnapshotError` naming the file and what is wrong: not a snapshot file (truncated,
not a zip archive), another format version, a header field of the wrong type, a number that is NaN or
infinite where the bank never holds one (:meth:`Snapshot.check_finite`), an integer outside its range or
unlike the configuration's (:meth:`Snapshot.check_integers`), another configuration or number of loops.
A file that cannot be read does not stop the others from loading: the store lists it under
:attr:`SnapshotStore.broken` and refuses to restore it, with the reason.

:class:`BacktrackRing` takes a snapshot every ``interval`` simulated seconds and keeps the last ``size``
(commercial stations use 60 s to 600 s), so an instructor can rewind an exercise.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import re
import time
import zipfile
from collections import deque
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from valve_emulator.errors import UserError
from valve_emulator.simulation.state import join, split

__all__ = ["Snapshot", "SnapshotError", "SnapshotNotFound", "SnapshotStore", "BacktrackRing", "check_name"]

_log = logging.getLogger("valve_emulator.station")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")
_FORMAT = 1


class SnapshotError(UserError):
    """A snapshot that cannot be stored or restored; ``field`` names what is wrong (``name``, ``units`` ...)."""

    def __init__(self, message: str, *, field: str = "name") -> None:
        super().__init__(message)
        self.field = field


class SnapshotNotFound(SnapshotError, KeyError):
    """No snapshot of that name."""

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


def check_name(name: Any) -> str:
    """``name`` if it is a valid snapshot name (letters, digits, ``_ . -``, 1..64, no leading dot)."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise SnapshotError(f"field 'name': snapshot names are 1..64 letters, digits, '_', '.', '-', starting "
                            f"with a letter or digit; got {name!r}", field="name")
    return name


@dataclass(kw_only=True)
class Snapshot:
    """The state of a device at one tick (see the module docstring)."""

    name: str
    time: float                  # simulated time of the sample the device showed (s)
    ticks: int
    bank: dict[str, Any] = field(repr=False)
    device: dict[str, Any] = field(repr=False)   # tick count, malfunction ramps, configuration fingerprint
    created: float = field(default_factory=time.time)   # wall clock (s since the epoch)
    source: Path | None = None   # the file it was read from, for error messages

    @property
    def label(self) -> str:
        """How errors name it: ``'NAME'``, with its file when it was read from one."""
        return f"{self.name!r}" + (f" (file {self.source})" if self.source is not None else "")

    def summary(self) -> dict[str, Any]:
        return {"name": self.name, "time": self.time, "ticks": self.ticks, "created": self.created}

    def check_finite(self, allowed: Mapping[str, str]) -> None:
        """Raise :class:`SnapshotError` naming the first number in the bank's state that is NaN or infinite
        where that is not ``allowed`` (state path -> what the non-finite value means there, e.g.
        ``pv_stuck``: NaN for "not stuck"): restored, such a value would stop the tick at its next step."""
        for path, value in self.bank.items():
            if path in allowed:
                continue
            if isinstance(value, np.ndarray) and value.dtype.kind in "fc":
                bad = np.flatnonzero(~np.isfinite(value))
                if bad.size:
                    first = float(value.ravel()[bad[0]])
                    raise SnapshotError(f"snapshot {self.label}: state field {path} holds {first!r} at "
                                        f"[{bad[0]}]; only finite numbers are valid there", field="file")
            elif not _finite(value):
                raise SnapshotError(f"snapshot {self.label}: state field {path} holds a NaN or infinity; only "
                                    f"finite numbers are valid there", field="file")

    def check_integers(self, current: Mapping[str, Any], dynamic: Mapping[str, tuple[int, int]]) -> None:
        """Raise :class:`SnapshotError` naming the first integer field of the bank's state that is outside its
        range (``dynamic``: path -> inclusive range, for the fields that change as the bank runs) or, for
        every other integer field, differs from ``current`` (the device's own state: sizes, model codes,
        delays are set by the configuration)."""
        for path, value in self.bank.items():
            if not _integers(value) or path not in current:
                continue
            if path in dynamic:
                lo, hi = dynamic[path]
                values = np.asarray(value)
                if values.size and not (lo <= values.min() and values.max() <= hi):
                    raise SnapshotError(f"snapshot {self.label}: state field {path} = {value!r} is outside "
                                        f"{lo}..{hi}"[:300], field="file")
            elif not np.array_equal(np.asarray(value), np.asarray(current[path])):
                raise SnapshotError(f"snapshot {self.label}: state field {path} = {value!r} differs from this "
                                    f"device's {current[path]!r}, which its configuration sets"[:300], field="file")

    def save(self, path: Path) -> None:
        """Write ``path`` (``.npz``): the bank's arrays plus one JSON header; atomic (write, then rename)."""
        arrays, text = split(self.bank)
        header = json.dumps({"format": _FORMAT, "name": self.name, "time": self.time, "ticks": self.ticks,
                             "created": self.created, "device": self.device, "bank": text})
        tmp = path.with_name(path.name + ".tmp")
        with tmp.open("wb") as f:
            np.savez(f, __header__=np.array(header), **{f"bank:{k}": v for k, v in arrays.items()})
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> Snapshot:
        """Read a file written by :meth:`save`; a broken file raises :class:`SnapshotError` naming it and
        what is wrong (see the module docstring)."""
        try:
            with np.load(path, allow_pickle=False) as data:
                header = json.loads(str(data["__header__"]), parse_constant=_not_json)
                arrays = {k[5:]: data[k] for k in data.files if k.startswith("bank:")}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise SnapshotError(f"{path}: not a readable snapshot file ({type(exc).__name__}: {exc})",
                                field="file") from None
        if not isinstance(header, dict):
            raise SnapshotError(f"{path}: the header is not a JSON object", field="file")
        if header.get("format") != _FORMAT:
            raise SnapshotError(f"{path}: snapshot format {header.get('format')!r}; this version of "
                                f"valve-emulator reads format {_FORMAT}", field="file")
        for key, kind in _HEADER.items():
            if not isinstance(header.get(key), kind) or isinstance(header.get(key), bool):
                raise SnapshotError(f"{path}: header field {key!r} must be {_KIND[kind]}, got "
                                    f"{header.get(key)!r}"[:300], field="file")
        for key in ("time", "created"):
            if not math.isfinite(header[key]):
                raise SnapshotError(f"{path}: header field {key!r} is {header[key]!r}; only a finite number is "
                                    f"valid there", field="file")
        device = header["device"]
        if not (isinstance(device.get("config"), dict) and isinstance(device.get("ticks"), int)
                and isinstance(device.get("ramps"), list)):
            raise SnapshotError(f"{path}: header field 'device' must hold 'config' (an object), 'ticks' (a whole "
                                f"number) and 'ramps' (a list)", field="file")
        try:
            bank = join(arrays, header["bank"])
        except (ValueError, TypeError, KeyError) as exc:
            raise SnapshotError(f"{path}: the bank's state does not decode ({exc})", field="file") from None
        return cls(name=header["name"], time=float(header["time"]), ticks=header["ticks"], bank=bank,
                   device=header["device"], created=float(header["created"]), source=path)


def _integers(value: Any) -> bool:
    """An integer or an array of integers (not booleans)?"""
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "iu"
    return isinstance(value, int) and not isinstance(value, bool)


def _finite(value: Any) -> bool:
    """No NaN or infinity in ``value`` (a number, or lists of them such as a set-point schedule)."""
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return all(_finite(v) for v in value)
    return True


def _not_json(constant: str) -> Any:
    raise ValueError(f"{constant} is not a JSON number")


#: the header's fields and their JSON types
_HEADER = {"name": str, "time": (int, float), "ticks": int, "created": (int, float), "device": dict, "bank": str}
_KIND = {str: "text", (int, float): "a number", int: "a whole number", dict: "an object"}


class SnapshotStore:
    """Named snapshots, kept in memory and, with ``directory``, as ``NAME.npz`` files there.

    The files found at start are read then; one that cannot be read is logged (ERROR, naming the file and
    what is wrong) and kept in :attr:`broken` (name -> reason) instead of stopping the station. A file that
    appears later (copied from another station) is read when its name is first asked for.
    """

    def __init__(self, directory: Path | None = None) -> None:
        self.directory = directory
        self._snaps: dict[str, Snapshot] = {}
        self.broken: dict[str, str] = {}
        if directory is not None:
            directory.mkdir(parents=True, exist_ok=True)
            for path in sorted(directory.glob("*.npz")):
                if _NAME.fullmatch(path.stem):
                    with contextlib.suppress(SnapshotError):   # logged and listed in self.broken
                        self._read(path)

    def _read(self, path: Path) -> Snapshot:
        """Read ``path`` into the store; a broken file is recorded in :attr:`broken` and raised."""
        try:
            snap = dataclasses.replace(Snapshot.load(path), name=path.stem)   # a renamed copy goes by its file
        except SnapshotError as exc:
            self.broken[path.stem] = str(exc)
            _log.error("snapshot file not loaded: %s", exc)
            raise
        self.broken.pop(path.stem, None)
        self._snaps[path.stem] = snap
        return snap

    def __contains__(self, name: str) -> bool:
        return name in self._snaps

    def __iter__(self) -> Iterator[Snapshot]:
        return iter(sorted(self._snaps.values(), key=lambda s: s.created))

    def __len__(self) -> int:
        return len(self._snaps)

    def get(self, name: str) -> Snapshot:
        """The snapshot ``name``; its file is read now if it is not in memory (:class:`SnapshotError` if that
        file is broken, :class:`SnapshotNotFound` if there is none)."""
        check_name(name)
        if name in self._snaps:
            return self._snaps[name]
        path = self._path(name)
        if path is not None and path.is_file():
            return self._read(path)
        raise SnapshotNotFound(f"no snapshot named {name!r} (have: {', '.join(sorted(self._snaps)) or 'none'})",
                               field="name")

    def put(self, snap: Snapshot) -> None:
        check_name(snap.name)
        if self.directory is not None:
            snap.save(self.directory / f"{snap.name}.npz")
        self._snaps[snap.name] = snap
        self.broken.pop(snap.name, None)

    def delete(self, name: str) -> None:
        """Forget ``name`` and remove its file (also a broken one)."""
        check_name(name)
        path = self._path(name)
        if name not in self._snaps and not (path is not None and path.is_file()):
            raise SnapshotNotFound(f"no snapshot named {name!r}", field="name")
        if path is not None:
            path.unlink(missing_ok=True)
        self._snaps.pop(name, None)
        self.broken.pop(name, None)

    def _path(self, name: str) -> Path | None:
        return self.directory / f"{name}.npz" if self.directory is not None else None


class BacktrackRing:
    """A snapshot every ``interval`` simulated seconds, the last ``size`` kept (named ``bt-<seconds>``)."""

    def __init__(self, interval: float = 60.0, size: int = 30) -> None:
        if not (interval > 0) or size < 1:
            raise ValueError(f"backtrack interval must be > 0 s and size >= 1, got {interval!r}, {size!r}")
        self.interval, self.size = float(interval), int(size)
        self._ring: deque[Snapshot] = deque(maxlen=self.size)
        self._next = 0.0

    def due(self, t: float) -> bool:
        return t >= self._next

    def add(self, snap: Snapshot) -> None:
        self._ring.append(snap)
        self._next = snap.time + self.interval

    def reset(self, t: float) -> None:
        """After a restore to ``t``: forget the points after it, the next one an interval later."""
        while self._ring and self._ring[-1].time > t:
            self._ring.pop()
        self._next = t + self.interval

    def __iter__(self) -> Iterator[Snapshot]:
        return iter(self._ring)

    def get(self, name: str) -> Snapshot:
        for snap in self._ring:
            if snap.name == name:
                return snap
        raise SnapshotNotFound(f"no backtrack point named {name!r}", field="name")
