"""The web UI in a real headless Chromium (Selenium + Debian's chromium-driver) against a live uvicorn API and
Celery worker with authentication ON and the random-weight SMOKE-TEST model (VOXE_SDS_MODEL=tiny): plumbing
only, never edit quality. A screenshot of each page lands in tests/.artifacts/ (gitignored) on every run.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from pathlib import Path
from urllib.parse import urlparse

import httpx
import pytest

from needs import MIC, missing, require_data
from service_helpers import service, small_mic, wait_until, zip_folder

pytestmark = pytest.mark.slow

ARTIFACTS = Path(__file__).resolve().parent / ".artifacts"
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
PARAMS = {  # tests/test_service_e2e.py's tiny local-edit parameters (8 frames: the cut needs an occupied grid)
    "downsample": 16, "max_images": 8, "iterations": 5, "render_size": 48, "preview_every": 2,
    "reconstruction": {"preset": "fast", "resolution": 24, "iterations": [10, 10, 20], "rays_per_step": 1024},
    "refine": {"iterations": 20, "views": 4, "render_size": 64, "rays_per_step": 2048},
    "export": {"views": 1, "view_size": 48, "turntable_frames": 4, "turntable_size": 48, "gif": False},
}
# Run in every page before its own scripts: collects the page's CSP violations (window.cspViolations) and its
# fetch() requests (window.requests), and answers a request whose URL holds a key of sessionStorage "test.faults"
# (a key ending in "$": whose path is the key; the first in sorted order, as Selenium sends a dict's keys sorted)
# as a slow or failing server would: after `delay` ms, and/or with the given status, type, body and other `headers`
# (`method`: requests of that method only; `skip`: the first so many such requests go through; `once`: only the first
# such request after them); or, given `timeline` (events {id, kind, ...}), as a job's events would: its first
# `recorded` events as JSON, or as an event stream (Accept) every event after the request's Last-Event-ID, left open
# with nothing more sent when `open` (a connection dropped unsaid).
# Each request in window.requests has `at`: when it was sent (Date.now()).
PAGE_HOOKS = """
window.cspViolations = [];
document.addEventListener("securitypolicyviolation",
                          (e) => cspViolations.push(`${e.violatedDirective} ${e.blockedURI}`));
window.requests = [];
const realFetch = window.fetch;
window.fetch = async (resource, options = {}) => {
  const url = resource instanceof Request ? resource.url : String(resource);
  requests.push({ url, method: options.method || "GET", headers: options.headers || {}, at: Date.now() });
  const method = options.method || "GET";
  const faults = JSON.parse(sessionStorage.getItem("test.faults") || "{}");
  const matches = ([key, fault]) => (!fault.method || fault.method === method)
    && (key.endsWith("$") ? new URL(url, location.href).pathname === key.slice(0, -1) : url.includes(key));
  const [part, fault] = Object.entries(faults).find(matches) || [];
  if (fault?.skip) {
    faults[part] = { ...fault, skip: fault.skip - 1 };
    sessionStorage.setItem("test.faults", JSON.stringify(faults));
    return realFetch(resource, options);
  }
  if (fault?.once) { delete faults[part]; sessionStorage.setItem("test.faults", JSON.stringify(faults)); }
  if (fault?.delay) {
    await new Promise((resolve, reject) => {
      setTimeout(resolve, fault.delay);
      options.signal?.addEventListener("abort", () => reject(options.signal.reason));
    });
  }
  if (fault?.timeline) {
    if (options.headers?.Accept !== "text/event-stream") {
      return new Response(JSON.stringify(fault.timeline.slice(0, fault.recorded)),
                          { headers: { "Content-Type": "application/json" } });
    }
    const after = Number(options.headers["Last-Event-ID"] || 0);
    const text = fault.timeline.filter((e) => e.id > after)
      .map((e) => `id: ${e.id}\nevent: ${e.kind}\ndata: ${JSON.stringify(e)}\n\n`).join("");
    const body = fault.open
      ? new ReadableStream({ start: (out) => out.enqueue(new TextEncoder().encode(text)) }) : text;
    return new Response(body, { headers: { "Content-Type": "text/event-stream" } });
  }
  if (fault?.status) {
    return new Response(fault.body, { status: fault.status, statusText: fault.statusText,
                                      headers: { "Content-Type": fault.type, ...fault.headers } });
  }
  return realFetch(resource, options);
};
"""


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """(service, API key token, small mic zip)."""
    require_data(MIC)
    root = tmp_path_factory.mktemp("ui")
    archive = zip_folder(small_mic(root / "mic_small", frames=8), root / "mic_small.zip", prefix="mic_small")
    with service(root / "svc", VOXE_AUTH="on", VOXE_PROGRESS_INTERVAL_S="0.5") as svc:
        made = subprocess.run([sys.executable, "-m", "api.admin", "create-key", "--name", "browser"], env=svc.env,
                              capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[1])
        yield svc, made.stdout.strip(), archive


@pytest.fixture(scope="module")
def browser():
    if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
        missing("chromium / chromium-driver are not installed (.ci/test installs them)")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service as DriverService
    except ImportError:
        missing("selenium is not installed (the dev extra)")
    profile = tempfile.mkdtemp(prefix="voxe-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1280,1600",
                 f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=DriverService(CHROMEDRIVER))
    driver.set_script_timeout(30)
    driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": PAGE_HOOKS})
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def screenshot(driver, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    driver.save_screenshot(str(ARTIFACTS / f"ui_{name}.png"))


def text(driver, selector: str, tries: int = 3) -> str:
    """The element's visible text, found again when the page replaced it between the find and the read (the job
    list's poll re-renders its rows)."""
    from selenium.common.exceptions import StaleElementReferenceException

    for _ in range(tries - 1):
        try:
            return driver.find_element("css selector", selector).text
        except StaleElementReferenceException:
            continue
    return driver.find_element("css selector", selector).text


def faults(driver, spec: dict) -> None:
    """From now on, answer the page's requests as ``spec`` says (PAGE_HOOKS); ``{}``: as the server does."""
    driver.execute_script("sessionStorage.setItem('test.faults', JSON.stringify(arguments[0]))", spec)


PROCESSING_SCENE = {"id": "x", "name": "tetra", "state": "processing"}
"""A scene still processing, as a stand-in answer of ``GET /v1/scenes/{id}`` (:func:`scene_answered`)."""


def scene_answered(scene: dict) -> dict:
    """A :func:`faults` entry answering the page's ``GET`` of a scene with ``scene`` (200, JSON)."""
    return {"method": "GET", "status": 200, "type": "application/json", "body": json.dumps(scene)}


def requested(driver, part: str, method: str = "GET") -> list[dict]:
    """The page's fetch() requests (since it loaded, or ``window.requests = []``) whose URL holds ``part``."""
    return [r for r in driver.execute_script("return window.requests")
            if part in r["url"] and r["method"] == method]


def streams(driver, job_id: str) -> list[dict]:
    """The page's event stream requests for the job (its timeline read as JSON is none)."""
    return [r for r in requested(driver, f"/v1/jobs/{job_id}/events")
            if r["headers"].get("Accept") == "text/event-stream"]


def go(driver, hash_: str) -> None:
    driver.execute_script("location.hash = arguments[0]", hash_)


def shown_media(driver) -> list[str]:
    return driver.execute_script("return ['#job-preview', '#job-mask', '#job-video', '#job-model']"
                                 ".filter((s) => !document.querySelector(s).hidden)")


def use_key(driver, key: str) -> None:
    """Enter the key in the header's field and Use it (the page's own form)."""
    field = driver.find_element("id", "api-key")
    field.clear()
    field.send_keys(key)
    driver.find_element("css selector", "#key-form button").click()


def set_key(driver, svc, token: str) -> None:
    driver.get(f"{svc.base}/")
    use_key(driver, token)
    wait_until(lambda: "key set" in text(driver, "#key-state"), 10, what="the key to be kept")


def test_upload_edit_and_watch_a_local_edit_to_its_video_and_3d_view(live, browser):
    from selenium.webdriver import ActionChains
    from selenium.webdriver.support.select import Select

    svc, token, archive = live
    driver = browser
    wait = lambda predicate, what, timeout=240: wait_until(predicate, timeout, what=what,  # noqa: E731
                                                           processes=svc.processes)
    # Without the key the page says what the API said (401), next to the job list.
    driver.get(f"{svc.base}/")
    wait(lambda: "401" in text(driver, '[data-error-for="list"]'), "the 401 beside the job list", 20)
    set_key(driver, svc, token)
    assert driver.execute_script("return sessionStorage.getItem('voxe.apiKey')") == token

    # A file that is no dataset: the API's 4xx message beside the upload field.
    bad = Path(tempfile.mkdtemp()) / "notes.zip"
    bad.write_bytes(b"not a zip at all")
    driver.find_element("id", "upload-archive").send_keys(str(bad))
    driver.find_element("css selector", "#upload-form button").click()
    wait(lambda: "422" in text(driver, '[data-error-for="upload"]'), "the upload's 422", 30)

    # The real scene, with upload progress, until its ingest is done and it is offered for editing. Two clicks
    # upload it once; a proxy's 502 page on the first look at the new scene is shown, and the look retried, also
    # after a look at a job page meanwhile (the upload had been left "processing…" for good).
    driver.get(f"{svc.base}/")
    faults(driver, {"/v1/scenes/": {"once": True, "status": 502, "statusText": "Bad Gateway", "type": "text/html",
                                    "body": "<html><body><h1>502 Bad Gateway</h1></body></html>"}})
    driver.find_element("id", "upload-archive").send_keys(str(archive))
    for _ in range(2):  # each click where the button is now (the progress bar, once shown, moves it down)
        driver.find_element("css selector", "#upload-form button").click()
    wait(lambda: "502: Bad Gateway; retrying" in text(driver, '[data-error-for="upload"]'), "the failed look", 30)
    go(driver, "#/jobs/elsewhere")
    go(driver, "#/")
    wait(lambda: "ready" in text(driver, "#upload-status"), "the scene to be ready", 60)
    assert not text(driver, '[data-error-for="upload"]')
    assert driver.execute_script("return document.querySelector('#upload-progress').value") == 1
    scene_id = wait(lambda: driver.execute_script("return document.querySelector('#job-scene').value"),
                    "the scene offered for editing", 20)
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        assert [s["id"] for s in client.get("/v1/scenes").json()["items"]] == [scene_id]

    # The API's validation shown beside the field it names: an empty prompt, an iterations count below 0.
    driver.find_element("id", "job-iterations").send_keys("-3")
    driver.find_element("css selector", "#job-form button").click()
    wait(lambda: text(driver, '[data-error-for="prompt"]') and text(driver, '[data-error-for="params.iterations"]'),
         "the 422 beside prompt and iterations", 20)
    assert "at least 1 character" in text(driver, '[data-error-for="prompt"]')
    assert "greater than or equal to" in text(driver, '[data-error-for="params.iterations"]')

    # A local edit with the tiny parameters.
    driver.find_element("id", "job-prompt").send_keys("a mic made of gold")
    driver.find_element("id", "job-mode-local").click()
    driver.find_element("id", "job-edit-words").send_keys("gold")
    driver.find_element("id", "job-iterations").clear()
    driver.find_element("css selector", "#job-form details summary").click()
    driver.find_element("id", "job-params").send_keys(json.dumps(PARAMS))
    driver.execute_script("window.requests = []")
    ActionChains(driver).double_click(driver.find_element("css selector", "#job-form button")).perform()
    wait(lambda: "#/jobs/" in driver.current_url, "the job page", 20)
    job_id = driver.current_url.rsplit("/", 1)[1]
    posts = requested(driver, "/v1/jobs", "POST")  # one job for a double click, sent with an Idempotency-Key
    assert len(posts) == 1 and posts[0]["headers"].get("Idempotency-Key"), posts
    assert driver.find_element("id", "job").is_displayed() and not driver.find_element("id", "home").is_displayed()

    # Progress advances on the page without a reload: the event stream drives it.
    seen: list[float] = []

    def finished() -> bool:
        seen.append(driver.execute_script("return document.querySelector('#job-overall-progress').value"))
        return text(driver, "#job-state") in ("succeeded", "failed", "canceled")

    wait_until(finished, 300, interval=0.1, what="the job to finish", processes=svc.processes)
    screenshot(driver, "job_finished")
    assert text(driver, "#job-state") == "succeeded", text(driver, "#job-message")
    assert len({v for v in seen if 0 < v < 1}) >= 2, seen  # several values in between, as the job ran
    assert driver.execute_script("return document.querySelector('#job-overall-progress').value") == 1
    assert text(driver, "#job-eta") == "–"  # (the API's 0 s left for it had read "finishing…")
    assert max(seen[:len(seen) // 2]) < 1, seen
    events = [e.get_attribute("data-event") for e in driver.find_elements("css selector", "#job-events li")]
    assert events[-1] == "succeeded" and "preview" in events and "stage_completed" in events, events

    # The media, fetched with the key: the turntable plays, the GLB is in <model-viewer>, the mask overlay shows.
    wait(lambda: driver.execute_script("const v = document.querySelector('#job-video');"
                                       "return !v.hidden && v.src.startsWith('blob:') && v.readyState >= 1"),
         "the turntable video to load", 30)
    wait(lambda: driver.execute_script("const m = document.querySelector('#job-model');"
                                       "return !m.hidden && m.src.startsWith('blob:') && m.loaded === true"),
         "model-viewer to load mesh.glb", 60)
    assert driver.execute_script("return document.querySelector('#job-mask').naturalWidth") > 0
    assert driver.execute_script("return document.querySelector('#job-preview').naturalWidth") > 0
    listed = {a.get_attribute("data-artifact") for a in driver.find_elements("css selector", "#job-artifacts a")}
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        assert listed == {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
        assert client.get(f"/v1/jobs/{job_id}").json()["scene_id"] == scene_id
    assert {"turntable.mp4", "mesh.glb", "mask_overlay.png", "edited_grid.safetensors"} <= listed
    screenshot(driver, "job_media")
    assert driver.execute_script("return window.cspViolations") == []  # the page's policy lets it all work
    leave_and_revisit_job_pages(driver, svc, token, scene_id, job_id, wait)

    # The job list shows it, and filtering by another state hides it.
    driver.get(f"{svc.base}/#/")
    wait(lambda: driver.find_elements("css selector", f'tr[data-job="{job_id}"]'), "the job in the list", 20)
    assert "100 %" in text(driver, f'tr[data-job="{job_id}"]')
    Select(driver.find_element("id", "filter-state")).select_by_visible_text("failed")
    wait(lambda: not driver.find_elements("css selector", f'tr[data-job="{job_id}"]'), "the filter", 20)
    screenshot(driver, "home")
    assert same_origin_only(driver, svc)


def leave_and_revisit_job_pages(driver, svc, token: str, scene_id: str, done_id: str, wait) -> None:
    """Jobs that fail to load, media that fail, and switching pages before one has loaded, on the succeeded job
    ``done_id`` and a second one made here (long, and canceled from its page)."""
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        other_id = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic made of silver",
                                                  "params": {**PARAMS, "iterations": 1000}}).json()["id"]
        job = lambda job_id: client.get(f"/v1/jobs/{job_id}").json()  # noqa: E731

        # A job id that names no job (and needs encoding) after a running job: its 404 on an empty page, Cancel
        # disabled, so that it cannot cancel the job shown before; that job's own Cancel cancels it.
        go(driver, f"#/jobs/{other_id}")
        wait(lambda: driver.find_element("id", "job-cancel").is_enabled(), "Cancel for the other job", 20)
        go(driver, "#/jobs/no such?job")
        wait(lambda: "404" in text(driver, '[data-error-for="stream"]'), "the unknown job's 404", 20)
        assert requested(driver, "/v1/jobs/no%20such%3Fjob")
        assert not (text(driver, "#job-title") or text(driver, "#job-meta") or text(driver, "#job-state"))
        assert not driver.find_element("id", "job-cancel").is_enabled()
        driver.find_element("id", "job-cancel").click()
        time.sleep(0.5)
        assert not job(other_id)["cancel_requested"]
        go(driver, f"#/jobs/{other_id}")
        wait(lambda: driver.find_element("id", "job-cancel").is_enabled(), "Cancel for the other job", 20)
        driver.find_element("id", "job-cancel").click()
        wait(lambda: job(other_id)["cancel_requested"], "the other job's cancel", 20)
        assert not job(done_id)["cancel_requested"]

    # Back on the succeeded job: its video, mask and 3D view again.
    go(driver, f"#/jobs/{done_id}")
    wait(lambda: set(shown_media(driver)) == {"#job-preview", "#job-mask", "#job-video", "#job-model"},
         "the media again", 30)

    # Leaving a job page that is still loading (its artifact list slow): nothing of it reaches the next page
    # (its artifacts, media and event stream).
    faults(driver, {f"/v1/jobs/{done_id}/artifacts": {"delay": 1500}})
    go(driver, f"#/jobs/{other_id}")
    wait(lambda: other_id in text(driver, "#job-meta"), "the other job's page", 20)
    driver.execute_script("window.requests = []")
    go(driver, f"#/jobs/{done_id}")
    time.sleep(0.3)
    go(driver, f"#/jobs/{other_id}")
    time.sleep(2)
    assert other_id in text(driver, "#job-meta")
    assert "turntable.mp4" not in text(driver, "#job-artifacts") and set(shown_media(driver)) <= {"#job-preview"}
    assert not streams(driver, done_id)

    # A file of the job gone from storage: its preview's 404 is shown beside the media, the artifacts are listed
    # all the same, and its timeline to the job's end; a download that fails says so.
    faults(driver, {"/artifacts/preview.png": {"status": 404, "type": "application/json",
                                                "body": json.dumps({"detail": "artifact missing from storage"})},
                    "/artifacts/edited_grid.safetensors": {"status": 404, "type": "application/json",
                                                           "body": json.dumps({"detail": "artifact gone"})}})
    go(driver, f"#/jobs/{done_id}")
    wait(lambda: "edited_grid.safetensors" in text(driver, "#job-artifacts"), "the artifacts listed", 20)
    assert driver.execute_script("return document.querySelector('#job-events li:last-child')?.dataset.event") \
        == "succeeded"
    assert "404: artifact missing from storage" in text(driver, '[data-error-for="media"]')
    assert not text(driver, '[data-error-for="stream"]')
    driver.find_element("css selector", 'a[data-artifact="edited_grid.safetensors"]').click()
    wait(lambda: "404: artifact gone" in text(driver, '[data-error-for="artifacts"]'), "the download's 404", 20)

    # A finished job's page reads its timeline once and opens no stream.
    go(driver, "#/")
    driver.execute_script("window.requests = []")
    go(driver, f"#/jobs/{done_id}")
    wait(lambda: text(driver, "#job-state") == "succeeded", "the finished job's page", 20)
    time.sleep(2.5)  # a retry interval
    assert len(requested(driver, f"/v1/jobs/{done_id}/events")) == 1 and not streams(driver, done_id)

    # The job read again at its terminal event (the page opened before it: its timeline read as empty) failing
    # once: the stream reconnects once, its terminal progress snapshot ends it (it had reconnected every 2 s for as
    # long as the page stayed open).
    faults(driver, {f"/v1/jobs/{done_id}/events": {"once": True, "status": 200, "type": "application/json",
                                                    "body": "[]"},
                    f"/v1/jobs/{done_id}$": {"skip": 1, "once": True, "status": 502, "statusText": "Bad Gateway",
                                              "type": "text/plain", "body": "Bad Gateway"}})
    go(driver, "#/")
    driver.execute_script("window.requests = []")
    go(driver, f"#/jobs/{done_id}")
    wait(lambda: len(streams(driver, done_id)) == 2, "the one reconnect", 20)
    time.sleep(5)  # two and a half retry intervals
    assert len(streams(driver, done_id)) == 2
    assert text(driver, "#job-state") == "succeeded"

    # Going on before a page has loaded: the job page left loading opens no event stream, and the home page left
    # loading (its scene list slow) does not poll the job list on the job page shown next. There (its timeline
    # read as empty: the page opened before the job ended), the stream's 401 (the key revoked meanwhile) ends it,
    # saying so.
    revoked = {"status": 401, "type": "application/json", "body": json.dumps({"detail": "API key revoked"})}
    faults(driver, {f"/v1/jobs/{other_id}/artifacts": {"delay": 1500}, "/v1/scenes?": {"delay": 1500},
                    f"/v1/jobs/{other_id}/events": {"skip": 1, **revoked},  # its timeline read, not its stream
                    f"/v1/jobs/{done_id}/events": {"once": True, "status": 200, "type": "application/json",
                                                   "body": "[]"},
                    f"/v1/jobs/{done_id}/events$": revoked})
    driver.execute_script("window.requests = []")
    go(driver, f"#/jobs/{other_id}")
    time.sleep(0.3)
    go(driver, "#/")
    time.sleep(0.3)
    go(driver, f"#/jobs/{done_id}")
    time.sleep(5)
    assert not streams(driver, other_id) and not requested(driver, "/v1/jobs?")
    assert len(streams(driver, done_id)) == 1
    assert "401: API key revoked; not reconnecting" in text(driver, '[data-error-for="stream"]')
    faults(driver, {})


def test_errors_of_any_shape_are_shown_and_unreadable_input_is_not_sent(live, browser):
    from selenium.webdriver.support.select import Select

    svc, token, _archive = live
    driver = browser
    error = lambda name: text(driver, f'[data-error-for="{name}"]')  # noqa: E731
    # A key that an HTTP header cannot carry is refused where it is entered (every request would throw on it).
    driver.get(f"{svc.base}/")
    driver.find_element("id", "api-key").send_keys("voxe_abc…")
    driver.find_element("css selector", "#key-form button").click()
    assert "not used" in text(driver, "#key-state")
    assert driver.execute_script("return sessionStorage.getItem('voxe.apiKey')") in (None, token)
    set_key(driver, svc, token)

    # Error answers that are no JSON (a plain-text 500, a proxy's HTML 502): their status line.
    for status, reason, kind, body in ((500, "Internal Server Error", "text/plain", "Internal Server Error"),
                                       (502, "Bad Gateway", "text/html", "<html><h1>502 Bad Gateway</h1></html>")):
        faults(driver, {"/v1/jobs?": {"status": status, "statusText": reason, "type": kind, "body": body}})
        driver.refresh()
        wait_until(lambda: error("list"), 10, what="the job list's error")
        assert error("list") == f"{status}: {reason}"

    # The scene list failing as the page loads (the API restarting, a proxy's 502): said beside the Scene field it
    # leaves empty, and loaded again with the job list (its error had been wiped at once by the job list's answer,
    # and the field left empty until a reload).
    faults(driver, {"/v1/scenes?": {"once": True, "status": 503, "statusText": "Service Unavailable",
                                    "type": "application/json", "body": json.dumps({"detail": "database busy"})}})
    driver.refresh()
    wait_until(lambda: error("scene_id"), 10, what="the scene list's error")
    assert error("scene_id") == "loading the scenes: 503: database busy; retrying"
    wait_until(lambda: not error("scene_id"), 10, what="the scene list loaded again")
    assert len(requested(driver, "/v1/scenes?")) == 2
    # The poll's job list answering late (a busy API) after the user filtered it: the filtered list stays (the late
    # answer had shown the jobs the filter hides until the next poll).
    stale = {"id": "stale-job", "prompt": "a mic", "mode": "global", "state": "canceled", "overall_progress": 0,
             "created_at": "2026-01-01T00:00:00Z"}
    faults(driver, {"/v1/jobs?limit=50": {"once": True, "delay": 1500, "status": 200, "type": "application/json",
                                          "body": json.dumps({"items": [stale], "total": 1})}})
    driver.refresh()
    wait_until(lambda: requested(driver, "/v1/jobs?"), 10, interval=0.05, what="the poll's job list")
    Select(driver.find_element("id", "filter-state")).select_by_visible_text("failed")
    shown = set()
    for _ in range(25):  # the late answer lands 1.5 s after it was sent, the next poll 3 s after that
        shown |= set(driver.execute_script("return [...document.querySelectorAll('#job-list tr[data-job]')]"
                                           ".map((row) => row.dataset.job)"))
        time.sleep(0.1)
    assert "stale-job" not in shown
    faults(driver, {})
    driver.refresh()

    # What the form cannot read is refused before anything is sent: a number typed wrong, parameters that are no
    # JSON object.
    driver.find_element("id", "job-prompt").send_keys("a mic made of gold")
    driver.find_element("id", "job-iterations").send_keys("2e")
    driver.execute_script("window.requests = []")
    driver.find_element("css selector", "#job-form button").click()
    wait_until(lambda: error("params.iterations"), 10, what="the refused iterations")
    assert error("params.iterations") == "not a number"
    driver.find_element("id", "job-iterations").clear()
    driver.find_element("id", "job-iterations").send_keys("10")
    driver.find_element("css selector", "#job-form details summary").click()
    driver.find_element("id", "job-params").send_keys("5")
    driver.find_element("css selector", "#job-form button").click()
    wait_until(lambda: "not a JSON object" in error("params"), 10, what="the refused parameters")
    assert not requested(driver, "/v1/jobs", "POST")

    # A submission whose answer is lost (a proxy's 504), sent again unchanged, keeps its Idempotency-Key; a body
    # changed by code (no input event, as the scene list's refresh changes the scene) gets a new one: the API
    # refuses a key reused with another body.
    driver.find_element("id", "job-params").clear()
    faults(driver, {"/v1/jobs$": {"method": "POST", "status": 504, "statusText": "Gateway Timeout",
                                  "type": "text/plain", "body": "Gateway Timeout"}})
    for _ in range(2):
        driver.find_element("css selector", "#job-form button").click()
        wait_until(lambda: "504" in error("job"), 10, what="the lost answer")
        driver.execute_script("document.querySelector('[data-error-for=job]').textContent = ''")
    driver.execute_script("document.querySelector('#job-prompt').value = 'a mic made of silver'")
    driver.find_element("css selector", "#job-form button").click()
    wait_until(lambda: "504" in error("job"), 10, what="the third lost answer")
    keys = [r["headers"]["Idempotency-Key"] for r in requested(driver, "/v1/jobs", "POST")]
    assert len(keys) == 3 and keys[0] == keys[1] != keys[2], keys
    faults(driver, {})

    # The API's 422 on keys typed into the parameters, one with a quote: both shown beside the parameters.
    driver.find_element("id", "job-params").clear()
    driver.find_element("id", "job-params").send_keys('{"bad\\"key": 1, "downsampel": 4}')
    driver.find_element("css selector", "#job-form button").click()
    wait_until(lambda: "downsampel" in error("params"), 10, what="the 422 beside the parameters")
    assert 'params.bad"key' in error("params")


def test_a_dataset_folder_uploads_with_its_images_paths(live, browser):
    """The folder picker sends each file named by its path in the folder (a NeRF-synthetic set's images sit in
    train/), and the folder's name names the scene: files picked one by one had come without their folders, and the
    upload's 422 said its images were not found."""
    svc, token, archive = live
    driver = browser
    set_key(driver, svc, token)
    driver.find_element("id", "upload-folder").send_keys(str(archive.parent / "mic_small"))
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: "ready" in text(driver, "#upload-status"), 60, what="the scene to be ready",
               processes=svc.processes)
    assert not text(driver, '[data-error-for="upload"]')
    scene_id = driver.execute_script("return document.querySelector('#job-scene').value")
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        scene = client.get(f"/v1/scenes/{scene_id}").json()
        assert (scene["name"], scene["format"], scene["image_count"]) == ("mic_small", "nerf_synthetic", 8)
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204  # the other tests expect their own only


def tetrahedron(folder: Path) -> Path:
    """A closed tetrahedron's OBJ in ``folder``: the smallest mesh an upload takes."""
    mesh = folder / "tetra.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    return mesh


def test_a_mesh_uploads_with_the_shading_and_up_axis_chosen(live, browser, tmp_path):
    """The upload form's mesh options reach the stored upload (the form had no field for them: every mesh was
    shaded "auto" and stood on its y axis)."""
    from selenium.webdriver.support.select import Select

    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    mesh = tetrahedron(tmp_path)
    Select(driver.find_element("id", "upload-mesh-shading")).select_by_value("baked")
    Select(driver.find_element("id", "upload-mesh-up-axis")).select_by_value("z")
    driver.find_element("id", "upload-files").send_keys(str(mesh))
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: "stored as" in text(driver, "#upload-status"), 30, what="the mesh stored",
               processes=svc.processes)
    assert not text(driver, '[data-error-for="upload"]')
    scene_id = text(driver, "#upload-status").split("stored as ")[1].split(";")[0]
    stored = Path(svc.env["VOXE_STORAGE_DIR"]) / "scenes" / scene_id / "upload.zip"
    with zipfile.ZipFile(stored) as archive:
        options = json.loads(archive.read("mesh/options.json"))
    assert (options["shading"], options["up_axis"]) == ("baked", "z")
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204  # the other tests expect their own only


def test_an_upload_name_is_counted_in_characters_as_the_api_counts_it(live, browser, tmp_path):
    """The name field's maxlength="255" counted UTF-16 units where the API counts characters: a name of 200 emoji,
    which the API takes, was cut to its first 127 as it was pasted, and the scene stored under the cut name, saying
    nothing. The name is kept whole; one over the API's 255 characters is refused beside it, before the upload."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    mesh = tetrahedron(tmp_path)
    field = driver.find_element("id", "upload-name")
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        scenes_before = client.get("/v1/scenes").json()["total"]  # (the module's earlier tests may keep theirs)

    def paste(name: str) -> None:
        field.clear()
        field.click()
        driver.execute_cdp_cmd("Input.insertText", {"text": name})  # as a paste or an IME types it

    paste("🎤" * 256)
    assert field.get_attribute("value") == "🎤" * 256
    driver.find_element("id", "upload-files").send_keys(str(mesh))
    driver.find_element("css selector", "#upload-form button").click()
    shown = lambda: text(driver, '[data-error-for="name"]')  # noqa: E731
    wait_until(shown, 10, what="the name's refusal")
    assert shown() == "String should have at most 255 characters (name)"
    assert not text(driver, "#upload-status") and not text(driver, '[data-error-for="upload"]')
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        assert client.get("/v1/scenes").json()["total"] == scenes_before  # nothing was uploaded
    paste("🎤" * 200)
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: "stored as" in text(driver, "#upload-status"), 30, what="the mesh stored",
               processes=svc.processes)
    assert not shown()
    scene_id = text(driver, "#upload-status").split("stored as ")[1].split(";")[0]
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        assert client.get(f"/v1/scenes/{scene_id}").json()["name"] == "🎤" * 200
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204  # the other tests expect their own only


def test_an_upload_answered_after_a_look_at_a_job_is_watched_until_its_scene_is_ready(live, browser, tmp_path):
    """An upload still being sent while the user looks at a job and comes back: its scene is watched until it is
    ready, and offered. The answer had been watched on the page it was sent from, gone by then, and the home page
    shown since had found nothing to watch when it opened: "processing…" for good, the scene offered nowhere."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    mesh = tetrahedron(tmp_path)
    # The upload leaves 4 s late, as a large one would take that long to send.
    driver.execute_script("const send = XMLHttpRequest.prototype.send;"
                          "XMLHttpRequest.prototype.send = function (body) {"
                          "  setTimeout(() => send.call(this, body), 4000); };")
    driver.find_element("id", "upload-files").send_keys(str(mesh))
    driver.find_element("css selector", "#upload-form button").click()
    go(driver, "#/jobs/elsewhere")
    go(driver, "#/")
    assert "stored as" not in text(driver, "#upload-status")  # not answered yet
    wait_until(lambda: "ready" in text(driver, "#upload-status"), 120, what="the scene to be ready",
               processes=svc.processes)
    scene_id = re.search(r"\((\S+)\): ready$", text(driver, "#upload-status"))[1]
    offered = "return [...document.querySelectorAll('#job-scene option')].map((option) => option.value)"
    wait_until(lambda: scene_id in driver.execute_script(offered), 10, what="the scene offered for editing")
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204  # the other tests expect their own only


def test_a_scene_s_warnings_are_listed_under_the_upload_once_it_is_ready(live, browser, tmp_path):
    """What the ingest loaded a mesh without (its .mtl not sent: the mesh loads grey) is listed under the upload's
    outcome, as the scene's ``warnings`` say: the page had said "ready" only, the user told nothing until a job's
    events. A later upload without warnings clears the list."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    mesh = tetrahedron(tmp_path)
    mesh.write_text("mtllib tetra.mtl\n" + mesh.read_text())
    driver.find_element("id", "upload-files").send_keys(str(mesh))
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: "ready" in text(driver, "#upload-status"), 120, what="the scene to be ready",
               processes=svc.processes)
    scene_id = re.search(r"\((\S+)\): ready$", text(driver, "#upload-status"))[1]
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        warnings = client.get(f"/v1/scenes/{scene_id}").json()["warnings"]
        assert len(warnings) == 1 and "tetra.mtl" in warnings[0], warnings
        listed = [item.text for item in driver.find_elements("css selector", "#upload-warnings li")]
        assert listed == [f"warning: {warning}" for warning in warnings]
        assert driver.find_element("id", "upload-warnings").is_displayed()
        screenshot(driver, "scene_warnings")
        driver.find_element("id", "upload-files").clear()
        (tmp_path / "plain").mkdir()
        driver.find_element("id", "upload-files").send_keys(str(tetrahedron(tmp_path / "plain")))
        driver.find_element("css selector", "#upload-form button").click()
        wait_until(lambda: re.search(r"\((\S+)\): ready$", text(driver, "#upload-status"))
                   and scene_id not in text(driver, "#upload-status"), 120, what="the second scene to be ready",
                   processes=svc.processes)
        assert not driver.find_elements("css selector", "#upload-warnings li")
        assert not driver.find_element("id", "upload-warnings").is_displayed()
        second = re.search(r"\((\S+)\): ready$", text(driver, "#upload-status"))[1]
        for made in (scene_id, second):  # the other tests expect their own only
            assert client.delete(f"/v1/scenes/{made}").status_code == 204


def test_an_upload_s_error_stays_shown_while_an_earlier_upload_s_scene_is_watched(live, browser, tmp_path):
    """The scene of an upload still processing is asked after every second, and each answer had cleared the error
    beside the upload field: a second upload refused (a .zip that is none) or sent with nothing chosen had its reason
    shown for a second, then wiped, the form saying nothing. The watch clears only a failure it said itself."""
    svc, token, _archive = live
    driver = browser
    error = lambda: text(driver, '[data-error-for="upload"]')  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/scenes/": scene_answered(PROCESSING_SCENE)})
    try:
        driver.find_element("id", "upload-files").send_keys(str(tetrahedron(tmp_path)))
        driver.find_element("css selector", "#upload-form button").click()
        wait_until(lambda: "stored as" in text(driver, "#upload-status"), 30, what="the upload stored")
        first = re.search(r"stored as (\S+);", text(driver, "#upload-status"))[1]
        wait_until(lambda: requested(driver, f"/v1/scenes/{first}"), 10, what="the scene asked after")
        driver.find_element("id", "upload-files").clear()
        (tmp_path / "bad.zip").write_text("not a zip")
        driver.find_element("id", "upload-archive").send_keys(str(tmp_path / "bad.zip"))
        driver.find_element("css selector", "#upload-form button").click()
        wait_until(error, 30, what="the second upload refused")
        refused = error()
        assert refused.startswith("422: archive 'bad.zip' is not a readable zip file"), refused
        polls = len(requested(driver, f"/v1/scenes/{first}"))
        wait_until(lambda: len(requested(driver, f"/v1/scenes/{first}")) >= polls + 2, 10, what="two more polls")
        assert error() == refused
        driver.find_element("id", "upload-archive").clear()
        driver.find_element("css selector", "#upload-form button").click()
        assert error() == "choose a zip, the dataset's folder, or its files"
        polls = len(requested(driver, f"/v1/scenes/{first}"))
        wait_until(lambda: len(requested(driver, f"/v1/scenes/{first}")) >= polls + 2, 10, what="two more polls")
        assert error() == "choose a zip, the dataset's folder, or its files"
    finally:
        faults(driver, {})
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        wait_until(lambda: client.get(f"/v1/scenes/{first}").json()["state"] != "processing", 120,
                   what="the first scene processed", processes=svc.processes)
        assert client.delete(f"/v1/scenes/{first}").status_code == 204  # the other tests expect their own only


def test_a_second_upload_s_status_is_not_written_over_by_the_first_s_outcome(live, browser, tmp_path):
    """Each upload's scene is watched until processed: a second upload sent while the first's scene was processing
    had its status ("stored as B; processing…") written over by the first's outcome ("scene A (A): ready"), and the
    first's warnings listed under it. The form reports the last upload sent only."""
    svc, token, _archive = live
    driver = browser
    status = lambda: text(driver, "#upload-status")  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/scenes/": scene_answered(PROCESSING_SCENE)})
    try:
        first, second = made = _upload_two(driver, tmp_path, status)
        ready = {"id": first, "name": "first", "state": "ready", "warnings": ["a warning of the first"]}
        polls = len(requested(driver, f"/v1/scenes/{first}"))
        faults(driver, {f"/v1/scenes/{first}": scene_answered(ready),  # (keys matched in sorted order: no prefix)
                        f"/v1/scenes/{second}": scene_answered(PROCESSING_SCENE)})
        wait_until(lambda: len(requested(driver, f"/v1/scenes/{first}")) > polls, 10, what="the first told ready")
        polls = len(requested(driver, f"/v1/scenes/{second}"))
        wait_until(lambda: len(requested(driver, f"/v1/scenes/{second}")) >= polls + 2, 10, what="two more polls")
        assert status() == f"stored as {second}; processing…", status()
        assert not driver.find_elements("css selector", "#upload-warnings li")
    finally:
        faults(driver, {})
    wait_until(lambda: status() == f"scene second ({second}): ready", 120, what="the second scene ready",
               processes=svc.processes)
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        wait_until(lambda: client.get(f"/v1/scenes/{first}").json()["state"] != "processing", 120,
                   what="the first scene processed", processes=svc.processes)
        for scene_id in made:  # the other tests expect their own only
            assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204


def _upload_two(driver, tmp_path, status) -> list[str]:
    """Upload two tetrahedra named first and second; their scene ids."""
    made = []
    for name in ("first", "second"):
        (tmp_path / name).mkdir()
        driver.find_element("id", "upload-files").clear()
        driver.find_element("id", "upload-files").send_keys(str(tetrahedron(tmp_path / name)))
        driver.find_element("id", "upload-name").clear()
        driver.find_element("id", "upload-name").send_keys(name)
        driver.find_element("css selector", "#upload-form button").click()
        wait_until(lambda: (found := re.search(r"stored as (\S+);", status())) and found[1] not in made, 30,
                   what=f"the {name} upload stored")
        made.append(re.search(r"stored as (\S+);", status())[1])
    driver.find_element("id", "upload-name").clear()
    return made


def test_an_earlier_upload_s_failed_ingest_is_listed_under_the_form(live, browser, tmp_path):
    """The form reports the last upload sent: a first upload whose ingest failed once a second was sent had its
    failure said nowhere (its scene just never offered). It is listed under the form, naming the scene and why."""
    svc, token, _archive = live
    driver = browser
    status = lambda: text(driver, "#upload-status")  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/scenes/": scene_answered(PROCESSING_SCENE)})
    try:
        first, second = made = _upload_two(driver, tmp_path, status)
        failed = {"id": first, "name": "first", "state": "failed", "error": "the mesh has no faces"}
        faults(driver, {f"/v1/scenes/{first}": scene_answered(failed),
                        f"/v1/scenes/{second}": scene_answered(PROCESSING_SCENE)})
        wait_until(lambda: driver.find_elements("css selector", "#upload-earlier li"), 10, what="the failure listed")
        listed = [item.text for item in driver.find_elements("css selector", "#upload-earlier li")]
        assert listed == [f"scene first ({first}) failed: the mesh has no faces"], listed
        assert driver.find_element("id", "upload-earlier").is_displayed()
        assert status() == f"stored as {second}; processing…", status()
        assert not text(driver, '[data-error-for="upload"]')
    finally:
        faults(driver, {})
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        for scene_id in made:  # the other tests expect their own only
            wait_until(lambda: client.get(f"/v1/scenes/{scene_id}").json()["state"] != "processing", 120,
                       what="the scene processed", processes=svc.processes)
            assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204
    driver.refresh()


def test_every_upload_still_processing_is_watched_again_after_a_look_at_a_job_or_a_reload(live, browser, tmp_path):
    """Two uploads still processing: back from a job's page, only the last one's scene had been watched again (the
    first never offered once ready, until the page was loaded again), and after a reload neither. Both are now watched
    until they are processed, then offered."""
    svc, token, _archive = live
    driver = browser
    status = lambda: text(driver, "#upload-status")  # noqa: E731
    offered = "return [...document.querySelectorAll('#job-scene option')].map((option) => option.value)"
    set_key(driver, svc, token)
    faults(driver, {"/v1/scenes/": scene_answered(PROCESSING_SCENE)})
    try:
        made = _upload_two(driver, tmp_path, status)
        go(driver, "#/jobs/elsewhere")
        driver.execute_script("window.requests = []")
        go(driver, "#/")
        for scene_id in made:
            wait_until(lambda: len(requested(driver, f"/v1/scenes/{scene_id}")) >= 2, 10,
                       what=f"{scene_id} watched again after a look at a job")
        listed = {"items": [{"id": scene_id, "name": "tetra", "state": "processing"} for scene_id in made],
                  "next_cursor": None}
        faults(driver, {"/v1/scenes/": scene_answered(PROCESSING_SCENE), "/v1/scenes?": scene_answered(listed)})
        driver.refresh()
        for scene_id in made:
            wait_until(lambda: len(requested(driver, f"/v1/scenes/{scene_id}")) >= 2, 10,
                       what=f"{scene_id} watched after a reload")
    finally:
        faults(driver, {})
    for scene_id in made:
        wait_until(lambda: scene_id in driver.execute_script(offered), 120, what=f"{scene_id} offered once ready",
                   processes=svc.processes)
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        for scene_id in made:  # the other tests expect their own only
            assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204
    driver.refresh()


def test_an_upload_answered_with_no_scene_says_so(live, browser, tmp_path):
    """An upload answered 200 with no scene (a proxy's login page it was redirected to) is said beside the upload: its
    answer had been parsed unguarded, an unhandled rejection left the form at "100 % sent". Sent again, it keeps its
    Idempotency-Key: it may have been stored."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    mesh = tetrahedron(tmp_path)
    driver.execute_script("window.rejections = [];"
                          "addEventListener('unhandledrejection', (e) => rejections.push(String(e.reason)));"
                          "window.keys = [];"
                          "XMLHttpRequest.prototype.setRequestHeader = ((set) => function (name, value) {"
                          " if (name === 'Idempotency-Key') keys.push(value); set.call(this, name, value); })"
                          "(XMLHttpRequest.prototype.setRequestHeader);"
                          "XMLHttpRequest.prototype.open = ((open) => function () { open.call(this, 'GET', '/'); })"
                          "(XMLHttpRequest.prototype.open);")
    driver.find_element("id", "upload-files").send_keys(str(mesh))
    for _ in range(2):
        driver.find_element("css selector", "#upload-form button").click()
        wait_until(lambda: text(driver, '[data-error-for="upload"]'), 10, what="the answer refused")
        assert text(driver, '[data-error-for="upload"]') == ("200: the answer (text/html; charset=utf-8) is no scene: "
                                                             "the upload may not have been stored")
        assert driver.execute_script("return window.rejections") == []
        assert driver.find_element("css selector", "#upload-form button").is_enabled()
        assert driver.execute_script("return document.querySelector('#upload-progress').hidden")
    keys = driver.execute_script("return window.keys")
    assert len(keys) == 2 and keys[0] == keys[1], keys
    driver.refresh()


def test_an_edit_answered_with_no_job_says_so(live, browser):
    """An edit's submission answered 2xx with no job, a proxy's HTML login page or a JSON answer without an id, is
    said beside the form, naming what came back, and sent again with the same Idempotency-Key (it may have been
    created): the HTML had shown JSON.parse's "SyntaxError: Unexpected token…", the JSON opened "#/jobs/undefined"."""
    svc, token, _archive = live
    driver = browser
    error = lambda: text(driver, '[data-error-for="job"]')  # noqa: E731
    set_key(driver, svc, token)
    driver.execute_script("window.rejections = [];"
                          "addEventListener('unhandledrejection', (e) => rejections.push(String(e.reason)));")
    driver.find_element("id", "job-prompt").send_keys("a mic made of gold")
    for kind, body, said in (("text/html; charset=utf-8", "<html><body><form>Sign in</form></body></html>",
                              "200: the answer (text/html; charset=utf-8) is no JSON: it may have been created "
                              "(sent again, it is found)"),
                             ("application/json", '{"ok": true}',
                              '200: the answer ({"ok": true}) is no job: it may have been created (sent again, it is '
                              'found)')):
        faults(driver, {"/v1/jobs$": {"method": "POST", "status": 200, "type": kind, "body": body}})
        driver.find_element("css selector", "#job-form button").click()
        wait_until(error, 10, what="the answer refused")
        assert error() == said
        assert driver.execute_script("return location.hash") in ("", "#/")
        assert driver.find_element("css selector", "#job-form button").is_enabled()
    assert driver.execute_script("return window.rejections") == []
    keys = [r["headers"]["Idempotency-Key"] for r in requested(driver, "/v1/jobs", "POST")]
    assert len(keys) == 2 and keys[0] == keys[1], keys
    faults(driver, {})
    driver.refresh()


def test_a_scene_chosen_then_deleted_leaves_one_offered_chosen(live, browser):
    """The scene chosen for an edit, and as the job list's filter, deleted meanwhile: the next look at the scenes
    chooses one offered, and the filter "all" (both had shown nothing chosen, the edit sent with no scene)."""
    from selenium.webdriver.support.select import Select

    svc, token, _archive = live
    driver = browser
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    scene = lambda i: {"id": f"scene-{i}", "name": f"scene {i}", "state": "ready"}  # noqa: E731
    no_jobs = answer({"items": [], "total": 0})
    set_key(driver, svc, token)
    faults(driver, {"/v1/scenes?": answer({"items": [scene(1), scene(2)], "total": 2}), "/v1/jobs?": no_jobs})
    driver.refresh()
    offered = "return [...document.querySelectorAll('#job-scene option')].map((option) => option.value)"
    wait_until(lambda: driver.execute_script(offered) == ["scene-1", "scene-2"], 10, what="the scenes offered")
    Select(driver.find_element("id", "job-scene")).select_by_value("scene-2")
    Select(driver.find_element("id", "filter-scene")).select_by_value("scene-2")
    faults(driver, {"/v1/scenes?": answer({"items": [scene(1)], "total": 1}), "/v1/jobs?": no_jobs})
    go(driver, "#/jobs/elsewhere")
    go(driver, "#/")
    wait_until(lambda: driver.execute_script(offered) == ["scene-1"], 10, what="the scenes offered again")
    chosen = "return ['#job-scene', '#filter-scene'].map((s) => [document.querySelector(s).value," \
             " document.querySelector(s).selectedIndex])"
    assert driver.execute_script(chosen) == [["scene-1", 0], ["", 0]]
    faults(driver, {})


def test_the_job_list_pages_and_every_scene_is_offered(live, browser):
    """A key with more jobs than a page (50) steps to its older ones and back, and every scene is offered, past the
    API's largest page (200): the oldest had been out of reach. Each page is read after the last one shown (its
    next_cursor): by offset, a job created while the first page was shown made "older" show its last job again."""
    svc, token, _archive = live
    driver = browser
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    scene = lambda i: {"id": f"scene-{i}", "name": f"scene {i}", "state": "ready"}  # noqa: E731
    job = lambda i: {"id": f"job-{i}", "prompt": "a mic", "mode": "global", "state": "succeeded",  # noqa: E731
                     "overall_progress": 1, "created_at": "2026-01-01T00:00:00Z"}
    page = lambda items, total, offset, after: answer(  # noqa: E731
        {"items": items, "total": total, "limit": 50, "offset": offset, "next_cursor": after})
    set_key(driver, svc, token)
    # (a job created while the first page is shown: read by offset 50, the older page had shown job-49 again)
    faults(driver, {"/v1/scenes?cursor=after-scene-199&limit=200": answer(
                        {"items": [scene(200)], "total": 201, "next_cursor": None}),
                    "/v1/scenes?limit=200": answer(
                        {"items": [scene(i) for i in range(200)], "total": 201, "next_cursor": "after-scene-199"}),
                    "/v1/jobs?cursor=after-job-49&limit=50": page([job(50)], 52, 51, None),
                    "/v1/jobs?limit=50": page([job(i) for i in range(50)], 51, 0, "after-job-49")})
    driver.refresh()
    rows = "return [...document.querySelectorAll('#job-list tr[data-job]')].map((row) => row.dataset.job)"
    wait_until(lambda: len(driver.execute_script(rows)) == 50, 10, what="the first page of jobs")
    assert text(driver, "#jobs-range") == "1–50 of 51"
    assert not driver.find_element("id", "jobs-newer").is_enabled()
    offered = "return [...document.querySelectorAll(arguments[0])].map((option) => option.value)"
    wait_until(lambda: "scene-200" in driver.execute_script(offered, "#job-scene option"), 10, what="every scene")
    assert len(driver.execute_script(offered, "#job-scene option")) == 201
    assert len(driver.execute_script(offered, "#filter-scene option")) == 202  # and "all"
    driver.find_element("id", "jobs-older").click()
    wait_until(lambda: driver.execute_script(rows) == ["job-50"], 10, what="the older page")
    assert text(driver, "#jobs-range") == "52–52 of 52"  # where it stands now, the job created meanwhile first
    assert not driver.find_element("id", "jobs-older").is_enabled()
    time.sleep(3.5)  # the poll keeps the page shown
    assert driver.execute_script(rows) == ["job-50"]
    driver.find_element("id", "jobs-newer").click()
    wait_until(lambda: len(driver.execute_script(rows)) == 50, 10, what="the newer page again")
    # The older page emptied meanwhile (a job deleted): the poll shows the page before it, not an empty one.
    driver.find_element("id", "jobs-older").click()
    wait_until(lambda: driver.execute_script(rows) == ["job-50"], 10, what="the older page")
    faults(driver, {"/v1/jobs?cursor=after-job-49&limit=50": page([], 50, 50, None),
                    "/v1/jobs?limit=50": page([job(i) for i in range(50)], 50, 0, None)})
    wait_until(lambda: len(driver.execute_script(rows)) == 50, 10, what="the last page")
    assert text(driver, "#jobs-range") == "1–50 of 50" and not driver.find_element("id", "jobs-older").is_enabled()
    faults(driver, {})


def running_job(job_id: str, **fields) -> dict:
    """A running job's fields as GET /v1/jobs/{id} answers them, ``fields`` replacing its own."""
    return {"id": job_id, "scene_id": "s", "prompt": "a mic", "mode": "global", "edit_words": [],
            "models": {"sds": "tiny"}, "device": "cpu", "state": "running", "stage": "edit", "completed_stages": [],
            "progress": 0.5, "iteration": 2, "total": 4, "overall_progress": 0.5, "eta_seconds": 1,
            "overall_eta_seconds": 2, "losses": {}, "message": None, "preview_url": None, "error": None,
            "cancel_requested": False, "created_at": "2026-01-01T00:00:00Z", **fields}


def test_a_job_page_streams_only_the_events_after_its_timeline(live, browser):
    """The timeline so far is read once and listed; the stream sends what follows (Last-Event-ID): replayed through
    the stream, each past preview had been downloaded again, and the artifacts listed again per past artifact, at
    every opening of the page."""
    svc, token, _archive = live
    driver = browser
    job = running_job("replay", stage="export", completed_stages=["reconstruct", "edit"], iteration=1, total=2,
                      overall_progress=0.9, overall_eta_seconds=1,
                      preview_url="/v1/jobs/replay/artifacts/preview.png")
    kinds = ["stage_started"] + ["preview"] * 10 + ["stage_completed"] + ["artifact"] * 4 + ["preview", "succeeded"]
    timeline = [{"id": i, "kind": kind, "stage": "edit", "detail": {"preview": "preview.png", "artifact": "a.png"}
                 .get(kind)} for i, kind in enumerate(kinds, 1)]
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    artifact = {"name": "a.png", "url": "/v1/jobs/replay/artifacts/a.png", "size": 1, "kind": "image",
                "sha256": "0" * 64}
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/replay$": answer(json.dumps(job)),
                    "/v1/jobs/replay/artifacts$": answer(json.dumps([artifact])),
                    "/v1/jobs/replay/artifacts/": answer("", "image/png"),
                    "/v1/jobs/replay/events": {"timeline": timeline, "recorded": 16}})
    driver.execute_script("window.requests = []")
    go(driver, "#/jobs/replay")
    listed = "return [...document.querySelectorAll('#job-events li')].map((item) => item.dataset.event)"
    wait_until(lambda: driver.execute_script(listed)[-1:] == ["succeeded"], 10, what="the job's end")
    assert driver.execute_script(listed) == kinds
    assert len(requested(driver, "/artifacts/preview.png")) == 2  # the page's, the new preview's
    assert len([r for r in requested(driver, "/artifacts") if r["url"].endswith("/artifacts")]) == 2  # and the end's
    assert [r["headers"].get("Last-Event-ID") for r in streams(driver, "replay")] == ["16"]
    faults(driver, {})


def test_an_answer_of_another_shape_is_said_not_met_as_a_type_error(live, browser):
    """A 2xx JSON answer of another shape than the API's (a proxy's own JSON), or an empty one, is said where it was
    asked for, quoted: the job list had shown "TypeError: Cannot read properties of undefined (reading 'length')", a
    cancel answered with nothing "TypeError: Cannot read properties of null (reading 'state')"."""
    svc, token, _archive = live
    driver = browser
    error = lambda name: text(driver, f'[data-error-for="{name}"]')  # noqa: E731
    answer = lambda body: {"status": 200, "type": "application/json", "body": body}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs?": answer('{"ok": true}'), "/v1/scenes?": answer('{"items": null}')})
    driver.refresh()
    wait_until(lambda: error("list") and error("scene_id"), 10, what="the answers said")
    assert error("list") == '200: the answer ({"ok": true}) is no page of jobs'
    assert error("scene_id") == 'loading the scenes: 200: the answer ({"items": null}) is no page of scenes; retrying'
    faults(driver, {"/v1/jobs/shapeless$": answer(json.dumps(running_job("shapeless"))),
                    "/v1/jobs/shapeless/artifacts$": answer("[]"),
                    "/v1/jobs/shapeless/events": {"recorded": 0, "open": True, "timeline": []},
                    "/v1/jobs/shapeless/cancel": {"method": "POST", **answer("")}})
    go(driver, "#/jobs/shapeless")
    wait_until(lambda: driver.find_element("id", "job-cancel").is_enabled(), 10, what="Cancel")
    driver.find_element("id", "job-cancel").click()
    wait_until(lambda: error("cancel"), 10, what="the cancel's answer said")
    assert error("cancel") == "200: the answer (empty) is no job"
    assert text(driver, "#job-state") == "running"
    faults(driver, {})


def test_a_retry_after_is_waited_for_and_said(live, browser):
    """An answer with Retry-After (a 429, a 503) is asked again no sooner than it says, saying so: the job list had
    been asked again every 3 s, the job page's first reads 2 s after their failure."""
    svc, token, _archive = live
    driver = browser
    error = lambda name: text(driver, f'[data-error-for="{name}"]')  # noqa: E731
    throttled = lambda seconds: {  # noqa: E731
        "status": 429, "statusText": "Too Many Requests", "type": "application/json",
        "body": json.dumps({"detail": "slow down"}), "headers": {"Retry-After": seconds}}
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs?": throttled("7")})
    driver.refresh()
    wait_until(lambda: error("list"), 10, what="the 429 said")
    assert error("list") == "429: slow down (the server asks to wait 7 s)"
    wait_until(lambda: len(requested(driver, "/v1/jobs?")) == 2, 12, interval=0.1, what="the list asked again")
    first, second = (r["at"] for r in requested(driver, "/v1/jobs?"))
    assert second - first >= 7000
    faults(driver, {"/v1/jobs/throttled": throttled("5")})
    go(driver, "#/jobs/throttled")
    wait_until(lambda: len(requested(driver, "/v1/jobs/throttled/events")) == 2, 10, interval=0.1,
               what="the job asked again")
    assert error("stream") == "loading the job: 429: slow down (the server asks to wait 5 s); retrying"
    first, second = (r["at"] for r in requested(driver, "/v1/jobs/throttled/events"))
    assert second - first >= 5000
    faults(driver, {})


def test_a_far_off_retry_after_is_waited_for_minutes_at_most_and_said_so(live, browser):
    """A Retry-After of weeks or years (a proxy's: seconds past setTimeout()'s 2^31-1 ms, an HTTP date in 2100) is
    waited for a few minutes, and the page says that wait: setTimeout() had fired at once, the page asking again
    hundreds of times a second while saying it waits 24 days."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    for retry_after in ("2147484", "Fri, 01 Jan 2100 00:00:00 GMT"):
        faults(driver, {"/v1/jobs?": {"status": 429, "statusText": "Too Many Requests", "type": "application/json",
                                      "body": json.dumps({"detail": "slow down"}),
                                      "headers": {"Retry-After": retry_after}}})
        driver.refresh()
        wait_until(lambda: text(driver, '[data-error-for="list"]'), 10, what="the 429 said")
        time.sleep(3)  # a poll interval: the list is not asked again in it
        assert len(requested(driver, "/v1/jobs?")) == 1, retry_after
        assert text(driver, '[data-error-for="list"]') == (
            "429: slow down (the server asks to wait 5 min 0 s or more; this page waits 5 min 0 s at most)")
    faults(driver, {})


def test_a_hidden_page_polls_nothing_until_it_shows(live, browser):
    """While the tab is hidden (Page Visibility) the job list is not asked for, and it is asked as soon as the tab
    shows again: it had been asked every 3 s for a tab nobody looked at."""
    svc, token, _archive = live
    driver = browser
    visible = """const hidden = !arguments[0];
                 Object.defineProperty(document, "hidden", { configurable: true, get: () => hidden });
                 Object.defineProperty(document, "visibilityState", { configurable: true,
                                                                      get: () => hidden ? "hidden" : "visible" });
                 document.dispatchEvent(new Event("visibilitychange"));"""
    set_key(driver, svc, token)
    wait_until(lambda: requested(driver, "/v1/jobs?"), 10, what="the job list")
    driver.execute_script(visible, False)
    time.sleep(0.5)  # (a look already sent)
    driver.execute_script("window.requests = []")
    time.sleep(7)  # two polls' time
    assert not requested(driver, "/v1/jobs?")
    driver.execute_script(visible, True)
    wait_until(lambda: requested(driver, "/v1/jobs?"), 1, interval=0.05, what="the list asked once shown")


def test_a_refused_key_is_not_asked_with_again_until_another_is_used(live, browser, tmp_path):
    """With no key or one the API refuses (401, 403), the job list and the scenes are asked once, and the key field
    says a key is needed: both had been asked again every 3 s for as long as the page stayed open, refused each time.
    An upload's scene gone (404) is not watched again either: it had been asked every 30 s for good; the upload's status
    says it was deleted (a "checking scene …: 404" error had stayed beside the upload field for good)."""
    svc, token, _archive = live
    driver = browser
    error = lambda name: text(driver, f'[data-error-for="{name}"]')  # noqa: E731
    for key in ("", "voxe_not_a_key"):
        driver.get(f"{svc.base}/")
        driver.find_element("id", "api-key").clear()
        driver.find_element("id", "api-key").send_keys(key)
        driver.find_element("css selector", "#key-form button").click()
        wait_until(lambda: "enter one" in text(driver, "#key-state"), 10, what="the key refused")
        refused = "this key is refused" if key else "a key is needed"
        assert text(driver, "#key-state") == f"{refused}: enter one and Use it"
        assert error("list").startswith("401: ") and not error("scene_id").endswith("retrying")
        driver.execute_script("window.requests = []")
        time.sleep(7)  # two polls' time
        assert not requested(driver, "/v1/jobs?") and not requested(driver, "/v1/scenes?")
    set_key(driver, svc, token)
    wait_until(lambda: text(driver, "#jobs-range"), 10, what="the job list with the key")
    assert not error("list")

    faults(driver, {"/v1/scenes/": {"status": 404, "type": "application/json",
                                    "body": json.dumps({"detail": "scene not found"})}})
    driver.execute_script("window.requests = []")
    driver.find_element("id", "upload-files").send_keys(str(tetrahedron(tmp_path)))
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: "no longer watched" in text(driver, "#upload-status"), 10, what="the scene gone said")
    scene_id = re.search(r"^scene (\S+) was deleted", text(driver, "#upload-status"))[1]
    assert text(driver, "#upload-status") == (f"scene {scene_id} was deleted before its ingest ended (404: scene not "
                                              "found); no longer watched")
    assert error("upload") == ""  # "checking scene …: 404: scene not found; not asked again" had stayed there
    time.sleep(3)  # the watch's first retry had come 2 s after its failure
    assert len(requested(driver, "/v1/scenes/")) == 1
    faults(driver, {})
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        wait_until(lambda: client.get(f"/v1/scenes/{scene_id}").json()["state"] != "processing", 60,
                   what="the scene's ingest", processes=svc.processes)
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204  # the other tests expect their own only


def test_an_api_with_authentication_off_refusing_the_page_does_not_ask_for_a_key(live, browser, tmp_path,
                                                                                 monkeypatch):
    """With authentication off the API serves its own machine only: the page opened through a proxy (or on another
    address) is refused 401 whatever key it sends. The page had said "a key is needed: enter one and Use it", and
    then, of any key entered, "this key is refused"."""
    from fastapi.testclient import TestClient

    from service_helpers import reset_service_caches, service_env

    for key, value in service_env(tmp_path, VOXE_AUTH="off").items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from api.main import create_app

    with TestClient(create_app()) as client:  # the API's own answer to a relayed request
        refusal = client.get("/v1/jobs", headers={"X-Forwarded-For": "192.0.2.7"})
    reset_service_caches()
    assert refusal.status_code == 401
    svc, token, _archive = live
    driver = browser
    answer = {"status": 401, "type": "application/json", "body": refusal.text}
    for key in ("", token):
        driver.get(f"{svc.base}/")
        faults(driver, {"/v1/jobs?": answer, "/v1/scenes?": answer})
        use_key(driver, key)
        wait_until(lambda: "authentication is off" in text(driver, "#key-state"), 10, what="the refusal said")
        assert text(driver, "#key-state") == "no key is asked (authentication is off): see why beside the job list"
        assert text(driver, '[data-error-for="list"]') == f"401: {refusal.json()['detail']}"
    faults(driver, {})


def test_an_api_serving_the_page_without_a_key_says_none_is_needed(live, browser):
    """With authentication off the API serves the page's requests sent without a key: the key field had said "no key"
    all the same, as if one were missing."""
    svc, _token, _archive = live
    driver = browser
    empty = {"status": 200, "type": "application/json",
             "body": json.dumps({"items": [], "total": 0, "limit": 50, "offset": 0, "next_cursor": None})}
    driver.get(f"{svc.base}/")
    use_key(driver, "")
    faults(driver, {"/v1/jobs?": empty, "/v1/scenes?": empty})  # as an API with authentication off answers
    driver.refresh()
    wait_until(lambda: "authentication is off" in text(driver, "#key-state"), 10, what="the key field's state")
    assert text(driver, "#key-state") == "no key needed: authentication is off"
    assert text(driver, "#jobs-range") == "no jobs"
    faults(driver, {})


def test_a_job_page_opened_in_a_new_tab_asks_for_the_key_and_loads_with_it(live, browser):
    """A job's link opened in a new tab (a middle click) has no key: sessionStorage is the tab's, and the key is kept
    nowhere longer. The job page refused 401 now says a key is needed, as the home page does, and loads once one is
    used; it had said "no key" only, beside the API's 401."""
    svc, token, _archive = live
    driver = browser
    driver.get(f"{svc.base}/")
    driver.execute_script("sessionStorage.removeItem('voxe.apiKey')")  # a new tab's storage
    driver.get(f"{svc.base}/#/jobs/not-a-job")
    driver.refresh()
    wait_until(lambda: text(driver, '[data-error-for="stream"]').startswith("401: missing API key"), 10,
               what="the job page refused")
    assert text(driver, "#key-state") == "a key is needed: enter one and Use it"
    use_key(driver, token)
    wait_until(lambda: text(driver, '[data-error-for="stream"]').startswith("404: "), 10,
               what="the job asked for with the key")
    assert text(driver, "#key-state") == "key set for this session"


def test_an_artifact_s_link_is_its_file_and_a_middle_click_downloads_it_with_the_key(live, browser):
    """An artifact's link had the href "#": a middle click (or "Open link in new tab") opened the home page in a new
    tab, saying nothing. It is the file's URL now (a new tab has no key: with authentication on, the API says the
    key it needs), and a middle click downloads it with the key, as a click does."""
    svc, token, _archive = live
    driver = browser
    job = running_job("aux", state="succeeded", stage="export", completed_stages=["reconstruct", "edit", "export"])
    artifact = {"name": "a.png", "url": "/v1/jobs/aux/artifacts/a.png", "size": 1, "kind": "image", "sha256": "0" * 64}
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/aux$": answer(json.dumps(job)),
                    "/v1/jobs/aux/artifacts$": answer(json.dumps([artifact])),
                    "/v1/jobs/aux/artifacts/": answer("", "image/png"),
                    "/v1/jobs/aux/events": {"recorded": 1, "timeline": [{"id": 1, "kind": "succeeded"}]}})
    go(driver, "#/jobs/aux")
    wait_until(lambda: driver.find_elements("css selector", '#job-artifacts a[data-artifact="a.png"]'), 10,
               what="the artifact listed")
    link = driver.find_element("css selector", '#job-artifacts a[data-artifact="a.png"]')
    assert link.get_attribute("href") == f"{svc.base}{artifact['url']}"
    driver.execute_script("window.requests = []")
    middle = """const click = new MouseEvent("auxclick", { button: 1, bubbles: true, cancelable: true });
                arguments[0].dispatchEvent(click);
                return click.defaultPrevented;"""
    assert driver.execute_script(middle, link)  # no new tab opened
    wait_until(lambda: requested(driver, artifact["url"]), 10, what="the download")
    assert requested(driver, artifact["url"])[0]["headers"]["Authorization"] == f"Bearer {token}"
    faults(driver, {})


def test_a_key_used_while_the_refused_one_s_job_list_is_read_is_not_said_refused(live, browser):
    """The key-less page's job list still on its way when a good key is used: that page's scenes, refused for no
    key, had named the good key "refused", the page showing that key's jobs beside it."""
    svc, token, _archive = live
    driver = browser
    driver.get(f"{svc.base}/")
    use_key(driver, "")
    faults(driver, {"/v1/jobs?": {"once": True, "delay": 2000}})  # the key-less page's job list slow
    driver.refresh()
    wait_until(lambda: text(driver, '[data-error-for="scene_id"]').startswith("loading the scenes: 401"), 10,
               what="the scenes refused", interval=0.05)
    use_key(driver, token)
    wait_until(lambda: text(driver, "#jobs-range"), 10, what="the job list with the key")
    time.sleep(2)  # the slow list's answer (aborted) due
    assert text(driver, "#key-state") == "key set for this session"
    faults(driver, {})


def test_an_upload_s_scene_refused_for_a_mistyped_key_is_watched_again_once_a_good_key_is_used(live, browser,
                                                                                                tmp_path):
    """A key mistyped while a new scene's ingest is watched, then corrected: the watch goes on with the good key
    until the scene is ready. A 401 had ended it for good: "processing…", the scene offered only on a reload."""
    svc, token, _archive = live
    driver = browser
    error = lambda name: text(driver, f'[data-error-for="{name}"]')  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/scenes/": {"delay": 3000}})  # the watch's first look slow: the mistyped key meets it
    driver.find_element("id", "upload-files").send_keys(str(tetrahedron(tmp_path)))
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: "stored as" in text(driver, "#upload-status"), 20, what="the upload stored")
    scene_id = re.search(r"stored as (\S+);", text(driver, "#upload-status"))[1]
    use_key(driver, "voxe_not_a_key")
    faults(driver, {})
    wait_until(lambda: error("upload").startswith(f"checking scene {scene_id}: 401: "), 10, what="the watch refused")
    use_key(driver, token)
    wait_until(lambda: "ready" in text(driver, "#upload-status"), 60, what="the scene ready",
               processes=svc.processes)
    assert not error("upload")
    offered = "return [...document.querySelectorAll('#job-scene option')].map((option) => option.value)"
    wait_until(lambda: scene_id in driver.execute_script(offered), 10, what="the scene offered for editing")
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204  # the other tests expect their own only


def test_an_upload_s_progress_is_not_read_out_at_every_step(live, browser):
    """The share of an upload sent is the progress bar's value, not the status line's text: that line is a live
    region, and a screen reader queued each of its changes, many a second, before it could say "stored as…"."""
    svc, token, archive = live
    driver = browser
    set_key(driver, svc, token)
    driver.execute_script("""window.spoken = [];
        const observer = new MutationObserver(() => {
          for (const region of document.querySelectorAll("[aria-live]")) {
            if (region.textContent) spoken.push(region.textContent);
          }
        });
        observer.observe(document.body, { subtree: true, childList: true, characterData: true });""")
    driver.find_element("id", "upload-archive").send_keys(str(archive))
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: "stored as" in text(driver, "#upload-status"), 30, what="the upload stored")
    scene_id = re.search(r"stored as (\S+);", text(driver, "#upload-status"))[1]
    assert [line for line in driver.execute_script("return spoken") if "sent" in line] == []
    assert driver.find_element("id", "upload-progress").get_attribute("aria-valuetext") == "100 % sent"
    with httpx.Client(base_url=svc.base, headers={"Authorization": f"Bearer {token}"}) as client:
        wait_until(lambda: client.get(f"/v1/scenes/{scene_id}").json()["state"] != "processing", 60,
                   what="the scene's ingest", processes=svc.processes)
        assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204  # the other tests expect their own only


def _cutting_proxy(port: int, cut_after: int) -> tuple[int, socket.socket]:
    """(its port, its listening socket: close it to stop) A TCP proxy to 127.0.0.1:``port`` that reads a POST
    /v1/scenes slowly (an upload's progress is seen) and resets both its connections once ``cut_after`` bytes of it
    have passed: a network failing mid-upload."""
    listener = socket.create_server(("127.0.0.1", 0))

    def pipe(source: socket.socket, sink: socket.socket, watched: bool) -> None:
        tail, passed = b"", None  # (bytes of the upload passed, once its request line is seen)
        try:
            while data := source.recv(64 << 10):
                if watched and passed is None and b"POST /v1/scenes" in tail + data:
                    passed = 0
                tail = data[-32:]
                if passed is not None:
                    passed += len(data)
                    time.sleep(0.02)
                    if passed > cut_after:
                        for end in (source, sink):
                            end.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                        return
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for end in (source, sink):
                end.close()

    def serve() -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:  # closed: the test is over
                return
            upstream = socket.create_connection(("127.0.0.1", port))
            threading.Thread(target=pipe, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=pipe, args=(upstream, client, False), daemon=True).start()

    threading.Thread(target=serve, daemon=True).start()
    return listener.getsockname()[1], listener


def test_an_upload_cut_off_by_the_network_leaves_no_progress_shown(live, browser, tmp_path):
    """An upload whose connection is reset mid-way (a network error) hides its progress bar with the failure said:
    the bar had stayed at its share sent beside "the upload failed", as if the upload were still going on."""
    svc, token, _archive = live
    driver = browser
    port, listener = _cutting_proxy(int(urlparse(svc.base).port), 4 << 20)
    big = tmp_path / "big.bin"
    big.write_bytes(os.urandom(32 << 20))
    try:
        driver.get(f"http://127.0.0.1:{port}/")
        use_key(driver, token)
        wait_until(lambda: "key set" in text(driver, "#key-state"), 10, what="the key to be kept")
        driver.execute_script("window.shares = [];"
                              "new MutationObserver(() => shares.push(document.querySelector('#upload-progress').value))"
                              ".observe(document.querySelector('#upload-progress'), { attributes: true });")
        driver.find_element("id", "upload-files").send_keys(str(big))
        driver.find_element("css selector", "#upload-form button").click()
        wait_until(lambda: text(driver, '[data-error-for="upload"]'), 60, what="the upload's failure")
        assert text(driver, '[data-error-for="upload"]') == "the upload failed (network error)"
        shares = driver.execute_script("return window.shares")
        assert any(0 < share < 1 for share in shares), shares  # (it failed mid-way)
        assert driver.execute_script("return document.querySelector('#upload-progress').hidden")
        assert driver.find_element("css selector", "#upload-form button").is_enabled()
    finally:
        listener.close()
    driver.get(f"{svc.base}/")


def test_an_upload_refused_leaves_no_progress_shown(live, browser, tmp_path):
    """An upload sent whole and refused (a 422: a .zip that is none) hides its progress bar with the refusal said: the
    bar had stayed at 100 % beside the error, as if the upload had gone through."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    driver.execute_script("window.shares = [];"
                          "new MutationObserver(() => shares.push(document.querySelector('#upload-progress').value))"
                          ".observe(document.querySelector('#upload-progress'), { attributes: true });")
    (tmp_path / "bad.zip").write_bytes(b"not a zip" * 4096)
    driver.find_element("id", "upload-archive").send_keys(str(tmp_path / "bad.zip"))
    driver.find_element("css selector", "#upload-form button").click()
    wait_until(lambda: text(driver, '[data-error-for="upload"]'), 30, what="the upload refused")
    assert text(driver, '[data-error-for="upload"]').startswith("422: archive 'bad.zip' is not a readable zip file")
    assert 1 in driver.execute_script("return window.shares")  # (it was sent whole)
    assert driver.execute_script("return document.querySelector('#upload-progress').hidden")
    assert driver.find_element("css selector", "#upload-form button").is_enabled()
    driver.find_element("id", "upload-archive").clear()


def test_an_edit_with_no_scene_to_edit_says_what_to_do_and_sends_nothing(live, browser):
    """An edit submitted while the Scene field offers none is refused beside it, saying why and what to do: it had
    been sent, and the API's 422 shown there, "String should have at least 1 character (scene_id)"."""
    svc, token, _archive = live
    driver = browser
    error = lambda: text(driver, '[data-error-for="scene_id"]')  # noqa: E731
    answer = lambda scenes: {"status": 200, "type": "application/json",  # noqa: E731
                             "body": json.dumps({"items": scenes, "total": len(scenes)})}
    down = {"status": 503, "statusText": "Service Unavailable", "type": "text/plain", "body": "down"}
    set_key(driver, svc, token)
    try:
        for scenes, said in (
                (down, "the scenes have not loaded yet: wait for them, or reload the page"),
                (answer([]), "no scene to edit: upload one (1. Upload a scene), then choose it here once it is ready"),
                (answer([{"id": "made", "name": "tetra", "state": "processing"},
                         {"id": "broken", "name": "bad", "state": "failed"}]),
                 "no scene is ready yet: wait until the one uploaded is processed (it is offered here once it is "
                 "ready)")):
            faults(driver, {"/v1/scenes?": scenes, "/v1/jobs?": answer([])})
            driver.refresh()
            wait_until(lambda: requested(driver, "/v1/jobs?"), 10, what="the scenes, then the jobs, asked for")
            driver.find_element("id", "job-prompt").clear()
            driver.find_element("id", "job-prompt").send_keys("a mic made of gold")
            driver.find_element("css selector", "#job-form button").click()
            wait_until(error, 10, what="the edit refused")
            assert error() == said
            assert not requested(driver, "/v1/jobs", "POST")
    finally:
        faults(driver, {})
    driver.refresh()


def test_a_keyboard_s_focus_follows_the_page_it_opens(live, browser):
    """A job opened from the list with the keyboard (Enter on its link), and the list opened again ("← all jobs", or
    Back from an artifact's link), take the focus with them: it had been dropped with the page hidden, the next Tab
    starting over at the header (from an artifact's link too, removed before the focus was looked for)."""
    from selenium.webdriver.common.keys import Keys

    svc, token, _archive = live
    driver = browser
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    job = running_job("keyed")
    log = {"name": "log.txt", "url": "/v1/jobs/keyed/artifacts/log.txt", "sha256": "0" * 64, "size": 9, "kind": "log"}
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs?": answer({"items": [job], "total": 1}), "/v1/jobs/keyed$": answer(job),
                    "/v1/jobs/keyed/artifacts$": answer([log]),
                    "/v1/jobs/keyed/events": {"recorded": 0, "open": True, "timeline": []}})
    driver.refresh()
    focused_page = "return document.activeElement.closest('main:not([hidden])')?.id ?? null"
    wait_until(lambda: driver.find_elements("css selector", 'tr[data-job="keyed"] a'), 10, what="the job listed")
    driver.find_element("css selector", 'tr[data-job="keyed"] a').send_keys(Keys.ENTER)
    wait_until(lambda: text(driver, "#job-state") == "running", 10, what="the job page")
    assert driver.execute_script(focused_page) == "job"
    driver.find_element("css selector", '#job a[href="#/"]').send_keys(Keys.ENTER)
    wait_until(lambda: not driver.find_element("id", "home").get_attribute("hidden"), 10, what="the home page")
    assert driver.execute_script(focused_page) == "home"
    driver.execute_script("history.back()")
    wait_until(lambda: driver.find_elements("css selector", "#job-artifacts a"), 10, what="the job's artifacts")
    driver.execute_script("document.querySelector('#job-artifacts a').focus()")
    driver.execute_script("history.back()")  # (Alt+Left)
    wait_until(lambda: not driver.find_element("id", "home").get_attribute("hidden"), 10, what="the home page")
    assert driver.execute_script(focused_page) == "home"
    faults(driver, {})


def test_a_job_s_progress_reads_as_it_stands(live, browser):
    """The list's and the job page's numbers as they are: a running job 99.6 % done is not "100 %", a job made three
    days ago is not "74 h" old, a checkpoint says which iteration it holds,
    a queued job has no stage's "0/0"."""
    svc, token, _archive = live
    driver = browser
    created = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(time.time() - 3 * 86400 - 2 * 3600 - 60))
    job = running_job("nearly", stage="export", completed_stages=["reconstruct", "edit"], overall_progress=0.996,
                      created_at=created)
    timeline = [{"id": 1, "kind": "checkpoint", "stage": "edit", "iteration": 200, "detail": None},
                {"id": 2, "kind": "resumed", "stage": "edit", "iteration": 200, "detail": None}]
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    set_key(driver, svc, token)
    waiting = {**job, "id": "waiting", "state": "queued", "stage": None, "completed_stages": [], "progress": 0,
               "iteration": 0, "total": 0, "overall_progress": 0, "eta_seconds": None, "overall_eta_seconds": None,
               "message": "waiting for the scene 's' to be processed"}
    faults(driver, {"/v1/jobs?": answer(json.dumps({"items": [job], "total": 1})),
                    "/v1/jobs/nearly$": answer(json.dumps(job)),
                    "/v1/jobs/waiting$": answer(json.dumps(waiting)),
                    "/v1/jobs/waiting/artifacts$": answer("[]"),
                    "/v1/jobs/waiting/events": {"timeline": [], "recorded": 0},
                    "/v1/jobs/nearly/artifacts$": answer("[]"),
                    "/v1/jobs/nearly/events": {"timeline": timeline, "recorded": 2}})
    driver.refresh()
    wait_until(lambda: driver.find_elements("css selector", 'tr[data-job="nearly"]'), 10, what="the job listed")
    assert "99 %" in text(driver, 'tr[data-job="nearly"]')
    assert text(driver, 'tr[data-job="nearly"] td:last-child') == "3 d 2 h ago"  # had read "74 h 1 min ago"
    go(driver, "#/jobs/nearly")
    wait_until(lambda: text(driver, "#job-state") == "running", 10, what="the job page")
    assert text(driver, "#job-overall-text") == "99 %"
    assert [item.text for item in driver.find_elements("css selector", "#job-events li")] == [
        "checkpoint · edit · iteration 200", "resumed · edit · iteration 200"]  # the iterations had not been shown
    assert text(driver, "#job-stage-text") == "2/4"
    go(driver, "#/jobs/waiting")
    wait_until(lambda: text(driver, "#job-state") == "queued", 10, what="the queued job's page")
    assert (text(driver, "#job-stage"), text(driver, "#job-stage-text"), text(driver, "#job-eta")) == ("–", "–", "–")
    faults(driver, {})


def test_every_progress_bar_has_a_name_a_screen_reader_says(live, browser):
    """The job list's and the job page's progress bars had no accessible name (a <dt> beside one names nothing, nor
    a column's header): a screen reader said "progress bar, 99 %", of which no one could tell. Each has one, as the
    upload's has."""
    svc, token, _archive = live
    driver = browser
    job = running_job("named", stage="edit", completed_stages=["reconstruct"], overall_progress=0.5)
    answer = lambda body: {"status": 200, "type": "application/json", "body": body}  # noqa: E731

    def names() -> list[str]:
        nodes = driver.execute_cdp_cmd("Accessibility.getFullAXTree", {})["nodes"]
        return [node.get("name", {}).get("value", "") for node in nodes
                if not node.get("ignored") and node.get("role", {}).get("value") == "progressbar"]

    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs?": answer(json.dumps({"items": [job], "total": 1})),
                    "/v1/jobs/named$": answer(json.dumps(job)),
                    "/v1/jobs/named/artifacts$": answer("[]"),
                    "/v1/jobs/named/events": {"timeline": [], "recorded": 0}})
    try:
        driver.refresh()
        wait_until(lambda: driver.find_elements("css selector", 'tr[data-job="named"]'), 10, what="the job listed")
        assert names() == ["overall progress"]
        go(driver, "#/jobs/named")
        wait_until(lambda: text(driver, "#job-state") == "running", 10, what="the job page")
        assert names() == ["stage progress", "overall progress"]
    finally:
        faults(driver, {})


def test_a_requested_cancel_stays_shown_until_the_job_stops(live, browser):
    """A cancel requested is shown while the job runs its last iterations: the stream's progress snapshots say so
    (they had left cancel_requested out, and the first after a cancel had wiped its "(cancel requested)")."""
    svc, token, _archive = live
    driver = browser
    job = running_job("stopping", completed_stages=["reconstruct"])
    snapshot = {key: job[key] for key in ("state", "stage", "progress", "total", "overall_progress", "losses",
                                          "completed_stages", "eta_seconds", "overall_eta_seconds", "message",
                                          "error", "preview_url")}
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/stopping$": answer(job),
                    "/v1/jobs/stopping/artifacts$": answer([]),
                    "/v1/jobs/stopping/cancel": {"method": "POST", **answer({**job, "cancel_requested": True})},
                    # the stream's snapshot comes 3 s after the page asked (its timeline as late)
                    "/v1/jobs/stopping/events": {"delay": 3000, "recorded": 0,
                                                 "timeline": [{**snapshot, "id": 1, "kind": "progress",
                                                               "iteration": 3, "cancel_requested": True}]}})
    go(driver, "#/jobs/stopping")
    wait_until(lambda: driver.find_element("id", "job-cancel").is_enabled(), 10, what="Cancel")
    driver.find_element("id", "job-cancel").click()
    wait_until(lambda: text(driver, "#job-state") == "running (cancel requested)", 5, what="the cancel shown")
    wait_until(lambda: text(driver, "#job-stage-text") == "3/4", 10, what="the next progress snapshot")
    assert text(driver, "#job-state") == "running (cancel requested)"
    faults(driver, {})


def test_a_silent_stream_is_opened_again_after_its_last_event(live, browser):
    """A stream on which nothing comes for 45 s, not even the server's keepalive comment (sent every 15 s), is taken
    for a dropped connection and opened again after its last event: a connection dropped unsaid (a laptop's sleep, a
    network change) had left the page waiting for ever, frozen at its last progress."""
    svc, token, _archive = live
    driver = browser
    job = running_job("silent")
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/silent$": answer(job), "/v1/jobs/silent/artifacts$": answer([]),
                    "/v1/jobs/silent/events": {"recorded": 0, "open": True, "timeline": [
                        {"id": 7, "kind": "stage_started", "stage": "edit", "detail": None}]}})
    driver.execute_script("window.requests = []")
    go(driver, "#/jobs/silent")
    wait_until(lambda: streams(driver, "silent"), 10, what="the stream")
    started = time.monotonic()
    wait_until(lambda: "nothing received for 45 s; reconnecting" in text(driver, '[data-error-for="stream"]'), 60,
               what="the silence noticed")
    assert time.monotonic() - started > 40
    wait_until(lambda: len(streams(driver, "silent")) == 2, 10, what="the stream opened again")
    assert [r["headers"].get("Last-Event-ID") for r in streams(driver, "silent")] == [None, "7"]
    listed = "return [...document.querySelectorAll('#job-events li')].map((item) => item.dataset.event)"
    assert driver.execute_script(listed) == ["stage_started"]
    faults(driver, {})


def test_a_job_page_whose_first_read_fails_on_a_proxy_s_502_loads_when_it_answers(live, browser):
    """The job page's first reads failing as the API restarts (a proxy's 502 page) are tried again until they answer,
    the failure said meanwhile: the page had stayed empty for good, its 502 beside it."""
    svc, token, _archive = live
    driver = browser
    job = {"id": "flaky", "scene_id": "s", "prompt": "a mic", "mode": "global", "edit_words": [],
           "models": {"sds": "tiny"}, "device": "cpu", "state": "succeeded", "stage": "export",
           "completed_stages": ["reconstruct", "edit", "export"], "progress": 1, "iteration": 4, "total": 4,
           "overall_progress": 1, "eta_seconds": None, "overall_eta_seconds": None, "losses": {}, "message": None,
           "preview_url": None, "error": None, "cancel_requested": False, "created_at": "2026-01-01T00:00:00Z"}
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/flaky$": answer(job), "/v1/jobs/flaky/artifacts$": answer([]),
                    "/v1/jobs/flaky/events": {"once": True, "status": 502, "statusText": "Bad Gateway",
                                              "type": "text/html", "body": "<h1>502 Bad Gateway</h1>"},
                    "/v1/jobs/flaky/events$": {"recorded": 1, "timeline": [
                        {"id": 1, "kind": "succeeded", "stage": "export", "detail": None}]}})
    go(driver, "#/jobs/flaky")
    wait_until(lambda: text(driver, '[data-error-for="stream"]') == "loading the job: 502: Bad Gateway; retrying", 10,
               what="the failure said")
    wait_until(lambda: text(driver, "#job-state") == "succeeded", 10, what="the job shown")
    assert not text(driver, '[data-error-for="stream"]')
    listed = "return [...document.querySelectorAll('#job-events li')].map((item) => item.dataset.event)"
    assert driver.execute_script(listed) == ["succeeded"]
    go(driver, "#/jobs/%E0")  # no URI-encoded text: said, and not tried again
    wait_until(lambda: "URI malformed" in text(driver, '[data-error-for="stream"]'), 10, what="the id refused")
    assert "retrying" not in text(driver, '[data-error-for="stream"]')
    faults(driver, {})


def test_a_stream_s_error_event_ends_it_saying_why(live, browser):
    """The stream's ``error`` event (the job deleted, the key revoked) is said beside the stream, which ends: it had
    been listed as a timeline event, and the stream opened again."""
    svc, token, _archive = live
    driver = browser
    job = running_job("gone")
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/gone$": answer(json.dumps(job)),
                    "/v1/jobs/gone/artifacts$": answer("[]"),
                    "/v1/jobs/gone/events": {"once": True, **answer("[]")},
                    "/v1/jobs/gone/events$": answer('event: error\ndata: {"detail": "job \'gone\' was deleted"}\n\n',
                                                    "text/event-stream")})
    driver.execute_script("window.requests = []")
    go(driver, "#/jobs/gone")
    wait_until(lambda: "not reconnecting" in text(driver, '[data-error-for="stream"]'), 10, what="the stream's end")
    assert text(driver, '[data-error-for="stream"]') == ("event stream: job 'gone' was deleted; not reconnecting "
                                                         "(reload the page to try again)")
    time.sleep(2.5)  # a retry interval
    assert len(streams(driver, "gone")) == 1 and not driver.find_elements("css selector", "#job-events li")
    faults(driver, {})


def test_a_stream_refused_as_asked_is_not_asked_again(live, browser):
    """A 422 to the stream request (its Last-Event-ID past the job's newest event, as after a database restore) ends
    the stream, saying why: asked again with the same id, it had been refused every retry for as long as the page
    stayed open."""
    svc, token, _archive = live
    driver = browser
    answer = lambda body: {"status": 200, "type": "application/json", "body": body}  # noqa: E731
    refused = {"status": 422, "type": "application/json",
               "body": json.dumps({"detail": "Last-Event-ID 99 is past job 'restored''s newest event, 7"})}
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/restored$": answer(json.dumps(running_job("restored"))),
                    "/v1/jobs/restored/artifacts$": answer("[]"),
                    "/v1/jobs/restored/events": {"once": True, **answer("[]")},
                    "/v1/jobs/restored/events$": refused})
    driver.execute_script("window.requests = []")
    go(driver, "#/jobs/restored")
    wait_until(lambda: "not reconnecting" in text(driver, '[data-error-for="stream"]'), 10, what="the stream's end")
    assert text(driver, '[data-error-for="stream"]') == (
        "event stream: 422: Last-Event-ID 99 is past job 'restored''s newest event, 7; not reconnecting "
        "(reload the page to try again)")
    time.sleep(5)  # two and a half retry intervals
    assert len(streams(driver, "restored")) == 1
    faults(driver, {})


def test_the_api_s_values_are_shown_as_text_never_as_markup(live, browser):
    """Every value the API sends is shown as text: a job's mode, state and creation time had been spliced into the
    job list's HTML unescaped, and parsed as the elements and attributes they wrote."""
    svc, token, _archive = live
    driver = browser
    markup = '<img src="/static/app.css" class="injected">'
    job = running_job("marked", mode=markup, state='running"><b class="injected">x</b>',
                      created_at='2026-01-01T00:00:00Z" class="injected', prompt=markup)
    scene = {"id": 'scene"><i class="injected"></i>', "name": markup, "state": "ready"}
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs?": answer({"items": [job], "total": 1}),
                    "/v1/scenes?": answer({"items": [scene], "total": 1, "next_cursor": None})})
    driver.refresh()
    wait_until(lambda: driver.find_elements("css selector", 'tr[data-job="marked"]'), 10, what="the job listed")
    wait_until(lambda: driver.find_elements("css selector", "#job-scene option"), 10, what="the scene offered")
    assert not driver.find_elements("css selector", ".injected")
    cells = driver.find_elements("css selector", 'tr[data-job="marked"] td')
    assert [cell.text for cell in cells[1:4]] == [markup, markup, job["state"]]
    assert cells[5].get_attribute("title") == job["created_at"]
    assert text(driver, "#job-scene option") == f"{markup} ({scene['id']})"
    assert driver.find_element("css selector", "#job-scene option").get_attribute("value") == scene["id"]
    faults(driver, {})


def test_an_error_answer_without_a_status_text_says_its_status_s_reason(live, browser):
    """HTTP/2 sends no status text: a non-JSON error answer reads its status's reason phrase, or, for a status
    without one, a plain-text body's first line, without a CRLF's CR (both had read "<status>: error")."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    shown = "return document.querySelector('[data-error-for=\"list\"]').textContent"
    for status, kind, body, said in ((502, "text/html", "<html><h1>502 Bad Gateway</h1></html>", "Bad Gateway"),
                                     (520, "text/plain", "  origin unreachable\nretry later", "origin unreachable"),
                                     (521, "text/plain", "origin down\r\nretry later", "origin down"),
                                     (599, "text/html", "<p>?</p>", "no reason given")):
        faults(driver, {"/v1/jobs?": {"status": status, "statusText": "", "type": kind, "body": body}})
        driver.refresh()
        wait_until(lambda: driver.execute_script(shown), 10, what="the job list's error")
        assert driver.execute_script(shown) == f"{status}: {said}"
    faults(driver, {})


def test_a_failing_stream_is_asked_again_less_often_each_time(live, browser):
    """The event stream's reconnections after failures in a row wait twice as long each time (from the server's
    retry interval), back to that interval once a connection is answered: a failing server had been asked again
    every 2 s for as long as the page stayed open."""
    svc, token, _archive = live
    driver = browser
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    failing = {"status": 503, "statusText": "Service Unavailable", "type": "application/json",
               "body": json.dumps({"detail": "database busy"})}
    answered = {"once": True, **answer("retry: 100\n\n", "text/event-stream")}  # then it ends: opened again
    set_key(driver, svc, token)
    # (the keys in sorted order: the timeline read as JSON, then a stream answered with its retry, then failures)
    faults(driver, {"/v1/jobs/busy$": answer(json.dumps(running_job("busy"))),
                    "/v1/jobs/busy/artifacts$": answer("[]"),
                    "/v1/jobs/busy/event": {"once": True, **answer("[]")},
                    "/v1/jobs/busy/events": answered, "/v1/jobs/busy/events$": failing})
    driver.execute_script("window.requests = []")
    go(driver, "#/jobs/busy")
    wait_until(lambda: len(streams(driver, "busy")) >= 6, 10, what="five failed reconnections")
    faults(driver, {"/v1/jobs/busy/events": answered, "/v1/jobs/busy/events$": failing})
    count = len(streams(driver, "busy"))
    wait_until(lambda: len(streams(driver, "busy")) >= count + 3, 20, what="an answered stream and a failure")
    times = [r["at"] for r in streams(driver, "busy")]
    gaps = [later - earlier for earlier, later in zip(times, times[1:])]
    # 100 ms after the answered stream and after the first failure, then 200, 400, 800, 1600
    for earlier, later in zip(gaps[1:5], gaps[2:6]):
        assert 1.5 * earlier < later < 3 * earlier, gaps
    answered_at = count  # the stream answered after the failures, then the first failure after it
    assert gaps[answered_at] < 500 and gaps[answered_at] < gaps[answered_at - 1] / 2, gaps
    go(driver, "#/")
    faults(driver, {})


def test_a_far_off_stream_retry_interval_is_waited_for_minutes_at_most(live, browser):
    """A stream's ``retry:`` past setTimeout()'s 2^31-1 ms (or past any number) is waited for a few minutes before
    reconnecting: setTimeout() had fired at once, the failing stream asked again hundreds of times a second."""
    svc, token, _archive = live
    driver = browser
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    failing = {"status": 503, "statusText": "Service Unavailable", "type": "application/json",
               "body": json.dumps({"detail": "database busy"})}
    set_key(driver, svc, token)
    for retry in ("3000000000", "9" * 400):
        # (the keys in sorted order: the timeline read as JSON, then a stream answered with its retry, then failures)
        faults(driver, {"/v1/jobs/far$": answer(json.dumps(running_job("far"))),
                        "/v1/jobs/far/artifacts$": answer("[]"),
                        "/v1/jobs/far/event": {"once": True, **answer("[]")},
                        "/v1/jobs/far/events": {"once": True, **answer(f"retry: {retry}\n\n", "text/event-stream")},
                        "/v1/jobs/far/events$": failing})
        driver.execute_script("window.requests = []")
        go(driver, "#/jobs/far")
        wait_until(lambda: streams(driver, "far"), 10, what="the stream")
        time.sleep(3)  # the stream is not asked again in 3 s (it had been thousands of times)
        assert len(streams(driver, "far")) == 1, retry
        go(driver, "#/")
    faults(driver, {})


def test_a_stream_answered_with_no_event_stream_is_a_failure_said_and_asked_less_often(live, browser):
    """A 2xx answer to the stream request that is no event stream (a proxy's login page), or an event stream that
    ends with nothing delivered, is a failure, said and asked again less often each time; the count goes back to
    none once a stream delivers anything, be it a comment (the server's keepalive). Counted answered on any 2xx,
    such answers had been asked for again every 2 s (here: the retry interval), with no word on the page."""
    svc, token, _archive = live
    driver = browser
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    stream_error = lambda: text(driver, '[data-error-for="stream"]')  # noqa: E731
    login = answer("<html><body><form>Sign in</form></body></html>", "text/html; charset=utf-8")
    set_key(driver, svc, token)

    def gaps_after(first: dict, then: dict, count: int) -> list[int]:
        """The gaps between the stream requests (ms) once ``first`` answered one and ``then`` the next ``count``."""
        faults(driver, {"/v1/jobs/proxied/events": {"once": True, **first}, "/v1/jobs/proxied/events$": then})
        known = len(streams(driver, "proxied"))
        wait_until(lambda: len(streams(driver, "proxied")) >= known + count + 1, 20, what="the stream asked again")
        times = [r["at"] for r in streams(driver, "proxied")][known:known + count + 1]
        return [later - earlier for earlier, later in zip(times, times[1:])]

    faults(driver, {"/v1/jobs/proxied$": answer(json.dumps(running_job("proxied"))),
                    "/v1/jobs/proxied/artifacts$": answer("[]"),
                    "/v1/jobs/proxied/event": {"once": True, **answer("[]")},  # the timeline read as JSON
                    "/v1/jobs/proxied/events$": login})
    driver.execute_script("window.requests = []")
    go(driver, "#/jobs/proxied")
    wait_until(lambda: "no event stream" in stream_error(), 10, what="the login page refused")
    assert stream_error() == ("event stream: 200: the answer (text/html; charset=utf-8) is no event stream; "
                              "reconnecting")
    # The server's retry interval (100 ms) after its stream, then twice as long after each login page.
    for first, then in ((answer("retry: 100\n\n", "text/event-stream"), login),
                        (answer(": keepalive\n\n", "text/event-stream"), answer("", "text/event-stream"))):
        gaps = gaps_after(first, then, 5)
        for earlier, later in zip(gaps[1:], gaps[2:]):
            assert 1.5 * earlier < later < 3 * earlier, gaps
        assert gaps[0] < 250, gaps
    assert stream_error() == "event stream: 200: the stream ended with nothing received; reconnecting"
    go(driver, "#/")
    faults(driver, {})


def test_only_a_running_job_and_stage_show_a_time_left(live, browser):
    """The ETAs the API sends (voxe_service.progress.overall's): a succeeded job's 0 s left shows no ETA, a running
    job between stages (the worker's 0 s left for the stage done) none for the stage, and only a running stage's
    ETA reached reads "finishing…" (each had read "finishing…")."""
    from voxe_service.progress import overall

    svc, token, _archive = live
    driver = browser
    costs = [("reconstruct", 10.0), ("edit", 80.0), ("export", 10.0)]
    ended = dict(state="succeeded", stage="export", completed_stages=["reconstruct", "edit", "export"])
    between = dict(state="running", stage="edit", completed_stages=["reconstruct", "edit"])
    last = dict(state="running", stage="export", completed_stages=["reconstruct", "edit"])
    jobs = {"done": ({**ended, "eta_seconds": None}, 1.0, None, True),
            "between": ({**between, "eta_seconds": 0.0}, 1.0, 0.0, False),
            "last": ({**last, "eta_seconds": 0.3}, 0.99, 0.3, False)}
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    set_key(driver, svc, token)
    shown = {}
    for job_id, (fields, fraction, stage_eta, finished) in jobs.items():
        _, left = overall(costs=costs, completed=fields["completed_stages"], stage=fields["stage"],
                          stage_fraction=fraction, stage_eta_s=stage_eta, finished=finished)
        faults(driver, {f"/v1/jobs/{job_id}$": answer(running_job(job_id, **fields, overall_eta_seconds=left)),
                        f"/v1/jobs/{job_id}/artifacts$": answer([]),
                        f"/v1/jobs/{job_id}/events": {"timeline": [], "recorded": 0, "open": True}})
        go(driver, f"#/jobs/{job_id}")
        wait_until(lambda: text(driver, "#job-state") == fields["state"], 10, what="the job page")
        shown[job_id] = text(driver, "#job-eta")
        go(driver, "#/")
    assert shown == {"done": "–", "between": "10 s left", "last": "finishing… (this stage: finishing…)"}
    faults(driver, {})


def test_a_prompt_over_the_api_s_limit_is_refused_beside_it_not_cut(live, browser):
    """The prompt field's maxlength="500" cut a longer prompt typed or pasted into it to its first 500 UTF-16 units
    (fewer characters than the API's 500 where it holds emoji), and the edit ran with the cut prompt, saying nothing.
    The prompt is sent whole and the API's 422 said beside it."""
    svc, token, _archive = live
    driver = browser
    set_key(driver, svc, token)
    prompt = "a mic made of " + "gold " * 120  # 614 characters
    field = driver.find_element("id", "job-prompt")
    field.send_keys(prompt)
    assert field.get_attribute("value") == prompt
    driver.find_element("css selector", "#job-form button").click()
    shown = lambda: text(driver, '[data-error-for="prompt"]')  # noqa: E731
    wait_until(shown, 10, what="the API's refusal of the prompt")
    assert shown() == "String should have at most 500 characters (prompt)"
    assert len(requested(driver, "/v1/jobs", "POST")) == 1


def test_a_long_one_word_prompt_wraps_inside_the_window(live, browser):
    """A prompt (and the error quoting it) of one 500-character word, in the job list and on its job page: the
    text wraps, the page stays as wide as the window, and the list's State column stays on screen (the table and
    the page had grown to over 4,000 px, the job's state scrolled out of sight)."""
    svc, token, _archive = live
    driver = browser
    prompt = ("a mic made of " + "gold" * 130)[:500]
    job = {"id": "long-prompt", "scene_id": "s", "prompt": prompt, "mode": "global", "edit_words": [],
           "models": {"sds": "tiny"}, "device": "cpu", "state": "failed", "stage": "reconstruct",
           "completed_stages": [], "progress": 0, "iteration": 0, "total": 0, "overall_progress": 0,
           "eta_seconds": None, "overall_eta_seconds": None, "losses": {}, "message": None, "preview_url": None,
           "error": f"reconstruct: the prompt {prompt!r} is too long", "cancel_requested": False,
           "created_at": "2026-01-01T00:00:00Z"}
    answer = lambda body, kind="application/json": {"status": 200, "type": kind, "body": body}  # noqa: E731
    set_key(driver, svc, token)
    end = [{"id": 1, "kind": "failed", "stage": "reconstruct", "detail": job["error"]}]
    faults(driver, {"/v1/jobs?": answer(json.dumps({"items": [job], "total": 1})),
                    "/v1/jobs/long-prompt$": answer(json.dumps(job)),
                    "/v1/jobs/long-prompt/artifacts": answer("[]"),
                    "/v1/jobs/long-prompt/events": {"timeline": end, "recorded": 1}})
    overflow = "return document.documentElement.scrollWidth - document.documentElement.clientWidth"
    driver.refresh()
    wait_until(lambda: driver.find_elements("css selector", 'tr[data-job="long-prompt"]'), 10, what="the job listed")
    assert driver.execute_script(overflow) == 0
    assert driver.execute_script("return document.querySelector('tr[data-job=\"long-prompt\"] .state-failed')"
                                 ".getBoundingClientRect().right <= document.documentElement.clientWidth")
    go(driver, "#/jobs/long-prompt")
    wait_until(lambda: driver.find_elements("css selector", '#job-events li[data-event="failed"]'), 10,
               what="the job page")
    assert text(driver, "#job-state") == "failed" and "too long" in text(driver, "#job-message")
    assert driver.execute_script(overflow) == 0
    faults(driver, {})


def test_a_failed_job_without_a_reason_says_none_was_recorded(live, browser):
    """A job failed with no error nor message (a row ended by hand, an error of no text): its Message had been blank
    beside "failed", as if the page had not loaded it."""
    svc, token, _archive = live
    driver = browser
    job = running_job("no-reason", state="failed", eta_seconds=None, overall_eta_seconds=None)
    answer = lambda body: {"status": 200, "type": "application/json", "body": json.dumps(body)}  # noqa: E731
    set_key(driver, svc, token)
    faults(driver, {"/v1/jobs/no-reason$": answer(job), "/v1/jobs/no-reason/artifacts$": answer([]),
                    "/v1/jobs/no-reason/events": {"recorded": 1, "timeline": [{"id": 1, "kind": "failed"}]}})
    go(driver, "#/jobs/no-reason")
    wait_until(lambda: text(driver, "#job-state") == "failed", 10, what="the failed job")
    assert text(driver, "#job-message") == "(no reason was recorded)"
    faults(driver, {})


def test_docs_render_from_the_vendored_swagger_ui(live, browser):
    svc, _token, _archive = live
    browser.get(f"{svc.base}/docs")
    wait_until(lambda: browser.find_elements("css selector", ".swagger-ui .opblock"), 30, what="Swagger UI")
    screenshot(browser, "docs")
    assert "/v1/jobs" in browser.page_source
    assert same_origin_only(browser, svc)
    assert browser.execute_script("return window.cspViolations") == []
    assert httpx.get(f"{svc.base}/redoc").status_code == 404  # ReDoc would come from a CDN: not served


def same_origin_only(driver, svc) -> bool:
    """Every resource the page loaded came from the API itself (or was a blob:/data: URL)."""
    urls = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    foreign = [u for u in urls if urlparse(u).scheme in ("http", "https") and not u.startswith(svc.base)]
    assert not foreign, foreign
    return True


def test_the_published_text_patterns_read_in_javascript_refuse_nothing_the_server_accepts(browser):
    """A JSON Schema pattern is an ECMA-262 regular expression (read with the u flag by some validators, without by
    others): so read, the prompt's pattern never refuses what the server takes as a prompt, and is exact for single
    ASCII characters (a contraction's ending alone, "'s", it takes and the server refuses); the edit word's matches
    exactly what the server takes. Its \\w had been ASCII's there: a Chinese prompt, which the server accepts, was
    one the document refused."""
    from api.schemas import EDIT_WORD_PATTERN, TEXT_PATTERN, clean_text

    def accepted(text: str, need_words: bool) -> bool:
        try:
            clean_text(text, "text", need_words)
            return True
        except ValueError:
            return False

    # Every code point but the surrogates (no text of its own); each range's [first, last] the pattern matches.
    matched_ranges = """
        const re = new RegExp(arguments[0], arguments[1]);
        const ranges = [];
        for (let c = 0; c <= 0x10ffff; c++) {
          if (c === 0xd800) c = 0xe000;
          if (!re.test(String.fromCodePoint(c))) continue;
          if (ranges.length && ranges.at(-1)[1] === c - 1) ranges.at(-1)[1] = c; else ranges.push([c, c]);
        }
        return ranges;"""
    code_points = [*range(0xd800), *range(0xe000, 0x110000)]
    texts = ["猫が好き", "一只戴着墨镜的猫", "𠀀", "a\x1fb", "\x85x", "mic\x7f", "  猫 ", "!!!", "½", "--"]
    for pattern, need_words in ((TEXT_PATTERN, True), (EDIT_WORD_PATTERN, False)):
        server = bytearray(0x110000)
        for code in code_points:
            server[code] = accepted(chr(code), need_words)
        for flags in ("", "u"):
            matched = bytearray(0x110000)
            for first, last in browser.execute_script(matched_ranges, pattern, flags):
                matched[first:last + 1] = b"\x01" * (last + 1 - first)
            refused = [hex(code) for code in code_points if server[code] and not matched[code]]
            assert not refused, (pattern, flags, len(refused), refused[:20])
            exact_up_to = 0x80 if need_words else 0x110000  # beyond ASCII the prompt's rule is the description's
            differ = [hex(code) for code in code_points[:exact_up_to] if server[code] != matched[code]]
            assert not differ, (pattern, flags, differ[:20])
            read = browser.execute_script("return arguments[2].map((t) => new RegExp(arguments[0], arguments[1])"
                                          ".test(t))", pattern, flags, texts)
            for text, js in zip(texts, read):
                assert js or not accepted(text, need_words), (pattern, flags, text)
                assert js == accepted(text, need_words) or need_words and not text.isascii(), (pattern, flags, text)


def test_behind_a_proxy_prefix_the_page_calls_the_api_under_it(browser, monkeypatch, tmp_path):
    """A proxy serving the service at /api (uvicorn --root-path /api behind it): the page's own calls (its job and
    scene lists, a job's events) had gone to /v1/... at the proxy's top, another site's paths or none. (An API in
    this process, no worker: the page's calls are what is tested.)"""
    import uvicorn

    from service_helpers import free_port, reset_service_caches, service_env

    env = service_env(tmp_path, VOXE_AUTH="on")
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from api.main import create_app

    app = create_app()

    async def proxy(scope, receive, send):
        """What the app gets behind the proxy: paths under /api with root_path /api; nothing else is this service."""
        if scope["type"] == "lifespan":
            return await app(scope, receive, send)
        if scope["path"] == "/api" or scope["path"].startswith("/api/"):
            return await app({**scope, "root_path": "/api"}, receive, send)
        await send({"type": "http.response.start", "status": 404, "headers": [(b"content-type", b"text/plain")]})
        await send({"type": "http.response.body", "body": b"not this service"})

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(proxy, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    driver = browser
    try:
        wait_until(lambda: server.started, 60, what="the proxied API to start")
        token = subprocess.run([sys.executable, "-m", "api.admin", "create-key", "--name", "browser"],
                               env={**os.environ, **env}, capture_output=True, text=True, check=True,
                               cwd=Path(__file__).resolve().parents[1]).stdout.strip()
        driver.get(f"http://127.0.0.1:{port}/api/")
        use_key(driver, token)
        wait_until(lambda: "key set" in text(driver, "#key-state"), 10, what="the key to be kept")
        wait_until(lambda: text(driver, "#jobs-range") != "", 15, what="the job list")
        go(driver, "#/jobs/not-a-job")
        wait_until(lambda: text(driver, '[data-error-for="stream"]').startswith("404: "), 15,
                   what="the job page's answer")
        assert "not-a-job" in text(driver, '[data-error-for="stream"]')
        paths = [urlparse(r["url"]).path for r in driver.execute_script("return window.requests")]
        assert {"/api/v1/jobs", "/api/v1/scenes", "/api/v1/jobs/not-a-job/events"} <= set(paths), paths
        assert all(path.startswith("/api/") for path in paths), paths
        assert text(driver, '[data-error-for="list"]') == ""
        assert driver.execute_script("return window.cspViolations") == []
    finally:
        server.should_exit = True
        thread.join(10)
        reset_service_caches()
