"""The ``Examples:`` blocks of the docstrings run and print what they say (doctest), and the names the README gives
exist.

Every module of the library, the client, the service core, the API and the worker that has examples is found, so a new
example cannot go untested.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil
import re
from pathlib import Path

import pytest

PACKAGES = ("voxe_core", "voxe_client", "voxe_service", "api", "worker")
REPO = Path(__file__).resolve().parents[1]


def modules_with_examples() -> list[str]:
    names = []
    for package in PACKAGES:
        root = importlib.import_module(package)
        for info in pkgutil.walk_packages(root.__path__, package + "."):
            if info.name.endswith(".__main__") or ".migrations" in info.name:  # runs the CLI / alembic's scripts
                continue
            try:
                module = importlib.import_module(info.name)
            except ModuleNotFoundError as exc:
                if exc.name == "triton":  # voxe_core.fused_render: Triton's wheels are Linux's (the dev extra's)
                    continue
                raise
            tests = doctest.DocTestFinder().find(module)
            if any(test.examples for test in tests):
                names.append(info.name)
    return names


MODULES = modules_with_examples()


def test_the_documented_modules_are_found():
    assert {"voxe_core.render", "voxe_core.refine.cut", "voxe_client.client", "voxe_service.webhooks",
            "api.http_semantics"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_hold(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"


def names_something(dotted: str) -> bool:
    """Whether ``dotted`` is a module, or an attribute (a dataclass's or pydantic model's field included) of one."""
    parts = dotted.split(".")
    for known in range(len(parts), 0, -1):
        try:
            found = importlib.import_module(".".join(parts[:known]))
        except ModuleNotFoundError as exc:
            if exc.name == "triton":  # voxe_core.fused_render: Triton's wheels are Linux's (the dev extra's)
                pytest.skip("Triton is not installed")
            continue
        for part in parts[known:]:
            fields = getattr(found, "__dataclass_fields__", None) or getattr(found, "model_fields", None) or {}
            if not hasattr(found, part) and part not in fields:
                return False
            found = getattr(found, part, None)
        return True
    return False


def test_the_names_the_readme_gives_exist():
    """Every voxe_core / voxe_service / voxe_client / api / worker name the README writes out whole (a module, a
    function, a class, its attribute or field) is one, so a rename cannot leave the README pointing at nothing."""
    text = (REPO / "README.md").read_text()
    names = set(re.findall(r"(?<![\w./-])((?:voxe_core|voxe_service|voxe_client|api|worker)(?:\.[A-Za-z_]\w*)+)", text))
    assert names
    assert not [name for name in sorted(names) if not names_something(name)]
