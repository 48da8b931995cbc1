r"""The unit-free frame the plant-data diagnosis works in, and the way back to OP's own units.

A recording's OP may be % of travel, mA, a 0–1 fraction, raw analog counts, engineering units of the
manipulated flow, or a mean-centred or normalised signal. Grids, thresholds and the stiction machine must
not depend on where its 0 and 100 lie, so OP is mapped once, by a positive affine map, to an internal
coordinate ``u`` in which the whole search runs:

* **travel span known** (the standard recording format, ``--op-units``, ``--op-range LO HI``, or a nominal
  model): ``u = 100 (op − LO) / (HI − LO)``, % of travel, so saturation at the travel stops and the flow
  characteristic keep their meaning;
* **unknown**: ``u = 50 + 40 (op − m) / R`` with ``m`` the midpoint and ``R`` the width of OP's robust range
  (0.5th–99.5th percentile). It depends on the data only through statistics that move with any positive
  affine map of OP, so the diagnosis gives the same answer and findings whatever OP's units and offset.
  Saturation and the flow characteristic, which need the travel stops, are not candidates then.

PV needs no frame: the fit scales it (``y = (pv − ȳ)/σ_y``) and its candidates (a quantum, a disturbance
amplitude) move with it. Parameters come back in OP's units (:meth:`Frame.op_delta`, :meth:`Frame.op_level`),
and in % of travel when the span is known (:meth:`Frame.travel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Frame", "CENTER", "WIDTH", "TRAVEL", "UNKNOWN_UNITS"]

#: Internal coordinate of OP's robust midpoint when the span is unknown.
CENTER = 50.0
#: Internal width of OP's robust range when the span is unknown.
WIDTH = 40.0
#: Units of a quantity in % of travel.
TRAVEL = "% travel"
#: The units of an OP whose span is not known: its own, whatever they are.
UNKNOWN_UNITS = "OP units"


@dataclass(frozen=True, kw_only=True)
class Frame:
    """The positive affine map ``u = offset + gain · op`` and what is known about OP's units.

    Attributes
    ----------
    offset, gain : the map (``gain > 0``).
    units : OP's units for reports (``"% travel"``, ``"OP units"``, ...).
    span : OP's values at 0 and 100 % travel, when known (else None).
    span_source : how the span is known (``"standard format"``, ``"--op-range"``, ``"op_units"``, ``"model"``).
    """

    offset: float = 0.0
    gain: float = 1.0
    units: str = TRAVEL
    span: tuple[float, float] | None = (0.0, 100.0)
    span_source: str = "assumed"

    @classmethod
    def travel_percent(cls, span: tuple[float, float] = (0.0, 100.0), *, source: str = "assumed",
                       units: str | None = None) -> Frame:
        """The frame of a known travel span (``span`` = OP at 0 and 100 %)."""
        lo, hi = float(span[0]), float(span[1])
        if not hi > lo:
            raise ValueError(f"op range: the value at 100 % travel ({hi:g}) must exceed the one at 0 % ({lo:g})")
        gain = 100.0 / (hi - lo)
        label = units or (TRAVEL if (lo, hi) == (0.0, 100.0) else UNKNOWN_UNITS)
        return cls(offset=-lo * gain, gain=gain, units=label, span=(lo, hi), span_source=source)

    @classmethod
    def unit_free(cls, op: np.ndarray, *, units: str = UNKNOWN_UNITS) -> Frame:
        """The frame of an OP whose span is unknown (robust midpoint and range, see the module docstring)."""
        lo, hi = np.percentile(np.asarray(op, dtype=float), [0.5, 99.5])
        width = float(hi - lo)
        if not width > 0.0:   # OP nearly constant: any positive scale keeps the map invertible
            width = float(np.ptp(op)) or 1.0
        gain = WIDTH / width
        return cls(offset=CENTER - gain * 0.5 * float(lo + hi), gain=gain, units=units, span=None,
                   span_source="")

    @property
    def known(self) -> bool:
        """Whether OP's travel span is known (saturation and the characteristic are candidates only then)."""
        return self.span is not None

    @property
    def identity(self) -> bool:
        return self.offset == 0.0 and self.gain == 1.0

    # -- into the frame and back ------------------------------------------------------------------------------
    def to_internal(self, op) -> np.ndarray:
        return self.offset + self.gain * np.asarray(op, dtype=float)

    def from_internal(self, u) -> np.ndarray:
        """Internal OP signals (OP, valve position, flow) back in OP's units."""
        return (np.asarray(u, dtype=float) - self.offset) / self.gain

    def op_level(self, u: float) -> float:
        """An internal OP level (a saturation limit) in OP's units."""
        return (float(u) - self.offset) / self.gain

    def op_delta(self, du: float) -> float:
        """An internal OP difference (a band S, a jump J) in OP's units."""
        return float(du) / self.gain

    def travel(self, delta: float) -> float | None:
        """An OP difference in OP's units as % of travel (None when the span is unknown)."""
        if self.span is None:
            return None
        return 100.0 * float(delta) / (self.span[1] - self.span[0])

    def convert(self, dims: dict[str, str], values: dict) -> dict:
        """Parameters from the internal frame to OP's units; ``dims`` says which are OP differences
        (``"op"``) or OP levels (``"op_level"``); others pass through."""
        out = {}
        for k, v in values.items():
            d = dims.get(k, "")
            if v is None or d not in ("op", "op_level"):
                out[k] = v
            elif isinstance(v, tuple):
                out[k] = tuple(self.op_delta(x) if d == "op" else self.op_level(x) for x in v)
            else:
                out[k] = self.op_delta(v) if d == "op" else self.op_level(v)
        return out
