"""The UI's HTTP headers (in-process, no browser): its caching, its Content-Security-Policy and the security
headers on every answer; and what its page's markup tells assistive technology. tests/test_ui.py checks in Chromium
that the pages work under that policy."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import pytest
from fastapi.testclient import TestClient

from service_helpers import reset_service_caches, service_env

SECURITY = {"x-content-type-options": "nosniff", "x-frame-options": "DENY"}


@pytest.fixture
def client(tmp_path, monkeypatch):
    for key, value in service_env(tmp_path).items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from api.main import create_app

    with TestClient(create_app()) as test_client:
        yield test_client
    reset_service_caches()


def test_pages_forbid_framing_and_foreign_code_and_answer_head(client):
    for path in ("/", "/docs"):
        for method in ("GET", "HEAD"):
            response = client.request(method, path)
            assert response.status_code == 200, (method, path)
            policy = response.headers["content-security-policy"]
            assert "default-src 'self'" in policy and "frame-ancestors 'none'" in policy
            assert SECURITY.items() <= response.headers.items()
    assert "'unsafe-inline'" not in client.get("/").headers["content-security-policy"]
    docs_policy = client.get("/docs").headers["content-security-policy"]
    assert "script-src 'self' 'sha256-" in docs_policy
    assert "img-src 'self' data: blob:" in docs_policy  # Swagger UI shows an image answer from a blob: URL


def test_no_form_of_a_page_sends_its_fields_elsewhere(client):
    """form-action, which default-src does not cover, had been in neither policy: a form injected into a page (or one
    of the UI's own submitted before app.js ran) could send its fields to any site. The UI sends each form itself."""
    assert "form-action 'none'" in client.get("/").headers["content-security-policy"].split("; ")
    assert "form-action 'self'" in client.get("/docs").headers["content-security-policy"].split("; ")


def test_the_page_served_as_a_static_file_carries_the_ui_s_policy_too(client):
    """The page is also /static/index.html, which had been served with no Content-Security-Policy at all."""
    for path in ("/static/index.html", "/static/app.js"):
        assert client.get(path).headers.get("content-security-policy") == client.get("/").headers[
            "content-security-policy"], path


def test_api_answers_carry_the_security_headers_too(client):
    for response in (client.get("/v1/jobs"), client.get("/v1/jobs/nope"), client.get("/healthz")):
        assert SECURITY.items() <= response.headers.items(), response.request.url


def test_an_unhandled_errors_500_carries_them_too(tmp_path, monkeypatch):
    """Starlette answers it outside every middleware: it had had neither header."""
    for key, value in service_env(tmp_path).items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from api.main import create_app

    app = create_app()

    @app.get("/broken")
    def broken():
        raise RuntimeError("a bug")

    with TestClient(app, raise_server_exceptions=False) as client:
        response = client.get("/broken")
    reset_service_caches()
    assert response.status_code == 500 and response.text == "Internal Server Error"
    assert SECURITY.items() <= response.headers.items()



def test_the_app_s_own_files_are_revalidated_and_vendored_ones_cached(client):
    for name in ("app.js", "app.css"):
        assert client.get(f"/static/{name}").headers["cache-control"] == "no-cache"
    vendored = client.get("/static/vendor/model-viewer-3.5.0/model-viewer.min.js")
    assert "max-age=31536000" in vendored.headers["cache-control"]


STATUS_LINES = ("key-state", "upload-status")  # what a key or an upload came to: "this key is refused", "failed"


class PageControls(HTMLParser):
    """The page's form fields, each with whether it has a label (one around it, one naming its id, or an
    aria-label), and its error slots (``data-error-for``) and STATUS_LINES with their attributes."""

    def __init__(self):
        super().__init__()
        self.open_labels = 0
        self.labelled_ids: set[str] = set()
        self.fields: list[tuple[str, bool]] = []
        self.field_attributes: list[dict] = []
        self.error_slots: list[dict] = []

    def handle_starttag(self, tag, attrs):
        attributes = dict(attrs)
        if tag == "label":
            self.open_labels += 1
            self.labelled_ids.add(attributes.get("for"))
        elif tag in ("input", "select", "textarea") and attributes.get("type") != "hidden":
            self.fields.append((attributes.get("id") or attributes.get("name"),
                                bool(self.open_labels or attributes.get("aria-label"))))
            self.field_attributes.append(attributes)
        if "data-error-for" in attributes or attributes.get("id") in STATUS_LINES:
            self.error_slots.append(attributes)

    def handle_endtag(self, tag):
        if tag == "label":
            self.open_labels -= 1


def test_every_field_is_labelled_and_every_error_is_announced(client):
    """A screen reader names each field and reads out an error, or what a key or an upload came to, as it appears:
    the parameters' JSON had no label (its placeholder only), and no error slot or status line was a live region, so
    an upload or an edit refused, or a key refused, was said to nobody."""
    page = PageControls()
    page.feed(client.get("/").text)
    assert len(page.fields) > 10 and len(page.error_slots) > 10
    assert [name for name, labelled in page.fields if not (labelled or name in page.labelled_ids)] == []
    assert {slot.get("id") for slot in page.error_slots} >= set(STATUS_LINES)
    assert [slot.get("data-error-for") or slot["id"] for slot in page.error_slots
            if slot.get("aria-live") != "polite"] == []


def test_each_field_s_error_is_read_with_it(client):
    """A field's error slot (and the key field's status line) is its description (aria-describedby): a screen reader
    moving to a field refused had read nothing of why, the slot being no part of the field. A slot is a field's when
    it is named by the field's name (a 422's loc: "prompt", "params.iterations"); the upload's, by its three file
    fields."""
    page = PageControls()
    page.feed(client.get("/").text)
    slot_ids = {slot.get("data-error-for") or slot["id"]: slot.get("id") for slot in page.error_slots}
    described = {}
    for field in page.field_attributes:
        name = field.get("name")
        slot = ("upload" if field.get("type") == "file" else "key-state" if field.get("id") == "api-key"
                else next((s for s in (name, f"params.{name}") if s in slot_ids), None))
        if slot is not None:
            described[field.get("id") or f"{name}={field.get('value')}"] = (slot_ids[slot], field.get("aria-describedby"))
    assert len(described) == 15  # the upload name's among them
    assert {field: ids for field, ids in described.items() if ids[0] is None or ids[0] != ids[1]} == {}


def test_the_page_s_limit_on_a_scene_name_is_the_api_s(client):
    """app.js refuses a name over NAME_MOST characters before the upload: that is the document's maxLength of the
    upload's name, so the page refuses no name the API takes, and lets through none it refuses."""
    import re

    form = client.get("/openapi.json").json()["paths"]["/v1/scenes"]["post"]["requestBody"]["content"][
        "multipart/form-data"]["schema"]["$ref"].rsplit("/", 1)[1]
    name = client.get("/openapi.json").json()["components"]["schemas"][form]["properties"]["name"]
    [most] = [kind["maxLength"] for kind in name["anyOf"] if kind.get("type") == "string"]
    script = client.get("/static/app.js").text
    assert re.search(r"^const NAME_MOST = (\d+);", script, re.MULTILINE).group(1) == str(most)
    assert 'id="upload-name"' in client.get("/").text and "maxlength" not in client.get("/").text


def test_behind_a_proxy_prefix_the_page_and_docs_link_under_it(client):
    """``uvicorn --root-path /api`` behind a proxy that serves the service at /api: the page's links to its CSS, its
    scripts and /docs, and /docs' document and assets, had pointed at the proxy's top (/static/app.js, /openapi.json):
    the page came up bare, /docs with nothing to show."""
    from api.ui import inline_sources

    with TestClient(client.app, root_path="/api") as proxied:
        page = proxied.get("/api/").text
        links = re.findall(r'(?:href|src)="(/[^"]*)"', page)
        assert links and all(link.startswith("/api/") for link in links), links
        assert {"/api/static/app.js", "/api/static/app.css", "/api/docs"} <= set(links)
        for link in links:
            assert proxied.get(link).status_code == 200, link
        docs = proxied.get("/api/docs")
        assert "url: '/api/openapi.json'" in docs.text
        assets = re.findall(r'(?:href|src)="(/[^"]*)"', docs.text)
        assert assets and all(asset.startswith("/api/static/vendor/") for asset in assets), assets
        for link in assets:
            assert proxied.get(link).status_code == 200, link
        assert f"script-src 'self' {inline_sources(docs.text, 'script')};" in docs.headers["content-security-policy"]
        assert proxied.get("/api/openapi.json").json()["servers"] == [{"url": "/api"}]
    page, docs = client.get("/"), client.get("/docs")  # at the top, as before
    assert 'src="/static/app.js"' in page.text and "url: '/openapi.json'" in docs.text
    assert f"script-src 'self' {inline_sources(docs.text, 'script')};" in docs.headers["content-security-policy"]


def test_behind_a_proxy_prefix_the_page_as_a_static_file_links_under_it_too(client):
    """/api/static/index.html, the page reached as its file, had kept the file's links (/static/app.js, /docs) at the
    proxy's top: it came up bare. It is the page /api/ serves; at the top the file, as before."""
    from api.ui import STATIC_DIR

    with TestClient(client.app, root_path="/api") as proxied:
        as_file = proxied.get("/api/static/index.html")
        assert as_file.status_code == 200 and 'src="/api/static/app.js"' in as_file.text
        assert as_file.text == proxied.get("/api/").text
        assert as_file.headers["content-security-policy"] == proxied.get("/api/").headers["content-security-policy"]
        assert proxied.head("/api/static/index.html").status_code == 200
        assert proxied.post("/api/static/index.html").status_code == 405
    assert client.get("/static/index.html").content == (STATIC_DIR / "index.html").read_bytes()
