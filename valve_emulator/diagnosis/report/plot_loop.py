r"""One loop's assessment as a figure (PNG, on a :class:`matplotlib.figure.Figure` of its own: no display, no
pyplot state): the data, and why the answer is what it is.

Three panels:

1. OP (left axis) and PV with its set point (right axis) over time — where a stuck valve, a cycle or a
   flat PV shows; shaded, the half a record was answered on when one model explains neither the whole;
2. PV against OP (MV against OP when the valve position is recorded), coloured by time — a sticky valve
   draws a parallelogram, a linear valve a line;
3. the recorded PV against the final model's replay (and the linear model's) when there is a diagnosis,
   otherwise the refusal's reason.

The title holds the label (when given), the answer and its reason.
"""

from __future__ import annotations

import os
import textwrap

import numpy as np
from matplotlib.figure import Figure

from valve_emulator.diagnosis.answers import Reason
from valve_emulator.diagnosis.assess.result import Assessment
from valve_emulator.diagnosis.report.plot import op_units, plot_phase, plot_trend
from valve_emulator.recordings.recording import Recording

__all__ = ["plot_loop"]


def plot_loop(rec: Recording, a: Assessment, path: str | os.PathLike, *, title: str = "",
              summary: tuple[str, ...] = ()) -> None:
    """Write the three-panel figure of ``a`` (on recording ``rec``) to ``path``; ``summary`` lines (the
    oscillation summary, the action) join the refusal's reason."""
    fig = Figure(figsize=(13, 8.5), constrained_layout=True)
    grid = fig.add_gridspec(2, 2, height_ratios=(1.0, 1.1))
    head = (title + "\n" if title else "") + "\n".join(textwrap.wrap(a.statement, 150))
    fig.suptitle(head, fontsize=9)

    # Without a model (a refused record) nothing says what OP's units are: the recording's own.
    op_label = f"OP ({op_units(a.frame)})" if a.frame is not None else "OP"
    ax = fig.add_subplot(grid[0, :])
    handles = plot_trend(ax, rec, op_label)
    if a.explanation is not None and Reason.PART_OF_RECORD in a.codes:
        t = a.explanation.traces.t
        handles.append(ax.axvspan(t[0], t[-1], color="tab:green", alpha=0.08, label="the part answered"))
    ax.legend(handles, [h.get_label() for h in handles], fontsize=8, loc="upper left")

    plot_phase(fig, fig.add_subplot(grid[1, 0]), rec, op_label)

    ax = fig.add_subplot(grid[1, 1])
    d = a.explanation
    if d is None:
        lines = (f"no model: {a.reason}", *summary)
        ax.text(0.5, 0.5, "\n\n".join("\n".join(textwrap.wrap(line, 60)) for line in lines), ha="center",
                va="center", transform=ax.transAxes, fontsize=9)
        ax.set_axis_off()
    else:
        tr = d.traces
        ax.plot(tr.t, tr.pv, color="0.55", lw=0.8, label="recorded PV")
        ax.plot(tr.t, tr.pv_base, color="tab:red", ls="--", lw=1.0,
                label=f"linear valve and plant, fit {d.fit_base:.0f} %")
        if d.findings:
            names = ", ".join(f.physics for f in d.findings)
            ax.plot(tr.t, tr.pv_after, color="tab:blue", lw=1.1, label=f"with {names}, fit {d.fit_after:.0f} %")
        lo, hi = np.percentile(tr.pv, [0.5, 99.5])
        pad = 0.5 * max(hi - lo, 1e-9)
        ax.set_ylim(lo - pad, hi + pad)
        ax.set(xlabel="t (s)", ylabel="PV", title="Replay of the recorded OP (fits cross-validated)")
        ax.legend(fontsize=8, loc="best")
    fig.savefig(path, dpi=90)
