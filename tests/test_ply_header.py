"""ply_header's reading of PLY headers and bodies (its faults in the mesh loader's words: tests/test_mesh_input.py)."""

from __future__ import annotations

import numpy as np
import pytest

from voxe_core.ply_header import ply_fault

_VERTICES = "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
_FACES = "element face 1\nproperty list uchar int vertex_indices\n"
_BODY = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "<f4").tobytes() + b"\x03" + np.array([0, 1, 2], "<i4").tobytes()


@pytest.mark.parametrize("read_body", [True, False])
@pytest.mark.parametrize("elements, name", [(_VERTICES + _FACES + "element extra 2\n", "extra"),
                                            (_VERTICES + _FACES + "element extra 0\n", "extra"),
                                            ("element vertex 3\n" + _FACES, "vertex")],
                         ids=["a 2-row element", "a 0-row element", "the vertices"])
def test_a_binary_plys_element_without_properties_is_a_fault_naming_it(tmp_path, elements, name, read_body):
    """Regression: the body's check divided by the element's row size, 0 (ZeroDivisionError out of load_mesh, not a
    MeshError); trimesh fails on such an element ("data type '' not understood"), so an upload's header check says so
    too."""
    path = tmp_path / "bare.ply"
    path.write_bytes(f"ply\nformat binary_little_endian 1.0\n{elements}end_header\n".encode() + _BODY)
    assert ply_fault(path, read_body) == (f"its header's element '{name}' has no properties, which the loader cannot "
                                          "read in a binary PLY: leave it out, or save the PLY as ASCII")


def test_an_ascii_plys_element_without_properties_is_no_fault(tmp_path):
    """An ASCII body's rows of no values are empty lines, which trimesh reads."""
    path = tmp_path / "bare.ply"
    path.write_text(f"ply\nformat ascii 1.0\n{_VERTICES}{_FACES}element extra 2\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n\n\n")
    assert ply_fault(path) is None
