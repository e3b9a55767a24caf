// photonfarm viewer: submit a bundled or uploaded scene with any job setting, follow jobs and
// workers, watch the image refine with an exposure control and a per-pixel readout.
// Plain JavaScript against the JSON API; everything is polled once a second. Images and
// downloads are fetched as blobs so that a bearer token can go with them.
"use strict";

const $ = (id) => document.getElementById(id);
const FINISHED = ["completed", "converged", "cancelled", "failed"];
const ARCHIVE = /\.(zip|tar\.gz|tgz|tar)$/i;
const SCENE_FILE = /\.(json|xml)$/i;
const state = {
  selected: null, job: null, shownPasses: -1, shownMap: null, bitmap: null,
  offset: 0, total: 0, settingFields: [], pointer: null, pixelBusy: false,
};

$("token").value = localStorage.getItem("photonfarm-token") || "";
$("token").addEventListener("change", () => localStorage.setItem("photonfarm-token", $("token").value));

async function api(path, options = {}) {
  const headers = { ...(options.headers || {}) };
  if ($("token").value) headers.Authorization = `Bearer ${$("token").value}`;
  const resp = await fetch(path, { ...options, headers });
  if (!resp.ok) {
    let detail = resp.statusText;
    try {
      const body = await resp.json();
      detail = Array.isArray(body.detail)
        ? body.detail.map((d) => `${d.loc.filter((p) => p !== "body").join(".")}: ${d.msg}`).join("; ")
        : body.detail;
    } catch (e) { /* not JSON */ }
    const error = new Error(`HTTP ${resp.status}: ${detail}`);
    error.status = resp.status;
    throw error;
  }
  return resp;
}

const escape = (text) => String(text).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]);

async function loadScenes() {
  const scenes = await (await api("/v1/scenes")).json();
  $("scene").innerHTML = scenes
    .map((s) => `<option value="${escape(s.name)}" title="${escape(s.description)}">${escape(s.name)}</option>`)
    .join("");
}

// ---------------------------------------------------------------- settings form
// One input per field of the API's JobSettings schema (GET /openapi.json): the list, the
// defaults, the bounds and the help all come from the service, so the form has every setting.
function settingField(name, prop, required) {
  const nullable = (prop.anyOf || []).some((p) => p.type === "null");
  const spec = (prop.anyOf || []).find((p) => p.type !== "null") || prop;
  const id = `set-${name}`;
  const help = escape(prop.description || "");
  const label = name.replace(/_/g, " ");
  let input;
  if (spec.enum) {
    input = `<select id="${id}">${spec.enum.map((v) => `<option${v === prop.default ? " selected" : ""}>${escape(v)}</option>`).join("")}</select>`;
  } else if (spec.type === "boolean") {
    input = `<input id="${id}" type="checkbox"${prop.default ? " checked" : ""}>`;
  } else if (spec.type === "integer" || spec.type === "number") {
    const bounds = ["minimum", "maximum"].filter((k) => spec[k] !== undefined && Math.abs(spec[k]) < 1e15)
      .map((k) => ` ${k.slice(0, 3)}="${spec[k]}"`).join("");
    const step = spec.type === "integer" ? "1" : "any";
    input = `<input id="${id}" type="number" step="${step}"${bounds} value="${prop.default ?? ""}" placeholder="${nullable ? "none" : ""}">`;
  } else if (spec.type === "array") {
    input = `<input id="${id}" placeholder="WxH (scene's own)" pattern="\\s*\\d+\\s*[xX]\\s*\\d+\\s*">`;
  } else {
    input = `<input id="${id}" value="${escape(prop.default ?? "")}">`;
  }
  return { name, nullable, spec, required, html: `<label title="${help}">${label} ${input}</label>` };
}

async function loadSettingsForm() {
  const schema = (await (await fetch("/openapi.json")).json()).components.schemas.JobSettings;
  state.settingFields = Object.entries(schema.properties)
    .map(([name, prop]) => settingField(name, prop, (schema.required || []).includes(name)));
  $("settings").innerHTML = state.settingFields.map((f) => f.html).join("");
  for (const [name, prop] of Object.entries(schema.properties)) showDefaultBy(name, prop["x-default-by"]);
}

// A field whose default depends on another (alpha on the method, worker/settings.py): its
// placeholder shows the default the chosen value of the other field gives.
function showDefaultBy(name, by) {
  if (!by) return;
  for (const [other, defaults] of Object.entries(by)) {
    const show = () => { $(`set-${name}`).placeholder = `${defaults[$(`set-${other}`).value] ?? "none"} (${other} default)`; };
    $(`set-${other}`).addEventListener("change", show);
    show();
  }
}

function readSettings() {
  const settings = {};
  for (const field of state.settingFields) {
    const input = $(`set-${field.name}`);
    if (field.spec.type === "boolean") { settings[field.name] = input.checked; continue; }
    const text = input.value.trim();
    if (text === "") {
      if (!field.nullable) settings[field.name] = null;  // the service names the field in its 422
      continue;
    }
    if (field.spec.type === "array") settings[field.name] = text.toLowerCase().split("x").map((v) => Number(v.trim()));
    else if (field.spec.type === "integer" || field.spec.type === "number") settings[field.name] = Number(text);
    else settings[field.name] = text;
  }
  return settings;
}

// ---------------------------------------------------------------- submit (bundled or upload)
function uploadedFiles() {
  const files = [...$("upload-files").files, ...$("upload-folder").files];
  return files.map((file) => ({ file, name: file.webkitRelativePath || file.name }));
}

// Choosing files (or a folder) replaces the other choice and picks the upload; the scene
// file is filled in when the choice holds exactly one.
function chooseUpload(other) {
  $(other).value = "";
  const scenes = uploadedFiles().filter((f) => SCENE_FILE.test(f.name));
  document.querySelector("input[name=source][value=upload]").checked = true;
  $("upload-scene").value = scenes.length === 1 ? scenes[0].name : "";
}
$("upload-files").addEventListener("change", () => chooseUpload("upload-folder"));
$("upload-folder").addEventListener("change", () => chooseUpload("upload-files"));

// The same request as the API's POST /v1/jobs/upload: an archive, or files named by their paths.
function uploadBody(settings) {
  const files = uploadedFiles();
  if (files.length === 0) throw new Error("upload: choose an archive, the scene's files or its folder");
  const body = new FormData();
  body.append("scene", $("upload-scene").value.trim());
  body.append("settings", JSON.stringify(settings));
  if (files.length === 1 && ARCHIVE.test(files[0].name)) body.append("archive", files[0].file, files[0].name);
  else files.forEach((f) => body.append("files", f.file, f.name));
  return body;
}

$("submit-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  $("submit-error").textContent = "";
  try {
    const settings = readSettings();
    const upload = document.querySelector("input[name=source]:checked").value === "upload";
    const request = upload
      ? api("/v1/jobs/upload", { method: "POST", body: uploadBody(settings) })
      : api("/v1/jobs", {
        method: "POST", headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ scene_name: $("scene").value, settings }),
      });
    const job = await (await request).json();
    state.offset = 0;
    select(job.id);
    await refresh();
  } catch (e) {
    $("submit-error").textContent = e.message;
  }
});

// ---------------------------------------------------------------- job list (paged)
function progress(job) {
  const budget = job.settings;
  const est = job.error_estimate;
  if (FINISHED.includes(job.status)) return 1;
  if (budget.error_threshold && est && est.error) return Math.min(1, budget.error_threshold / est.error);
  if (budget.max_passes) return job.passes / budget.max_passes;
  return Math.min(1, job.elapsed_seconds / (budget.max_seconds || 1));
}

function renderJobs(jobs) {
  $("jobs").querySelector("tbody").innerHTML = jobs.map((j) => `
    <tr data-id="${j.id}" class="${j.id === state.selected ? "selected" : ""}">
      <td>${j.id.slice(0, 8)}</td><td>${escape(j.scene_name || "uploaded")}</td><td class="st">${j.status}</td>
      <td>${j.passes}</td><td>${(j.photons_per_second / 1e6).toFixed(2)}</td>
      <td>${j.error_estimate && j.error_estimate.error !== null ? j.error_estimate.error.toFixed(4) : "-"}</td>
      <td><div class="bar"><span style="width:${(100 * progress(j)).toFixed(0)}%"></span></div></td>
    </tr>`).join("");
  const limit = pageSize();
  const last = Math.min(state.offset + jobs.length, state.total);
  $("jobs-range").textContent = state.total ? `${state.offset + 1}-${last} of ${state.total}` : "none yet";
  $("prev").disabled = state.offset === 0;
  $("next").disabled = state.offset + limit >= state.total;
}

const pageSize = () => Number($("page-size").value);

async function loadJobs() {
  let resp = await api(`/v1/jobs?offset=${state.offset}&limit=${pageSize()}`);
  state.total = Number(resp.headers.get("X-Total-Count") || 0);
  if (state.offset > 0 && state.offset >= state.total) {  // the last page emptied (deletes): step back
    state.offset = Math.max(0, Math.floor((state.total - 1) / pageSize()) * pageSize());
    resp = await api(`/v1/jobs?offset=${state.offset}&limit=${pageSize()}`);
  }
  renderJobs(await resp.json());
}

$("prev").addEventListener("click", () => { state.offset = Math.max(0, state.offset - pageSize()); refresh(); });
$("next").addEventListener("click", () => { state.offset += pageSize(); refresh(); });
$("page-size").addEventListener("change", () => { state.offset = 0; refresh(); });
$("jobs").addEventListener("click", (event) => {
  const row = event.target.closest("tr[data-id]");
  if (row) { select(row.dataset.id); refresh(); }
});

// ---------------------------------------------------------------- workers
function ago(seconds) {
  if (seconds < 60) return `${seconds.toFixed(1)} s ago`;
  if (seconds < 3600) return `${(seconds / 60).toFixed(1)} min ago`;
  return `${(seconds / 3600).toFixed(1)} h ago`;
}

// A worker's heartbeat keeps the job and batch it rendered last: greyed while it is not busy.
const lastWork = (w) => (w.state === "busy" ? "" : ` title="its last job and batch (the worker is ${escape(w.state)})"`);

async function loadWorkers() {
  const workers = await (await api("/v1/workers")).json();
  $("workers").querySelector("tbody").innerHTML = workers.map((w) => `
    <tr class="${w.alive ? "" : "gone"}" data-name="${escape(w.name)}">
      <td class="host">${escape(w.hostname)}</td><td>${w.pid}</td><td class="state">${escape(w.state)}${w.alive ? "" : " (gone)"}</td>
      <td class="beat">${ago(w.last_seen_seconds_ago)}</td>
      <td class="job"${lastWork(w)}>${w.job ? w.job.slice(0, 8) : "-"}</td><td class="batch"${lastWork(w)}>${escape(w.batch || "-")}</td>
    </tr>`).join("");
  $("workers-count").textContent = `${workers.filter((w) => w.alive).length} alive`;
}

// ---------------------------------------------------------------- the selected job
function select(id) {
  state.selected = id;
  state.shownPasses = -1;
  state.bitmap = null;
  state.job = null;
  $("job-id").textContent = id ? id.slice(0, 8) : "-";
  $("status").textContent = "";
  for (const button of ["cancel", "delete", "download-png", "download-exr"]) $(button).disabled = true;
  $("placeholder").hidden = Boolean(id);
  $("job-panel").hidden = !id;
  $("image").hidden = true;
  for (const key of ["passes", "view", "exposure"]) delete $("image").dataset[key];
  $("no-image").hidden = false;
  $("pixel-readout").textContent = "Point at the image for a pixel's linear RGB and its error.";
}

// Seconds left, as `eta_seconds` of service/client.py: from the error's slope when the job has
// a threshold (a least-squares line through log error against log seconds over the later half
// of its history), else from its budget.
function etaSeconds(job) {
  const settings = job.settings;
  const threshold = settings.error_threshold;
  const history = (job.error_history || []).filter((h) => h.error && h.seconds > 0);
  if (threshold && history.length >= 3) {
    const recent = history.slice(Math.floor(history.length / 2));
    const t = recent.map((h) => Math.log(h.seconds));
    const e = recent.map((h) => Math.log(h.error));
    const mean = (v) => v.reduce((a, b) => a + b, 0) / v.length;
    const tm = mean(t), em = mean(e);
    let slope = 0;
    if (Math.max(...t) > Math.min(...t)) {
      slope = t.reduce((a, ti, i) => a + (ti - tm) * (e[i] - em), 0) / t.reduce((a, ti) => a + (ti - tm) ** 2, 0);
    }
    if (slope < 0) {  // seconds at which the fitted error meets the threshold
      return Math.max(0, Math.exp(t.at(-1) + (Math.log(threshold) - e.at(-1)) / slope) - job.elapsed_seconds);
    }
  }
  if (settings.max_seconds) return Math.max(0, settings.max_seconds - job.elapsed_seconds);
  if (settings.max_passes && job.passes > 0) return job.elapsed_seconds * (settings.max_passes - job.passes) / job.passes;
  return null;
}

function showJob(job) {
  state.job = job;
  $("status").textContent = job.status;
  const est = job.error_estimate;
  $("facts").textContent = `${job.scene_name || "uploaded scene"}, ${job.width}x${job.height}, ${job.settings.method} `
    + `${job.settings.gather}, ${job.passes} passes, ${(job.photons / 1e6).toFixed(1)}M photons, `
    + `${job.elapsed_seconds.toFixed(1)} s, ${job.workers_active} workers`
    + (est && est.error !== null ? `, estimated error ${est.error.toFixed(4)}` : "")
    + (job.failure ? `; failed: ${job.failure}` : "");
  const eta = FINISHED.includes(job.status) ? null : etaSeconds(job);
  $("eta").textContent = FINISHED.includes(job.status) ? `none: ${job.status}` : eta === null ? "unknown" : `${Math.round(eta)} s`;
  $("eta").dataset.seconds = eta === null ? "" : String(eta);
  $("cancel").disabled = FINISHED.includes(job.status);
  $("delete").disabled = !FINISHED.includes(job.status);
  $("download-png").disabled = $("download-exr").disabled = job.image_passes === 0;
  const history = job.error_history || [];
  drawChart($("chart-time"), history, "seconds", "seconds", job.settings.error_threshold);
  drawChart($("chart-passes"), history, "passes", "passes", job.settings.error_threshold);
}

// ---------------------------------------------------------------- charts
// Round steps (1, 2 or 5 times a power of ten), about `count` of them, from 0 to the first
// tick at or past `max` (the axis ends there, so every point lies on it).
function ticks(max, count) {
  const raw = max / count;
  const power = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
  const out = [0];
  while (out.at(-1) < max) out.push(Number((out.length * step).toPrecision(12)));
  return out;
}

const percent = (v) => `${Number((100 * v).toPrecision(3))}%`;

// A log-y scatter of the estimated relative error against `key` (seconds or passes), with
// ticked, labelled axes and the threshold drawn and labelled.
function drawChart(svg, history, key, label, threshold) {
  const W = 360, H = 220, L = 52, R = 12, T = 14, B = 36;
  const pts = history.filter((h) => h.error > 0 && Number.isFinite(h.error));
  const xs = pts.map((h) => h[key]);
  const ys = pts.map((h) => Math.log10(h.error)).concat(threshold ? [Math.log10(threshold)] : []);
  const xTicks = ticks(Math.max(key === "passes" ? 4 : 1, ...xs), 4);
  const x1 = xTicks.at(-1);
  const y0 = Math.floor(Math.min(...ys, -2)), y1 = Math.ceil(Math.max(...ys, 0));
  const sx = (x) => L + (W - L - R) * x / x1;
  const sy = (y) => T + (H - T - B) * (1 - (y - y0) / (y1 - y0));
  let out = "";
  for (let e = y0; e <= y1; e++) {  // decades: grid, tick, label
    out += `<line class="grid" x1="${L}" x2="${W - R}" y1="${sy(e)}" y2="${sy(e)}"/>`
      + `<line class="tick" x1="${L - 4}" x2="${L}" y1="${sy(e)}" y2="${sy(e)}"/>`
      + `<text class="ytick" x="${L - 6}" y="${sy(e) + 3}" text-anchor="end">${percent(10 ** e)}</text>`;
  }
  for (const x of xTicks) {
    out += `<line class="tick" x1="${sx(x)}" x2="${sx(x)}" y1="${H - B}" y2="${H - B + 4}"/>`
      + `<text class="xtick" x="${sx(x)}" y="${H - B + 14}" text-anchor="middle">${x}</text>`;
  }
  out += `<line class="axis" x1="${L}" y1="${H - B}" x2="${W - R}" y2="${H - B}"/>`
    + `<line class="axis" x1="${L}" y1="${T}" x2="${L}" y2="${H - B}"/>`
    + `<text class="xlabel" x="${(L + W - R) / 2}" y="${H - 4}" text-anchor="middle">${label}</text>`
    + `<text class="ylabel" transform="translate(11 ${(T + H - B) / 2}) rotate(-90)" text-anchor="middle">relative error</text>`;
  if (threshold) {
    const y = sy(Math.log10(threshold));
    out += `<line class="threshold" x1="${L}" x2="${W - R}" y1="${y}" y2="${y}"/>`
      + `<text class="threshold-label" x="${W - R - 2}" y="${y - 3}" text-anchor="end">threshold ${percent(threshold)}</text>`;
  }
  if (pts.length === 0) {
    out += `<text class="empty-note" x="${(L + W - R) / 2}" y="${(T + H - B) / 2}" text-anchor="middle">no error estimate yet</text>`;
  }
  out += pts.map((h) => `<circle class="pt" r="2.5" cx="${sx(h[key])}" cy="${sy(Math.log10(h.error))}"/>`).join("");
  svg.innerHTML = out;
}

// ---------------------------------------------------------------- the image: exposure, zoom
// The PNG holds srgb(1 - exp(-L)) of the linear radiance L (worker/image_io.py, tonemap). The
// exposure control inverts that per 8-bit value, scales L by 2^EV and maps it back; a value
// of 255 stands for every L above about 6.2, so brightening cannot recover detail there.
const toLinear = (s) => (s <= 0.04045 ? s / 12.92 : ((s + 0.055) / 1.055) ** 2.4);
const toSrgb = (x) => (x <= 0.0031308 ? 12.92 * x : 1.055 * x ** (1 / 2.4) - 0.055);
const MAX_TONE = 1 - 0.5 / 255;  // the tone mapped value that stands for 255

function exposureTable(ev) {
  const gain = 2 ** ev;
  const table = new Uint8ClampedArray(256);
  for (let v = 0; v < 256; v++) {
    const radiance = -Math.log(1 - Math.min(toLinear(v / 255), MAX_TONE));
    table[v] = Math.round(255 * toSrgb(1 - Math.exp(-gain * radiance)));
  }
  return table;
}

function draw() {
  const canvas = $("image");
  const bitmap = state.bitmap;
  if (!bitmap) return;
  canvas.width = bitmap.width;
  canvas.height = bitmap.height;
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  ctx.drawImage(bitmap, 0, 0);
  const ev = Number($("exposure").value);
  const map = state.shownMap;
  $("exposure").disabled = map;
  if (!map && ev !== 0) {
    const table = exposureTable(ev);
    const image = ctx.getImageData(0, 0, canvas.width, canvas.height);
    const px = image.data;
    for (let i = 0; i < px.length; i += 4) {
      px[i] = table[px[i]]; px[i + 1] = table[px[i + 1]]; px[i + 2] = table[px[i + 2]];
    }
    ctx.putImageData(image, 0, 0);
  }
  canvas.dataset.passes = state.shownPasses;  // say which estimate is on screen only once it is
  canvas.dataset.view = map ? "error" : "image";
  canvas.dataset.exposure = map ? "0" : String(ev);
  canvas.hidden = false;
  $("no-image").hidden = true;
  applyZoom();
}

// 1:1 maps one image pixel to one device pixel (CSS pixels divided by devicePixelRatio).
function applyZoom() {
  const canvas = $("image");
  const zoom = $("zoom").value;
  canvas.classList.toggle("fit", zoom === "fit");
  canvas.style.width = zoom === "fit" ? "" : `${(canvas.width * Number(zoom)) / window.devicePixelRatio}px`;
}

$("exposure").addEventListener("input", () => {
  $("exposure-value").textContent = `${Number($("exposure").value) > 0 ? "+" : ""}${$("exposure").value} EV`;
  draw();
});
$("zoom").addEventListener("change", applyZoom);

async function showImage(job) {
  const map = $("errormap").checked;
  if (job.image_passes === 0 || (job.image_passes === state.shownPasses && map === state.shownMap)) return;
  const link = map ? job.links.error_png : job.links.image_png;
  let bitmap, passes;
  try {
    const resp = await api(link);
    passes = Number(resp.headers.get("X-Passes"));  // the passes in this image (a fold may have landed since the poll)
    bitmap = await createImageBitmap(await resp.blob());
  } catch (e) {
    return; // 409 (no error estimation): keep what is shown
  }
  if (job.id !== state.selected) return;  // another job was picked meanwhile
  state.bitmap = bitmap;
  state.shownPasses = passes;
  state.shownMap = map;
  draw();
}

// ---------------------------------------------------------------- pixel readout
// The pixel under the cursor from GET /v1/jobs/{id}/pixel: linear RGB and its error bound.
// One request at a time; the latest position wins.
async function readPixel() {
  if (state.pixelBusy || !state.pointer || !state.job) return;
  const { x, y } = state.pointer;
  state.pointer = null;
  state.pixelBusy = true;
  const out = $("pixel-readout");
  try {
    const p = await (await api(`/v1/jobs/${state.job.id}/pixel?x=${x}&y=${y}`)).json();
    const error = p.relative_error === null ? "error not estimated"
      : `relative error ${percent(p.relative_error)}` + (p.bound === null ? " (unknown)" : ` (bound ${p.bound.toPrecision(4)} at ${percent(p.confidence)} confidence)`);
    out.textContent = `x ${p.x}, y ${p.y}: RGB ${p.rgb.map((v) => v.toPrecision(4)).join(" ")} (linear), ${error}, pass ${p.passes}`;
    Object.assign(out.dataset, { x: p.x, y: p.y, rgb: JSON.stringify(p.rgb), relative: String(p.relative_error) });
  } catch (e) {
    out.textContent = e.message;
  } finally {
    state.pixelBusy = false;
    if (state.pointer) readPixel();
  }
}

$("image").addEventListener("mousemove", (event) => {
  const canvas = $("image");
  const rect = canvas.getBoundingClientRect();
  const x = Math.floor(((event.clientX - rect.left) / rect.width) * canvas.width);
  const y = Math.floor(((event.clientY - rect.top) / rect.height) * canvas.height);
  if (x < 0 || y < 0 || x >= canvas.width || y >= canvas.height) return;
  state.pointer = { x, y };
  readPixel();
});

// ---------------------------------------------------------------- actions and polling
async function refresh() {
  try {
    await Promise.all([loadJobs(), loadWorkers()]);
    if (state.selected) {
      let job;
      try {
        job = await (await api(`/v1/jobs/${state.selected}`)).json();
      } catch (e) {
        if (e.status === 404) { select(null); return; }  // deleted
        throw e;
      }
      showJob(job);
      await showImage(job);
    }
  } catch (e) {
    $("submit-error").textContent = e.message;
  }
}

$("errormap").addEventListener("change", () => state.job && showImage(state.job));
$("cancel").addEventListener("click", async () => {
  await api(`/v1/jobs/${state.selected}`, { method: "DELETE" });
  await refresh();
});
$("delete").addEventListener("click", async () => {
  try {
    await api(`/v1/jobs/${state.selected}`, { method: "DELETE" });  // 204: a finished job is gone
    select(null);
    await refresh();
  } catch (e) {
    $("submit-error").textContent = e.message;
  }
});

async function download(format) {
  const job = state.job;
  const blob = await (await api(format === "png" ? job.links.image_png : job.links.image_exr)).blob();
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = `${job.scene_name || "job"}-${job.id}.${format}`;
  a.click();
  URL.revokeObjectURL(a.href);
}
$("download-png").addEventListener("click", () => download("png"));
$("download-exr").addEventListener("click", () => download("exr"));

select(null);
loadSettingsForm().catch((e) => { $("submit-error").textContent = `settings form: ${e.message}`; });
loadScenes().catch((e) => { $("submit-error").textContent = e.message; });
refresh();
setInterval(refresh, 1000);
