// trimag review: the page asks the server (GET overview/state/results/download, POST fit) and draws what it answers
// with Plotly; nothing is fitted, corrected or exported here.
"use strict";
const token = document.querySelector('meta[name="trimag-token"]').content;
const $ = (id) => document.getElementById(id);
const config = { displaylogo: false, responsive: true };
let overview = null;
let fitsSeen = 0;

function text(value) {
  const span = document.createElement("span");
  span.textContent = value === null || value === undefined ? "-" : String(value);
  return span.innerHTML;
}

function num(value, digits = 4) {
  return typeof value === "number" ? Number(value.toPrecision(digits)).toString() : "-";
}

async function ask(url, options = {}) {
  const r = await fetch(url, { cache: "no-store", ...options });
  const body = await r.json();
  if (!r.ok) throw new Error(body.error || `HTTP ${r.status}`);
  return body;
}

function downloads(compass) {
  const kinds = overview.target === "px4"
    ? [["qgc", "QGroundControl .params"], ["px4", "param set script"]]
    : [["ardupilot", ".param (Mission Planner, MAVProxy)"]];
  const links = kinds.map(([what, label]) =>
    `<a class="dl" id="dl-${what}-${compass}" href="download?what=${what}&compass=${compass}" download>${label}</a>`);
  if (compass !== "all") {
    links.push(`<a class="dl" id="dl-json-${compass}" href="download?what=json&compass=${compass}" download>calibration JSON</a>`);
  }
  return links.join(" ");
}

function compassTable(results) {
  const byNumber = Object.fromEntries((results || []).map((r) => [r.number, r]));
  const cs = overview.compasses;
  const row = (label, cell) => `<tr><th>${label}</th>${cs.map((c) => `<td>${cell(c, byNumber[c.number])}</td>`).join("")}</tr>`;
  const onboard = (c) => Object.entries(c.onboard || {}).map(([k, v]) => `${text(k)} ${num(v)}`).join("<br>") || "-";
  const stats = (r, key) => (r && r.statistics && r.statistics[key] !== undefined ? num(r.statistics[key]) : "-");
  return "<table>" +
    row("compass", (c) => `<b>${c.number}</b> ${text(c.name)}`) +
    row("device id", (c) => text(c.device_id)) +
    row("samples, rate", (c) => `${c.n_samples} at ${num(c.rate_hz, 3)} Hz over ${num(c.span_s, 4)} s`) +
    row("gaps", (c) => `${c.n_gaps} (longest ${num(c.longest_gap_s, 3)} s)`) +
    row("health", (c) => `|B| ${num(c.health.mean_norm)} ${text(c.unit)} &plusmn; ${num(c.health.std_norm_percent, 3)} %; ` +
        `${c.health.non_finite_rows} bad rows`) +
    row("the log's calibration", onboard) +
    row("verdict", (c, r) => r ? `<span class="verdict ${r.error ? "refused" : ""}">${text(r.verdict)}</span>` : "-") +
    row("level chosen", (c, r) => (r && r.level) || "-") +
    row("vector RMS, fitted rows", (c, r) => `log ${stats(r, "logged_fitted_rms")} &rarr; fit ${stats(r, "candidate_fitted_rms")}`) +
    row("vector RMS, held-out rows", (c, r) => `log ${stats(r, "logged_held_out_rms")} &rarr; fit ${stats(r, "candidate_held_out_rms")}` +
        ` (${r && r.statistics ? r.statistics.held_out_rows || 0 : 0} rows)`) +
    row("download", (c, r) => (r && !r.error ? (typeof r.parameters === "string" ? text(r.parameters)
                                                 : downloads(c.number)) : "-")) +
    "</table>";
}

function levelsTable(levels, stats) {
  if (!levels) return "";
  // each candidate's vector RMS against the expected field (the server's statistics), by its label
  const vector = Object.fromEntries(((stats && stats.levels) || []).map((v) => [v.label, v]));
  const rows = levels.map((l) => {
    const v = vector[l.level + (l.motor ? ` + ${l.motor}` : "")] || {};
    return `<tr${l.chosen ? ' style="font-weight:600"' : ""}><td>${text(l.level)}</td>` +
      `<td>${text(l.motor || "-")}</td><td class="num">${l.n_params}</td><td class="num">${num(l.rms)}</td>` +
      `<td class="num">${num(l.heldout_rms)}</td><td>${l.identified ? "all" : `${l.n_identified} of ${l.n_params}`}</td>` +
      `<td>${l.within_limits ? "ok" : "outside"}</td>` +
      `<td class="num">${num(v.fitted_rms)} / ${num(v.held_out_rms)}</td><td>${l.chosen ? "&larr;" : ""}</td></tr>`;
  }).join("");
  return "<table><tr><th>level</th><th>motor</th><th>params</th><th>rms</th><th>held-out</th><th>identified</th>" +
    `<th>limits</th><th title="against the expected field (IGRF rotated by the attitude): on the fitted rows / on ` +
    `the held-out rows">vs expected</th><th>chosen</th></tr>${rows}</table>`;
}

function checks(r) {
  const out = [];
  if (r.halves) {
    const h = r.halves;
    out.push(`halves check: ${h.checked ? "checked" : "not checked"}` +
      (h.first ? `; first half's fit on the second ${num(h.first.rms_other_half_fit)}, second's on the first ` +
        `${num(h.second.rms_other_half_fit)}` : "") +
      (h.refuse && h.refuse.length ? `; refused: ${text(h.refuse.join(", "))}` : ""));
  }
  if (r.heading) {
    const h = r.heading;
    out.push(`heading check against ${text(h.against)}: RMS ${num(h.rms_before_deg, 3)} deg with the log's ` +
      `calibration &rarr; ${num(h.rms_after_deg, 3)} deg with this fit (${text(h.decision)})`);
  }
  if (r.orientation) {
    out.push(`orientation: ${text(r.orientation.decision)} ${text(r.orientation.value)} (the log's ${text(r.orientation.log_value)})`);
  }
  return out.map((line) => `<div>${line}</div>`).join("");
}

function render(results) {
  $("compasses").innerHTML = compassTable(results.compasses);
  $("downloads-all").innerHTML = results.compasses.some((r) => !r.error && typeof r.parameters === "object")
    ? downloads("all") : "no compass has parameters to write";
  const holder = $("per-compass");
  holder.style.gridTemplateColumns = `repeat(${Math.max(1, results.compasses.length)}, minmax(0, 1fr))`;
  holder.innerHTML = results.compasses.map((r) => `<section id="compass-${r.number}"><h2>compass ${r.number}</h2>` +
    `<div class="verdict ${r.error ? "refused" : ""}">${text(r.verdict)}</div>` +
    (r.attitude ? `<div class="figure-attitude">attitude of the figures (the fit's): ${text(r.attitude)}</div>` : "") +
    `${checks(r)}${levelsTable(r.levels, r.statistics)}` +
    `<h3>the same fit on the command line</h3><pre>${text(r.command)}</pre>` +
    `<h3>what the fit said</h3><pre>${text((r.messages || []).join("\n") || r.error || "")}</pre>` +
    Object.keys(r.figures).map((name) => `<div class="fig" id="fig-${r.number}-${name}"></div>`).join("") +
    "</section>").join("");
  for (const r of results.compasses) {
    for (const [name, fig] of Object.entries(r.figures)) {
      Plotly.newPlot(`fig-${r.number}-${name}`, fig.data, fig.layout, config);
    }
  }
  if (results.flight) Plotly.react("flight", results.flight.data, { ...results.flight.layout }, config);
  if (results.choice) {
    $("start").value = results.choice.start_s.toFixed(1);
    $("stop").value = results.choice.stop_s.toFixed(1);
    $("level").value = results.choice.level;
    $("motor").value = results.choice.motor;
    $("yaw").value = results.choice.yaw_source;
  }
}

async function poll() {
  try {
    const st = await ask("state");
    document.body.dataset.busy = st.busy ? "1" : "0";
    $("progress").textContent = st.busy ? st.progress : "";
    $("fit").disabled = st.busy;
    $("error").textContent = st.error || "";
    if (!st.busy && st.fits > fitsSeen) {
      const results = await ask("results");
      render(results);
      fitsSeen = st.fits;
      document.body.dataset.fits = String(fitsSeen);
    }
  } catch (e) {
    $("progress").textContent = `the server does not answer (${e.message}); is trimag review still running?`;
  }
  setTimeout(poll, 500);
}

async function fit() {
  $("error").textContent = "";
  const body = { start_s: parseFloat($("start").value), stop_s: parseFloat($("stop").value),
                 level: $("level").value, motor: $("motor").value, yaw_source: $("yaw").value };
  try {
    // the session's token, which the server put into this page (no other page can read it): POST needs it
    await ask("fit", { method: "POST", headers: { "X-Trimag-Token": token, "Content-Type": "application/json" },
                       body: JSON.stringify(body) });
    document.body.dataset.busy = "1";
  } catch (e) {
    $("error").textContent = e.message;
  }
}

async function init() {
  for (;;) {  // the server reads the log first: the page says how far it is (GET /overview answers 503 meanwhile)
    const r = await fetch("overview", { cache: "no-store" });
    const body = await r.json().catch(() => ({}));
    if (r.ok) { overview = body; break; }
    if (r.status !== 503) throw new Error(body.error || `HTTP ${r.status}`);
    document.body.dataset.reading = "1";
    $("progress").textContent = body.progress || "reading the log";
    await new Promise((resolve) => setTimeout(resolve, 300));
  }
  document.body.dataset.reading = "0";
  $("log").textContent = `${overview.path}: ${overview.format}${overview.vehicle ? ", " + overview.vehicle : ""}; ` +
    `parameters for ${overview.target}; ${overview.compasses.length} compass(es)`;
  $("level").innerHTML = overview.levels.map((l) => `<option>${text(l)}</option>`).join("");
  $("motor").innerHTML = overview.motors.map((m) => `<option>${text(m)}</option>`).join("");
  const yawLabels = { auto: "auto", attitude: `EKF (${overview.attitude_source})`, gsf: "EKF-GSF yaw (XKY0)",
                      gps: "GPS heading", dcm: `DCM (${(overview.attitude_sources || {}).AHR2 || "AHR2"})` };
  $("yaw").innerHTML = overview.yaw_choices.map((y) => `<option value="${text(y)}">${text(yawLabels[y] || y)}</option>`)
    .join("");
  $("attitude").textContent = `(attitude: ${overview.attitude_source || "none"}` +
    Object.values(overview.attitude_sources || {}).map((s) => `; also ${s}`).join("") +
    (overview.yaw_sources.length ? `; yaw also from ${overview.yaw_sources.join(", ")}` : "") +
    (overview.altitude_source ? `; altitude: ${overview.altitude_source})` : ")");
  $("unavailable").innerHTML = (overview.unavailable || []).map((line) => `<div>${text(line)}</div>`).join("");
  $("start").value = overview.span_s[0].toFixed(1);
  $("stop").value = overview.span_s[1].toFixed(1);
  $("compasses").innerHTML = compassTable([]);
  const flight = $("flight");
  await Plotly.newPlot(flight, overview.flight.data, overview.flight.layout, config);
  flight.on("plotly_relayout", (ev) => {  // a drag across the flight zooms to the range to fit
    const lo = ev["xaxis.range[0]"] ?? (ev["xaxis.range"] || [])[0];
    const hi = ev["xaxis.range[1]"] ?? (ev["xaxis.range"] || [])[1];
    if (ev["xaxis.autorange"]) {
      $("start").value = overview.span_s[0].toFixed(1);
      $("stop").value = overview.span_s[1].toFixed(1);
    } else if (lo !== undefined && hi !== undefined) {
      $("start").value = Math.max(lo, overview.span_s[0]).toFixed(1);
      $("stop").value = Math.min(hi, overview.span_s[1]).toFixed(1);
    }
  });
  $("fit").addEventListener("click", fit);
  document.body.dataset.ready = "1";
  poll();
}

init().catch((e) => { $("log").textContent = `cannot read the review: ${e.message}`; });
