"""End to end over real HTTP: a uvicorn API and a Celery worker as subprocesses, run twice:

* ``embedded``: the default setup of ``bash .ci/serve`` (SQL broker, SQLite, local storage);
* ``redis``: a real redis-server as broker and S3 storage (a real SeaweedFS), with the API and the
  worker on separate scratch folders, so the worker gets every input through the storage and
  nothing through a shared filesystem.

The model is the random-weight SMOKE-TEST Stable Diffusion (VOXE_SDS_MODEL=tiny): these tests prove
the plumbing (queueing, progress, reuse, cancellation, artifacts), never edit quality.
"""

from __future__ import annotations

import contextlib
import hashlib
import shutil
import time
from dataclasses import dataclass, field

import httpx
import pytest

from needs import MIC, missing, require_data
from service_helpers import (
    check_resumed_from_the_last_checkpoint, check_the_edit_changed_the_object, checkpoint_at_least, job_events,
    poll_job, redis_server, service, verify_artifacts, wait_for_event, wait_for_scene, zip_folder,
)

pytestmark = pytest.mark.slow

RECONSTRUCTION = {"preset": "fast", "resolution": 24, "iterations": [10, 10, 20], "rays_per_step": 1024}
PARAMS = {
    "downsample": 16, "max_images": 8, "iterations": 5, "render_size": 48, "preview_every": 2,
    "reconstruction": RECONSTRUCTION,
    "refine": {"iterations": 20, "views": 4, "render_size": 64, "rays_per_step": 2048},
    "export": {"views": 2, "view_size": 48, "turntable_frames": 8, "turntable_size": 48},
}
SMOKE_LABEL = "tiny (smoke test, random weights)"
COMMON_ARTIFACTS = {"initial_grid.safetensors", "edited_grid.safetensors", "render_000.png", "render_001.png",
                    "turntable.mp4", "turntable.gif", "mesh.ply", "mesh.glb", "mesh.obj", "mesh.mtl", "preview.png"}
RESUMED_ARTIFACTS = {"initial_grid.safetensors", "edited_grid.safetensors", "render_000.png", "render_001.png",
                     "turntable.mp4", "preview.png"}  # no gif, no mesh
LOCAL_ARTIFACTS = {"refined_grid.safetensors", "mask.safetensors", "attention_probabilities.safetensors",
                   "mask_overlay.png"}


@dataclass
class Stack:
    broker: str
    client: httpx.Client
    service: object
    scene: dict
    jobs: dict = field(default_factory=dict)
    root: object = None

    def diagnostics(self) -> str:
        return self.service.diagnostics()


@pytest.fixture(scope="session")
def mic_zip(tmp_path_factory):
    require_data(MIC)
    return zip_folder(MIC, tmp_path_factory.mktemp("upload") / "nerf_synthetic_mic.zip", prefix="nerf_synthetic_mic")


@pytest.fixture(scope="module", params=["embedded", "redis"])
def stack(request, tmp_path_factory, mic_zip):
    broker = request.param
    root = tmp_path_factory.mktemp(f"service-{broker}")
    with contextlib.ExitStack() as stack_:
        broker_url, extra, worker_env = None, {}, None
        if broker == "redis":
            if shutil.which("redis-server") is None:
                missing("redis-server is not installed (.ci/test installs it)")
            broker_url = stack_.enter_context(redis_server(root / "redis")).url
            extra = {**request.getfixturevalue("seaweedfs"), "VOXE_S3_BUCKET": "voxe-e2e"}
            worker_env = {"VOXE_WORK_DIR": str(root / "worker-work"), "VOXE_MODEL_DIR": str(root / "worker-models")}
        svc = stack_.enter_context(service(root, broker_url, worker_env, VOXE_CHECKPOINT_EVERY="10", **extra))
        client = stack_.enter_context(httpx.Client(base_url=svc.base, timeout=60))
        with open(mic_zip, "rb") as handle:
            response = client.post("/v1/scenes", files={"archive": ("nerf_synthetic_mic.zip", handle,
                                                                     "application/zip")})
        assert response.status_code == 201, response.text
        assert response.json()["state"] == "processing"  # decoded by the worker's ingest, off the request path
        yield Stack(broker, client, svc, wait_for_scene(client, svc, response.json()["id"]), root=root)


def wait_for_job(stack: Stack, job_id: str, timeout: float = 240, until=None) -> dict:
    return poll_job(stack.client, stack.service, job_id, until, timeout)


def create_job(stack: Stack, **body) -> dict:
    response = stack.client.post("/v1/jobs", json={"scene_id": stack.scene["id"], **body})
    assert response.status_code == 201, response.text
    return response.json()


STAGE_OUTPUTS = {"reconstruct": {"initial_grid.safetensors"}, "edit": {"edited_grid.safetensors"},
                 "refine": LOCAL_ARTIFACTS, "export": {"turntable.mp4", "turntable.gif", "mesh.ply", "mesh.glb",
                                                             "mesh.obj", "mesh.mtl"}}


def cancel_during(stack: Stack, stage: str, **body) -> tuple[dict, dict, int]:
    """Create a job and cancel it a few iterations into ``stage``; check it stops promptly and consistently.

    Returns (the record while running, the final record, the iteration when the cancel was accepted).
    """
    job = create_job(stack, **body)
    running = wait_for_job(stack, job["id"], until=lambda j: j["stage"] == stage and j["iteration"] >= 3 and j["total"]
                           or j["state"] in ("succeeded", "failed", "canceled"))
    assert running["state"] == "running" and running["stage"] == stage, running
    response = stack.client.post(f"/v1/jobs/{job['id']}/cancel")
    assert response.status_code == 200 and response.json()["cancel_requested"] is True
    started = time.monotonic()
    final = wait_for_job(stack, job["id"], timeout=60)
    assert time.monotonic() - started < 30, f"cancel during {stage} took {time.monotonic() - started:.0f} s"
    assert final["state"] == "canceled" and final["stage"] == stage, final
    assert final["message"] == f"canceled during {stage}" and final["error"] is None, final
    assert final["finished_at"] and final["eta_seconds"] is None and final["cancel_requested"] is True
    stages = ["reconstruct", "edit"] + (["refine"] if final["mode"] == "local" else []) + ["export"]
    assert final["completed_stages"] == stages[:stages.index(stage)], final
    # Nothing half done is listed: none of the stage's outputs, and every listed artifact is whole.
    listing = stack.client.get(f"/v1/jobs/{job['id']}/artifacts").json()
    assert not {a["name"] for a in listing} & STAGE_OUTPUTS[stage], listing
    for artifact in listing:
        data = stack.client.get(artifact["url"]).content
        assert len(data) == artifact["size"] and hashlib.sha256(data).hexdigest() == artifact["sha256"], artifact
    if stack.broker == "embedded":  # the job's checkpoints were deleted from the (local) storage
        assert not (stack.root / "storage" / "jobs" / job["id"] / "checkpoints").exists()
    again = stack.client.post(f"/v1/jobs/{job['id']}/cancel")
    assert again.status_code == 200 and again.json()["state"] == "canceled"
    return running, final, response.json()["iteration"]


# ---------------------------------------------------------------------------------------------- tests
def test_scene_and_readiness(stack):
    scene = stack.scene
    assert scene["state"] == "ready" and scene["error"] is None, scene
    assert scene["format"] == "nerf_synthetic"
    assert scene["image_count"] > 0 and (scene["width"], scene["height"]) == (800, 800)
    assert stack.client.get(f"/v1/scenes/{scene['id']}").json()["sha256"] == scene["sha256"]
    ready = stack.client.get("/readyz")
    assert ready.status_code == 200, ready.text
    checks = ready.json()["checks"]
    assert all(c["ok"] for c in checks.values())
    assert checks["worker"]["workers"], checks
    assert checks["worker"]["method"] == ("database heartbeat" if stack.broker == "embedded" else "celery control ping")
    assert ready.json()["models"]["sds"] == SMOKE_LABEL
    assert checks["storage"]["backend"].startswith("s3:" if stack.broker == "redis" else "local:")


def test_local_and_global_jobs_share_one_reconstruction(stack):
    local = create_job(stack, prompt="a mic wearing big sunglasses", mode="local", edit_words=["sunglasses"],
                       params=PARAMS)
    global_ = create_job(stack, prompt="a wood carving of a mic", mode="global", params=PARAMS)
    assert local["state"] == "queued" and local["models"] == {"sds": SMOKE_LABEL, "attention": SMOKE_LABEL}
    assert local["reconstruction"]["id"] == global_["reconstruction"]["id"]
    local, global_ = wait_for_job(stack, local["id"]), wait_for_job(stack, global_["id"])
    for job in (local, global_):
        assert job["state"] == "succeeded", f"{job}\n{stack.diagnostics()}"
        assert job["error"] is None and job["worker_hostname"]
        assert job["started_at"] and job["finished_at"] and job["elapsed_seconds"] > 0
        assert job["preview_url"] == f"/v1/jobs/{job['id']}/artifacts/preview.png"
    assert local["completed_stages"] == ["reconstruct", "edit", "refine", "export"]
    assert global_["completed_stages"] == ["reconstruct", "edit", "export"]

    # One fit, used by both jobs: the run counter says it ran once, and exactly one job reused it.
    reconstructions = stack.client.get(f"/v1/scenes/{stack.scene['id']}/reconstructions").json()
    assert len(reconstructions) == 1 and reconstructions[0]["state"] == "succeeded"
    assert reconstructions[0]["run_count"] == 1
    assert sorted([local["reconstruction"]["reused"], global_["reconstruction"]["reused"]]) == [False, True]

    initial = verify_artifacts(stack.client, global_, COMMON_ARTIFACTS, stack.root)
    grids = verify_artifacts(stack.client, local, COMMON_ARTIFACTS | LOCAL_ARTIFACTS, stack.root)
    assert initial["initial_grid.safetensors"].resolution == grids["initial_grid.safetensors"].resolution == (24,) * 3
    # Each edit changed the object G_i holds, and the local one's cut kept some of it.
    check_the_edit_changed_the_object(stack.client, global_, initial)
    check_the_edit_changed_the_object(stack.client, local, grids)
    assert grids["mask"].any()
    stack.jobs.update(local=local, global_=global_)


def test_cancel_running_job(stack):
    # Same reconstruction parameters (reused), an edit far too long to finish.
    params = {**PARAMS, "iterations": 100_000, "render_size": 64}
    running, final, at_cancel = cancel_during(stack, "edit", prompt="a mic wearing a party hat", mode="local",
                                              edit_words=["party hat"], params=params)
    assert running["reconstruction"]["reused"] is True
    assert running["eta_seconds"] is not None and running["total"] == 100_000
    assert final["iteration"] - at_cancel <= 25, (at_cancel, final["iteration"])
    # The worker is free again and the reconstruction still ran only once.
    reconstructions = stack.client.get(f"/v1/scenes/{stack.scene['id']}/reconstructions").json()
    assert [r["run_count"] for r in reconstructions] == [1]


def test_killed_worker_resumes_the_edit_from_its_checkpoint(stack):
    """SIGKILL the worker mid-edit and start a new one: the job goes on from the last checkpoint."""
    if stack.broker != "embedded":
        pytest.skip("Redis redelivers only after the visibility timeout (hours); the SQL broker path is re-queued")
    from datetime import datetime

    total = 60
    params = {**PARAMS, "iterations": total, "export": {**PARAMS["export"], "gif": False, "mesh": False}}
    job = create_job(stack, prompt="a yarn doll of a mic", params=params)
    wait_for_event(stack.client, stack.service, job["id"], checkpoint_at_least("edit", 10), what="an edit checkpoint")
    stack.service.kill_worker()
    at_kill = job_events(stack.client, job["id"])
    stack.service.start_worker()
    seen: list[dict] = []
    final = poll_job(stack.client, stack.service, job["id"], seen=seen)
    assert final["state"] == "succeeded", f"{final}\n{stack.diagnostics()}"
    assert final["completed_stages"] == ["reconstruct", "edit", "export"]
    # Resumed from its last checkpoint (every 10 iterations), not from iteration 0; the restarted worker
    # re-queued it, and no edit progress the resumed run recorded was below where it resumed.
    events = job_events(stack.client, job["id"])
    at = check_resumed_from_the_last_checkpoint(at_kill, events, total, 10)
    assert [e["stage"] for e in events if e["kind"] == "requeued"] == ["edit"], events
    resumed_at = datetime.fromisoformat(next(e["at"] for e in events if e["kind"] == "resumed"))
    later = [j["iteration"] for j in seen if j["stage"] == "edit" and j["total"]
             and datetime.fromisoformat(j["updated_at"]) >= resumed_at]
    assert min(later, default=at) >= at, (at, later)
    # Complete: every artifact listed, each download matching its recorded size and sha256.
    verify_artifacts(stack.client, final, RESUMED_ARTIFACTS, stack.root)


def test_job_listing(stack):
    jobs = stack.client.get("/v1/jobs", params={"scene_id": stack.scene["id"], "limit": 2}).json()
    runs = 4 if stack.broker == "embedded" else 3  # the embedded run also has the killed-worker job
    assert jobs["total"] == runs and len(jobs["items"]) == 2 and jobs["limit"] == 2
    succeeded = stack.client.get("/v1/jobs", params={"state": "succeeded"}).json()
    assert succeeded["total"] == runs - 1 and {j["state"] for j in succeeded["items"]} == {"succeeded"}
    canceled = stack.client.get("/v1/jobs", params={"state": "canceled", "offset": 0}).json()
    assert canceled["total"] == 1
    assert stack.client.get("/v1/jobs", params={"state": "bogus"}).status_code == 422


@pytest.mark.parametrize("stage", ["reconstruct", "refine", "export"])
def test_cancel_during_each_stage(stack, stage):
    """Cancellation reads the job's flag in the database (no broker involved): the embedded run covers it."""
    if stack.broker != "embedded":
        pytest.skip("cancellation does not depend on the broker")
    params = {**PARAMS, "iterations": 5}
    if stage == "reconstruct":  # parameters of their own: a fresh fit, far too long to finish
        params["reconstruction"] = {**RECONSTRUCTION, "iterations": [2000, 2000, 2000]}
    elif stage == "refine":
        params["refine"] = {**PARAMS["refine"], "iterations": 100_000}
    else:
        params["export"] = {**PARAMS["export"], "turntable_frames": 1000, "turntable_size": 64}
    mode = {"mode": "local", "edit_words": ["sunglasses"]} if stage == "refine" else {"mode": "global"}
    _, final, _ = cancel_during(stack, stage, prompt="a mic wearing big sunglasses", params=params, **mode)
    if stage == "reconstruct":  # the canceled fitter handed the reconstruction back for a later job
        rec = next(r for r in stack.client.get(f"/v1/scenes/{stack.scene['id']}/reconstructions").json()
                   if r["id"] == final["reconstruction"]["id"])
        assert rec["state"] == "pending" and rec["run_count"] == 1, rec


def test_nothing_shared_but_storage(stack):
    """With S3 storage nothing is written to a local storage folder; the worker used its own scratch."""
    if stack.broker != "redis":
        pytest.skip("the embedded setup uses local storage on purpose")
    assert not (stack.root / "storage").exists()
    assert (stack.root / "worker-work" / "scenes").is_dir()  # the worker's own copy of the dataset
    assert not (stack.root / "work" / "scenes").exists()  # the API never unpacks for the worker
