"""What a test needs from outside the repository, and what happens when it is missing.

The shared data sits beside the repository (``<repo>/../shared/data``; CI clones the same
way). A test that needs it, or a server (redis-server, PostgreSQL), skips on a developer's
machine that lacks it, but fails in CI (``CI=true``): CI never passes on what it did not run.
"""

from __future__ import annotations

import os
from pathlib import Path

# VOXE_DATA_ROOT: elsewhere, e.g. the GPU machine, where bench/gpu_device.sh carries mic inside the repository.
DATA_ROOT = Path(os.environ.get("VOXE_DATA_ROOT") or Path(__file__).resolve().parents[1].parent / "shared" / "data")
MIC = DATA_ROOT / "nerf_synthetic_mic"
FOX = DATA_ROOT / "fox"
SPOT = DATA_ROOT / "meshes" / "spot"


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def missing(reason: str):
    """Skip the test, or fail it in CI."""
    import pytest

    if in_ci():
        pytest.fail(f"{reason} (CI=true: a test never skips on a missing dependency)", pytrace=False)
    pytest.skip(reason)


def require_data(*paths: Path) -> None:
    """Skip (fail in CI) unless every path of the shared data exists."""
    absent = [p for p in paths if not p.exists()]
    if absent:
        missing(f"shared data missing: {', '.join(map(str, absent))}")


def needs_data(*paths: Path):
    """A mark for tests that read the shared data: conftest's setup hook calls :func:`require_data`."""
    import pytest

    return pytest.mark.needs_data(*paths)


def require_triton_interpreter() -> None:
    """Skip (fail in CI) unless Triton is installed and runs in its interpreter here: tests/conftest.py turns it on
    where there is no CUDA (the fused marcher's kernels then run on the CPU tensors the tests build)."""
    import importlib.util

    if importlib.util.find_spec("triton") is None:
        missing("Triton is not installed (the dev extra installs it on Linux x86-64)")
    if os.environ.get("TRITON_INTERPRET") != "1":
        missing("Triton's interpreter is off (tests/conftest.py turns it on only without CUDA)")
