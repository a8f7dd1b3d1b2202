"""A Python client of the Vox-E job service's HTTP API (``/v1``), over httpx.

    from voxe_client import Client

    with Client("http://127.0.0.1:8000", api_key="...") as client:
        sweep = client.create_sweep([{"scene_id": scene_id, "object": "microphone"}])
        sweep = client.get_sweep(sweep["id"])

Errors the service answers with (4xx / 5xx) and unreachable services are :class:`ServiceError`.
"""

from voxe_client.client import Client, ServiceError

__all__ = ["Client", "ServiceError"]
