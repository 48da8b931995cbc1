r"""The fitted loop as a simulator: the final model of a diagnosis, replayed on any OP.

A diagnosis ends with a model of the path OP → PV (see :mod:`~valve_emulator.diagnosis.fit.chain`):

.. math::  \mathrm{flow} = \mathcal{C}_\eta(\mathrm{op}), \qquad
           \hat y_k = \sum_i b_i\, z_{k - \theta/\Delta t - i} + c + d\,k/N, \qquad
           \widehat{\mathrm{pv}} = \mathcal{O}_\zeta(\hat y)\,\sigma_y + \bar y,

with :math:`\mathcal C_\eta` the chain with the accepted physics (the nominal valve and characteristic where
none was accepted), :math:`z` the flow filtered by the fitted poles around the recorded flow's mean, θ the
dead time, :math:`b, c, d` the fitted taps, offset and trend (N the record's length), :math:`\mathcal O_\zeta`
an accepted output term (a disturbance sinusoid, a quantiser) and :math:`\sigma_y, \bar y` the PV scaling of
the fit. :meth:`FittedLoop.predict` evaluates it as a free run — no measured PV enters — so on the recorded OP
it gives the prediction whose held-out fit the diagnosis reports, and on a new OP what the fitted loop would do.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainContext
from valve_emulator.diagnosis.fit.chain import Active, run_chain
from valve_emulator.diagnosis.fit.frame import Frame
from valve_emulator.diagnosis.fit.linear import LinearFit

__all__ = ["FittedLoop"]


@dataclass(frozen=True, eq=False, kw_only=True)
class FittedLoop:
    """The final model of a diagnosis (see the module docstring).

    Attributes
    ----------
    active : the accepted physics with their parameters, by slot.
    nominal_valve : ``(S, J)`` of the nominal valve, used when no valve physics was accepted.
    ctx : the chain context of the fit (sample time, valve model, nominal characteristic, PV scaling).
    linear : the fitted linear part (PV domain, scaled units).
    level : the recorded flow's mean, which the linear part's filter removed.
    record_length : samples in the fitted record (the trend regressor's scale).
    op : the recorded OP in the search's frame (a prediction on it reuses what the output term measured).
    frame : the map of OP's own units into the search's frame (:mod:`~valve_emulator.diagnosis.fit.frame`).
    """

    active: dict[str, Active]
    nominal_valve: tuple[float, float]
    ctx: ChainContext
    linear: LinearFit
    level: float
    record_length: int
    op: np.ndarray
    frame: Frame | None = None

    def flow(self, op: np.ndarray) -> np.ndarray:
        """The chain's output (% flow) for ``op`` (T,)."""
        ctx = replace(self.ctx, op=op)
        chain = {k: a for k, a in self.active.items() if k not in ("delay", "output")}
        return run_chain(op, chain, ctx, nominal_valve=self.nominal_valve)[:, 0]

    def predict(self, op) -> np.ndarray:
        """Free-run PV (engineering units) of the fitted loop for the controller output ``op`` (OP's units, as
        recorded).

        ``op`` is any 1-D array of at least two finite values sampled at the recording's step; the first
        sample is ``t = 0`` of the run (an output disturbance's phase counts from it).
        """
        op = np.asarray(op, dtype=float)
        if op.ndim != 1 or op.size < 2:
            raise ValueError(f"op must be a 1-D array of at least 2 samples, got shape {op.shape}")
        bad = np.flatnonzero(~np.isfinite(op))
        if bad.size:
            raise ValueError(f"op must be finite, got {op[bad[0]]} at index {bad[0]}")
        if self.frame is not None:
            op = self.frame.to_internal(op)
        recorded = op.shape == self.op.shape and np.array_equal(op, self.op)
        flow = self.flow(op)
        if recorded:
            y = self.linear.predict(flow, self.ctx.dt)
        else:
            y = self.linear.predict(flow, self.ctx.dt, level=self.level, record_length=self.record_length)
        out = self.active.get("output")
        if out is not None:
            if recorded:
                y = out.candidate.predict(y, out.params, self.ctx)
            else:
                y = out.candidate.simulate(y, out.params, replace(self.ctx, op=op, pv=None))
        return y * self.ctx.y_scale + self.ctx.y_mean
