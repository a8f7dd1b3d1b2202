"""``Client``: one httpx connection pool to the service, one method per call, errors as ``ServiceError``."""

from __future__ import annotations

from typing import Any

import httpx

DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_TIMEOUT_S = 60.0


class ServiceError(Exception):
    """The service answered with an error status (its detail is the message), or could not be reached.

    ``status`` is the HTTP status (None when the service was not reached) and ``detail`` its ``detail`` field.
    """

    def __init__(self, message: str, status: int | None = None, detail: Any = None):
        super().__init__(message)
        self.status = status
        self.detail = detail


class Client:
    """The job service at ``base_url``; ``api_key`` goes as ``Authorization: Bearer`` (none on a loopback service).

    Use it as a context manager (or call :meth:`close`) to release its connections. ``transport``
    replaces httpx's network transport (tests pass ``httpx.MockTransport``).

    Examples:
        >>> def answer(request):
        ...     return httpx.Response(404, json={"detail": "scene 'nope' not found"})
        >>> with Client(transport=httpx.MockTransport(answer)) as client:
        ...     try:
        ...         client.get_sweep("nope")
        ...     except ServiceError as error:
        ...         print(error.status, error)
        404 GET /v1/sweeps/nope: HTTP 404: scene 'nope' not found
    """

    def __init__(self, base_url: str = DEFAULT_URL, api_key: str | None = None, timeout: float = DEFAULT_TIMEOUT_S,
                 transport: httpx.BaseTransport | None = None):
        self.base_url = base_url.rstrip("/")
        headers = {"accept": "application/json"}
        if api_key:
            headers["authorization"] = f"Bearer {api_key}"
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout, transport=transport)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def request(self, method: str, path: str, body: dict | None = None) -> Any:
        """The decoded JSON answer of ``method path`` (``body`` sent as JSON); ServiceError for an error status."""
        try:
            response = self._http.request(method, path, json=body)
        except httpx.TransportError as exc:
            raise ServiceError(f"cannot reach the service at {self.base_url}: {exc}") from None
        if response.is_error:
            try:
                detail = response.json().get("detail")
            except (ValueError, AttributeError):
                detail = response.reason_phrase
            raise ServiceError(f"{method} {path}: HTTP {response.status_code}: {detail}", response.status_code, detail)
        return response.json()

    # ------------------------------------------------------------------ sweeps (SPEC §4)
    def create_sweep(self, scenes: list[dict], params: dict | None = None, evaluation: dict | None = None) -> dict:
        """``POST /v1/sweeps``: every scene ({scene_id, object}) × the paper's six prompts, each edit then evaluated."""
        body: dict = {"scenes": scenes}
        if params is not None:
            body["params"] = params
        if evaluation is not None:
            body["evaluation"] = evaluation
        return self.request("POST", "/v1/sweeps", body)

    def get_sweep(self, sweep_id: str) -> dict:
        """``GET /v1/sweeps/{id}``: the jobs' states and the summary table."""
        return self.request("GET", f"/v1/sweeps/{sweep_id}")
