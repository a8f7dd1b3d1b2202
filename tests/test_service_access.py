"""Access to the API: hashed keys, ownership (another key's resources are 404), the auth switch and its
loopback rule, per-key quotas (429, with Retry-After where waiting can clear it) and Idempotency-Key replay.
In-process (TestClient)."""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from datetime import timedelta

import anyio
import pytest
from fastapi.testclient import TestClient

from service_helpers import ingest, zip_folder
from test_service_api import BOTH_DATABASES, JOB, _reset, dataset, root, staged, stored_files  # noqa: F401 - fixtures
from test_service_faults import add_heartbeat, add_job, add_scene, db, job_row  # noqa: F401 - the reaper's fixtures


def _create_key(name: str, **quota) -> tuple[str, str]:
    from api.auth import create_key
    from voxe_service.db import session_scope

    with session_scope() as session:
        key, token = create_key(session, name, **quota)
        return key.id, token


def bearer(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture
def auth_client(root, monkeypatch):  # noqa: F811 - the fixture imported above
    monkeypatch.setenv("VOXE_AUTH", "on")
    _reset()
    from api.main import create_app

    with TestClient(create_app()) as client:
        yield client


@pytest.fixture
def local_client(root):  # noqa: F811
    """Authentication off (the embedded default on loopback): every request acts as the local key."""
    from api.main import create_app

    with TestClient(create_app()) as client:
        yield client


@pytest.fixture(scope="module")
def mic_zip(dataset, tmp_path_factory):  # noqa: F811
    return zip_folder(dataset, tmp_path_factory.mktemp("zips") / "mic.zip", prefix="mic_small")


def _upload(client, mic_zip, headers=None, name="mic.zip"):
    with open(mic_zip, "rb") as handle:
        return client.post("/v1/scenes", files={"archive": (name, handle, "application/zip")}, headers=headers or {})


# ------------------------------------------------------------------------------------------ keys
def test_requests_need_a_valid_live_key(auth_client, mic_zip):
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, utcnow

    for headers in ({}, bearer("voxe_000000000000_" + "x" * 43), bearer("garbage"), {"Authorization": "Basic abc"},
                    {"X-API-Key": "voxe_nope"}):
        response = auth_client.get("/v1/scenes", headers=headers)
        assert response.status_code == 401, headers
        assert response.headers["www-authenticate"] == "Bearer"
        assert "API key" in response.json()["detail"] and "api.admin create-key" in response.json()["detail"]
    key_id, token = _create_key("alice")
    assert auth_client.get("/v1/scenes", headers=bearer(token)).status_code == 200
    assert auth_client.get("/v1/scenes", headers={"X-API-Key": token}).status_code == 200
    # behind a proxy that uses Authorization for its own (Basic) credentials, X-API-Key carries the key
    assert auth_client.get("/v1/scenes", headers={"Authorization": "Basic dXNlcjpwYXNz",
                                                  "X-API-Key": token}).status_code == 200
    # A token for the right id with a wrong secret, and the local key (no token at all), never authenticate.
    assert auth_client.get("/v1/scenes", headers=bearer(token[:-4] + "AAAA")).status_code == 401
    assert auth_client.get("/v1/scenes", headers=bearer("voxe_local_" + "x" * 43)).status_code == 401
    with session_scope() as session:
        session.get(ApiKey, key_id).revoked_at = utcnow()
    revoked = auth_client.get("/v1/scenes", headers=bearer(token))
    assert revoked.status_code == 401 and "invalid or revoked" in revoked.json()["detail"]
    assert auth_client.get("/healthz").status_code == 200  # liveness needs no key


def test_a_key_sent_without_bearer_or_under_another_scheme_is_told_why_it_was_not_read(auth_client):
    """A key sent in Authorization without "Bearer " before it (curl -H "Authorization: voxe_..."), or under another
    scheme (Token, Basic), had been told "missing API key", as though none was sent. The 401 says what was not read,
    without quoting the key itself."""
    _, token = _create_key("alice")
    usage = ("send 'Authorization: Bearer <key>' or 'X-API-Key: <key>' (keys come from 'python -m api.admin "
             "create-key')")
    for authorization, why in ((token, "Authorization holds a key without 'Bearer ' before it"),
                               (f"Token {token}", "Authorization's scheme 'Token' is not read: only Bearer is"),
                               ("Basic dXNlcjpwYXNz", "Authorization's scheme 'Basic' is not read: only Bearer is")):
        refused = auth_client.get("/v1/scenes", headers={"Authorization": authorization})
        assert (refused.status_code, refused.json()["detail"]) == (401, f"missing API key ({why}): {usage}")
        assert token not in refused.text
    assert auth_client.get("/v1/scenes").json()["detail"] == f"missing API key: {usage}"  # none sent: as before
    assert auth_client.get("/v1/scenes", headers={"Authorization": "Bearer "}).json()["detail"] == (
        f"missing API key: {usage}")
    assert auth_client.get("/v1/scenes", headers={"Authorization": f"bearer {token}"}).status_code == 200


def test_a_key_sent_with_bearer_where_it_goes_alone_is_told_why_it_was_not_read(auth_client):
    """``X-API-Key: Bearer <key>`` (the value written as Authorization's), or ``Authorization: Bearer Bearer <key>``,
    had been told "invalid or revoked API key", a live key's holder left to suspect the key. The 401 says what was
    not read, without quoting the key."""
    _, token = _create_key("alice")
    usage = ("send 'Authorization: Bearer <key>' or 'X-API-Key: <key>' (keys come from 'python -m api.admin "
             "create-key')")
    why = "'Bearer ' sent before it: X-API-Key takes the key alone, 'Authorization: Bearer <key>' once"
    for headers in ({"X-API-Key": f"Bearer {token}"}, {"X-API-Key": f"bearer {token}"},
                    {"Authorization": f"Bearer Bearer {token}"}):
        refused = auth_client.get("/v1/scenes", headers=headers)
        assert (refused.status_code, refused.json()["detail"]) == (401, f"invalid or revoked API key ({why}): {usage}")
        assert token not in refused.text
    for other in ("Bearer voxe_nope", "Bearer x", f"Token {token}"):  # no key of its form after Bearer: as before
        refused = auth_client.get("/v1/scenes", headers={"X-API-Key": other})
        assert refused.json()["detail"] == f"invalid or revoked API key: {usage}"
    assert auth_client.get("/v1/scenes", headers={"X-API-Key": token}).status_code == 200


def test_an_authorization_scheme_sent_in_utf8_is_quoted_as_sent(auth_client):
    """The 401 quoting an Authorization scheme it does not read quoted its UTF-8 bytes read as Latin-1, one character
    a byte ('SchlÃ¼ssel' for "Schlüssel"), where the other messages quoting a header quote it as the client wrote it
    (http_semantics.as_sent)."""
    refused = auth_client.get("/v1/scenes", headers={"Authorization": "Schlüssel abc".encode()})
    assert refused.status_code == 401
    assert "Authorization's scheme 'Schlüssel' is not read: only Bearer is" in refused.json()["detail"]


def test_an_expired_key_is_401_saying_it_expired_and_list_keys_shows_when(auth_client, capsys):
    """A key created with --expires-in works until then, and is refused after with a 401 naming the expiry (keys had
    never expired, and a refused one could only read "invalid or revoked"); list-keys shows each key's expiry."""
    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, utcnow

    assert admin.main(["create-key", "--name", "intern", "--expires-in", "90d"]) == 0
    out = capsys.readouterr()
    token = out.out.strip()
    key_id = token.split("_")[1]
    with session_scope() as session:
        expires_at = session.get(ApiKey, key_id).expires_at
    assert abs(expires_at - (utcnow() + timedelta(days=90))) < timedelta(minutes=1)
    assert f"created key {key_id} (intern, expires {expires_at.isoformat(timespec='seconds')})" in out.err
    _, lasting = _create_key("lasting")
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 200
    assert admin.main(["list-keys"]) == 0
    rows = dict(line.split("\t", 1) for line in capsys.readouterr().out.splitlines())
    assert rows[key_id].startswith("intern\tactive\t") and rows[key_id].endswith(f"expires_at={expires_at.isoformat()}")
    assert rows[lasting.split("_")[1]].endswith("\texpires_at=never")

    with session_scope() as session:
        session.get(ApiKey, key_id).expires_at = expired_at = utcnow() - timedelta(seconds=1)
    for headers in (bearer(token), {"X-API-Key": token}):
        refused = auth_client.get("/v1/jobs", headers=headers)
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
        assert refused.json()["detail"].startswith(
            f"API key {key_id} expired at {expired_at.isoformat(timespec='seconds')}: ask the service's admin for a later "
            "expiry ('python -m api.admin update-key --expires-in') or a new key")
    # a wrong secret for the expired key's id learns nothing of it
    forged = auth_client.get("/v1/jobs", headers=bearer(token[:-4] + "AAAA"))
    assert forged.status_code == 401 and "expired" not in forged.json()["detail"]
    assert auth_client.get("/v1/jobs", headers=bearer(lasting)).status_code == 200
    assert admin.main(["list-keys"]) == 0
    listing = capsys.readouterr().out
    assert f"{key_id}\tintern\texpired {expired_at.isoformat()}\t" in listing


@pytest.mark.parametrize("given, expected", [
    ("0d", "must be 1s to 36500d (100 years), got '0d'"), ("36501d", "must be 1s to 36500d (100 years), got '36501d'"),
    ("9" * 40 + "s", "must be 1s to 36500d"), ("90", "must be a whole number of s, m, h or d (e.g. 90d, 12h), got '90'"),
    ("1.5h", "must be a whole number of s, m, h or d"), ("-1d", "must be a whole number of s, m, h or d")])
def test_create_key_refuses_an_expiry_it_cannot_keep_naming_why(auth_client, capsys, given, expected):
    from api import admin

    with pytest.raises(SystemExit):
        admin.main(["create-key", "--name", "x", f"--expires-in={given}"])
    assert f"argument --expires-in: {expected}" in capsys.readouterr().err


def test_a_request_carrying_two_different_keys_is_401_whichever_comes_first(auth_client):
    """Headers repeated, or both forms: the first line had counted (another reader may take the last), so one request
    acted as either key by the order of its lines."""
    _, alice = _create_key("alice")
    _, bob = _create_key("bob")
    # Each told the lines that carried them (two Bearer lines had been told "Bearer and X-API-Key lines").
    for headers, lines in (([("Authorization", f"Bearer {alice}"), ("Authorization", f"Bearer {bob}")],
                            "2 Authorization: Bearer lines"),
                           ([("X-API-Key", bob), ("X-API-Key", alice)], "2 X-API-Key lines"),
                           ([("Authorization", f"Bearer {alice}"), ("X-API-Key", bob)],
                            "1 Authorization: Bearer line and 1 X-API-Key line"),
                           ([("Authorization", "Basic dXNlcjpwYXNz"), ("Authorization", f"Bearer {bob}"),
                             ("X-API-Key", alice)], "1 Authorization: Bearer line and 1 X-API-Key line")):
        refused = auth_client.get("/v1/jobs", headers=headers)
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer", headers
        assert refused.json()["detail"] == f"2 different API keys sent ({lines}): send one key", headers
        assert alice not in refused.text and bob not in refused.text
    # The same key twice, or beside an empty one, is one key.
    for headers in ([("X-API-Key", alice), ("Authorization", f"Bearer {alice}")],
                    [("Authorization", "Bearer "), ("X-API-Key", alice)]):
        assert auth_client.get("/v1/jobs", headers=headers).status_code == 200, headers


def test_only_the_tokens_hash_is_stored(auth_client):
    from sqlalchemy import text

    from voxe_service.db import session_scope

    key_id, token = _create_key("bob")
    assert token.startswith(f"voxe_{key_id}_") and len(token) > 50
    with session_scope() as session:
        rows = [tuple(r) for r in session.execute(text("SELECT * FROM api_keys"))]
    assert not any(token in str(value) for row in rows for value in row)
    assert any(hashlib.sha256(token.encode()).hexdigest() in row for row in rows)


def test_another_keys_resources_answer_404(auth_client, mic_zip, root):  # noqa: F811
    from voxe_service.db import session_scope
    from voxe_service.models import Artifact
    from voxe_service.storage import get_storage

    _, alice = _create_key("alice")
    _, bob = _create_key("bob")
    scene = _upload(auth_client, mic_zip, bearer(alice)).json()
    job = auth_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=bearer(alice)).json()
    stored = get_storage().put_bytes(f"jobs/{job['id']}/preview.png", b"png")
    with session_scope() as session:
        session.add(Artifact(job_id=job["id"], name="preview.png", key=stored.key, size=stored.size,
                             sha256=stored.sha256, content_type="image/png", kind="preview"))
    urls = [f"/v1/scenes/{scene['id']}", f"/v1/scenes/{scene['id']}/reconstructions", f"/v1/jobs/{job['id']}",
            f"/v1/jobs/{job['id']}/artifacts", f"/v1/jobs/{job['id']}/artifacts/preview.png"]
    for url in urls:
        assert auth_client.get(url, headers=bearer(alice)).status_code == 200, url
        missing = auth_client.get(url, headers=bearer(bob))
        assert missing.status_code == 404 and "not found" in missing.json()["detail"], url
    assert auth_client.post(f"/v1/jobs/{job['id']}/cancel", headers=bearer(bob)).status_code == 404
    assert auth_client.delete(f"/v1/scenes/{scene['id']}", headers=bearer(bob)).status_code == 404
    assert auth_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=bearer(bob)).status_code == 404
    assert auth_client.get("/v1/scenes", headers=bearer(bob)).json()["total"] == 0
    assert auth_client.get("/v1/jobs", headers=bearer(bob)).json()["total"] == 0
    assert auth_client.get("/v1/jobs", headers=bearer(alice)).json()["total"] == 1
    assert auth_client.get(f"/v1/jobs/{job['id']}", headers=bearer(alice)).json()["state"] == "queued"


def test_admin_cli_creates_lists_and_revokes_keys(auth_client, capsys):
    from api import admin

    assert admin.main(["create-key", "--name", "ci robot", "--max-active-jobs", "3"]) == 0
    out = capsys.readouterr()
    token = out.out.strip()
    assert "shown only this once" in out.err and token.startswith("voxe_")
    key_id = token.split("_")[1]
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 200

    assert admin.main(["list-keys"]) == 0
    listing = capsys.readouterr().out
    assert f"{key_id}\tci robot\tactive" in listing and "max_active_jobs=3" in listing
    assert token not in listing and "local" not in listing

    assert admin.main(["revoke-key", key_id]) == 0
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 401
    assert admin.main(["list-keys"]) == 0 and "revoked" in capsys.readouterr().out
    assert admin.main(["revoke-key", "nosuchkey"]) == 1
    assert "no API key 'nosuchkey'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        admin.main(["create-key", "--name", "x", "--max-active-jobs", "0"])
    # past what the columns hold (PostgreSQL's 32-bit and 64-bit integers): a traceback had ended the command
    for option, value, most in (("--max-active-jobs", 2**31, 2**31 - 1), ("--max-upload-bytes", 10**20, 2**63 - 1),
                                ("--max-upload-bytes", "10GB", None)):
        with pytest.raises(SystemExit):
            admin.main(["create-key", "--name", "x", option, str(value)])
        expected = f"must be 1 to {most}, got {value}" if most else f"must be a whole number, got '{value}'"
        assert f"argument {option}: {expected}" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a name with a tab and a newline had printed a forged row in list-keys
        admin.main(["create-key", "--name", "x\nfake1234abcd\tadmin\tactive"])
    assert "forge list-keys' rows), got '\\n' at 1" in capsys.readouterr().err


@pytest.mark.parametrize("name, kept", [
    ("山田\u3000太郎", "山田\u3000太郎"),  # an ideographic space, as Japanese names are written
    ("Zoë\u00a0Smith", "Zoë\u00a0Smith"),  # a no-break space
    ("  " + "a" * 255 + "  ", "a" * 255),  # 255 characters once the spaces around it are cut
])
def test_a_key_name_spaced_as_people_write_it_is_kept(auth_client, capsys, name, kept):
    """Only an ASCII space had counted as one (str.isprintable): a name with a no-break or ideographic space was
    refused as "must be 1-255 printable characters (a tab or newline would forge list-keys' rows)", as was one
    under 255 characters but for the spaces the command cuts from its ends."""
    from api import admin

    assert admin.main(["create-key", "--name", name]) == 0
    key_id = capsys.readouterr().out.strip().split("_")[1]
    assert admin.main(["list-keys"]) == 0
    assert f"{key_id}\t{kept}\tactive" in capsys.readouterr().out


@pytest.mark.parametrize("name, named", [("x\u2028fake", r"'\u2028'"), ("admin\u202e", r"'\u202e'"),
                                         ("x\tadmin", r"'\t'"), ("a" * 256, "1-255 characters, got 256")])
def test_a_key_name_that_could_forge_list_keys_rows_is_refused_naming_why(auth_client, capsys, name, named):
    from api import admin

    with pytest.raises(SystemExit):
        admin.main(["create-key", "--name", name])
    assert named in capsys.readouterr().err


def test_revoke_key_given_the_keys_token_revokes_it_and_never_prints_the_token(auth_client, capsys):
    """The token is what an operator holding a leaked one has: it had been looked up as a key id, "no API key
    'voxe_<id>_<secret>'" printing the secret into the terminal (and any log of it), the key left live."""
    from api import admin

    key_id, token = _create_key("leaked")
    assert admin.main(["revoke-key", token]) == 0
    err = capsys.readouterr().err
    assert f"revoked key {key_id} (leaked)" in err and token.rpartition("_")[2] not in err
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 401
    other_id, other = _create_key("other")  # a token of that form no key has: named by its id only, nothing revoked
    forged = f"voxe_{other_id}_{'x' * 43}"
    assert admin.main(["revoke-key", forged]) == 1
    err = capsys.readouterr().err
    assert f"no API key has this token (of key id {other_id!r})" in err and "x" * 43 not in err
    assert auth_client.get("/v1/jobs", headers=bearer(other)).status_code == 200


@pytest.mark.parametrize("around", [(" ", ""), ("", "\r\n"), ("", "\n"), ("\t", " ")])
def test_a_token_given_with_spaces_or_a_line_ending_around_it_is_found_and_its_secret_never_printed(
        auth_client, capsys, around):
    """A token pasted with a space, or read from a file's line (CR LF), had been looked up as a key id and printed
    back, secret and all ("no API key ' voxe_<id>_<secret>'"); one ending in a newline was refused as "no API key has
    this token": the leaked key left live either way."""
    from api import admin

    key_id, token = _create_key("leaked")
    secret = token.rpartition("_")[2]
    assert admin.main(["update-key", around[0] + token + around[1], "--max-active-jobs", "4"]) == 0
    assert f"updated key {key_id} (leaked): max_active_jobs=4" in capsys.readouterr().err
    assert admin.main(["revoke-key", around[0] + token + around[1]]) == 0
    err = capsys.readouterr().err
    assert f"revoked key {key_id} (leaked)" in err and secret not in err
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 401


def test_text_holding_a_token_that_names_no_key_is_not_quoted(auth_client, capsys):
    """Text that is no token but holds one (a pasted "Bearer voxe_..." line) had been quoted whole: "no API key
    'Bearer voxe_<id>_<secret>'"."""
    from api import admin

    _, token = _create_key("leaked")
    for given in (f"Bearer {token}", f"'{token}'", f"{token},"):
        assert admin.main(["revoke-key", given]) == 1
        err = capsys.readouterr().err
        assert token.rpartition("_")[2] not in err
        assert "no API key: the text given holds 'voxe_' but is no token (voxe_<key id>_<secret>) nor a key id " \
            "(not quoted: it may hold a secret) (python -m api.admin list-keys shows them)" in err
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 200


def test_rotate_webhook_secret_of_a_revoked_or_expired_key_says_who_can_read_the_new_one(auth_client, capsys):
    """"which its holder reads at GET /v1/webhooks/secret" had been said of a revoked key (and of an expired one),
    whose token that endpoint answers 401."""
    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, utcnow

    key_id, token = _create_key("gone")
    assert admin.main(["revoke-key", key_id]) == 0
    capsys.readouterr()
    assert admin.main(["rotate-webhook-secret", key_id]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"rotated the webhook secret of key {key_id} (gone)")
    assert ("is signed with the new one, which no one can read: the key is revoked (GET /v1/webhooks/secret answers "
            "its token 401), so its receivers refuse the deliveries still sent") in err
    assert auth_client.get("/v1/webhooks/secret", headers=bearer(token)).status_code == 401

    key_id, token = _create_key("lapsed")
    with session_scope() as session:
        session.get(ApiKey, key_id).expires_at = when = utcnow() - timedelta(hours=1)
    assert admin.main(["rotate-webhook-secret", key_id]) == 0
    assert ("is signed with the new one, which its holder reads at GET /v1/webhooks/secret only once the key is given "
            "a later expiry (update-key --expires-in): it expired "
            f"{when.isoformat(timespec='seconds')}") in capsys.readouterr().err
    assert auth_client.get("/v1/webhooks/secret", headers=bearer(token)).status_code == 401

    key_id, token = _create_key("live")  # a live key's holder reads it, as before
    assert admin.main(["rotate-webhook-secret", key_id]) == 0
    assert capsys.readouterr().err.rstrip().endswith(
        "is signed with the new one, which its holder reads at GET /v1/webhooks/secret")
    assert auth_client.get("/v1/webhooks/secret", headers=bearer(token)).status_code == 200


def test_revoke_key_of_a_key_revoked_before_says_since_when(auth_client, capsys):
    """A second revoke-key had printed "revoked key <id>" as the first did, as though the key had been live until
    then; it says when it was revoked, and still cancels what is unfinished (exit 0, as before)."""
    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey

    key_id, token = _create_key("leaked")
    assert admin.main(["revoke-key", key_id]) == 0
    assert capsys.readouterr().err.startswith(f"revoked key {key_id} (leaked); its 0 unfinished job(s) canceled")
    with session_scope() as session:
        when = session.get(ApiKey, key_id).revoked_at.isoformat(timespec="seconds")
    assert admin.main(["revoke-key", token]) == 0
    assert capsys.readouterr().err.startswith(f"key {key_id} (leaked) was already revoked at {when}; its 0 "
                                              "unfinished job(s) canceled")
    with session_scope() as session:
        assert session.get(ApiKey, key_id).revoked_at.isoformat(timespec="seconds") == when  # not moved


def test_revoke_key_of_the_built_in_local_key_says_what_it_is(auth_client, capsys):
    """It had answered "no API key 'local' (python -m api.admin list-keys shows them)", a key every request acts as
    with authentication off, and that list-keys leaves out."""
    from api import admin

    assert admin.main(["revoke-key", "local"]) == 1
    assert ("'local' is the built-in key that requests act as with authentication off; it has no token to revoke "
            "(VOXE_AUTH=on requires a key of every request)") in capsys.readouterr().err


def _database_down(monkeypatch) -> None:
    """VOXE_DATABASE_URL set to a PostgreSQL nobody serves (a port just closed), its password ``s3cret``."""
    import socket

    from service_helpers import reset_service_caches

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens once it is closed
    monkeypatch.setenv("VOXE_DATABASE_URL", f"postgresql+psycopg://voxe:s3cret@127.0.0.1:{port}/voxe")
    reset_service_caches()


@pytest.mark.parametrize("command", [["list-keys"], ["create-key", "--name", "x"], ["revoke-key", "abc"]])
def test_an_admin_command_facing_a_database_that_is_down_says_so_without_a_traceback(monkeypatch, capsys, command):
    """It had ended in SQLAlchemy's traceback ("sqlalchemy.exc.OperationalError: (psycopg.OperationalError)
    connection failed: ..."), a page of it for the operator to read the cause out of."""
    from api import admin
    from service_helpers import reset_service_caches

    _database_down(monkeypatch)
    try:
        assert admin.main(command) == 1
    finally:
        reset_service_caches()
    err = capsys.readouterr().err
    assert err.startswith("python -m api.admin: the database cannot be reached or is locked (VOXE_DATABASE_URL): "
                          "connection failed: "), err
    assert "Traceback" not in err and "s3cret" not in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("command", [["list-keys"], ["create-key", "--name", "x"]])
def test_an_admin_command_under_a_refused_setting_names_it_without_a_traceback(monkeypatch, capsys, command):
    """VOXE_DEVICE=gpu (an environment the API and the workers refuse at start, naming the variable) had ended the
    command in get_settings()'s traceback, the line naming the variable at its bottom."""
    from api import admin
    from service_helpers import reset_service_caches

    monkeypatch.setenv("VOXE_DEVICE", "gpu")
    reset_service_caches()
    try:
        assert admin.main(command) == 1
    finally:
        monkeypatch.delenv("VOXE_DEVICE")
        reset_service_caches()
    err = capsys.readouterr().err
    assert err.startswith("python -m api.admin: bad service settings: VOXE_DEVICE='gpu': String should match "), err
    assert "Traceback" not in err and len(err.splitlines()) == 1


def test_the_readmes_admin_exit_codes_are_those_the_commands_exit_with(auth_client, capsys):
    """The README's admin section said nothing of them (a script calling create-key could not tell a bad name from a
    key not found); each it names is checked here."""
    from pathlib import Path

    from api import admin

    readme = " ".join((Path(__file__).parent.parent / "README.md").read_text().split())
    assert ("Each admin command exits 0 when done; 1 when the key it names does not exist (update-key: or was "
            "revoked) or the database cannot be reached (said in one line naming `VOXE_DATABASE_URL`) or a setting is "
            "refused (said in one line naming the variable); 2 for a usage "
            "error (an unknown command or option, a value refused, such as a `--name` of control characters, or "
            "update-key with nothing to change), said before the database is touched.") in readme
    assert admin.main(["create-key", "--name", "exit codes"]) == 0
    key_id = capsys.readouterr().out.strip().split("_")[1]
    assert admin.main(["update-key", "nosuchkey", "--never-expires"]) == 1
    assert admin.main(["revoke-key", key_id]) == 0
    assert admin.main(["update-key", key_id, "--never-expires"]) == 1
    for usage in (["no-such-command"], ["list-keys", "--no-such-option"], ["create-key", "--name", "a\x07b"],
                  ["update-key", key_id]):
        with pytest.raises(SystemExit) as exc:
            admin.main(usage)
        assert exc.value.code == 2, usage


def test_an_admin_usage_error_is_said_before_the_database_is_reached(monkeypatch, capsys):
    """Regression: a --name create-key refuses was checked after the database's migrations ran: with the database
    down, ``create-key --name ""`` exited 1 saying the database cannot be reached, not 2 naming --name."""
    from api import admin
    from service_helpers import reset_service_caches

    _database_down(monkeypatch)
    try:
        with pytest.raises(SystemExit) as exc:
            admin.main(["create-key", "--name", " "])
    finally:
        reset_service_caches()
    assert exc.value.code == 2
    assert capsys.readouterr().err.endswith("python -m api.admin create-key: error: --name must be 1-255 characters, "
                                            "got 0\n")


@BOTH_DATABASES
def test_revoking_a_key_cancels_its_unfinished_jobs(auth_client, mic_zip, capsys):
    """Its jobs had run on, holding workers, with results no key could read and no request able to cancel them."""
    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import RUNNING, Job

    key_id, token = _create_key("leaving")
    _, other = _create_key("staying")
    jobs = []
    for owner in (token, token, other):
        scene = _upload(auth_client, mic_zip, bearer(owner)).json()
        jobs.append(auth_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=bearer(owner)).json())
    queued, running, others = (job["id"] for job in jobs)
    with session_scope() as session:
        session.get(Job, running).state = RUNNING

    assert admin.main(["revoke-key", key_id]) == 0
    assert "its 2 unfinished job(s) canceled" in capsys.readouterr().err
    with session_scope() as session:
        canceled, flagged, untouched = (session.get(Job, job_id) for job_id in (queued, running, others))
        assert canceled.state == "canceled"
        assert canceled.message == f"canceled while queued: its API key {key_id} was revoked"
        assert flagged.state == RUNNING and flagged.cancel_requested  # stops at its worker's next cancel check
        assert untouched.state == "queued" and not untouched.cancel_requested
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 401


@BOTH_DATABASES
def test_a_running_job_canceled_by_revoking_its_key_ends_naming_the_revoke(auth_client, mic_zip):
    """revoke-key flags a running job canceled and its run ends it at its next cancel check: it had ended "canceled
    during edit", its webhook's canceled event saying the same, with nothing of the revoke (a job its owner canceled
    reads alike)."""
    from sqlalchemy import select

    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import RUNNING, Job, JobEvent
    from worker import runtime

    key_id, token = _create_key("leaving")
    _, other = _create_key("staying")
    ids = []
    for owner in (token, other):
        scene = _upload(auth_client, mic_zip, bearer(owner)).json()
        ids.append(auth_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=bearer(owner)).json()["id"])
    with session_scope() as session:
        for job_id in ids:
            session.get(Job, job_id).state, session.get(Job, job_id).stage = RUNNING, "edit"
    assert admin.main(["revoke-key", key_id]) == 0
    assert auth_client.post(f"/v1/jobs/{ids[1]}/cancel", headers=bearer(other)).json()["cancel_requested"]
    for job_id in ids:  # as the worker's run ends it (worker.tasks._end_job)
        assert runtime.finish_job(job_id, "canceled", message="canceled during edit")
    with session_scope() as session:
        revoked, canceled = (session.get(Job, job_id) for job_id in ids)
        said = f"canceled during edit: its API key {key_id} was revoked"
        assert (revoked.state, revoked.message) == ("canceled", said)
        assert session.scalars(select(JobEvent.detail).where(JobEvent.job_id == ids[0],
                                                             JobEvent.kind == "canceled")).all() == [said]
        assert (canceled.state, canceled.message) == ("canceled", "canceled during edit")  # its owner's own cancel


@BOTH_DATABASES
def test_a_key_revoked_while_its_request_is_handled_records_nothing(auth_client, mic_zip, monkeypatch,
                                                                    root):  # noqa: F811
    """Revoked after the request was authenticated (an upload is unpacked for minutes), before it recorded its job or
    scene: that job had run on after revoke-key canceled the key's jobs, for a key nothing could read or cancel with."""
    from sqlalchemy import func, select

    from api import admin
    from api.services import jobs, scenes
    from voxe_service.db import session_scope
    from voxe_service.models import Job, Scene

    key_id, token = _create_key("leaving")
    scene = _upload(auth_client, mic_zip, bearer(token)).json()

    def revoked_meanwhile(original):
        def run(*args, **kwargs):
            assert admin.main(["revoke-key", key_id]) == 0
            return original(*args, **kwargs)
        return run

    monkeypatch.setattr(jobs, "refuse_without_models", revoked_meanwhile(jobs.refuse_without_models))
    refused = auth_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=bearer(token))
    assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
    assert refused.json()["detail"] == (f"API key {key_id} was revoked while this request was handled: nothing was "
                                        "recorded")

    key_id, token = _create_key("leaving too")
    stored = stored_files(root)
    monkeypatch.setattr(scenes, "stage_upload", revoked_meanwhile(scenes.stage_upload))
    refused = _upload(auth_client, mic_zip, bearer(token))
    assert refused.status_code == 401 and f"API key {key_id} was revoked while" in refused.json()["detail"]
    assert stored_files(root) == stored
    with session_scope() as session:
        assert session.scalar(select(func.count()).select_from(Job)) == 0
        assert [s.id for s in session.scalars(select(Scene))] == [scene["id"]]


@BOTH_DATABASES
def test_revoking_a_key_while_its_request_holds_it_waits_then_cancels_the_job_it_recorded(auth_client, mic_zip,
                                                                                         monkeypatch):  # noqa: F811
    """The other order: revoke-key run while a request holds the key's lock (its job flushed, not committed) waits for
    it, then finds that job and cancels it (it had found none, and the job ran on for a key nothing could read it
    with)."""
    from api import admin
    from api.services import jobs
    from voxe_service.db import session_scope
    from voxe_service.models import Job

    key_id, token = _create_key("leaving")
    scene = _upload(auth_client, mic_zip, bearer(token)).json()
    revoke = threading.Thread(target=admin.main, args=(["revoke-key", key_id],))
    check_active_jobs = jobs.check_active_jobs

    def revoked_under_the_lock(*args, **kwargs):
        revoke.start()
        revoke.join(2)
        assert revoke.is_alive()  # waiting for the request's lock on the key
        return check_active_jobs(*args, **kwargs)

    monkeypatch.setattr(jobs, "check_active_jobs", revoked_under_the_lock)
    made = auth_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=bearer(token))
    revoke.join(60)
    assert made.status_code == 201 and not revoke.is_alive()
    with session_scope() as session:
        job = session.get(Job, made.json()["id"])
        assert job.state == "canceled" and job.message == f"canceled while queued: its API key {key_id} was revoked"


@BOTH_DATABASES
def test_revoking_a_key_fails_its_scenes_still_processing_so_no_worker_ingests_them(auth_client, mic_zip, capsys):
    """A scene still processing when its key was revoked kept its ingest queued, and a worker decoded it for a scene
    no key could use or delete. It fails naming the revoke, its bytes go, its ingest is skipped; the job waiting on
    it is canceled, as the key's others are, and another key's scene is left processing."""
    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import Job, Scene
    from voxe_service.settings import get_settings
    from voxe_service.storage import get_storage
    from worker.ingest import ingest_scene

    key_id, token = _create_key("leaving")
    _, other = _create_key("staying")
    leaving, staying = (_upload(auth_client, mic_zip, bearer(owner)).json() for owner in (token, other))
    waiting = auth_client.post("/v1/jobs", json={"scene_id": leaving["id"], **JOB}, headers=bearer(token)).json()
    with session_scope() as session:
        stored = session.get(Scene, leaving["id"]).storage_key
    storage = get_storage(get_settings())
    assert storage.exists(stored)

    assert admin.main(["revoke-key", key_id]) == 0
    assert "and 1 scene(s) still processing failed" in capsys.readouterr().err
    with session_scope() as session:
        failed, untouched, job = (session.get(Scene, leaving["id"]), session.get(Scene, staying["id"]),
                                  session.get(Job, waiting["id"]))
        assert (failed.state, failed.error) == ("failed", f"its API key {key_id} was revoked while it was processing")
        assert untouched.state == "processing"
        assert (job.state, job.message) == ("canceled", f"canceled while queued: its API key {key_id} was revoked")
    assert not storage.exists(stored)
    assert ingest_scene(leaving["id"], get_settings(), storage, "w@host") == {
        "scene_id": leaving["id"], "skipped": f"scene {leaving['id']} is failed"}



def test_revoking_a_key_stops_its_scenes_ingest_already_running(auth_client, mic_zip, monkeypatch, capsys):
    """A key revoked while a worker ingests its scene: the revoke fails the scene, but the running ingest went on to
    the end, decoding (a mesh's: rendering too) the whole upload for a scene no key can use, and only then had its
    result refused. It stops at its next step, as a canceled job's stage stops at its next cancel check: the scene
    stays failed naming the revoke, the ingest is skipped saying so, and nothing of the scene is stored."""
    from api import admin
    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.settings import get_settings
    from voxe_service.storage import get_storage, scene_key
    from worker import ingest as ingest_module
    from worker.ingest import ingest_scene

    key_id, token = _create_key("leaving")
    scene_id = _upload(auth_client, mic_zip, bearer(token)).json()["id"]
    unpack, decoded = datasets.unpack, []

    def revoked_as_it_unpacks(archive, dest):
        assert admin.main(["revoke-key", key_id]) == 0
        return unpack(archive, dest)

    def decode(folder, downsample):
        decoded.append(folder)
        return ingest_module.Decoded(1, "relu")

    monkeypatch.setattr(datasets, "unpack", revoked_as_it_unpacks)
    monkeypatch.setattr(ingest_module, "decode", decode)
    storage = get_storage(get_settings())
    assert ingest_scene(scene_id, get_settings(), storage, "w@host") == {
        "scene_id": scene_id, "skipped": f"scene {scene_id} was deleted or failed meanwhile"}
    assert decoded == []  # stopped before decoding the upload
    with session_scope() as session:
        scene = session.get(Scene, scene_id)
        assert (scene.state, scene.error) == ("failed", f"its API key {key_id} was revoked while it was processing")
    assert storage.list(scene_key(scene_id)) == []

@pytest.mark.parametrize("level, said", [("info", True), ("warning", False)])
def test_the_api_under_uvicorn_says_authentication_is_on_at_its_log_level(tmp_path, level, said):
    """uvicorn configures only its own loggers: the API's INFO lines had gone nowhere, so a deployment with
    authentication on (the docker one) logged neither that nor the API's "ready" line, where one with it off warns."""
    import os
    import sys

    import httpx
    from service_helpers import Process, free_port, service_env, wait_until

    port = free_port()
    api = Process(f"api-{level}", [sys.executable, "-m", "uvicorn", "api.main:app", "--host", "127.0.0.1", "--port",
                                   str(port), "--log-level", level],
                  {**os.environ, **service_env(tmp_path, VOXE_AUTH="on")}, tmp_path)
    try:
        wait_until(lambda: httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200, 120,
                   what="the API to start", processes=[api])
    finally:
        api.stop()
    log = api.log_path.read_text()
    lines = ("INFO:     Vox-E API: authentication ON (VOXE_AUTH=on, host 127.0.0.1): every request needs an API key",
             "INFO:     Vox-E API ready: SDS model tiny (smoke test, random weights)")
    assert [line in log for line in lines] == [said, said], log


# ------------------------------------------------------------------------------------------ the auth switch
def test_auth_is_off_only_on_loopback(root, monkeypatch, caplog):  # noqa: F811
    from api.main import create_app
    from voxe_service.settings import Settings, SettingsError, is_loopback

    for host in ("127.0.0.1", "127.8.9.1", "::1", "[::1]", "localhost", "localhost.", "LocalHost"):
        assert is_loopback(host) and not Settings(host=host).auth_enabled, host
    for host in ("0.0.0.0", "::", "10.0.0.5", "example.com", "localhost.example", ".", "localhost.."):
        assert not is_loopback(host) and Settings(host=host).auth_enabled, host
    assert not is_loopback("")  # (an empty VOXE_HOST is refused at start: test_service_settings.py)
    assert Settings(host="127.0.0.1", auth="on").auth_enabled

    with caplog.at_level(logging.WARNING, logger="voxe.api"):
        with TestClient(create_app()) as client:
            assert client.get("/v1/scenes").status_code == 200  # no key needed
    assert "authentication OFF" in caplog.text and "loopback host 127.0.0.1" in caplog.text

    monkeypatch.setenv("VOXE_HOST", "0.0.0.0")
    monkeypatch.setenv("VOXE_AUTH", "off")
    _reset()
    with pytest.raises(SettingsError, match="refusing to start: VOXE_AUTH=off on the non-loopback host '0.0.0.0'"):
        with TestClient(create_app()):
            pass

    monkeypatch.setenv("VOXE_AUTH", "auto")  # a reachable host turns authentication on by itself
    _reset()
    with TestClient(create_app()) as client:
        assert client.get("/v1/scenes").status_code == 401


def test_with_authentication_off_only_loopback_connections_are_served(root):  # noqa: F811
    """VOXE_HOST only tells the API where uvicorn listens: uvicorn run with --host 0.0.0.0 beside the default
    VOXE_HOST had served whoever reached the machine's address as the local key, no key asked."""
    from api.main import create_app

    app = create_app()
    for server in ("127.0.0.1", "[::1]", "[::ffff:127.0.0.1]", "192.0.2.2", "[2001:db8::2]"):
        with TestClient(app, base_url=f"http://{server}:8000") as client:  # (the address the request came in on)
            response = client.get("/v1/scenes")
            assert client.get("/healthz").status_code == 200 and client.options("/v1/scenes").status_code == 204
        if server in ("192.0.2.2", "[2001:db8::2]"):
            assert response.status_code == 401 and response.headers["www-authenticate"] == "Bearer", server
            assert (f"authentication is off (VOXE_AUTH=auto, VOXE_HOST=127.0.0.1), so only loopback connections are "
                    f"served, and this one came in on {server.strip('[]')}") in response.json()["detail"]
        else:
            assert response.status_code == 200, (server, response.text)


def test_with_authentication_off_a_browsers_request_for_another_site_is_401(root, mic_zip):  # noqa: F811
    """A page of another site posting a form here (an upload needs no preflight; Origin), or one whose name its owner
    pointed at 127.0.0.1 reading and writing the API as its own (DNS rebinding; Host), had acted as the local key."""
    from api.main import create_app

    with TestClient(create_app()) as client:
        for headers in ({"Origin": "http://evil.example"}, {"Origin": "null"}, {"Host": "evil.example:8000"},
                        {"Host": "[::1"}, {"Host": "127.0.0.1.evil.example"}):
            refused = _upload(client, mic_zip, headers)
            assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer", headers
            (name, value), = headers.items()
            assert (f"so only loopback connections are served, and this one names another host ({name}: {value}): a "
                    "page of another site, or of a name pointed at this machine, may not act as the local key"
                    ) in refused.json()["detail"], headers
        assert client.get("/v1/scenes").json()["total"] == 0  # nothing stored
        for headers in ({"Host": "localhost:8000", "Origin": "http://localhost:8000"}, {"Host": "[::1]:8000"},
                        {"Host": "127.0.0.1:8000", "Origin": "http://127.0.0.1:8000"}, {"Origin": "http://testserver"},
                        {"Host": "localhost.:8000", "Origin": "http://localhost.:8000"}):  # (the root's dot)
            assert client.get("/v1/scenes", headers=headers).status_code == 200, headers
        assert _upload(client, mic_zip, {"Origin": "http://127.0.0.1:8000"}).status_code == 201  # the web UI's


def test_with_authentication_off_a_request_a_proxy_relayed_is_401(root):  # noqa: F811
    """A proxy on the machine (nginx, Caddy in front of bash .ci/serve) comes in on loopback: whoever reached the
    proxy had been served as the local key, no key asked."""
    from api.main import create_app

    with TestClient(create_app()) as client:
        for sent, named in (("Forwarded", "Forwarded"), ("X-Forwarded-For", "X-Forwarded-For"),
                            ("x-forwarded-host", "X-Forwarded-Host"), ("X-Forwarded-Proto", "X-Forwarded-Proto"),
                            ("x-real-ip", "X-Real-IP")):
            response = client.get("/v1/scenes", headers={sent: "203.0.113.7"})
            assert response.status_code == 401 and response.headers["www-authenticate"] == "Bearer", sent
            assert (f"so only loopback connections are served, and this one was relayed by a proxy (its {named} "
                    "header), which serves whoever reaches it: turn authentication on (VOXE_AUTH=on"
                    ) in response.json()["detail"], sent
        assert client.get("/v1/scenes").status_code == 200


def test_resources_made_before_keys_belong_to_the_local_key(database_url):
    from alembic import command
    from sqlalchemy import text

    from service_helpers import database_at

    config, engine = database_at(
        database_url, "0001", "INSERT INTO scenes (id, name, format, image_count, width, height, splits, storage_key, "
        "size_bytes, sha256, created_at) VALUES ('s1', 'old', 'nerf_synthetic', 1, 8, 8, '[]', 'k', 1, 'x', "
        "'2026-01-01 00:00:00')")
    command.upgrade(config, "head")
    with engine.begin() as conn:
        assert conn.execute(text("SELECT owner_key_id FROM scenes")).scalar_one() == "local"
        assert conn.execute(text("SELECT token_sha256 FROM api_keys WHERE id = 'local'")).scalar_one() is None
    command.downgrade(config, "0001")
    with engine.begin() as conn:
        assert conn.execute(text("SELECT name FROM scenes")).scalar_one() == "old"
    engine.dispose()


def _connection_once_free(engine, within_s: float = 30.0):
    """A connection of ``engine``'s pool, waited for while the app's threads (the webhook sender's and the reaper's
    first passes) hold the one it has: on a loaded machine they had held it past the pool's 0.2 s timeout."""
    from sqlalchemy.exc import TimeoutError as PoolTimeout

    deadline = time.monotonic() + within_s
    while True:
        try:
            return engine.connect()
        except PoolTimeout:
            if time.monotonic() > deadline:
                raise


@BOTH_DATABASES
@pytest.mark.parametrize("auth", ["off", "on"])
def test_a_database_out_of_connections_is_a_503_with_retry_after(root, monkeypatch, auth):  # noqa: F811
    """A request finding every pooled connection busy is refused 503 + Retry-After naming the pool settings (not a
    bare 500), whether the key check (auth on, a middleware) or the route (auth off) meets it; served again once a
    connection is returned."""
    from api.main import create_app
    from voxe_service.db import get_engine

    monkeypatch.setenv("VOXE_AUTH", auth)
    _reset()
    with TestClient(create_app()):  # the key made on the usual pool: on one connection, the app's own threads (the
        headers = bearer(_create_key("busy")[1]) if auth == "on" else {}  # webhook sender, the reaper) had taken it
    for key, value in {"VOXE_DATABASE_POOL_SIZE": "1", "VOXE_DATABASE_MAX_OVERFLOW": "0",
                       "VOXE_DATABASE_POOL_TIMEOUT_S": "0.2",
                       # the app's own threads pass once as it starts, then keep off the one connection
                       "VOXE_WEBHOOK_POLL_INTERVAL_S": "3600", "VOXE_REAPER_INTERVAL_S": "3600"}.items():
        monkeypatch.setenv(key, value)
    _reset()
    with TestClient(create_app(), raise_server_exceptions=False) as client:
        held = _connection_once_free(get_engine())
        try:
            response = client.get("/v1/jobs", headers=headers)
        finally:
            held.close()
        assert response.status_code == 503, response.text
        assert response.headers["retry-after"] == "5"
        assert "VOXE_DATABASE_POOL_SIZE" in response.json()["detail"]
        assert response.headers["x-content-type-options"] == "nosniff"
        assert client.get("/v1/jobs", headers=headers).status_code == 200
        assert "503" in client.get("/openapi.json").json()["paths"]["/v1/jobs"]["get"]["responses"]


def test_only_a_database_that_cannot_serve_now_is_a_503_a_service_fault_stays_a_500(root, monkeypatch):  # noqa: F811
    """SQLite raises OperationalError for a missing table or bad SQL as for a locked file: the first are the
    service's faults (a 500 with its traceback), not an outage to retry."""
    import sqlite3

    import psycopg
    from sqlalchemy.exc import OperationalError

    from api.http_semantics import unavailability
    from api.main import create_app

    def error(cause):
        return OperationalError("SELECT 1", {}, cause)

    assert unavailability(error(sqlite3.OperationalError("database is locked"))).endswith("or is locked")
    assert unavailability(error(psycopg.OperationalError("connection failed: Connection refused"))) is not None
    assert unavailability(error(sqlite3.OperationalError("no such table: api_keys"))) is None
    assert unavailability(error(sqlite3.OperationalError('near "SELCT": syntax error'))) is None
    with TestClient(create_app(migrate=False), raise_server_exceptions=False) as client:  # a database never migrated
        response = client.get("/v1/jobs")
    assert response.status_code == 500 and "retry-after" not in response.headers


# ------------------------------------------------------------------------------------------ quotas
def test_update_key_changes_a_keys_quotas_and_expiry_and_the_next_request_is_held_to_them(auth_client, mic_zip,
                                                                                           capsys):
    """Quotas had been fixed at creation: a key outgrowing its job quota (or abusing its bytes) could only be revoked,
    its jobs canceled and a new token handed out. update-key changes them, or the expiry, on the same token."""
    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, utcnow

    key_id, token = _create_key("growing", max_active_jobs=1)
    scene = _upload(auth_client, mic_zip, bearer(token)).json()
    body = {"scene_id": scene["id"], **JOB}
    assert auth_client.post("/v1/jobs", json=body, headers=bearer(token)).status_code == 201
    assert auth_client.post("/v1/jobs", json=body, headers=bearer(token)).status_code == 429

    assert admin.main(["update-key", key_id, "--max-active-jobs", "2"]) == 0
    assert f"updated key {key_id} (growing): max_active_jobs=2, max_upload_bytes=default, never expires" in \
        capsys.readouterr().err
    assert auth_client.post("/v1/jobs", json=body, headers=bearer(token)).status_code == 201
    refused = auth_client.post("/v1/jobs", json=body, headers=bearer(token))
    assert refused.status_code == 429 and "the limit is 2" in refused.json()["detail"]

    assert admin.main(["update-key", token, "--max-upload-bytes", "1", "--expires-in", "12h"]) == 0  # by its token
    with session_scope() as session:
        expires_at = session.get(ApiKey, key_id).expires_at
    assert abs(expires_at - (utcnow() + timedelta(hours=12))) < timedelta(minutes=1)
    assert f"max_upload_bytes=1, expires {expires_at.isoformat(timespec='seconds')}" in capsys.readouterr().err
    over = _upload(auth_client, mic_zip, bearer(token))
    assert over.status_code == 429 and f"key 'growing' stores {scene['size_bytes']} bytes of scenes, before this " \
        "upload is read, the limit is 1 " in over.json()["detail"]
    assert admin.main(["update-key", key_id, "--max-active-jobs", "default", "--max-upload-bytes", "default",
                       "--never-expires"]) == 0
    assert "max_active_jobs=default, max_upload_bytes=default, never expires" in capsys.readouterr().err
    assert auth_client.post("/v1/jobs", json=body, headers=bearer(token)).status_code == 201  # the setting's 3 jobs
    assert admin.main(["list-keys"]) == 0
    assert f"{key_id}\tgrowing\tactive\t" in capsys.readouterr().out

    # an expired key is given a later expiry: it works again
    assert admin.main(["update-key", key_id, "--expires-in", "1s"]) == 0
    time.sleep(1.1)
    assert "expired at" in auth_client.get("/v1/jobs", headers=bearer(token)).json()["detail"]
    assert admin.main(["update-key", key_id, "--expires-in", "30d"]) == 0
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 200


@pytest.mark.parametrize("argv, code, expected", [
    (["update-key", "abc"], 2, "say what to change: --max-active-jobs, --max-upload-bytes, --expires-in or "
                                "--never-expires"),
    (["update-key", "abc", "--expires-in", "1d", "--never-expires"], 2, "not allowed with argument --expires-in"),
    (["update-key", "abc", "--max-active-jobs", "none"], 2, "must be a whole number or 'default', got 'none'"),
    (["update-key", "abc", "--max-active-jobs", "0"], 2, "must be 1 to 2147483647, got 0"),
    (["update-key", "nosuchkey", "--max-active-jobs", "3"], 1, "no API key 'nosuchkey'"),
    (["update-key", "local", "--max-active-jobs", "3"], 1, "'local' is the built-in key that requests act as with "
     "authentication off; its quotas are VOXE_MAX_ACTIVE_JOBS_PER_KEY and VOXE_MAX_UPLOAD_BYTES_PER_KEY"),
])
def test_update_key_refuses_what_it_cannot_do_naming_why(auth_client, capsys, argv, code, expected):
    from api import admin

    try:
        assert admin.main(argv) == code
    except SystemExit as exc:
        assert exc.code == code
    assert expected in capsys.readouterr().err


def test_update_key_of_an_expired_key_says_it_stays_expired(auth_client, capsys):
    """Changing an expired key's quotas leaves it expired: update-key had said "expires <a time past>", as if the key
    worked; it says it expired and that its token is refused until --expires-in."""
    from datetime import datetime, timezone

    from api import admin

    key_id, token = _create_key("lapsed", expires_at=datetime(2026, 1, 1, tzinfo=timezone.utc))
    assert admin.main(["update-key", key_id, "--max-active-jobs", "3"]) == 0
    assert (f"updated key {key_id} (lapsed): max_active_jobs=3, max_upload_bytes=default, expired "
            "2026-01-01T00:00:00+00:00: its token is refused until --expires-in gives it a later expiry"
            ) in capsys.readouterr().err
    assert "expired at" in auth_client.get("/v1/jobs", headers=bearer(token)).json()["detail"]


def test_update_key_of_a_revoked_key_changes_nothing(auth_client, capsys):
    from api import admin
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey

    key_id, token = _create_key("gone")
    assert admin.main(["revoke-key", key_id]) == 0
    assert admin.main(["update-key", key_id, "--never-expires", "--max-active-jobs", "9"]) == 1
    assert f"API key {key_id} (gone) was revoked at" in capsys.readouterr().err
    with session_scope() as session:
        assert session.get(ApiKey, key_id).max_active_jobs is None
    assert auth_client.get("/v1/jobs", headers=bearer(token)).status_code == 401


@BOTH_DATABASES
def test_concurrent_job_quota_is_429_with_retry_after(auth_client, mic_zip):
    _, token = _create_key("small", max_active_jobs=2)
    scene = _upload(auth_client, mic_zip, bearer(token)).json()
    body = {"scene_id": scene["id"], **JOB}
    first, second = (auth_client.post("/v1/jobs", json=body, headers=bearer(token)) for _ in range(2))
    assert first.status_code == second.status_code == 201
    refused = auth_client.post("/v1/jobs", json=body, headers=bearer(token))
    assert refused.status_code == 429 and refused.headers["retry-after"] == "60"
    assert "already has 2 queued or running job(s) and asked for 1 more, the limit is 2" in refused.json()["detail"]
    assert auth_client.get("/v1/jobs", headers=bearer(token)).json()["total"] == 2  # nothing half made
    auth_client.post(f"/v1/jobs/{first.json()['id']}/cancel", headers=bearer(token))
    assert auth_client.post("/v1/jobs", json=body, headers=bearer(token)).status_code == 201
    # The service-wide default applies to keys without their own value.
    _, other = _create_key("default")
    scene = _upload(auth_client, mic_zip, bearer(other)).json()
    for _ in range(3):
        response = auth_client.post("/v1/jobs", json={**body, "scene_id": scene["id"]}, headers=bearer(other))
        assert response.status_code == 201


def test_a_request_over_a_keys_whole_job_quota_says_how_to_raise_that_keys_own(auth_client, mic_zip, capsys):
    """A sweep of more jobs than the key may ever run had been told "use a key created with a higher
    --max-active-jobs": a new key, which sees none of this one's scenes. update-key raises this one's."""
    from api import admin

    key_id, token = _create_key("small", max_active_jobs=2)
    scene = _upload(auth_client, mic_zip, bearer(token)).json()
    body = {"scenes": [{"scene_id": scene["id"], "object": "mic"}]}
    over = auth_client.post("/v1/sweeps", json=body, headers=bearer(token))
    assert (over.status_code, over.json()["detail"]) == (422, (
        "this request creates 12 jobs but key 'small' may have at most 2 queued or running "
        "(VOXE_MAX_ACTIVE_JOBS_PER_KEY or the key's own), so it can never be accepted: ask for fewer (a sweep over "
        f"fewer scenes), or have the service's admin raise the key's own ('python -m api.admin update-key {key_id} "
        "--max-active-jobs 12')"))
    assert admin.main(["update-key", key_id, "--max-active-jobs", "12"]) == 0  # what it says, run as said
    capsys.readouterr()
    assert auth_client.post("/v1/sweeps", json=body, headers=bearer(token)).status_code == 201


@BOTH_DATABASES
def test_upload_quota_is_429_and_leaves_nothing(auth_client, mic_zip, root):  # noqa: F811
    _, probe = _create_key("probe")
    size = _upload(auth_client, mic_zip, bearer(probe)).json()["size_bytes"]
    _, token = _create_key("small", max_upload_bytes=size + size // 2)
    first = _upload(auth_client, mic_zip, bearer(token))
    assert first.status_code == 201
    before = stored_files(root)
    refused = _upload(auth_client, mic_zip, bearer(token))
    assert refused.status_code == 429 and "retry-after" not in refused.headers  # waiting frees no space
    detail = refused.json()["detail"]
    assert "quota of upload bytes exceeded" in detail and f"stores {size} bytes" in detail and f"adds {size}" in detail
    assert auth_client.get("/v1/scenes", headers=bearer(token)).json()["total"] == 1
    assert stored_files(root) == before and staged(root) == []
    assert auth_client.delete(f"/v1/scenes/{first.json()['id']}", headers=bearer(token)).status_code == 204
    assert _upload(auth_client, mic_zip, bearer(token)).status_code == 201  # space freed
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey

    with session_scope() as session:  # a key already over its quota is refused before the upload is read
        session.get(ApiKey, token.split("_")[1]).max_upload_bytes = size // 2
    early = _upload(auth_client, mic_zip, bearer(token))
    assert early.status_code == 429 and "before this upload is read" in early.json()["detail"]
    _, tiny = _create_key("tiny", max_upload_bytes=size // 2)  # the upload alone is over: deleting frees nothing
    alone = _upload(auth_client, mic_zip, bearer(tiny))
    assert alone.status_code == 413 and f"more than the whole upload quota of key 'tiny' ({size // 2} bytes" in \
        alone.json()["detail"]
    assert auth_client.get("/v1/scenes", headers=bearer(tiny)).json()["total"] == 0 and staged(root) == []


def test_an_upload_over_a_keys_whole_upload_quota_says_how_to_raise_that_keys_own(auth_client, mic_zip, capsys):
    """The 413 for an upload larger than the key's whole byte quota gave no advice (the job quota's 422 names
    update-key): it names the command raising this key's own to what fits it, or, for the local key, the setting."""
    from fastapi import HTTPException

    from api import admin
    from api.auth import check_upload_bytes
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, ApiKey
    from voxe_service.settings import get_settings

    _, probe = _create_key("probe")
    size = _upload(auth_client, mic_zip, bearer(probe)).json()["size_bytes"]
    key_id, tiny = _create_key("tiny", max_upload_bytes=size - 1)
    alone = _upload(auth_client, mic_zip, bearer(tiny))
    assert (alone.status_code, alone.json()["detail"]) == (413, (
        f"this upload stores {size} bytes, more than the whole upload quota of key 'tiny' ({size - 1} bytes: "
        "VOXE_MAX_UPLOAD_BYTES_PER_KEY or the key's own), so it can never be accepted: have the service's admin "
        f"raise the key's own ('python -m api.admin update-key {key_id} --max-upload-bytes {size}')"))
    assert admin.main(["update-key", key_id, "--max-upload-bytes", str(size)]) == 0  # what it says, run as said
    capsys.readouterr()
    assert _upload(auth_client, mic_zip, bearer(tiny)).status_code == 201
    settings = get_settings()
    with session_scope() as session, pytest.raises(HTTPException) as refused:
        check_upload_bytes(session, session.get(ApiKey, LOCAL_KEY_ID), settings, settings.max_upload_bytes_per_key + 1)
    assert refused.value.status_code == 413
    assert refused.value.detail.endswith("so it can never be accepted: raise VOXE_MAX_UPLOAD_BYTES_PER_KEY")


def _post_upload_counting(app, token: str | None, total_bytes: int, idempotency_key: str) -> tuple[int, int, bytes]:
    """POST /v1/scenes a multipart upload of ``total_bytes`` (one zip of zeros, sent a MiB a message) to the ASGI
    app directly; (the status, the body bytes the app took in, the answer's body)."""
    boundary = b"b0undary"
    head = (b"--" + boundary + b'\r\nContent-Disposition: form-data; name="archive"; filename="big.zip"\r\n'
            b"Content-Type: application/zip\r\n\r\n")
    tail = b"\r\n--" + boundary + b"--\r\n"
    chunk = 1 << 20
    sizes = [len(head), *[chunk] * ((total_bytes - len(head) - len(tail)) // chunk), len(tail)]
    blocks = iter([head, *(bytes(size) for size in sizes[1:-1]), tail])
    taken, answer = [0], {"status": 0, "body": b""}
    length = len(head) + sum(sizes[1:-1]) + len(tail)

    async def receive():
        block = next(blocks, None)
        if block is None:
            return {"type": "http.request", "body": b"", "more_body": False}
        taken[0] += len(block)
        return {"type": "http.request", "body": block, "more_body": True}

    async def send(message):
        if message["type"] == "http.response.start":
            answer["status"] = message["status"]
        elif message["type"] == "http.response.body":
            answer["body"] += message.get("body", b"")

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": "/v1/scenes", "raw_path": b"/v1/scenes", "root_path": "", "query_string": b"",
             "server": ("testserver", 80), "client": ("127.0.0.1", 5000),
             "headers": [(b"host", b"testserver"), *([(b"authorization", f"Bearer {token}".encode())] if token else []),
                         (b"idempotency-key", idempotency_key.encode()), (b"content-length", str(length).encode()),
                         (b"content-type", b"multipart/form-data; boundary=" + boundary)]}
    anyio.run(app, scope, receive, send)
    return answer["status"], taken[0], answer["body"]


@BOTH_DATABASES
def test_an_upload_to_a_key_with_no_quota_left_is_refused_before_its_body_is_read(auth_client, mic_zip, root):  # noqa: F811
    """FastAPI receives and spools an upload's whole form before its route runs: the 429 of a key whose upload quota
    is used up ("before this upload is read") had come once all of it was in (a 200 MB upload: 200 MB received and
    spooled to disk for a refusal). It comes before the first body byte now; a retry whose Idempotency-Key has a
    record still replays what its first request created."""
    _, probe = _create_key("probe")
    size = _upload(auth_client, mic_zip, bearer(probe)).json()["size_bytes"]
    _, token = _create_key("full", max_upload_bytes=size)
    first = _upload(auth_client, mic_zip, {**bearer(token), "Idempotency-Key": "first"})
    assert first.status_code == 201
    code, taken, body = _post_upload_counting(auth_client.app, token, 200 << 20, "another")
    assert (code, taken) == (429, 0), (code, taken, body[:300])
    assert f"stores {size} bytes of scenes, before this upload is read" in body.decode()
    retry = _upload(auth_client, mic_zip, {**bearer(token), "Idempotency-Key": "first"})
    assert (retry.status_code, retry.json()["id"]) == (200, first.json()["id"])
    assert auth_client.get("/v1/scenes", headers=bearer(token)).json()["total"] == 1 and staged(root) == []


def test_an_upload_to_the_local_key_with_no_quota_left_is_refused_before_its_body_is_read(local_client, mic_zip,
                                                                                              monkeypatch):
    """With authentication off every request acts as the local key, held to VOXE_MAX_UPLOAD_BYTES_PER_KEY: its
    used-up quota is refused before the body is read too."""
    from voxe_service.settings import get_settings

    size = _upload(local_client, mic_zip).json()["size_bytes"]
    monkeypatch.setenv("VOXE_MAX_UPLOAD_BYTES_PER_KEY", str(size))
    get_settings.cache_clear()
    try:
        code, taken, body = _post_upload_counting(local_client.app, None, 8 << 20, "another")
    finally:
        monkeypatch.delenv("VOXE_MAX_UPLOAD_BYTES_PER_KEY")
        get_settings.cache_clear()
    assert (code, taken) == (429, 0), (code, taken, body[:300])
    assert f"stores {size} bytes of scenes, before this upload is read" in body.decode()


def test_an_upload_over_the_quota_is_refused_before_its_bytes_are_stored(auth_client, mic_zip, monkeypatch):
    """The packed archive's size is known before it is stored: an upload over the key's whole quota (413), or over
    what is left of it (429), had been written to storage and then deleted (GBs sent to S3 for nothing). An upload
    filling the quota exactly is accepted."""
    from voxe_service.storage import get_storage

    storage, stored = get_storage(), []
    put_file = storage.put_file
    monkeypatch.setattr(storage, "put_file", lambda key, *args: stored.append(key) or put_file(key, *args))
    _, probe = _create_key("probe")
    size = _upload(auth_client, mic_zip, bearer(probe)).json()["size_bytes"]
    _, tiny = _create_key("tiny", max_upload_bytes=size - 1)
    alone = _upload(auth_client, mic_zip, bearer(tiny))
    assert alone.status_code == 413, alone.text
    assert f"stores {size} bytes, more than the whole upload quota of key 'tiny' ({size - 1} bytes" in \
        alone.json()["detail"]
    _, exact = _create_key("exact", max_upload_bytes=2 * size)
    assert [_upload(auth_client, mic_zip, bearer(exact)).status_code for _ in range(2)] == [201, 201]
    full = _upload(auth_client, mic_zip, bearer(exact))
    assert full.status_code == 429  # refused before it is read: a quota exactly used up has room for no byte
    assert f"stores {2 * size} bytes of scenes, before this upload is read" in full.json()["detail"]
    _, small = _create_key("small", max_upload_bytes=size + size // 2)
    assert _upload(auth_client, mic_zip, bearer(small)).status_code == 201
    over = _upload(auth_client, mic_zip, bearer(small))
    assert over.status_code == 429
    assert f"stores {size} bytes of scenes, this upload adds {size}" in over.json()["detail"]
    assert len(stored) == 4  # the accepted uploads' only


def test_an_upload_retry_racing_its_first_request_replays_it_not_a_quota_refusal(auth_client, mic_zip, root,  # noqa: F811
                                                                                   monkeypatch):
    """A retry with the Idempotency-Key, unpacking while its first request commits, on a key with room for one
    upload: the quota check before storing had answered it 429 (the first request's scene filling the quota), where
    the check under the key's lock replays it."""
    import api.services.scenes as scenes

    _, probe = _create_key("probe")
    size = _upload(auth_client, mic_zip, bearer(probe)).json()["size_bytes"]
    _, token = _create_key("one", max_upload_bytes=size + size // 2)
    headers, stagings, first = {**bearer(token), "Idempotency-Key": "up-1"}, [], {}
    stage_upload = scenes.stage_upload

    def first_request_completes_while_staging(*args, **kwargs):
        staged_upload = stage_upload(*args, **kwargs)
        stagings.append(staged_upload)
        if len(stagings) == 1:  # the retry's: its first request comes and completes meanwhile
            first["response"] = _upload(auth_client, mic_zip, headers)
        return staged_upload

    monkeypatch.setattr(scenes, "stage_upload", first_request_completes_while_staging)
    retry = _upload(auth_client, mic_zip, headers)
    assert first["response"].status_code == 201, first["response"].text
    assert retry.status_code == 200 and retry.headers["idempotent-replayed"] == "true", retry.text
    assert retry.json() == first["response"].json() and staged(root) == []
    assert auth_client.get("/v1/scenes", headers=bearer(token)).json()["total"] == 1


def test_an_upload_refused_by_a_racing_one_answers_its_quota_even_when_its_bytes_cannot_be_deleted(
        auth_client, mic_zip, monkeypatch, caplog):
    """Two uploads racing for a key's last room: the one refused under the key's lock deletes the bytes it stored.
    A storage failing that deletion had turned the 429 naming the quota into a 503 "try again" (retrying the same
    upload, refused again); the bytes left behind are counted in no quota, and the failure is logged."""
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import StorageUnavailable, get_storage

    _, probe = _create_key("probe")
    size = _upload(auth_client, mic_zip, bearer(probe)).json()["size_bytes"]
    key_id, token = _create_key("small", max_upload_bytes=size + size // 2)
    storage = get_storage()
    put_file = storage.put_file

    def racing_put_file(key, *args):
        with session_scope() as session:  # the racing upload lands while this one's bytes are stored
            session.add(Scene(owner_key_id=key_id, name="racer", format="nerf_synthetic", image_count=1, width=1,
                              height=1, storage_key="k", size_bytes=size, sha256="0" * 64))
        return put_file(key, *args)

    def unreachable(key):
        raise StorageUnavailable(f"cannot delete {key}: the storage is unreachable")

    monkeypatch.setattr(storage, "put_file", racing_put_file)
    monkeypatch.setattr(storage, "delete", unreachable)
    with caplog.at_level(logging.WARNING, logger="voxe"):
        refused = _upload(auth_client, mic_zip, bearer(token))
    assert refused.status_code == 429, refused.text
    assert f"key 'small' stores {size} bytes of scenes, this upload adds {size}" in refused.json()["detail"]
    assert "could not delete the stored object scenes/" in caplog.text
    assert [s["name"] for s in auth_client.get("/v1/scenes", headers=bearer(token)).json()["items"]] == ["racer"]


@BOTH_DATABASES
def test_a_mesh_whose_rendered_views_go_over_the_upload_quota_fails_at_its_ingest(auth_client, root,  # noqa: F811
                                                                                    monkeypatch):
    """A mesh upload is a few hundred bytes; its ingest stores its rendered views instead (MBs at the default 100
    views of 256 px). Three 449-byte meshes had each passed a 100 kB quota and stored 6.3 MB."""
    import trimesh

    from service_helpers import ingest
    from voxe_service import datasets

    monkeypatch.setattr(datasets, "MESH_VIEWS", 4)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    cube = trimesh.creation.box().export(file_type="ply")

    def upload_mesh(token):
        response = auth_client.post("/v1/scenes", files={"files": ("cube.ply", cube)}, headers=bearer(token))
        assert response.status_code == 201, response.text
        return response.json()

    _, probe = _create_key("probe")
    rendered = ingest(upload_mesh(probe)["id"])["state"] == "ready" and \
        auth_client.get("/v1/scenes", headers=bearer(probe)).json()["items"][0]["size_bytes"]
    assert rendered > 10 * len(cube)
    _, token = _create_key("small", max_upload_bytes=rendered + rendered // 2)  # room for one rendered mesh
    first, second = upload_mesh(token), upload_mesh(token)  # each small as uploaded: both accepted
    waiting = auth_client.post("/v1/jobs", json={"scene_id": second["id"], **JOB}, headers=bearer(token)).json()
    assert ingest(first["id"])["state"] == "ready"
    assert ingest(second["id"])["state"] == "failed"
    failed = auth_client.get(f"/v1/scenes/{second['id']}", headers=bearer(token)).json()
    assert failed["state"] == "failed" and failed["size_bytes"] == 0
    assert f"the mesh's rendered views take {rendered} bytes and key 'small' stores {rendered} bytes" in \
        failed["error"]
    assert not [f for f in stored_files(root) if f.startswith(f"scenes/{second['id']}")]
    job = auth_client.get(f"/v1/jobs/{waiting['id']}", headers=bearer(token)).json()
    assert job["state"] == "failed" and "quota of upload bytes exceeded" in job["error"]


def test_a_mesh_ingest_over_quota_keeps_nothing_whatever_became_of_its_scene(root, auth_client,  # noqa: F811
                                                                             monkeypatch):
    """The quota check of a mesh's ingest meets a scene failed (by the reaper) or deleted meanwhile: its rendered
    views had stayed in storage, and a deleted scene's check looked a key up by a NULL id. The scene's objects are
    cleared once (a scene failed over quota had its prefix deleted twice: another listing of an S3 prefix)."""
    import warnings

    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import FAILED, PROCESSING, Scene
    from voxe_service.settings import get_settings
    from voxe_service.storage import get_storage, scene_key
    from worker.ingest import _ready

    key_id, _ = _create_key("full", max_upload_bytes=100)
    settings, storage = get_settings(), get_storage()

    def scene(state: str) -> str:
        with session_scope() as session:
            row = Scene(owner_key_id=key_id, name="m", format="mesh", image_count=1, width=1, height=1,
                        storage_key="k", size_bytes=10, sha256="0" * 64, state=state, ingest_token="run")
            session.add(row)
            session.flush()
            storage.put_bytes(scene_key(row.id, datasets.DATASET_ARCHIVE), b"rendered views" * 100)
            return row.id

    cleared, delete_prefix = [], storage.delete_prefix

    def counted_delete_prefix(prefix: str) -> None:
        cleared.append(prefix)
        delete_prefix(prefix)

    monkeypatch.setattr(storage, "delete_prefix", counted_delete_prefix)
    for state in (PROCESSING, FAILED):
        scene_id = scene(state)
        cleared.clear()
        assert _ready(scene_id, "run", {"size_bytes": 1400, "storage_key": "x"}, storage, settings, None).keys() >= \
            {"scene_id"}
        assert storage.list(scene_key(scene_id)) == [] and cleared == [scene_key(scene_id)], (state, cleared)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SQLAlchemy's "fully NULL primary key identity" warning
        gone = _ready("0" * 32, "run", {"size_bytes": 1400, "storage_key": "x"}, storage, settings, None)
    assert "deleted or failed meanwhile" in gone["skipped"]


# ------------------------------------------------------------------------------------------ Idempotency-Key
def test_job_creation_is_idempotent(auth_client, mic_zip):
    _, alice = _create_key("alice")
    _, bob = _create_key("bob")
    scene = _upload(auth_client, mic_zip, bearer(alice)).json()
    body = {"scene_id": scene["id"], **JOB}
    headers = {**bearer(alice), "Idempotency-Key": "retry-1"}
    created = auth_client.post("/v1/jobs", json=body, headers=headers)
    replayed = auth_client.post("/v1/jobs", json=body, headers=headers)
    assert created.status_code == 201 and "idempotent-replayed" not in created.headers
    assert replayed.status_code == 200 and replayed.headers["idempotent-replayed"] == "true"
    assert replayed.json()["id"] == created.json()["id"]
    assert auth_client.get("/v1/jobs", headers=bearer(alice)).json()["total"] == 1

    conflict = auth_client.post("/v1/jobs", json={**body, "prompt": "a mic wearing a hat", "edit_words": ["hat"]},
                                headers=headers)
    assert conflict.status_code == 422
    assert conflict.json()["detail"] == (  # the job named as a job ("it created jobs '...'" had been said)
        f"Idempotency-Key 'retry-1' was already used with a different request body (it created job "
        f"{created.json()['id']!r}); use a new key for a new request")
    # Keys are per API key: bob's "retry-1" is his own (and alice's scene is not his).
    response = auth_client.post("/v1/jobs", json=body, headers={**bearer(bob), "Idempotency-Key": "retry-1"})
    assert response.status_code == 404
    for bad, said in (("", "is blank"), (" ", "is blank"), ("k" * 256, "must be 1-255 characters, got 256")):
        response = auth_client.post("/v1/jobs", json=body, headers={**bearer(alice), "Idempotency-Key": bad})
        assert response.status_code == 422 and f"Idempotency-Key header {said}" in response.text


def test_evaluation_creation_is_idempotent_and_a_refused_one_runs_again_on_retry(local_client, mic_zip,
                                                                                 monkeypatch):
    """POST /v1/evaluations honours Idempotency-Key as POST /v1/jobs does (the same shared submission): a retry had
    created a second evaluation of the same jobs."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.queue import TaskQueue

    scene = _upload(local_client, mic_zip).json()
    assert ingest(scene["id"])["state"] == "ready"  # (no worker here): the evaluation is sent at once
    edit = local_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == edit["id"]).values(state="succeeded"))
    body, headers = {"job_ids": [edit["id"]], "object": "mic"}, {"Idempotency-Key": "eval-1"}

    def evaluations():
        return [j["id"] for j in local_client.get("/v1/jobs").json()["items"] if j["mode"] == "evaluate"]

    with monkeypatch.context() as broker_down:  # a 503 keeps nothing: the retry submits it anew
        broker_down.setattr(TaskQueue, "send", lambda self, *args: (_ for _ in ()).throw(ConnectionError("down")))
        refused = local_client.post("/v1/evaluations", json=body, headers=headers)
    assert refused.status_code == 503 and evaluations() == []
    created = local_client.post("/v1/evaluations", json=body, headers=headers)
    replayed = local_client.post("/v1/evaluations", json=body, headers=headers)
    assert created.status_code == 201 and "idempotent-replayed" not in created.headers
    assert replayed.status_code == 200 and replayed.headers["idempotent-replayed"] == "true"
    assert replayed.json()["id"] == created.json()["id"] and evaluations() == [created.json()["id"]]
    conflict = local_client.post("/v1/evaluations", json={**body, "object": "lamp"}, headers=headers)
    assert conflict.status_code == 422 and conflict.json()["detail"] == (
        f"Idempotency-Key 'eval-1' was already used with a different request body (it created evaluation "
        f"{created.json()['id']!r}); use a new key for a new request")
    # per endpoint: the same key on POST /v1/jobs is another request's
    assert local_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=headers).status_code == 201


def test_sweep_creation_is_idempotent(local_client, mic_zip):
    """POST /v1/sweeps honours Idempotency-Key as POST /v1/jobs and /v1/evaluations do: a client retrying a sweep
    after a lost response had queued the whole protocol twice."""
    scene = _upload(local_client, mic_zip).json()
    assert ingest(scene["id"])["state"] == "ready"
    body, headers = {"scenes": [{"scene_id": scene["id"], "object": "mic"}]}, {"Idempotency-Key": "sweep-1"}
    created = local_client.post("/v1/sweeps", json=body, headers=headers)
    replayed = local_client.post("/v1/sweeps", json=body, headers=headers)
    assert created.status_code == 201 and "idempotent-replayed" not in created.headers
    assert replayed.status_code == 200 and replayed.headers["idempotent-replayed"] == "true"
    assert replayed.json()["id"] == created.json()["id"] and local_client.get("/v1/jobs").json()["total"] == 12
    conflict = local_client.post("/v1/sweeps", json={**body, "evaluation": {"views": 4}}, headers=headers)
    assert conflict.status_code == 422 and conflict.json()["detail"].startswith(
        "Idempotency-Key 'sweep-1' was already used with a different request body (it created sweep holding job ")
    blank = local_client.post("/v1/sweeps", json=body, headers={"Idempotency-Key": " "})
    assert blank.status_code == 422 and "Idempotency-Key header is blank" in blank.text


def test_a_sweep_the_broker_refuses_part_way_is_withdrawn_whole_and_a_retry_runs_anew(local_client, mic_zip,
                                                                                     monkeypatch):
    """A broker refusing a sweep's third edit had left the two sent running and failed the rest: the 503 named
    neither, and the retry queued those two edits again. A sweep is all or nothing: the 503 withdraws it, what was
    sent canceled with the rest, and a retry with the same Idempotency-Key runs it anew."""
    from voxe_service.queue import TaskQueue

    scene = _upload(local_client, mic_zip).json()
    assert ingest(scene["id"])["state"] == "ready"
    body, headers = {"scenes": [{"scene_id": scene["id"], "object": "mic"}]}, {"Idempotency-Key": "sweep-2"}
    sent, send = [], TaskQueue.send

    def refuse_the_third(self, *args):
        if len(sent) == 2:
            raise ConnectionError("down")
        sent.append(send(self, *args))
        return sent[-1]

    with monkeypatch.context() as broker_dies:
        broker_dies.setattr(TaskQueue, "send", refuse_the_third)
        refused = local_client.post("/v1/sweeps", json=body, headers=headers)
    assert refused.status_code == 503 and len(sent) == 2
    jobs = local_client.get("/v1/jobs", params={"limit": 200}).json()["items"]
    assert len(jobs) == 12 and {j["state"] for j in jobs} == {"canceled"}
    assert refused.json()["detail"] == (
        "could not queue the job: the job queue is unavailable; the sweep is withdrawn: its 12 jobs are canceled (the "
        "4 already sent too: any a worker already started stops at its next cancel check; sweep "
        f"{jobs[0]['batch_id']!r} lists them), so a retry repeats none of them; try again in 5 s")
    assert {j["message"] for j in jobs} == {"the sweep was withdrawn: the broker refused part of it"}
    retried = local_client.post("/v1/sweeps", json=body, headers=headers)
    assert retried.status_code == 201 and retried.json()["counts"] == {"queued": 12}
    assert retried.json()["id"] != jobs[0]["batch_id"]
    again = local_client.post("/v1/sweeps", json=body, headers=headers)
    assert again.status_code == 200 and again.json()["id"] == retried.json()["id"]


def test_a_sweep_retry_is_not_replayed_while_its_first_request_may_still_withdraw_it(root, mic_zip,  # noqa: F811
                                                                                     monkeypatch):
    """The record had named the sweep's last job: its scene still processing, that scene's ingest sent it while the
    first request was still sending the other scene's, a retry replayed the sweep (200), and the broker refusing the
    first request's next send withdrew it a moment later. The 503 had also counted as sent only what the request
    itself sent."""
    from voxe_service.queue import TaskQueue

    monkeypatch.setenv("VOXE_MAX_ACTIVE_JOBS_PER_KEY", "24")
    _reset()
    from api.main import create_app

    with TestClient(create_app()) as client:
        ready = _upload(client, mic_zip, name="ready.zip").json()
        assert ingest(ready["id"])["state"] == "ready"
        processing = _upload(client, mic_zip, name="processing.zip").json()  # its jobs wait for its ingest
        body = {"scenes": [{"scene_id": ready["id"], "object": "mic"},
                           {"scene_id": processing["id"], "object": "mic"}]}
        headers, sent, seen, real_send = {"Idempotency-Key": "sweep-3"}, [], {}, TaskQueue.send

        def ingest_and_retry_during_the_second_send(self, *args):
            if seen.get("ingesting"):  # the ingest's own sends go through
                return real_send(self, *args)
            if len(sent) == 1:  # the processing scene's ingest ends (sending its 6 chains), and a retry comes
                seen["ingesting"] = True
                seen["ingest"] = ingest(processing["id"])["state"]
                seen["ingesting"] = False
                seen["retry"] = client.post("/v1/sweeps", json=body, headers=headers)
            if len(sent) == 2:
                raise ConnectionError("down")
            sent.append(real_send(self, *args))
            return sent[-1]

        with monkeypatch.context() as broker:
            broker.setattr(TaskQueue, "send", ingest_and_retry_during_the_second_send)
            refused = client.post("/v1/sweeps", json=body, headers=headers)
        assert seen["ingest"] == "ready" and refused.status_code == 503, refused.text
        retry = seen["retry"]
        assert retry.status_code == 409 and "has not answered yet" in retry.json()["detail"], retry.text
        jobs = client.get("/v1/jobs", params={"limit": 200}).json()["items"]
        assert len(jobs) == 24 and {j["state"] for j in jobs} == {"canceled"}
        # 2 chains of the ready scene's (an edit and its evaluation each), 6 of the processing one's by its ingest
        assert "its 24 jobs are canceled (the 16 already sent too" in refused.json()["detail"]
        again = client.post("/v1/sweeps", json=body, headers=headers)
        assert again.status_code == 201 and again.json()["id"] != jobs[0]["batch_id"]


def test_a_job_retried_across_an_upgrade_that_changed_a_default_replays(auth_client, mic_zip, monkeypatch):
    """The digest had been of the body with every default filled in: a release changing a default (or adding a
    field) turned a client's unchanged retry into "a different request body". It is of what the client sent; a
    record holding the whole body's digest (recorded before this change) still matches."""
    from sqlalchemy import update

    import api.schemas as schemas
    from voxe_service.db import session_scope
    from voxe_service.models import IdempotencyRecord

    _, alice = _create_key("alice")
    scene = _upload(auth_client, mic_zip, bearer(alice)).json()
    body = {"scene_id": scene["id"], "prompt": "a mic wearing big sunglasses", "mode": "local",
            "edit_words": ["sunglasses"]}
    headers = {**bearer(alice), "Idempotency-Key": "retry-2"}
    created = auth_client.post("/v1/jobs", json=body, headers=headers).json()
    whole = hashlib.sha256(schemas.JobCreate.model_validate(body).model_dump_json().encode()).hexdigest()
    field = schemas.RefineParams.model_fields["iterations"]
    try:  # the release after: the refinement's default iterations change, nothing the client sent does
        monkeypatch.setattr(field, "default", field.default + 100)
        for model in (schemas.RefineParams, schemas.JobParams, schemas.JobCreate):
            model.model_rebuild(force=True)
        retried = auth_client.post("/v1/jobs", json=body, headers=headers)
    finally:
        monkeypatch.undo()
        for model in (schemas.RefineParams, schemas.JobParams, schemas.JobCreate):
            model.model_rebuild(force=True)
    assert retried.status_code == 200 and retried.json()["id"] == created["id"]
    with session_scope() as session:  # as the version before this change recorded it
        session.execute(update(IdempotencyRecord).where(IdempotencyRecord.idempotency_key == "retry-2")
                        .values(request_sha256=whole))
    again = auth_client.post("/v1/jobs", json=body, headers=headers)
    assert again.status_code == 200 and again.json()["id"] == created["id"]


@BOTH_DATABASES
def test_concurrent_retries_create_one_job(auth_client, mic_zip):
    _, token = _create_key("racer")
    scene = _upload(auth_client, mic_zip, bearer(token)).json()
    headers = {**bearer(token), "Idempotency-Key": "same"}
    barrier, results = threading.Barrier(4), []

    def post():
        barrier.wait()
        results.append(auth_client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers=headers))

    threads = [threading.Thread(target=post) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    (created,) = [r for r in results if r.status_code == 201]
    replays = [r for r in results if r.status_code == 200]
    early = [r for r in results if r.status_code == 409]  # before the first request answered: it may yet withdraw it
    assert len(replays) + len(early) == 3 and {r.json()["id"] for r in replays} <= {created.json()["id"]}
    assert all("has not answered yet" in r.json()["detail"] for r in early)
    assert auth_client.get("/v1/jobs", headers=bearer(token)).json()["total"] == 1


def test_an_uploads_idempotency_digest_counts_a_field_added_later_only_when_it_is_sent():
    """A retry with the same Idempotency-Key across the upgrade that added ``mesh_up_axis`` must match its first
    request: the digest of an upload without it is the one the earlier version stored."""
    import io

    from api.services.scenes import Upload

    data = b"PK\x05\x06" + bytes(18)
    earlier = hashlib.sha256(repr(("cow", "auto")).encode() + b"\0archive\0" + data).hexdigest()
    assert Upload(io.BytesIO(data), "a.zip", [], "cow", "auto").digests() == (earlier, None)
    assert Upload(io.BytesIO(data), "a.zip", [], "cow", "auto", mesh_up_axis="z").digests()[0] != earlier


def test_an_unnamed_zip_retried_across_the_upgrade_counting_its_file_name_replays(local_client, mic_zip):  # noqa: F811
    """The digest of an upload sent without a name counts the zip's file name since it names the scene: a retry of
    one whose record the version before wrote (file name not counted) had been a 422 "different request body". That
    digest is still matched, so such a record also replays the same bytes under another file name."""
    import io

    from sqlalchemy import update

    from api.services.scenes import Upload
    from voxe_service.db import session_scope
    from voxe_service.models import IdempotencyRecord

    data = b"PK\x05\x06" + bytes(18)  # the version before's digest: the fields sent, then the archive's bytes
    before = "31a92870efad6ae88099a9df1238caf92cbbfac6fb46d761b9febedc1dad2903"
    assert hashlib.sha256(repr((None, None)).encode() + b"\0archive\0" + data).hexdigest() == before
    current, earlier = Upload(io.BytesIO(data), "a.zip", [], None, None).digests()
    assert earlier == before and current != before

    headers = {"Idempotency-Key": "before-the-upgrade"}
    created = _upload(local_client, mic_zip, headers)
    with open(mic_zip, "rb") as handle:
        recorded = hashlib.sha256(repr((None, None)).encode() + b"\0archive\0" + handle.read()).hexdigest()
    with session_scope() as session:  # as the version before recorded it
        session.execute(update(IdempotencyRecord).where(IdempotencyRecord.idempotency_key == headers["Idempotency-Key"])
                        .values(request_sha256=recorded))
    for name in ("mic.zip", "guitar.zip"):
        retried = _upload(local_client, mic_zip, headers, name=name)
        assert (retried.status_code, retried.json()) == (200, created.json()), name


def test_scene_creation_is_idempotent(local_client, mic_zip, dataset, root, tmp_path):  # noqa: F811
    headers = {"Idempotency-Key": "upload-1"}
    created = _upload(local_client, mic_zip, headers)
    replayed = _upload(local_client, mic_zip, headers)
    assert created.status_code == 201 and replayed.status_code == 200
    assert replayed.json() == created.json() and replayed.headers["idempotent-replayed"] == "true"
    assert stored_files(root) == [f"scenes/{created.json()['id']}/dataset.zip"] and staged(root) == []

    other = zip_folder(dataset, tmp_path / "two.zip", prefix="mic_small", only=lambda rel: "r_4" not in rel)
    conflict = _upload(local_client, other, headers)
    assert conflict.status_code == 422 and "different request body" in conflict.json()["detail"]
    assert f"(it created scene {created.json()['id']!r})" in conflict.json()["detail"]  # (had been "scenes '...'")
    # The same bytes under another file name ask for another scene name (a scene is named after its zip): it had
    # been replayed as the scene named "mic".
    renamed = _upload(local_client, mic_zip, headers, name="guitar.zip")
    assert renamed.status_code == 422 and "different request body" in renamed.json()["detail"]
    assert local_client.get("/v1/scenes").json()["total"] == 1
    # With a name sent, the file name names nothing: a client renaming the file it sends still replays.
    named = {"Idempotency-Key": "upload-2"}
    with open(mic_zip, "rb") as handle:
        first = local_client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")},
                                  data={"name": "studio mic"}, headers=named)
    with open(mic_zip, "rb") as handle:
        again = local_client.post("/v1/scenes", files={"archive": ("tmp1234.zip", handle, "application/zip")},
                                  data={"name": "studio mic"}, headers=named)
    assert first.status_code == 201 and again.status_code == 200 and again.json() == first.json()
    assert local_client.get("/v1/scenes").json()["total"] == 2

    assert local_client.delete(f"/v1/scenes/{created.json()['id']}").status_code == 204
    gone = _upload(local_client, mic_zip, headers)
    assert gone.status_code == 409 and "has been deleted" in gone.json()["detail"]


def test_malformed_credentials_are_401_never_5xx(root, monkeypatch):  # noqa: F811
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from api.main import create_app

    monkeypatch.setenv("VOXE_AUTH", "on")
    _reset()
    header_text = st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=80)
    token_like = st.builds(lambda i, s: f"voxe_{i}_{s}", st.text("0123456789abcdefl", max_size=14), header_text)
    with TestClient(create_app(), raise_server_exceptions=False) as client:
        _, token = _create_key("real")

        @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck), database=None)
        @given(st.sampled_from(["authorization", "x-api-key"]), st.sampled_from(["", "Bearer ", "bearer ", "Basic "]),
               st.one_of(header_text, token_like, st.just(token[:-1]), st.just(token + "x")))
        def probe(header, scheme, value):
            response = client.get("/v1/jobs", headers={header: scheme + value})
            assert response.status_code == 401, (header, scheme, value, response.text)

        probe()
        assert client.get("/v1/jobs", headers=bearer(token)).status_code == 200


def test_an_anonymous_upload_is_refused_before_its_body_is_read(auth_client):
    """The 401 comes from the middleware: neither the body nor the route is ever touched; so too for a revoked key
    (the routes' own check of it had hidden a middleware letting it through to the body)."""
    from api.auth import RequireKey
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, utcnow

    def untouchable(*_args):
        raise AssertionError("the request body or the route was reached")

    sent = []

    async def send(message):
        sent.append(message)

    async def run(headers, root_path):
        scope = {"type": "http", "method": "POST", "path": f"{root_path}/v1/scenes", "root_path": root_path,
                 "headers": headers, "query_string": b""}
        await RequireKey(untouchable)(scope, untouchable, send)

    for root_path in ("", "/api"):  # "/api": mounted behind a proxy (uvicorn --root-path /api)
        for headers in ([], [(b"authorization", b"Bearer voxe_0123456789ab_" + b"x" * 43)]):
            sent.clear()
            anyio.run(run, [(b"content-length", b"2000000000"), *headers], root_path)
            assert sent[0]["status"] == 401 and b"API key" in sent[1]["body"]

    key_id, token = _create_key("uploader")
    passed = []

    async def route(scope, _receive, _send):
        passed.append(scope["state"]["api_key_id"])

    async def run_valid():
        scope = {"type": "http", "method": "POST", "path": "/v1/scenes", "query_string": b"",
                 "headers": [(b"authorization", f"Bearer {token}".encode())]}
        await RequireKey(route)(scope, untouchable, send)

    anyio.run(run_valid)
    assert passed == [token.split("_")[1]]
    with session_scope() as session:
        session.get(ApiKey, key_id).revoked_at = utcnow()
    sent.clear()
    anyio.run(run, [(b"content-length", b"2000000000"), (b"authorization", f"Bearer {token}".encode())], "")
    assert sent[0]["status"] == 401 and b"invalid or revoked API key" in sent[1]["body"]


def test_a_job_canceled_once_no_run_renews_its_hold_ends_at_the_reapers_next_pass_freeing_its_quota_place(
        db, monkeypatch):  # noqa: F811
    """A running job whose run stopped renewing its hold (its worker died mid-stage, or the run stalled) and whose
    user then canceled it (it looked stuck): no run would ever see the flag, and the cancel had refreshed the job, so
    it stayed running, holding a place of the key's concurrent-job quota (and its scene from deletion: "canceled and
    still stopping"), until VOXE_JOB_STALE_TIMEOUT_S (15 min) after the cancel. It ends canceled at the next pass,
    as a job between stages does; one a live run holds is left to stop at its next check."""
    from api.reaper import reap_orphaned_jobs
    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.models import utcnow

    scene = add_scene()
    add_heartbeat("alive@host", age_s=1)
    lapsed = utcnow() - timedelta(seconds=5)
    dead = add_job(scene, "running", 0, "dead@host", "edit", run_token="t1", run_lease_until=lapsed)
    stalled = add_job(scene, "running", 0, "alive@host", "edit", run_token="t2", run_lease_until=lapsed)
    held = add_job(scene, "running", 0, "alive@host", "edit", run_token="t3",
                   run_lease_until=utcnow() + timedelta(seconds=60))
    with session_scope() as session:
        request_cancel(session=session, job_ids=[dead, stalled, held])
    assert sorted(reap_orphaned_jobs(db)) == sorted([dead, stalled])
    for job_id in (dead, stalled):
        ended = job_row(job_id)
        assert (ended.state, ended.message, ended.run_token) == ("canceled", "canceled: asked during edit", None)
    assert (job_row(held).state, job_row(held).cancel_requested) == ("running", True)


def test_readyz_shows_its_details_only_to_a_key_holder(auth_client, root):  # noqa: F811 - the fixture
    """/readyz needs no key (a load balancer's probe), and showed anyone the storage path, the broker's URL, worker
    hostnames and the errors' text. With authentication on, a caller without a live key gets the status code, the
    status and which check failed; a key's holder (the operator) every detail, as with authentication off."""
    anonymous = auth_client.get("/readyz")
    assert anonymous.status_code == 503  # no worker here
    assert anonymous.json() == {
        "status": "not ready",
        "checks": {"database": {"ok": True}, "broker": {"ok": True}, "storage": {"ok": True}, "worker": {"ok": False}},
        "details": "send an API key for each check's details and the models' availability"}
    assert str(root) not in anonymous.text
    for wrong in (bearer("voxe_000000000000_" + "x" * 43), {"X-API-Key": "garbage"}):
        assert auth_client.get("/readyz", headers=wrong).json() == anonymous.json()
    _, token = _create_key("operator")
    detailed = auth_client.get("/readyz", headers=bearer(token))
    assert detailed.status_code == 503
    checks = detailed.json()["checks"]
    assert checks["worker"] == {"ok": False, "method": "database heartbeat", "workers": []}
    assert "url" in checks["broker"] and "backend" in checks["storage"] and "model_availability" in detailed.json()


def test_readyz_sent_two_different_keys_answers_its_status_not_a_401(auth_client):
    """/readyz needs no key, but a request carrying two different keys (a probe's X-API-Key and a proxy's Bearer) was
    answered /v1's 401 "2 different API keys sent", a load balancer then taking a ready service for a failed one. It
    now answers its status and code as to a caller sending none, the details withheld and the reason said."""
    _, token = _create_key("operator")
    anonymous = auth_client.get("/readyz")
    both = auth_client.get("/readyz", headers={**bearer(token), "X-API-Key": "voxe_000000000000_" + "y" * 43})
    assert both.status_code == anonymous.status_code == 503  # (no worker here)
    assert both.json()["checks"] == anonymous.json()["checks"]
    assert both.json()["details"] == ("2 different API keys sent (1 Authorization: Bearer line and 1 X-API-Key line): "
                                      "send one key for each check's details and the models' availability")
    assert "model_availability" not in both.json()


def test_readyz_with_the_database_down_does_not_tell_a_key_holder_to_send_a_key(auth_client, monkeypatch):
    """With the database down, /readyz cannot check a key, so it shows no details: it told an operator presenting
    their live key to "send an API key", the one they had sent. It now says the key sent could not be checked, and
    still shows nothing more than to a caller sending none."""
    import contextlib

    from sqlalchemy.exc import OperationalError

    import api.routes.health as health

    _, token = _create_key("operator")

    @contextlib.contextmanager
    def database_down():
        raise OperationalError("SELECT 1", {}, ConnectionRefusedError("connection refused"))
        yield  # (a generator: never reached)

    monkeypatch.setattr(health, "session_scope", database_down)
    anonymous = auth_client.get("/readyz")
    assert anonymous.status_code == 503 and anonymous.json()["checks"]["database"] == {"ok": False}
    assert anonymous.json()["details"] == "send an API key for each check's details and the models' availability"
    answer = auth_client.get("/readyz", headers=bearer(token))
    assert answer.status_code == 503
    assert answer.json()["checks"] == anonymous.json()["checks"]
    assert answer.json()["details"] == ("the API key sent could not be checked (the database is not reachable): each "
                                        "check's details and the models' availability are shown to a live key's "
                                        "holder once it is")
    assert "connection refused" not in answer.text


def test_readyz_answers_within_its_deadline_while_the_database_hangs(auth_client, monkeypatch):
    """A database that accepts and never answers (hung, partitioned): the checks are cut at their deadline
    (VOXE_READINESS_TIMEOUT_S x 3 + 2 s), but the models' availability and a key's check then waited on the database
    in the request itself, each up to a connect timeout (10 s, or the pool's 30 s), and a load balancer's probe got no
    answer in time while the request held a thread. Both are bounded by the same deadline now: 503, the database
    check failed, and a key holder told that the key could not be checked."""
    import contextlib

    import api.routes.health as health
    from voxe_service.settings import get_settings

    _, token = _create_key("operator")
    release = threading.Event()

    @contextlib.contextmanager
    def database_hung():
        release.wait(30)
        raise ConnectionRefusedError("released")
        yield  # (a generator: never reached)

    monkeypatch.setattr(get_settings(), "readiness_timeout_s", 0.2)  # a deadline of 2.6 s
    monkeypatch.setattr(health, "session_scope", database_hung)
    try:
        for headers in ({}, bearer(token)):
            started = time.monotonic()
            answer = auth_client.get("/readyz", headers=headers)
            assert time.monotonic() - started < 6, headers
            assert answer.status_code == 503 and answer.json()["checks"]["database"] == {"ok": False}
        assert answer.json()["details"].startswith("the API key sent could not be checked")
    finally:
        release.set()


def test_readyz_with_authentication_off_shows_its_details_only_to_a_local_caller(local_client, root):  # noqa: F811
    """With authentication off, only loopback requests from this machine are served as the local key (a /v1 request
    that came in on another address, that a proxy relayed or that names another host is a 401), but /readyz showed
    every caller the storage path, the broker's URL, worker hostnames and the errors' text: a proxy in front, or a
    page of another site whose name was pointed at 127.0.0.1 (DNS rebinding), read the deployment's internals. Such
    a caller now gets what a caller without a key gets with authentication on, told why; a local one every detail."""
    local = local_client.get("/readyz")
    assert local.status_code == 503 and "model_availability" in local.json() and str(root) in local.text
    for headers, why in (({"X-Forwarded-For": "203.0.113.9"}, "relayed by a proxy (its X-Forwarded-For header)"),
                         ({"Host": "rebound.example"}, "names another host (Host: rebound.example)")):
        answer = local_client.get("/readyz", headers=headers)
        assert answer.status_code == 503
        assert answer.json()["checks"] == {"database": {"ok": True}, "broker": {"ok": True}, "storage": {"ok": True},
                                           "worker": {"ok": False}}
        assert set(answer.json()) == {"status", "checks", "details"} and str(root) not in answer.text
        assert answer.json()["details"].startswith("authentication is off, so each check's details and the models' "
                                                   "availability are shown only to loopback connections from this "
                                                   "machine, and this one "), answer.json()
        assert why in answer.json()["details"]
        assert local_client.get("/v1/scenes", headers=headers).status_code == 401  # (as the API itself answers it)


def test_idempotency_records_go_once_past_their_retention_and_a_retry_then_makes_anew(db):  # noqa: F811
    """voxe_client sends an Idempotency-Key with every upload, job, evaluation and sweep: their records had been kept
    for good. The reaper's pass deletes those created VOXE_IDEMPOTENCY_RETENTION_S (a day) ago, pending ones
    included (a request answers in far less), and keeps the younger ones, which still replay."""
    from sqlalchemy import select

    from api.auth import Idempotency
    from api.reaper import Reaper, reap_idempotency_records
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, ApiKey, IdempotencyRecord, Job, utcnow

    assert db.idempotency_retention_s == 24 * 3600.0
    job = add_job(add_scene(), "succeeded", 0)
    ages = {"old": (db.idempotency_retention_s + 60, False), "old-pending": (db.idempotency_retention_s + 60, True),
            "young": (db.idempotency_retention_s - 60, False)}
    with session_scope() as session:
        local = session.get(ApiKey, LOCAL_KEY_ID)
        for name, (age_s, pending) in ages.items():
            record = Idempotency(name, "0" * 64, "jobs").record(session, local, job)
            record.created_at, record.pending = utcnow() - timedelta(seconds=age_s), pending

    def kept() -> list[str]:
        with session_scope() as session:
            return sorted(session.scalars(select(IdempotencyRecord.idempotency_key)))

    reaper = Reaper(db).start()  # its first pass, at startup
    try:
        deadline = time.monotonic() + 30
        while kept() != ["young"] and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        reaper.stop()
    assert kept() == ["young"]
    assert reap_idempotency_records(db, utcnow() + timedelta(seconds=120)) == 1  # the young one, a retention later
    with session_scope() as session:
        local = session.get(ApiKey, LOCAL_KEY_ID)
        assert Idempotency("old", "0" * 64, "jobs").replayed(session, local, Job) is None  # a retry now runs anew
