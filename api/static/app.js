// The Vox-E web UI: one page over the /v1 API, no build step.
//
// Authentication: the key is entered once and kept in sessionStorage (this tab's session). Every request,
// including the event stream and the media (preview, video, GLB), is a fetch() that sends it as
// `Authorization: Bearer <key>`; media become blob: URLs. EventSource cannot send headers, so the stream is
// read with fetch() and parsed here (reconnecting with Last-Event-ID), and no key ever travels in a URL.

const KEY_STORE = "voxe.apiKey";
const TERMINAL = new Set(["succeeded", "failed", "canceled"]);
const NAME_MOST = 255;  // characters (code points) of a scene's name: POST /v1/scenes' name, maxLength
const $ = (selector) => document.querySelector(selector);
// The API's /v1 beside this file's folder, so that a service mounted under a prefix by a proxy (uvicorn
// --root-path /api: the page at /api/, this file at /api/static/app.js) is called at /api/v1.
const V1 = new URL("../v1", import.meta.url).pathname;

const apiKey = () => sessionStorage.getItem(KEY_STORE) || "";

function authHeaders(extra = {}) {
  const key = apiKey();
  return key ? { ...extra, Authorization: `Bearer ${key}` } : extra;
}

/** A JSON request whose answer is ``answer`` (one of ANSWERS); throws an ApiError carrying the response's `detail`
 * on a non-2xx answer, one naming its type on a 2xx answer that is no JSON (a login page a proxy sent the request
 * to: JSON.parse's SyntaxError had been shown, "Unexpected token '<'"), and one quoting it on a 2xx answer of another
 * shape (a proxy's own JSON, an empty body: the caller's TypeError had been shown, "Cannot read properties of
 * null"). */
async function api(path, answer, { method = "GET", body, headers = {}, signal } = {}) {
  const sent = authHeaders(body === undefined ? headers : { ...headers, "Content-Type": "application/json" });
  const response = await fetch(path, { method, signal, headers: sent,
                                       body: body === undefined ? undefined : JSON.stringify(body) });
  if (!response.ok) throw await responseError(response);
  const text = await response.text();
  let value = null;
  try {
    value = text ? JSON.parse(text) : null;
  } catch {
    throw notTheApis(response.status, response.headers.get("Content-Type"), "JSON");
  }
  if (!answer.fits(value)) {
    throw new ApiError(response.status, `the answer (${text ? text.slice(0, 200) : "empty"}) is no ${answer.name}`);
  }
  // Served without a key: authentication is off (with it on, /v1 answers 401). The field had said "no key", as if
  // one were missing.
  if (!sent.Authorization && !apiKey()) $("#key-state").textContent = "no key needed: authentication is off";
  return value;
}

const isObject = (value) => typeof value === "object" && value !== null && !Array.isArray(value);
const identified = (value) => isObject(value) && typeof value.id === "string" && typeof value.state === "string";
const listOf = (name, fits) => ({ name, fits: (value) => Array.isArray(value) && value.every(fits) });
const pageOf = (name) => ({ name, fits: (value) => isObject(value) && Array.isArray(value.items)
                                                    && value.items.every(isObject) });
/** The answers the page reads, each with what it is called when another came instead. */
const ANSWERS = {
  job: { name: "job", fits: identified },
  scene: { name: "scene", fits: identified },
  jobs: pageOf("page of jobs"),
  scenes: pageOf("page of scenes"),
  events: listOf("list of events", isObject),
  artifacts: listOf("list of artifacts", (a) => isObject(a) && ["name", "url", "sha256"]
    .every((key) => typeof a[key] === "string")),
};

/** The error of a non-2xx answer: FastAPI's `detail` from a JSON body, else the status text (a plain-text 500 or
 * a proxy's HTML 502 page says nothing more useful, and is no JSON to parse). HTTP/2 sends no status text: then the
 * status's standard reason phrase, or for a status without one a plain-text body's first line (it had read
 * "502: error"). */
function apiError(status, statusText, contentType, text, retryAfter) {
  let detail = null;
  if (/^application\/([\w.-]+\+)?json\b/i.test(contentType || "")) {
    try { detail = JSON.parse(text).detail; } catch { /* a broken JSON body: the status text below */ }
  }
  const plain = /^text\/plain\b/i.test(contentType || "") ? text.trim().split(/\r?\n/)[0].slice(0, 200) : "";
  return new ApiError(status, detail ?? (statusText || REASON_PHRASES[status] || plain || "no reason given"),
                      retryAfterMs(retryAfter));
}

/** The longest a Retry-After, or an event stream's ``retry:``, is waited for: setTimeout() fires at once for a wait
 * over 2^31-1 ms (24.8 days), so a proxy's far-off Retry-After (an HTTP date in 2100) had the page asking again
 * hundreds of times a second while saying it waits, and a ``retry: 3000000000`` the stream reconnecting as often;
 * and a wait of days or weeks, even kept, leaves the page stopped long after the server is back. */
const RETRY_AFTER_CAP_MS = 5 * 60_000;

/** A Retry-After header's wait in ms (seconds, or an HTTP date: RFC 9110 §10.2.3), at most RETRY_AFTER_CAP_MS; null
 * when absent or unreadable. */
function retryAfterMs(value) {
  const ms = /^\s*\d+\s*$/.test(value || "") ? Number(value) * 1000 : Date.parse(value || "") - Date.now();
  return Number.isNaN(ms) ? null : Math.min(Math.max(0, ms), RETRY_AFTER_CAP_MS);
}

/** How long to wait before asking again: ``ms``, or longer where a failure's Retry-After (a 429's, a 503's) asks it
 * (a throttled page had asked again at its own pace, every 3 s for the job list). */
const retryWait = (ms, ...failures) => Math.max(ms, ...failures.map((failure) => failure?.retryAfterMs ?? 0));

/** The standard reason phrases (RFC 9110, and 429 of RFC 6585) of the statuses the API or a proxy before it sends. */
const REASON_PHRASES = {
  400: "Bad Request", 401: "Unauthorized", 403: "Forbidden", 404: "Not Found", 405: "Method Not Allowed",
  408: "Request Timeout", 409: "Conflict", 410: "Gone", 411: "Length Required", 412: "Precondition Failed",
  413: "Content Too Large", 414: "URI Too Long", 415: "Unsupported Media Type", 422: "Unprocessable Content",
  429: "Too Many Requests", 431: "Request Header Fields Too Large", 500: "Internal Server Error",
  501: "Not Implemented", 502: "Bad Gateway", 503: "Service Unavailable", 504: "Gateway Timeout",
  507: "Insufficient Storage",
};

/** The error of a 2xx answer that is no ``expected`` (a login page a proxy sent the request to), naming what came
 * back. */
function notTheApis(status, contentType, expected) {
  return new ApiError(status, `the answer (${contentType || "untyped"}) is no ${expected}`);
}

async function responseError(response) {
  return apiError(response.status, response.statusText, response.headers.get("Content-Type"), await response.text(),
                  response.headers.get("Retry-After"));
}

class ApiError extends Error {
  constructor(status, detail, retryAfterMs = null) {
    super(typeof detail === "string" ? detail : JSON.stringify(detail));
    this.status = status;
    this.detail = detail;
    this.retryAfterMs = retryAfterMs;
  }
}

/** A same-origin URL for a protected file: a blob: URL fetched with the key. */
async function blobUrl(path, signal) {
  const response = await fetch(path, { headers: authHeaders(), cache: "no-store", signal });
  if (!response.ok) throw await responseError(response);
  return URL.createObjectURL(await response.blob());
}

/** Resolves after `ms`, or as soon as `signal` is aborted (the page changed). */
function sleep(ms, signal) {
  return new Promise((resolve) => {
    const done = () => { clearTimeout(timer); signal.removeEventListener("abort", done); resolve(); };
    const timer = setTimeout(done, ms);
    signal.addEventListener("abort", done);
  });
}

/** Resolves once the page is shown (at once if it is), or as soon as `signal` is aborted: a hidden tab's polls wait
 * for it (the job list had been asked for every 3 s in a tab nobody looked at). */
function shown(signal) {
  return new Promise((resolve) => {
    const done = () => {
      if (document.hidden && !signal.aborted) return;
      document.removeEventListener("visibilitychange", done);
      signal.removeEventListener("abort", done);
      resolve();
    };
    document.addEventListener("visibilitychange", done);
    signal.addEventListener("abort", done);
    done();
  });
}

/** A random Idempotency-Key (crypto.randomUUID() exists only on HTTPS and localhost; this works on plain HTTP). */
function randomKey() {
  return Array.from(crypto.getRandomValues(new Uint8Array(16)), (b) => b.toString(16).padStart(2, "0")).join("");
}

/** The Idempotency-Key of a form's submissions. The same request again (a double submit, a retry after a lost
 * answer) sends the same key, so it gets what the first one created instead of a second one; any other request
 * (``what``: its fingerprint; a field changed, by the user or by code such as the scene list's refresh), or one
 * after a success, gets a new key: the API refuses a key reused with another body. */
function submissionKey() {
  let key = null;
  let sent = null;
  return {
    for: (what) => {
      if (what !== sent) { key = randomKey(); sent = what; }
      return key;
    },
    succeeded: () => { sent = null; },
  };
}

const jobPath = (jobId) => `${V1}/jobs/${encodeURIComponent(jobId)}`;

// ------------------------------------------------------------------ errors next to their fields
function clearErrors(form) {
  form.querySelectorAll(".error").forEach((el) => { el.textContent = ""; });
}

/** The element that shows the errors of field `name` (any text: a 422 may name a key typed by the user). */
const errorSlot = (name) => document.querySelector(`[data-error-for="${CSS.escape(name)}"]`);

function showError(name, message) {
  errorSlot(name).textContent = message;
}

function errorText(error) {
  if (!(error instanceof ApiError)) return String(error);
  const cap = duration(RETRY_AFTER_CAP_MS / 1000);
  const wait = error.retryAfterMs == null ? ""
    : error.retryAfterMs < RETRY_AFTER_CAP_MS ? ` (the server asks to wait ${duration(error.retryAfterMs / 1000)})`
    : ` (the server asks to wait ${cap} or more; this page waits ${cap} at most)`;
  return `${error.status}: ${error.message}${wait}`;
}

/** FastAPI's 422 list ({loc, msg}) shown beside each named field, all of a field's together; anything else
 * beside ``fallback``. */
function showApiError(error, fallback) {
  if (!(error instanceof ApiError) || !Array.isArray(error.detail)) {
    showError(fallback, errorText(error));
    return;
  }
  const messages = new Map();  // field -> its messages
  for (const item of error.detail) {
    const loc = (item.loc || []).filter((part) => part !== "body");
    const text = `${item.msg}${loc.length ? ` (${loc.join(".")})` : ""}`;
    const prefixes = loc.map((_, i) => loc.slice(0, loc.length - i).join("."));  // the longest first
    const field = prefixes.find((name) => errorSlot(name)) ?? fallback;
    messages.set(field, [...(messages.get(field) || []), text]);
  }
  for (const [field, texts] of messages) showError(field, texts.join("; "));
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
    if (/[^\x21-\x7e]/.test(value)) {  // an HTTP header cannot carry it (fetch and XMLHttpRequest would throw)
      $("#key-state").textContent = "not used: a key holds only ASCII letters, digits and punctuation";
      return;
    }
    if (value) sessionStorage.setItem(KEY_STORE, value); else sessionStorage.removeItem(KEY_STORE);
    describe();
    route();
  });
}

// ------------------------------------------------------------------ upload (XMLHttpRequest: upload progress)
function initUpload() {
  const form = $("#upload-form");
  const button = form.querySelector('button[type="submit"]');
  const idempotency = submissionKey();
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    clearErrors(form);
    const data = new FormData();
    const archive = $("#upload-archive").files[0];
    // A folder's files are named by their paths in it (webkitRelativePath): a dataset's images sit in a subfolder
    // (train/), which files picked one by one cannot say. Its name is the scene's, as a zip's is.
    const folder = [...$("#upload-folder").files];
    const files = [...folder, ...$("#upload-files").files];
    const name = $("#upload-name").value.trim() || (folder[0]?.webkitRelativePath.split("/")[0] ?? "");
    if (archive) data.append("archive", archive, archive.name);
    for (const file of files) data.append("files", file, file.webkitRelativePath || file.name);
    if (name) data.append("name", name);
    // A mesh's options only when chosen: the API refuses them (even its defaults) for a dataset of images.
    const meshOptions = [["mesh_shading", "#upload-mesh-shading"], ["mesh_up_axis", "#upload-mesh-up-axis"]]
      .map(([field, id]) => [field, $(id).value]).filter(([, value]) => value);
    for (const [field, value] of meshOptions) data.append(field, value);
    if (!archive && !files.length) { showError("upload", "choose a zip, the dataset's folder, or its files"); return; }
    // Said before the upload, whose 422 would come only once it is sent: in characters, as the API counts (a
    // maxlength counts UTF-16 units, and had cut a name of emoji the API takes)
    if ([...name].length > NAME_MOST) {
      showError("name", `String should have at most ${NAME_MOST} characters (name)`);
      return;
    }
    const bar = $("#upload-progress");
    const status = $("#upload-status");
    const sent = $("#upload-sent");
    bar.hidden = false;
    bar.value = 0;
    status.textContent = "";  // (the last upload's outcome)
    reported = null;  // (an earlier upload's scene, still watched, no longer reports here)
    showSceneWarnings([]);
    button.disabled = true;  // until the upload is answered: a second click would upload it twice
    const xhr = new XMLHttpRequest();
    xhr.open("POST", `${V1}/scenes`);
    const upload = JSON.stringify([archive, ...files].filter(Boolean)
      .map((f) => [f.webkitRelativePath || f.name, f.size, f.lastModified]).concat([name, meshOptions]));
    for (const [name, value] of Object.entries(authHeaders({ "Idempotency-Key": idempotency.for(upload) }))) {
      xhr.setRequestHeader(name, value);
    }
    // The share sent is shown beside the bar and is the bar's spoken value, outside the status's live region: a
    // screen reader had queued each of its many changes a second.
    xhr.upload.onprogress = (e) => {
      if (!e.lengthComputable) return;
      bar.value = e.loaded / e.total;
      sent.textContent = `${percent(bar.value)} sent`;
      bar.setAttribute("aria-valuetext", sent.textContent);
    };
    xhr.onloadend = () => { button.disabled = false; sent.textContent = ""; };
    // The bar goes with the upload it showed, unless stored: left at its share sent (at 100 % on a refusal), it had
    // read as an upload still going on, or one that went through.
    xhr.onerror = () => {
      bar.hidden = true;
      showError("upload", "the upload failed (network error)");
    };
    xhr.onload = async () => {
      if (xhr.status >= 400) {
        const error = apiError(xhr.status, xhr.statusText, xhr.getResponseHeader("Content-Type"), xhr.responseText,
                               xhr.getResponseHeader("Retry-After"));
        bar.hidden = true;
        showApiError(error, "upload");
        status.textContent = "";
        return;
      }
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch { /* no JSON: said below */ }
      if (typeof body?.id !== "string") {  // no API answer (a login page a proxy sent the upload to): said, not thrown
        const error = notTheApis(xhr.status, xhr.getResponseHeader("Content-Type"), "scene");
        bar.hidden = true;
        showError("upload", `${errorText(error)}: the upload may not have been stored`);
        status.textContent = "";
        return;
      }
      idempotency.succeeded();
      bar.value = 1;
      status.textContent = `stored as ${body.id}; ${body.state}…`;
      ingesting.add(body.id);
      reported = body.id;
      // Watched on the page shown when the upload is answered (and again on a later home page: ingesting): the
      // page it was sent from is gone after a look at a job meanwhile, and the home page shown since had found
      // nothing to watch when it opened, leaving the scene "processing…" and never offered.
      await waitForScene(body.id, status, page.signal);
    };
    xhr.send(data);
  });
}

/** The scenes whose ingest the page watches until it ends: each uploaded here, and each the scene lists found
 * processing (after a reload); all watched again whenever the home page shows. A look at a job meanwhile had left it
 * "processing…" for good and the scene never offered; only the last upload's had been watched again, an earlier
 * one's (and after a reload, any) left unoffered until the page was loaded again once it was ready. */
const ingesting = new Set();

/** The scene of the last upload sent, the one the upload form's status, warnings and error report: an earlier
 * upload's scene still watched once it is sent had its outcome ("scene A: ready") written over the later one's. */
let reported = null;

/** Poll a new scene until its ingest is done, while the page is shown; a failed ingest's reason goes beside the
 * upload field. A failed poll is shown there too and retried, less often each time, until the page changes. */
async function waitForScene(sceneId, status, signal) {
  for (let failures = 0; !signal.aborted;) {
    let failure = null;
    try {
      const scene = await api(`${V1}/scenes/${encodeURIComponent(sceneId)}`, ANSWERS.scene, { signal });
      // Only what a watch of this scene said there (a failed poll): every answer had cleared the field, wiping a
      // later upload's refusal a second after it was shown.
      if (errorSlot("upload").textContent.startsWith(`checking scene ${sceneId}: `)) showError("upload", "");
      failures = 0;
      if (scene.state !== "processing") {
        ingesting.delete(sceneId);
        if (reported === sceneId) {
          status.textContent = `scene ${scene.name} (${scene.id}): ${scene.state}`;
          showSceneWarnings(scene.warnings);
          if (scene.state === "failed") showError("upload", scene.error || "the scene could not be decoded");
        } else if (scene.state === "failed") {
          listEarlierFailure(scene);
        }
        await loadScenes(signal, scene.state === "ready" ? scene.id : undefined);
        return;
      }
    } catch (error) {
      if (signal.aborted) return;
      // The scene gone (deleted meanwhile): asked again it is answered the same (it had been asked every 30 s for
      // as long as the page stayed open, and again on every later home page). Said as the upload's outcome, where
      // "checking scene …: 404" had stayed beside the upload field for good, as if the page could not check it.
      if (error.status === 404) {
        ingesting.delete(sceneId);
        if (errorSlot("upload").textContent.startsWith(`checking scene ${sceneId}: `)) showError("upload", "");
        const gone = `scene ${sceneId} was deleted before its ingest ended (${errorText(error)}); no longer watched`;
        if (reported === sceneId) status.textContent = gone;
        else listEarlier(gone);
        return;
      }
      // The key refused: watched again (ingesting kept) by the next home page, the one a key's use opens.
      if (keyRefused(error)) {
        showError("upload", `checking scene ${sceneId}: ${errorText(error)}; asked again once a key is used`);
        return;
      }
      failures += 1;
      failure = error;
      showError("upload", `checking scene ${sceneId}: ${errorText(error)}; retrying`);
    }
    await sleep(retryWait(Math.min(1000 * 2 ** failures, 30_000), failure), signal);
    await shown(signal);
  }
}

/** An earlier upload's failed ingest, listed under the upload form: the form reports the last upload sent only, and
 * an earlier one's failure, once a later upload was sent, had been said nowhere (its scene just never offered). */
function listEarlierFailure(scene) {
  listEarlier(`scene ${scene.name} (${scene.id}) failed: ${scene.error || "the scene could not be decoded"}`);
}

/** An earlier upload's outcome, listed under the upload form (its failure, its scene deleted). */
function listEarlier(said) {
  const list = $("#upload-earlier");
  const item = document.createElement("li");
  item.textContent = said;
  list.append(item);
  list.hidden = false;
}

/** What the scene's processing loaded the upload without (a mesh's .mtl not sent, its PLY's texture unread: it
 * loads grey), listed under the upload's outcome: else they are told only as warning events of its edit jobs. */
function showSceneWarnings(warnings) {
  const list = $("#upload-warnings");
  const items = Array.isArray(warnings) ? warnings.map(String) : [];
  list.replaceChildren(...items.map((warning) => {
    const item = document.createElement("li");
    item.textContent = `warning: ${warning}`;
    return item;
  }));
  list.hidden = !items.length;
}

/** Load the scene lists; a failure is shown beside the Scene field it leaves empty, and returned (null: none). */
async function refreshScenes(signal) {
  try {
    await loadScenes(signal);
    showError("scene_id", "");
    return null;
  } catch (error) {
    if (!signal.aborted) {
      showError("scene_id", `loading the scenes: ${errorText(error)}${keyRefused(error) ? "" : "; retrying"}`);
    }
    return error;
  }
}

const SCENES_PER_REQUEST = 200;  // the API's largest page

/** Every scene of the key, newest first, page by page (the 201st had been offered nowhere), each page after the
 * last one read (by offset, a scene made meanwhile shifted the pages: one was met twice, and one deleted made the
 * next page skip a scene). */
async function allScenes(signal) {
  const scenes = [];
  let cursor = null;
  do {
    const query = new URLSearchParams({ ...(cursor && { cursor }), limit: String(SCENES_PER_REQUEST) });
    const answer = await api(`${V1}/scenes?${query}`, ANSWERS.scenes, { signal });
    scenes.push(...answer.items);
    cursor = answer.next_cursor;
  } while (cursor);
  return scenes;
}

/** Why the Scene field offers none, said when an edit is submitted without one: the API's 422 had said "String
 * should have at least 1 character (scene_id)". */
let noSceneReason = "the scenes have not loaded yet: wait for them, or reload the page";

async function loadScenes(signal, selected) {
  const scenes = await allScenes(signal);
  const ready = scenes.filter((s) => s.state === "ready");
  for (const s of scenes) if (s.state === "processing") ingesting.add(s.id);
  noSceneReason = scenes.some((s) => s.state === "processing")
    ? "no scene is ready yet: wait until the one uploaded is processed (it is offered here once it is ready)"
    : "no scene to edit: upload one (1. Upload a scene), then choose it here once it is ready";
  const option = (s) => new Option(`${s.name} (${s.id})`, s.id);
  const jobScene = $("#job-scene");
  const keep = selected || jobScene.value;
  jobScene.replaceChildren(...ready.map(option));
  // A choice kept only while its scene is offered: set to one gone (deleted meanwhile), a <select> shows nothing
  // chosen, the edit would be sent with no scene, and the job list, shown unfiltered, read as filtered.
  if (ready.some((s) => s.id === keep)) jobScene.value = keep;
  const filter = $("#filter-scene");
  const filterValue = filter.value;
  filter.replaceChildren(new Option("all", ""), ...scenes.map(option));
  filter.value = scenes.some((s) => s.id === filterValue) ? filterValue : "";
}

// ------------------------------------------------------------------ submit an edit
function initJobForm() {
  const form = $("#job-form");
  const button = form.querySelector('button[type="submit"]');
  const idempotency = submissionKey();
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    clearErrors(form);
    const body = jobRequest(form);
    if (!body) return;
    button.disabled = true;  // until answered: a double click would create the job twice
    try {
      const headers = { "Idempotency-Key": idempotency.for(JSON.stringify(body)) };
      const job = await api(`${V1}/jobs`, ANSWERS.job, { method: "POST", body, headers });
      idempotency.succeeded();
      location.hash = `#/jobs/${encodeURIComponent(job.id)}`;
    } catch (error) {
      // a proxy's page or own JSON: said, not opened as "#/jobs/undefined"
      const answered = error instanceof ApiError && error.status >= 200 && error.status < 300;
      if (answered) showError("job", `${errorText(error)}: it may have been created (sent again, it is found)`);
      else showApiError(error, "job");
    } finally {
      button.disabled = false;
    }
  });
}

/** The POST /v1/jobs body from the form; null (the reasons shown beside the fields) when a field cannot be read. */
function jobRequest(form) {
  let params = {};
  const extra = $("#job-params").value.trim();
  if (extra) {
    try { params = JSON.parse(extra); } catch (e) { showError("params", `not JSON: ${e.message}`); return null; }
    if (typeof params !== "object" || params === null || Array.isArray(params)) {
      showError("params", 'not a JSON object: write {"name": value, …}');
      return null;
    }
  }
  let readable = true;
  if (!$("#job-scene").value) {
    showError("scene_id", noSceneReason);
    readable = false;
  }
  for (const [field, id] of [["iterations", "#job-iterations"], ["render_size", "#job-render-size"]]) {
    const input = $(id);
    if (input.validity.badInput) {  // its value reads "" as if left empty: the paper's value would run instead
      showError(`params.${field}`, "not a number");
      readable = false;
    } else if (input.value !== "") {
      params[field] = Number(input.value);
    }
  }
  if (!readable) return null;
  const words = $("#job-edit-words").value.split(",").map((w) => w.trim()).filter(Boolean);
  return { scene_id: $("#job-scene").value, prompt: $("#job-prompt").value,
           mode: form.querySelector('input[name="mode"]:checked').value, edit_words: words, params };
}

// ------------------------------------------------------------------ job list
const JOBS_PER_PAGE = 50;
const JOB_LIST_POLL_MS = 3000;
/** The shown page of the job list (newest first), kept while a job is looked at: the cursor it starts after (null:
 * the newest jobs), those of the newer pages it was reached through, and its own next_cursor, where "older" goes.
 * By offset, a job created while a page was shown shifted the next: "older" had repeated jobs just seen. */
let jobsCursor = null;
const newerJobsCursors = [];
let olderJobsCursor = null;

function initJobList() {
  const show = (cursor) => { jobsCursor = cursor; loadJobs(page.signal); };
  const newest = () => { newerJobsCursors.length = 0; show(null); };
  $("#filter-scene").addEventListener("change", newest);
  $("#filter-state").addEventListener("change", newest);
  $("#jobs-newer").addEventListener("click", () => show(newerJobsCursors.pop() ?? null));
  $("#jobs-older").addEventListener("click", () => {
    $("#jobs-older").disabled = true;  // until the page after answers (a second click would skip it in the stack)
    newerJobsCursors.push(jobsCursor);
    show(olderJobsCursor);
  });
}

/** The newest job list request: an older one answering after it (the poll's, sent before a filter changed) is
 * dropped, else it had shown the jobs the filter hides until the next poll. */
let jobListRequest = 0;

/** Show the job list's page; its failure is shown beside it, and returned (null: none). */
async function loadJobs(signal) {
  const request = ++jobListRequest;
  const cursor = jobsCursor;
  const query = new URLSearchParams({ ...(cursor && { cursor }), limit: String(JOBS_PER_PAGE) });
  if ($("#filter-scene").value) query.set("scene_id", $("#filter-scene").value);
  if ($("#filter-state").value) query.set("state", $("#filter-state").value);
  try {
    const jobs = await api(`${V1}/jobs?${query}`, ANSWERS.jobs, { signal });
    if (request !== jobListRequest) return null;
    if (!jobs.items.length && cursor) {  // every job past the cursor deleted meanwhile: show the page before
      jobsCursor = newerJobsCursors.pop() ?? null;
      return loadJobs(signal);
    }
    olderJobsCursor = jobs.next_cursor;
    showError("list", "");
    $("#jobs-range").textContent = jobs.items.length
      ? `${jobs.offset + 1}–${jobs.offset + jobs.items.length} of ${jobs.total}` : "no jobs";
    $("#jobs-newer").disabled = cursor === null;
    $("#jobs-older").disabled = !jobs.next_cursor;
    $("#job-list tbody").replaceChildren(...jobs.items.map(jobRow));
    return null;
  } catch (error) {
    if (signal.aborted || request !== jobListRequest) return null;
    showApiError(error, "list");
    return error;
  }
}

/** A job's row in the list, built as elements: every field the API sends is set as text (a mode or a time spliced
 * into HTML had been parsed as markup). */
function jobRow(job) {
  const row = document.createElement("tr");
  row.dataset.job = job.id;
  const cell = (...content) => { const td = document.createElement("td"); td.append(...content); return td; };
  const link = document.createElement("a");
  link.href = `#/jobs/${encodeURIComponent(job.id)}`;
  link.textContent = job.id;
  const progress = document.createElement("progress");
  progress.setAttribute("max", "1");
  progress.setAttribute("value", job.overall_progress);  // (a property refuses a value that is no number)
  progress.setAttribute("aria-label", "overall progress");  // (a column's header names no cell's bar)
  const prompt = cell(job.prompt);
  prompt.className = "prompt";
  const state = cell(job.state);
  state.className = `state-${job.state}`;
  const created = cell(age(job.created_at));
  created.title = job.created_at;
  row.append(cell(link), prompt, cell(job.mode), state, cell(progress, ` ${percent(job.overall_progress)}`), created);
  return row;
}

// ------------------------------------------------------------------ job page
const JOB_MEDIA = ["#job-preview", "#job-mask", "#job-video", "#job-model"];

/** Empty the job page before a job loads into it: nothing of the job shown before stays, its Cancel least of all. */
function clearJobView() {
  for (const id of ["#job-title", "#job-meta", "#job-state", "#job-stage", "#job-stage-text", "#job-overall-text",
                    "#job-eta", "#job-losses", "#job-message", "#job-artifacts", "#job-events"]) $(id).textContent = "";
  $("#job-stage-progress").value = 0;
  $("#job-overall-progress").value = 0;
  $("#job-cancel").disabled = true;
  $("#job-cancel").onclick = null;
  for (const name of ["cancel", "stream", "media", "artifacts"]) showError(name, "");
  for (const id of JOB_MEDIA) hideMedia($(id));
}

/** The job page: its timeline so far read once (before the job and its artifacts, so that nothing falls between
 * them and the stream), then the stream of what comes after it, unless the timeline has ended. Replayed through
 * the stream, the history had downloaded the preview again for each past preview, and listed the artifacts again
 * for each past artifact, at every opening of the page. */
async function showJob(jobId, signal) {
  const history = await api(`${jobPath(jobId)}/events`, ANSWERS.events, { signal });
  const job = await api(jobPath(jobId), ANSWERS.job, { signal });
  $("#job-title").textContent = `“${job.prompt}”`;
  $("#job-meta").textContent = `job ${job.id} · ${job.mode}${job.edit_words.length ? ` (${job.edit_words.join(", ")})` : ""}`
    + ` · scene ${job.scene_id} · model ${job.models.sds ?? "?"} · ${job.device}`;
  $("#job-cancel").onclick = async () => {
    showError("cancel", "");
    try { renderProgress(await api(`${jobPath(jobId)}/cancel`, ANSWERS.job, { method: "POST", signal })); }
    catch (error) { if (!signal.aborted) showApiError(error, "cancel"); }
  };
  renderProgress(job);
  for (const event of history) listEvent(event.kind, event);
  // Each on its own: a preview gone from the storage leaves the artifacts listed (no later event lists them).
  if (job.preview_url) await refreshMedia(() => refreshPreview(job.preview_url, signal), signal);
  await refreshMedia(() => refreshArtifacts(jobId, signal), signal);
  const last = history.at(-1);
  if (!TERMINAL.has(last?.kind)) followEvents(jobId, last?.id, signal);
}

/** The statuses of a request refused for its key (none, a wrong or a revoked one): sent again with the same key, it
 * is refused again. */
const KEY_REFUSED = new Set([401, 403]);
const keyRefused = (error) => error instanceof ApiError && KEY_REFUSED.has(error.status);
/** Whether a refusal is an API's with authentication off, serving only its own machine (api/auth.py's RequireKey:
 * the page opened on another address, or through a proxy): no key is read, so none helps (the page had said "a key
 * is needed: enter one", then "this key is refused" of any key entered). */
const authOff = (error) => /^authentication is off\b/.test(error.message);

/** Say beside the key field what a refusal for the key asks for (``where``: where the API's reason is shown). The
 * job page says it too: opened in a new tab (a middle click on a job's link), which has no key (sessionStorage is
 * the tab's, and kept nowhere longer: the key is a secret), it had said "no key" only. */
function sayKeyRefused(error, where) {
  $("#key-state").textContent = authOff(error) ? `no key is asked (authentication is off): see why ${where}`
    : `${apiKey() ? "this key is refused" : "a key is needed"}: enter one and Use it`;
}

/** Whether a failed request may succeed sent again: it got no answer (fetch's TypeError), or a 5xx or 429. */
const transient = (error) => error instanceof TypeError
  || (error instanceof ApiError && (error.status >= 500 || error.status === 429));

/** The job page of ``encodedId`` (the id as the URL has it), its first reads tried again (less often each time)
 * while they fail for a reason that a retry may change (the API restarting, a proxy's 502): such a failure had left
 * the page empty for good. Nothing is shown before those reads succeed, so nothing is shown twice. */
async function openJob(encodedId, signal) {
  for (let failures = 1; !signal.aborted; failures += 1) {
    let failure = null;
    try {
      await showJob(decodeURIComponent(encodedId), signal);
      showError("stream", "");
      return;
    } catch (error) {
      if (signal.aborted) return;
      if (!transient(error)) {  // the job, or the key, is wrong (or the URL's id is no URI-encoded text)
        showApiError(error, "stream");
        if (keyRefused(error)) sayKeyRefused(error, "below");
        return;
      }
      failure = error;
      showError("stream", `loading the job: ${errorText(error)}; retrying`);
    }
    await sleep(retryWait(Math.min(1000 * 2 ** failures, 30_000), failure), signal);
  }
}

/** Run a refresh of the media or artifacts; its failure (a file gone, say) is shown beside the media, leaving the
 * rest of the page and the event stream going. */
async function refreshMedia(refresh, signal) {
  try {
    await refresh();
  } catch (error) {
    if (signal.aborted) throw error;
    showApiError(error, "media");
  }
}

function renderProgress(p) {
  $("#job-state").textContent = p.state + (p.cancel_requested && !TERMINAL.has(p.state) ? " (cancel requested)" : "");
  $("#job-state").className = `state-${p.state}`;
  $("#job-stage").textContent = p.stage ? `${p.stage}${p.completed_stages?.length ? ` (done: ${p.completed_stages.join(", ")})` : ""}` : "–";
  $("#job-stage-progress").value = p.progress ?? 0;
  $("#job-stage-text").textContent = p.total ? `${p.iteration}/${p.total}` : "–";  // none before a stage starts
  $("#job-overall-progress").value = p.overall_progress ?? 0;
  $("#job-overall-text").textContent = percent(p.overall_progress ?? 0);
  $("#job-eta").textContent = eta(p);
  const losses = Object.entries(p.losses || {});
  $("#job-losses").textContent = losses.length ? losses.map(([k, v]) => `${k} ${Number(v).toPrecision(4)}`).join(" · ") : "–";
  // A failed job's reason, said missing where none was recorded (its Message had been left blank).
  $("#job-message").textContent = p.error || p.message || (p.state === "failed" ? "(no reason was recorded)" : "");
  $("#job-cancel").disabled = TERMINAL.has(p.state);
}

/** The time left of a running job, and of its stage while one runs; none for a job that ended (the API's 0 s left
 * for a succeeded job had read "finishing…"), nor for a stage done (the worker's 0 s left between stages had read
 * "this stage: finishing…"). */
function eta(p) {
  if (TERMINAL.has(p.state) || p.overall_eta_seconds == null) return "–";
  const stageRuns = p.stage && !(p.completed_stages || []).includes(p.stage);
  return timeLeft(p.overall_eta_seconds) + (stageRuns ? ` (this stage: ${timeLeft(p.eta_seconds)})` : "");
}

/** Show a file in an <img>, <video> or <model-viewer> (through the attribute, which all three read). */
function setMedia(el, url) {
  const old = el.getAttribute("src");
  el.setAttribute("src", url);
  el.hidden = false;
  if (old?.startsWith("blob:")) URL.revokeObjectURL(old);
}

/** Hide a media element and free its file, forgetting which one it was (so that showMedia shows it again). */
function hideMedia(el) {
  const old = el.getAttribute("src");
  el.removeAttribute("src");
  if (el instanceof HTMLMediaElement) el.load();  // a hidden <video> would go on playing its old file
  if (old?.startsWith("blob:")) URL.revokeObjectURL(old);
  delete el.dataset.sha;
  el.hidden = true;
}

async function refreshPreview(url, signal) {
  setMedia($("#job-preview"), await blobUrl(url, signal));
}

/** Every artifact as a download (fetched with the key, saved from a blob: URL); the media shown inline. */
async function refreshArtifacts(jobId, signal) {
  const artifacts = await api(`${jobPath(jobId)}/artifacts`, ANSWERS.artifacts, { signal });
  const list = $("#job-artifacts");
  list.replaceChildren();
  for (const artifact of artifacts) {
    const item = document.createElement("li");
    const link = document.createElement("a");
    // The file's own URL, which a new tab (the context menu's "Open link in new tab") opens without the key: one with
    // authentication off is served, another says the key it needs. "#" had opened the home page, saying nothing.
    link.href = artifact.url;
    link.textContent = artifact.name;
    link.dataset.artifact = artifact.name;
    // A click, modified (Ctrl, Shift) or not, and a middle click (auxclick) download it with the key: a middle click
    // had opened "#" in a new tab.
    link.onclick = link.onauxclick = async (event) => {
      if (event.button > 1) return;  // (a right click's auxclick: the context menu)
      event.preventDefault();
      showError("artifacts", "");
      try {
        const save = document.createElement("a");
        save.href = await blobUrl(artifact.url, signal);
        save.download = artifact.name;
        save.click();
        setTimeout(() => URL.revokeObjectURL(save.href), 60_000);
      } catch (error) {
        if (!signal.aborted) showError("artifacts", `${artifact.name}: ${errorText(error)}`);
      }
    };
    item.append(link, ` ${bytes(artifact.size)} · ${artifact.kind} · sha256 ${artifact.sha256.slice(0, 12)}…`);
    list.append(item);
  }
  const byName = Object.fromEntries(artifacts.map((a) => [a.name, a]));
  await showMedia(byName["turntable.mp4"], "#job-video", signal);
  await showMedia(byName["mesh.glb"], "#job-model", signal);
  await showMedia(byName["mask_overlay.png"], "#job-mask", signal);
}

async function showMedia(artifact, selector, signal) {
  const el = $(selector);
  if (!artifact || el.dataset.sha === artifact.sha256) return;
  setMedia(el, await blobUrl(artifact.url, signal));
  el.dataset.sha = artifact.sha256;
}

/** Answers to the stream request that no reconnection changes: the key, or the job, is not (or no longer) valid, or
 * the request is refused as it stands (a 422: a Last-Event-ID past the job's newest event, after a database restore;
 * asked again with it, it had been refused for as long as the page stayed open). */
const FINAL_STREAM_STATUS = new Set([...KEY_REFUSED, 404, 422]);
/** The longest wait for a word of the stream (the server sends a comment every 15 s when nothing happens): past it
 * the connection is taken for dead and opened again. A connection dropped unsaid (a laptop's sleep, a network change,
 * a proxy's timeout) had left the read waiting for ever, the page frozen at its last progress. */
const STREAM_SILENCE_MS = 45_000;
/** The longest wait before a reconnection after failures in a row (each doubles the wait). */
const STREAM_RETRY_CAP_MS = 30_000;

/** Read the job's Server-Sent Events after event ``afterId`` (none: from its start) with fetch() (the key in a
 * header), reconnecting with Last-Event-ID until the job ends or the page changes: after the server's retry
 * interval (RETRY_AFTER_CAP_MS at most), doubled for each failure in a row (a failing server had been asked again
 * every 2 s for as long as the page stayed open), back to it once a stream delivers an event or a comment. A 2xx
 * answer that is no event stream (a proxy's login page), or a stream that ends with nothing delivered, is such a
 * failure: reset on any 2xx, they had been asked again every 2 s, saying nothing. */
async function followEvents(jobId, afterId, signal) {
  let lastId = afterId == null ? null : String(afterId);
  let retryMs = 2000;
  let failures = 0;
  while (!signal.aborted) {
    let finished = false;
    let failure = null;
    try {
      const headers = authHeaders({ Accept: "text/event-stream", ...(lastId ? { "Last-Event-ID": lastId } : {}) });
      const response = await fetch(`${jobPath(jobId)}/events`, { headers, signal, cache: "no-store" });
      if (!response.ok) {
        const error = await responseError(response);
        if (FINAL_STREAM_STATUS.has(response.status)) {
          showError("stream", `event stream: ${errorText(error)}; not reconnecting (reload the page to try again)`);
          return;
        }
        throw error;
      }
      const type = response.headers.get("Content-Type");
      if (!/^text\/event-stream\b/i.test(type || "")) {
        response.body?.cancel().catch(() => {});  // (unread, it would hold its connection)
        throw notTheApis(response.status, type, "event stream");
      }
      let delivered = false;
      for await (const event of parseSse(response.body, STREAM_SILENCE_MS)) {
        if (!delivered) {
          delivered = true;
          failures = 0;
          showError("stream", "");
        }
        if (event.retry) retryMs = Math.min(event.retry, RETRY_AFTER_CAP_MS);
        if (event.id) lastId = event.id;
        if (!event.event) continue;
        if (event.event === "error") {  // the server's last word: the job was deleted, or the key revoked
          showError("stream", `event stream: ${event.data?.detail}; not reconnecting (reload the page to try again)`);
          return;
        }
        await handleEvent(jobId, event.event, event.data, signal);
        // A reconnect after the terminal event gets only a progress snapshot in the terminal state (and the end).
        if (TERMINAL.has(event.event) || TERMINAL.has(event.data?.state)) finished = true;
      }
      if (finished) return;  // the server ends the stream after the terminal event
      if (!delivered) throw new ApiError(response.status, "the stream ended with nothing received");
    } catch (error) {
      if (signal.aborted) return;
      failures += 1;
      failure = error;
      showError("stream", `event stream: ${errorText(error)}; reconnecting`);
    }
    const backoff = retryMs * 2 ** Math.max(0, failures - 1);
    await sleep(retryWait(Math.min(backoff, Math.max(retryMs, STREAM_RETRY_CAP_MS)), failure), signal);
  }
}

async function handleEvent(jobId, kind, data, signal) {
  if (kind === "progress") { renderProgress(data); return; }
  listEvent(kind, data);
  await refreshMedia(async () => {
    if (kind === "preview") {
      await refreshPreview(`${jobPath(jobId)}/artifacts/${encodeURIComponent(data.detail || "preview.png")}`, signal);
    }
    if (kind === "artifact" || TERMINAL.has(kind)) await refreshArtifacts(jobId, signal);
  }, signal);
  if (TERMINAL.has(kind)) renderProgress(await api(jobPath(jobId), ANSWERS.job, { signal }));
}

/** One timeline event at the end of the job page's list (a checkpoint's or a resume's iteration too). */
function listEvent(kind, data) {
  const item = document.createElement("li");
  const iteration = data.iteration != null ? `iteration ${data.iteration}` : "";
  item.textContent = [kind, data.stage, iteration, data.detail].filter(Boolean).join(" · ");
  item.dataset.event = kind;
  $("#job-events").append(item);
}

/** Server-Sent Events from a byte stream: {id, event, data (JSON-decoded), retry} per blank-line-ended block, and
 * {comment} per comment line (the server's keepalive: a sign of life, with no event). A
 * TimeoutError when nothing arrives for ``silenceMs``; the stream is cancelled (its connection closed) when its
 * reading ends, however it ends. */
async function* parseSse(body, silenceMs) {
  const reader = body.pipeThrough(new TextDecoderStream()).getReader();
  try {
    yield* sseBlocks(reader, silenceMs);
  } finally {
    reader.cancel().catch(() => {});  // (refused for a stream that failed: nothing is left to close)
  }
}

async function* sseBlocks(reader, silenceMs) {
  let buffer = "";
  let block = { data: [] };
  for (;;) {
    const { value, done } = await within(reader.read(), silenceMs, "nothing received");
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
      } else if (line.startsWith(":")) {
        yield { comment: line.slice(1) };
      } else {
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

/** ``promise``'s outcome, or a TimeoutError ("``what`` for N s") if it has none after ``ms``. */
async function within(promise, ms, what) {
  let timer;
  const late = new Promise((_, reject) => {
    timer = setTimeout(() => reject(new DOMException(`${what} for ${ms / 1000} s`, "TimeoutError")), ms);
  });
  try {
    return await Promise.race([promise, late]);
  } finally {
    clearTimeout(timer);
  }
}

// ------------------------------------------------------------------ formatting
/** A fraction as a whole percentage, rounded down: a job 99.6 % done reads 99 %, not 100 % (done). The epsilon
 * keeps 0.57 at 57 % (100 * 0.57 is 56.99999999999999). */
function percent(fraction) {
  return `${Math.floor(100 * fraction + 1e-9)} %`;
}

function duration(seconds) {
  const s = Math.max(0, Math.round(seconds));
  return s >= 86400 ? `${Math.floor(s / 86400)} d ${Math.floor((s % 86400) / 3600)} h`
    : s >= 3600 ? `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`
    : s >= 60 ? `${Math.floor(s / 60)} min ${s % 60} s` : `${s} s`;
}

/** A running job's or stage's ETA as the time left; one that rounds to 0 (its estimate reached) reads "finishing…",
 * not "0 s left". */
function timeLeft(seconds) {
  return seconds == null ? "–" : Math.round(seconds) > 0 ? `${duration(seconds)} left` : "finishing…";
}

function age(iso) {
  const zoned = /([zZ]|[+-]\d\d:?\d\d)$/.test(iso) ? iso : `${iso}Z`;  // the API's times are UTC
  return `${duration((Date.now() - Date.parse(zoned)) / 1000)} ago`;
}

function bytes(n) {
  return n >= 1 << 20 ? `${(n / (1 << 20)).toFixed(1)} MiB` : n >= 1024 ? `${(n / 1024).toFixed(1)} KiB` : `${n} B`;
}

// ------------------------------------------------------------------ routing (#/ and #/jobs/<id>)
let page = new AbortController();  // the shown page's: a route change aborts its requests, event stream and polling

async function route() {
  page.abort();
  page = new AbortController();
  const { signal } = page;
  const match = location.hash.match(/^#\/jobs\/([^/]+)$/);
  const [shownPage, hiddenPage] = match ? [$("#job"), $("#home")] : [$("#home"), $("#job")];
  // Before clearJobView(), which removes the artifact links (a focus on one had been dropped with it, unseen).
  const focusHidden = hiddenPage.contains(document.activeElement);
  clearJobView();
  shownPage.hidden = false;
  hiddenPage.hidden = true;
  // A keyboard's focus on the page just hidden (the job link pressed, "← all jobs") goes to the page shown: it had
  // been dropped to the document's start, the next Tab back at the header's first link.
  if (focusHidden) shownPage.focus();
  if (match) {
    await openJob(match[1], signal);
    return;
  }
  // The scenes are loaded again with the job list until they load (the API restarting, a proxy's 502): a failure
  // had left the Scene field empty for good, its message at once wiped by the job list's. Both are asked again
  // once the page shows, no sooner than a failure's Retry-After asks.
  let scenesFailure = await refreshScenes(signal);
  for (const sceneId of ingesting) waitForScene(sceneId, $("#upload-status"), signal);
  while (!signal.aborted) {
    const jobsFailure = await loadJobs(signal);
    // A key used meanwhile aborted this page: its scenes' refusal was for the old key (the new one had been named
    // refused).
    if (signal.aborted) return;
    const refused = [jobsFailure, scenesFailure].find(keyRefused);
    if (refused) {  // (both had been asked again every 3 s, for good)
      sayKeyRefused(refused, "beside the job list");
      return;
    }
    await sleep(retryWait(JOB_LIST_POLL_MS, jobsFailure, scenesFailure), signal);
    await shown(signal);
    if (scenesFailure) scenesFailure = await refreshScenes(signal);
  }
}

initKey();
initUpload();
initJobForm();
initJobList();
window.addEventListener("hashchange", route);
route();
