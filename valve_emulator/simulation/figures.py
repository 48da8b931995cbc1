"""Figures in the style of the 2003 paper: time trends beside MV-OP (and PV-OP) phase plots.

Only this module (and the diagnosis plots) import matplotlib. Each figure is a
:class:`matplotlib.figure.Figure` of its own, written straight to a file: it needs no screen, and pyplot's state
and the caller's backend (a notebook's) are left alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from valve_emulator.recordings.recording import Recording

__all__ = ["plot_open_loop_rows", "plot_closed_loop"]

_OP_STYLE = dict(color="0.35", lw=0.9, label="op (valve input)")
_MV_STYLE = dict(color="C0", lw=1.8, label="mv (valve position)")
_PV_STYLE = dict(color="C3", lw=1.4, label="pv")


def plot_open_loop_rows(t: np.ndarray, op: np.ndarray, rows: Sequence[tuple[str, np.ndarray]],
                        path: str | Path, *, title: str = "") -> Path:
    """One row per case: OP and MV against time (left), MV against OP (right): the layout of
    Figure 5 of Choudhury, Thornhill & Shah (2003)."""
    fig = Figure(figsize=(10, 2.1 * len(rows)))
    axes = fig.subplots(len(rows), 2, gridspec_kw={"width_ratios": [2.2, 1]}, squeeze=False)
    for (label, mv), (ax_t, ax_xy) in zip(rows, axes):
        ax_t.plot(t, op, **_OP_STYLE)
        ax_t.plot(t, mv, **_MV_STYLE)
        ax_t.set_ylabel("% travel")
        ax_t.set_title(label, loc="left", fontsize=10)
        ax_xy.plot(op, mv, color="C0", lw=1.4)
        lo, hi = min(op.min(), mv.min()), max(op.max(), mv.max())
        ax_xy.plot([lo, hi], [lo, hi], color="0.8", lw=0.8, ls="--")
        ax_xy.set_xlabel("op, % travel")
        ax_xy.set_ylabel("mv, % travel")
        ax_xy.set_aspect("equal", adjustable="datalim")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time, s")
    return _save(fig, path, title)


def plot_closed_loop(rec: Recording, path: str | Path, *, title: str = "", last: float | None = None) -> Path:
    """Closed-loop recording like the 2003 paper's Figures 6-8.

    Rows: OP and MV against time; PV and SP against time. Right column: MV-OP and PV-OP plots. ``last``
    restricts the plots to the final ``last`` seconds (the steady limit cycle); default the last third.
    """
    t = np.asarray(rec.t)
    span = t[-1] - t[0]
    t0 = t[-1] - (span / 3 if last is None else last)
    sel = t >= t0
    fig = Figure(figsize=(11, 6))
    axes = fig.subplots(2, 2, gridspec_kw={"width_ratios": [2.2, 1]})
    (a_op, a_mvop), (a_pv, a_pvop) = axes
    a_op.plot(t[sel], rec.op[sel], **_OP_STYLE)
    if np.isfinite(rec.mv).any():
        a_op.plot(t[sel], rec.mv[sel], **_MV_STYLE)
        a_mvop.plot(rec.op[sel], rec.mv[sel], color="C0", lw=1.2)
    a_op.set_ylabel("% travel")
    a_op.legend(loc="upper right", fontsize=8)
    a_mvop.set_xlabel("op, % travel")
    a_mvop.set_ylabel("mv, % travel")
    a_mvop.set_title("mv - op", fontsize=10)
    a_pv.plot(t[sel], rec.pv[sel], **_PV_STYLE)
    if np.isfinite(rec.sp).any():
        a_pv.plot(t[sel], rec.sp[sel], color="k", lw=0.8, ls="--", label="sp")
    a_pv.set_xlabel("time, s")
    a_pv.set_ylabel("pv")
    a_pv.legend(loc="upper right", fontsize=8)
    a_pvop.plot(rec.op[sel], rec.pv[sel], color="C3", lw=1.2)
    a_pvop.set_xlabel("op, % travel")
    a_pvop.set_ylabel("pv")
    a_pvop.set_title("pv - op", fontsize=10)
    return _save(fig, path, title)


def _save(fig: Figure, path: str | Path, title: str) -> Path:
    """Every figure's last step: the title (when there is one) over the laid-out axes, written to ``path``."""
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    return path
