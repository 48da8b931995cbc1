"""A tick in one compiled call: the loop bank's step and its loops' registers encoded into the device's image.

A lockstep client's ``step`` = 1 waits for one tick. At one loop that tick is mostly the price of entering
compiled code, not the physics: numba unboxes every array argument of a call (about 50 ns each), and a tick made
of the bank's step and the image encoder paid that twice, for some 60 arrays. A
:class:`~valve_emulator.simulation.loop.LoopBank` keeps its state in a dozen arrays
(:class:`~valve_emulator.simulation.loop.PackedState`), so :class:`SteppingEncoder` hands those, and the image,
to one kernel that steps the bank (:func:`~valve_emulator.simulation.loop.packed_step_kernel`, the bank's own
step) and then writes every loop's registers with the encoder's own rows (:func:`.registers.kernel._encode_bank_rows`):
the same state and the same words as a step followed by :class:`~.registers.kernel.ImageEncoder`, in one call.

Only for the standard loop current (no custom mA table: ``4 + 0.16·OP``, computed in the kernel); a bank with a
custom table is stepped and encoded as two calls (:class:`~valve_emulator.device.tick.Device` chooses).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from valve_emulator.device.registers.kernel import (
    _CONSTANTS,
    _MAP,
    ImageEncoder,
    _Constants,
    _encode_bank_rows,
    _Map,
)
from valve_emulator.device.registers.scaling import Scaling
from valve_emulator.device.registers.words import CDAB
from valve_emulator.simulation.loop import BOOL_ROWS, ROWS, packed_step_kernel

__all__ = ["SteppingEncoder"]


class SteppingEncoder(ImageEncoder):
    """An :class:`~.registers.kernel.ImageEncoder` that can also step the bank first, in the same compiled call
    (:meth:`step`)."""

    def __init__(self, scaling: Scaling, image: bytearray | np.ndarray, offsets: np.ndarray) -> None:
        super().__init__(scaling, image, offsets)
        if not scaling.linear_ma:
            raise ValueError("SteppingEncoder: the loop current of a custom mA table is computed outside the kernel")
        self._pv_range = np.ascontiguousarray(np.stack([scaling.pv_lo, scaling.pv_hi]), dtype=np.float64)
        self._cdab = scaling.word_order is CDAB

    @staticmethod
    def fits(bank: Any, scaling: Scaling) -> bool:
        """Can this encoder step ``bank`` (a loop bank with packed state) for ``scaling`` (the standard current)?"""
        return hasattr(bank, "step_by") and scaling.linear_ma

    def step(self, bank: Any, tick: int, overruns: int) -> None:
        """``bank.step()``, then the image of the bank as :class:`~.registers.kernel.ImageEncoder` encodes it with
        the counters ``tick`` and ``overruns`` and the time of the sample just computed: one compiled call.
        Raises as ``bank.step()`` does, the image then unchanged."""
        bank.step_by(_step_encode_kernel, self._pv_range, int(tick) & 0xFFFFFFFF, int(overruns) & 0xFFFFFFFF,
                     self._cdab, self._half, self._words16)


def _compile(m: _Map, k: _Constants, rows: tuple, bool_rows: tuple):
    """The kernel for the register table's cells ``m`` and constants ``k`` (literals, as in
    :func:`.registers.kernel._compile`, whose bank encoder this calls after the step) and the loop bank's row numbers
    ``rows`` and ``bool_rows``: closure variables, on whose values numba keys its on-disk cache, so that a bank
    whose rows moved compiles a new kernel instead of loading one that reads the old rows."""

    @numba.njit(cache=True)
    def step_encode_kernel(floats, bools, ints, valve, flow_limits, plant_A, plant_vectors, plant_buf, plant_work, t,
                           dt, noise_missing, pv_range, tick, overruns, cdab, word0,
                           img):  # pragma: no cover - compiled
        """:func:`packed_step_kernel`, then (where it returned 0) every loop's registers at words ``word0`` of
        ``img``, the time register showing ``t``; returns the step's code."""
        code = packed_step_kernel(floats, bools, ints, valve, flow_limits, plant_A, plant_vectors, plant_buf,
                                  plant_work, t, dt, noise_missing)
        if code != 0:
            return code
        F, B = floats, bools
        f32 = np.empty(1, np.float32)
        f32[0] = t
        op = F[rows.op]
        _encode_bank_rows(m, k, img, word0, op, op, True, valve, F[rows.flow], F[rows.pv], F[rows.sp], F[rows.kc],
                          F[rows.ti_inv], F[rows.td], F[rows.S], F[rows.J], F[rows.load], F[rows.noise_std],
                          B[bool_rows.auto], B[bool_rows.has_controller], B[bool_rows.frozen], pv_range[0],
                          pv_range[1], tick, overruns, f32.view(np.uint32)[0], cdab)
        return 0

    return step_encode_kernel


_step_encode_kernel = _compile(_MAP, _CONSTANTS, ROWS, BOOL_ROWS)
