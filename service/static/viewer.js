// photonfarm viewer: submit a bundled scene, follow jobs, watch the image refine.
// Plain JavaScript against the JSON API; everything is polled once a second. Images and
// downloads are fetched as blobs so that a bearer token can go with them.
"use strict";

const $ = (id) => document.getElementById(id);
const FINISHED = ["completed", "converged", "cancelled", "failed"];
const state = { selected: null, job: null, shownPasses: -1, shownMap: null, imageUrl: null };

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
    throw new Error(`HTTP ${resp.status}: ${detail}`);
  }
  return resp;
}

async function loadScenes() {
  const scenes = await (await api("/v1/scenes")).json();
  $("scene").innerHTML = scenes
    .map((s) => `<option value="${s.name}" title="${s.description.replace(/"/g, "&quot;")}">${s.name}</option>`)
    .join("");
}

$("submit-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  $("submit-error").textContent = "";
  const settings = {
    max_seconds: Number($("max-seconds").value),
    photons_per_pass: Number($("photons").value),
    confidence: Number($("confidence").value),
  };
  if (Number($("threshold").value) > 0) settings.error_threshold = Number($("threshold").value);
  const res = $("resolution").value.trim();
  if (res) settings.resolution = res.toLowerCase().split("x").map(Number);
  try {
    const job = await (await api("/v1/jobs", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ scene_name: $("scene").value, settings }),
    })).json();
    select(job.id);
    await refresh();
  } catch (e) {
    $("submit-error").textContent = e.message;
  }
});

function progress(job) {
  const budget = job.settings;
  const est = job.error_estimate;
  if (FINISHED.includes(job.status)) return 1;
  if (budget.error_threshold && est) return Math.min(1, budget.error_threshold / est.error);
  if (budget.max_passes) return job.passes / budget.max_passes;
  return Math.min(1, job.elapsed_seconds / (budget.max_seconds || 1));
}

function renderJobs(jobs) {
  $("jobs").querySelector("tbody").innerHTML = jobs.map((j) => `
    <tr data-id="${j.id}" class="${j.id === state.selected ? "selected" : ""}">
      <td>${j.id.slice(0, 8)}</td><td>${j.scene_name || "inline"}</td><td class="st">${j.status}</td>
      <td>${j.passes}</td><td>${(j.photons_per_second / 1e6).toFixed(2)}</td>
      <td>${j.error_estimate ? j.error_estimate.error.toFixed(4) : "-"}</td>
      <td><div class="bar"><span style="width:${(100 * progress(j)).toFixed(0)}%"></span></div></td>
    </tr>`).join("");
}

$("jobs").addEventListener("click", (event) => {
  const row = event.target.closest("tr[data-id]");
  if (row) { select(row.dataset.id); refresh(); }
});

function select(id) {
  state.selected = id;
  state.shownPasses = -1;
  $("job-id").textContent = id.slice(0, 8);
}

async function showImage(job) {
  const map = $("errormap").checked;
  if (job.passes === state.shownPasses && map === state.shownMap) return;
  const link = map ? job.links.error_png : job.links.image_png;
  let blob;
  try {
    blob = await (await api(link)).blob();
  } catch (e) {
    return; // 409 before the first merge: keep what is shown
  }
  const previous = state.imageUrl;
  state.imageUrl = URL.createObjectURL(blob);
  state.shownPasses = job.passes;
  state.shownMap = map;
  $("image").onload = () => {  // say which estimate is on screen only once it is
    $("image").dataset.passes = job.passes;
    $("image").dataset.view = map ? "error" : "image";
    if (previous) URL.revokeObjectURL(previous);
  };
  $("image").src = state.imageUrl;
}

// A log-y scatter of the estimated error against `key` (seconds or passes), with the threshold.
function drawChart(svg, history, key, label, threshold) {
  const W = 360, H = 220, L = 48, R = 10, T = 16, B = 32;
  const pts = history.filter((h) => h.error > 0 && Number.isFinite(h.error));
  const xs = pts.map((h) => h[key]);
  const ys = pts.map((h) => Math.log10(h.error)).concat(threshold ? [Math.log10(threshold)] : []);
  const x0 = 0, x1 = Math.max(1e-9, ...xs, 0) || 1;
  const y0 = Math.min(...ys, -2), y1 = Math.max(...ys, 0);
  const sx = (x) => L + (W - L - R) * (x - x0) / (x1 - x0 || 1);
  const sy = (y) => T + (H - T - B) * (1 - (y - y0) / (y1 - y0 || 1));
  let out = `<line class="axis" x1="${L}" y1="${H - B}" x2="${W - R}" y2="${H - B}"/>`
    + `<line class="axis" x1="${L}" y1="${T}" x2="${L}" y2="${H - B}"/>`
    + `<text x="${(L + W - R) / 2}" y="${H - 6}" text-anchor="middle">${label}</text>`
    + `<text x="4" y="${T + 4}">error</text>`;
  for (let e = Math.ceil(y0); e <= Math.floor(y1); e++) {
    out += `<text x="${L - 4}" y="${sy(e) + 3}" text-anchor="end">1e${e}</text>`;
  }
  out += `<text x="${W - R}" y="${H - B + 12}" text-anchor="end">${x1.toFixed(key === "passes" ? 0 : 1)}</text>`;
  if (threshold) {
    out += `<line class="threshold" x1="${L}" x2="${W - R}" y1="${sy(Math.log10(threshold))}" y2="${sy(Math.log10(threshold))}"/>`;
  }
  out += pts.map((h) => `<circle class="pt" r="2.5" cx="${sx(h[key])}" cy="${sy(Math.log10(h.error))}"/>`).join("");
  svg.innerHTML = out;
}

function showJob(job) {
  state.job = job;
  $("status").textContent = job.status;
  const est = job.error_estimate;
  $("facts").textContent = `${job.width}x${job.height}, ${job.passes} passes, ${(job.photons / 1e6).toFixed(1)}M photons, `
    + `${job.elapsed_seconds.toFixed(1)} s, ${job.workers_active} workers` + (est ? `, estimated error ${est.error.toFixed(4)}` : "")
    + (job.failure ? `; failed: ${job.failure}` : "");
  $("cancel").disabled = FINISHED.includes(job.status);
  $("download-png").disabled = $("download-exr").disabled = job.passes === 0;
  const history = job.error_history || [];
  drawChart($("chart-time"), history, "seconds", "seconds", job.settings.error_threshold);
  drawChart($("chart-passes"), history, "passes", "passes", job.settings.error_threshold);
}

async function refresh() {
  try {
    renderJobs(await (await api("/v1/jobs")).json());
    if (state.selected) {
      const job = await (await api(`/v1/jobs/${state.selected}`)).json();
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

loadScenes().catch((e) => { $("submit-error").textContent = e.message; });
refresh();
setInterval(refresh, 1000);
