"""The web UI in a real headless Chromium (Selenium + Debian's chromium-driver) against a live uvicorn API and
Celery worker with authentication ON and the random-weight SMOKE-TEST model (VOXE_SDS_MODEL=tiny): plumbing
only, never edit quality. A screenshot of each page lands in tests/.artifacts/ (gitignored) on every run.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
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
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def screenshot(driver, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    driver.save_screenshot(str(ARTIFACTS / f"ui_{name}.png"))


def text(driver, selector: str) -> str:
    return driver.find_element("css selector", selector).text


def set_key(driver, svc, token: str) -> None:
    driver.get(f"{svc.base}/")
    field = driver.find_element("id", "api-key")
    field.clear()
    field.send_keys(token)
    driver.find_element("css selector", "#key-form button").click()
    wait_until(lambda: "key set" in text(driver, "#key-state"), 10, what="the key to be kept")


def test_upload_edit_and_watch_a_local_edit_to_its_video_and_3d_view(live, browser):
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

    # The real scene, with upload progress, until its ingest is done and it is offered for editing.
    driver.get(f"{svc.base}/")
    driver.find_element("id", "upload-archive").send_keys(str(archive))
    driver.find_element("css selector", "#upload-form button").click()
    wait(lambda: "ready" in text(driver, "#upload-status"), "the scene to be ready")
    assert driver.execute_script("return document.querySelector('#upload-progress').value") == 1
    scene_id = driver.execute_script("return document.querySelector('#job-scene').value")
    assert scene_id

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
    driver.find_element("css selector", "#job-form button").click()
    wait(lambda: "#/jobs/" in driver.current_url, "the job page", 20)
    job_id = driver.current_url.rsplit("/", 1)[1]
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

    # The job list shows it, and filtering by another state hides it.
    driver.get(f"{svc.base}/#/")
    wait(lambda: driver.find_elements("css selector", f'tr[data-job="{job_id}"]'), "the job in the list", 20)
    assert "100 %" in text(driver, f'tr[data-job="{job_id}"]')
    from selenium.webdriver.support.select import Select

    Select(driver.find_element("id", "filter-state")).select_by_visible_text("failed")
    wait(lambda: not driver.find_elements("css selector", f'tr[data-job="{job_id}"]'), "the filter", 20)
    screenshot(driver, "home")
    assert same_origin_only(driver, svc)


def test_docs_render_from_the_vendored_swagger_ui(live, browser):
    svc, _token, _archive = live
    browser.get(f"{svc.base}/docs")
    wait_until(lambda: browser.find_elements("css selector", ".swagger-ui .opblock"), 30, what="Swagger UI")
    screenshot(browser, "docs")
    assert "/v1/jobs" in browser.page_source
    assert same_origin_only(browser, svc)
    assert httpx.get(f"{svc.base}/redoc").status_code == 404  # ReDoc would come from a CDN: not served


def same_origin_only(driver, svc) -> bool:
    """Every resource the page loaded came from the API itself (or was a blob:/data: URL)."""
    urls = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    foreign = [u for u in urls if urlparse(u).scheme in ("http", "https") and not u.startswith(svc.base)]
    assert not foreign, foreign
    return True
