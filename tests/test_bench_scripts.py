"""Every bench script still imports and parses its options: `--help` through its own `__main__` block exits 0 and
prints its usage (a script whose imports or argparse setup broke fails here, not on the day it is needed), and it takes
every option the READMEs run it with."""

from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "bench"
# blender_render.py runs inside Blender (`blender --python`), where bpy exists; it has no command line of its own.
SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if p.name != "blender_render.py")


def test_every_bench_script_is_listed():
    assert len(SCRIPTS) >= 20 and "gpu.py" in SCRIPTS and "report.py" in SCRIPTS


OPTION = r"(?<![\w-])--[a-z][a-z0-9-]*"


def options_written(script: str) -> set[str]:
    """The options the READMEs run ``script`` with: ``python bench/<script> ...`` anywhere, and the rerun column of
    its row in bench/README.md's table of scripts."""
    written = set()
    for readme in ("README.md", "bench/README.md"):
        for line in (REPO / readme).read_text().splitlines():
            for command in re.findall(rf"python (?:\.\./)?bench/{re.escape(script)}([^`\n|]*)", line):
                written |= set(re.findall(OPTION, command))
            if readme == "bench/README.md" and line.startswith(f"| `{script}` |"):
                written |= set(re.findall(OPTION, line.rsplit("|", 2)[-2]))
    return written


@pytest.mark.parametrize("script", SCRIPTS)
def test_bench_script_help(script, monkeypatch, capsys):
    monkeypatch.setattr(sys, "path", [str(BENCH), *sys.path])  # as `python bench/<script>` puts it first
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), "--help"])
    with pytest.raises(SystemExit) as exited:
        runpy.run_path(str(BENCH / script), run_name="__main__")
    assert exited.value.code == 0
    usage = capsys.readouterr().out
    assert usage.startswith(f"usage: {script} ")
    unknown = options_written(script) - set(re.findall(OPTION, usage))
    assert not unknown, f"the READMEs run {script} with {sorted(unknown)}, which it does not take"
