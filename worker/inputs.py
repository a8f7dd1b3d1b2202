"""What a stage reads: the job's scene and its images, and grids from the storage (cached in the job's scratch,
reused while they are the recorded bytes)."""

from __future__ import annotations

from voxe_service.models import READY, Job, Scene
from voxe_service.storage import StoredObject
from worker import runtime


def job_scene(job: Job) -> Scene:
    """The job's scene (ready: jobs on a processing scene are only sent once its ingest is done)."""
    with runtime.session_scope() as session:
        scene = session.get(Scene, job.scene_id)
        if scene is None:
            raise RuntimeError(f"scene {job.scene_id} was deleted")
        if scene.state != READY:
            raise RuntimeError(f"scene {job.scene_id} is {scene.state}, not ready{f': {scene.error}' if scene.error else ''}")
        return scene


def load_images(job: Job, rec_params: dict, settings, storage):
    """The scene's images as the reconstruction parameters ask (split, downsampling, filter, count)."""
    from voxe_core.data import load_scene

    # Reconstructions stored before the option existed were fitted on box-filtered images.
    resample = rec_params.get("resample", "box")
    with runtime.scene_dataset(job_scene(job), settings, storage) as root:
        return load_scene(root, rec_params["split"], rec_params["downsample"], rec_params["max_images"],
                          resample=resample)


def fetch_grid(job_id: str, name: str, settings, storage, stored: StoredObject | None = None):
    """A recorded grid (default: the job's artifact ``name``), downloaded once into the job's scratch."""
    from voxe_core.backbones import load_grid as load_grid_file

    stored = stored or runtime.recorded_artifact(job_id, name)
    path = runtime.fetch(storage, stored, runtime.scratch_dir(job_id, settings) / name)
    return load_grid_file(path)
