"""The OpenAPI document tells the truth: requests drawn from its own JSON schemas (``from_schema`` below) are
accepted unless a rule the document states in words refuses them, and requests it forbids are refused; every
status the middleware and handlers answer (400, 405, OPTIONS) is documented, with a correct ``Allow``."""

from __future__ import annotations

import asyncio
import copy
import gzip
import json

import jsonschema
import pytest
from fastapi import HTTPException
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service_helpers import reset_service_caches, service_env
from test_service_api import _published_render, dataset, make_scene  # noqa: F401 - the fixture

# Refusals for reasons a JSON schema cannot state (they relate two fields, or the scene); each is said in the
# document's descriptions of the fields involved.
BEYOND_SCHEMA = (
    "edit_words is required for a local edit", "does not occur in the prompt", "names nothing",
    "cover the whole prompt", "apply to local edits only", "webhook_events needs a webhook_url", "takes one value or one per stage",
    "cannot give backbone 'scene'", "needs a scene uploaded as a mesh", "tokens as the model sees it",
    # (has no words: beyond single ASCII characters, no pattern every validator reads alike states it)
    "lift_start='constant' with iterations=0", "has no words", "max_images 1 keeps a single image",
)
HOOK = "http://127.0.0.1:9/hook"
LIMITED = settings(max_examples=60, deadline=None, database=None,
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


@pytest.fixture
def root(tmp_path, monkeypatch):
    env = service_env(tmp_path, VOXE_MAX_ACTIVE_JOBS_PER_KEY="100000", VOXE_WEBHOOK_ALLOW_NETWORKS="127.0.0.0/8")
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    yield tmp_path
    reset_service_caches()


@pytest.fixture
def client(root):
    from api.main import create_app

    with TestClient(create_app(), raise_server_exceptions=False) as test_client:
        yield test_client


@pytest.fixture
def spec(client) -> dict:
    return client.get("/openapi.json").json()


def from_schema(schema: dict, components: dict | None = None) -> st.SearchStrategy:
    """Values valid under ``schema``: the JSON-schema keywords the document uses (hypothesis-jsonschema 0.23 no
    longer runs on this hypothesis). Patterns are drawn with Python's ``re``, as pydantic-core's checks read them."""
    components = components if components is not None else schema.get("components", {}).get("schemas", {})
    draw = lambda sub: from_schema(sub, components)  # noqa: E731
    if "$ref" in schema:
        return st.deferred(lambda: draw(components[schema["$ref"].rsplit("/", 1)[-1]]))
    if "const" in schema:
        return st.just(schema["const"])
    if "enum" in schema:
        return st.sampled_from(schema["enum"])
    if "anyOf" in schema:
        siblings = {k: v for k, v in schema.items() if k not in ("anyOf", "default")}  # apply to every variant
        return st.one_of([draw({**siblings, **variant}) for variant in schema["anyOf"]])
    kind = schema.get("type")
    if kind == "null":
        return st.none()
    if kind == "boolean":
        return st.booleans()
    if kind == "integer":
        return st.integers(schema.get("minimum"), schema.get("maximum"))
    if kind == "number":
        low, high = schema.get("minimum", schema.get("exclusiveMinimum")), schema.get("maximum")
        return st.floats(low, high, exclude_min="exclusiveMinimum" in schema, allow_nan=False, allow_infinity=False)
    if kind == "string":
        low, high = schema.get("minLength", 0), schema.get("maxLength", 60)
        text = st.from_regex(schema["pattern"]) if "pattern" in schema else st.text(min_size=low, max_size=high)
        return text.filter(lambda v: low <= len(v) <= high)
    if kind == "array":
        return st.lists(draw(schema.get("items", {})), min_size=schema.get("minItems", 0),
                        max_size=min(schema.get("maxItems", 5), 5), unique_by=repr if schema.get("uniqueItems") else None)
    if kind == "object" or "properties" in schema:
        properties, required = schema.get("properties", {}), set(schema.get("required", ()))
        return st.fixed_dictionaries({k: draw(v) for k, v in properties.items() if k in required},
                                     optional={k: draw(v) for k, v in properties.items() if k not in required})
    raise NotImplementedError(f"no strategy for {schema}")


def body_schema(spec: dict, name: str, **fixed: dict) -> dict:
    """The component ``name`` as a standalone JSON schema (its refs resolvable), with ``fixed`` properties replaced."""
    schema = copy.deepcopy(spec["components"]["schemas"][name])
    schema["properties"].update(fixed)
    return {**schema, "components": {"schemas": spec["components"]["schemas"]}}


def refusal_reasons(response) -> list[str]:
    detail = response.json()["detail"]
    return [e["msg"] for e in detail] if isinstance(detail, list) else [detail]


def post_json(client, path: str, body) -> object:
    return client.post(path, content=json.dumps(body), headers={"content-type": "application/json"})


def test_job_bodies_the_document_allows_are_accepted_unless_a_stated_cross_field_rule_refuses(
        client, spec, dataset, root):  # noqa: F811
    scene = make_scene(client, dataset, root)
    schema = body_schema(spec, "JobCreate", scene_id={"const": scene["id"]},
                         webhook_url={"anyOf": [{"const": HOOK}, {"type": "null"}]})
    outcomes = {"accepted": 0, "beyond": 0}

    @LIMITED
    @given(from_schema(schema))
    def allowed(body):
        response = post_json(client, "/v1/jobs", body)
        if response.status_code == 201:
            outcomes["accepted"] += 1
            return
        assert response.status_code == 422, response.text
        reasons = refusal_reasons(response)
        assert all(any(rule in reason for rule in BEYOND_SCHEMA) for reason in reasons), reasons
        outcomes["beyond"] += 1

    allowed()
    assert outcomes["accepted"] > 0  # the property was not met by refusing everything


# What breaks one constraint of a JSON value: the wrong JSON type, or just past a bound the schema states.
def _breakers(schema: dict) -> list:
    out = [{"unexpected": "object"}]
    kind = schema.get("type")
    if kind == "boolean":
        out += [1, 0, "true"]
    if kind == "integer":
        out += [1.5, "5", True]
        out += [schema["maximum"] + 1] if "maximum" in schema else []
        out += [schema["minimum"] - 1] if "minimum" in schema else []
    if kind == "number":
        out += ["1", True]
        out += [schema["maximum"] * 2 + 1] if "maximum" in schema else []
        out += [schema["minimum"] - 1] if "minimum" in schema else []
        out += [schema["exclusiveMinimum"]] if "exclusiveMinimum" in schema else []
    if kind == "string":
        out += [5, ""] + (["x" * (schema["maxLength"] + 1)] if "maxLength" in schema else [])
    if "enum" in schema:
        out += ["not-" + str(schema["enum"][0])]
    if kind == "array":
        out += ["a string"] + ([[]] if schema.get("minItems") else [])
    return out


def _leaves(schema: dict, components: dict, path=()):
    """(path, schema) of every property, depth first, refs followed and nullable anyOf unwrapped."""
    if "$ref" in schema:
        schema = components[schema["$ref"].rsplit("/", 1)[-1]]
    for name, prop in schema.get("properties", {}).items():
        variants = [v for v in prop.get("anyOf", [prop]) if v.get("type") != "null"]
        for variant in variants:
            resolved = components[variant["$ref"].rsplit("/", 1)[-1]] if "$ref" in variant else variant
            yield path + (name,), resolved
            if "properties" in resolved:
                yield from _leaves(resolved, components, path + (name,))


def _set(body: dict, path: tuple, value) -> dict:
    body = copy.deepcopy(body)
    node = body
    for name in path[:-1]:
        node = node.setdefault(name, {})
        if not isinstance(node, dict):
            return body
    node[path[-1]] = value
    return body


FORBIDDEN_CASES = [  # (path, body component, a body the schema allows; None: a job on the test's scene)
    ("/v1/jobs", "JobCreate", None),
    ("/v1/evaluations", "EvaluationCreate", {"job_ids": ["x"], "object": "mic"}),
    ("/v1/sweeps", "SweepCreate", {"scenes": [{"scene_id": "x", "object": "mic"}]}),
]


@pytest.mark.parametrize("path,component,base", FORBIDDEN_CASES)
def test_bodies_the_document_forbids_are_refused(client, spec, dataset, root, path, component, base):  # noqa: F811
    components = spec["components"]["schemas"]
    schema = body_schema(spec, component)
    mutations = [(name, value) for name, leaf in _leaves(components[component], components)
                 for value in _breakers(leaf)] + [(("params", "bogus"), 1), (("bogus",), 1)]
    if base is None:
        scene = make_scene(client, dataset, root)
        base = {"scene_id": scene["id"], "prompt": "a mic wearing big sunglasses", "mode": "local",
                "edit_words": ["sunglasses"]}
        assert post_json(client, path, base).status_code == 201
    jsonschema.validate(base, schema)
    # Every mutation, not a sample: hypothesis' 60 draws of the ~260 had let one field the server accepts past the
    # document's bound go unseen in most runs.
    for mutation in mutations:
        body = _set(base, *mutation)
        with pytest.raises(jsonschema.ValidationError):  # the document forbids it ...
            jsonschema.validate(body, schema)
        response = post_json(client, path, body)
        assert response.status_code == 422, (mutation, response.text)  # ... and so does the server


@pytest.mark.parametrize("path", ["/v1/jobs", "/v1/scenes"])
def test_listing_queries_follow_their_documented_parameters(client, spec, path):
    parameters = {p["name"]: p["schema"] for p in spec["paths"][path]["get"]["parameters"]}
    # A cursor is what a page's next_cursor gives (documented so), not any text its schema allows.
    query = st.fixed_dictionaries({}, optional={name: from_schema(schema) for name, schema in parameters.items()
                                                if name != "cursor"})

    @LIMITED
    @given(query)
    def allowed(params):
        params = {k: v for k, v in params.items() if v is not None}
        response = client.get(path, params=params)
        assert response.status_code == 200, (params, response.text)

    allowed()
    bad_values = [("limit", 0), ("limit", parameters["limit"]["maximum"] + 1), ("offset", -1), ("limit", "1.5"),
                  ("cursor", "x"), ("cursor", "x" * (parameters["cursor"]["anyOf"][0]["maxLength"] + 1))]
    for name, bad in bad_values + ([("state", "sleeping")] if "state" in parameters else []):
        response = client.get(path, params={name: bad})
        assert response.status_code == 422 and name in response.text, (name, bad)


@pytest.mark.parametrize("path", ["/v1/jobs", "/v1/scenes"])
def test_the_listings_document_their_cursor(spec, path):
    """A listing takes the ``cursor`` its page's ``next_cursor`` gives, not with ``offset``; both documented."""
    operation = spec["paths"][path]["get"]
    parameters = {p["name"]: p for p in operation["parameters"]}
    assert "next_cursor" in parameters["cursor"]["description"] and "offset" in parameters["cursor"]["description"]
    assert "cursor" in parameters["offset"]["description"]
    page = spec["components"]["schemas"][operation["responses"]["200"]["content"]["application/json"]["schema"]
                                         ["$ref"].split("/")[-1]]
    assert "next_cursor" in page["required"] and "cursor" in page["properties"]["next_cursor"]["description"]
    assert "cursor" in operation["responses"]["422"]["description"]


def test_a_query_parameter_not_taken_or_sent_twice_is_a_documented_422_naming_it(client, spec):
    """``GET /v1/jobs?stat=running`` (a typo) had listed every job, and ``?limit=1&limit=500`` read the last value,
    where a proxy or a cache may read the first."""
    for method, url, detail in (
            ("GET", "/v1/jobs?stat=running", "unknown query parameter(s) 'stat': GET /v1/jobs takes 'state', "
                                             "'scene_id', 'limit', 'offset', 'cursor'"),
            ("GET", "/v1/scenes?offset=0&z=1&a=", "unknown query parameter(s) 'a', 'z': GET /v1/scenes takes 'limit', "
                                                  "'offset', 'cursor'"),
            ("GET", "/v1/jobs/x/artifacts/y?download=1", "unknown query parameter(s) 'download': GET "
                                                         "/v1/jobs/{job_id}/artifacts/{name} takes none"),
            ("POST", "/v1/jobs/x/cancel?force=1", "unknown query parameter(s) 'force': POST /v1/jobs/{job_id}/cancel "
                                                  "takes none"),
            ("POST", "/v1/scenes?name=x", "unknown query parameter(s) 'name': POST /v1/scenes takes none"),
            ("GET", "/v1/jobs?limit=1&state=queued&limit=500&state=failed",
             "query parameter(s) 'limit', 'state' sent more than once: send each once"),
            ("GET", "/v1/jobs?" + "&".join(f"{n}{'y' * 50}=1" for n in range(7)),  # 5 named, each cut to 40
             "unknown query parameter(s) " + ", ".join(repr(f"{n}{'y' * 39}...") for n in range(5)) + " and 2 more: "
             "GET /v1/jobs takes 'state', 'scene_id', 'limit', 'offset', 'cursor'")):
        response = client.request(method, url)
        assert (response.status_code, response.json()["detail"]) == (422, detail), url
        path = url.split("?")[0].replace("/x/", "/{job_id}/").replace("/y", "/{name}")
        assert "a query parameter the operation does not take" in (
            spec["paths"][path][method.lower()]["responses"]["422"]["description"]), path
    assert client.head("/v1/jobs?stat=running").status_code == 422  # HEAD as the GET
    assert client.get("/v1/jobs?limit=1&offset=0&state=queued&scene_id=x").status_code == 200
    assert client.get("/healthz?probe=1").status_code == 200  # outside /v1: a prober's own parameters pass


def test_each_422_body_is_one_its_documented_schema_admits(client, spec):
    """The strict checks' 422s send their detail as a string, where an operation's own 422 was documented as
    FastAPI's HTTPValidationError only (detail: an array): the merged document described no such answer."""
    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    for path, method, response in (
            ("/v1/jobs", "get", client.get("/v1/jobs?stat=running")),  # unknown query parameter
            ("/v1/jobs", "get", client.get("/v1/jobs?limit=1&limit=2")),  # sent twice
            ("/v1/jobs", "get", client.get("/v1/jobs?limit=x")),  # FastAPI's own
            ("/v1/jobs/{job_id}", "get", client.get("/v1/jobs/x?verbose=1")),
            ("/v1/jobs", "post", client.post("/v1/jobs?dry=1", json={})),
            ("/v1/scenes", "post", client.post("/v1/scenes", files={"files": ("t.obj", obj), "bogus": (None, "1")})),
            ("/v1/scenes", "post", client.post("/v1/scenes", files=[("files", ("t.obj", obj)), ("name", (None, "a")),
                                                                    ("name", (None, "b"))])),
            ("/v1/scenes", "post", client.post("/v1/scenes", files={"name": (None, "x" * 300)}))):  # FastAPI's own
        assert response.status_code == 422, (path, response.text)
        documented = spec["paths"][path][method]["responses"]["422"]["content"]["application/json"]["schema"]
        jsonschema.validate(response.json(), {**documented, "components": spec["components"]})
    for path, item in spec["paths"].items():  # every 422 states a body: one a client can check (a HEAD's has none)
        for method, operation in item.items():
            if "422" in operation["responses"] and method != "head":
                assert "schema" in operation["responses"]["422"]["content"]["application/json"], (method, path)


def test_strict_types_refuse_coercions(client):
    for params in ({"view_words": 1}, {"iterations": "5"}, {"iterations": 5.0}, {"export": {"gif": "true"}}):
        response = post_json(client, "/v1/jobs", {"scene_id": "x", "prompt": "a mic", "params": params})
        assert response.status_code == 422, (params, response.text)
    words = post_json(client, "/v1/jobs", {"scene_id": "x", "prompt": "a mic", "mode": "local", "edit_words": "mic"})
    assert words.status_code == 422 and "edit_words" in words.text  # a list is documented: no string for one


def test_prompt_pattern_states_the_text_rule():
    """The patterns refuse nothing the server accepts; the prompt's is exact for single ASCII characters (beyond them,
    and for texts such as a contraction's ending alone, "'s", the description says the rule), the edit word's
    everywhere. (As JavaScript reads them: tests/test_ui.py.)"""
    from api.schemas import EDIT_WORD_PATTERN, TEXT_PATTERN, clean_text
    import re

    for text in ("a mic", "é", "'", "mic\t\n", "mic\x1f", "!!!", "  ", "mic\x00", "mic\x7f", "\x85x", "?\x9f",
                 "\U0001f3a9", "\u2665 ", "\x1c\x85", "\x85", "猫", "½", *map(chr, range(0x80))):
        for pattern, need_words in ((TEXT_PATTERN, True), (EDIT_WORD_PATTERN, False)):
            try:
                clean_text(text, "text", need_words)
                server = True
            except ValueError:
                server = False
            matched = bool(re.search(pattern, text))
            assert matched == server or (matched and need_words and not text.isascii()), (repr(text), pattern)


def test_the_text_fields_descriptions_state_the_special_tokens_refused(spec):
    """Every field of text the model reads (a pattern of clean_text's) says that CLIP's special tokens written out
    are refused: the 422 had been stated nowhere in the document."""
    from api.schemas import CLIP_SPECIAL_TOKENS, EDIT_WORD_PATTERN, TEXT_PATTERN

    stated = []
    for name, schema in spec["components"]["schemas"].items():
        for field, prop in schema.get("properties", {}).items():
            if {prop.get("pattern"), prop.get("items", {}).get("pattern")} & {TEXT_PATTERN, EDIT_WORD_PATTERN}:
                stated.append(f"{name}.{field}")
                assert all(token in prop["description"] for token in CLIP_SPECIAL_TOKENS), (name, field)
    assert sorted(stated) == ["EvaluationCreate.object", "JobCreate.edit_words", "JobCreate.prompt",
                              "SweepScene.object"]



def test_edit_word_pattern_read_as_json_schema_states_the_server_rule():
    """A JSON Schema pattern is ECMA-262's: its \\s lacks \\x1c-\\x1f and \\x85 (str.split() splits at them) and
    has \\ufeff (it does not), so the published pattern had said "\\x1c" was an edit word and "\\ufeff" was none."""
    from api.schemas import EDIT_WORD_PATTERN, clean_text
    import re

    ecma_space = r"\t\n\v\f\r \xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000\ufeff"
    as_ecma = EDIT_WORD_PATTERN.replace(r"\s", ecma_space)  # (only ever inside a class)
    for code in [*range(0x3001), 0xfeff]:
        try:
            clean_text(chr(code), "an edit word", need_words=False)
            server = True
        except ValueError:
            server = False
        assert bool(re.search(as_ecma, chr(code))) == server, hex(code)


def test_webhook_url_pattern_read_as_json_schema_states_the_server_rule(spec):
    """The published webhook_url pattern excluded whitespace as \\s, which ECMA-262 (a JSON Schema pattern's dialect)
    and the server's check read apart: a URL holding \\x85 was valid to the document and refused by the server, one
    holding \\ufeff the other way round. Its classes now spell the characters out, in escapes ECMA-262 and Python's
    re read alike, and it takes what the server's check takes, in the host and in the path: checked at each end of
    each of its classes' ranges and beside it, for every whitespace character (refused), and for characters beyond
    the BMP (two code units each to ECMA-262 without the u flag, neither excluded). But for the rule of every string,
    which the field's description states: a NUL character and a lone surrogate (U+D800-U+DFFF) are 422s of their own
    (Strict), which the pattern does not say."""
    import re

    from pydantic import ValidationError

    from api.schemas import JobCreate

    webhook_url = spec["components"]["schemas"]["JobCreate"]["properties"]["webhook_url"]
    (published,) = [s["pattern"] for s in webhook_url["anyOf"] if "pattern" in s]
    one = r"\\[tnvfr]|\\x[0-9a-f]{2}|\\u[0-9a-f]{4}|[^\\\]]"
    escapes = {"t": "\t", "n": "\n", "v": "\v", "f": "\f", "r": "\r"}

    def code(written: str) -> int:
        return ord(written) if len(written) == 1 else ord(escapes.get(written[1]) or chr(int(written[2:], 16)))

    classes = re.findall(r"\[\^((?:\\.|[^\\\]])*)\]", published)
    ranges = [(code(low), code(high or low))
              for body in classes for low, high in re.findall(f"({one})(?:-({one}))?", body)]
    assert len(classes) == 2 and (0x2000, 0x200a) in ranges and (ord("#"), ord("#")) in ranges
    every_strings_rule = {0: "value_error", 0xd800: "string_unicode", 0xdbff: "string_unicode",
                          0xdc00: "string_unicode", 0xdfff: "string_unicode"}
    near_the_ends = {c + step for low, high in ranges for c in (low, high) for step in (-1, 0, 1)}
    beyond_the_bmp = {0x10000, 0x1f600, 0x20000, 0xe0041, 0x10ffff}
    whitespace = {c for c in range(0x110000) if chr(c).isspace()} | {0xfeff}  # str.split()'s, and ECMA-262's \s

    def refusal(url: str) -> str | None:
        """The type of the server's error for a job sending ``url``; None when it takes it."""
        try:
            JobCreate.model_validate({"scene_id": "x", "prompt": "a mic", "webhook_url": url})
        except ValidationError as exc:
            return exc.errors()[0]["type"]
        return None

    for probe in sorted(near_the_ends | whitespace | beyond_the_bmp | set(every_strings_rule) | {ord("a"), 0xe9}):
        for url in (f"http://h{chr(probe)}x/hook", f"http://h/{chr(probe)}"):
            document_takes = bool(re.fullmatch(published, url))
            if probe in every_strings_rule:  # refused as any string holding it is, whatever its pattern says
                assert (document_takes, refusal(url)) == (True, every_strings_rule[probe]), (hex(probe), url)
            else:
                assert document_takes == (refusal(url) is None) != (probe in whitespace), (hex(probe), url)
    assert "NUL" in webhook_url["description"] and "U+D800" in webhook_url["description"]


def test_malformed_json_is_a_documented_400(client, spec):
    for path in ("/v1/jobs", "/v1/evaluations", "/v1/sweeps"):
        response = client.post(path, content=b'{"prompt": ', headers={"content-type": "application/json"})
        assert response.status_code == 400 and response.json()["detail"].startswith("malformed JSON body"), path
        assert "400" in spec["paths"][path]["post"]["responses"]
    assert client.post("/v1/jobs", json={"prompt": 1}).status_code == 422  # JSON, but not the schema's: 422
    body = b'{"scene_id": "x", "prompt": "a mic"}'  # JSON sent as text had been a 422 echoing the body as a string
    for headers, named in (({"content-type": "text/plain"}, "text/plain"), ({}, "no media type")):
        response = client.post("/v1/jobs", content=body, headers=headers)
        assert response.status_code == 415 and response.json()["detail"] == (
            f"the body must be sent as JSON (Content-Type: application/json), not as {named}")
        assert "415" in spec["paths"]["/v1/jobs"]["post"]["responses"]
    plus_json = {"content-type": "application/merge-patch+json"}
    # JSON under a +json type is read (no such scene), and one not the schema's is its 422, not a 415 "not JSON"
    assert client.post("/v1/jobs", content=body, headers=plus_json).status_code == 404
    response = client.post("/v1/jobs", content=b"[]", headers=plus_json)
    assert (response.status_code, response.json()["detail"][0]["type"]) == (422, "model_attributes_type")


def test_a_415_quotes_the_media_type_sent_cut_short_and_as_written(client):
    """The 415s naming the media type sent (a body not sent as JSON, an upload not sent as a form, a body sent to an
    operation taking none) quoted the whole Content-Type, 5,000 characters of it back in the message, and its UTF-8
    read as Latin-1 ("text/plän" as 'text/plã¤n'). They quote it as written, cut as the other quoted headers are."""
    long_type = "text/" + "x" * 5000
    for path, said in (("/v1/jobs", "the body must be sent as JSON (Content-Type: application/json), not as "),
                       ("/v1/scenes", "the body must be sent as a form (multipart/form-data, as curl -F sends it), "
                                      "not as "),
                       ("/v1/jobs/x/cancel", "POST /v1/jobs/{job_id}/cancel takes no body: send none (got 2 bytes of ")):
        for sent, shown in ((long_type, "text/" + "x" * 95 + "..."), ("text/plän", "text/plän")):
            response = client.post(path, content=b"{}", headers={"content-type": sent.encode()})
            assert response.status_code == 415, (path, response.text[:200])
            detail = response.json()["detail"]
            assert detail.startswith(said + shown) and len(detail) < 300, (path, detail[:300])


def test_an_upload_not_sent_as_a_form_is_a_documented_415_and_a_broken_form_a_documented_400(client, spec):
    """A raw zip or JSON posted to /v1/scenes had been read as an empty form: a 422 telling to send an 'archive' it
    had been sent; sent as a urlencoded form (curl --data-binary's default), which cannot carry a file, as field
    names: a 422 naming them, the whole body (1.9 MB for a 900 KiB zip). Starlette's 400 for a multipart body it
    cannot parse was answered but not documented."""
    raw_zip = b"PK\x03\x04" + bytes(range(256)).replace(b"&", b"").replace(b"=", b"") * 400 + b"PK\x05\x06"
    for body, sent_as in ((raw_zip, "application/zip"), (b'{"archive": "scene.zip"}', "application/json"),
                          (raw_zip, "application/x-www-form-urlencoded"), (raw_zip, None)):
        response = client.post("/v1/scenes", content=body, headers={"content-type": sent_as} if sent_as else {})
        assert (response.status_code, response.json()["detail"]) == (
            415, "the body must be sent as a form (multipart/form-data, as curl -F sends it), not as "
                 f"{sent_as or 'no media type'}"), sent_as
    for length in ("0", "00"):  # no body, however its length is written: the 422 naming what to send
        response = client.post("/v1/scenes", headers={"content-length": length})
        assert response.status_code == 422 and response.json()["detail"].startswith("send either one zip"), length
    broken = client.post("/v1/scenes", content=b"x", headers={"content-type": "multipart/form-data"})
    assert (broken.status_code, broken.json()["detail"]) == (400, "Missing boundary in multipart.")
    assert {"400", "415"} <= set(spec["paths"]["/v1/scenes"]["post"]["responses"])
    assert client.get("/v1/scenes").json()["total"] == 0


def test_a_body_sent_with_a_content_encoding_is_a_documented_415_naming_it(client, spec):
    """Content-Encoding was never read: a gzipped JSON body (a client or proxy compressing requests) was a 400
    "malformed JSON body: it is not UTF-8", a gzipped upload Starlette's 400 "Invalid multipart data.", and a plain
    body labelled gzip was read as if unencoded. Such a body is a 415 naming the coding, with Accept-Encoding:
    identity (RFC 9110 §15.5.16), before any of it is read; identity is no coding."""
    job = b'{"scene_id": "x", "prompt": "a mic"}'
    form = client.build_request("POST", "/v1/scenes", files={"archive": ("a.zip", b"PK\x05\x06" + bytes(18))})
    for path, body, sent_as in (("/v1/jobs", gzip.compress(job), "application/json"),
                                ("/v1/jobs", job, "application/json"),
                                ("/v1/sweeps", gzip.compress(b'{"scenes": []}'), "application/json"),
                                ("/v1/scenes", gzip.compress(form.read()), form.headers["content-type"])):
        for coding in ("gzip", "GZip", "identity, gzip", "br"):
            refused = client.post(path, content=body, headers={"content-type": sent_as, "content-encoding": coding})
            assert (refused.status_code, refused.json()["detail"]) == (
                415, f"the body was sent with Content-Encoding {coding!r}: send it unencoded (only identity is "
                     "read)"), (path, coding)
            assert refused.headers["accept-encoding"] == "identity"
        assert "Content-Encoding" in spec["paths"][path]["post"]["responses"]["415"]["description"], path
    plain = client.post("/v1/jobs", content=job, headers={"content-type": "application/json",
                                                          "content-encoding": "identity"})
    assert plain.status_code == 404  # read: no such scene
    assert client.get("/v1/scenes").json()["total"] == 0 and client.get("/v1/jobs").json()["total"] == 0


def test_json_naming_a_member_twice_is_a_documented_400_naming_it(client, spec, dataset, root):  # noqa: F811
    """``json.loads`` keeps a duplicate name's last value silently: ``{"prompt": "a", "prompt": "b"}`` had made a job
    of "b", though a proxy or the client's own checks may read the first."""
    scene = make_scene(client, dataset, root)
    job = f'"scene_id": "{scene["id"]}", "mode": "global", "prompt": "a red mic"'
    for path, body, named in (
            ("/v1/jobs", '{%s, "prompt": "a blue mic"}' % job, "prompt"),
            ("/v1/jobs", '{%s, "params": {"seed": 1, "iterations": 5, "seed": 2}}' % job, "seed"),
            ("/v1/evaluations", '{"job_ids": ["x"], "object": "mic", "object": "hat"}', "object"),
            ("/v1/sweeps", '{"scenes": [{"scene_id": "x", "object": "a", "scene_id": "y"}]}', "scene_id")):
        response = client.post(path, content=body, headers={"content-type": "application/json"})
        assert (response.status_code, response.json()["detail"]) == (
            400, f"malformed JSON body: an object names the member {named!r} twice (which one counts is undefined: "
                 "send it once)"), (path, body)
        assert "names a member twice" in spec["paths"][path]["post"]["responses"]["400"]["description"]
    assert client.get("/v1/jobs").json()["total"] == 0
    refused = client.post("/v1/jobs/x/cancel", content='{"a": 1, "a": 2}', headers={"content-type": "application/json"})
    assert refused.status_code == 415  # a route taking no body parses none: any body sent to it is refused as such
    same_name_apart = '{%s, "params": {"seed": 1, "reconstruction": {"seed": 2}}}' % job  # one name per object
    assert client.post("/v1/jobs", content=same_name_apart, headers={"content-type": "application/json"}
                       ).status_code == 201


def test_a_json_body_is_parsed_once_checking_its_member_names(client, monkeypatch):
    """The duplicate-name check had parsed each JSON body a second time, on the event loop (an 8 MB body: 596 ->
    918 ms): FastAPI's one parse checks it."""
    body = b'{"scene_id": "x", "prompt": "a mic"}'
    parses = []

    def counting(text, *args, **kwargs):
        parses.extend([text] if text == body else [])
        return loads(text, *args, **kwargs)

    loads = json.loads
    monkeypatch.setattr(json, "loads", counting)
    response = client.post("/v1/jobs", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 404 and parses == [body]  # no such scene: read, once


def test_a_client_gone_mid_json_body_is_fastapis_400_not_a_500(client):
    """The duplicate-name check read the body itself, outside FastAPI's handling of a failed read: a client gone
    mid-body (Starlette's ClientDisconnect) had been an unhandled error, a 500 and its traceback."""
    messages = iter([{"type": "http.request", "body": b'{"scene_id": "x", ', "more_body": True},
                     {"type": "http.disconnect"}])
    sent = []

    async def receive():
        return next(messages)

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": "/v1/jobs", "raw_path": b"/v1/jobs", "root_path": "", "query_string": b"",
             "server": ("127.0.0.1", 80), "client": ("127.0.0.1", 5),
             "headers": [(b"host", b"127.0.0.1"), (b"content-type", b"application/json")]}
    asyncio.run(client.app(scope, receive, send))
    assert [m["status"] for m in sent if m["type"] == "http.response.start"] == [400]
    assert json.loads(b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")) == {
        "detail": "There was an error parsing the body"}


def test_a_json_body_over_its_own_limit_is_a_documented_413_naming_it(client, spec):
    """JSON bodies had been allowed up to the upload limit (VOXE_MAX_UPLOAD_BYTES, 2 GiB), each read whole and
    parsed on the event loop; the largest job, sweep or evaluation the schemas allow is under 100 KiB. Any body but
    a multipart form has the limit: FastAPI reads a text/plain one (or one of no media type) whole before its 415,
    and a JSON route's limit had been escaped by naming another type."""
    padding = b" " * (1 << 20)  # whitespace: valid JSON, only its size refuses it
    body = b'{"scene_id": "x", "prompt": "a mic"' + padding + b"}"
    over = (413, f"JSON body (any body but an upload's multipart form) over the limit of {1 << 20} bytes "
                 "(VOXE_MAX_JSON_BODY_BYTES)")
    for streamed in (False, True):  # by Content-Length, and counted while it streams
        for path, sent_as in (("/v1/jobs", "application/json"), ("/v1/jobs", "text/plain"), ("/v1/jobs", None),
                              ("/v1/sweeps", "application/x-www-form-urlencoded"), ("/v1/scenes", "application/zip")):
            content = iter([body[:1000], body[1000:]]) if streamed else body
            response = client.post(path, content=content, headers={"content-type": sent_as} if sent_as else {})
            if path == "/v1/scenes" and streamed:  # the upload's 415 comes first, before any of the body is read
                assert response.status_code == 415, sent_as
                continue
            assert (response.status_code, response.json()["detail"]) == over, (path, sent_as, streamed)
    assert "VOXE_MAX_JSON_BODY_BYTES" in spec["paths"]["/v1/jobs"]["post"]["responses"]["413"]["description"]
    under = b'{"scene_id": "x", "prompt": "a mic"' + padding[:-100] + b"}"
    assert client.post("/v1/jobs", content=under, headers={"content-type": "application/json"}).status_code == 404


def test_json_that_python_cannot_read_is_a_400_naming_why(client):
    """JSON with a number past Python's int-string conversion limit, bytes not UTF-8, or nesting past the recursion
    limit: ``json.loads`` raises no JSONDecodeError for them, and FastAPI had answered a bare "There was an error
    parsing the body"."""
    long_number = b'{"scene_id": "x", "prompt": "a mic", "params": {"seed": ' + b"7" * 5000 + b"}}"
    for path, body, reason in (
            ("/v1/jobs", long_number, "a number has more than 4300 digits"),
            ("/v1/sweeps", long_number, "a number has more than 4300 digits"),
            ("/v1/jobs", b'{"prompt": "a \xff mic"}', "it is not UTF-8 (invalid start byte at byte 14)"),
            ("/v1/jobs", b"[" * 100_000, "its arrays or objects nest too deeply")):
        response = client.post(path, content=body, headers={"content-type": "application/json"})
        assert (response.status_code, response.json()) == (400, {"detail": f"malformed JSON body: {reason}"}), path
    assert client.post("/v1/jobs", json={"scene_id": "x", "prompt": "a mic", "params": {"seed": 10**4299}}
                       ).status_code == 422  # 4300 digits parse: the schema refuses the seed


def test_options_and_405_answer_each_paths_documented_methods(client, spec):
    for path, item in spec["paths"].items():
        concrete = path.replace("{", "").replace("}", "")  # any value fills a path parameter
        documented = sorted({m.upper() for m in item} | ({"HEAD"} if "get" in item else set()))  # HEAD as GET
        response = client.options(concrete)
        assert response.status_code == 204 and response.headers["allow"] == ", ".join(documented), path
        missing = next(m for m in ("PUT", "PATCH", "DELETE", "POST") if m not in documented)
        refused = client.request(missing, concrete)
        assert refused.status_code == 405 and refused.headers["allow"] == ", ".join(documented), (path, missing)
        assert "405" in item["options"]["responses"]


def test_the_ui_s_static_files_answer_options_and_405_with_the_methods_they_serve(client):
    """Inside the /static mount the 405 handler had read the path under the mount ("/app.js"): OPTIONS said only
    OPTIONS was served, and a POST's 405 named OPTIONS as the one method allowed, though GET serves the file."""
    assert client.get("/static/app.js").status_code == 200
    assert client.options("/static/app.js").headers["allow"] == "GET, HEAD, OPTIONS"
    refused = client.post("/static/app.js")
    assert refused.status_code == 405 and refused.headers["allow"] == "GET, HEAD, OPTIONS"
    assert refused.json()["detail"] == "method POST is not allowed on /static/app.js; allowed: GET, HEAD, OPTIONS"


def test_a_405_shows_a_long_path_cut(client):
    """Regression: a 405 echoed the whole path, the client's, of any length (PUT /v1/jobs/<5000 x>: a 5 kB detail)."""
    refused = client.put(f"/v1/jobs/{'x' * 5000}")
    assert refused.status_code == 405 and refused.json()["detail"] == (
        f"method PUT is not allowed on /v1/jobs/{'x' * 91}...; allowed: GET, HEAD, OPTIONS")


def test_behind_a_proxy_prefix_the_405_still_names_the_paths_methods(client):
    """``uvicorn --root-path /api``: the request path carries the prefix ("/api/v1/jobs"), the routes do not. The
    detail names the path as requested, with its prefix (it had said "/v1/jobs", a path the client never sent)."""
    import anyio
    import httpx

    async def refuse():
        transport = httpx.ASGITransport(client.app, root_path="/api")
        async with httpx.AsyncClient(transport=transport, base_url="http://proxy") as proxied:
            return await proxied.delete("/api/v1/jobs"), await proxied.post("/api/static/app.js")

    sent_with_prefix = anyio.run(refuse)  # uvicorn's shape: the path holds the prefix
    with TestClient(client.app, root_path="/api") as proxied:  # a server that leaves the prefix out of the path
        sent_without = proxied.delete("/v1/jobs"), proxied.post("/static/app.js")
    for refused, static in (sent_with_prefix, sent_without):
        assert refused.status_code == 405 and refused.headers["allow"] == "GET, HEAD, OPTIONS, POST"
        assert refused.json()["detail"] == (
            "method DELETE is not allowed on /api/v1/jobs; allowed: GET, HEAD, OPTIONS, POST")
        assert static.status_code == 405 and static.headers["allow"] == "GET, HEAD, OPTIONS"
        assert static.json()["detail"] == "method POST is not allowed on /api/static/app.js; allowed: GET, HEAD, OPTIONS"
    with TestClient(client.app, root_path="/api") as proxied:  # an escaped "?" named as sent, not as a query
        assert proxied.put("/v1/jobs/a%3Fb").json()["detail"] == (
            "method PUT is not allowed on /api/v1/jobs/a%3Fb; allowed: GET, HEAD, OPTIONS")


def test_each_proxy_prefix_reads_its_own_servers_in_the_document(client):
    """One service reached under two prefixes and directly: FastAPI 0.132.0, which pyproject.toml had allowed, kept
    the first request's prefix as every later document's ``servers`` (Try it out and generated clients calling the
    other prefix's paths); 0.132.1 names each request's own."""
    import tomllib
    from importlib.metadata import version
    from pathlib import Path

    from packaging.requirements import Requirement

    for prefix in ("/api", "/b", ""):
        with TestClient(client.app, root_path=prefix) as reached:
            assert reached.get(f"{prefix}/openapi.json").json().get("servers") == (
                [{"url": prefix}] if prefix else None), prefix
    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    required = next(r for r in map(Requirement, project["dependencies"]) if r.name == "fastapi")
    assert not required.specifier.contains("0.132.0") and required.specifier.contains(version("fastapi"))


def test_every_v1_operation_documents_auth_and_body_statuses(spec):
    for path, item in spec["paths"].items():
        for method, operation in item.items():
            if path.startswith("/v1") and method != "options":
                assert "401" in operation["responses"] and operation["security"], (method, path)
            if method in ("delete", "post"):
                assert "413" in operation["responses"], (method, path)


def test_with_auth_on_options_needs_no_key_and_the_rest_answer_the_documented_401(root, monkeypatch):
    from api.main import create_app

    monkeypatch.setenv("VOXE_AUTH", "on")
    reset_service_caches()
    with TestClient(create_app()) as client:
        spec = client.get("/openapi.json").json()
        assert client.options("/v1/jobs").headers["allow"] == "GET, HEAD, OPTIONS, POST"
        refused = client.get("/v1/jobs")
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
        assert "401" in spec["paths"]["/v1/jobs"]["get"]["responses"]
        assert set(spec["components"]["securitySchemes"]) == {"bearer", "apiKey"}


def test_the_idempotency_key_header_is_documented_with_the_length_the_server_enforces(client, spec):
    header = next(p for p in spec["paths"]["/v1/jobs"]["post"]["parameters"] if p["name"] == "Idempotency-Key")
    longest = header["schema"]["maxLength"]
    body = {"scene_id": "x", "prompt": "a mic"}
    assert client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k" * longest}).status_code == 404
    assert client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k" * (longest + 1)}).status_code == 422
    # characters, as the schema counts them, not the bytes of their UTF-8 (a 200-character key had been "400")
    assert client.post("/v1/jobs", json=body, headers={"Idempotency-Key": ("é" * longest).encode()}).status_code == 404
    too_long = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": ("é" * (longest + 1)).encode()})
    assert too_long.status_code == 422 and too_long.json()["detail"] == \
        f"Idempotency-Key header must be 1-{longest} characters, got {longest + 1}"
    from api.auth import idempotency_key

    with pytest.raises(HTTPException) as not_utf8:  # b"caf\xe9" as Starlette hands it over (TestClient sends UTF-8)
        idempotency_key(b"caf\xe9".decode("latin-1"))
    assert (not_utf8.value.status_code, not_utf8.value.detail) == (422, "Idempotency-Key header must be UTF-8 text")


def test_idempotent_operations_document_the_409_of_a_deleted_original(spec):
    """A retry whose first request's resource was deleted answers 409 (test_service_access); clients generated from
    the document must know that answer."""
    idempotent = {(path, method) for path, operations in spec["paths"].items() for method, operation in operations.items()
                  if any(p["name"] == "Idempotency-Key" for p in operation.get("parameters", []))}
    assert {("/v1/scenes", "post"), ("/v1/jobs", "post")} <= idempotent
    for path, method in idempotent:
        assert "deleted" in spec["paths"][path][method]["responses"]["409"]["description"], (path, method)


def test_the_one_line_headers_read_from_every_line_are_documented_as_strings(spec):
    """Range, If-Range and Last-Event-ID are read from all their lines, but each is one string: their parameters had
    been typed list[str], so the document (and clients generated from it, Swagger's form) made them arrays."""
    documented = {(path, parameter["name"].lower()): parameter["schema"]
                  for path, operations in spec["paths"].items() for operation in operations.values()
                  for parameter in operation.get("parameters", []) if parameter["in"] == "header"}
    artifact, events = "/v1/jobs/{job_id}/artifacts/{name}", "/v1/jobs/{job_id}/events"
    for key in ((artifact, "range"), (artifact, "if-range"), (events, "last-event-id")):
        assert documented[key]["anyOf"] == [{"type": "string"}, {"type": "null"}], (key, documented[key])


def test_a_retry_s_200_documents_the_body_and_header_it_answers_with(client, spec, dataset, root):  # noqa: F811
    """A retry with the same Idempotency-Key answers 200 with the resource the first request created and
    ``Idempotent-Replayed: true``, but the document gave that 200 no body: a client generated from it read the replay
    as empty (the job it had made lost to it)."""
    idempotent = {(path, method) for path, operations in spec["paths"].items() for method, operation in operations.items()
                  if any(p["name"] == "Idempotency-Key" for p in operation.get("parameters", []))}
    assert {("/v1/scenes", "post"), ("/v1/jobs", "post"), ("/v1/evaluations", "post"), ("/v1/sweeps", "post")} <= idempotent
    for path, method in idempotent:
        responses = spec["paths"][path][method]["responses"]
        assert responses["200"]["content"] == responses["201"]["content"], (path, method)
        assert "Idempotent-Replayed" in responses["200"]["headers"], (path, method)
    scene = make_scene(client, dataset, root)
    body = {"scene_id": scene["id"], "prompt": "a mic made of gold", "mode": "global"}
    first = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "retry-1"})
    retry = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "retry-1"})
    assert (first.status_code, retry.status_code, retry.headers["idempotent-replayed"]) == (201, 200, "true")
    documented = spec["paths"]["/v1/jobs"]["post"]["responses"]["200"]["content"]["application/json"]["schema"]
    jsonschema.validate(retry.json(), {**documented, "components": spec["components"]})
    assert retry.json()["id"] == first.json()["id"]


def test_a_download_documents_its_bytes_and_a_head_none(client, spec, root):
    """A download's 200 and 206 were documented with no body (FastAPI's for a streamed answer), so a client generated
    from the document read an artifact as empty; the HEAD's 200 was documented as JSON, which it never sends."""
    operations = spec["paths"]["/v1/jobs/{job_id}/artifacts/{name}"]
    _, url = _published_render(root)
    for code, headers in (("200", {}), ("206", {"Range": "bytes=0-9"})):
        got = client.get(url, headers=headers)
        assert got.status_code == int(code) and got.content == b"A" * len(got.content) and got.content
        (media_range, documented), = operations["get"]["responses"][code]["content"].items()
        assert media_range == "*/*" and documented["schema"] == {"type": "string", "format": "binary"}, code
        assert got.headers["content-type"] == "image/png"  # (the artifact's own type, which */* admits)
        assert "content" not in operations["head"]["responses"][code], code
        assert client.head(url, headers=headers).content == b""


def test_no_answer_of_a_head_is_documented_with_a_body(client, spec, root):
    """The 401, 422 and 503 the document adds to every /v1 operation were given a JSON Problem body on the artifact's
    HEAD too, which answers none (a client generated from it would wait for one)."""
    heads = {path: item["head"] for path, item in spec["paths"].items() if "head" in item}
    assert heads
    for path, operation in heads.items():
        for code in ("401", "422", "503"):
            assert code in operation["responses"], (path, code)
        for code, answer in operation["responses"].items():
            assert "content" not in answer, (path, code)
    _, url = _published_render(root)
    refused = client.head(url + "?unknown=1")
    assert refused.status_code == 422 and refused.content == b""


def test_each_error_a_route_documents_states_the_body_it_answers_with(client, spec, root):
    """The errors each route documents itself (a 404, 409, 412, 416, 429) had no body in the document, though each
    answers {"detail": "..."}: a client generated from it could not read why it was refused. (A HEAD's have none.)"""
    for path, item in spec["paths"].items():
        for method, operation in item.items():
            if path.startswith("/v1") and method not in ("head", "options"):
                for code, answer in operation["responses"].items():
                    if code[0] in "45":
                        assert "schema" in answer["content"]["application/json"], (method, path, code)
    job_id, url = _published_render(root)
    for path, method, response in (
            ("/v1/jobs/{job_id}", "get", client.get("/v1/jobs/no-such-job")),
            ("/v1/jobs/{job_id}/cancel", "post", client.post(f"/v1/jobs/{job_id}/cancel")),  # it succeeded
            ("/v1/jobs/{job_id}/artifacts/{name}", "get", client.get(url, headers={"Range": "bytes=9999-"})),
            ("/v1/jobs/{job_id}/artifacts/{name}", "get", client.get(url, headers={"If-Match": '"other"'}))):
        assert response.status_code in (404, 409, 416, 412), (path, response.text)
        documented = spec["paths"][path][method]["responses"][str(response.status_code)]
        schema = documented["content"]["application/json"]["schema"]
        jsonschema.validate(response.json(), {**schema, "components": spec["components"]})
