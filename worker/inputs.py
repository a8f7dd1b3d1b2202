"""What a stage reads: the job's scene and its images, and grids from the storage (cached in the job's scratch,
reused while they are the recorded bytes)."""

from __future__ import annotations

from voxe_service.models import READY, Job, Reconstruction, Scene
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


def recorded_initial_grid(job_id: str, rec: Reconstruction) -> StoredObject | None:
    """G_i as the job's reconstruct stage recorded it (its ``initial_grid.safetensors``), which its later stages and
    an evaluation of it read: the reconstruction's grid is that one unless the fit was made again since (its grid
    deleted from the storage: ``worker.tasks._reconstruct``), and reading the new fit had worked from another G_i than
    the stages before. The reconstruction's own for a job that recorded none; None when it has none either."""
    try:
        return runtime.recorded_artifact(job_id, "initial_grid.safetensors")
    except RuntimeError:  # none recorded
        return None if rec.grid_key is None else runtime.reconstruction_grid(rec)


def fetch_grid(job_id: str, name: str, settings, storage, stored: StoredObject | None = None):
    """A recorded grid (default: the job's artifact ``name``), downloaded once into the job's scratch."""
    from voxe_core.backbones import load_grid as load_grid_file

    stored = stored or runtime.recorded_artifact(job_id, name)
    path = runtime.fetch(storage, stored, runtime.scratch_dir(job_id, settings) / name)
    return load_grid_file(path)
