r"""Can these data support a conclusion at all? The checks behind a polite "cannot tell".

A diagnosis without a plant model must identify the plant from the data themselves, so some records cannot
answer "is the valve sticky?" whatever the method, and saying so beats a wrong answer. In order:

1. **Too short**: fewer than :data:`~valve_emulator.diagnosis.fit.data.MIN_SAMPLES` samples (room for a burn-in,
   a dead time and two cross-validation blocks).
2. **Flat PV**: PV holds one value over at least :data:`FLAT_SHARE` of the record (the longest constant run).
   Half the record then carries no information about the valve. A PV that does not move while OP travels
   far (a robust range of at least :data:`EXCITATION` noise σ) is a finding of its own, *no response* (the
   answer :attr:`~valve_emulator.diagnosis.answers.Answer.NO_RESPONSE`): the valve is not moving or the loop is
   open — a seized valve, a closed block valve, an open bypass, a dead transmitter and a frozen archive all
   produce it, and the record cannot tell them apart, but each needs someone to inspect the loop. A constant
   OP is refused the same way (the valve was never asked to move).
3. **No oscillation and no excitation**: nothing moved the loop that the data could learn from. Oscillation
   is the regularity test of Thornhill, Huang & Zhang (J. Process Control 13 (2003) 91–100; ``r > 1``,
   :func:`~valve_emulator.detectors.base.oscillation`, the test the comparison detectors use) on the
   control error SP − PV (when there is a set point: set-point steps would mask a cycle in PV), PV or OP,
   the most regular of them; excitation is a set-point change, or OP travelling over a robust range (0.5th–99.5th
   percentile) of at least :data:`EXCITATION` times its noise σ. White noise alone spans about 5 σ between those
   percentiles, so twice that is movement the noise cannot make. The noise σ is
   :func:`~valve_emulator.diagnosis.fit.frame.noise_sigma`, the robust standard deviation of sample-to-sample
   changes divided by √2 (as for the
   OP turning points of :mod:`~valve_emulator.diagnosis.explain.locate`); for an OP that mostly holds its
   value (σ = 0) it is OP's resolution, the median non-zero step.

Thresholds are constants, chosen once for every loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from valve_emulator.detectors.base import oscillation
from valve_emulator.diagnosis.answers import Reason
from valve_emulator.diagnosis.explain.locate import turning_points
from valve_emulator.diagnosis.fit.data import MIN_SAMPLES
from valve_emulator.diagnosis.fit.frame import noise_sigma
from valve_emulator.recordings.recording import Recording

__all__ = ["Adequacy", "adequacy", "Cycle", "cycle", "cycle_swing", "longest_constant_run", "swings", "op_swings",
           "FLAT_SHARE", "EXCITATION", "TURN_BANDS"]

#: PV (or OP) constant over at least this share of the record is "flat".
FLAT_SHARE = 0.5
#: OP's robust range must reach this many noise σ to count as excitation.
EXCITATION = 10.0
#: OP turns when it comes back by more than this many noise σ (the package's "beyond noise", as for the OP turning
#: points of :mod:`~valve_emulator.diagnosis.explain.locate`).
TURN_BANDS = 3.0


def _step(x: np.ndarray) -> float:
    """OP's resolution when it mostly holds its value (zero noise σ): the median non-zero step (inf if none)."""
    d = np.abs(np.diff(np.asarray(x, dtype=float)))
    d = d[d > 0.0]
    return float(np.median(d)) if d.size else float("inf")


def longest_constant_run(x: np.ndarray) -> int:
    """Length of the longest run of exactly repeated values (1 for a signal that never repeats)."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return 0
    change = np.flatnonzero(np.diff(x) != 0.0)
    edges = np.concatenate([[-1], change, [x.size - 1]])
    return int(np.max(np.diff(edges)))


def swings(x: np.ndarray, turn: float) -> np.ndarray:
    """The sizes of ``x``'s swings: the travel between consecutive turning points, a turn counting when ``x``
    comes back from its latest extreme by more than ``turn``
    (:func:`~valve_emulator.diagnosis.explain.locate.turning_points`, a hysteresis, so that noise smaller than it
    makes no turning point). The swing before the first turn and the one still running at the end are left out
    (where they start or end is not known). Empty when ``x`` turns fewer than twice."""
    x = np.asarray(x, dtype=float)
    return np.abs(np.diff(x[turning_points(x, turn)]))


def op_swings(op: np.ndarray) -> np.ndarray:
    """OP's :func:`swings`, a turn counting beyond :data:`TURN_BANDS` noise σ
    (:func:`~valve_emulator.diagnosis.fit.frame.noise_sigma`; OP's resolution for an OP that mostly holds its
    value)."""
    op = np.asarray(op, dtype=float)
    noise = noise_sigma(op)
    return swings(op, TURN_BANDS * (noise if noise > 0 else _step(op)))


@dataclass(frozen=True)
class Adequacy:
    """Whether a record can be diagnosed, why not, and the facts checked.

    Attributes
    ----------
    ok : the record supports a conclusion.
    reason : for a refusal, the sentence after "cannot tell: " (or "no response: "); "" otherwise.
    code : for a refusal, its :class:`~valve_emulator.diagnosis.answers.Reason` (``too_short``, ``flat_pv``,
        ``no_response``, ``flat_op``, ``no_excitation``); None otherwise.
    facts : the numbers checked (samples, flat shares, oscillation regularity and period, OP range in noise
        σ, set-point changes).
    """

    ok: bool
    reason: str = ""
    facts: dict = field(default_factory=dict)
    code: Reason | None = None


def adequacy(rec: Recording) -> Adequacy:
    """Run the checks of the module docstring on ``rec`` (``t``, ``op``, ``pv``, and ``sp`` if present)."""
    T = len(rec)
    facts: dict = {"samples": T}
    if T < MIN_SAMPLES:
        span = f" ({T * rec.dt:g} s at {rec.dt:g} s)" if T >= 2 else ""
        return Adequacy(False, f"the record has {T} samples{span}; a diagnosis without a plant model needs at "
                               f"least {MIN_SAMPLES} (a burn-in, a dead time and two cross-validation blocks)",
                        facts, Reason.TOO_SHORT)
    op, pv = np.asarray(rec.op, dtype=float), np.asarray(rec.pv, dtype=float)
    lo, hi = np.percentile(op, [0.5, 99.5])
    facts["op_range"] = float(hi - lo)
    noise = noise_sigma(op)
    facts["op_noise"] = noise
    facts["op_range_in_noise"] = float((hi - lo) / (noise if noise > 0 else _step(op)))
    facts["pv_moves"] = float(np.mean(np.diff(pv) != 0.0))
    for name, x in (("PV", pv), ("OP", op)):
        share = longest_constant_run(x) / T
        facts[f"{name.lower()}_flat_share"] = share
        if share < FLAT_SHARE:
            continue
        flat = f"{name} is flat: it holds one value over {100 * share:.0f} % of the record"
        if name == "OP":
            return Adequacy(False, f"{flat}; the valve was never asked to move", facts, Reason.FLAT_OP)
        if facts["op_range_in_noise"] >= EXCITATION:
            return Adequacy(False, f"{flat} while OP travelled over {facts['op_range']:.3g} (OP units; "
                                   f"{facts['op_range_in_noise']:.3g} noise σ): PV does not respond to OP, so the "
                                   "valve is not moving or the loop is open — inspect it; a seized valve, a "
                                   "closed block valve, an open bypass, a dead transmitter or a frozen archive "
                                   "look the same, and the record cannot tell them apart", facts,
                            Reason.NO_RESPONSE)
        return Adequacy(False, f"{flat}; a seized valve, a closed block valve, a dead transmitter or a frozen "
                               "archive look the same", facts, Reason.FLAT_PV)
    sp_changes = 0
    if rec.has_sp and np.all(np.isfinite(rec.sp)):
        sp_changes = int(np.count_nonzero(np.diff(np.asarray(rec.sp, dtype=float)) != 0.0))
    _, osc = most_regular(rec)
    facts["regularity"], facts["period"] = osc.regularity, osc.period * rec.dt
    facts["oscillating"] = bool(osc.regular)
    facts["sp_changes"] = sp_changes
    excited = sp_changes > 0 or facts["op_range_in_noise"] >= EXCITATION
    facts["excited"] = excited
    if not (excited or osc.regular):
        return Adequacy(False, f"no oscillation (regularity r = {osc.regularity:.2f} ≤ 1) and no excitation (no "
                               f"set-point change; OP's range is {facts['op_range_in_noise']:.1f} noise σ, "
                               f"less than {EXCITATION:g}): nothing moved the loop that the data could learn "
                               "from", facts, Reason.NO_EXCITATION)
    return Adequacy(True, "", facts)


@dataclass(frozen=True)
class Cycle:
    """What a loop-monitoring user reads first: does the loop oscillate, how regularly, how far, how fast.

    Attributes
    ----------
    oscillating : Thornhill et al.'s regularity test says so (``regularity > 1``).
    regularity : that test's index r (mean period over three standard deviations of the periods; nan when too
        few zero crossings).
    period : the cycle's period (s; nan without a cycle).
    pv_amplitude, op_amplitude : half the peak-to-peak swing of PV and OP over the cycle (their units), as
        √2 × the standard deviation left after removing a moving mean one period long (set-point steps and
        slow drift are not cycle); None without a cycle.
    signal : the signal the test found most regular (``"SP − PV"``, ``"PV"`` or ``"OP"``).
    """

    oscillating: bool
    regularity: float
    period: float
    pv_amplitude: float | None = None
    op_amplitude: float | None = None
    signal: str = ""

    @property
    def words(self) -> str:
        """One phrase: ``"oscillation: period 52 s, PV ± 1.3, OP ± 4.1, regularity r = 3.2 (on SP − PV)"``."""
        if not self.oscillating:
            r = "" if not np.isfinite(self.regularity) else f" (regularity r = {self.regularity:.2f} ≤ 1)"
            return f"no oscillation{r}"
        return (f"oscillation: period {self.period:.3g} s, PV ± {self.pv_amplitude:.3g}, OP ± "
                f"{self.op_amplitude:.3g}, regularity r = {self.regularity:.2f} (on {self.signal})")

    def to_json(self) -> dict:
        def num(x):
            return None if x is None or not np.isfinite(x) else float(f"{x:.6g}")
        return {"oscillating": self.oscillating, "regularity": num(self.regularity),
                "period": num(self.period) if self.oscillating else None, "pv_amplitude": num(self.pv_amplitude),
                "op_amplitude": num(self.op_amplitude), "signal": self.signal or None, "words": self.words}


def most_regular(rec: Recording):
    """The regularity test (Thornhill, Huang & Zhang 2003) on SP − PV (when a set point is recorded), PV and OP:
    ``(name, result)`` of the most regular of them (the first on a tie), regular or not."""
    pv, op = np.asarray(rec.pv, dtype=float), np.asarray(rec.op, dtype=float)
    signals = {"PV": pv, "OP": op}
    if rec.has_sp and np.all(np.isfinite(rec.sp)):
        signals = {"SP − PV": np.asarray(rec.sp, dtype=float) - pv, **signals}
    tests = {name: oscillation(x) for name, x in signals.items()}
    return max(tests.items(), key=lambda kv: kv[1].regularity if kv[1].regular else -1.0)


def cycle_swing(x: np.ndarray, samples: int) -> float:
    """Half the peak-to-peak swing of a cycle ``samples`` long in ``x``: √2 × the standard deviation of ``x``
    less its centred moving mean over one period (exact for a sine)."""
    x = np.asarray(x, dtype=float)
    n = int(min(max(samples, 1), x.size))
    mean = np.convolve(np.pad(x, (n // 2, n - 1 - n // 2), mode="edge"), np.ones(n) / n, mode="valid")
    return float(np.sqrt(2.0) * np.std(x - mean))


def cycle(rec: Recording) -> Cycle:
    """The oscillation summary of ``rec``: the regularity test on SP − PV (with a set point), PV and OP, the most
    regular of them, and the swings of PV and OP at its period."""
    pv, op = np.asarray(rec.pv, dtype=float), np.asarray(rec.op, dtype=float)
    name, osc = most_regular(rec)
    if not osc.regular:
        return Cycle(False, float(osc.regularity), float("nan"))
    samples = int(round(osc.period))
    return Cycle(True, float(osc.regularity), float(osc.period * rec.dt), cycle_swing(pv, samples),
                 cycle_swing(op, samples), name)
