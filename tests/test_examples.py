"""The ``Examples:`` blocks of the docstrings run and print what they say (doctest).

Every module of the library, the client, the service core, the API and the worker that has examples is found, so a new
example cannot go untested.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

PACKAGES = ("voxe_core", "voxe_client", "voxe_service", "api", "worker")


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
