"""The device's register image in shared memory, for an OPC UA server in another process.

The device process owns an :class:`ImagePublisher`: whenever the image changes (after a tick's refresh, an
accepted write, an alarm word: :attr:`Device.image_listeners <valve_emulator.device.tick.Device>`) it copies the
image, the doubles the tick computed for the float32 quantities (PV, OP, MV, SP: served at full precision) and
the tick's counters into one ``multiprocessing.shared_memory`` block. That copy is all the tick pays for OPC
UA, however many clients subscribe.

The block holds the last :data:`SLOTS` ticks, each in a slot of its own (tick ``k`` in slot ``k % SLOTS``; a write
between ticks copies into the current tick's slot): so a hand-off of the OPC UA process that runs after the device
has published a newer tick still samples the tick it is for (:meth:`ImageReader.pinned` with ``tick``), and the
hand-off of the next tick that tick's. (With the newest tick only, a hand-off run late sampled the next tick, and the
next hand-off found the same tick, unchanged: no notification, a publishing interval without the item,
docs/benchmarks.md §9.19.) The copy per publication is the same size as with one slot.

The OPC UA process owns an :class:`ImageReader` on the same block. A sequence counter per slot (odd while the
publisher writes it) lets it take a consistent copy: it retries when the counter moved or was odd, so it never
serves half of one tick and half of the next. A generation counter at the block's start (with the newest slot)
says when anything was published. Both run single-threaded over x86's ordered stores; a counter is written last
and read first. A slot's header says which tick the copy holds (``ticks``, ``sample_time``) and when the device
ran it (``wall time``: the time of the copy that first held that tick, not of a later write's): the
SourceTimestamp of every value sampled from it, whenever the OPC UA process samples it.
:meth:`ImageReader.pinned` keeps one copy for a whole block of reads (a chunk of a hand-off), so a chunk never
mixes two ticks.

Layout: a header ``generation, newest slot (uint64)``, then :data:`SLOTS` slots, each a header ``seq, ticks
(uint64), sample_time, wall time (float64)``, the image's bytes, then ``COMPUTED × n`` float64 (quantity-major).
A tick count that goes back (a restored snapshot) marks every other slot empty.
"""

from __future__ import annotations

import contextlib
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from multiprocessing import resource_tracker, shared_memory
from typing import Any

import numpy as np

__all__ = ["COMPUTED", "SLOTS", "SharedLayout", "ImagePublisher", "ImageReader", "TickImage"]

#: The quantities whose doubles are published beside the image (the image holds them as float32).
COMPUTED = ("pv", "op", "mv", "sp")
#: The ticks the block keeps: a hand-off up to this many ticks late less one still samples its own tick (the OPC UA
#: process registers hand-offs ``HAND_AHEAD`` = 10 ticks ahead; 1,000 loops: 16 slots of 96 kB).
SLOTS = 16
_TOP = struct.Struct("<QQ")
_HEADER = struct.Struct("<QQdd")
_SEQ = struct.Struct("<Q")
#: A slot's tick count when it holds no tick (before its first copy, after the tick count went back).
_EMPTY = 2**64 - 1


@dataclass(frozen=True)
class SharedLayout:
    """Where things are in the block: ``size`` image bytes for ``n`` loops, in ``slots`` slots."""

    size: int
    n: int
    slots: int = SLOTS

    @property
    def image_at(self) -> int:
        """The image's offset in a slot."""
        return _HEADER.size

    @property
    def doubles_at(self) -> int:
        """The doubles' offset in a slot."""
        return (_HEADER.size + self.size + 7) // 8 * 8

    @property
    def slot_size(self) -> int:
        return self.doubles_at + 8 * len(COMPUTED) * self.n

    def slot_at(self, slot: int) -> int:
        """Slot number ``slot``'s offset in the block."""
        return _TOP.size + slot * self.slot_size

    @property
    def total(self) -> int:
        return self.slot_at(self.slots)


@dataclass(frozen=True)
class TickImage:
    """One consistent copy of what the device published: the image, the doubles, the counters."""

    image: bytes
    computed: np.ndarray      # (len(COMPUTED), n) float64
    ticks: int
    sample_time: float
    wall_time: float
    seq: int


class ImagePublisher:
    """The device side: :meth:`publish` copies ``device``'s image into shared memory (see the module docstring).

    Counters: :attr:`copies` (one per publish)."""

    def __init__(self, device: Any, slots: int = SLOTS) -> None:
        self.device = device
        lay = self.layout = SharedLayout(size=len(device.image), n=int(device.bank.n), slots=slots)
        self.shm = shared_memory.SharedMemory(create=True, size=lay.total)
        self._images = [np.ndarray(lay.size, dtype=np.uint8, buffer=self.shm.buf, offset=lay.slot_at(k) + lay.image_at)
                        for k in range(slots)]
        self._doubles = [np.ndarray((len(COMPUTED), lay.n), dtype=np.float64, buffer=self.shm.buf,
                                    offset=lay.slot_at(k) + lay.doubles_at) for k in range(slots)]
        self._no_controller = ~np.asarray(device.scaling.has_controller, dtype=bool)
        self._seqs = [0] * slots
        for k in range(slots):
            _HEADER.pack_into(self.shm.buf, lay.slot_at(k), 0, _EMPTY, 0.0, 0.0)
        self._generation = 0
        self._tick: tuple[int, float] | None = None
        self._tick_wall = 0.0
        self.copies = 0

    @property
    def name(self) -> str:
        return self.shm.name

    def publish(self) -> None:
        """Copy the image and the tick's doubles into the tick's slot (its counter odd meanwhile), then say so."""
        device, bank, buf, lay = self.device, self.device.bank, self.shm.buf, self.layout
        tick = (int(device.ticks), float(bank.sample_time))
        if self._tick is not None and tick[0] < self._tick[0]:   # went back: the other slots hold no tick of this run
            for k in range(lay.slots):
                self._seqs[k] += 2
                _HEADER.pack_into(buf, lay.slot_at(k), self._seqs[k], _EMPTY, 0.0, 0.0)
        slot = tick[0] % lay.slots
        at = lay.slot_at(slot)
        self._seqs[slot] += 1
        _SEQ.pack_into(buf, at, self._seqs[slot])
        self._images[slot][:] = np.frombuffer(device.image, dtype=np.uint8)
        doubles = self._doubles[slot]
        for row, quantity in enumerate(COMPUTED):
            doubles[row] = getattr(bank, quantity)
        doubles[COMPUTED.index("sp"), self._no_controller] = 0.0   # a loop without controller reads SP 0
        self._seqs[slot] += 1
        if tick != self._tick:   # a new tick (or a restored snapshot): its time; a write keeps the tick's
            self._tick, self._tick_wall = tick, time.time()
        _HEADER.pack_into(buf, at, self._seqs[slot], tick[0], tick[1], self._tick_wall)
        self._generation += 1
        _TOP.pack_into(buf, 0, self._generation, slot)
        self.copies += 1

    def close(self) -> None:
        self._images = self._doubles = None   # release the views before the block
        self.shm.close()
        self.shm.unlink()


class ImageReader:
    """The OPC UA side: :meth:`read` is the latest consistent :class:`TickImage`, copied only when it changed;
    inside :meth:`pinned`, the one taken on entering it."""

    def __init__(self, name: str, layout: SharedLayout) -> None:
        self.layout = layout
        self.shm = shared_memory.SharedMemory(name=name)
        # the device process created the block and unlinks it; without this the reader's resource tracker would
        # unlink it too when this process ends (and warn of a leak)
        resource_tracker.unregister(self.shm._name, "shared_memory")
        self._last: TickImage | None = None
        self._generation = -1
        self._pinned: TickImage | None = None
        #: the last copy of each slot (by slot number): a slot whose counter has not moved is not copied again
        self._kept: dict[int, TickImage] = {}

    def seq(self) -> int:
        """The block's generation: it moves with every publication."""
        return _TOP.unpack_from(self.shm.buf, 0)[0]

    def read(self) -> TickImage:
        """The latest published image (the same object as long as nothing new was published); inside
        :meth:`pinned`, the one taken on entering it."""
        if self._pinned is not None:
            return self._pinned
        buf = self.shm.buf
        while True:
            generation, slot = _TOP.unpack_from(buf, 0)
            if generation == self._generation and self._last is not None:
                return self._last
            got = self._slot(slot)
            if got is not None and _TOP.unpack_from(buf, 0)[0] == generation:
                self._last, self._generation = got, generation
                return got
            time.sleep(0)

    def _slot(self, slot: int, tick: int | None = None) -> TickImage | None:
        """A consistent copy of slot number ``slot`` (None: it was being written; with ``tick``, or it does not
        hold that tick)."""
        buf, lay = self.shm.buf, self.layout
        at = lay.slot_at(slot)
        for _ in range(100):
            seq, ticks, sample_time, wall = _HEADER.unpack_from(buf, at)
            if tick is not None and ticks != tick:
                return None
            if seq % 2:
                time.sleep(0)
                continue
            kept = self._kept.get(slot)
            if kept is not None and kept.seq == seq:   # copied already (the chunks of one late hand-off)
                return kept
            image = bytes(buf[at + lay.image_at:at + lay.image_at + lay.size])
            computed = np.frombuffer(bytes(buf[at + lay.doubles_at:at + lay.slot_size]), dtype=np.float64)
            if _SEQ.unpack_from(buf, at)[0] == seq:
                kept = self._kept[slot] = TickImage(image, computed.reshape(len(COMPUTED), lay.n), ticks,
                                                    sample_time, wall, seq)
                return kept
        return None

    def at_most(self, tick: int) -> TickImage:
        """The image of tick number ``tick``, or of the newest tick before it the block still holds, when the
        newest published is later (a hand-off that runs after the device published the next tick); else the
        newest. Never a tick newer than ``tick`` unless the block holds none at or before it."""
        newest = self.read()
        if newest.ticks <= tick:
            return newest
        lay = self.layout
        for back in range(min(lay.slots, tick + 1)):
            got = self._slot((tick - back) % lay.slots, tick - back)
            if got is not None:
                return got
        return newest

    @contextlib.contextmanager
    def pinned(self, tick: int | None = None) -> Iterator[TickImage]:
        """Every :meth:`read` inside the block answers the image taken on entering it (one tick, however
        many the device runs meanwhile in its own process): the newest, or with ``tick`` :meth:`at_most` that tick;
        nested blocks keep the outer one's."""
        if self._pinned is not None:
            yield self._pinned
            return
        self._pinned = self.read() if tick is None else self.at_most(tick)
        try:
            yield self._pinned
        finally:
            self._pinned = None

    def close(self) -> None:
        self.shm.close()
