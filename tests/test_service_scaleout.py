"""Scale-out for real: two workers on one Redis, the metadata in SQLite and then in PostgreSQL (the deployment's
database), the objects in S3 (a real SeaweedFS), the API and the workers as subprocesses with their own scratch
folders.

The model is the random-weight SMOKE-TEST Stable Diffusion (VOXE_SDS_MODEL=tiny): the plumbing, not quality.
"""

from __future__ import annotations

import shutil

import pytest

from needs import MIC, missing, require_data
from service_helpers import job_events, poll_job, redis_server, service, small_mic, wait_for_scene, zip_folder

pytestmark = pytest.mark.slow

RECONSTRUCTION = {"preset": "fast", "resolution": 24, "iterations": [10, 10, 20], "rays_per_step": 1024}
EXPORT = {"views": 2, "view_size": 48, "turntable_frames": 8, "turntable_size": 48, "gif": False, "mesh": False}
PARAMS = {"downsample": 16, "max_images": 8, "iterations": 5, "render_size": 48, "reconstruction": RECONSTRUCTION,
          "export": EXPORT}


@pytest.fixture(scope="module")
def scene_zip(tmp_path_factory):
    require_data(MIC)
    folder = tmp_path_factory.mktemp("scene")
    return zip_folder(small_mic(folder / "mic", frames=3), folder / "mic.zip")


@pytest.mark.parametrize("database", ["sqlite", "postgres"])
def test_two_workers_on_one_redis_split_the_jobs_and_fit_one_reconstruction(tmp_path, request, scene_zip, database):
    """Two jobs on one scene and parameter set, two workers: each worker takes one job's first stage (a busy
    worker takes no second message), exactly one fits G_i, the other waits for it and reuses it."""
    if shutil.which("redis-server") is None:
        missing("redis-server is not installed (.ci/test installs it)")
    database_url = request.getfixturevalue("postgres_server").create_database() if database == "postgres" else None
    s3 = {**request.getfixturevalue("seaweedfs"), "VOXE_S3_BUCKET": f"voxe-scaleout-{database}"}
    with redis_server(tmp_path / "redis") as redis, \
            service(tmp_path, redis.url, {"VOXE_WORK_DIR": str(tmp_path / "work-a")}, database_url, **s3) as svc:
        svc.start_worker(suffix="-b", env={"VOXE_WORK_DIR": str(tmp_path / "work-b")})
        client = svc_client(svc)
        with open(scene_zip, "rb") as handle:
            response = client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")})
        assert response.status_code == 201, response.text
        scene = wait_for_scene(client, svc, response.json()["id"])
        assert scene["state"] == "ready", scene
        jobs = [client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": prompt, "params": PARAMS}).json()
                for prompt in ("a yarn doll of a mic", "a wood carving of a mic")]
        assert jobs[0]["reconstruction"]["id"] == jobs[1]["reconstruction"]["id"]
        finals = [poll_job(client, svc, job["id"]) for job in jobs]
        for final in finals:
            assert final["state"] == "succeeded", f"{final}\n{svc.diagnostics()}"

        reconstructions = client.get(f"/v1/scenes/{scene['id']}/reconstructions").json()
        assert [(r["state"], r["run_count"]) for r in reconstructions] == [("succeeded", 1)]
        assert sorted(f["reconstruction"]["reused"] for f in finals) == [False, True]
        workers = {svc.worker_name(), svc.worker_name("-b")}
        first_stage = [next(e["worker_hostname"] for e in job_events(client, job["id"])
                            if e["kind"] == "stage_started" and e["stage"] == "reconstruct") for job in jobs]
        assert set(first_stage) == workers, first_stage  # one job's reconstruct on each worker
        assert not (tmp_path / "storage").exists()  # every object went through S3


def svc_client(svc):
    import httpx

    return httpx.Client(base_url=svc.base, timeout=60)
