"""A Python client of the Vox-E job service's HTTP API (``/v1``), over httpx.

    from voxe_client import Client

    with Client("http://127.0.0.1:8000", api_key="...") as client:
        scene = client.upload_scene("mic.zip")
        job = client.create_job(scene["id"], "a mic made of gold")
        job = client.wait(job["id"], on_progress=lambda p: print(p["overall_progress"]))  # live, over SSE
        client.download(job["id"], "turntable.mp4", "out/turntable.mp4")  # size and sha256 checked
        sweep = client.create_sweep([{"scene_id": scene["id"], "object": "microphone"}])

Errors the service answers with (4xx / 5xx) and unreachable services are :class:`ServiceError` (its
``service_failed`` tells a 5xx or an unreachable service from a refusal); a ``wait(job_id, timeout=...)`` past its
timeout is a :class:`JobWaitTimeout` (a ``TimeoutError``) naming the job and its last state.
"""

from voxe_client.client import Client, JobWaitTimeout, ServiceError

__all__ = ["Client", "JobWaitTimeout", "ServiceError"]
