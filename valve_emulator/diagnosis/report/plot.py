r"""The diagnosis figure (PNG; drawn on a :class:`matplotlib.figure.Figure` of its own, so it needs no display
and leaves pyplot and the caller's backend alone).

With the recording (:meth:`~valve_emulator.diagnosis.report.diagnosis.Diagnosis.plot`), the figure opens with
what every loop-monitoring user reads first: the raw OP, PV (and SP) trend over the whole record, and the
PV–OP phase plot (MV–OP when the recording has the valve position; a sticky valve draws a parallelogram, a
linear valve a line), beside the answer, its oscillation summary and the recommended action. Then four panels:

1. the nominal model's residual (plant data: the identified linear model's) over the whole record, the
   located windows shaded, the held-out part marked;
2. recorded PV against the nominal replay and the final model on a stretch of the held-out part;
3. MV against OP of the fitted valve (the model's valve position; the recording has none), or flow against
   OP when the finding is a flow characteristic;
4. the cost surface over (S, J) of the stiction search, as ΔBIC against its best point, with the estimate.
"""

from __future__ import annotations

import os
import textwrap

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from valve_emulator.detectors.base import oscillation
from valve_emulator.diagnosis.explain.result import Explanation
from valve_emulator.diagnosis.fit.frame import TRAVEL, UNKNOWN_UNITS, Frame
from valve_emulator.recordings.recording import Recording

__all__ = ["op_units", "plot_diagnosis", "plot_trend", "plot_phase"]

# Samples the PV panel shows of the held-out part when OP does not cycle (else a few cycles of it).
_SHOW = 600
# Cycles shown: of the held-out part in the PV panel, and at the record's end in the valve panel.
_CYCLES_PV, _CYCLES_VALVE = 4, 2


def op_units(frame: Frame | None) -> str:
    """OP's units for an axis label: % travel by default, the recording's own when its span is unknown."""
    if frame is None:
        return TRAVEL
    return "its own units" if frame.units == UNKNOWN_UNITS else frame.units


def _shown(period: float | None, cycles: int, otherwise: int) -> int:
    """Samples to show: ``cycles`` periods of OP's regular cycle (``period`` in samples), else ``otherwise`` —
    a fixed number of samples shows a fraction of a cycle of a finely sampled record and a tangle of cycles of
    a coarsely sampled one."""
    return int(np.ceil(cycles * period)) if period is not None else otherwise


def plot_trend(ax, rec: Recording, op_label: str) -> list:
    """OP (left axis), PV and SP (right axis) over the whole record; returns the lines for a legend."""
    ax.plot(rec.t, rec.op, color="tab:blue", lw=0.8, label=op_label)
    ax.set(xlabel="t (s)", ylabel=op_label)
    ax2 = ax.twinx()
    ax2.plot(rec.t, rec.pv, color="tab:red", lw=0.8, label="PV")
    if rec.has_sp:
        ax2.plot(rec.t, rec.sp, color="k", ls="--", lw=0.7, label="SP")
    ax2.set_ylabel("PV")
    ax.set_title("The recording: OP, PV and SP", fontsize=10)
    return ax.get_lines() + ax2.get_lines()


def plot_phase(fig: Figure, ax, rec: Recording, op_label: str) -> None:
    """The phase plot, coloured by time: MV against OP when the recording has the valve position, else PV
    against OP."""
    y, name = (rec.mv, "MV") if rec.mv is not None and np.all(np.isfinite(rec.mv)) else (rec.pv, "PV")
    sc = ax.scatter(rec.op, y, c=rec.t, s=3, cmap="viridis")
    ax.plot(rec.op, y, color="0.75", lw=0.3, zorder=0)
    fig.colorbar(sc, ax=ax, label="t (s)")
    ax.set(xlabel=op_label, ylabel=name, title=f"{name} against OP (phase plot)")


def _summary(ax, lines: tuple[str, ...]) -> None:
    """A text panel: the answer, the oscillation summary, the action."""
    text = "\n\n".join("\n".join(textwrap.wrap(line, 62)) for line in lines)
    ax.text(0.0, 1.0, text, ha="left", va="top", fontsize=9, transform=ax.transAxes)
    ax.set_axis_off()


def plot_diagnosis(d: Explanation, path: str | os.PathLike, *, recording: Recording | None = None,
                   summary: tuple[str, ...] = (), title: str = "") -> None:
    """Write the figure of ``d`` to ``path`` (PNG): with ``recording``, the trend, the phase plot and the
    ``summary`` lines first, then the four panels."""
    tr = d.traces
    top = recording is not None
    fig = Figure(figsize=(13, 14.5 if top else 8.5), constrained_layout=True)
    grid = fig.add_gridspec(4 if top else 2, 2, height_ratios=(0.9, 1.0, 1.0, 1.0) if top else (1.0, 1.0))
    if top:
        units = op_units(d.fitted.frame if d.fitted is not None else None)
        op_label = f"OP ({units})"
        ax = fig.add_subplot(grid[0, :])
        handles = plot_trend(ax, recording, op_label)
        ax.legend(handles, [h.get_label() for h in handles], fontsize=8, loc="upper left")
        plot_phase(fig, fig.add_subplot(grid[1, 0]), recording, op_label)
        _summary(fig.add_subplot(grid[1, 1]), summary)
    axes = np.array([[fig.add_subplot(grid[r, c]) for c in range(2)] for r in ((2, 3) if top else (0, 1))])
    head = (title + "\n" if title else "") + "\n".join(textwrap.wrap(d.verdict, 150))
    fig.suptitle(head, fontsize=10 if not top else 9)

    ax = axes[0, 0]
    ax.plot(tr.t, tr.pv - tr.pv_before, lw=0.6, color="tab:red")
    for a, b in d.located.windows:
        ax.axvspan(a, b, color="tab:orange", alpha=0.3, lw=0)
    ax.axvline(tr.t[tr.test_start], color="k", ls="--", lw=0.8)
    ax.text(tr.t[tr.test_start], ax.get_ylim()[1], " held out →", va="top", fontsize=8)
    base = "nominal model" if d.given else "linear model identified from the data"
    ax.set(title=f"Residual of the {base} (windows shaded)", xlabel="t (s)", ylabel="PV − simulated PV")

    osc = oscillation(tr.op)
    period = osc.period if osc.regular else None   # Thornhill's r > 1
    ax = axes[0, 1]
    s = slice(tr.test_start, min(tr.t.size, tr.test_start + _shown(period, _CYCLES_PV, _SHOW)))
    ax.plot(tr.t[s], tr.pv[s], color="0.7", lw=2.6, label="recorded PV")  # wide: visible under a fit of 100 %
    ax.plot(tr.t[s], tr.pv_before[s], color="tab:red", ls="--", lw=1.0,
            label=f"{base}, fit {d.fit_before:.0f} %")
    ax.plot(tr.t[s], tr.pv_after[s], color="tab:blue", lw=1.2, label=f"with the findings, fit {d.fit_after:.0f} %")
    ax.set(title="Held-out part: recorded vs simulated PV", xlabel="t (s)", ylabel="PV")
    ax.legend(fontsize=8, loc="best")

    frame = d.fitted.frame if d.fitted is not None else None
    units = op_units(frame)
    ax = axes[1, 0]
    k = slice(max(0, tr.t.size - _shown(period, _CYCLES_VALVE, 2 * _SHOW)), tr.t.size)
    found = {f.physics for f in d.findings}
    if "characteristic" in found:  # the finding lives on the flow axis: show the fitted curve
        order = np.argsort(tr.op)
        ax.plot(tr.op[order], tr.flow_after[order], color="tab:blue", lw=1.2, label="fitted valve")
        flow = "flow (% of maximum)" if frame is None else f"flow (as OP, {units})"
        ax.set(title="Fitted valve: flow against OP", xlabel=f"OP ({units})", ylabel=flow)
    else:
        ax.plot(tr.op[k], tr.mv_after[k], color="tab:blue", lw=0.8, label="fitted valve")
        ax.set(title="Fitted valve: MV against OP (last part of the record)", xlabel=f"OP ({units})",
               ylabel=f"MV ({units})")
    lo, hi = float(np.min(tr.op[k])), float(np.max(tr.op[k]))
    ax.plot([lo, hi], [lo, hi], color="0.6", ls=":", lw=1.0, label="nominal (linear, MV = OP)")
    ax.legend(fontsize=8, loc="best")

    ax = axes[1, 1]
    if tr.surface is None:
        ax.text(0.5, 0.5, "stiction not searched", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
    else:
        S, J, cost = tr.surface
        shown = np.ma.masked_invalid(cost + 1.0)  # +1: a log colour scale that starts at the best point
        mesh = ax.pcolormesh(S, J, shown, shading="nearest", cmap="viridis_r",
                             norm=LogNorm(vmin=1.0, vmax=max(10.0, float(np.nanmax(cost)) + 1.0)))
        fig.colorbar(mesh, ax=ax, label="ΔBIC + 1 (log scale)")
        ax.plot(S, S, color="w", lw=0.8, ls=":")
        ax.text(S[-1], S[-1], " J = S", color="w", fontsize=8, va="bottom", ha="right")
        accepted = "stiction" in {f.physics for f in d.findings}
        if tr.surface_best is not None:
            ax.plot(*tr.surface_best, marker="x", color="r", ms=10, mew=2,
                    label="estimate" if accepted else "best of the search (not accepted)")
            ax.legend(fontsize=8, loc="upper left")
        title = "Stiction cost surface over (S, J)" + ("" if accepted else " — stiction not accepted")
        if tr.surface_load_model:
            title += "\n(scored through the drifting-load noise model)"
        ax.set(title=title,
               xlabel=f"S ({units})", ylabel=f"J ({units})", ylim=(J[0], J[-1]))
    fig.savefig(path, dpi=110)
