"""A PLY's header, read without its body and without torch or trimesh (the API's upload checks and the client's
upload both read it): the texture coordinates it declares and the texture its ``comment TextureFile`` names.

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
from dataclasses import dataclass

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


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """The header of the PLY at ``path`` (ASCII before ``end_header``, whatever the body's format); its lines and
    their bytes are bounded: a damaged file may hold no newline."""
    declared, element, texture_file = set(), None, None
    with open(path, "rb") as handle:
        if handle.readline(HEADER_LINE_BYTES).strip() == b"ply":
            for _ in range(HEADER_LINES):
                text = handle.readline(HEADER_LINE_BYTES).decode("utf-8", "replace").strip()
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
