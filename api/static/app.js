// The Vox-E web UI: one page over the /v1 API, no build step.
//
// Authentication: the key is entered once and kept in sessionStorage (this tab's session). Every request,
// including the event stream and the media (preview, video, GLB), is a fetch() that sends it as
// `Authorization: Bearer <key>`; media become blob: URLs. EventSource cannot send headers, so the stream is
// read with fetch() and parsed here (reconnecting with Last-Event-ID), and no key ever travels in a URL.

const KEY_STORE = "voxe.apiKey";
const TERMINAL = new Set(["succeeded", "failed", "canceled"]);
const $ = (selector) => document.querySelector(selector);

const apiKey = () => sessionStorage.getItem(KEY_STORE) || "";

function authHeaders(extra = {}) {
  const key = apiKey();
  return key ? { ...extra, Authorization: `Bearer ${key}` } : extra;
}

/** A JSON request; throws an ApiError carrying the response's `detail` on a non-2xx answer. */
async function api(path, { method = "GET", body } = {}) {
  const headers = authHeaders(body === undefined ? {} : { "Content-Type": "application/json" });
  const response = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  const text = await response.text();
  const data = text ? JSON.parse(text) : null;
  if (!response.ok) throw new ApiError(response.status, data?.detail ?? text);
  return data;
}

class ApiError extends Error {
  constructor(status, detail) {
    super(typeof detail === "string" ? detail : JSON.stringify(detail));
    this.status = status;
    this.detail = detail;
  }
}

/** A same-origin URL for a protected file: a blob: URL fetched with the key. */
async function blobUrl(path) {
  const response = await fetch(path, { headers: authHeaders(), cache: "no-store" });
  if (!response.ok) throw new ApiError(response.status, await response.text());
  return URL.createObjectURL(await response.blob());
}

// ------------------------------------------------------------------ errors next to their fields
function clearErrors(form) {
  form.querySelectorAll(".error").forEach((el) => { el.textContent = ""; });
}

function showError(name, message) {
  const el = document.querySelector(`[data-error-for="${name}"]`);
  if (el) el.textContent = message;
  return Boolean(el);
}

/** FastAPI's 422 list ({loc, msg}) shown beside each named field; anything else beside ``fallback``. */
function showApiError(error, fallback) {
  if (!(error instanceof ApiError) || !Array.isArray(error.detail)) {
    showError(fallback, error instanceof ApiError ? `${error.status}: ${error.message}` : String(error));
    return;
  }
  const unplaced = [];
  for (const item of error.detail) {
    const loc = (item.loc || []).filter((part) => part !== "body");
    const text = `${item.msg}${loc.length ? ` (${loc.join(".")})` : ""}`;
    let placed = false;
    for (let n = loc.length; n > 0 && !placed; n--) placed = showError(loc.slice(0, n).join("."), text);
    if (!placed) unplaced.push(text);
  }
  if (unplaced.length) showError(fallback, unplaced.join("; "));
}

// ------------------------------------------------------------------ API key
function initKey() {
  const input = $("#api-key");
  input.value = apiKey();
  const describe = () => { $("#key-state").textContent = apiKey() ? "key set for this session" : "no key"; };
  describe();
  $("#key-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const value = input.value.trim();
    if (value) sessionStorage.setItem(KEY_STORE, value); else sessionStorage.removeItem(KEY_STORE);
    describe();
    route();
  });
}

// ------------------------------------------------------------------ upload (XMLHttpRequest: upload progress)
function initUpload() {
  const form = $("#upload-form");
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    clearErrors(form);
    const data = new FormData();
    const archive = $("#upload-archive").files[0];
    const files = [...$("#upload-files").files];
    if (archive) data.append("archive", archive, archive.name);
    for (const file of files) data.append("files", file, file.webkitRelativePath || file.name);
    if ($("#upload-name").value.trim()) data.append("name", $("#upload-name").value.trim());
    if (!archive && !files.length) { showError("upload", "choose a zip, or the dataset's files"); return; }
    const bar = $("#upload-progress");
    const status = $("#upload-status");
    bar.hidden = false;
    bar.value = 0;
    const xhr = new XMLHttpRequest();
    xhr.open("POST", "/v1/scenes");
    for (const [name, value] of Object.entries(authHeaders())) xhr.setRequestHeader(name, value);
    xhr.upload.onprogress = (e) => {
      if (e.lengthComputable) { bar.value = e.loaded / e.total; status.textContent = `${Math.round(100 * bar.value)} % sent`; }
    };
    xhr.onerror = () => showError("upload", "the upload failed (network error)");
    xhr.onload = async () => {
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch { /* not JSON: shown as text below */ }
      if (xhr.status >= 400) {
        showApiError(new ApiError(xhr.status, body?.detail ?? xhr.responseText), "upload");
        status.textContent = "";
        return;
      }
      bar.value = 1;
      status.textContent = `stored as ${body.id}; ${body.state}…`;
      await waitForScene(body.id, status);
    };
    xhr.send(data);
  });
}

/** Poll a new scene until its ingest is done; a failed ingest's reason goes beside the upload field. */
async function waitForScene(sceneId, status) {
  for (;;) {
    const scene = await api(`/v1/scenes/${sceneId}`);
    if (scene.state !== "processing") {
      status.textContent = `scene ${scene.name} (${scene.id}): ${scene.state}`;
      if (scene.state === "failed") showError("upload", scene.error || "the scene could not be decoded");
      await loadScenes(scene.state === "ready" ? scene.id : undefined);
      return;
    }
    await new Promise((resolve) => setTimeout(resolve, 1000));
  }
}

async function loadScenes(selected) {
  const page = await api("/v1/scenes?limit=200");
  const ready = page.items.filter((s) => s.state === "ready");
  const option = (s) => `<option value="${s.id}">${escapeHtml(s.name)} (${s.id})</option>`;
  const jobScene = $("#job-scene");
  const keep = selected || jobScene.value;
  jobScene.innerHTML = ready.map(option).join("");
  if (keep) jobScene.value = keep;
  const filter = $("#filter-scene");
  const filterValue = filter.value;
  filter.innerHTML = `<option value="">all</option>${page.items.map(option).join("")}`;
  filter.value = filterValue;
}

// ------------------------------------------------------------------ submit an edit
function initJobForm() {
  const form = $("#job-form");
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    clearErrors(form);
    let params = {};
    const extra = $("#job-params").value.trim();
    if (extra) {
      try { params = JSON.parse(extra); } catch (e) { showError("params", `not JSON: ${e.message}`); return; }
    }
    for (const [field, id] of [["iterations", "#job-iterations"], ["render_size", "#job-render-size"]]) {
      if ($(id).value !== "") params[field] = Number($(id).value);
    }
    const words = $("#job-edit-words").value.split(",").map((w) => w.trim()).filter(Boolean);
    const body = { scene_id: $("#job-scene").value, prompt: $("#job-prompt").value,
                   mode: form.querySelector('input[name="mode"]:checked').value, edit_words: words, params };
    try {
      const job = await api("/v1/jobs", { method: "POST", body });
      location.hash = `#/jobs/${job.id}`;
    } catch (error) {
      showApiError(error, "job");
    }
  });
}

// ------------------------------------------------------------------ job list
function initJobList() {
  $("#filter-scene").addEventListener("change", loadJobs);
  $("#filter-state").addEventListener("change", loadJobs);
}

async function loadJobs() {
  const query = new URLSearchParams({ limit: "50" });
  if ($("#filter-scene").value) query.set("scene_id", $("#filter-scene").value);
  if ($("#filter-state").value) query.set("state", $("#filter-state").value);
  showError("list", "");
  try {
    const page = await api(`/v1/jobs?${query}`);
    $("#job-list tbody").innerHTML = page.items.map((job) => `
      <tr data-job="${job.id}">
        <td><a href="#/jobs/${job.id}">${job.id}</a></td><td>${escapeHtml(job.prompt)}</td><td>${job.mode}</td>
        <td class="state-${job.state}">${job.state}</td>
        <td><progress max="1" value="${job.overall_progress}"></progress> ${Math.round(100 * job.overall_progress)} %</td>
        <td title="${job.created_at}">${age(job.created_at)}</td>
      </tr>`).join("");
  } catch (error) {
    showApiError(error, "list");
  }
}

// ------------------------------------------------------------------ job page
let currentStream = null;  // AbortController of the open event stream

async function showJob(jobId) {
  const job = await api(`/v1/jobs/${jobId}`);
  $("#job-title").textContent = `“${job.prompt}”`;
  $("#job-meta").textContent = `job ${job.id} · ${job.mode}${job.edit_words.length ? ` (${job.edit_words.join(", ")})` : ""}`
    + ` · scene ${job.scene_id} · model ${job.models.sds ?? "?"} · ${job.device}`;
  $("#job-events").innerHTML = "";
  $("#job-artifacts").innerHTML = "";
  for (const id of ["#job-preview", "#job-mask", "#job-video", "#job-model"]) $(id).hidden = true;
  renderProgress(job);
  $("#job-cancel").onclick = async () => {
    showError("cancel", "");
    try { renderProgress(await api(`/v1/jobs/${jobId}/cancel`, { method: "POST" })); }
    catch (error) { showApiError(error, "cancel"); }
  };
  if (job.preview_url) await refreshPreview(job.preview_url);
  await refreshArtifacts(jobId);
  followEvents(jobId);
}

function renderProgress(p) {
  $("#job-state").textContent = p.state + (p.cancel_requested && !TERMINAL.has(p.state) ? " (cancel requested)" : "");
  $("#job-state").className = `state-${p.state}`;
  $("#job-stage").textContent = p.stage ? `${p.stage}${p.completed_stages?.length ? ` (done: ${p.completed_stages.join(", ")})` : ""}` : "–";
  $("#job-stage-progress").value = p.progress ?? 0;
  $("#job-stage-text").textContent = `${p.iteration}/${p.total}`;
  $("#job-overall-progress").value = p.overall_progress ?? 0;
  $("#job-overall-text").textContent = `${Math.round(100 * (p.overall_progress ?? 0))} %`;
  $("#job-eta").textContent = p.overall_eta_seconds != null
    ? `${duration(p.overall_eta_seconds)} left (this stage: ${p.eta_seconds != null ? duration(p.eta_seconds) : "–"})` : "–";
  const losses = Object.entries(p.losses || {});
  $("#job-losses").textContent = losses.length ? losses.map(([k, v]) => `${k} ${Number(v).toPrecision(4)}`).join(" · ") : "–";
  $("#job-message").textContent = p.error || p.message || "";
  $("#job-cancel").disabled = TERMINAL.has(p.state);
}

async function refreshPreview(url) {
  const img = $("#job-preview");
  const old = img.src;
  img.src = await blobUrl(url);
  img.hidden = false;
  if (old.startsWith("blob:")) URL.revokeObjectURL(old);
}

/** Every artifact as a download (fetched with the key, saved from a blob: URL); the media shown inline. */
async function refreshArtifacts(jobId) {
  const artifacts = await api(`/v1/jobs/${jobId}/artifacts`);
  const list = $("#job-artifacts");
  list.innerHTML = "";
  for (const artifact of artifacts) {
    const item = document.createElement("li");
    const link = document.createElement("a");
    link.href = "#";
    link.textContent = artifact.name;
    link.dataset.artifact = artifact.name;
    link.onclick = async (event) => {
      event.preventDefault();
      const save = document.createElement("a");
      save.href = await blobUrl(artifact.url);
      save.download = artifact.name;
      save.click();
      setTimeout(() => URL.revokeObjectURL(save.href), 60_000);
    };
    item.append(link, ` ${bytes(artifact.size)} · ${artifact.kind} · sha256 ${artifact.sha256.slice(0, 12)}…`);
    list.append(item);
  }
  const byName = Object.fromEntries(artifacts.map((a) => [a.name, a]));
  await showMedia(byName["turntable.mp4"], "#job-video");
  await showMedia(byName["mesh.glb"], "#job-model");
  await showMedia(byName["mask_overlay.png"], "#job-mask");
}

async function showMedia(artifact, selector) {
  const el = $(selector);
  if (!artifact || el.dataset.sha === artifact.sha256) return;
  el.src = await blobUrl(artifact.url);
  el.dataset.sha = artifact.sha256;
  el.hidden = false;
}

/** Read the job's Server-Sent Events with fetch() (the key in a header), reconnecting with Last-Event-ID. */
async function followEvents(jobId) {
  currentStream?.abort();
  const controller = new AbortController();
  currentStream = controller;
  let lastId = null;
  let retryMs = 2000;
  while (!controller.signal.aborted) {
    let finished = false;
    try {
      const headers = authHeaders({ Accept: "text/event-stream", ...(lastId ? { "Last-Event-ID": lastId } : {}) });
      const response = await fetch(`/v1/jobs/${jobId}/events`, { headers, signal: controller.signal, cache: "no-store" });
      if (!response.ok) throw new ApiError(response.status, await response.text());
      showError("stream", "");
      for await (const event of parseSse(response.body)) {
        if (event.retry) retryMs = event.retry;
        if (event.id) lastId = event.id;
        if (!event.event) continue;
        await handleEvent(jobId, event.event, event.data);
        if (TERMINAL.has(event.event)) finished = true;
      }
      if (finished) break;  // the server ends the stream after the terminal event
    } catch (error) {
      if (controller.signal.aborted) return;
      showError("stream", `event stream: ${error.message}; reconnecting`);
      if (error instanceof ApiError && error.status < 500) return;
    }
    await new Promise((resolve) => setTimeout(resolve, retryMs));
  }
}

async function handleEvent(jobId, kind, data) {
  if (kind === "progress") { renderProgress(data); return; }
  const item = document.createElement("li");
  item.textContent = `${kind}${data.stage ? ` · ${data.stage}` : ""}${data.detail ? ` · ${data.detail}` : ""}`;
  item.dataset.event = kind;
  $("#job-events").append(item);
  if (kind === "preview") await refreshPreview(`/v1/jobs/${jobId}/artifacts/${data.detail || "preview.png"}`);
  if (kind === "artifact" || TERMINAL.has(kind)) await refreshArtifacts(jobId);
  if (TERMINAL.has(kind)) renderProgress(await api(`/v1/jobs/${jobId}`));
}

/** Server-Sent Events from a byte stream: {id, event, data (JSON-decoded), retry} per blank-line-ended block. */
async function* parseSse(body) {
  const reader = body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  let block = { data: [] };
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value;
    let newline;
    while ((newline = buffer.indexOf("\n")) >= 0) {
      const line = buffer.slice(0, newline).replace(/\r$/, "");
      buffer = buffer.slice(newline + 1);
      if (line === "") {
        if (block.data.length || block.retry) {
          const text = block.data.join("\n");
          yield { id: block.id, event: block.event, retry: block.retry, data: text ? JSON.parse(text) : null };
        }
        block = { data: [] };
      } else if (!line.startsWith(":")) {
        const colon = line.indexOf(":");
        const field = colon < 0 ? line : line.slice(0, colon);
        const value = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
        if (field === "data") block.data.push(value);
        else if (field === "id") block.id = value;
        else if (field === "event") block.event = value;
        else if (field === "retry" && /^\d+$/.test(value)) block.retry = Number(value);
      }
    }
  }
}

// ------------------------------------------------------------------ formatting
function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

function duration(seconds) {
  const s = Math.max(0, Math.round(seconds));
  return s >= 3600 ? `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`
    : s >= 60 ? `${Math.floor(s / 60)} min ${s % 60} s` : `${s} s`;
}

function age(iso) {
  const zoned = /([zZ]|[+-]\d\d:?\d\d)$/.test(iso) ? iso : `${iso}Z`;  // the API's times are UTC
  return `${duration((Date.now() - Date.parse(zoned)) / 1000)} ago`;
}

function bytes(n) {
  return n >= 1 << 20 ? `${(n / (1 << 20)).toFixed(1)} MiB` : n >= 1024 ? `${(n / 1024).toFixed(1)} KiB` : `${n} B`;
}

// ------------------------------------------------------------------ routing (#/ and #/jobs/<id>)
let listTimer = null;

async function route() {
  const match = location.hash.match(/^#\/jobs\/([^/]+)$/);
  $("#home").hidden = Boolean(match);
  $("#job").hidden = !match;
  clearInterval(listTimer);
  if (match) {
    try { await showJob(match[1]); } catch (error) { showApiError(error, "stream"); }
    return;
  }
  currentStream?.abort();
  try { await loadScenes(); } catch (error) { showApiError(error, "list"); }
  await loadJobs();
  listTimer = setInterval(loadJobs, 3000);
}

initKey();
initUpload();
initJobForm();
initJobList();
window.addEventListener("hashchange", route);
route();
