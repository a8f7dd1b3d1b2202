"""The Vox-E job service: a thin FastAPI layer over ``voxe_core`` (scenes, jobs, artifacts)."""
