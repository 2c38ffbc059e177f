// Tissue Twin dashboard: plain JS over the REST API (see /docs). No build step.
"use strict";

const $ = (sel) => document.querySelector(sel);
let jobTypes = [];
let sessions = [];
let selectedJob = null;

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
async function loadJobs() {
  const jobs = await api("GET", "/api/jobs?limit=50");
  const body = $("#jobs-table tbody");
  body.innerHTML = jobs.map((j) => {
    const active = j.status === "queued" || j.status === "running";
    const actions = [
      active ? `<button class="cancel-btn" data-id="${j.id}">cancel</button>` : "",
      j.type === "replay" && j.status === "done" ? `<button class="view-btn" data-id="${j.id}">view</button>` : "",
    ].join(" ");
    return `<tr data-job-id="${j.id}" data-status="${j.status}">
      <td><a href="#" class="job-link" data-id="${j.id}">${j.id}</a></td><td>${j.type}</td><td>${j.session_id ?? ""}</td>
      <td class="status status-${j.status}">${j.status}${j.cancel_requested && active ? " (cancelling)" : ""}</td>
      <td><progress max="1" value="${j.progress}"></progress> ${(100 * j.progress).toFixed(0)}%</td>
      <td class="muted">${esc(j.error || j.message)}</td><td>${actions}</td></tr>`;
  }).join("");
  body.querySelectorAll(".cancel-btn").forEach((b) => b.onclick = () => api("POST", `/api/jobs/${b.dataset.id}/cancel`).then(loadJobs).catch((e) => alert(e.message)));
  body.querySelectorAll(".view-btn").forEach((b) => b.onclick = () => showInViewer(+b.dataset.id));
  body.querySelectorAll(".job-link").forEach((a) => a.onclick = (ev) => { ev.preventDefault(); showResult(+a.dataset.id); });
  if (selectedJob !== null) {
    const j = jobs.find((x) => x.id === selectedJob);
    if (j && j.status !== $("#result-body").dataset.status) showResult(selectedJob);
  }
}

// ---------------------------------------------------------------- results and plots
async function showResult(id) {
  selectedJob = id;
  const j = await api("GET", `/api/jobs/${id}`);
  const arts = await api("GET", `/api/jobs/${id}/artifacts`);
  $("#result-title").textContent = `job ${j.id}: ${j.type}, ${j.status}`;
  const out = [];
  const r = j.result || {};
  if (j.type === "sweep" && j.status === "done") {
    out.push(`<img class="plot" id="sweep-plot" src="/api/jobs/${id}/artifacts/sweep.png?t=${Date.now()}" alt="error against E">`);
    out.push(`<table id="sweep-table"><thead><tr><th>E (Pa)</th><th>mean error (mm)</th></tr></thead><tbody>` +
      r.table.map((row) => `<tr class="${row.youngs_modulus === r.best ? "best" : ""}"><td class="num">${row.youngs_modulus.toPrecision(3)}</td><td class="num">${row.mean_error === null ? "N/A (diverged)" : mm(row.mean_error)}</td></tr>`).join("") +
      `</tbody></table><p class="muted">cf. Wu et al. 2020, Tables 1-2; best E ${r.best}</p>`);
  } else if (j.type === "fit" && j.status === "done") {
    const y = r.youngs_modulus || {};
    out.push(`<p><b>Young's modulus</b>: ${y.identifiable ? `${Number(y.value).toPrecision(4)} Pa (95 % interval ${y.interval.map((v) => Number(v).toPrecision(3)).join(" - ")} Pa)` : "not identifiable: " + esc(y.reason)}</p>`);
    out.push(`<p>errors (mm): ${Object.entries(r.errors || {}).map(([k, v]) => `${k} ${mm(v)}`).join(", ")}</p>`);
  } else if (j.type === "replay" && j.status === "done") {
    out.push(`<table id="replay-table"><thead><tr><th>sequence</th><th>role</th><th>frames</th><th>status</th><th>mean error (mm)</th></tr></thead><tbody>` +
      Object.entries(r.sequences || {}).map(([n, s]) => `<tr><td>${n}</td><td>${s.role}</td><td class="num">${s.frames}</td><td>${s.status}</td><td class="num">${mm(s.mean_error)}</td></tr>`).join("") +
      `</tbody></table><p class="muted">noise floor ${mm(r.noise_floor)} mm; camera ICP rms ${mm((r.calibration || {}).camera_rms)} mm</p>
      <button class="view-btn" onclick="showInViewer(${id})">show in 3D viewer</button>`);
  } else if (j.type === "generate" && j.status === "done") {
    out.push(`<p>new session ${r.session_id}: ${esc(r.session)}</p>`);
  }
  for (const png of arts.filter((a) => a.path.endsWith(".png") && a.path !== "sweep.png")) {
    out.push(`<img class="plot" src="/api/jobs/${id}/artifacts/${png.path}" alt="${esc(png.path)}">`);
  }
  if (j.error) out.push(`<p class="error">${esc(j.error)}</p>`);
  if (j.traceback) out.push(`<details><summary>traceback</summary><pre>${esc(j.traceback)}</pre></details>`);
  out.push(`<details><summary>log</summary><pre id="job-log">${esc(j.log)}</pre></details>`);
  out.push(`<details><summary>artifacts (${arts.length})</summary><ul>` +
    arts.slice(0, 200).map((a) => `<li><a href="/api/jobs/${id}/artifacts/${a.path}">${esc(a.path)}</a> <span class="muted">${a.size} B</span></li>`).join("") + `</ul></details>`);
  $("#result-body").innerHTML = out.join("");
  $("#result-body").dataset.status = j.status;
  $("#result-body").className = "";
}

// ---------------------------------------------------------------- viewer
let viewerPort = null;
async function setupViewer() {
  const cfg = await api("GET", "/api/config");
  $("#cluster").textContent = `jobs on ${cfg.scheduler}`;
  viewerPort = cfg.viewer_port;
  if (!viewerPort) { $("#viewer-status").textContent = "viewer disabled"; return; }
  $("#viewer-frame").src = `${location.protocol}//${location.hostname}:${viewerPort}/`;
}

async function showInViewer(id) {
  try {
    const st = await api("POST", "/api/viewer/show", { job_id: id });
    $("#viewer-status").textContent = `run ${st.run_id}, ${st.sequence}: ${st.n_frames} frames (loaded in ${st.first_frame_seconds.toFixed(2)} s)`;
    $("#viewer").scrollIntoView();
  } catch (e) { $("#viewer-status").textContent = e.message; }
}

async function startIcp(sessionId) {
  try {
    await api("POST", "/api/viewer/icp", { session_id: sessionId });
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
  setInterval(() => loadJobs().catch(() => {}), 1000);
  document.body.dataset.ready = "1";
}
init().catch((e) => { document.body.insertAdjacentHTML("afterbegin", `<p class="error">${esc(e.message)}</p>`); });
