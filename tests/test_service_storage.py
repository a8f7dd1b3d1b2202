"""The storage layer: the local-directory and the S3 implementation (against moto's real HTTP server)."""

from __future__ import annotations

import hashlib

import pytest

from voxe_service.storage import LocalStorage, ObjectNotFound, S3Storage, StorageError, check_key
from service_helpers import free_port


@pytest.fixture(scope="module")
def s3_endpoint():
    moto_server = pytest.importorskip("moto.server")
    port = free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.stop()


@pytest.fixture
def aws_env(monkeypatch):
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    for name in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_SECURITY_TOKEN"):
        monkeypatch.delenv(name, raising=False)


@pytest.fixture(params=["local", "s3"])
def storage(request, tmp_path):
    if request.param == "local":
        return LocalStorage(tmp_path / "store")
    request.getfixturevalue("aws_env")
    endpoint = request.getfixturevalue("s3_endpoint")
    return S3Storage(f"voxe-test-{request.node.name.split('[')[0].replace('_', '-')[:40]}", endpoint_url=endpoint,
                     region="us-east-1", prefix="svc")


def test_put_get_range_list_delete(storage, tmp_path):
    data = bytes(range(256)) * 4100  # > one 1 MiB chunk
    source = tmp_path / "blob.bin"
    source.write_bytes(data)
    stored = storage.put_file("jobs/a/blob.bin", source, "application/octet-stream")
    assert stored.size == len(data) and stored.sha256 == hashlib.sha256(data).hexdigest()
    assert storage.size("jobs/a/blob.bin") == len(data) and storage.exists("jobs/a/blob.bin")
    assert b"".join(storage.open_range("jobs/a/blob.bin")) == data
    assert b"".join(storage.open_range("jobs/a/blob.bin", 1000, 1009)) == data[1000:1010]
    assert b"".join(storage.open_range("jobs/a/blob.bin", len(data) - 5)) == data[-5:]
    assert b"".join(storage.open_range("jobs/a/blob.bin", 5, 2 * 1024 * 1024)) == data[5:2 * 1024 * 1024 + 1]
    storage.get_file("jobs/a/blob.bin", tmp_path / "copy.bin")
    assert (tmp_path / "copy.bin").read_bytes() == data
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []

    storage.put_bytes("jobs/a/small.txt", b"one")
    storage.put_bytes("jobs/a/small.txt", b"two")  # replaced whole
    assert b"".join(storage.open_range("jobs/a/small.txt")) == b"two"
    storage.put_bytes("jobs/b/other.txt", b"x")
    assert storage.list("jobs/a/") == ["jobs/a/blob.bin", "jobs/a/small.txt"]
    assert storage.list() == ["jobs/a/blob.bin", "jobs/a/small.txt", "jobs/b/other.txt"]
    assert storage.delete_prefix("jobs/a/") == 2
    assert storage.list() == ["jobs/b/other.txt"]
    storage.delete("jobs/b/other.txt")
    storage.delete("jobs/b/other.txt")  # missing: not an error
    assert storage.list() == [] and not storage.exists("jobs/b/other.txt")
    with pytest.raises(ObjectNotFound):
        storage.size("nothing/here")
    with pytest.raises(ObjectNotFound):
        storage.get_file("nothing/here", tmp_path / "x")
    assert not (tmp_path / "x").exists()
    storage.check_writable()
    assert storage.list() == []


def test_both_backends_agree_on_tmp_keys_and_empty_ranges(storage):
    """A key may end in .tmp (only a local writer's own temporary name is hidden), and a range that starts past
    the end or ends before its start holds no bytes, on either backend."""
    storage.put_bytes("jobs/t/notes.tmp", b"kept")
    storage.put_bytes("jobs/t/data.bin", b"0123456789")
    assert storage.list("jobs/t/") == ["jobs/t/data.bin", "jobs/t/notes.tmp"]
    assert b"".join(storage.open_range("jobs/t/data.bin", 10)) == b""
    assert b"".join(storage.open_range("jobs/t/data.bin", 50, 60)) == b""
    assert b"".join(storage.open_range("jobs/t/data.bin", 5, 4)) == b""
    with pytest.raises(ObjectNotFound):
        storage.open_range("jobs/t/missing.bin", 5, 4)
    assert storage.delete_prefix("jobs/t/") == 2 and storage.list() == []


def test_both_backends_list_by_plain_prefix(storage):
    """A prefix is a plain string prefix on either backend (a folder name may be cut short); the local one walks
    only the prefix's folder, and a prefix whose folder does not exist lists nothing."""
    for key in ("jobs/a/x.bin", "jobs/ab/y.bin", "jobs/a.txt", "jobsx/z.bin", "scenes/s/data.zip"):
        storage.put_bytes(key, b"1")
    assert storage.list("jobs/a") == ["jobs/a.txt", "jobs/a/x.bin", "jobs/ab/y.bin"]
    assert storage.list("jobs/a/") == ["jobs/a/x.bin"]
    assert storage.list("jobs/a/x") == ["jobs/a/x.bin"]
    assert storage.list("jobs") == ["jobs/a.txt", "jobs/a/x.bin", "jobs/ab/y.bin", "jobsx/z.bin"]
    assert storage.list("jobs/missing/") == [] and storage.list("nowhere/at/all") == []
    assert storage.list("jobs//a") == storage.list("./") == storage.list("a b/") == []
    assert storage.delete_prefix("jobs/a") == 3
    assert storage.list() == ["jobsx/z.bin", "scenes/s/data.zip"]


def test_s3_objects_a_delete_kept_are_an_error(caplog):
    """S3's DeleteObjects answers 200 and names the objects it could not delete: that is a failure, as a local
    delete that fails raises."""
    class Pages:
        def paginate(self, **kwargs):
            return [{"Contents": [{"Key": "svc/jobs/j/a.png"}, {"Key": "svc/jobs/j/b.png"}]}]

    class Client:
        def get_paginator(self, name):
            return Pages()

        def delete_objects(self, Bucket, Delete):
            return {"Errors": [{"Key": Delete["Objects"][1]["Key"], "Code": "AccessDenied"}]}

    store = S3Storage("bucket", prefix="svc", create_bucket=False, client=Client())
    with pytest.raises(StorageError, match=r"could not delete 1 object\(s\) under 'jobs/j/': svc/jobs/j/b.png "
                                           r"\(AccessDenied\)"):
        store.delete_prefix("jobs/j/")
    with caplog.at_level("WARNING", logger="voxe.storage"):  # cleanup of debris: said, not raised
        store.discard_prefixes("jobs/j/")
    assert "could not delete the stored objects under jobs/j/" in caplog.text


@pytest.mark.parametrize("key", ["../etc/passwd", "/abs", "a//b", "a/./b", "a/../b", "", "a\\b", "a/b c"])
def test_keys_cannot_escape(storage, key):
    with pytest.raises(StorageError):
        storage.put_bytes(key, b"x")
    with pytest.raises(StorageError):
        check_key(key)


def test_local_writes_are_atomic(tmp_path, monkeypatch):
    store = LocalStorage(tmp_path / "store")
    store.put_bytes("a/b.bin", b"old")

    class Boom(Exception):
        pass

    def failing_replace(src, dst):
        raise Boom()

    monkeypatch.setattr("voxe_service.storage.os.replace", failing_replace)
    with pytest.raises(Boom):
        store.put_bytes("a/b.bin", b"new")
    monkeypatch.undo()
    assert b"".join(store.open_range("a/b.bin")) == b"old"
    assert sorted(p.name for p in (tmp_path / "store" / "a").iterdir()) == ["b.bin"]


def test_api_stores_uploads_in_s3(tmp_path, monkeypatch, aws_env, s3_endpoint):
    """The API with VOXE_STORAGE_BACKEND=s3: an upload lands in the bucket, nothing on the local disk."""
    from fastapi.testclient import TestClient

    from needs import require_data
    from service_helpers import MIC, reset_service_caches, service_env, small_mic, zip_folder
    from voxe_service import storage as storage_module

    require_data(MIC)
    env = service_env(tmp_path, VOXE_STORAGE_BACKEND="s3", VOXE_S3_BUCKET="voxe-api", VOXE_S3_ENDPOINT_URL=s3_endpoint,
                      VOXE_S3_REGION="us-east-1")
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    try:
        from api.main import create_app

        archive = zip_folder(small_mic(tmp_path / "mic", frames=2), tmp_path / "mic.zip")
        with TestClient(create_app()) as client:
            with open(archive, "rb") as handle:
                response = client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")})
            assert response.status_code == 201, response.text
            scene = response.json()
            s3 = storage_module.get_storage()
            assert isinstance(s3, S3Storage)
            assert s3.list("scenes/") == [f"scenes/{scene['id']}/dataset.zip"]
            assert hashlib.sha256(b"".join(s3.open_range(f"scenes/{scene['id']}/dataset.zip"))).hexdigest() \
                == scene["sha256"]
            assert client.get("/readyz").json()["checks"]["storage"]["ok"]
            assert client.delete(f"/v1/scenes/{scene['id']}").status_code == 204
            assert s3.list("scenes/") == []
        assert not (tmp_path / "storage").exists()
    finally:
        reset_service_caches()
