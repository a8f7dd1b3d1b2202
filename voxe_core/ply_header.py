"""A PLY's header, read without its body and without torch or trimesh (the API's upload checks and the client's
upload both read it): the texture coordinates it declares and the texture its ``comment TextureFile`` names; and, for
the mesh loader, whether an ASCII body holds the rows its header declares.

Examples:
    >>> import tempfile
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "quad.ply"
    >>> _ = path.write_bytes(b"ply\\nformat binary_little_endian 1.0\\ncomment TextureFile quad.png\\n"
    ...                      b"element vertex 4\\nproperty float x\\nproperty float s\\nproperty float t\\nend_header\\n")
    >>> read_ply_header(path)
    PlyHeader(complete=True, declares_texture_coordinates=True, texture_file='quad.png')
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO

TEXTURE_COORDINATES = ({("face", "texcoord")}, {("vertex", "texture_u"), ("vertex", "texture_v")},
                       {("vertex", "u"), ("vertex", "v")}, {("vertex", "s"), ("vertex", "t")})
"""The (element, property) sets a PLY's texture coordinates are read from (trimesh's names: per corner, or per
vertex)."""
HEADER_LINES, HEADER_LINE_BYTES = 10_000, 1024  # far past any real header (a few dozen short lines)


@dataclass(frozen=True)
class PlyHeader:
    complete: bool  # a "ply" first line and an end_header within the bounds: otherwise the loader names the fault
    declares_texture_coordinates: bool
    texture_file: str | None  # the rest of its "comment TextureFile" line, as trimesh reads it


def _header_lines(handle: BinaryIO) -> Iterator[str]:
    """The lines of the header of the PLY open in ``handle`` after its "ply" line (none without one), each stripped,
    the handle left past the last one read; their count and bytes are bounded: a damaged file may hold no newline."""
    if handle.readline(HEADER_LINE_BYTES).strip() == b"ply":
        for _ in range(HEADER_LINES):
            yield handle.readline(HEADER_LINE_BYTES).decode("utf-8", "replace").strip()


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """The header of the PLY at ``path`` (ASCII before ``end_header``, whatever the body's format)."""
    declared, element, texture_file = set(), None, None
    with open(path, "rb") as handle:
        for text in _header_lines(handle):
            words = text.split()
            if words[:1] == ["end_header"]:
                return PlyHeader(True, any(names <= declared for names in TEXTURE_COORDINATES), texture_file)
            if words[:1] == ["element"] and len(words) > 1:
                element = words[1]
            elif words[:1] == ["property"] and len(words) > 1:
                declared.add((element, words[-1]))
            elif "texturefile" in text.lower():
                texture_file = text[text.lower().index("texturefile") + len("texturefile"):].strip() or None
    return PlyHeader(False, False, texture_file)


def short_ascii_element(path: str | os.PathLike) -> tuple[str, int, int] | None:
    """The first element of the ASCII PLY at ``path`` whose rows its body holds fewer of than its header declares:
    (name, declared, held); None when each is whole, the body is binary or the header is not one to count by (the
    loader names its fault). trimesh reads an element's rows one per line and takes the lines there are: a truncated
    file, or a header overstating a count, had loaded as part of its mesh without a word."""
    counts, ascii_body = [], False
    with open(path, "rb") as handle:
        for text in _header_lines(handle):
            words = text.split()
            if words[:1] == ["format"]:
                ascii_body = "ascii" in text.lower()  # as trimesh tells the body's format
            elif words[:1] == ["element"]:
                if len(words) != 3 or not words[2].isdigit():
                    return None
                counts.append((words[1], int(words[2])))
            elif words[:1] == ["end_header"]:
                if not ascii_body:
                    return None
                rows = len(handle.read().decode("utf-8", "replace").splitlines())  # as trimesh splits them
                for name, declared in counts:
                    if rows < declared:
                        return name, declared, rows
                    rows -= declared
                return None
    return None
