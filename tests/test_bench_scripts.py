"""Every bench script still imports and parses its options: `--help` through its own `__main__` block exits 0 and
prints its usage (a script whose imports or argparse setup broke fails here, not on the day it is needed)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
# blender_render.py runs inside Blender (`blender --python`), where bpy exists; it has no command line of its own.
SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if p.name != "blender_render.py")


def test_every_bench_script_is_listed():
    assert len(SCRIPTS) >= 20 and "gpu.py" in SCRIPTS and "report.py" in SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS)
def test_bench_script_help(script, monkeypatch, capsys):
    monkeypatch.setattr(sys, "path", [str(BENCH), *sys.path])  # as `python bench/<script>` puts it first
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), "--help"])
    with pytest.raises(SystemExit) as exited:
        runpy.run_path(str(BENCH / script), run_name="__main__")
    assert exited.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: {script} ")
