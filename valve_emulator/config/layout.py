"""Split one server configuration into slices served by separate processes (or machines).

Pure (no I/O). A plant-size fleet uses every core when each core runs one server process that owns a
contiguous range of *whole* unit ids: a client then finds any loop at one ``(port, unit, block)`` and
never needs to know that the fleet is split. Every process loads the same file and keeps only its
slice, so the parent of ``valve-emulator serve --processes N`` and an orchestrator starting
``valve-emulator serve CONFIG --process-index I --processes N`` on N machines get the same layout.

Partition rule: units in the order they first appear in ``config.loops``; slice ``p`` takes whole units
until its loop count reaches ``(p + 1)·n/N`` (it takes a unit when at least half of it fits under that
mark), keeping one unit for each later slice; the last slice takes the rest. Equal units therefore
split evenly, and no slice is empty.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from valve_emulator.config.schema import ServerConfig
from valve_emulator.errors import UserError

__all__ = ["Slice", "partition", "server_slice", "unit_ranges"]


@dataclasses.dataclass(frozen=True, slots=True)
class Slice:
    """The part of a fleet one process serves: its index, its unit ids and its loops' indices."""

    index: int
    units: tuple[int, ...]          # unit ids, in config order
    loops: tuple[int, ...]          # indices into ``config.loops``, in config order

    def describe(self) -> str:
        """e.g. ``units 1-50 (5,000 loops)``."""
        return f"units {unit_ranges(self.units)} ({len(self.loops):,} loop{'s' if len(self.loops) != 1 else ''})"


def partition(config: ServerConfig, parts: int) -> list[Slice]:
    """Split ``config``'s loops into ``parts`` slices of whole units (module docstring); ``ValueError``
    when there are fewer units than parts."""
    if isinstance(parts, bool) or not isinstance(parts, int) or parts < 1:
        raise UserError(f"processes must be an integer >= 1, got {parts!r}")
    members: dict[int, list[int]] = {}
    for i, loop in enumerate(config.loops):
        members.setdefault(loop.device.unit, []).append(i)
    units = list(members)
    if parts > len(units):
        raise UserError(f"processes ({parts}) must be <= the number of unit ids in the config ({len(units)}): "
                        f"each process serves whole units")
    n = len(config.loops)
    slices, u, done = [], 0, 0
    for p in range(parts):
        mark = (p + 1) * n / parts
        take = [units[u]]
        done += len(members[units[u]])
        u += 1
        keep = parts - p - 1                      # units the later slices still need
        while u < len(units) - keep and (p == parts - 1 or done + len(members[units[u]]) / 2 <= mark):
            take.append(units[u])
            done += len(members[units[u]])
            u += 1
        loops = tuple(sorted(i for unit in take for i in members[unit]))
        slices.append(Slice(p, tuple(take), loops))
    return slices


def server_slice(config: ServerConfig, index: int, parts: int) -> ServerConfig:
    """The server configuration of slice ``index`` (0-based) of ``parts``: the same device settings,
    only that slice's loops (at their unchanged unit ids and blocks)."""
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < parts:
        raise UserError(f"process index must be 0..{parts - 1} for {parts} processes, got {index!r}")
    part = partition(config, parts)[index]
    return dataclasses.replace(config, loops=tuple(config.loops[i] for i in part.loops))


def unit_ranges(units: Sequence[int]) -> str:
    """``[1, 2, 3, 7, 9, 10]`` -> ``"1-3, 7, 9-10"`` (runs of consecutive ids, in the given order)."""
    runs: list[list[int]] = []
    for u in units:
        if runs and u == runs[-1][1] + 1:
            runs[-1][1] = u
        else:
            runs.append([u, u])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)
