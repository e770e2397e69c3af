// The rangefuse web page: scenes (create from the API's own schema, delete), scans (drag
// and drop), jobs (progress, ETA, cancel), the viewer, downloads and slices. It talks to
// the REST API under /v1 with the token from the form or the URL fragment (docs/webapp.md).
import { Viewer, decodePreview, parsePly } from "./viewer.js";

const $ = id => document.getElementById(id);

// --- the token: from the form or the fragment (/#token=...), which the browser never
// sends to the server (a query string would land in access logs); kept in sessionStorage
// (this tab only) and removed from the address bar.
const params = new URLSearchParams(location.search);
const fragment = new URLSearchParams(location.hash.slice(1));
localStorage.removeItem("rangefuse-token");  // where earlier versions of this page kept it
let token = fragment.get("token") || sessionStorage.getItem("rangefuse-token") || "";
if (fragment.has("token")) sessionStorage.setItem("rangefuse-token", token);
if (fragment.has("token") || params.has("token")) {  // ?token= is not read, only dropped
  fragment.delete("token"); params.delete("token");
  const query = params.toString(), rest = fragment.toString();
  history.replaceState(null, "", location.pathname + (query ? "?" + query : "") + (rest ? "#" + rest : ""));
}

const state = {
  scenes: [], jobs: [], selected: params.get("scene"), scene: null,
  meshEtag: null, placements: [], seen: new Map(), schema: null,
  jobsLoaded: false,  // once the jobs were read: a job new since then started after
};

function setStatus(text, error = false) {
  const s = $("status");
  s.textContent = text;
  s.classList.toggle("error", error);
}

class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

// Every call carries the token; a refusal becomes an ApiError with the service's words.
async function api(path, options = {}) {
  let r;
  try {
    r = await fetch(path, { ...options, headers: { Authorization: "Bearer " + token, ...(options.headers || {}) } });
  } catch (e) {
    throw unreachable(e);
  }
  if (r.status === 401) throw new ApiError(401, "the token was not accepted: paste a valid API token above");
  if (!r.ok && r.status !== 304) {
    const body = await r.json().catch(() => ({}));
    throw new ApiError(r.status, body.detail || `${r.status} ${r.statusText}`);
  }
  return r;
}
const json = async (path, options) => {
  const r = await api(path, options);
  try { return await r.json(); } catch (e) { throw e.name === "TimeoutError" ? unreachable(e) : e; }
};
function unreachable(e) {
  if (e.name === "TimeoutError") return new ApiError(0, `the service did not answer within ${POLL_TIMEOUT_S} s`);
  return new ApiError(0, "cannot reach the service (is rangefuse serve running?)");
}

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) e.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

const fmtSeconds = s => s < 90 ? `${Math.round(s)} s` : s < 5400 ? `${Math.round(s / 60)} min` : `${(s / 3600).toFixed(1)} h`;
const fmtInt = n => Number(n).toLocaleString("en");

// --- the token form ---------------------------------------------------------------------
const tokenInput = $("token");
tokenInput.value = token;
function useToken() {
  token = tokenInput.value.trim();
  sessionStorage.setItem("rangefuse-token", token);
  refresh(); loadSchema();
  if (state.selected) selectScene(state.selected);
}
tokenInput.addEventListener("change", useToken);
$("auth").addEventListener("submit", ev => { ev.preventDefault(); useToken(); });

// --- the scene form, rendered from the API's own schema (/openapi.json) -------------------
function resolve(schema, node) {
  if (node && node.$ref) return schema.components.schemas[node.$ref.split("/").pop()];
  return node;
}
function fieldFor(schema, name, prop, required, prefix) {
  const id = `f-${prefix}${name}`;
  const options = prop.anyOf ? prop.anyOf.filter(a => a.type !== "null") : [prop];
  const main = resolve(schema, options[0]) || {};
  const nullable = !!(prop.anyOf && prop.anyOf.some(a => a.type === "null"));
  const help = el("div", { class: "help" }, prop.description || main.description || "");
  const label = el("label", { for: id }, (prop.title || name) + (required ? " *" : ""));
  if (main.properties) {  // a nested object (the noise model): its own fields
    const inner = Object.entries(main.properties).map(([n, p]) => fieldFor(schema, n, p, false, `${prefix}${name}.`));
    return el("fieldset", { "data-object": prefix + name }, el("legend", {}, prop.title || name), help, ...inner);
  }
  let input;
  const enumValues = main.enum || prop.enum;
  if (enumValues) {
    input = el("select", { id }, ...(nullable ? [el("option", { value: "" }, "(none)")] : []),
      ...enumValues.map(v => el("option", { value: v, selected: v === prop.default }, v)));
  } else if (main.type === "object") {
    input = el("textarea", { id, rows: 3, placeholder: "JSON object (optional)", spellcheck: "false" });
  } else if (main.type === "array") {
    input = el("input", { id, type: "text", placeholder: `${prop.minItems || ""} numbers, comma-separated (optional)` });
  } else if (main.type === "number" || main.type === "integer") {
    input = el("input", { id, type: "number", step: "any", placeholder: required ? "required" : "default" });
    if (prop.default !== undefined && prop.default !== null) input.value = prop.default;
  } else {
    input = el("input", { id, type: "text", placeholder: required ? "required" : "" });
    if (prop.default !== undefined && prop.default !== null) input.value = prop.default;
  }
  input.dataset.field = prefix + name;
  input.dataset.kind = main.type || (enumValues ? "string" : "string");
  if (required) input.required = true;
  return el("div", { class: "field" }, label, input, help);
}

async function loadSchema() {
  if (state.schema || !token) return;
  try {
    const schema = await (await fetch("/openapi.json")).json();
    const scene = schema.components.schemas.SceneIn;
    const required = new Set(scene.required || []);
    $("scene-fields").replaceChildren(...Object.entries(scene.properties)
      .map(([n, p]) => fieldFor(schema, n, p, required.has(n), "")));
    state.schema = schema;
  } catch (e) {
    $("scene-fields").textContent = "could not load the scene's parameters: " + e.message;
  }
}

function formBody() {
  const body = {};
  for (const input of $("scene-fields").querySelectorAll("[data-field]")) {
    const raw = input.value.trim();
    if (raw === "") continue;
    let value;
    const kind = input.dataset.kind;
    const label = input.dataset.field;
    if (kind === "number" || kind === "integer") value = Number(raw);
    else if (kind === "array") {
      value = raw.split(/[\s,]+/).filter(Boolean).map(Number);
      if (value.some(Number.isNaN)) throw new Error(`${label}: give numbers separated by commas`);
    } else if (kind === "object") {
      try { value = JSON.parse(raw); } catch (e) { throw new Error(`${label}: not valid JSON (${e.message})`); }
    } else value = raw;
    const path = label.split(".");
    let target = body;
    for (const key of path.slice(0, -1)) target = target[key] ??= {};
    target[path.at(-1)] = value;
  }
  return body;
}

$("new-scene").addEventListener("click", () => { $("scene-form").hidden = false; loadSchema(); });
$("cancel-scene").addEventListener("click", () => { $("scene-form").hidden = true; });
$("scene-form").addEventListener("submit", async ev => {
  ev.preventDefault();
  try {
    const scene = await json("/v1/scenes", {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(formBody()),
    });
    $("scene-form").hidden = true;
    setStatus(`created scene “${scene.name}”: now add scans`);
    await refresh();
    selectScene(scene.id);
  } catch (e) { setStatus("the scene was not created: " + e.message, true); }
});

// --- scenes -------------------------------------------------------------------------------
function renderScenes() {
  const box = $("scenes");
  if (!state.scenes.length) { box.replaceChildren("no scenes yet: create one"); return; }
  box.replaceChildren(...state.scenes.map(s => el("div", {
    class: "scene" + (s.id === state.selected ? " selected" : ""), "data-scene": s.id,
    onclick: () => selectScene(s.id),
  }, el("b", {}, s.name), el("div", { class: "muted" }, `${s.mode}, ${s.voxel_size * 1000} mm voxels`))));
}

async function selectScene(id) {
  const changed = id !== state.selected;
  state.selected = id;
  const url = new URL(location.href);
  url.searchParams.set("scene", id);
  history.replaceState(null, "", url.pathname + url.search + url.hash);
  renderScenes();
  $("scene-panel").hidden = false;
  if (changed) { state.meshEtag = null; viewer.clear(); }
  const up = localStorage.getItem(`rangefuse-up-${id}`) || "z";
  $("up-axis").value = up;
  viewer.root.rotation.set(0, 0, 0);
  await loadScene();
  viewer.setUp(up);
  await loadMesh(true);
  if (!$("slice-panel").hidden) { updateSliceRange(); loadSlice(); }
}

async function loadScene() {
  if (!state.selected) return;
  try {
    const s = await json(`/v1/scenes/${state.selected}`);
    state.scene = s;
    $("scene-title").textContent = s.name;
    $("scene-info").textContent = `${s.mode} mode, ${s.voxel_size * 1000} mm voxels, ${s.scans} scans, ${fmtInt(s.tiles)} tiles`;
    $("scene-info").dataset.scans = s.scans;
    state.placements = await json(`/v1/scenes/${state.selected}/placements`);
    viewer.setPoses(state.placements, $("show-scans").checked);
    if (!viewer.mesh) viewer.fit();
    updateSliceRange();
  } catch (e) {
    if (e.status === 404) { state.selected = null; $("scene-panel").hidden = true; }
    setStatus(e.message, true);
  }
}

// The latest reconstruction: the preview (at most 300 k faces), or the full mesh.
async function loadMesh(fit = false) {
  if (!state.selected) return;
  const full = $("full-res").checked;
  const path = full ? `/v1/scenes/${state.selected}/mesh?format=ply` : `/v1/scenes/${state.selected}/preview`;
  try {
    setStatus(full ? "loading the full mesh…" : "loading the mesh…");
    const r = await api(path);
    const etag = r.headers.get("ETag") || "";
    const data = full ? parsePly(await r.arrayBuffer()) : decodePreview(await r.arrayBuffer());
    if (!full) state.preview = data;
    else if (!state.preview || state.previewEtag !== etag.replace("-ply", "-preview")) {
      // the preview's levels, drawn while the camera moves over the full mesh
      state.preview = decodePreview(await (await api(`/v1/scenes/${state.selected}/preview`)).arrayBuffer());
    }
    state.previewEtag = full ? etag.replace("-ply", "-preview") : etag;
    state.meshEtag = etag;
    const firstMesh = !viewer.mesh;
    const coarse = full ? (state.preview.coarse || state.preview) : data.coarse;
    viewer.setMesh(data, { keepView: true, coarse });
    viewer.setPoses(state.placements, $("show-scans").checked);
    if (fit || firstMesh) viewer.setUp($("up-axis").value);  // and fits the view
    const inferred = data.nFaces - data.nMeasured;
    const what = full ? `full mesh, ${fmtInt(data.nFaces)} faces`
      : data.nFaces < data.sourceFaces ? `preview of ${fmtInt(data.nFaces)} faces (the mesh has ${fmtInt(data.sourceFaces)})`
      : `${fmtInt(data.nFaces)} faces`;
    const moving = coarse ? ` (${fmtInt(coarse.nFaces)} while moving)` : "";
    setStatus(`${state.scene ? state.scene.name : "scene"}: ${what}${moving}, ${fmtInt(inferred)} inferred. Drag to orbit, right-drag to pan, wheel to zoom.`);
    $("status").dataset.faces = data.nFaces;
    $("status").dataset.full = full ? "1" : "0";
    $("status").dataset.coarseFaces = coarse ? coarse.nFaces : data.nFaces;
    $("status").dataset.sourceFaces = data.sourceFaces;
    $("status").dataset.inferred = inferred;
    renderDownloads(true);
  } catch (e) {
    if (e.status === 409 && /no reconstruction/.test(e.message)) {
      viewer.clear();
      renderDownloads(false);
      setStatus(state.scene && state.scene.scans
        ? "No reconstruction yet: press Reconstruct to mesh the scans."
        : "No scans yet: drop scans on the panel at the left, then press Reconstruct.");
    } else setStatus(e.message, true);
  }
}

// --- uploads: drag and drop or the file input -------------------------------------------
const drop = $("drop");
for (const ev of ["dragenter", "dragover"]) drop.addEventListener(ev, e => { e.preventDefault(); drop.classList.add("over"); });
for (const ev of ["dragleave", "drop"]) drop.addEventListener(ev, e => { e.preventDefault(); drop.classList.remove("over"); });
drop.addEventListener("drop", e => uploadFiles([...e.dataTransfer.files]));
$("files").addEventListener("change", e => { uploadFiles([...e.target.files]); e.target.value = ""; });

const stem = name => name.replace(/\.[^.]*$/, "");

async function uploadFiles(files) {
  const sceneId = state.selected;
  if (!sceneId) { setStatus("select or create a scene first", true); return; }
  const jsons = new Map();
  for (const f of files.filter(f => f.name.toLowerCase().endsWith(".json"))) {
    try { jsons.set(stem(f.name), JSON.parse(await f.text())); }
    catch (e) { setStatus(`${f.name}: not valid JSON (${e.message})`, true); return; }
  }
  let shared = {};
  const typed = $("upload-meta").value.trim();
  if (typed) {
    try { shared = JSON.parse(typed); } catch (e) { setStatus(`the metadata box is not valid JSON (${e.message})`, true); return; }
  }
  const sensor = jsons.get("sensor");  // a dataset's sensor.json, dropped with its scans
  const scans = files.filter(f => !f.name.toLowerCase().endsWith(".json"));
  if (!scans.length) { setStatus("no scan files among those dropped (.npz, .npy, .png, .tif)", true); return; }
  const box = $("uploads");
  let ok = 0;
  for (const [i, f] of scans.entries()) {
    const row = el("div", { class: "upload" }, `${f.name}: uploading (${i + 1} of ${scans.length})…`);
    box.prepend(row);
    const meta = { ...shared, ...(sensor && !shared.sensor ? { sensor } : {}), ...(jsons.get(stem(f.name)) || {}) };
    if (!meta.name) meta.name = f.name;
    const form = new FormData();
    form.append("range", f, f.name);
    form.append("meta", JSON.stringify(meta));
    try {
      const r = await json(`/v1/scenes/${sceneId}/scans`, { method: "POST", body: form });
      row.textContent = `${f.name}: stored, fusing in job ${r.job.id}` + (r.scan.far_ranges ? ` (${fmtInt(r.scan.far_ranges)} ranges beyond the sensor's reach ignored)` : "");
      row.dataset.state = "stored";
      ok++;
    } catch (e) {
      const hint = /^meta\.(pose|sensor|depth_scale)/.test(e.message) && !f.name.endsWith(".npz")
        ? ` (drop ${stem(f.name)}.json beside it, or fill in the metadata box)` : "";
      row.textContent = `${f.name}: refused: ${e.message}${hint}`;
      row.classList.add("error");
      row.dataset.state = "refused";
    }
  }
  while (box.children.length > 30) box.lastChild.remove();
  setStatus(`${ok} of ${scans.length} scans stored` + (ok ? ": they are being fused; press Reconstruct to mesh them" : ""), ok < scans.length);
  refresh(); loadScene();
}

// --- scene actions ------------------------------------------------------------------------
$("reconstruct").addEventListener("click", async () => {
  try {
    const r = await json(`/v1/scenes/${state.selected}/reconstructions`, {
      method: "POST", headers: { "Content-Type": "application/json" }, body: "{}",
    });
    setStatus(`reconstruction queued (job ${r.job.id}); the view updates when it is done`);
    refresh();
  } catch (e) { setStatus("cannot reconstruct: " + e.message, true); }
});

const del = $("delete-scene");
del.addEventListener("click", async () => {
  if (!del.classList.contains("armed")) {  // a second click confirms
    del.classList.add("armed"); del.textContent = "Click again to delete";
    setTimeout(() => { del.classList.remove("armed"); del.textContent = "Delete scene"; }, 4000);
    return;
  }
  del.classList.remove("armed"); del.textContent = "Delete scene";
  try {
    const name = state.scene ? state.scene.name : state.selected;
    await api(`/v1/scenes/${state.selected}`, { method: "DELETE" });
    state.selected = null; state.scene = null; viewer.clear(); viewer.setPoses([], false);
    $("scene-panel").hidden = true;
    $("slice-panel").hidden = true; $("slice-img").removeAttribute("src"); viewer.resize();
    setStatus(`deleted scene “${name}”`);
    refresh();
  } catch (e) { setStatus("the scene was not deleted: " + e.message, true); }
});

function renderDownloads(available) {
  const box = $("downloads");
  if (!available) { box.replaceChildren(el("span", { class: "muted" }, "after the first reconstruction")); return; }
  box.replaceChildren(...["ply", "obj", "glb", "stl"].map(fmt => el("button", {
    type: "button", class: "secondary", "data-format": fmt, onclick: () => download(fmt),
  }, fmt.toUpperCase())));
}

async function download(fmt) {
  try {
    setStatus(`preparing the ${fmt.toUpperCase()}…`);
    const r = await api(`/v1/scenes/${state.selected}/mesh?format=${fmt}`);
    const disposition = r.headers.get("Content-Disposition") || "";
    const name = (/filename="?([^";]+)"?/.exec(disposition) || [])[1] || `${state.selected}.${fmt}`;
    const url = URL.createObjectURL(await r.blob());
    const a = el("a", { href: url, download: name });
    document.body.append(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60000);
    setStatus(`downloaded ${name}`);
  } catch (e) { setStatus(`the ${fmt.toUpperCase()} could not be made: ` + e.message, true); }
}

// --- jobs: progress, ETA, cancel; the page follows them ----------------------------------
const FINISHED = new Set(["done", "failed", "cancelled"]);

function eta(job, now) {
  const seen = state.seen.get(job.id);
  if (!seen || job.state !== "running") return "";
  const elapsed = now - seen.t0;
  if (job.progress > seen.p0 && elapsed > 0.5) {
    const left = elapsed * (1 - job.progress) / (job.progress - seen.p0);
    return `about ${fmtSeconds(left)} left`;
  }
  return `running for ${fmtSeconds(now - job.created_at)}`;
}

function describeJob(j) {
  const scene = state.scenes.find(s => s.id === j.scene_id);
  const where = scene ? `“${scene.name}”` : "a deleted scene";
  const what = { integrate: "fusing scans", reconstruct: "reconstructing", remove: "removing a scan", delete: "deleting the scene" }[j.kind] || j.kind;
  return `${what} of ${where}`;
}

function renderJobs() {
  const now = Date.now() / 1000;
  const box = $("jobs");
  if (!state.jobs.length) { box.replaceChildren("no jobs yet"); return; }
  box.replaceChildren(...state.jobs.slice(0, 20).map(j => {
    const running = !FINISHED.has(j.state);
    const detail = j.state === "failed" ? `failed: ${j.error || "no reason given"}`
      : j.state === "done" ? `done in ${fmtSeconds((j.finished_at || now) - j.created_at)}` + (j.kind === "reconstruct" && j.result ? `, ${fmtInt(j.result.faces)} faces` : "")
      : j.state === "cancelled" ? "cancelled: nothing it did was kept"
      : j.state === "queued" ? "waiting for a worker"
      : j.state === "cancelling" ? "stopping…" : `${Math.round(j.progress * 100)} %, ${eta(j, now)}`
        + (j.message ? ` (${j.message})` : "");  // e.g. "compiling kernels, first run only"
    return el("div", { class: `job ${j.state}`, "data-job": j.id, "data-state": j.state },
      el("div", { class: "head" }, el("span", {}, describeJob(j)),
        running && j.kind !== "delete" && j.state !== "cancelling"
          ? el("button", { type: "button", class: "small", onclick: () => cancel(j.id) }, "cancel") : null),
      el("div", { class: j.state === "failed" ? "failed" : "muted" }, detail),
      running || j.state === "done" ? el("div", { class: "bar" }, el("div", { style: `width:${Math.round((j.state === "done" ? 1 : j.progress) * 100)}%` })) : null);
  }));
}

async function cancel(id) {
  try { await api(`/v1/jobs/${id}/cancel`, { method: "POST" }); setStatus("the job is being cancelled"); refresh(); }
  catch (e) { setStatus("cannot cancel: " + e.message, true); }
}

// One refresh at a time. Asked mid-refresh, it runs once more after the current one, and
// the caller waits for that one: its scene list was read after the call (a scene just
// created is in it, so selecting it next is not undone by the older list, which lacks it).
// Each poll's reads give up after POLL_TIMEOUT_S: a request that never answers (a stalled
// proxy, a dropped connection) would otherwise hold every later refresh behind it.
const POLL_TIMEOUT_S = 10;
let refreshing = null, refreshAgain = null, pollFailed = null;  // the last poll's failure
function refresh() {
  if (!token) return Promise.resolve();
  if (refreshing) {
    refreshAgain = refreshAgain || refreshing.then(() => { refreshAgain = null; return refresh(); });
    return refreshAgain;
  }
  refreshing = refreshOnce().finally(() => { refreshing = null; });
  return refreshing;
}

async function refreshOnce() {
  try {
    state.scenes = await json("/v1/scenes", { signal: AbortSignal.timeout(POLL_TIMEOUT_S * 1000) });
    renderScenes();
    const jobs = await json("/v1/jobs?limit=30", { signal: AbortSignal.timeout(POLL_TIMEOUT_S * 1000) });
    if (pollFailed) { setStatus(`the service answers again (last error: ${pollFailed})`); pollFailed = null; }
    const now = Date.now() / 1000;
    let sceneChanged = false, meshChanged = false;
    for (const j of jobs) {
      const before = state.jobs.find(x => x.id === j.id);
      if (j.state === "running" && !state.seen.has(j.id)) state.seen.set(j.id, { t0: now, p0: j.progress });
      // ended since the last poll; a job not listed then that has ended already was queued
      // and done between two polls (a reconstruction of a small scene takes a second)
      const ended = FINISHED.has(j.state) && (before ? !FINISHED.has(before.state) : state.jobsLoaded);
      if (ended && j.scene_id === state.selected) {
        sceneChanged = true;
        if (j.kind === "reconstruct" && j.state === "done") meshChanged = true;
        if (j.state === "failed") setStatus(`${describeJob(j)} failed: ${j.error}`, true);
        if (j.state === "cancelled") setStatus(`${describeJob(j)}: cancelled`);
      }
    }
    state.jobs = jobs;
    state.jobsLoaded = true;
    renderJobs();
    if (state.selected && !state.scenes.some(s => s.id === state.selected)) {
      state.selected = null; $("scene-panel").hidden = true; viewer.clear();
    }
    if (sceneChanged) await loadScene();
    if (meshChanged) await loadMesh(!viewer.mesh);
  } catch (e) {
    if (e.status === 0) pollFailed = e.message;
    setStatus(e.message, true);
  }
}

// --- the viewer's controls ----------------------------------------------------------------
const viewer = new Viewer($("viewer"));
window.rangefuseViewer = viewer;  // for tests and benchmarks/viewer_fps.py
$("up-axis").addEventListener("change", e => {
  if (state.selected) localStorage.setItem(`rangefuse-up-${state.selected}`, e.target.value);
  viewer.setUp(e.target.value);
});
$("inferred-mode").addEventListener("change", e => viewer.setInferred(e.target.value));
$("show-scans").addEventListener("change", e => viewer.showPoses(e.target.checked));
$("full-res").addEventListener("change", () => loadMesh(false));
$("reset-view").addEventListener("click", () => viewer.fit());

// --- slices: axis, position, a legend of the log-odds ------------------------------------
$("toggle-slice").addEventListener("click", () => {
  $("slice-panel").hidden = !$("slice-panel").hidden;
  viewer.resize();
  if (!$("slice-panel").hidden) { drawLegend(); updateSliceRange(); loadSlice(); }
});

// The extent along the slice axis: the scene's bounds, else the mesh's, else the scans'.
function updateSliceRange() {
  const axis = "xyz".indexOf($("slice-axis").value);
  let lo = -1, hi = 1;
  const b = state.scene && state.scene.bounds;
  if (b) { lo = b[axis]; hi = b[axis + 3]; }
  else if (viewer.mesh) {
    viewer.mesh.geometry.computeBoundingBox();
    const bb = viewer.mesh.geometry.boundingBox;
    lo = bb.min.getComponent(axis); hi = bb.max.getComponent(axis);
  } else if (state.placements.length) {
    const xs = state.placements.map(p => p.pose[axis][3]);
    lo = Math.min(...xs) - 1; hi = Math.max(...xs) + 1;
  }
  const input = $("slice-at");
  const voxel = state.scene ? state.scene.voxel_size : 0.01;
  input.min = lo; input.max = hi; input.step = voxel;
  if (+input.value < lo || +input.value > hi) input.value = (lo + hi) / 2;
  $("slice-at-value").textContent = `${(+input.value).toFixed(3)} m`;
}

let sliceTimer = null, sliceUrl = null;
async function loadSlice() {
  if (!state.selected || $("slice-panel").hidden) return;
  const axis = $("slice-axis").value, at = +$("slice-at").value;
  $("slice-at-value").textContent = `${at.toFixed(3)} m`;
  try {
    const blob = await (await api(`/v1/scenes/${state.selected}/slice?axis=${axis}&at=${at}`)).blob();
    if (sliceUrl) URL.revokeObjectURL(sliceUrl);
    sliceUrl = URL.createObjectURL(blob);
    const img = $("slice-img");
    img.src = sliceUrl;
    img.dataset.axis = axis; img.dataset.at = at;
    const [h, v] = "xyz".replace(axis, "");  // service/api/routes/slices.py: rows flipped
    $("slice-axes").textContent = `the tiles crossing ${axis} = ${at.toFixed(3)} m: ${h} to the right, ${v} up`;
  } catch (e) { setStatus("no slice: " + e.message, true); }
}
$("slice-axis").addEventListener("change", () => { updateSliceRange(); loadSlice(); });
$("slice-at").addEventListener("input", () => {
  $("slice-at-value").textContent = `${(+$("slice-at").value).toFixed(3)} m`;
  clearTimeout(sliceTimer); sliceTimer = setTimeout(loadSlice, 120);
});

// The slice's colours (service/api/routes/slices.py): free blue, occupied red, both darker
// toward log-odds 0 and saturated at |L| = 10; unknown grey.
function drawLegend() {
  const c = $("slice-legend"), g = c.getContext("2d");
  for (let x = 0; x < c.width; x++) {
    const L = -10 + 20 * x / (c.width - 1);
    const s = Math.min(Math.abs(L) / 10, 1), k = 0.4 + 0.6 * s;
    const [r, gg, b] = L < 0 ? [60, 120, 255] : [230, 40, 40];
    g.fillStyle = `rgb(${Math.floor(r * k)},${Math.floor(gg * k)},${Math.floor(b * k)})`;
    g.fillRect(x, 0, 1, c.height);
  }
}

// --- start --------------------------------------------------------------------------------
if (!token) setStatus("paste the API token that rangefuse serve printed (or open /#token=…)");
loadSchema();
refresh().then(() => { if (state.selected) selectScene(state.selected); });
setInterval(refresh, 1000);
