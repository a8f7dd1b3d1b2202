"""Celery workers of the Vox-E service: thin tasks that run the voxe_core stages of a job."""
