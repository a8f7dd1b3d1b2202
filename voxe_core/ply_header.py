"""A PLY's header, read without its body and without torch or trimesh (the API's upload checks and the client's
upload both read it): the texture coordinates it declares and the texture its ``comment TextureFile`` names; and, for
the mesh loader, what in its header or body trimesh would fail on, or misread, said in words of PLY's (``ply_fault``).

Examples:
    >>> import tempfile
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "quad.ply"
    >>> _ = path.write_bytes(b"ply\\nformat binary_little_endian 1.0\\ncomment TextureFile quad.png\\n"
    ...                      b"element vertex 4\\nproperty float x\\nproperty float s\\nproperty float t\\nend_header\\n")
    >>> read_ply_header(path)
    PlyHeader(complete=True, declares_texture_coordinates=True, texture_file='quad.png', faces=None)
"""

from __future__ import annotations

import codecs
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO

TEXTURE_COORDINATES = ({("face", "texcoord")}, {("vertex", "texture_u"), ("vertex", "texture_v")},
                       {("vertex", "u"), ("vertex", "v")}, {("vertex", "s"), ("vertex", "t")})
"""The (element, property) sets a PLY's texture coordinates are read from (trimesh's names: per corner, or per
vertex)."""
HEADER_LINES, HEADER_LINE_BYTES = 10_000, 1024  # far past any real header (a few dozen short lines)
BODY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
PROPERTY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4", "float": "f4",
                  "double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2", "int32": "i4",
                  "uint32": "u4", "int64": "i8", "uint64": "u8", "float16": "f2", "float32": "f4", "float64": "f8"}
"""The property types trimesh's PLY reader knows, and their numpy types."""
UTF8_BOM = b"\xef\xbb\xbf"
TEXT_NUMBER_BYTES = b"0123456789+-.eE \t\r\n"  # what a body of numbers written as text is made of


@dataclass(frozen=True)
class PlyHeader:
    complete: bool  # a "ply" first line and an end_header within the bounds: otherwise the loader names the fault
    declares_texture_coordinates: bool
    texture_file: str | None  # the rest of its "comment TextureFile" line, as trimesh reads it
    faces: int | None  # the count its "element face" line declares (None: no such line, or not a count)


def _header_lines(handle: BinaryIO) -> Iterator[bytes]:
    """The lines of the header of the PLY open in ``handle`` after its "ply" line (none without one; in capitals, or
    after a UTF-8 byte order mark, trimesh reads it too), as read, the handle left past the last one read; their
    count and bytes are bounded: a damaged file may hold no newline (a longer line comes in pieces)."""
    if handle.readline(HEADER_LINE_BYTES).removeprefix(UTF8_BOM).strip().lower() == b"ply":
        for _ in range(HEADER_LINES):
            if not (line := handle.readline(HEADER_LINE_BYTES)):  # the end of the file
                return
            yield line


def _count(word: str) -> int | None:
    """``word`` as an element's count, or None: ASCII digits only ("²" is a digit to ``str.isdigit`` that ``int``
    refuses: an upload's check had raised a ValueError, a 500)."""
    return int(word) if word.isascii() and word.isdigit() else None


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """The header of the PLY at ``path`` (ASCII before ``end_header``, whatever the body's format)."""
    declared, element, texture_file, faces = set(), None, None, None
    with open(path, "rb") as handle:
        for line in _header_lines(handle):
            text = line.decode("utf-8", "replace").strip()
            words = text.split()
            if words[:1] == ["end_header"]:
                return PlyHeader(True, any(names <= declared for names in TEXTURE_COORDINATES), texture_file, faces)
            if words[:1] == ["element"] and len(words) > 1:
                element = words[1]
                if element == "face" and len(words) > 2 and (count := _count(words[2])) is not None:
                    faces = count
            elif words[:1] == ["property"] and len(words) > 1:
                declared.add((element, words[-1]))
            elif "texturefile" in text.lower():
                texture_file = text[text.lower().index("texturefile") + len("texturefile"):].strip() or None
    return PlyHeader(False, False, texture_file, faces)


def ply_fault(path: str | os.PathLike, read_body: bool = True) -> str | None:
    """What in the PLY at ``path`` the mesh loader (trimesh) would fail on in words of its own, or misread without a
    word, said for a user (the file not named), or None: a header line not of PLY's forms, and an ASCII body whose
    rows do not hold what the header declares (``_ascii_body_fault``) or a binary one that is text. trimesh had
    said "list index out of range" (no end_header), "'utf-8' codec can't decode byte 0xe9" (a header line not UTF-8,
    a Latin-1 comment's 'é'), "'z'" (vertices without a z), "cannot access local variable 'faces'" (faces whose
    corners are not vertex_indices), "'flot'" (a type it does not know), "not enough values to unpack" (a list
    property without its two types), "'(' was never closed" (a binary list's length of a float type, even a whole
    one), "data type '' not understood" (a binary PLY's element without properties, where this check had failed on a
    division by zero), "string or file could not be read to its end" (a word in a row), "PLY is unexpected length!"
    (a text body under a binary format line, or a binary body not the length its header makes:
    ``_binary_body_fault``), and had dropped a face row holding fewer indices than its count; it keeps one element
    of a name declared twice (of two face elements, an ASCII body's first rows read as the last one's count, the
    rest dropped; a binary body "PLY is unexpected length!"), whose count an upload's face limit had taken from the
    last alone; it ends the header at a line holding the word end_header among others (a comment), its later lines
    read as the body (a file that failed, or one ending there, which this check had said had no end_header). Without
    ``read_body``, the header's faults only."""
    elements: list[tuple[str, int, list[list[str]]]] = []  # (name, count, per property its types: a list's two)
    declared = set()  # (element, property) names
    body_format, lines_read = None, 1
    with open(path, "rb") as handle:
        utf8 = codecs.getincrementaldecoder("utf-8")()  # (a character may span the pieces of a long line)
        for line in _header_lines(handle):
            lines_read += 1
            try:  # trimesh decodes the header strictly: it had failed "'utf-8' codec can't decode byte 0xe9 ..."
                text = utf8.decode(line).strip()
            except UnicodeDecodeError:
                return (f"its header's line {lines_read}, {line.decode('utf-8', 'replace').strip()[:60]!r}, is not "
                        "UTF-8 text, as the loader reads a PLY's header (a comment saved in another encoding?): save "
                        "it as UTF-8, or without that line")
            words = text.split()
            if lines_read == 2:  # trimesh takes the second line as the format line, whatever it says
                body_format = words[1].lower() if words[:1] == ["format"] and len(words) > 1 else None
                if body_format not in BODY_FORMATS:
                    return (f"its format line is {text[:60]!r}, not 'format' and one of {', '.join(BODY_FORMATS)} "
                            "(then the version, 1.0)")
            elif not words:  # trimesh had failed on it: "list index out of range"
                return f"its header's line {lines_read} is empty, which the loader cannot read: remove it"
            elif "end_header" in words[1:]:  # trimesh ends the header at it: the lines after it were read as the body
                return (f"its header's line {lines_read}, {text[:60]!r}, holds the word end_header, at which the loader "
                        "ends the header: reword or remove that line (the header's end is a line of end_header alone)")
            elif "element" in words[0]:  # as trimesh reads them ("elements 3" had failed "not enough values to unpack")
                if len(words) != 3 or (count := _count(words[2])) is None:
                    return f"its header's line {lines_read}, {text[:60]!r}, is not 'element <name> <count>'"
                if any(name == words[1] for name, _, _ in elements):  # trimesh keeps one, of the last count
                    return (f"its header's line {lines_read}, {text[:60]!r}, declares a second {words[1][:20]!r} "
                            "element: the loader keeps one, of the last one's count (the other rows misread or "
                            f"dropped); write one {words[1][:20]!r} element holding them all")
                elements.append((words[1], count, []))
            elif "property" in words[0]:  # (its vertices' x, y, z and faces' corners as trimesh finds them)
                if not elements:
                    return f"its header's line {lines_read}, {text[:60]!r}, is a property before any element"
                is_list = words[1:2] == ["list"]
                if len(words) != (5 if is_list else 3):
                    return (f"its header's line {lines_read}, {text[:60]!r}, is not 'property <type> <name>' nor "
                            "'property list <count type> <type> <name>'")
                if unknown := [word for word in words[1 + is_list:-1] if word not in PROPERTY_TYPES]:
                    return (f"its header's line {lines_read}, {text[:60]!r}: {unknown[0][:20]!r} is not a property "
                            "type (char, uchar, short, ushort, int, uint, float, double, or a sized one: int32 ...)")
                if is_list and body_format != "ascii" and PROPERTY_TYPES[words[2]][0] not in "iu":
                    return (f"its header's line {lines_read}, {text[:60]!r}: a binary list's length is of "
                            f"{words[2]!r}, not an integer type (uchar, ushort, uint, or a sized one: uint8 ...)")
                elements[-1][2].append(words[1 + is_list:-1])
                declared.add((elements[-1][0], words[-1]))
            elif words[:1] == ["end_header"]:
                if body_format != "ascii" and (bare := next((name for name, _, types in elements if not types), None)):
                    return (f"its header's element {bare[:20]!r} has no properties, which the loader cannot read in a "
                            "binary PLY: leave it out, or save the PLY as ASCII")
                vertices = any(name == "vertex" and count for name, count, _ in elements)
                if vertices and (missing := [axis for axis in "xyz" if ("vertex", axis) not in declared]):
                    return (f"its vertex element has no {' or '.join(missing)} property: the loader reads each "
                            "vertex's position from its x, y and z")
                faces = next((types for name, count, types in elements if name == "face" and count), None)
                if (faces is not None and not {("face", "vertex_indices"), ("face", "vertex_index")} & declared
                        and (body_format == "ascii" or len(faces) > 1)):  # (a binary face's one property: any name)
                    return ("its face element has no vertex_indices property (nor vertex_index): the loader reads each "
                            "face's corners from it")
                if not read_body:  # the header's lines only (an upload's check: the body may be GBs)
                    return None
                body = handle.read()
                if body_format == "ascii":
                    return _ascii_body_fault(body, elements, lines_read)
                if body and not body.strip(TEXT_NUMBER_BYTES):
                    return (f"its format line says {body_format}, but its body is text: an ASCII PLY's format line "
                            "is 'format ascii 1.0'")
                return _binary_body_fault(body, elements, "<" if body_format == "binary_little_endian" else ">")
    if lines_read == 1:
        return "its first line is not 'ply': it is not a PLY file"
    return "its header has no end_header line: it is truncated, or not a PLY file"


def _ascii_body_fault(body: bytes, elements: list, header_lines: int) -> str | None:
    """What in an ASCII body the rows of ``elements`` (read one a line, as trimesh reads them) hold other than
    their header declares: too few rows (trimesh takes the lines there are: a truncated file, or a header
    overstating a count, had loaded as part of its mesh), a row short of its properties' values (a face of
    two indices under a count of 3: trimesh had dropped it), or a word that is not a number, in the rows or after
    them."""
    try:
        rows = body.decode("utf-8").splitlines()  # as trimesh decodes and splits them
    except UnicodeDecodeError:
        rows = None
    if rows is None or b"\0" in body:
        return ("its format line says ascii, but its body is not text: a binary body's format line is "
                "'format binary_little_endian 1.0' (or binary_big_endian)")
    first = 0
    for name, count, lists in elements:
        if len(rows) - first < count:
            return (f"its header declares {count} {name} elements, the file holds {len(rows) - first}: it is "
                    "truncated, or its header overstates a count")
        block, line = rows[first:first + count], header_lines + first + 1  # the file's line of the block's first row
        for index, row in enumerate(block):
            words, needed = row.split(), 0
            for types in lists:
                if len(types) == 2 and needed < len(words):
                    length = _number(words[needed])
                    if length is None or not (length >= 0 and length.is_integer()):
                        return (f"line {line + index} ({name} {index + 1}): a list's length, "
                                f"{words[needed][:20]!r}, is not a count")
                    if length > len(words):  # a damaged length, not a short row (1e300 had been told in 301 digits)
                        return (f"line {line + index} ({name} {index + 1}): a list's length, "
                                f"{words[needed][:20]!r}, runs past its row of {len(words)} values")
                    needed += int(length)
                needed += 1
            if len(words) < needed:
                return (f"line {line + index} ({name} {index + 1}), {row.strip()[:40]!r}, holds {len(words)} values "
                        f"where its header's properties (and the lengths of its lists) make {needed}")
        if not is_numbers(" ".join(block)):  # every word at once; a word at a time only to name the one that is not
            for index, row in enumerate(block):
                if word := next((word for word in row.split() if not is_numbers(word)), None):
                    return f"line {line + index} ({name} {index + 1}): {word[:20]!r} is not a number"
        first += count
    rest = rows[first:]  # trimesh reads them too: a word there had failed it, "could not be read to its end"
    if not is_numbers(" ".join(rest)):
        for index, row in enumerate(rest):
            if word := next((word for word in row.split() if not is_numbers(word)), None):
                return (f"line {header_lines + first + index + 1}, after the rows its header declares: {word[:20]!r} "
                        "is not a number")
    return None


def _binary_body_fault(body: bytes, elements: list, endian: str) -> str | None:
    """What in a binary body the rows of ``elements`` hold other than trimesh reads: it takes each list's length from
    its element's first row for every row, and refuses a body not the length that makes ("PLY is unexpected
    length!"; a mix of triangles and quads, a truncated file, a count overstated or understated)."""
    import numpy as np  # (as in ``is_numbers``)

    start = 0
    for name, count, properties in elements:
        fields, lengths = [], {}
        for index, types in enumerate(properties):
            fields.append((f"{index}", endian + PROPERTY_TYPES[types[0]]))
            if len(types) == 2 and count:  # a list: its length, then as many items as the first row's
                offset = start + np.dtype(fields).itemsize - np.dtype(fields[-1][1]).itemsize
                first = np.frombuffer(body[offset:offset + np.dtype(fields[-1][1]).itemsize], dtype=fields[-1][1])
                if not len(first):
                    break  # the body ends there
                items_left = (len(body) - offset - first.itemsize) // np.dtype(PROPERTY_TYPES[types[1]]).itemsize
                if fault := _list_length_fault(first[0].item(), items_left, name):
                    return fault
                lengths[f"{index}"] = int(first[0])
                fields.append((f"{index} items", endian + PROPERTY_TYPES[types[1]], (lengths[f"{index}"],)))
        row = np.dtype(fields)
        rows = np.frombuffer(body, dtype=row, count=min(count, max(0, len(body) - start) // row.itemsize), offset=start)
        for field, length in lengths.items():
            if len(odd := np.flatnonzero(rows[field] != length)):
                return (f"its {name} element {odd[0] + 1} holds a list of {rows[field][odd[0]]} where the first holds "
                        f"{length}: the loader reads a binary PLY's lists all as long as the first (save it as ASCII, "
                        "or its faces all of one size)")
        if len(rows) < count:
            return (f"its body ends within its {name} element {len(rows) + 1}, of the {count} its header declares: "
                    "it is truncated, or its header overstates a count")
        start += count * row.itemsize
    if len(body) > start:
        return (f"its body holds {len(body) - start} bytes past its elements' last ({elements[-1][0]} "
                f"{elements[-1][1]}): its header understates a count, or something was appended")
    return None


def _list_length_fault(length: int, items_left: int, name: str) -> str | None:
    """What is wrong with the length ``length`` (of an integer type: ``ply_fault`` refuses others) of a list in a
    binary body's first ``name`` element, with room for ``items_left`` items after it, or None. A negative length (a
    signed count type) or one past the end of the body had failed numpy's reading of the rows in words of its own
    ("invalid shape in fixed-type tuple: dimension smaller then zero"), not a ``MeshError``."""
    if length < 0:
        return f"its {name} element 1: a list's length, {length}, is not a count"
    if length > items_left:
        return (f"its {name} element 1: a list's length, {length}, runs past the end of its body (room for "
                f"{items_left} items): it is truncated, or that length is damaged")
    return None


def _number(word: str) -> float | None:
    """A list's length, ``word``, as a number, or None (every word's reading as trimesh's: ``is_numbers``)."""
    try:
        return float(word)
    except ValueError:
        return None


def is_numbers(text: str) -> bool:
    """Whether ``text`` is numbers apart, as numpy's text parsing (trimesh's) reads them."""
    import numpy as np  # here: the client and the API read headers only, and ``voxe status`` need not load numpy

    try:
        np.fromstring(text, sep=" ")
    except ValueError:
        return False
    return True
