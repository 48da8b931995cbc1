"""The end-of-session report as one self-contained HTML page (trend PNGs inlined as data URIs)."""

from __future__ import annotations

import base64
import html
from typing import Any

from valve_emulator.station.evaluation import trend_png

__all__ = ["render_html"]


def _row(cells: list[Any], tag: str = "td") -> str:
    return "<tr>" + "".join(f"<{tag}>{html.escape(str(c))}</{tag}>" for c in cells) + "</tr>"


def render_html(station: Any) -> str:
    """The report of ``station``'s current session: scores, per-loop IAE and time outside limits, response
    times, the action log, and a trend PNG (PV, SP, OP, MV) of each loop the trend keeps."""
    rep = station.report()
    ev = station.evaluation
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>Training session report</title>",
             "<style>body{font-family:sans-serif;margin:2em;color:#222}table{border-collapse:collapse;margin:1em 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}"
             "td:first-child,th:first-child{text-align:left}</style></head><body>",
             "<h1>Training session report</h1>",
             f"<p>Simulated time {rep['start']:.1f} s to {rep['end']:.1f} s ({rep['samples']} samples of "
             f"{rep['dt']:g} s). Score <b>{rep['score']['score']:.1f}</b> (penalty "
             f"{rep['score']['penalty']:.1f}).</p>", "<h2>Loops</h2><table>",
             _row(["unit", "name", "IAE (PV units·s)", "time outside limits (s)", "limits"], "th")]
    for lp in rep["loops"]:
        parts.append(_row([lp["unit"], lp["name"], f"{lp['iae']:.3f}", f"{lp['time_outside']:.1f}",
                           f"{lp['limits'][0]:g} .. {lp['limits'][1]:g}"]))
    parts.append("</table><h2>Responses to malfunctions</h2><table>")
    parts.append(_row(["unit", "malfunction", "injected (s)", "first correct action", "response time (s)"], "th"))
    for r in rep["responses"]:
        parts.append(_row([r["unit"], r["malfunction"], f"{r['injected']:.1f}", r["action"],
                           f"{r['response_time']:.1f}"]))
    for u in rep["unanswered"]:
        parts.append(_row([u["unit"], u["malfunction"], f"{u['injected']:.1f}", "none", "—"]))
    parts.append("</table><h2>Action log</h2><table>")
    parts.append(_row(["simulated time (s)", "wall time", "who", "unit", "action", "value", "result"], "th"))
    import time as _time
    for a in rep["actions"]:
        wall = _time.strftime("%H:%M:%S", _time.localtime(a["wall_time"]))
        parts.append(_row([f"{a['sim_time']:.1f}", wall, a["who"], a["unit"] if a["unit"] is not None else "",
                           a["action"], "" if a["value"] is None else a["value"],
                           "ok" if a["accepted"] else f"refused: {a['message']}"]))
    parts.append("</table><h2>Trends</h2>")
    for i in range(ev.trend.loops):
        series = ev.trend.series(i)
        if series["t"].size < 2:
            continue
        png = trend_png(series, title=f"unit {station.device.units[i]} ({station.names[i]})", show_mv=True)
        parts.append(f"<p><img alt='trend of unit {station.device.units[i]}' "
                     f"src='data:image/png;base64,{base64.b64encode(png).decode()}'></p>")
    parts.append("</body></html>")
    return "\n".join(parts)
