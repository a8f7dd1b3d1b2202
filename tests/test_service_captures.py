"""A real capture end to end over real HTTP (a uvicorn API and a Celery worker as subprocesses, the embedded setup):
ten photos of ``../shared/data/fox`` (a phone capture: instant-ngp transforms.json with lens distortion) uploaded as
a zip, and a local edit run through every stage.

What a capture job does differently from an object's, and what is checked here: the worker picks the scene
backbone on its own (photos with no transparent background) and fits it in the canonical frame of the capture's
cameras; the edit takes SPEC §5's schedule (5,000 iterations, annealing from 3,000 every 400) where the job
leaves the iteration count at its default; the refinement's graph cut stays in the foreground cube and its merge
is exact; the renders and the turntable look at G_i's orbit centre (where the fitted object sits). The model is
the random-weight SMOKE-TEST Stable Diffusion (VOXE_SDS_MODEL=tiny): plumbing and geometry, never edit quality.
"""

from __future__ import annotations

import io
import json
import os

import httpx
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from needs import FOX, require_data
from service_helpers import poll_job, service, verify_artifacts, wait_for_scene, zip_folder

pytestmark = pytest.mark.slow

FRAMES = slice(0, 50, 5)  # ten photos spread over the capture's arc
DOWNSAMPLE = 32  # 1080x1920 photos -> 33x60
RECONSTRUCTION = {"resolution": 17, "iterations": [3, 12], "rays_per_step": 256}  # no backbone: "auto"; the scene preset: 2 stages
SHORT_EDIT = 2
PARAMS = {
    "downsample": DOWNSAMPLE, "iterations": SHORT_EDIT, "render_size": 32, "preview_every": 0,
    "reconstruction": RECONSTRUCTION,
    "refine": {"iterations": 10, "views": 2, "render_size": 32, "rays_per_step": 512},
    "export": {"views": 2, "view_size": 32, "turntable_frames": 4, "turntable_size": 48},  # helpers read 48 px videos
}
PROMPT, EDIT_WORDS = "a fox wearing big sunglasses", ["sunglasses"]
CAPTURE_ARTIFACTS = {"initial_grid.safetensors", "edited_grid.safetensors", "refined_grid.safetensors",
                     "mask.safetensors", "attention_probabilities.safetensors", "mask_overlay.png", "render_000.png",
                     "render_001.png", "turntable.mp4", "turntable.gif", "mesh.ply", "mesh.glb", "mesh.obj",
                     "mesh.mtl", "preview.png"}


def fox_subset(dest):
    """fox's transforms.json cut to ``FRAMES``, its photos linked (not copied) beside it."""
    meta = json.loads((FOX / "transforms.json").read_text())
    meta["frames"] = meta["frames"][FRAMES]
    for frame in meta["frames"]:
        target = dest / frame["file_path"]
        target.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(FOX / frame["file_path"], target)
    (dest / "transforms.json").write_text(json.dumps(meta))
    return dest


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """(client, service, scene, the subset's folder, the service's root) with the fox subset uploaded and ingested."""
    require_data(FOX)
    root = tmp_path_factory.mktemp("service-capture")
    folder = fox_subset(root / "fox_subset")
    archive = zip_folder(folder, root / "fox.zip", prefix="fox")
    with service(root / "service") as svc, httpx.Client(base_url=svc.base, timeout=60) as client:
        with open(archive, "rb") as handle:
            response = client.post("/v1/scenes", files={"archive": ("fox.zip", handle, "application/zip")})
        assert response.status_code == 201, response.text
        scene = wait_for_scene(client, svc, response.json()["id"])
        yield client, svc, scene, folder, root


def create_job(client, scene_id: str, **body) -> dict:
    response = client.post("/v1/jobs", json={"scene_id": scene_id, **body})
    assert response.status_code == 201, response.text
    return response.json()


def test_a_capture_is_ingested_as_the_photos_it_holds(capture):
    _, _, scene, _, _ = capture
    assert scene["state"] == "ready" and scene["error"] is None, scene
    assert scene["format"] == "instant_ngp" and scene["image_count"] == 10
    assert (scene["width"], scene["height"]) == (1080, 1920)


def test_a_local_edit_of_a_capture_runs_every_stage_on_the_scene_backbone(capture):
    from voxe_core.data import load_scene
    from voxe_core.export import render_views, turntable_cameras
    from voxe_core.presets import edit_config, reconstruct_config, reconstruction_params
    from voxe_core.refine.cut import node_mask
    from voxe_core.refine.pipeline import merge
    from voxe_core.scene_grid import SceneGrid, scene_frame

    client, svc, scene, folder, root = capture
    job = create_job(client, scene["id"], prompt=PROMPT, mode="local", edit_words=EDIT_WORDS, params=PARAMS)
    assert job["params"]["reconstruction"]["backbone"] == "auto"
    job = poll_job(client, svc, job["id"], timeout=400)
    assert job["state"] == "succeeded", f"{job}\n{svc.diagnostics()}"
    assert job["completed_stages"] == ["reconstruct", "edit", "refine", "export"]
    grids = verify_artifacts(client, job, CAPTURE_ARTIFACTS, root)
    initial, edited = grids["initial_grid.safetensors"], grids["edited_grid.safetensors"]
    refined, mask = grids["refined_grid.safetensors"], grids["mask"]

    # Reconstruct: "auto" chose the scene backbone, in the frame of the photos' own cameras.
    assert isinstance(initial, SceneGrid) and initial.resolution == (17,) * 3
    cameras = load_scene(folder, "train", DOWNSAMPLE).cameras
    assert torch.allclose(initial.frame, scene_frame(cameras), atol=1e-5)
    # The fit's recipe, recorded by the worker for progress to weigh it by (voxe_service.progress.FitWork).
    fitted = reconstruct_config(reconstruction_params(job["params"]), backbone="scene")
    assert job["result"]["fit"] == {"backbone": "scene", "steps": fitted.total_iterations,
                                    "rays_per_step": fitted.rays_per_step}

    # Edit: SPEC §5's annealing for a scene G_i, run for the count the job asked; the defaults are §5's 5,000.
    assert job["result"]["edit_schedule"] == {"backbone": "scene", "iterations": SHORT_EDIT, "i_start": 3000,
                                              "every": 400, "floor": 0.35}
    defaults = edit_config({**job["params"], "iterations": None}, backbone=initial.kind)
    assert (defaults.iterations, defaults.schedule.i_start, defaults.schedule.every) == (5000, 3000, 400)
    assert isinstance(edited, SceneGrid) and edited.header() == initial.header()
    assert not torch.equal(edited.features, initial.features)

    # Refine: a non-empty cut among the foreground's occupied vertices; the refined grid is exactly the merge.
    assert mask.any() and not (mask & ~initial.object_vertices()).any()
    assert not (mask & ~node_mask(edited, rule="maxpool")).any()
    assert isinstance(refined, SceneGrid) and torch.equal(refined.features, merge(initial, edited, mask).features)

    # Export: the renders look at G_i's orbit centre (recorded on the job); the mesh is of the foreground.
    centre = initial.orbit_centre()
    assert torch.equal(torch.tensor(job["result"]["orbit_centre"]), centre)  # exact: float32 -> JSON -> float32
    options = job["params"]["export"]
    expected = render_views(refined, turntable_cameras(2, options["elevation"], options["view_size"], centre=centre))
    for i in range(2):
        served = client.get(f"/v1/jobs/{job['id']}/artifacts/render_{i:03d}.png").content
        image = np.asarray(Image.open(io.BytesIO(served)).convert("RGB"), dtype=np.float32) / 255.0
        assert np.abs(image - expected[i].numpy()).max() <= 1.0 / 255 + 1e-6, i
    mesh_vertices = np.asarray(trimesh.load(root / f"downloads-{job['id']}" / "mesh.ply").vertices)
    assert len(mesh_vertices) and np.abs(mesh_vertices).max() <= initial.foreground_extent + 1e-4


def test_a_capture_job_left_at_the_default_count_edits_for_5000_iterations(capture):
    """The stored schedule of a job with the default edit parameters, canceled once its edit has begun."""
    client, svc, scene, _, _ = capture
    params = {"downsample": DOWNSAMPLE, "render_size": 32, "preview_every": 0, "reconstruction": RECONSTRUCTION}
    job = create_job(client, scene["id"], prompt="a wood carving of a fox", mode="global", params=params)
    running = poll_job(client, svc, job["id"], timeout=300, until=lambda j: (
        j["stage"] == "edit" and j["total"] and (j["result"] or {}).get("edit_schedule"))
        or j["state"] in ("succeeded", "failed", "canceled"))
    assert running["state"] == "running", f"{running}\n{svc.diagnostics()}"
    assert running["result"]["edit_schedule"] == {"backbone": "scene", "iterations": 5000, "i_start": 3000,
                                                  "every": 400, "floor": 0.35}
    assert running["total"] == 5000
    assert client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 200
    assert poll_job(client, svc, job["id"], timeout=120)["state"] == "canceled"
