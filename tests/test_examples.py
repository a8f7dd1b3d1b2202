"""The ``Examples:`` blocks of the docstrings run and print what they say (doctest)."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = ["voxe_core.grid", "voxe_core.gridfile", "voxe_core.volrend", "voxe_core.render", "voxe_core.backbones",
           "voxe_core.presets", "voxe_core.progress", "voxe_core.guidance.loading", "voxe_core.export",
           "voxe_core.cameras", "voxe_core.mesh_input", "voxe_client.client",
           "voxe_service.model_inventory", "voxe_service.progress", "voxe_service.webhooks"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_hold(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"
