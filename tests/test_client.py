"""voxe_client: what it sends and how it reports the service's errors (httpx's MockTransport, no server).

The calls against a real service are in tests/test_evaluate.py (``voxe sweep`` end to end).
"""

from __future__ import annotations

import json

import httpx
import pytest

from voxe_client import Client, ServiceError


def test_it_sends_json_with_the_key_and_returns_the_answer():
    seen = []

    def answer(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(201, json={"id": "s1", "entries": []})

    with Client("http://svc.test/", api_key="k-123", transport=httpx.MockTransport(answer)) as client:
        scenes = [{"scene_id": "a", "object": "mic"}]
        assert client.create_sweep(scenes, evaluation={"views": 4}) == {"id": "s1", "entries": []}
        client.get_sweep("s1")
    post, get = seen
    assert (post.method, str(post.url)) == ("POST", "http://svc.test/v1/sweeps")
    assert json.loads(post.content) == {"scenes": scenes, "evaluation": {"views": 4}}  # no params: the service's
    assert post.headers["authorization"] == "Bearer k-123"
    assert (get.method, get.url.path) == ("GET", "/v1/sweeps/s1")


def test_error_statuses_name_the_call_the_status_and_the_detail():
    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/plain"):
            return httpx.Response(502, text="<html>bad gateway</html>")
        return httpx.Response(422, json={"detail": [{"loc": ["body", "scenes"], "msg": "lists a scene twice"}]})

    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ServiceError) as error:
            client.create_sweep([])
        assert error.value.status == 422 and error.value.detail[0]["msg"] == "lists a scene twice"
        assert str(error.value).startswith("POST /v1/sweeps: HTTP 422: [{")
        with pytest.raises(ServiceError, match=r"^GET /plain: HTTP 502: Bad Gateway$"):
            client.request("GET", "/plain")


def test_an_unreachable_service_is_a_service_error_naming_it():
    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused", request=request)

    with Client("http://127.0.0.1:9", transport=httpx.MockTransport(refuse)) as client:
        with pytest.raises(ServiceError, match="cannot reach the service at http://127.0.0.1:9: connection refused") as error:
            client.get_sweep("x")
    assert error.value.status is None
