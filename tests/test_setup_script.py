"""``.ci/setup``, which the README's two commands run first: a second run for the same project skips the install; and
those two commands are the ones CI runs."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_setup_installs_once_for_the_same_project_and_torch(tmp_path):
    """``bash .ci/serve`` ran the whole install (pip, torch, the project) at every start, needing a package index
    each time; now only when this script, pyproject.toml or the torch wheel asked for changed since the last one."""
    (tmp_path / ".ci").mkdir()
    shutil.copy(REPO / ".ci" / "setup", tmp_path / ".ci" / "setup")
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    python = tmp_path / ".venv" / "bin" / "python"  # records what it is asked to run
    python.parent.mkdir(parents=True)
    python.write_text('#!/usr/bin/env bash\necho "$*" >> "$(dirname "$0")/../calls"\n')
    python.chmod(0o755)
    calls = tmp_path / ".venv" / "calls"

    def setup(**env) -> list[str]:
        calls.unlink(missing_ok=True)
        result = subprocess.run(["bash", ".ci/setup"], cwd=tmp_path, capture_output=True, text=True, timeout=60,
                                env={**os.environ, "TORCH_SPEC": "torch==2.13.0", **env})
        assert result.returncode == 0, result.stderr
        return calls.read_text().splitlines() if calls.exists() else []

    installs = ["-m pip install -q --upgrade pip", "-m pip install -q torch==2.13.0", "-m pip install -q -e .[dev]"]
    assert setup() == installs
    assert setup() == []  # the same project and torch: nothing to install
    assert setup(TORCH_SPEC="torch") == [*installs[:1], "-m pip install -q torch", installs[2]]
    with open(tmp_path / "pyproject.toml", "a") as project:
        project.write("\n# a dependency changed\n")
    assert setup(TORCH_SPEC="torch") == [*installs[:1], "-m pip install -q torch", installs[2]]
    moved = tmp_path.parent / f"{tmp_path.name}-moved"  # the checkout moved: its editable install points elsewhere
    tmp_path.rename(moved)
    try:
        (moved / ".venv" / "calls").unlink()
        assert subprocess.run(["bash", ".ci/setup"], cwd=moved, capture_output=True, text=True, timeout=60,
                              env={**os.environ, "TORCH_SPEC": "torch"}).returncode == 0
        assert (moved / ".venv" / "calls").read_text().splitlines() == [*installs[:1], "-m pip install -q torch",
                                                                        installs[2]]
    finally:
        moved.rename(tmp_path)
    python.write_text('#!/usr/bin/env bash\necho "$*" >> "$(dirname "$0")/../calls"\nexit 1\n')  # an install fails
    with open(tmp_path / "pyproject.toml", "a") as project:
        project.write("# again\n")
    failed = subprocess.run(["bash", ".ci/setup"], cwd=tmp_path, capture_output=True, text=True, timeout=60,
                            env={**os.environ, "TORCH_SPEC": "torch"})
    assert failed.returncode != 0 and not (tmp_path / ".venv" / ".voxe-setup").exists()  # tried again next time


def test_the_readmes_two_commands_are_the_ones_ci_runs():
    """The README's fresh-machine section runs the service with ``bash .ci/serve`` and the tests with ``bash .ci/test``,
    CI's entry point (``.ci/run``) runs exactly the latter, and both set up with ``.ci/setup``."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("\n## Two commands for a fresh machine\n", 1)[1].split("\n## ", 1)[0]
    assert re.findall(r"^    (bash \S+)$", section, re.M) == ["bash .ci/serve", "bash .ci/test"]
    assert re.search(r"^exec bash \.ci/test$", (REPO / ".ci" / "run").read_text(), re.M)
    for script in ("serve", "test"):
        assert re.search(r"^[^#\n]*\bbash \.ci/setup\b", (REPO / ".ci" / script).read_text(), re.M), script


def test_serve_says_the_apis_url_for_every_loopback_host(tmp_path):
    """``bash .ci/serve`` prints where the API listens; for an IPv6 ``VOXE_HOST`` (``::1``, which the settings take as
    loopback) it had printed ``http://::1:8000``, a URL no browser or curl opens: now ``http://[::1]:8000``."""
    (tmp_path / ".ci").mkdir()
    shutil.copy(REPO / ".ci" / "serve", tmp_path / ".ci" / "serve")
    python = tmp_path / "python"  # does nothing: the migration passes, the API and the worker end at once
    python.write_text("#!/usr/bin/env bash\n")
    python.chmod(0o755)

    def serve(**env) -> str:
        result = subprocess.run(["bash", ".ci/serve"], cwd=tmp_path, capture_output=True, text=True, timeout=60,
                                env={**os.environ, "VOXE_PYTHON": str(python), **env})
        assert result.returncode == 0, result.stderr
        return result.stderr

    assert "voxe: API on http://127.0.0.1:8000 (docs: http://127.0.0.1:8000/docs)" in serve()
    assert "voxe: API on http://[::1]:8123 (docs: http://[::1]:8123/docs)" in serve(VOXE_HOST="::1", VOXE_PORT="8123")
    assert "voxe: API on http://localhost:8000 " in serve(VOXE_HOST="localhost")


def test_serve_on_all_interfaces_says_a_url_a_browser_opens(tmp_path):
    """With ``VOXE_HOST=0.0.0.0`` (or ``::``) ``bash .ci/serve`` had printed ``http://0.0.0.0:8000``, which browsers
    refuse to open: it now prints this machine's ``localhost`` URL and says the API listens on every interface."""
    (tmp_path / ".ci").mkdir()
    shutil.copy(REPO / ".ci" / "serve", tmp_path / ".ci" / "serve")
    python = tmp_path / "python"  # does nothing: the migration passes, the API and the worker end at once
    python.write_text("#!/usr/bin/env bash\n")
    python.chmod(0o755)
    for host in ("0.0.0.0", "::"):
        result = subprocess.run(["bash", ".ci/serve"], cwd=tmp_path, capture_output=True, text=True, timeout=60,
                                env={**os.environ, "VOXE_PYTHON": str(python), "VOXE_HOST": host, "VOXE_PORT": "8123"})
        assert result.returncode == 0, result.stderr
        assert (f"voxe: API on http://localhost:8123 (docs: http://localhost:8123/docs), listening on all interfaces "
                f"({host}), worker ") in result.stderr
        assert "0.0.0.0:" not in result.stderr and "[::]" not in result.stderr
