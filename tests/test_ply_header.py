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


@pytest.mark.parametrize("read_body", [True, False])
@pytest.mark.parametrize("fmt, body", [("ascii", b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"), ("binary_little_endian", _BODY)])
def test_a_header_line_that_is_not_utf8_is_a_fault_naming_its_line(tmp_path, fmt, body, read_body):
    """Regression: a comment saved in Latin-1 ('Créé par le scanner') passed the check, header and body, and the
    loader failed as "cannot read as a mesh: 'utf-8' codec can't decode byte 0xe9 in position 10: invalid
    continuation byte" (no line; an upload's check had let it through to the ingest). In UTF-8 it loads."""
    header = f"ply\nformat {fmt} 1.0\ncomment Créé par le scanner\n{_VERTICES}{_FACES}end_header\n"
    path = tmp_path / "latin.ply"
    path.write_bytes(header.encode("latin-1") + body)
    assert ply_fault(path, read_body) == (
        "its header's line 3, 'comment Cr\ufffd\ufffd par le scanner', is not UTF-8 text, as the loader reads a PLY's "
        "header (a comment saved in another encoding?): save it as UTF-8, or without that line")
    path.write_bytes(header.encode() + body)
    assert ply_fault(path, read_body) is None


def test_a_long_utf8_header_line_read_in_pieces_is_no_fault(tmp_path):
    """A comment longer than the bytes a header line is read in comes in pieces, which may split a character."""
    path = tmp_path / "long.ply"
    for prefix in ("comment ", "comment x"):  # the cut within an 'é' or between two
        path.write_bytes(f"ply\nformat ascii 1.0\n{prefix}{'é' * 1500}\n{_VERTICES}{_FACES}end_header\n"
                         "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n".encode())
        assert ply_fault(path) is None


@pytest.mark.parametrize("read_body", [True, False])
@pytest.mark.parametrize("properties, missing", [("xy", "z"), ("yzw", "x"), ("y", "x or z")])
def test_vertices_without_a_coordinate_are_a_fault_naming_it(tmp_path, properties, missing, read_body):
    """Regression: the loader had said "cannot read as a mesh: 'z'" (trimesh's KeyError), after an upload's check let
    the file through; vertices need x, y and z (an element of no vertices needs none)."""
    path = tmp_path / "flat.ply"
    vertices = "element vertex 3\n" + "".join(f"property float {name}\n" for name in properties)
    rows = "".join(" ".join(["0"] * len(properties)) + "\n" for _ in range(3))
    path.write_text(f"ply\nformat ascii 1.0\n{vertices}{_FACES}end_header\n{rows}3 0 1 2\n")
    assert ply_fault(path, read_body) == (f"its vertex element has no {missing} property: the loader reads each "
                                          "vertex's position from its x, y and z")
    path.write_text(f"ply\nformat ascii 1.0\n{vertices.replace(' 3', ' 0')}end_header\n")
    assert ply_fault(path, read_body) is None


@pytest.mark.parametrize("read_body", [True, False])
@pytest.mark.parametrize("fmt, extra, fault", [("ascii", "", True), ("ascii", "property uchar red\n", True),
                                               ("binary_little_endian", "property uchar red\n", True),
                                               ("binary_little_endian", "", False)])
def test_faces_whose_corners_are_not_vertex_indices_are_a_fault(tmp_path, fmt, extra, fault, read_body):
    """Regression: the loader had said "cannot read as a mesh: cannot access local variable 'faces' where it is not
    associated with a value" (or 'name'): trimesh reads corners from vertex_indices or vertex_index, but a binary
    face's only property whatever its name (that one loads)."""
    path = tmp_path / "corners.ply"
    header = f"ply\nformat {fmt} 1.0\n{_VERTICES}element face 1\nproperty list uchar int corners\n{extra}end_header\n"
    body = b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2" + (b" 9" if extra else b"") + b"\n" if fmt == "ascii" else \
        _BODY + (b"\x09" if extra else b"")
    path.write_bytes(header.encode() + body)
    assert ply_fault(path, read_body) == ("its face element has no vertex_indices property (nor vertex_index): the "
                                          "loader reads each face's corners from it" if fault else None)
    path.write_bytes(header.replace("corners", "vertex_index").encode() + body)
    assert ply_fault(path, read_body) is None


@pytest.mark.parametrize("tail, fault", [("comment made by me\n", "line 14, after the rows its header declares: "
                                          "'comment' is not a number"),
                                         ("\n1 2\nx\n", "line 16, after the rows its header declares: 'x' is not a "
                                          "number"),
                                         ("7 8 9\n\n", None)])
def test_words_after_an_ascii_plys_rows_are_a_fault_naming_the_line(tmp_path, tail, fault):
    """Regression: the loader had said "cannot read as a mesh: string or file could not be read to its end due to
    unmatched data" (trimesh parses the rest of the body too); numbers there it leaves alone."""
    path = tmp_path / "tail.ply"
    path.write_text(f"ply\nformat ascii 1.0\n{_VERTICES}{_FACES}end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n{tail}")
    assert ply_fault(path) == fault


@pytest.mark.parametrize("read_body", [True, False])
@pytest.mark.parametrize("header, fault_line", [
    (f"comment written before end_header\n{_VERTICES}{_FACES}end_header\n", 3),
    (f"{_VERTICES}comment no end_header yet\n{_FACES}end_header\n", 7),
    (f"{_VERTICES}{_FACES}comment end_header\nend_header\n", 9),
    (f"{_VERTICES}{_FACES}comment end_header\n", 9),  # (it loads, ending there: refused as no end_header before)
    (f"{_VERTICES}{_FACES}end_header and more\n", None),  # both end the header there
    (f"comment my_end_header\n{_VERTICES}{_FACES}end_header\n", None),  # not the word
], ids=["before the elements", "between them", "before the end", "as the end", "after end_header", "within a word"])
def test_a_header_line_holding_end_header_among_other_words_is_a_fault_naming_it(tmp_path, header, fault_line,
                                                                                 read_body):
    """trimesh ends the header at any line holding the word end_header: a comment saying it had passed the check (an
    upload's too), and the loader then read the lines after it as the body ("string or file could not be read to
    its end due to unmatched data"). A file the check passes loads."""
    import trimesh

    path = tmp_path / "comment.ply"
    path.write_text(f"ply\nformat ascii 1.0\n{header}0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    fault = ply_fault(path, read_body)
    if fault_line is None:
        assert fault is None
        assert len(trimesh.load(path, process=False).faces) == 1
    else:
        line = header.splitlines()[fault_line - 3]
        assert fault == (f"its header's line {fault_line}, {line!r}, holds the word end_header, at which the loader "
                         "ends the header: reword or remove that line (the header's end is a line of end_header alone)")


@pytest.mark.parametrize("read_body", [True, False])
@pytest.mark.parametrize("line, fault", [
    ("\n", "its header's line 3 is empty, which the loader cannot read: remove it"),  # "list index out of range"
    ("elements 2\n", "its header's line 3, 'elements 2', is not 'element <name> <count>'"),  # "not enough values ..."
    ("obj_info 2\n", None),  # (any other line: a word of its own)
])
def test_a_header_line_the_loader_misreads_is_a_fault_naming_it(tmp_path, line, fault, read_body):
    """Regression: trimesh fails on an empty header line, and reads a line whose first word holds "element" as one
    (its own words: in the comments); the check had skipped both. A first word holding "property" is one to it too:
    such a z or vertex_indices is there (the check had refused the file, which loads)."""
    path = tmp_path / "odd.ply"
    path.write_text(f"ply\nformat ascii 1.0\n{line}{_VERTICES}{_FACES}end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert ply_fault(path, read_body) == fault
    path.write_text(f"ply\nformat ascii 1.0\n{line}{_VERTICES.replace('property float z', 'propertyz float z')}"
                    f"{_FACES.replace('property list', 'property_ list')}end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert ply_fault(path, read_body) == fault


@pytest.mark.parametrize("read_body", [True, False])
@pytest.mark.parametrize("fmt, body", [("ascii", b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 2 1\n"),
                                       ("binary_little_endian", _BODY + _BODY[-13:])])
def test_an_element_declared_twice_is_a_fault_naming_it(tmp_path, fmt, body, read_body):
    """trimesh keeps one element of a name: of two face elements, an ASCII body's first rows had been read as the last
    one's count (the rest dropped without a word), a binary body failed "PLY is unexpected length!", and an upload's
    face limit had counted the last one's faces alone."""
    path = tmp_path / "twice.ply"
    path.write_bytes(f"ply\nformat {fmt} 1.0\n{_VERTICES}{_FACES}{_FACES}end_header\n".encode() + body)
    assert ply_fault(path, read_body) == ("its header's line 9, 'element face 1', declares a second 'face' element: "
                                          "the loader keeps one, of the last one's count (the other rows misread or "
                                          "dropped); write one 'face' element holding them all")
