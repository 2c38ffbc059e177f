// Tissue Twin dashboard: plain JS over the REST API (see /docs). No build step.
"use strict";

const $ = (sel) => document.querySelector(sel);
let jobTypes = [];
let sessions = [];
let selectedJob = null;
// Follow mode: until the user picks a job, the results panel shows the latest finished job,
// so analyses (the demo's sweep, fit, diagnosis, training) fill in as they finish.
let followLatest = !/^#job-\d+$/.test(location.hash);
const FINAL = new Set(["done", "failed", "cancelled", "interrupted"]);

async function api(method, url, body, isForm) {
  const opts = { method, headers: {} };
  if (body !== undefined) {
    if (isForm) { opts.body = body; } else { opts.body = JSON.stringify(body); opts.headers["Content-Type"] = "application/json"; }
  }
  const r = await fetch(url, opts);
  const text = await r.text();
  const data = text ? JSON.parse(text) : null;
  if (!r.ok) {
    let d = data && data.detail !== undefined ? data.detail : text;
    if (Array.isArray(d)) d = d.map((e) => `${(e.loc || []).join(".")}: ${e.msg}`).join("\n");
    throw new Error(`${r.status}: ${d}`);
  }
  return data;
}

function esc(s) { return String(s ?? "").replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c])); }
function say(el, text, isError) { el.textContent = text; el.className = "message" + (isError ? " error" : ""); }
function mm(m) { return m === null || m === undefined ? "N/A" : (m * 1e3).toFixed(4); }

// The replayed mesh in words, from a job's summary or the viewer's state: an STL phantom's
// Gmsh mesh ({kind: "stl", nodes, tets[, element_size]}) or a box's node grid ({kind: "box",
// grid, ...}, or a bare `grid` of an older summary); "" when neither is known.
function meshText(mesh, grid) {
  const m = mesh || {};
  if (m.kind === "stl") {
    const h = Number(m.element_size) > 0 ? `, element size ${(m.element_size * 1e3).toFixed(2)} mm` : "";
    return `STL phantom: Gmsh mesh, ${m.nodes ?? "?"} nodes, ${m.tets ?? "?"} tetrahedra${h}`;
  }
  const g = Array.isArray(m.grid) ? m.grid : grid;
  if (!Array.isArray(g) || g.length !== 3) return "";
  const [a, b, c] = g.map(Number);
  return `box: ${g.join("x")} node grid, ${m.nodes ?? a * b * c} nodes, ${m.tets ?? 6 * (a - 1) * (b - 1) * (c - 1)} tetrahedra`;
}

// ---------------------------------------------------------------- sessions
async function loadSessions() {
  sessions = await api("GET", "/api/sessions");
  const body = $("#sessions-table tbody");
  body.innerHTML = sessions.map((s) => `<tr data-session-id="${s.id}"><td>${s.id}</td><td>${esc(s.name)}</td><td>${s.source}</td>
    <td class="muted">${esc(s.path)}</td><td><button class="icp-btn" data-id="${s.id}">ICP init</button></td></tr>`).join("");
  body.querySelectorAll(".icp-btn").forEach((b) => b.onclick = () => startIcp(+b.dataset.id));
  document.querySelectorAll("select.session-select").forEach(fillSessionSelect);
}

function fillSessionSelect(sel) {
  const cur = sel.value;
  sel.innerHTML = sessions.map((s) => `<option value="${s.id}">${s.id}: ${esc(s.name)}</option>`).join("");
  if (cur && sessions.some((s) => String(s.id) === cur)) sel.value = cur;
  else if (sessions.length) sel.value = String(sessions[sessions.length - 1].id);
}

$("#register-form").onsubmit = async (ev) => {
  ev.preventDefault();
  try {
    const s = await api("POST", "/api/sessions", { path: $("#session-path").value.trim() });
    say($("#session-message"), `registered session ${s.id} (${s.name})`);
    await loadSessions();
  } catch (e) { say($("#session-message"), e.message, true); }
};

$("#upload-form").onsubmit = async (ev) => {
  ev.preventDefault();
  const fd = new FormData();
  fd.append("file", $("#upload-file").files[0]);
  if ($("#upload-name").value) fd.append("name", $("#upload-name").value);
  say($("#session-message"), "uploading ...");
  try {
    const s = await api("POST", "/api/sessions/upload", fd, true);
    say($("#session-message"), `uploaded session ${s.id} (${s.name})`);
    await loadSessions();
  } catch (e) { say($("#session-message"), e.message, true); }
};

// ---------------------------------------------------------------- launcher (forms from JSON schema)
function fieldSchema(p) {
  // Optional[X] is anyOf [X, null]
  if (p.anyOf) { const s = p.anyOf.find((a) => a.type !== "null"); return { ...s, optional: true, title: p.title, description: p.description, default: p.default }; }
  return p;
}

function renderForm() {
  const t = jobTypes.find((x) => x.name === $("#job-type").value);
  if (!t) return;
  $("#job-title").textContent = t.title;
  const props = t.params_schema.properties || {};
  const html = Object.entries(props).map(([name, raw]) => {
    const p = fieldSchema(raw);
    const label = `<label for="f-${name}">${esc(p.title || name)}</label>`;
    const hint = p.description ? `<small>${esc(p.description)}</small>` : "";
    let input;
    if (name === "session_id") {
      input = `<select id="f-${name}" name="${name}" class="session-select" data-kind="int"></select>`;
    } else if (p.enum) {
      input = `<select id="f-${name}" name="${name}" data-kind="str">${p.enum.map((v) => `<option ${v === p.default ? "selected" : ""}>${esc(v)}</option>`).join("")}</select>`;
    } else if (p.type === "boolean") {
      input = `<input id="f-${name}" name="${name}" type="checkbox" data-kind="bool" ${p.default ? "checked" : ""}>`;
    } else if (p.type === "integer" || p.type === "number") {
      input = `<input id="f-${name}" name="${name}" data-kind="${p.type === "integer" ? "int" : "num"}" value="${p.default ?? ""}" ${p.optional ? 'placeholder="(default)"' : ""}>`;
    } else if (p.type === "array" && p.items && (p.items.type === "number" || p.items.type === "integer" || p.items.type === "string")) {
      const def = Array.isArray(p.default) ? p.default.join(", ") : "";
      input = `<input id="f-${name}" name="${name}" data-kind="list-${p.items.type}" value="${esc(def)}" placeholder="comma-separated${p.optional ? " (optional)" : ""}">`;
    } else if (p.type === "string") {
      input = `<input id="f-${name}" name="${name}" data-kind="str" value="${esc(p.default ?? "")}">`;
    } else {
      input = `<input id="f-${name}" name="${name}" data-kind="json" value="${esc(JSON.stringify(p.default ?? []))}" size="40">`;
    }
    return `<div class="field">${label}${input}${hint}</div>`;
  }).join("");
  $("#job-fields").innerHTML = html;
  document.querySelectorAll("select.session-select").forEach(fillSessionSelect);
}

function readForm() {
  const params = {};
  document.querySelectorAll("#job-fields [name]").forEach((el) => {
    const kind = el.dataset.kind; const v = el.value.trim();
    if (kind === "bool") { params[el.name] = el.checked; return; }
    if (v === "") return;  // omitted: the server's default
    if (kind === "int") params[el.name] = parseInt(v, 10);
    else if (kind === "num") params[el.name] = Number(v);
    else if (kind.startsWith("list-")) {
      const items = v.split(",").map((s) => s.trim()).filter((s) => s);
      params[el.name] = kind === "list-string" ? items : items.map(Number);
    } else if (kind === "json") params[el.name] = JSON.parse(v);
    else params[el.name] = v;
  });
  return params;
}

$("#job-type").onchange = renderForm;
$("#job-form").onsubmit = async (ev) => {
  ev.preventDefault();
  try {
    const job = await api("POST", "/api/jobs", { type: $("#job-type").value, params: readForm() });
    say($("#launch-message"), `job ${job.id} queued`);
    await loadJobs();
  } catch (e) { say($("#launch-message"), e.message, true); }
};

// ---------------------------------------------------------------- jobs
// Downloads of a finished replay's or diagnosis's calibrated twin (GET /api/jobs/{id}/export, a zip each).
const EXPORT_TYPES = new Set(["replay", "diagnose"]);
const EXPORT_FORMATS = [["vtu", "VTU", "VTK meshes for ParaView"], ["sofa", "SOFA", "a SOFA Python3 scene"], ["mjcf", "MJCF", "a MuJoCo model"]];
function exportLinks(j) {
  if (j.status !== "done" || !EXPORT_TYPES.has(j.type)) return "";
  return `<span class="export-links">` + EXPORT_FORMATS.map(([f, label, what]) =>
    `<a class="export-link" data-format="${f}" href="/api/jobs/${j.id}/export?format=${f}" download="job-${j.id}-${f}.zip" title="download the calibrated twin as ${what} (zip)">${label}</a>`).join(" ") + `</span>`;
}

async function loadJobs() {
  const jobs = await api("GET", "/api/jobs?limit=50");
  const body = $("#jobs-table tbody");
  body.innerHTML = jobs.map((j) => {
    const active = j.status === "queued" || j.status === "running";
    const actions = [
      active ? `<button class="cancel-btn" data-id="${j.id}">cancel</button>` : "",
      j.status === "done" && (j.result || {}).viewer ? `<button class="view-btn" data-id="${j.id}">view</button>` : "",
      j.status === "done" && (j.result || {}).plan_view ? `<button class="plan-btn" data-id="${j.id}">view</button>` : "",
      exportLinks(j),
    ].join(" ");
    return `<tr data-job-id="${j.id}" data-status="${j.status}">
      <td><a href="#" class="job-link" data-id="${j.id}">${j.id}</a></td><td>${j.type}</td><td>${j.session_id ?? ""}</td>
      <td class="status status-${j.status}">${j.status}${j.cancel_requested && active ? " (cancelling)" : ""}</td>
      <td><progress max="1" value="${j.progress}"></progress> ${(100 * j.progress).toFixed(0)}%</td>
      <td class="muted">${esc(j.error || j.message)}</td><td>${actions}</td></tr>`;
  }).join("");
  body.querySelectorAll(".cancel-btn").forEach((b) => b.onclick = () => api("POST", `/api/jobs/${b.dataset.id}/cancel`).then(loadJobs).catch((e) => alert(e.message)));
  body.querySelectorAll(".view-btn").forEach((b) => b.onclick = () => showInViewer(+b.dataset.id));
  body.querySelectorAll(".plan-btn").forEach((b) => b.onclick = () => showPlanInViewer(+b.dataset.id));
  body.querySelectorAll(".job-link").forEach((a) => a.onclick = (ev) => { ev.preventDefault(); setFollow(false); showResult(+a.dataset.id); });
  if (followLatest) {
    const latest = jobs.filter((j) => FINAL.has(j.status) && j.finished_at)
      .sort((a, b) => (a.finished_at < b.finished_at ? 1 : a.finished_at > b.finished_at ? -1 : b.id - a.id))[0];
    if (latest && (latest.id !== selectedJob || latest.status !== $("#result-body").dataset.status)) { await showResult(latest.id); return; }
  }
  if (selectedJob !== null) {
    const j = jobs.find((x) => x.id === selectedJob);
    if (j && j.status !== $("#result-body").dataset.status) showResult(selectedJob);
  }
}

// ---------------------------------------------------------------- results and plots
function setFollow(on) {
  followLatest = on;
  $("#follow-latest").checked = on;
  if (on) loadJobs().catch(() => {});
}
$("#follow-latest").onchange = () => setFollow($("#follow-latest").checked);

async function showResult(id) {
  selectedJob = id;
  const j = await api("GET", `/api/jobs/${id}`);
  const arts = await api("GET", `/api/jobs/${id}/artifacts`);
  $("#result-title").textContent = `job ${j.id}: ${j.type}, ${j.status}`;
  $("#results").dataset.jobId = String(j.id);
  const out = [];
  const r = j.result || {};
  if (j.type === "sweep" && j.status === "done") {
    // the verdict decides whether the lowest row is an estimate: no bold "best" for a flat sweep
    const v = r.youngs_modulus;
    const marked = v && v.identifiable ? r.best : null;
    out.push(`<img class="plot" id="sweep-plot" src="/api/jobs/${id}/artifacts/sweep.png?t=${Date.now()}" alt="error against E">`);
    out.push(v ? youngsVerdict(v) : `<p class="youngs-verdict" data-identifiable="unknown">no verdict on E (a sweep from an older release); lowest mean error at E ${esc(r.best)} Pa</p>`);
    out.push(`<table id="sweep-table"><thead><tr><th>E (Pa)</th><th>mean error (mm)</th></tr></thead><tbody>` +
      r.table.map((row) => `<tr class="${marked !== null && row.youngs_modulus === marked ? "best" : ""}"><td class="num">${row.youngs_modulus.toPrecision(3)}</td><td class="num">${row.mean_error === null ? "N/A (diverged)" : mm(row.mean_error)}</td></tr>`).join("") +
      `</tbody></table><p class="muted">cf. Wu et al. 2020, Tables 1-2</p>`);
  } else if (j.type === "fit" && j.status === "done") {
    out.push(youngsVerdict(r.youngs_modulus));
    out.push(`<p>errors (mm): ${Object.entries(r.errors || {}).map(([k, v]) => `${k} ${mm(v)}`).join(", ")}</p>`);
  } else if (j.type === "replay" && j.status === "done") {
    out.push(`<table id="replay-table"><thead><tr><th>sequence</th><th>role</th><th>frames</th><th>status</th><th>mean error (mm)</th></tr></thead><tbody>` +
      Object.entries(r.sequences || {}).map(([n, s]) => `<tr><td>${n}</td><td>${s.role}</td><td class="num">${s.frames}</td><td>${s.status}</td><td class="num">${mm(s.mean_error)}</td></tr>`).join("") +
      `</tbody></table><p class="muted" id="replay-mesh" data-kind="${esc((r.mesh || {}).kind || (r.grid ? "box" : ""))}">${esc(meshText(r.mesh, r.grid))}</p>
      <p class="muted">noise floor ${mm(r.noise_floor)} mm; camera ICP rms ${mm((r.calibration || {}).camera_rms)} mm</p>
      <button class="view-btn" onclick="showInViewer(${id})">show in 3D viewer</button>`);
  } else if (j.type === "train" && j.status === "done") {
    out.push(lossPlot(r.losses || [], r.best_epoch, r.baseline_loss || {}));
    const te = r.test_error || {};
    out.push(`<table id="train-table"><thead><tr><th>${esc((r.model || "").toUpperCase())} network, E ${Number(r.youngs_modulus).toPrecision(3)} Pa</th><th>test error (mm)</th><th>improvement</th></tr></thead><tbody>
      <tr><td>no network</td><td class="num">${mm(te.no_network)}</td><td></td></tr>
      <tr><td>corrected in the loop</td><td class="num">${mm(te.corrected)}</td><td class="num">${pct(r.improvement)}</td></tr>
      <tr><td>corrected offline</td><td class="num">${mm(te.corrected_offline)}</td><td class="num">${pct(r.improvement_offline)}</td></tr>
      </tbody></table><p class="muted">best epoch ${r.best_epoch} of ${(r.losses || []).length}${r.stopped_early ? " (stopped early)" : ""}; cf. Wu et al. 2020, Table 3${r.mesh ? `; ${esc(meshText(r.mesh))}` : ""}</p>`);
    if (r.viewer) out.push(`<button class="view-btn" onclick="showInViewer(${id})">show the corrected mesh in 3D (${Object.entries(r.corrected_shown || {}).map(([n, m]) => `${esc(n)}: ${m.replace("_", "-")}`).join(", ")})</button>`);
  } else if (j.type === "evaluate" && j.status === "done") {
    out.push(evaluationTable(r));
    for (const [run, rep] of Object.entries(r.runs || {})) out.push(`<h4>${esc(run)}</h4>` + lossPlot(rep.losses || [], rep.best_epoch, rep.baseline_loss || {}));
  } else if (j.type === "diagnose" && j.status === "done") {
    out.push(diagnosisSummary(r, id));
    if (r.viewer) out.push(`<button class="view-btn" onclick="showInViewer(${id})">show the diagnosis in 3D</button> <span class="muted">(the viewer's Diagnosis tab: residuals, ${(r.extended || {}).kinds && r.extended.kinds.length ? "each cause's change and geometry, " : ""}the answer per kind, the largest-error frames)</span>`);
  } else if (j.type === "plan" && j.status === "done") {
    out.push(planSummary(r, id));
  } else if (j.type === "generate" && j.status === "done") {
    out.push(`<p>new session ${r.session_id}: ${esc(r.session)}</p>`);
  }
  const shown = new Set(["sweep.png", ...(j.type === "diagnose" ? DIAGNOSIS_FIGURES.map((f) => f[0]) : [])]);
  for (const png of arts.filter((a) => a.path.endsWith(".png") && !shown.has(a.path))) {
    out.push(`<img class="plot" src="/api/jobs/${id}/artifacts/${png.path}" alt="${esc(png.path)}">`);
  }
  if (exportLinks(j)) out.push(`<p id="export-links">export the calibrated twin (zip): ${exportLinks(j)}</p>`);
  if (j.error) out.push(`<p class="error">${esc(j.error)}</p>`);
  if (j.traceback) out.push(`<details><summary>traceback</summary><pre>${esc(j.traceback)}</pre></details>`);
  out.push(`<details><summary>log</summary><pre id="job-log">${esc(j.log)}</pre></details>`);
  out.push(`<details><summary>artifacts (${arts.length})</summary><ul>` +
    arts.slice(0, 200).map((a) => `<li><a href="/api/jobs/${id}/artifacts/${a.path}">${esc(a.path)}</a> <span class="muted">${a.size} B</span></li>`).join("") + `</ul></details>`);
  $("#result-body").innerHTML = out.join("");
  $("#result-body").dataset.status = j.status;
  $("#result-body").className = "";
}

// ---------------------------------------------------------------- plots: training losses, Table 3, diagnosis
function pct(v) { return v === null || v === undefined ? "N/A" : (v * 100).toFixed(1) + " %"; }

// ---------------------------------------------------------------- Young's modulus: one verdict everywhere
// The sweep, fit and diagnosis panels all state E through this function, from the same
// {identifiable, value, interval, reason} verdict (core.identification.verdict): an
// identifiable E with its 95 % interval in bold, otherwise "not identifiable" with the reason
// and never a value in bold.
function paUnit(v) {
  const a = Math.abs(v);
  return a >= 1e6 ? [1e6, "MPa"] : a >= 1e3 ? [1e3, "kPa"] : [1, "Pa"];
}
function youngsVerdict(v) {
  if (typeof v === "number") v = { value: v, identifiable: null };  // old diagnoses: a bare value
  v = v || {};
  const tip = v.statistic ? ` title="${esc(JSON.stringify(v.statistic))}"` : "";
  if (v.identifiable === true && v.value !== null && v.value !== undefined) {
    const [s, unit] = paUnit(v.value);
    const f = (x) => (Number(x) / s).toPrecision(3);
    const iv = Array.isArray(v.interval) && v.interval.length === 2 ? ` (95 % ${f(v.interval[0])}-${f(v.interval[1])} ${unit})` : "";
    return `<p class="youngs-verdict" data-identifiable="true"${tip}><b>E = ${f(v.value)} ${unit}</b>${iv}` +
      (v.reason ? ` <span class="muted">${esc(v.reason)}</span>` : "") + `</p>`;
  }
  if (v.identifiable === false) {
    if (v.reason === "not fitted") return `<p class="youngs-verdict" data-identifiable="false">E not fitted</p>`;
    return `<p class="youngs-verdict" data-identifiable="false"${tip}>E not identifiable from these data: ${esc(v.reason || "no reason given")}</p>`;
  }
  if (v.value !== null && v.value !== undefined) {
    const [s, unit] = paUnit(v.value);
    return `<p class="youngs-verdict" data-identifiable="unknown">E = ${(Number(v.value) / s).toPrecision(3)} ${unit} (no identifiability verdict)</p>`;
  }
  return `<p class="youngs-verdict" data-identifiable="unknown">E: no verdict</p>`;
}

// Train and validation loss (mm) per epoch as an SVG line plot; dashed: the loss without correction.
function lossPlot(losses, bestEpoch, baseline) {
  if (!losses.length) return `<p class="muted">no epochs recorded</p>`;
  const W = 520, H = 260, L = 64, R = 120, T = 14, B = 40;
  const series = [["train_loss", "train", "#1f5fbf"], ["validation_loss", "validation", "#d95f02"]];
  const vals = [];
  for (const e of losses) for (const [k] of series) if (Number.isFinite(e[k])) vals.push(e[k] * 1e3);
  for (const v of Object.values(baseline)) if (Number.isFinite(v)) vals.push(v * 1e3);
  let lo = Math.min(...vals), hi = Math.max(...vals);
  if (!(hi > lo)) { lo -= 0.001; hi += 0.001; }
  const pad = 0.06 * (hi - lo); lo -= pad; hi += pad;
  const n = losses.length, e0 = losses[0].epoch, e1 = losses[n - 1].epoch;
  const x = (ep) => L + (e1 > e0 ? (ep - e0) / (e1 - e0) : 0.5) * (W - L - R);
  const y = (v) => T + (1 - (v - lo) / (hi - lo)) * (H - T - B);
  const parts = [`<svg class="loss-plot" data-epochs="${n}" viewBox="0 0 ${W} ${H}" width="${W}" height="${H}" role="img" aria-label="training loss curves">`,
    `<rect x="${L}" y="${T}" width="${W - L - R}" height="${H - T - B}" fill="none" stroke="#ccd"/>`];
  for (let i = 0; i <= 4; i++) {
    const v = lo + (hi - lo) * i / 4;
    parts.push(`<line x1="${L - 4}" x2="${L}" y1="${y(v)}" y2="${y(v)}" stroke="#888"/><text x="${L - 6}" y="${y(v) + 4}" text-anchor="end" font-size="11">${v.toFixed(4)}</text>`);
  }
  const step = Math.max(1, Math.ceil((e1 - e0) / 8));
  for (let ep = e0; ep <= e1; ep += step) parts.push(`<text x="${x(ep)}" y="${H - B + 16}" text-anchor="middle" font-size="11">${ep}</text>`);
  parts.push(`<text x="${(L + W - R) / 2}" y="${H - 6}" text-anchor="middle" font-size="12">epoch</text>`,
    `<text x="14" y="${(T + H - B) / 2}" transform="rotate(-90 14 ${(T + H - B) / 2})" text-anchor="middle" font-size="12">Chamfer loss (mm)</text>`);
  series.forEach(([k, label, colour], i) => {
    const pts = losses.filter((e) => Number.isFinite(e[k])).map((e) => `${x(e.epoch).toFixed(1)},${y(e[k] * 1e3).toFixed(1)}`);
    parts.push(`<polyline class="loss-${label}" points="${pts.join(" ")}" fill="none" stroke="${colour}" stroke-width="2"/>`);
    for (const p of pts) { const [px, py] = p.split(","); parts.push(`<circle cx="${px}" cy="${py}" r="2.5" fill="${colour}"/>`); }
    const base = baseline[label];
    if (Number.isFinite(base)) parts.push(`<line x1="${L}" x2="${W - R}" y1="${y(base * 1e3)}" y2="${y(base * 1e3)}" stroke="${colour}" stroke-dasharray="4 3"/>`);
    parts.push(`<line x1="${W - R + 8}" x2="${W - R + 26}" y1="${T + 10 + 18 * i}" y2="${T + 10 + 18 * i}" stroke="${colour}" stroke-width="2"/><text x="${W - R + 30}" y="${T + 14 + 18 * i}" font-size="11">${label}</text>`);
  });
  parts.push(`<text x="${W - R + 8}" y="${T + 52}" font-size="10" fill="#666">dashed: no network</text>`);
  if (bestEpoch) parts.push(`<line class="best-epoch" x1="${x(bestEpoch)}" x2="${x(bestEpoch)}" y1="${T}" y2="${H - B}" stroke="#17803d" stroke-dasharray="2 2"/><text x="${x(bestEpoch) - 3}" y="${T + 12}" text-anchor="end" font-size="10" fill="#17803d">best</text>`);
  parts.push("</svg>");
  return parts.join("");
}

function evaluationTable(r) {
  const kinds = ["2d", "3d"].filter((k) => (r.rows || []).some((row) => k in row));
  const head = `<tr><th>E (Pa)</th><th>sequence</th><th>no network</th>${kinds.map((k) => `<th>${k.toUpperCase()}</th><th>improvement</th><th>${k.toUpperCase()} offline</th><th>improvement</th>`).join("")}</tr>`;
  const rows = (r.rows || []).map((row) => `<tr class="${row.sequence === "all test" ? "best" : ""}"><td>${Number(row.youngs_modulus).toPrecision(3)} (${esc(row.label)})</td><td>${esc(row.sequence)}</td><td class="num">${mm(row.no_network)}</td>` +
    kinds.map((k) => `<td class="num">${mm(row[k])}</td><td class="num">${pct(row[k + "_improvement"])}</td><td class="num">${mm(row[k + "_offline"])}</td><td class="num">${pct(row[k + "_offline_improvement"])}</td>`).join("") + "</tr>").join("");
  const fails = Object.entries(r.failures || {}).map(([k, v]) => `<li>${esc(k)}: ${esc(v)}</li>`).join("");
  return `<table id="evaluation-table"><thead>${head}</thead><tbody>${rows}</tbody></table>
    <p class="muted">mean distance (mm) from the measured test points to the 3x super-sampled mesh (Wu et al. 2020, Table 3); identified E by ${esc((r.identification || {}).method)}</p>` +
    (fails ? `<p>N/A:</p><ul>${fails}</ul>` : "");
}

const DIAGNOSIS_FIGURES = [
  ["residual_maps.png", "where the base model's signed top-face residual is systematic"],
  ["residual_when_where.png", "when (phases of the probing) and where (distance from the probe)"],
  ["evidence.png", "evidence per candidate effect (validation chi-square drop)"],
];

function planSummary(r, id) {
  // the planner's description, what it would show, the path in 3D and its kinematics.csv
  const rows = Object.entries(r.predicted_min_size || {}).map(([k, v]) => {
    const now = (r.current_min_size || {})[k];
    return `<tr><td>${esc(k)}</td><td>${now == null ? "cannot tell" : Number(now).toPrecision(3)}</td><td>${v == null ? "cannot tell" : Number(v).toPrecision(3)}</td></tr>`;
  }).join("");
  const targets = Object.entries(r.targets || {}).map(([k, why]) => `${esc(k)} (${esc(why)})`).join("; ") || "a general protocol";
  return `<p id="plan-summary">Plan for ${targets}: ${Number(r.duration_s).toFixed(1)} s of probing${r.record_force ? ", <b>record the probe force</b>" : ""}.</p>
    <ol id="plan-description">${(r.description || []).map((l) => `<li>${esc(l)}</li>`).join("")}</ol>
    <table id="plan-table"><thead><tr><th>kind</th><th>smallest size now</th><th>with this plan</th></tr></thead><tbody>${rows}</tbody></table>
    <p><button class="plan-btn" onclick="showPlanInViewer(${id})">show the plan in 3D</button>
    <a id="plan-kinematics" href="/api/jobs/${id}/artifacts/kinematics.csv" download="plan-${id}-kinematics.csv">download kinematics.csv</a>
    <span class="muted">(robot frame, the session's format; <code>tissuetwin generate --plan</code> records it in the virtual lab)</span></p>`;
}

function diagnosisSummary(r, id) {
  const causes = r.causes || [];
  const ext = r.extended || {};
  const fmt = (v) => (typeof v === "number" ? Number(v).toPrecision(3) : Array.isArray(v) ? `[${v.map(fmt).join(", ")}]` : esc(JSON.stringify(v)));
  const params = (p) => Object.entries(p || {}).map(([k, v]) => `${esc(k)} = ${fmt(v)}`).join(", ");
  const ym = r.youngs_modulus || {};
  // the E the base model ran at (when E is not identifiable: the replay's choice, not an estimate)
  const E = typeof ym === "number" ? ym : (ym.value ?? ym.replay_grid_value_used);
  const yesNo = (v) => (v && typeof v === "object" ? Object.entries(v).map(([k, b]) => `${esc(k)}: ${b ? "yes" : "no"}`).join(", ") : v ? "yes" : "no");
  const out = [youngsVerdict(ym),
    `<p>base model at E = ${E === null || E === undefined ? "?" : `${Number(E).toPrecision(4)} Pa`}: test error ${mm((r.baseline || {}).test_error)} mm</p>`];
  if (!causes.length) out.push(`<p id="diagnosis-verdict"><b>No effect found</b>: nothing explains the residual beyond the noise.</p>`);
  else {
    out.push(`<table id="causes-table"><thead><tr><th>cause</th><th>parameters</th><th>test error (mm)</th><th>gain</th><th>confidence</th><th>identifiable</th><th>delta chi2</th></tr></thead><tbody>` +
      causes.map((c) => `<tr><td>${esc(c.kind)}</td><td>${params(c.parameters)}</td><td class="num">${mm(c.test_error)}</td><td class="num">${pct(c.gain)}</td>
        <td class="num">${c.confidence === null || c.confidence === undefined ? "" : Number(c.confidence).toFixed(2)}</td><td>${yesNo(c.identifiable)}</td>
        <td class="num">${c.evidence && Number.isFinite(c.evidence.delta_chi2) ? Number(c.evidence.delta_chi2).toPrecision(3) : ""}</td></tr>`).join("") + "</tbody></table>");
    out.push(`<p id="diagnosis-verdict">extended model (${(ext.kinds || []).map(esc).join(" + ")}): test error ${mm(ext.test_error)} mm, gain ${pct(ext.gain)}` +
      (ext.gain_interval && ext.gain_interval.length === 2 ? ` (${pct(ext.gain_interval[0])} to ${pct(ext.gain_interval[1])})` : "") + "</p>");
  }
  if ((r.confounded || []).length) out.push(`<p>confounded: ${esc(JSON.stringify(r.confounded))}</p>`);
  const un = r.unexplained || {};
  out.push(`<p class="muted">unexplained: ${mm(un.test_error)} mm, noise floor ${mm(un.noise_floor)} mm</p>`);
  for (const [png, caption] of DIAGNOSIS_FIGURES) {
    out.push(`<figure><img class="plot diagnosis-figure" src="/api/jobs/${id}/artifacts/${png}" alt="${esc(png)}"><figcaption class="muted">${esc(caption)}</figcaption></figure>`);
  }
  return out.join("");
}

// ---------------------------------------------------------------- viewer
let viewerPort = null;
// this dashboard tab's token: its viewer iframe connects on /tab/<token>, and the view and
// ICP buttons name it, so they act on this tab's viewer only (kept across reloads of the tab)
const viewerTab = sessionStorage.getItem("tt-viewer-tab") || (() => {
  const t = Array.from({ length: 16 }, () => Math.floor(Math.random() * 36).toString(36)).join("");
  sessionStorage.setItem("tt-viewer-tab", t);
  return t;
})();
async function setupViewer() {
  const cfg = await api("GET", "/api/config");
  $("#cluster").textContent = `jobs on ${cfg.scheduler}`;
  viewerPort = cfg.viewer_port;
  if (!viewerPort) { $("#viewer-status").textContent = "viewer disabled"; return; }
  const ws = `${location.protocol === "https:" ? "wss" : "ws"}://${location.hostname}:${viewerPort}/tab/${viewerTab}`;
  $("#viewer-frame").src = `${location.protocol}//${location.hostname}:${viewerPort}/?websocket=${encodeURIComponent(ws)}`;
}

async function showInViewer(id) {
  try {
    const st = await api("POST", "/api/viewer/show", { job_id: id, tab: viewerTab });
    const mesh = meshText(st.mesh);
    $("#viewer-status").textContent = `run ${st.run_id}, ${st.sequence}: ${st.n_frames} frames${mesh ? `, ${mesh}` : ""}, layers ${(st.layers || []).join(", ")} (loaded in ${st.first_frame_seconds.toFixed(2)} s)`;
    $("#viewer").scrollIntoView();
  } catch (e) { $("#viewer-status").textContent = e.message; }
}

async function showPlanInViewer(id) {
  try {
    const st = await api("POST", "/api/viewer/plan", { job_id: id, tab: viewerTab });
    $("#viewer-status").textContent = `plan of job ${id} over the phantom (mode ${st.mode}): open the viewer's "Plan" tab for its description`;
    $("#viewer").scrollIntoView();
  } catch (e) { $("#viewer-status").textContent = e.message; }
}

async function startIcp(sessionId) {
  try {
    await api("POST", "/api/viewer/icp", { session_id: sessionId, tab: viewerTab });
    $("#viewer-status").textContent = `ICP initialisation on session ${sessionId}: open the "ICP init" tab in the viewer`;
    $("#viewer").scrollIntoView();
  } catch (e) { $("#viewer-status").textContent = e.message; }
}

// ---------------------------------------------------------------- start
async function init() {
  jobTypes = await api("GET", "/api/job-types");
  $("#job-type").innerHTML = jobTypes.map((t) => `<option value="${t.name}">${t.name}</option>`).join("");
  await loadSessions();
  renderForm();
  await loadJobs();
  await setupViewer();
  const linked = /^#job-(\d+)$/.exec(location.hash);  // e.g. the demo's link to its replay job
  $("#follow-latest").checked = followLatest;
  if (linked) await showResult(+linked[1]).catch((e) => say($("#launch-message"), e.message, true));
  setInterval(() => loadJobs().catch(() => {}), 1000);
  document.body.dataset.ready = "1";
}
init().catch((e) => { document.body.insertAdjacentHTML("afterbegin", `<p class="error">${esc(e.message)}</p>`); });
