// Operator and instructor station: live state over server-sent events, faceplate, canvas trend and XY plot.
// Plain JavaScript, no libraries. The page's role (trainee/instructor) is in <body data-role>.
"use strict";
const INSTRUCTOR = document.body.dataset.role === "instructor";
const $ = (id) => document.getElementById(id);
const TREND_SAMPLES = 600;        // points kept per loop for the trend
const S = { unit: null, loops: [], buf: [], source: null, last: null };

async function api(method, path, body) {
  const opts = { method, headers: { "Content-Type": "application/json" } };
  if (method !== "GET") opts.body = JSON.stringify(body || {});
  const resp = await fetch(path, opts);
  const data = await resp.json().catch(() => ({}));
  if (!resp.ok) throw new Error(data.error || resp.statusText);
  return data;
}

function say(text, ok) { const m = $("msg"); m.textContent = text; m.style.color = ok ? "#264" : "#a00"; }

// run an action; a string it returns is shown as confirmation, an error's message as a refusal
async function act(fn) {
  try { const note = await fn(); say(typeof note === "string" ? note : "", true); } catch (e) { say(e.message, false); }
}

// --- loop list and stream -------------------------------------------------------------------------------
async function loadLoops() {
  S.loops = (await api("GET", "/api/loops")).loops;
  const ul = $("loops"); ul.innerHTML = "";
  for (const lp of S.loops) {
    const li = document.createElement("li");
    li.dataset.unit = lp.unit; li.textContent = `${lp.unit} · ${lp.name}`;
    li.onclick = () => select(lp.unit);
    ul.appendChild(li);
  }
  if (S.loops.length) select(S.loops[0].unit);
}

function select(unit) {
  S.unit = unit; S.buf = [];
  for (const li of $("loops").children) li.classList.toggle("selected", Number(li.dataset.unit) === unit);
  if (S.source) S.source.close();
  S.source = new EventSource(`/api/stream?units=${unit}&rate=10${INSTRUCTOR ? "" : "&view=trainee"}`);
  S.source.onmessage = (ev) => update(JSON.parse(ev.data));
}

// --- rendering --------------------------------------------------------------------------------------------
function pct(x, lo, hi) { return Math.max(0, Math.min(100, 100 * (x - lo) / (hi - lo))); }
function fmt(x, d = 2) { return x === null || x === undefined ? "–" : Number(x).toFixed(d); }

function update(state) {
  S.last = state;
  $("clock").textContent = `t = ${state.time.toFixed(1)} s`;
  $("run-state").textContent = state.running ? `RUN ×${state.time_scale ?? "max"}` : "FROZEN";
  if (INSTRUCTOR && document.activeElement !== $("speed") && state.time_scale) $("speed").value = state.time_scale;
  const lp = state.loops.find((l) => l.unit === S.unit);
  if (!lp) return;
  const [lo, hi] = lp.pv_range, u = lp.pv_units ? ` ${lp.pv_units}` : "";
  $("fp-title").textContent = `${lp.name} (unit ${lp.unit})`;
  $("bar-sp").style.height = pct(lp.sp, lo, hi) + "%"; $("val-sp").textContent = fmt(lp.sp) + u;
  $("bar-pv").style.height = pct(lp.pv, lo, hi) + "%"; $("val-pv").textContent = fmt(lp.pv) + u;
  $("bar-op").style.height = pct(lp.op, 0, 100) + "%"; $("val-op").textContent = fmt(lp.op) + " %";
  $("lim-hi").style.bottom = pct(lp.limits[1], lo, hi) + "%"; $("lim-lo").style.bottom = pct(lp.limits[0], lo, hi) + "%";
  $("mode").textContent = lp.mode.toUpperCase();
  for (const k of ["stuck", "moving", "saturated", "fault"]) $("lamp-" + k).classList.toggle("on", lp.status[k]);
  const al = $("alarm"); al.className = lp.alarm;
  al.textContent = { normal: "no alarm", unacked: "PV ALARM (unacknowledged)", acked: "PV alarm (acknowledged)",
                     returned: "PV alarm returned (unacknowledged)" }[lp.alarm];
  for (const li of $("loops").children) if (Number(li.dataset.unit) === lp.unit) li.classList.toggle("alarm", lp.alarm !== "normal");
  const showMv = "mv" in lp;
  $("mv-legend").hidden = !showMv;
  if ($("xy-mv-title")) $("xy-mv-title").hidden = !showMv;
  if (INSTRUCTOR) {
    $("val-mv").textContent = fmt(lp.mv); $("val-S").textContent = fmt(lp.S); $("val-J").textContent = fmt(lp.J);
    $("reveal").checked = lp.mv_revealed;
    $("score").textContent = state.score ? fmt(state.score.score, 1) : "–";
    $("mf-active").textContent = state.malfunctions.length ? `ramps running: ${state.malfunctions.map((r) => `${r.quantity}→${r.target}`).join(", ")}` : "";
    $("notes").innerHTML = state.notes.map((n) => `<div>${n.time.toFixed(1)} s: ${escapeHtml(n.text)}</div>`).join("");
    renderScenario(state.scenario);
  } else {
    $("hints").innerHTML = state.hints.map((h) => `<div>Hint: ${escapeHtml(h)}</div>`).join("");
  }
  const last = S.buf[S.buf.length - 1];
  if (!last || last.t !== state.time) {
    S.buf.push({ t: state.time, sp: lp.sp, pv: lp.pv, op: lp.op, mv: showMv ? lp.mv : null });
    if (S.buf.length > TREND_SAMPLES) S.buf.shift();
  }
  drawTrend(lo, hi, showMv); drawXY(lo, hi, showMv);
}

function escapeHtml(s) { return String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`); }

function line(ctx, pts, color) {
  ctx.strokeStyle = color; ctx.lineWidth = 1.6; ctx.beginPath();
  pts.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y))); ctx.stroke();
}

function axes(ctx, w, h, m, xlab, ylab) {
  ctx.clearRect(0, 0, w, h); ctx.strokeStyle = "#999"; ctx.lineWidth = 1; ctx.strokeRect(m, 8, w - m - 8, h - m - 8);
  ctx.fillStyle = "#333"; ctx.font = "11px sans-serif"; ctx.fillText(xlab, w / 2 - 20, h - 6);
  ctx.save(); ctx.translate(11, h / 2); ctx.rotate(-Math.PI / 2); ctx.fillText(ylab, -20, 0); ctx.restore();
}

function drawTrend(lo, hi, showMv) {
  const c = $("trend"), ctx = c.getContext("2d"), w = c.width, h = c.height, m = 40, b = S.buf;
  axes(ctx, w, h, m, "time (s)", "PV / OP");
  if (b.length < 2) return;
  const t0 = b[0].t, t1 = Math.max(b[b.length - 1].t, t0 + 1e-9);
  const X = (t) => m + (w - m - 8) * (t - t0) / (t1 - t0);
  const Ypv = (y) => 8 + (h - m - 8) * (1 - (y - lo) / (hi - lo));
  const Yop = (y) => 8 + (h - m - 8) * (1 - y / 100);
  ctx.fillStyle = "#333";
  ctx.fillText(`${t0.toFixed(0)}`, m, h - m + 14); ctx.fillText(`${t1.toFixed(0)}`, w - 40, h - m + 14);
  ctx.fillText(`${hi}`, 2, 16); ctx.fillText(`${lo}`, 2, h - m);
  ctx.fillStyle = "#d0722e"; ctx.fillText("100 %", w - 44, 20); ctx.fillText("0 %", w - 34, h - m - 4);
  line(ctx, b.map((p) => [X(p.t), Yop(p.op)]), "#d0722e");
  if (showMv) line(ctx, b.filter((p) => p.mv !== null).map((p) => [X(p.t), Yop(p.mv)]), "#7a4bb0");
  line(ctx, b.map((p) => [X(p.t), Ypv(p.sp)]), "#3b9c4a");
  line(ctx, b.map((p) => [X(p.t), Ypv(p.pv)]), "#2f6fb4");
}

function drawXY(lo, hi, showMv) {
  const c = $("xy"), ctx = c.getContext("2d"), w = c.width, h = c.height, m = 40, b = S.buf;
  axes(ctx, w, h, m, "OP (%)", "PV, MV");
  if (b.length < 2) return;
  const ops = b.map((p) => p.op), o0 = Math.min(...ops) - 0.5, o1 = Math.max(...ops) + 0.5;
  const X = (x) => m + (w - m - 8) * (x - o0) / (o1 - o0);
  const pvs = b.map((p) => p.pv), p0 = Math.min(...pvs) - 0.1, p1 = Math.max(...pvs) + 0.1;
  const Ypv = (y) => 8 + (h - m - 8) * (1 - (y - p0) / (p1 - p0));
  line(ctx, b.map((p) => [X(p.op), Ypv(p.pv)]), "#2f6fb4");
  if (showMv) {
    const mvs = b.filter((p) => p.mv !== null);
    line(ctx, mvs.map((p) => [X(p.op), 8 + (h - m - 8) * (1 - (p.mv - o0) / (o1 - o0))]), "#7a4bb0");
  }
}

// --- operator actions ---------------------------------------------------------------------------------------
$("btn-auto").onclick = () => act(() => api("POST", `/api/loops/${S.unit}`, { mode: "auto" }));
$("btn-manual").onclick = () => act(() => api("POST", `/api/loops/${S.unit}`, { mode: "manual" }));
$("sp-set").onclick = () => act(() => api("POST", `/api/loops/${S.unit}`, { sp: Number($("sp-input").value) }));
$("op-set").onclick = () => act(() => api("POST", `/api/loops/${S.unit}`, { op: Number($("op-input").value) }));
$("ack").onclick = () => act(() => api("POST", `/api/alarms/${S.unit}/ack`));

// --- instructor -----------------------------------------------------------------------------------------------
const MF_PARAMS = { stiction: ["S", "J"], load: ["flow"], noise: ["std"], sensor_stuck: ["value"], sensor_drift: ["bias"] };

function renderMfParams() {
  const kind = $("mf-kind").value;
  $("mf-params").innerHTML = (MF_PARAMS[kind] || []).map((p) => `${p} <input id="mf-${p}" type="number" step="any">`).join(" ");
}

async function refreshSnapshots() {
  const data = await api("GET", "/api/snapshots");
  const row = (s) => `<tr><td>${escapeHtml(s.name)}</td><td>${s.time.toFixed(1)} s</td>` +
    `<td><button data-restore="${escapeHtml(s.name)}">restore</button></td>`;
  $("snap-list").innerHTML = data.snapshots.map((s) => row(s) + `<td><button data-delete="${escapeHtml(s.name)}">delete</button></td></tr>`).join("");
  $("bt-list").innerHTML = data.backtrack.slice().reverse().map((s) => row(s) + "</tr>").join("");
  for (const b of document.querySelectorAll("[data-restore]")) b.onclick = () => act(async () => { await api("POST", `/api/snapshots/${b.dataset.restore}/restore`); S.buf = []; });
  for (const b of document.querySelectorAll("[data-delete]")) b.onclick = () => act(async () => { await api("DELETE", `/api/snapshots/${b.dataset.delete}`); refreshSnapshots(); });
}

function renderScenario(sc) {
  if (!sc) { $("sc-info").textContent = "no scenario"; return; }
  $("sc-info").innerHTML = `<b>${escapeHtml(sc.name)}</b> ${sc.running ? "running" : "stopped"} · ${sc.fired.length} of ${sc.events} events, triggers fired: ${sc.triggers_fired.join(", ") || "none"}`;
  $("hints").innerHTML = sc.hints.map((h) => `<div>${h.released ? "✓" : `<button data-hint="${escapeHtml(h.id)}">release</button>`} ${escapeHtml(h.text)}</div>`).join("");
  for (const b of document.querySelectorAll("[data-hint]")) b.onclick = () => act(() => api("POST", `/api/hints/${b.dataset.hint}/release`));
}

if (INSTRUCTOR) {
  $("run").onclick = () => act(() => api("POST", "/api/run"));
  $("freeze").onclick = () => act(() => api("POST", "/api/freeze"));
  $("speed-set").onclick = () => act(() => api("POST", "/api/speed", { time_scale: Number($("speed").value) }));
  $("reveal").onchange = () => act(() => api("POST", "/api/reveal", { unit: S.unit, mv: $("reveal").checked }));
  $("mf-kind").onchange = renderMfParams; renderMfParams();
  $("mf-inject").onclick = () => act(async () => {
    const kind = $("mf-kind").value, body = { unit: S.unit, kind };
    for (const p of MF_PARAMS[kind] || []) { const v = $("mf-" + p).value; if (v !== "") body[p] = Number(v); }
    const ramp = Number($("mf-ramp").value); if (ramp > 0) body.ramp = ramp;
    await api("POST", "/api/malfunctions", body);
    return `injected ${kind}`;
  });
  $("snap-save").onclick = () => act(async () => { await api("POST", "/api/snapshots", { name: $("snap-name").value }); refreshSnapshots(); });
  $("sc-load").onclick = () => act(() => api("POST", "/api/scenario", { yaml: $("sc-yaml").value }));
  $("sc-start").onclick = () => act(() => api("POST", "/api/scenario/start"));
  $("sc-stop").onclick = () => act(() => api("POST", "/api/scenario/stop"));
  $("session").onclick = () => act(() => api("POST", "/api/session"));
  refreshSnapshots(); setInterval(() => refreshSnapshots().catch(() => {}), 5000);
}

// for tests and curious trainers: the samples the trend is drawn from
window.stationTrend = () => S.buf.slice();
loadLoops().catch((e) => say(e.message, false));
