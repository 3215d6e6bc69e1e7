// trimag live: polls GET /status several times a second and draws it (plain canvas, no library, nothing fetched
// from the internet).
"use strict";

let state = null;
let yaw = 0.6, pitch = 0.35, dragging = null;

function $(id) { return document.getElementById(id); }
function fmt(v, d) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "boolean") return v ? "yes" : "no";
  if (typeof v === "number") return Math.abs(v) >= 1e5 || (Math.abs(v) < 1e-3 && v !== 0) ? v.toExponential(d || 3)
    : v.toPrecision(d || 4);
  return String(v);
}

function centred(points, centre) {
  // points centred (on `centre`, else their mean) and scaled so that their RMS radius is 1
  const n = points.length;
  if (!n) return [];
  const m = centre ? centre.slice() : [0, 0, 0];
  if (!centre) {
    for (const p of points) { m[0] += p[0]; m[1] += p[1]; m[2] += p[2]; }
    m[0] /= n; m[1] /= n; m[2] /= n;
  }
  let r2 = 0;
  for (const p of points) r2 += (p[0] - m[0]) ** 2 + (p[1] - m[1]) ** 2 + (p[2] - m[2]) ** 2;
  const s = Math.sqrt(r2 / n) || 1;
  return points.map(p => [(p[0] - m[0]) / s, (p[1] - m[1]) / s, (p[2] - m[2]) / s]);
}

function scaled(points, radius) {
  const s = radius || 1;
  return points.map(p => [p[0] / s, p[1] / s, p[2] / s]);
}

function project(p) {
  // rotate about z (yaw) then about x (pitch); returns [screen x, screen y, depth]
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const x = cy * p[0] - sy * p[1], y = sy * p[0] + cy * p[1], z = p[2];
  return [x, -(cp * z - sp * y), cp * y + sp * z];
}

function drawCloud() {
  const c = $("cloud"), g = c.getContext("2d"), w = c.width, h = c.height, k = w * 0.3;
  g.clearRect(0, 0, w, h);
  g.save();
  g.translate(w / 2, h / 2);
  // the unit sphere: three great circles
  g.strokeStyle = "#c8ccd2"; g.lineWidth = 1;
  for (let axis = 0; axis < 3; axis++) {
    g.beginPath();
    for (let t = 0; t <= 64; t++) {
      const a = 2 * Math.PI * t / 64, q = [0, 0, 0];
      q[(axis + 1) % 3] = Math.cos(a); q[(axis + 2) % 3] = Math.sin(a);
      const s = project(q);
      if (t === 0) g.moveTo(s[0] * k, s[1] * k); else g.lineTo(s[0] * k, s[1] * k);
    }
    g.stroke();
  }
  // sensor axes
  const names = ["x", "y", "z"];
  g.font = "13px sans-serif"; g.fillStyle = "#4a5562";
  for (let i = 0; i < 3; i++) {
    const q = [0, 0, 0]; q[i] = 1.35; const s = project(q);
    g.strokeStyle = "#8a939e"; g.beginPath(); g.moveTo(0, 0); g.lineTo(s[0] * k, s[1] * k); g.stroke();
    g.fillText("+" + names[i], s[0] * k + 3, s[1] * k);
  }
  if (state) {
    const raw = centred(state.points_raw || [], state.offset);
    const radius = state.fitted_magnitude || 1;
    const cor = state.points_corrected ? scaled(state.points_corrected, radius) : [];
    const layers = [[raw, "rgba(224,122,31,0.55)"], [cor, "rgba(47,111,222,0.75)"]];
    for (const [pts, colour] of layers) {
      g.fillStyle = colour;
      for (const p of pts) {
        const s = project(p);
        g.fillRect(s[0] * k - 1.5, s[1] * k - 1.5, 3, 3);
      }
    }
  }
  g.restore();
}

function lambert(p, side) {
  // equal-area projection of the hemisphere z*side >= 0 onto a disk of radius 1
  const z = side * p[2], r = Math.sqrt(Math.max(0, 2 * (1 - z))) / Math.SQRT2;
  const n = Math.hypot(p[0], p[1]) || 1;
  return [r * p[0] / n, -r * p[1] / n * side];
}

function drawCoverage() {
  const c = $("coverage"), g = c.getContext("2d"), w = c.width, h = c.height, R = h * 0.42;
  g.clearRect(0, 0, w, h);
  const centres = state && state.coverage_centres, counts = state && state.coverage_cells;
  const minCount = (state && state.coverage_min_count) || 1, never = state && state.never_seen_axis;
  for (const side of [1, -1]) {
    const cx = side > 0 ? w * 0.25 : w * 0.75, cy = h / 2;
    g.strokeStyle = "#8a939e"; g.beginPath(); g.arc(cx, cy, R, 0, 2 * Math.PI); g.stroke();
    g.fillStyle = "#4a5562"; g.font = "13px sans-serif";
    g.fillText(side > 0 ? "+z side" : "−z side", cx - 22, h - 4);
    g.fillText("+x", cx + R + 4, cy + 4);
    g.fillText(side > 0 ? "+y" : "−y", cx - 8, cy - R - 2);
    if (!centres || !counts) continue;
    centres.forEach((p, i) => {
      if (side * p[2] < -0.05) return;
      const s = lambert(p, side), seen = counts[i] >= minCount;
      const isNever = never && Math.abs(p[0] - never[0]) + Math.abs(p[1] - never[1]) + Math.abs(p[2] - never[2]) < 1e-3;
      g.beginPath(); g.arc(cx + s[0] * R, cy + s[1] * R, R * 0.085, 0, 2 * Math.PI);
      g.fillStyle = isNever ? "#b3261e" : seen ? "#1b7f3b" : "#e0e3e8";
      g.fill();
      if (!seen) { g.strokeStyle = "#b3261e"; g.stroke(); }
    });
  }
}

function drawHist() {
  const c = $("hist"), g = c.getContext("2d"), w = c.width, h = c.height;
  g.clearRect(0, 0, w, h);
  if (!state || !state.points_raw || !state.points_raw.length) return;
  const raw = centred(state.points_raw, state.offset).map(p => Math.hypot(p[0], p[1], p[2]));
  const cor = (state.points_corrected || []).map(p => Math.hypot(p[0], p[1], p[2]));
  const bins = 60, lo = 0.5, hi = 1.5;
  const series = [[raw, "rgba(224,122,31,0.6)"], [cor, "rgba(47,111,222,0.7)"]];
  let peak = 1;
  const hists = series.map(([v]) => {
    const mean = v.reduce((a, b) => a + b, 0) / (v.length || 1), hist = new Array(bins).fill(0);
    for (const x of v) { const b = Math.floor((x / mean - lo) / (hi - lo) * bins); if (b >= 0 && b < bins) hist[b]++; }
    peak = Math.max(peak, ...hist);
    return hist;
  });
  hists.forEach((hist, k) => {
    g.fillStyle = series[k][1];
    hist.forEach((n, b) => { const bh = (h - 18) * n / peak; g.fillRect(b * w / bins, h - 16 - bh, w / bins - 1, bh); });
  });
  g.fillStyle = "#4a5562"; g.font = "12px sans-serif";
  g.fillText("0.5", 2, h - 3); g.fillText("1", w / 2 - 3, h - 3); g.fillText("1.5", w - 20, h - 3);
}

function drawHistory() {
  const c = $("history"), g = c.getContext("2d"), w = c.width, h = c.height;
  g.clearRect(0, 0, w, h);
  const hist = (state && state.history) || [];
  if (hist.length < 2) return;
  const nMax = hist[hist.length - 1][0] || 1;
  const rms = hist.map(e => e[2]).filter(v => v !== null), rmsMax = Math.max(...rms, 1e-300);
  const lines = [[1, 1, "#1b7f3b"], [2, rmsMax, "#2f6fde"]];
  for (const [col, top, colour] of lines) {
    g.strokeStyle = colour; g.lineWidth = 2; g.beginPath();
    let started = false;
    for (const e of hist) {
      if (e[col] === null) continue;
      const x = e[0] / nMax * (w - 4) + 2, y = h - 4 - (h - 8) * Math.min(1, e[col] / top);
      if (!started) { g.moveTo(x, y); started = true; } else g.lineTo(x, y);
    }
    g.stroke();
  }
  g.fillStyle = "#4a5562"; g.font = "12px sans-serif"; g.fillText(nMax + " samples", w - 90, h - 6);
}

function showNumbers() {
  const s = state, u = s.units;
  const rows = [
    ["samples", s.n_samples + (s.fit_lag_samples ? ` (fit lags ${s.fit_lag_samples})` : "")],
    ["lines not understood", s.n_garbage],
    ["source", s.source_state + (s.source_message ? ": " + s.source_message : "")],
    ["coverage of the sphere", s.coverage_fraction === null || s.coverage_fraction === undefined ? "–"
      : (100 * s.coverage_fraction).toFixed(0) + " %"],
    [`RMS of |B| − F before [${u}]`, fmt(s.rms_before)],
    [`RMS of |B| − F after [${u}]`, fmt(s.rms_after)],
    [`fitted |B| [${u}]`, fmt(s.fitted_magnitude)],
    ["converged", fmt(s.converged)],
    ["identifiable", fmt(s.identifiable)],
    ["worst-determined (× full sphere)", s.std_inflation_vs_full_sphere ? fmt(s.std_inflation_vs_full_sphere, 3) + " ("
      + (s.weakest_combination || []).join(", ") + ")" : "–"],
    ["fit", (s.fit_message || "") + (s.fit_seconds ? ` (${(1000 * s.fit_seconds).toFixed(0)} ms)` : "")],
  ];
  if (s.param_std) {
    rows.push(["parameter 1σ", Object.entries(s.param_std).map(([k, v]) => `${k} ${fmt(v, 2)}`).join(", ")]);
  }
  $("numbers").innerHTML = "";
  for (const [k, v] of rows) {
    const tr = document.createElement("tr");
    const a = document.createElement("td"), b = document.createElement("td");
    a.textContent = k; b.textContent = v;
    tr.append(a, b); $("numbers").append(tr);
  }
}

function show() {
  const s = state;
  const badge = $("badge");
  badge.className = s.good_enough ? "ok" : "";
  badge.textContent = s.good_enough ? "good enough: save" : s.n_samples ? "not good enough yet" : "waiting for samples";
  $("source").textContent = `${s.source} — ${s.source_state}`;
  $("hint").textContent = s.good_enough ? "The data suffice for the acceptance policy. Save, or keep turning to "
    + "lower the uncertainties." : s.next_orientations;
  const why = $("why"); why.innerHTML = "";
  for (const reason of s.not_good_enough_because || []) {
    const li = document.createElement("li"); li.textContent = reason; why.append(li);
  }
  showNumbers();
  drawCloud(); drawCoverage(); drawHist(); drawHistory();
  document.body.dataset.samples = s.n_samples;
  document.body.dataset.drawn = "1";
}

async function poll() {
  try {
    const r = await fetch("status", { cache: "no-store" });
    if (r.ok) { state = await r.json(); show(); }
  } catch (e) {
    $("source").textContent = "the trimag live server has stopped";
  }
  setTimeout(poll, 250);
}

$("save").addEventListener("click", async () => {
  $("saved").textContent = "saving…";
  try {
    // the session's token, which the server put into this page (no other page can read it): POST needs it
    const token = document.querySelector('meta[name="trimag-token"]').content;
    const r = await fetch("save", { method: "POST", headers: { "X-Trimag-Token": token } }), body = await r.json();
    $("saved").textContent = r.ok ? "saved " + Object.values(body.written).join(", ") : "not saved: " + body.error;
  } catch (e) {
    $("saved").textContent = "not saved: the server has stopped";
  }
});

const cloud = $("cloud");
cloud.addEventListener("pointerdown", e => { dragging = [e.clientX, e.clientY]; cloud.setPointerCapture(e.pointerId); });
cloud.addEventListener("pointerup", () => { dragging = null; });
cloud.addEventListener("pointermove", e => {
  if (!dragging) return;
  yaw += (e.clientX - dragging[0]) * 0.01;
  pitch = Math.max(-1.5, Math.min(1.5, pitch + (e.clientY - dragging[1]) * 0.01));
  dragging = [e.clientX, e.clientY];
  drawCloud();
});
drawCloud(); drawCoverage();
poll();
