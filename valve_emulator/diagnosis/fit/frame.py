r"""The unit-free frame the plant-data diagnosis works in, and the way back to OP's own units.

A recording's OP may be % of travel, mA, a 0–1 fraction, raw analog counts, engineering units of the
manipulated flow, or a mean-centred or normalised signal. Grids, thresholds and the stiction machine must
not depend on where its 0 and 100 lie, so OP is mapped once, by a positive affine map, to an internal
coordinate ``u = 50 + 40 (op − m) / R`` in which the whole search runs, with ``m`` the midpoint and ``R`` the
width of OP's robust range (0.5th–99.5th percentile, the *OP band used*). It depends on the data only through
statistics that move with any positive affine map of OP, so the search sees the same numbers, and gives the
same answer and findings, whatever OP's units and offset and whatever the file said about them.

A **travel span** (OP's values at 0 and 100 % travel) is a claim about OP that the file or the user makes:
the standard recording format (OP in %), ``--op-units``, ``--op-range LO HI``. It is kept beside the map,
never in it: it adds S and J in % of travel, and the travel stops at which the chain's saturation candidate
and the flow characteristic act (:attr:`Frame.stops`, their internal images). The data can refute it
(:meth:`Frame.refutation`): an OP whose robust range goes below 0 or above 100 % of the span by more than
:data:`SPAN_NOISE` of its noise σ (:func:`jitter_sigma`; whatever share of the range that is), or that moves
clearly beyond its noise within less than :data:`SPAN_MIN_USED` % of it, is not in those units (a 0–1
fraction, raw counts, a deviation from the operating point or a signal normalised to ±1 read as %); the span is
then dropped and the answer says so. A travel span is where a valve model clips OP, so an OP centred on 0 (half
of it below the span) is always refuted, never clipped in silence: its robust range reaches below −2.5 σ even
when it is noise alone. A nominal model's OP is % travel by construction: :meth:`Frame.travel_percent` with
the span (0, 100) is the identity map of the model path.

PV needs no frame: the fit scales it (``y = (pv − ȳ)/σ_y``, either sign of the process gain) and its
candidates (a quantum, a disturbance amplitude) move with it. Parameters come back in OP's units
(:meth:`Frame.op_delta`, :meth:`Frame.op_level`), as a fraction of the OP band used (:meth:`Frame.band`), and in %
of travel when the span is known (:meth:`Frame.travel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from valve_emulator.errors import UserError

__all__ = ["Frame", "CENTER", "WIDTH", "TRAVEL", "UNKNOWN_UNITS", "SPAN_NOISE", "SPAN_MIN_USED", "noise_sigma",
           "jitter_sigma"]

#: Internal coordinate of OP's robust midpoint.
CENTER = 50.0
#: Internal width of OP's robust range (the OP band used).
WIDTH = 40.0
#: Units of a quantity in % of travel.
TRAVEL = "% travel"
#: The units of an OP whose span is not known: its own, whatever they are.
UNKNOWN_UNITS = "OP units"
#: A declared span is refuted when OP's robust range goes beyond 0 or 100 % of it by more than this many noise
#: σ (:func:`jitter_sigma`): a DCS clamps an OP in % at its limits, so only noise (or an archive's rounding) can
#: carry it past them, where a 0–1 fraction, raw counts, or a deviation from the operating point or a ±1
#: normalisation read as % land outside (or, below, far inside) the span. Two σ: white noise alone reaches
#: 2.58 σ at its 0.5th percentile, so an OP that is noise centred on 0 is refuted too.
SPAN_NOISE = 2.0
#: ... or when OP moves clearly beyond its noise over less than this share (%) of the span: no loop cycles
#: or answers set-point changes with half a per cent of travel, where a 0–1 fraction read as % does.
SPAN_MIN_USED = 0.5


def noise_sigma(x) -> float:
    """Robust noise σ of a signal: 1.4826 · MAD of its first differences, divided by √2 (0 for fewer than two
    samples, or a signal that mostly holds its value)."""
    d = np.diff(np.asarray(x, dtype=float))
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def jitter_sigma(x) -> float:
    """Robust noise σ of a signal from its second differences (1.4826 · MAD / √6 for white noise): unlike
    :func:`noise_sigma` it does not count a fast cycle's slope as noise."""
    d = np.diff(np.asarray(x, dtype=float), n=2)
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(6.0))


def robust_range(x) -> tuple[float, float]:
    """The 0.5th and 99.5th percentiles: a signal's range without its few outliers."""
    lo, hi = np.percentile(np.asarray(x, dtype=float), [0.5, 99.5])
    return float(lo), float(hi)


@dataclass(frozen=True, kw_only=True)
class Frame:
    """The positive affine map ``u = offset + gain · op`` and what is known about OP's units.

    Attributes
    ----------
    offset, gain : the map (``gain > 0``).
    units : OP's units for reports (``"% travel"``, ``"OP units"``, ...).
    span : OP's values at 0 and 100 % travel, when known (else None).
    span_source : how the span is known (``"standard format"``, ``"op_range"``, ``"op_units mA"``, ``"model"``).
    band_range : OP's robust range (0.5th–99.5th percentile, OP's units), the OP band used, when the frame was
        made from the data (:meth:`unit_free`); S and J are also reported as fractions of its width.
    """

    offset: float = 0.0
    gain: float = 1.0
    units: str = TRAVEL
    span: tuple[float, float] | None = (0.0, 100.0)
    span_source: str = "assumed"
    band_range: tuple[float, float] | None = None

    @classmethod
    def travel_percent(cls, span: tuple[float, float] = (0.0, 100.0), *, source: str = "assumed",
                       units: str | None = None) -> Frame:
        """The frame of a known travel span (``span`` = OP at 0 and 100 %): a declaration, mapped to % travel.
        The plant-data search runs in :meth:`unit_free` of it; the model path in it (the identity for OP in %)."""
        lo, hi = float(span[0]), float(span[1])
        if not hi > lo:
            raise UserError(f"op range: the value at 100 % travel ({hi:g}) must exceed the one at 0 % ({lo:g})")
        gain = 100.0 / (hi - lo)
        label = units or (TRAVEL if (lo, hi) == (0.0, 100.0) else UNKNOWN_UNITS)
        return cls(offset=-lo * gain, gain=gain, units=label, span=(lo, hi), span_source=source)

    @classmethod
    def unit_free(cls, op: np.ndarray, *, units: str = UNKNOWN_UNITS, declared: Frame | None = None) -> Frame:
        """The search's frame of ``op`` (robust midpoint and range, see the module docstring), keeping the travel
        span (and its units) of ``declared`` when that has one."""
        lo, hi = robust_range(op)
        width = hi - lo
        if not width > 0.0:   # OP nearly constant: any positive scale keeps the map invertible
            width = float(np.ptp(op)) or 1.0
        gain = WIDTH / width
        keep = declared is not None and declared.known
        return cls(offset=CENTER - gain * 0.5 * (lo + hi), gain=gain, units=declared.units if keep else units,
                   span=declared.span if keep else None, span_source=declared.span_source if keep else "",
                   band_range=(lo, lo + width))

    def refutation(self, op: np.ndarray, *, moving: bool) -> str:
        """Why OP cannot be in this frame's declared travel span, a sentence naming OP's observed range (``""``
        when it can be, or no span is declared): its robust range goes below 0 or above 100 % of the span by more
        than :data:`SPAN_NOISE` noise σ, or, ``moving`` (OP moves clearly beyond its noise), it covers less than
        :data:`SPAN_MIN_USED` % of it."""
        if self.span is None:
            return ""
        lo, hi = robust_range(op)
        a, b = self.span
        pct_lo, pct_hi = (100.0 * (x - a) / (b - a) for x in (lo, hi))
        margin = 100.0 * SPAN_NOISE * jitter_sigma(op) / (b - a)
        said = f"OP ran from {lo:.4g} to {hi:.4g} (0.5th–99.5th percentile)"
        span = f"the declared span {a:g}..{b:g} ({self.span_source})"
        if pct_lo < -margin or pct_hi > 100.0 + margin:
            why = (f"{said}, {pct_lo:.4g}..{pct_hi:.4g} % of {span}, beyond 0..100 % by more than its noise "
                   f"({SPAN_NOISE:g} σ = {margin:.2g} %), where a valve would clip it")
        elif moving and pct_hi - pct_lo < SPAN_MIN_USED:
            why = (f"{said}, {pct_hi - pct_lo:.3g} % of {span}, less than {SPAN_MIN_USED:g} % while it moves "
                   "clearly beyond its noise")
        else:
            return ""
        return f"{why}: OP is not in those units"

    @property
    def known(self) -> bool:
        """Whether OP's travel span is known (saturation and the characteristic are candidates only then)."""
        return self.span is not None

    @property
    def identity(self) -> bool:
        return self.offset == 0.0 and self.gain == 1.0

    @property
    def stops(self) -> tuple[float, float]:
        """Where the chain's characteristic and limit slots put 0 and 100 % travel, in the internal frame: the
        span's images when it is known, else (0, 100) (the travel scale is then the internal one)."""
        if self.span is None:
            return 0.0, 100.0
        return float(self.to_internal(self.span[0])), float(self.to_internal(self.span[1]))

    # -- into the frame and back ------------------------------------------------------------------------------
    def to_internal(self, op) -> np.ndarray:
        return self.offset + self.gain * np.asarray(op, dtype=float)

    def from_internal(self, u) -> np.ndarray:
        """Internal OP signals (OP, valve position, flow) back in OP's units."""
        return (np.asarray(u, dtype=float) - self.offset) / self.gain

    def op_level(self, u: float) -> float:
        """An internal OP level in OP's units."""
        return (float(u) - self.offset) / self.gain

    def stop_level(self, v: float) -> float:
        """A level on the travel scale of the chain's characteristic and limit slots (0 and 100 at
        :attr:`stops`: a saturation limit) in OP's units."""
        lo, hi = self.stops
        return self.op_level(lo + float(v) * (hi - lo) / 100.0)

    def op_delta(self, du: float) -> float:
        """An internal OP difference (a band S, a jump J) in OP's units."""
        return float(du) / self.gain

    def travel(self, delta: float) -> float | None:
        """An OP difference in OP's units as % of travel (None when the span is unknown)."""
        if self.span is None:
            return None
        return 100.0 * float(delta) / (self.span[1] - self.span[0])

    def band(self, delta: float) -> float | None:
        """An OP difference in OP's units as a fraction of the OP band used (None when not made from data):
        the same figure whatever OP's units."""
        if self.band_range is None:
            return None
        return float(delta) / (self.band_range[1] - self.band_range[0])

    def convert(self, dims: dict[str, str], values: dict) -> dict:
        """Parameters from the internal frame to OP's units; ``dims`` says which are OP differences
        (``"op"``) or levels on the chain's travel scale (``"op_level"``, see :meth:`stop_level`); others pass
        through."""
        out = {}
        for k, v in values.items():
            d = dims.get(k, "")
            if v is None or d not in ("op", "op_level"):
                out[k] = v
            elif isinstance(v, tuple):
                out[k] = tuple(self.op_delta(x) if d == "op" else self.stop_level(x) for x in v)
            else:
                out[k] = self.op_delta(v) if d == "op" else self.stop_level(v)
        return out
