"""Meshes as input: an OBJ or a PLY, coloured by a texture image, materials or vertex colours, instead of posed
photos.

Two routes into G_i:

* (a) ``render_mesh_views``: render posed upper-hemisphere views (the paper
  rendered 100 in Blender) with a vectorised z-buffer rasteriser, then
  reconstruct as usual. Colour is the unlit albedo (texture or vertex colour):
  the grid has no view dependence, so shading would only be baked in.

A mesh without any colour would come out one flat grey, a silhouette with no shape
cue for the diffusion model. ``shade_mesh`` bakes a fixed shading into its colour
for both routes (``mesh_shading``: "auto" bakes it only for such meshes, "baked"
always, "none" never): per vertex, ambient occlusion times (``SHADING_AMBIENT`` +
(1 − ``SHADING_AMBIENT``)·max(0, n·l)) with l the key light ``SHADING_LIGHT`` (above,
in front and to the left in the canonical frame, z up). Occlusion is the fraction
of ``SHADING_AO_RAYS`` cosine-weighted rays from the vertex that leave the mesh's
filled occupancy (``SHADING_AO_RESOLUTION``³ over its box) within ``SHADING_AO_REACH``
(in canonical units, the mesh's largest half-extent being at most 1) without entering it.
* (b) ``voxelize``: write the mesh straight into the grid's vertices. Density
  is a ramp in the signed distance to the surface (zero level on the surface,
  opaque a voxel inside), so trilinear interpolation puts the rendered
  surface within a fraction of a voxel of the mesh; colour is the albedo at
  the nearest surface point.

``load_mesh`` normalises every mesh the same way: the up axis onto +z, the
bounding box centred on the origin, the largest half-extent scaled to
``extent`` (1.0 sits well inside the 3-unit box), or less where a point of the
mesh would then lie farther than ``VIEW_RADIUS`` from the centre, outside some
NeRF-synthetic camera's view (a box's corners, at √3). ``chamfer_distance``
closes the loop with ``export.extract_mesh``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import threading
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from voxe_core.cameras import Cameras, random_hemisphere_poses
from voxe_core.constants import FLOAT32_MAX, NERF_SYNTHETIC_FOV_X, NERF_SYNTHETIC_RADIUS
from voxe_core.data import PixelScaleError, image_pixels
from voxe_core.files import unreadable_file
from voxe_core.grid import DEFAULT_BOX, VoxelGrid
from voxe_core.ply_header import is_numbers, ply_fault

MESH_INPUT_SUFFIXES = (".obj", ".ply")
MAX_MESH_FACES = 2_000_000
"""The most triangles a mesh may load as (an N-cornered polygon is N - 2 of them): its ingest shades and renders 120
views of every one (``write_mesh_dataset``: ``MESH_VIEWS``, 100 upper-hemisphere training views, and 20 test views on
the evaluation ring), in time and memory that grow with them (1.3 million faces took 14 minutes)."""
DECIMATE = "decimate it (Blender's Decimate modifier, MeshLab's quadric edge collapse)"
"""What to do with a mesh over :data:`MAX_MESH_FACES`, as its upload's and its load's refusals say."""
DEFAULT_ALBEDO = (0.7, 0.7, 0.7)  # meshes without texture or vertex colours
MESH_SHADING = ("auto", "baked", "none")
SHADING_LIGHT = (-1.0, -1.0, 2.0)  # towards the key light, canonical frame (normalised where used)
SHADING_AMBIENT = 0.35  # the share of light reaching a face turned away from the key light
SHADING_AO_RAYS = 32
SHADING_AO_RESOLUTION = 64
SHADING_AO_REACH = 0.5
UP_AXES = {"x": 0, "y": 1, "z": 2}
# A camera at NERF_SYNTHETIC_RADIUS looking at the origin sees a ball about it of radius R·sin(fov / 2) = 1.365
# touch its image's border; 5 % less keeps the silhouette a few pixels inside every view (spot and horse reach 1.27).
VIEW_RADIUS = 0.95 * NERF_SYNTHETIC_RADIUS * math.sin(NERF_SYNTHETIC_FOV_X / 2)
_COLOR_EPS = 1e-3  # colours are clamped into (eps, 1 - eps) before the logit
_MAX_PAIRS = 1 << 22  # (face, pixel) candidates rasterised together
_INSIDE_TOLERANCE = 1e-9  # a pixel centre is in a face where none of its barycentric coordinates is below minus this
_MIN_SCREEN_AREA = 1e-12  # twice a face's area on screen (pixels²) below which it is not drawn
_SPANNED_MISSES_PER_ROW = 3.0  # a face whose box's rows hold more pixels outside it than this is drawn by row spans
_SLAB_VERTICES = 1 << 20  # grid vertices voxelize reads together


class MeshError(ValueError):
    """A mesh file that cannot be used; the message names the file and the problem."""


class MeshWarning(UserWarning):
    """What a mesh loads without (the .mtl its mtllib names, the texture its PLY header names): the service's ingest
    says it on the jobs waiting for the scene."""


@dataclass
class SurfaceMesh:
    """A triangle mesh in the canonical frame with its albedo: a texture over UVs, vertex colours, or one colour."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    uv: np.ndarray | None = None  # (V, 2), with texture
    texture: np.ndarray | None = None  # (H, W, 3) float32 in [0, 1], row 0 at the top (v = 1)
    vertex_colors: np.ndarray | None = None  # (V, 3) float32 in [0, 1]
    # (3,) float32 in [0, 1]: the one colour of a mesh with neither (a single material's Kd), else DEFAULT_ALBEDO.
    # One colour gives no shape cue, so it counts as no colour: shading "auto" bakes for it.
    colour: np.ndarray | None = None
    shading: np.ndarray | None = None  # (V,) float32 in [0, 1], multiplies the albedo (``shade_mesh``)

    @property
    def has_colour(self) -> bool:
        return self.texture is not None or self.vertex_colors is not None

    def trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def albedo(self, face_index: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        """Albedo (N, 3) at points given by face and barycentric coordinates (N, 3)."""
        corners = self.faces[face_index]  # (N, 3)
        if self.texture is not None:
            uv = np.einsum("nk,nkc->nc", barycentric, self.uv[corners])
            colour = sample_texture(self.texture, uv)
        elif self.vertex_colors is not None:
            colour = np.einsum("nk,nkc->nc", barycentric, self.vertex_colors[corners]).astype(np.float32)
        else:
            one = DEFAULT_ALBEDO if self.colour is None else self.colour
            colour = np.broadcast_to(np.asarray(one, dtype=np.float32), (len(face_index), 3)).copy()
        if self.shading is not None:
            colour = colour * np.einsum("nk,nk->n", barycentric, self.shading[corners]).astype(np.float32)[:, None]
        return colour


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup (N, 3) at UVs (N, 2); UVs outside [0, 1] wrap (repeat), v = 0 is the bottom row."""
    image = torch.from_numpy(np.ascontiguousarray(texture, dtype=np.float32)).permute(2, 0, 1)[None]
    wrapped = _wrapped(uv)
    grid = torch.from_numpy(np.stack([2 * wrapped[:, 0] - 1, 1 - 2 * wrapped[:, 1]], -1)).float()
    out = F.grid_sample(image, grid[None, :, None, :], mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, :, 0].T.numpy()


def _wrapped(uv: np.ndarray) -> np.ndarray:
    """UVs outside [0, 1] wrapped into it (repeat); 1 stays the right / top border, not 0."""
    return np.where((uv >= 0) & (uv <= 1), uv, np.mod(uv, 1.0))


# ------------------------------------------------------------------ loading
MESH_FRAMES = (1, 2)
"""How ``load_mesh`` places a mesh: 2, the box of the vertices faces use, shrunk into ``VIEW_RADIUS``; 1, the box of
every vertex in the file, its largest half-extent ``extent`` (how meshes were placed before 2: a scene stored then
keeps the frame its views were rendered in)."""


def load_mesh(
    path: str | os.PathLike, texture: str | os.PathLike | None = None, up_axis: str = "y", extent: float = 1.0,
    frame: int = 2,
) -> SurfaceMesh:
    """Read an OBJ or a PLY (with ``texture``: its image, UVs from the file), normalised.

    A ``texture`` given colours every part at the file's own UVs ((0, 0) on parts
    without vt) whatever the file's materials; without one, an OBJ's .mtl (a PLY's TextureFile, its vertex or face
    colours) colours it as trimesh reads it (its images and Kd packed into one atlas, ``_atlas``, where parts with
    neither are ``DEFAULT_ALBEDO`` or their vertex colours; a single material's own Kd is the mesh's one ``colour``
    when it names no image); with no image or Kd the file wrote (its .mtl missing, say: a warning names it), the mesh
    is uncoloured as one without vt is.

    ``up_axis``: the file's up axis ('y' for OBJ/glTF exports, 'z' for CAD and
    most scanners), turned onto +z. The box is centred on the origin and its
    largest half-extent made ``extent``, or less where the mesh would reach past
    ``VIEW_RADIUS`` (``frame`` 1: see ``MESH_FRAMES``). Raises ``MeshError`` naming the file for a mesh or texture not
    there (or a folder, or an empty file), for a malformed file (``ply_header.ply_fault``, ``_obj_fault``: what in it,
    where), for unreadable, triangle-less, degenerate or non-finite meshes (vertices, UVs or colours), for a PLY's
    triangle strips (not read), for one of more than ``MAX_MESH_FACES`` triangles, for a texture without UVs and for
    an .mtl's Kd that is neither one number nor three.
    """
    import trimesh
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() not in MESH_INPUT_SUFFIXES:
        raise MeshError(f"{path.name}: unsupported mesh type {path.suffix!r}; use one of {', '.join(MESH_INPUT_SUFFIXES)}")
    if up_axis not in UP_AXES:
        raise MeshError(f"up_axis must be one of {', '.join(UP_AXES)}, got {up_axis!r}")
    # An infinite one had been refused as the mesh's extent "too small to scale up"; one past 1.3e154 overflowed
    if not 0 < extent <= FLOAT32_MAX:  # squaring in the area test (its grid is float32 anyway)
        raise MeshError(f"extent must be positive and finite in float32, got {extent}")
    if frame not in MESH_FRAMES:
        raise MeshError(f"frame must be one of {MESH_FRAMES}, got {frame!r}")
    _check_readable(path, "a mesh file")
    if texture is not None:
        _check_readable(Path(texture), "an image")
    fault = ply_fault(path) if path.suffix.lower() == ".ply" else _obj_fault(path, textured=texture is not None)
    if fault is not None:
        raise MeshError(f"{path.name}: {fault}")
    try:  # with a texture, its parts as they are: the file's materials are not what colours it
        library = _MtlBySpec(trimesh.resolvers.FilePathResolver(path))
        with _PlyTextureWarning() as unread_texture:
            parts = trimesh.load(path, force="scene", process=False, skip_materials=texture is not None,
                                 resolver=library).dump()
        if texture is None:  # the parts joined as trimesh joins them (``Scene.to_mesh``), its materials packed
            meshes = _without_stand_in_textures([part for part in parts if isinstance(part, trimesh.Trimesh)])
            loaded = trimesh.util.concatenate(meshes)
    except Exception as e:  # trimesh raises many types for damaged files
        raise MeshError(f"{path.name}: cannot read as a mesh: {e}") from e
    if library.problem:
        raise MeshError(library.problem)
    if texture is None and (fault := _ply_colour_fault(parts)):
        raise MeshError(f"{path.name}: {fault}")
    if library.missing is not None:  # trimesh drops it without a word, the mesh grey
        warnings.warn(f"{path.name}: the material library its mtllib names, {library.missing!r}, is not found beside "
                      "it; the mesh loads without its materials", MeshWarning, stacklevel=2)
    if unread_texture.error is not None:  # (Pillow names the bytes trimesh hands it by an address, new at each load)
        error = re.sub(r" ?<_io\.BytesIO object at 0x[0-9a-fA-F]+>", "", str(unread_texture.error))
        warnings.warn(f"{path.name}: the texture its header names (TextureFile) cannot be read "
                      f"({type(unread_texture.error).__name__}: {error}); the mesh loads without it",
                      MeshWarning, stacklevel=2)
    if texture is None:
        vertices = np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64)
        faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))), dtype=np.int64)
    else:
        vertices, faces, uv = _joined_parts(parts)
    if any(part.metadata.get("_ply_raw", {}).get("tristrips", {}).get("length") for part in parts):
        raise MeshError(f"{path.name}: its faces are stored as triangle strips (a 'tristrips' element), which are "
                        "not read: save the mesh with a 'face' element (triangles or polygons)")
    if len(faces) == 0 or len(vertices) < 3:
        raise MeshError(f"{path.name}: no triangles in the file")
    if len(faces) > MAX_MESH_FACES:  # a binary PLY's polygons, say, which the upload's check cannot count cheaply
        raise MeshError(f"{path.name}: it loads as {len(faces):,} triangles, more than the {MAX_MESH_FACES:,} a mesh "
                        f"may hold: {DECIMATE}")
    if vertices.shape[1] != 3:  # an OBJ's "v x y" lines load so (as (V, 2)); placing them had raised an IndexError
        raise MeshError(f"{path.name}: its vertices read as {vertices.shape[1]} coordinates each, not 3 (x y z)")
    if faces.min() < 0:  # a PLY's load so, as do its indices past the count below (``_obj_fault`` refuses an OBJ's)
        raise MeshError(f"{path.name}: a face names a negative vertex index, {int(faces.min())}")
    if faces.max() >= len(vertices):
        raise MeshError(f"{path.name}: a face names vertex {int(faces.max()) + 1} of {len(vertices)}")
    mesh = SurfaceMesh(vertices, faces)
    if texture is not None:
        if uv is None:
            raise MeshError(f"{path.name}: a texture was given but the mesh has no texture coordinates (vt)")
        try:
            with Image.open(texture) as image:
                mesh.texture = _texture_rgb(image, Path(texture).name)
        except (MemoryError, MeshError):
            raise
        except Exception as e:  # Pillow's plugins raise many kinds on damaged headers (NotImplementedError for DDS's)
            raise MeshError(f"{Path(texture).name}: cannot read the texture image: {e}") from e
        mesh.uv = uv
    elif getattr(loaded.visual, "kind", None) == "vertex":
        mesh.vertex_colors = np.asarray(loaded.visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    elif getattr(loaded.visual, "kind", None) == "face":  # a PLY's: each face gets three vertices of its colour
        colours = np.asarray(loaded.visual.face_colors, dtype=np.float32)[:, :3] / 255.0
        mesh = SurfaceMesh(vertices[faces].reshape(-1, 3), np.arange(3 * len(faces)).reshape(-1, 3),
                           vertex_colors=np.repeat(colours, 3, axis=0))
    elif getattr(loaded.visual, "kind", None) == "texture" and getattr(loaded.visual.material, "image", None):
        mesh.texture, mesh.uv = _atlas(meshes, path.name)  # an OBJ whose .mtl named its image, or several materials
    else:
        mesh.colour = _written_diffuse(loaded.visual)
    mesh = _used_vertices_only(mesh)
    boxed = mesh.vertices if frame == 2 else vertices  # frame 1: every vertex the file holds

    if not np.isfinite(boxed).all():
        raise MeshError(f"{path.name}: vertex coordinates contain NaN or Inf")
    if mesh.uv is not None and not np.isfinite(mesh.uv).all():  # the texture lookup would sample garbage there
        raise MeshError(f"{path.name}: texture coordinates (vt) contain NaN or Inf")
    lo, hi = boxed.min(0), boxed.max(0)
    half = float((hi / 2 - lo / 2).max())  # each halved first: a span past float64's 1.8e308 had been inf
    if not half > 0:
        raise MeshError(f"{path.name}: all vertices coincide; the mesh has no extent")
    if not math.isfinite(extent / half):
        raise MeshError(f"{path.name}: the mesh's extent, {2 * half:.3g}, is too small to scale up in float64")
    up = UP_AXES[up_axis]
    order = [(up + 1) % 3, (up + 2) % 3, up]  # a cyclic permutation: a rotation, handedness kept
    mesh.vertices = (mesh.vertices - (lo / 2 + hi / 2))[:, order]
    scale = extent
    if frame == 2:  # the reach taken at half-extent 1: at 1e-170 (or 1e155) the norm's squares under- (over)flowed
        scale = min(scale, VIEW_RADIUS / float(np.linalg.norm(mesh.vertices / half, axis=1).max()))
    mesh.vertices *= scale / half
    # Voxelised, a mesh of no area would be an empty grid. Relative to the half-extent placed: the extent squared had
    # overflowed past 1.3e154, and at 3e38 refused every mesh shrunk into the view
    if not _has_area(mesh.vertices, mesh.faces, (1e-6 * scale) ** 2):
        raise MeshError(f"{path.name}: every triangle has zero area (repeated or collinear vertices); "
                        "the mesh has no surface")
    return mesh


def _check_readable(path: Path, kind: str) -> None:
    """Raises a MeshError naming ``path`` unless it is a readable file with something in it: trimesh had said "string
    is not a file: `<the full path>`" of a mesh that is not there or a folder, Pillow "[Errno 2] No such file or
    directory: '<the full path>'" of a texture (a worker's scratch path, in a service's error)."""
    if problem := unreadable_file(path, kind):  # (a FIFO had been "no such file", and trimesh would wait on it)
        raise MeshError(f"{path.name}: {problem}")
    if path.stat().st_size == 0:
        raise MeshError(f"{path.name}: the file is empty")


OBJ_CORNER_FIELDS = {"v": "vertex", "vt": "texture coordinate (vt)", "vn": "normal (vn)"}
"""What the fields of an OBJ face's corner (v/vt/vn) name, by the keyword of the lines that hold them."""
_OBJ_CORNER = r"[+-]?[0-9]+(?:/(?:[+-]?[0-9]+)?){0,2}"
"""One corner of an OBJ face: v, v/vt, v//vn or v/vt/vn."""
_OBJ_FACE = re.compile(rf"[^\S\n]*(?:{_OBJ_CORNER}(?:[^\S\n]+{_OBJ_CORNER})*)?[^\S\n]*")
"""What follows an OBJ face line's keyword: corners (a line of fewer than three trimesh skips)."""
_OBJ_BAD_FACE = re.compile(rf"\n(?!{_OBJ_FACE.pattern}$)", re.M)
"""The start of a face line's words (of those joined, each after a newline) that ``_OBJ_FACE`` does not match."""
_OBJ_WORDS = {**{keyword: re.compile(rf"\n{keyword} (.*)") for keyword in OBJ_CORNER_FIELDS},
              "f": re.compile(r"\nf(?:[^\S\n](.*)|$)", re.M)}
"""The words after the keyword of each line of a text (a newline put first) that trimesh reads as that keyword's
(a v, vt or vn line where a space follows it; ``_OBJ_UNREAD`` refuses the rest)."""
_NOT_FINITE = re.compile(r"(?i)nan|inf")
"""A NaN or Inf in number words (and anything holding those letters, checked value by value then)."""
_OBJ_UNREAD = re.compile(r"\n(?:([ \t\r\v\f]+)(vt|vn|v|f)(?=\s)|(vt|vn|v|f)([\t\r\v\f]))")
"""The newline before a v, vt, vn or f line trimesh does not read as one: indented, or a tab after its keyword."""
_OBJ_LONE_CR = re.compile(r"\r[ \t\v\f]*(?:vt|vn|v|f|usemtl)\s")
"""A v, vt, vn, f or usemtl line after a CR alone, which trimesh reads as part of the line before."""
_OBJ_INDICES = {"v": re.compile(r"(?<=\s)([+-]?[0-9]+)"), "vt": re.compile(r"(?<=\s)[+-]?[0-9]+/([+-]?[0-9]+)")}
"""The vertex and texture coordinate indices of the corners of one face line (which ``_OBJ_FACE`` matches)."""
_OBJ_NEGATIVE = {"v": re.compile(r"\nf[^\S\n][^\n]*?(?<=\s)(-[0-9]+)"),
                 "vt": re.compile(r"\nf[^\S\n][^\n]*?/(-[0-9]+)")}
"""A face line (a newline put first) with a negative vertex (vt) index, and that index."""
_OBJ_SHORT_ROW = re.compile(r"\n[^\S\n]*(?:\S+[^\S\n]*)?(?=\n)")
"""A line (of lines joined, a newline put first and last) of fewer than two words."""
_OBJ_FORMS = {(False, False): "v", (True, False): "v/vt", (False, True): "v//vn", (True, True): "v/vt/vn"}


def _obj_fault(path: Path, textured: bool = False) -> str | None:
    """What in the OBJ at ``path`` the mesh loader (trimesh) would fail on in words of its own, or misread without a
    word, said for a user (the file not named), or None: a v, vt, vn or f line it does not read as one (indented, a
    tab after its keyword, a byte order mark before it: ``_obj_unread_line``), a v, vt or vn line's word that is not
    a number, a face line that is not corners of indices, corners of one material's faces not all of one form
    (``_obj_form_fault``; forms dropping the texture coordinates, only where they colour the mesh: ``textured``, a
    texture given, or a material library named), a vt line of fewer than two values where corners name vt (trimesh
    reads every vt so short, which the rasteriser had failed on), a negative index in a face line with vertices (vt)
    after it, or a corner naming a vertex or texture coordinate the file does not hold (0, or past their count
    either way; normals, which the loader does not read, are not counted; texture coordinates neither in a file
    without vt lines, whose corners' vt the loader ignores). trimesh had said "index 8 is out of bounds for axis 0
    with size 3" or "string or file could not be read to its end due to unmatched data", read index 0 as vertex 1,
    and dropped every texture coordinate for one vt index past the count. As trimesh counts them, a negative index
    counts back from the file's last vertex (or vt), where an OBJ's counts back from the last before its line. A
    face line of fewer than three corners trimesh skips, as it does a line (l) or a point (p). Lines are numbered as
    the file's (a continued one, its backslash at the end, by its first).

    Each check runs over the whole file at once (a 13 MB OBJ of 327,680 faces in a fraction of trimesh's load), and
    over its lines one by one only to name the first at fault.
    """
    raw = path.read_bytes().decode("utf-8", "replace")
    pieces = raw.strip().replace("\r\n", "\n").split("\\\n")  # as trimesh: stripped, continued lines joined
    text = "".join(pieces)
    joins = np.cumsum([len(piece) for piece in pieces[:-1]])  # where in ``text`` a line was continued
    blank_lines = raw[:len(raw) - len(raw.lstrip())].count("\n")

    def number(start: int) -> int:
        """The file's number of the line at ``start`` in ``text``."""
        return blank_lines + 1 + text.count("\n", 0, start) + int(np.searchsorted(joins, start))

    def named(start: int, problem: str) -> str:
        """``problem`` of the line at ``start`` in ``text``, said with its number and its start."""
        end = text.find("\n", start)
        return f"line {number(start)}, {text[start:end if end >= 0 else None].strip()[:40]!r}: {problem}"

    def first(keywords: tuple, fault) -> str | None:
        """The first line of one of ``keywords`` at fault (``fault`` of its words after the keyword), named."""
        start = 0
        for line in text.split("\n"):
            keyword, *rest = line.split(None, 1) or [""]
            if keyword in keywords and (problem := fault("".join(rest))):
                return named(start, problem)
            start += len(line) + 1
        return None

    lined = "\n" + text + "\n"  # (a line's start in ``text``: the index of the newline before it here)
    if unread := _obj_unread_line(lined):
        return named(*unread)
    words = {keyword: pattern.findall(lined) for keyword, pattern in _OBJ_WORDS.items()}
    counts = {kind: len(words[kind]) for kind in OBJ_CORNER_FIELDS}
    faces = "\n".join(words["f"])
    if not is_numbers(" ".join(" ".join(words[kind]) for kind in OBJ_CORNER_FIELDS)) and (
            fault := first(tuple(OBJ_CORNER_FIELDS), _obj_number_fault)):
        return fault
    if _OBJ_BAD_FACE.search("\n" + faces) and (fault := first(("f",), _obj_face_fault)):
        return fault
    if _NOT_FINITE.search(" ".join(words["v"])) and (fault := first(("v",), _obj_colour_fault)):
        return fault
    corners = _corner_fields(faces)
    vertices, *fields = _corners_giving(corners)
    for field, kind in enumerate(_OBJ_INDICES):
        count = counts[kind]
        if kind == "vt" and count == 0:  # the loader ignores the corners' vt then
            continue
        if negative := _OBJ_NEGATIVE[kind].search(lined, 0, lined.rfind(f"\n{kind} ")):
            return named(negative.start(), (
                f"its {OBJ_CORNER_FIELDS[kind]} index {negative[1]} counts back from the last before this line, but "
                "the loader counts back from the file's last, and the file has more after this line: write the "
                "index positive"))
        indices = _corner_field(corners, field)
        if not ((indices != 0) & (indices >= -count) & (indices <= count)).all() and (
                fault := first(("f",), partial(_obj_index_fault, kind, count))):
            return fault
    if any(0 < given < vertices for given in fields) and (
            misread := _obj_form_fault(text, number, textured or "mtllib" in text)):
        return named(*misread)
    if fields[0] and _OBJ_SHORT_ROW.search("\n" + "\n".join(words["vt"]) + "\n") and (
            fault := first(("vt",), _obj_short_vt_fault)):
        return fault
    return None


def _obj_unread_line(lined: str) -> tuple[int, str] | None:
    """The first v, vt, vn or f line of ``lined`` (an OBJ's text as trimesh reads it, a newline put first and last)
    that trimesh does not read as one, as (its start in the text, the problem), or None: one indented, with a tab
    after its keyword (a face line so trimesh reads only between its first face, o, g, s or usemtl line and its last
    "f " line), after a carriage return alone (a classic Mac OS line end), or after a byte order mark at the start
    (which takes a usemtl line's material from the faces under it too)."""
    if lined.startswith("\n\ufeff") and (keyword := lined[2:lined.find("\n", 1)].split(None, 1)[:1]) and (
            keyword[0] in (*_OBJ_WORDS, "usemtl")):
        return 0, (f"the file begins with a byte order mark (U+FEFF), which the loader reads as part of this line's "
                   f"keyword, {keyword[0]!r}: save it as UTF-8 without one")
    if "\r" in lined and (alone := _OBJ_LONE_CR.search(lined)):  # (each CR LF's CR is gone)
        return lined.rfind("\n", 0, alone.start()), (
            "a carriage return (CR) alone ends a line within it, where the loader ends lines only at a line feed (LF, "
            "or CR LF): save it with those")
    faces = None  # where trimesh reads face lines (found for a tabbed one only: each search costs a scan)
    for line in _OBJ_UNREAD.finditer(lined):
        indent, keyword = line[1], line[2] or line[3]
        if not indent and keyword == "f":
            if faces is None:
                starts = [at for key in ("usemtl", "o", "f", "g", "s") if (at := lined.find(f"\n{key} ")) >= 0]
                faces = min(starts, default=len(lined)), lined.find("\n", lined.rfind("\nf ") + 3)
            if faces[0] <= line.start() < faces[1] - 1:
                continue
        return line.start(), (
            f"indented: the loader reads a {keyword} line only where its keyword begins the line" if indent else
            f"a {line[4]!r} after its keyword: the loader reads a {keyword} line only where a space follows it")
    return None


def _obj_form_fault(text: str, number, uv_used: bool) -> tuple[int, str] | None:
    """The first face line of ``text`` (an OBJ's) whose corners trimesh misreads among its material's, as (its start,
    the problem), or None (``number``: the file's number of the line at a start). trimesh reads the faces of one
    material (``usemtl``) at once as corners of the first line's form where every line holds as many numbers (a v/vt
    corner's vt read off a v//vn one's vn, three v/vt corners as six vertices), or else line by line, dropping
    every corner's vt when one corner (of a line of three or more) has none: a misreading where ``uv_used``."""
    materials: dict = {}  # a material's face lines: (start, their corners' forms, how many numbers)
    start, material = 0, None
    for line in text.split("\n"):
        words = line.split()
        if words[:1] == ["usemtl"]:
            material = line.strip()[6:].strip()
        elif words[:1] == ["f"]:
            forms = [_OBJ_FORMS[tuple(field != "" for field in (corner.split("/") + ["", ""])[1:3])]
                     for corner in words[1:]]
            numbers = len(" ".join(words[1:]).replace("/", " ").split())
            materials.setdefault(material, []).append((start, forms, numbers))
        start += len(line) + 1
    for faces in materials.values():
        if len({numbers for *_, numbers in faces}) == 1:
            kind, reading = (lambda form: form), "the loader reads them all as {}"
        elif uv_used:
            faces = [face for face in faces if len(face[1]) >= 3]
            kind, reading = (lambda form: "/vt" in form), "the loader drops every corner's texture coordinates (vt)"
        else:
            continue
        for start, forms, _ in faces:
            expected = faces[0][1][0]
            if odd := next((form for form in forms if kind(form) != kind(expected)), None):
                first = "this line's first" if start == faces[0][0] else f"line {number(faces[0][0])}'s"
                return start, (f"a corner {odd} among corners {expected} ({first}) in one material's faces: "
                               + reading.format(expected))
    return None


def _obj_number_fault(words: str) -> str | None:
    """What in a v, vt or vn line's ``words`` is not a number, or None."""
    if (word := next((word for word in words.split() if not is_numbers(word)), None)) is None:
        return None
    return _obj_comment_fault(words) if word.startswith("#") else f"{word[:20]!r} is not a number"


def _obj_comment_fault(words: str) -> str:
    """A line's comment after its values, ``words`` (which hold a #), said."""
    return (f"a comment after its values, {words[words.index('#'):][:20]!r}, which the loader reads as values: put it "
            "on a line of its own")


def _obj_colour_fault(words: str) -> str | None:
    """Why a v line's ``words`` hold a vertex colour the loader would read as black (NaN, Inf), or None."""
    colour = words.split()[3:]
    return None if np.isfinite(np.array(colour, dtype=np.float64)).all() else (
        f"its vertex colour {' '.join(colour)!r} is not finite (NaN or Inf), which the loader would read as black")


def _ply_colour_fault(parts: list) -> str | None:
    """Which element of a PLY's (trimesh's raw read of it, in ``parts``' metadata) has a colour value that is NaN or
    Inf, which trimesh turns into black without a word, or None."""
    for part in parts:
        for element, read in getattr(part, "metadata", {}).get("_ply_raw", {}).items():
            data = read.get("data")
            names = data.dtype.names or () if isinstance(data, np.ndarray) else tuple(data or ())
            for name in (name for name in ("red", "green", "blue", "alpha") if name in names):
                values = np.asarray(data[name])
                if values.dtype.kind == "f" and not np.isfinite(values).all():
                    return f"its {element} colours ({name}) contain NaN or Inf, which the loader would read as black"
    return None


def _obj_short_vt_fault(words: str) -> str | None:
    """Why a vt line's ``words`` are not a texture coordinate the loader reads, or None."""
    return None if len(words.split()) >= 2 else (
        f"a texture coordinate of {len(words.split())} value, not 2 (u v): the loader reads every vt as short then")


def _obj_face_fault(words: str) -> str | None:
    """Why a face line's ``words`` are not a face, or None."""
    if _OBJ_FACE.fullmatch(words):
        return None
    if "#" in words and _OBJ_FACE.fullmatch(words[:words.index("#")]):
        return _obj_comment_fault(words)
    return "not a face of three or more corners, each v, v/vt, v//vn or v/vt/vn"


def _obj_index_fault(kind: str, count: int, words: str) -> str | None:
    """The first corner in a face line's ``words`` naming a ``kind`` (v or vt) past the file's ``count``, or None."""
    index = next((index for index in map(int, _OBJ_INDICES[kind].findall(" " + words))
                  if not 1 <= abs(index) <= count), None)
    if index is None:
        return None
    return (f"a face names {OBJ_CORNER_FIELDS[kind]} {index}, of the {count} the file holds"
            + (" (an OBJ counts them from 1)" if index == 0 else ""))


def _corner_fields(faces: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The characters of ``faces`` (face lines' words that ``_OBJ_FACE`` matches) as bytes, whether each is between
    corners, and the field of each within its corner (0: the vertex, 1: the texture coordinate, 2: the normal; a slash
    the field it opens). Read off the characters all at once: a regex's match per corner costs more than trimesh's
    whole load."""
    data = np.frombuffer(faces.encode(), dtype=np.uint8)
    slash = data == ord("/")
    between = ~(slash | ((data >= ord("0")) & (data <= ord("9"))) | (data == ord("+")) | (data == ord("-")))
    # The slashes before each character within its corner (at most two): their running count, taken back at its end
    ends = np.flatnonzero(between)
    steps = slash.view(np.int8).copy()
    steps[ends] = -np.diff(np.searchsorted(np.flatnonzero(slash), ends), prepend=0)
    return data, between, np.cumsum(steps, dtype=np.int8)


def _corner_field(corners: tuple, field: int) -> np.ndarray:
    """The indices in field ``field`` of the corners (``_corner_fields``) that give it, as int64 (one past its range
    made the nearest end of it)."""
    data, between, fields = corners
    digits = (fields == field) & (data != ord("/")) & ~between
    if not digits.any():  # numpy reads blank text as one 0
        return np.empty(0, dtype=np.int64)
    return np.fromstring(np.where(between, ord(" "), data)[digits | between].tobytes(), sep=" ", dtype=np.int64)


def _corners_giving(corners: tuple) -> np.ndarray:
    """How many of the corners (``_corner_fields``) give a vertex, a texture coordinate and a normal (3,)."""
    data, between, fields = corners
    number = (data != ord("/")) & ~between
    starts = number & ~np.concatenate([[False], number[:-1]])
    return np.bincount(fields[starts], minlength=3)[:3]


def _texture_rgb(image, name: str) -> np.ndarray:
    """A texture image as (H, W, 3) float32 in [0, 1] by the capture images' rule (``data.image_pixels``: 8 and
    16 bits scaled, float or 32-bit pixels of unrecorded scale refused), a MeshError naming ``name``."""
    try:
        return image_pixels(image, alpha=False)
    except PixelScaleError as e:
        raise MeshError(f"{name}: the texture image {e}") from None


def _written_diffuse(visual) -> np.ndarray | None:
    """The colour (3,) in [0, 1] an OBJ's material (the file's one, or a part's) gives by its Kd alone, or None.

    Several materials ``_atlas`` packs into one texture, Kd colours included; one without an image trimesh leaves as a
    material, whose diffuse is trimesh's default grey unless the .mtl wrote a Kd. Only a Kd the file wrote
    (trimesh's parse_mtl keeps the .mtl's keys in the material's kwargs) colours the mesh: a file without a
    library, or whose material sets no Kd, keeps ``DEFAULT_ALBEDO``. Either way shading "auto" bakes light and
    occlusion in: one colour is no shape cue (Blender's default material writes Kd 0.8 0.8 0.8).
    """
    material = getattr(visual, "material", None)
    if getattr(visual, "kind", None) != "texture" or "kd" not in getattr(material, "kwargs", {}):
        return None
    return np.asarray(material.diffuse, dtype=np.float32)[:3] / 255.0


def _without_stand_in_textures(parts: list) -> list:
    """``parts`` (a file's meshes), each textured one with no colour the file wrote made a plain mesh.

    A part with texture coordinates but no material the file gives it (an OBJ without ``mtllib``, its .mtl
    missing, a ``usemtl`` the library does not define; a PLY's texcoord without its TextureFile) gets trimesh's
    stand-in, a 2×2 image of its grey named as a material of the library may be: joined, the mesh had loaded as
    textured in that grey, and shading "auto" left it a flat silhouette; beside coloured parts, that part had been
    trimesh's grey (0.39) where an uncoloured mesh is ``DEFAULT_ALBEDO``. It is told apart by what the file wrote:
    an image read from a file (Pillow sets ``format`` for those only) or a Kd. Made plain, it keeps the colours its
    vertices were given, if any; ``_atlas`` gives it ``DEFAULT_ALBEDO`` otherwise, as a part without vt or
    material is given.
    """
    import trimesh

    def written(part) -> bool:
        material = getattr(part.visual, "material", None)
        return (getattr(getattr(material, "image", None), "format", None) is not None
                or "kd" in getattr(material, "kwargs", {}))

    return [part if part.visual.kind != "texture" or written(part) else
            trimesh.Trimesh(part.vertices, part.faces, vertex_colors=part.vertex_attributes.get("color"),
                            process=False) for part in parts]


def _atlas(parts: list, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The texture (H, W, 3) and UVs (V, 2) colouring ``parts`` (a file's meshes, in ``trimesh.util.concatenate``'s
    vertex order): one part's own image at its own UVs, or every distinct colour side by side in one atlas.

    trimesh's atlas is read by its own texel convention, not ``sample_texture``'s, its blocks padded in black and
    at times placed past its image's edge: a Kd-only material had loaded 0.81 red at UVs near its 2×2 block's
    border, or black, and a map_Kd image shifted by up to a texel. Here each block is an image (or a part's one
    colour, sampled at its centre whatever the part's UVs) padded by a texel of its own edge, so a lookup reads
    what ``sample_texture`` reads from the image alone. Parts whose images hold the same pixels share one block
    (exporters give each material its own copy of one image: a block each had grown the atlas by the image at
    every material). A block's UVs are wrapped a vertex at a time (a face spanning a wrap is not repeated), as
    trimesh's were.
    """
    blocks: dict = {}  # the pixels' key -> (index, image), in first-use order
    placed = []
    for part in parts:
        source, uv = _part_colour(part, name)
        key = _pixels_key(source)
        if key not in blocks:
            blocks[key] = (len(blocks), source if isinstance(source, np.ndarray) else
                           _texture_rgb(source, f"{name} ({_image_source(name)})"))
        placed.append((blocks[key][0], uv))
    images = [image for _, image in blocks.values()]
    if len(parts) == 1:
        return images[0], placed[0][1]
    height = max(image.shape[0] for image in images) + 2
    lefts = np.cumsum([0] + [image.shape[1] + 2 for image in images])
    padded = [np.pad(image, ((1, height - image.shape[0] - 1), (1, 1), (0, 0)), mode="edge") for image in images]
    uvs = []
    for index, uv in placed:
        (h, w), uv = images[index].shape[:2], _wrapped(uv)
        uvs.append(np.stack([(lefts[index] + 1 + uv[:, 0] * w) / lefts[-1], 1 - (1 + (1 - uv[:, 1]) * h) / height],
                            -1))
    return np.concatenate(padded, axis=1), np.concatenate(uvs)


def _image_source(name: str) -> str:
    """Where a mesh file names its texture image, for messages."""
    return "its header's TextureFile" if name.lower().endswith(".ply") else "its .mtl's map_Kd"


def _pixels_key(source) -> tuple:
    """A key equal for two colour sources (a PIL image, or an (h, w, 3) array) exactly when their pixels are."""
    import hashlib

    pixels = source.tobytes()
    digest = hashlib.blake2b(pixels, digest_size=16).digest() if len(pixels) > 64 else pixels
    if isinstance(source, np.ndarray):
        return source.shape, digest
    # a palette image's bytes are its indices: two palettes over the same indices had shared one block
    return source.mode, source.size, bytes(source.getpalette() or ()), repr(source.info.get("transparency")), digest


def _part_colour(part, name: str) -> tuple:
    """(colour source, UVs (V, 2)) for one part: its material's image (a PIL image) at its UVs, or a 1×1 image
    (array) of its Kd; for a part without a material the file wrote (``_without_stand_in_textures``), its vertex
    colours as trimesh packs them (a texel per colour: exact at the vertices, a face's inside read between its
    texels, not blended from its corners), else ``DEFAULT_ALBEDO``. An image with no vt to place it is a
    MeshError, as a texture given beside such a file is."""
    import trimesh

    centre = np.full((len(part.vertices), 2), 0.5)
    if part.visual.kind == "vertex":
        material, uv = trimesh.visual.color.color_to_uv(part.visual.vertex_colors)
    elif part.visual.kind == "texture":
        material, uv = part.visual.material, part.visual.uv
    else:
        return np.asarray(DEFAULT_ALBEDO, dtype=np.float32).reshape(1, 1, 3), centre
    if getattr(material, "image", None) is None:
        return _written_diffuse(part.visual).reshape(1, 1, 3), centre
    if uv is None:
        whose = f"material {material.name!r}" if getattr(material, "name", None) else "the mesh"
        raise MeshError(f"{name}: {_image_source(name)} names an image but {whose} has no texture coordinates "
                        f"({'texcoord' if name.lower().endswith('.ply') else 'vt'}) to place it")
    return material.image, np.asarray(uv, dtype=np.float64)


class _PlyTextureWarning(logging.Filter):
    """Within ``with``, holds back the warning trimesh logs for a PLY's TextureFile it cannot read, keeping its
    error: "unable to load image!" and a traceback (a missing file's FileNotFoundError) read as a failure in a
    worker's log, where the mesh loads without its texture (a PLY uploaded without its image, say).
    ``load_mesh`` warns once instead, naming the mesh and the error. Only this thread's records are held."""

    def __init__(self):
        super().__init__()
        self.thread = threading.get_ident()
        self.error: BaseException | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        if record.thread != self.thread or record.getMessage() != "unable to load image!" or not record.exc_info:
            return True
        self.error = record.exc_info[1]
        return False

    def __enter__(self) -> _PlyTextureWarning:
        import trimesh

        trimesh.exchange.ply.log.addFilter(self)
        return self

    def __exit__(self, *exc) -> None:
        import trimesh

        trimesh.exchange.ply.log.removeFilter(self)


def referenced_base_name(name: str) -> str:
    """The name a file an OBJ refers to (an ``mtllib``'s, a ``map_Kd``'s) is found by in the mesh's folder, where the
    path written is not there: its base name after either separator ('C:\\me\\model.mtl', '../model.mtl'), in any
    case."""
    return re.split(r"[\\/]", name.strip())[-1].lower()


class _MtlBySpec(Mapping):
    """trimesh's lookup of an OBJ's files (``files``), the .mtl handed over with its colours as the MTL spec reads them.

    trimesh keeps a one-value colour as a number its material refuses, and then drops every material of the
    library, a map_Kd image among them: ``Kd 0.5`` (a grey: the spec takes g and b equal to r) had loaded in
    ``DEFAULT_ALBEDO``, ``Kd 0`` in trimesh's own grey. Here one value is written out three times; Ka and Ks, which
    an unlit albedo never reads, are left out, so that no malformed one loses the library either. A Kd of another
    shape (two values, a word such as ``spectral`` or ``xyz``, NaN) would be lost as silently: the first is kept in
    ``problem`` for ``load_mesh`` to refuse, as trimesh swallows whatever its lookup raises.
    """

    def __init__(self, files):
        self.files = files
        self.problem: str | None = None
        self.missing: str | None = None  # the first .mtl looked up and not found, for ``load_mesh`` to warn of

    def __getitem__(self, name: str) -> bytes:
        data = self._file(name)
        return self._by_spec(data, name) if name.strip().lower().endswith(".mtl") else data

    def _file(self, name: str) -> bytes:
        """The file ``name`` (an ``mtllib``'s, a ``map_Kd``'s) names: as trimesh looks it up (the path, then its base
        name), else the mesh folder's file whose name is its base name after either separator, in any case. Windows
        exporters write ``mtllib C:\\Users\\me\\model.mtl`` or ``..\\model.mtl``, and Windows' and macOS' file
        systems find ``Model.MTL`` as ``model.mtl``: such a library had been dropped without a word, the mesh grey."""
        try:
            return self.files[name]
        except (OSError, ValueError):  # not found, or outside the folder
            base = referenced_base_name(name)
            folder = Path(self.files.parent)
            match = next((path.name for path in sorted(folder.iterdir()) if path.name.lower() == base), None)
            if match is None:
                if base.endswith(".mtl"):
                    self.missing = self.missing or name.strip()
                raise
            return self.files[match]

    def __iter__(self):
        return iter(self.files.keys())

    def __len__(self) -> int:
        return sum(1 for _ in self.files.keys())

    def _by_spec(self, data: bytes, name: str) -> bytes:
        """``data`` (an .mtl) with one-value Kds written out, bare ones, Ka and Ks left out; bytes, as file names
        are kept."""
        lines = []
        for number, line in enumerate(data.splitlines(), 1):
            key, *values = line.split(b"#", 1)[0].split() or [b""]
            if key.lower() in (b"ka", b"ks") or (key.lower() == b"kd" and not values):  # (trimesh skips a bare Kd)
                continue
            if key.lower() == b"kd":
                try:
                    colour = [float(value) for value in values]
                except ValueError:
                    colour = []
                if len(colour) not in (1, 3) or not np.isfinite(colour).all():
                    self.problem = self.problem or (
                        f"{Path(name.strip()).name} line {number}: {line.strip().decode(errors='replace')!r}: "
                        "Kd must be one finite number (a grey level) or three (r g b)")
                else:  # one value written out three times; a trailing comment left out, which trimesh misreads
                    line = b" ".join([key, *values * (3 // len(values))])
            lines.append(line)
        return b"\n".join(lines)


def _used_vertices_only(mesh: SurfaceMesh) -> SurfaceMesh:
    """The mesh without the vertices no face uses: a file's strays must not set its box (or its occlusion grid's)."""
    used = np.unique(mesh.faces)
    if len(used) == len(mesh.vertices):
        return mesh
    kept = lambda per_vertex: None if per_vertex is None else per_vertex[used]  # noqa: E731
    return replace(mesh, vertices=mesh.vertices[used], faces=np.searchsorted(used, mesh.faces), uv=kept(mesh.uv),
                   vertex_colors=kept(mesh.vertex_colors), shading=kept(mesh.shading))


def _joined_parts(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(vertices, faces, UVs) of a file's parts (one per material or per vt-less group) joined into one mesh.

    trimesh's own join packs the parts' materials into one atlas and rewrites every UV
    for it, so a texture given beside the file would be sampled at the wrong place. A
    part without UVs gets (0, 0); UVs are None when no part has any.
    """
    parts = [part for part in parts if len(getattr(part, "faces", ())) > 0]  # not an OBJ's lines or points
    if not parts:
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64), None
    sizes = [len(part.vertices) for part in parts]
    offsets = np.cumsum([0, *sizes[:-1]])
    uvs = [getattr(part.visual, "uv", None) for part in parts]
    uvs = [uv if uv is not None and len(uv) == size else None for uv, size in zip(uvs, sizes)]
    uv = None if all(u is None for u in uvs) else np.concatenate(
        [np.zeros((size, 2)) if u is None else np.asarray(u, dtype=np.float64) for u, size in zip(uvs, sizes)])
    return (np.concatenate([np.asarray(part.vertices, dtype=np.float64) for part in parts]),
            np.concatenate([np.asarray(part.faces, dtype=np.int64) + offset for part, offset in zip(parts, offsets)]),
            uv)


# -------------------------------------------------------------- shading
def _has_area(vertices: np.ndarray, faces: np.ndarray, tolerance: float, chunk: int = 1 << 16) -> bool:
    """Whether some triangle's area exceeds ``tolerance``, read a chunk of faces at a time (a real mesh answers
    from its first chunk, without a float64 copy of every corner)."""
    for start in range(0, len(faces), chunk):
        corners = vertices[faces[start:start + chunk]]
        doubled = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=-1)
        if doubled.max() > 2 * tolerance:
            return True
    return False


def shade_mesh(mesh: SurfaceMesh, mode: str = "auto", seed: int = 0) -> SurfaceMesh:
    """The mesh with the fixed shading baked in (see the module docstring), or as it is.

    ``mode``: "auto" (bake only when the mesh has neither texture nor vertex colours),
    "baked" or "none".

    Examples:
        >>> import trimesh
        >>> ball = trimesh.creation.icosphere(subdivisions=2)
        >>> shaded = shade_mesh(SurfaceMesh(np.asarray(ball.vertices), np.asarray(ball.faces)))
        >>> bool(shaded.shading.min() >= SHADING_AMBIENT - 0.05 and shaded.shading.max() > 0.95)
        True
    """
    if mode not in MESH_SHADING:
        raise MeshError(f"mesh_shading must be one of {', '.join(MESH_SHADING)}, got {mode!r}")
    if mode == "none" or (mode == "auto" and mesh.has_colour):
        return mesh
    occupancy, lo, voxel = _filled_occupancy(mesh)
    occupied = _occupancy_lookup(occupancy, lo, voxel)
    step = 2.0 * voxel
    normals = _outward(mesh.vertices, _vertex_normals(mesh), occupied, step)
    visibility = np.empty(len(mesh.vertices))
    directions = _cosine_directions(SHADING_AO_RAYS, seed)  # (K, 3) about +z
    distances = np.arange(0.0, SHADING_AO_REACH + 1e-9, voxel)
    origins = mesh.vertices + step * normals  # off the surface's own voxels, so grazing rays do not hit them
    for start in range(0, len(mesh.vertices), 4096):
        frame = _tangent_frames(normals[start:start + 4096])  # (B, 3, 3): columns t, b, n
        rays = np.einsum("bij,kj->bki", frame, directions)  # (B, K, 3)
        points = origins[start:start + 4096, None, None] + rays[:, :, None] * distances[None, None, :, None]
        visibility[start:start + 4096] = 1.0 - occupied(points).any(-1).mean(-1)
    light = np.asarray(SHADING_LIGHT) / np.linalg.norm(SHADING_LIGHT)
    direct = SHADING_AMBIENT + (1 - SHADING_AMBIENT) * np.clip(normals @ light, 0.0, None)
    return replace(mesh, shading=(visibility * direct).astype(np.float32))


def _filled_occupancy(mesh: SurfaceMesh) -> tuple[np.ndarray, np.ndarray, float]:
    """Boolean (R, R, R) occupancy of the surface and its interior over the mesh's box; (grid, its corner, voxel)."""
    import trimesh
    from scipy import ndimage

    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    voxel = float((hi - lo).max()) * 1.1 / SHADING_AO_RESOLUTION
    corner = (lo + hi) / 2 - voxel * SHADING_AO_RESOLUTION / 2
    tm = mesh.trimesh()
    count = int(np.clip(tm.area / voxel**2 * 8, 10_000, 2_000_000))
    samples, _ = trimesh.sample.sample_surface(tm, count, seed=0)
    index = np.clip(np.floor((np.concatenate([samples, mesh.vertices]) - corner) / voxel).astype(np.int64), 0,
                    SHADING_AO_RESOLUTION - 1)
    shell = np.zeros((SHADING_AO_RESOLUTION,) * 3, dtype=bool)
    shell[index[:, 0], index[:, 1], index[:, 2]] = True
    return ndimage.binary_fill_holes(shell), corner, voxel


def _occupancy_lookup(occupancy: np.ndarray, corner: np.ndarray, voxel: float | np.ndarray):
    """Whether points (..., 3) fall in an occupied cell of ``occupancy`` (cells of side ``voxel`` from ``corner``)."""

    def occupied(points: np.ndarray) -> np.ndarray:
        index = np.floor((points - corner) / voxel).astype(np.int64)
        inside_box = ((index >= 0) & (index < occupancy.shape)).all(-1)
        clipped = np.clip(index, 0, np.asarray(occupancy.shape) - 1)
        return inside_box & occupancy[clipped[..., 0], clipped[..., 1], clipped[..., 2]]

    return occupied


def _outward(points: np.ndarray, normals: np.ndarray, occupied, step: float) -> np.ndarray:
    """``normals`` at surface ``points``, those pointing into the filled volume flipped: a winding that is
    inconsistent or turned inside out must not decide what is inside."""
    inward = occupied(points + step * normals) & ~occupied(points - step * normals)
    return np.where(inward[:, None], -normals, normals)


def _vertex_normals(mesh: SurfaceMesh) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) from the faces' winding."""
    corners = mesh.vertices[mesh.faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # length: 2 x area
    normals = np.zeros_like(mesh.vertices)
    for k in range(3):
        np.add.at(normals, mesh.faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.where(length > 1e-20, normals / np.maximum(length, 1e-20), [0.0, 0.0, 1.0])


def _cosine_directions(count: int, seed: int) -> np.ndarray:
    """``count`` stratified cosine-weighted unit directions about +z (Malley's method)."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(count)))
    cells = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)[:count]
    u = (cells + rng.random(cells.shape)) / side
    radius, angle = np.sqrt(u[:, 0]), 2 * np.pi * u[:, 1]
    return np.stack([radius * np.cos(angle), radius * np.sin(angle), np.sqrt(1 - u[:, 0])], -1)


def _tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(B, 3, 3) rotations whose third column is each normal."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    tangent = np.cross(helper, normals)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return np.stack([tangent, np.cross(normals, tangent), normals], -1)


# -------------------------------------------------------------- rasteriser
def rasterize(mesh: SurfaceMesh, cameras: Cameras, index: int, supersample: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Unlit render of camera ``index``: (rgb on white (H, W, 3), coverage alpha (H, W)).

    A z-buffer over the (face, pixel-centre) pairs of each row of each face's
    screen box (that its span on the row reaches, ``_row_span``, for a face its
    box misses by many pixels a row: ``_SPANNED_MISSES_PER_ROW``), with
    perspective-correct barycentrics; ``supersample``² samples per pixel,
    box-filtered, anti-alias the silhouette. Faces reaching behind the
    camera are dropped (meshes sit in front of the orbiting cameras).
    """
    s = int(supersample)
    width, height = cameras.width * s, cameras.height * s
    c2w = cameras.c2w[index].double().numpy()
    fx, fy = float(cameras.fx[index]) * s, float(cameras.fy[index]) * s
    cx, cy = float(cameras.cx[index]) * s, float(cameras.cy[index]) * s
    local = (mesh.vertices - c2w[:3, 3]) @ c2w[:3, :3]  # camera coordinates, looking down -z
    w = -local[:, 2]
    screen = np.stack([cx + fx * local[:, 0] / np.maximum(w, 1e-12), cy - fy * local[:, 1] / np.maximum(w, 1e-12)], -1)
    tri = screen[mesh.faces]  # (F, 3, 2)
    in_front = (w[mesh.faces] > 1e-6).all(1)
    lo = np.clip(np.ceil(tri.min(1) - 0.5), 0, [width, height]).astype(np.int64)  # first pixel index whose centre is >= min
    hi = np.clip(np.floor(tri.max(1) - 0.5) + 1, 0, [width, height]).astype(np.int64)
    doubled_area = np.abs(_cross2(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    drawn = in_front & (doubled_area > _MIN_SCREEN_AREA)
    rows = np.where(drawn & (hi[:, 0] > lo[:, 0]), np.maximum(hi[:, 1] - lo[:, 1], 0), 0)
    # A row's span costs about as many products as a few pixels tested: where a face's box misses it by more pixels
    # a row (a thin face's) its rows are cut to their spans, a small or compact face's box is tested whole
    spanned = (hi[:, 0] - lo[:, 0]) * rows - doubled_area / 2 > _SPANNED_MISSES_PER_ROW * rows
    depth = np.full(width * height, np.inf)
    winner = np.full(width * height, -1, dtype=np.int64)
    bary_of = np.zeros((width * height, 3))

    def draw(face: np.ndarray, px: np.ndarray, py: np.ndarray) -> None:
        """Keep, per pixel, the nearest of these (face, pixel) candidates whose centre is inside its face."""
        p = np.stack([px + 0.5, py + 0.5], -1)
        a, b, c = tri[face, 0], tri[face, 1], tri[face, 2]
        area = _cross2(b - a, c - a)
        l1 = _cross2(c - b, p - b) / area
        l2 = _cross2(a - c, p - c) / area
        screen_bary = np.stack([l1, l2, 1.0 - l1 - l2], -1)
        inside = np.isfinite(screen_bary).all(1) & (screen_bary >= -_INSIDE_TOLERANCE).all(1)
        face, px, py, screen_bary = face[inside], px[inside], py[inside], screen_bary[inside]
        # Perspective-correct barycentrics and depth: 1/w interpolates linearly on screen.
        inv_w = screen_bary / w[mesh.faces[face]]
        z = 1.0 / inv_w.sum(1)
        bary = inv_w * z[:, None]
        pixel = py * width + px
        np.minimum.at(depth, pixel, z)
        nearest = z <= depth[pixel]
        winner[pixel[nearest]] = face[nearest]
        bary_of[pixel[nearest]] = bary[nearest]

    faces_with_rows = np.nonzero(rows)[0]
    for chunk in _chunks(faces_with_rows, rows[faces_with_rows]):  # each row of each face's screen box
        face = np.repeat(chunk, rows[chunk])
        py = lo[face, 1] + _offsets(rows[chunk])
        first, count = lo[face, 0], hi[face, 0] - lo[face, 0]
        if (cut := np.nonzero(spanned[face])[0]).size:
            first[cut], count[cut] = _row_span(tri[face[cut]], py[cut] + 0.5, first[cut], first[cut] + count[cut])
        segments = np.nonzero(count)[0]
        for segment in _chunks(segments, count[segments]):  # each candidate pixel of those rows
            repeat = partial(np.repeat, repeats=count[segment])
            draw(repeat(face[segment]), repeat(first[segment]) + _offsets(count[segment]), repeat(py[segment]))
    covered = winner >= 0
    rgb = np.ones((width * height, 3), dtype=np.float32)
    if covered.any():
        rgb[covered] = mesh.albedo(winner[covered], bary_of[covered])
    image = torch.from_numpy(rgb).reshape(height, width, 3)
    alpha = torch.from_numpy(covered.astype(np.float32)).reshape(height, width)
    if s > 1:
        image = F.avg_pool2d(image.permute(2, 0, 1)[None], s)[0].permute(1, 2, 0)
        alpha = F.avg_pool2d(alpha[None, None], s)[0, 0]
    return image.contiguous(), alpha.contiguous()


def _cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _chunks(items: np.ndarray, sizes: np.ndarray):
    """``items`` in runs in order, each holding at most ``_MAX_PAIRS`` of ``sizes`` in all (at least one item)."""
    start = 0
    while start < len(items):
        stop = start + max(1, int(np.searchsorted(np.cumsum(sizes[start:]), _MAX_PAIRS, side="right")))
        yield items[start:stop]
        start = stop


def _offsets(counts: np.ndarray) -> np.ndarray:
    """0, 1, ..., count - 1 for each of ``counts``, one after another."""
    return np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)


def _row_span(tri: np.ndarray, y: np.ndarray, lo_x: np.ndarray, hi_x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first column, count) of the pixels on the row of centres at ``y`` that may lie in each screen triangle
    ``tri`` (N, 3, 2), within its box's columns ``lo_x`` .. ``hi_x``: where its three barycentric coordinates, each
    linear along the row, pass ``rasterize``'s inside test, widened by a pixel either side against rounding (the
    test itself decides). A face's box alone had made a long sliver or a disc's wedge test every pixel of it: a
    4,096-face disc took 20 s a view."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = _cross2(b - a, c - a)
    slopes, intercepts = [], []
    for start, end in ((b, c), (c, a)):  # l1 and l2, as ``_cross2(end - start, p - start) / area``
        edge = end - start
        slopes.append(-edge[:, 1] / area)
        intercepts.append((edge[:, 0] * (y - start[:, 1]) + edge[:, 1] * start[:, 0]) / area)
    slopes.append(-slopes[0] - slopes[1])  # l3 = 1 - l1 - l2
    intercepts.append(1.0 - intercepts[0] - intercepts[1])
    x_from, x_to = np.full(len(y), -np.inf), np.full(len(y), np.inf)
    for slope, intercept in zip(slopes, intercepts):
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = (-_INSIDE_TOLERANCE - intercept) / slope
        x_from = np.where(slope > 0, np.maximum(x_from, bound), x_from)
        x_to = np.where(slope < 0, np.minimum(x_to, bound), x_to)
        x_to = np.where((slope == 0) & (intercept < -_INSIDE_TOLERANCE), -np.inf, x_to)  # the row misses it
    first = np.clip(np.ceil(x_from - 1.5), lo_x, hi_x)  # centres (column + 0.5) from a pixel before x_from ...
    end = np.clip(np.floor(x_to + 0.5) + 1, lo_x, hi_x)  # ... to a pixel after x_to
    return first.astype(np.int64), np.maximum(end - first, 0).astype(np.int64)


def hemisphere_cameras(n: int = 100, size: int = 200, seed: int = 0) -> Cameras:
    """``n`` NeRF-synthetic cameras on the upper hemisphere looking at the origin, the zenith angle uniform in
    0°–90° and the azimuth in 0°–360°: denser towards the pole than uniform over the hemisphere's area (kept so,
    as every mesh dataset and benchmark was rendered)."""
    generator = torch.Generator().manual_seed(seed)
    c2w, _, _ = random_hemisphere_poses(n, generator, min_zenith_deg=0.0, max_zenith_deg=90.0)
    return Cameras.from_fov(c2w, NERF_SYNTHETIC_FOV_X, size, size)


def render_mesh_views(mesh: SurfaceMesh, cameras: Cameras, supersample: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Route (a)'s input: every camera's unlit render, (N, H, W, 3) on white and alphas (N, H, W)."""
    views = [rasterize(mesh, cameras, i, supersample) for i in range(len(cameras))]
    return torch.stack([v[0] for v in views]), torch.stack([v[1] for v in views])


def write_mesh_dataset(
    mesh: SurfaceMesh, folder: str | os.PathLike, views: int = 100, size: int = 400, test_views: int = 20, seed: int = 0
) -> Path:
    """Route (a) as a dataset: a NeRF-synthetic folder of RGBA renders, so uploads of meshes flow like photos.

    ``transforms_train.json``: ``views`` upper-hemisphere cameras; ``transforms_test.json``:
    ``test_views`` on the 30° evaluation ring. PNGs store the un-premultiplied albedo.
    """
    from voxe_core.cameras import ring_poses
    from voxe_core.export import save_png

    folder = Path(folder)
    splits = {
        "train": hemisphere_cameras(views, size, seed),
        "test": Cameras.from_fov(ring_poses(test_views, 30.0), NERF_SYNTHETIC_FOV_X, size, size),
    }
    for split, cameras in splits.items():
        frames = []
        for i in range(len(cameras)):
            rgb, alpha = rasterize(mesh, cameras, i)
            colour = (rgb - (1.0 - alpha[..., None])) / alpha[..., None].clamp_min(1e-6)  # undo the white composite
            save_png(folder / split / f"r_{i:03d}.png", torch.cat([colour.clamp(0, 1), alpha[..., None]], -1))
            frames.append({"file_path": f"./{split}/r_{i:03d}", "transform_matrix": cameras.c2w[i].tolist()})
        meta = {"camera_angle_x": NERF_SYNTHETIC_FOV_X, "frames": frames}
        (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    return folder


# -------------------------------------------------------------- voxeliser
@dataclass
class VoxelizeConfig:
    resolution: int = 160
    bbox_min: tuple[float, float, float] = DEFAULT_BOX[0]
    bbox_max: tuple[float, float, float] = DEFAULT_BOX[1]
    surface_optical_depth: float = 20.0  # sigma·voxel one voxel inside the surface: opaque
    band_voxels: float = 2.0  # signed distance from the tangent plane within this band, inside/outside beyond
    samples_per_voxel_area: float = 16.0  # surface samples per voxel face of area: spacing ≈ voxel / 4
    seed: int = 0


def voxelize(mesh: SurfaceMesh, config: VoxelizeConfig = VoxelizeConfig()) -> VoxelGrid:
    """Route (b): the mesh written straight into a ReLU-field grid, no optimisation.

    Raw density is ``-sdf / voxel · r1`` clamped to ±3·r1, with r1 chosen so
    one voxel inside has optical depth ``surface_optical_depth`` per voxel:
    the zero crossing is the surface, exactly where trilinear interpolation
    and the ReLU put it. Near the surface (``band_voxels``) the signed
    distance is to the tangent plane of the nearest of dense surface samples
    (exact on flat patches); beyond it only inside/outside matters, taken
    from a hole fill (scipy) of the voxels the surface passes through, so
    meshes need to be closed up to a voxel. That filled volume also turns
    each face's normal outwards, so the winding (inverted, or mixed) does
    not matter. Colour: the albedo of the
    nearest surface sample as a logit (beyond the band, that of the nearest
    band vertex, so carving an edit into the interior shows the surface colour).
    Memory: about 45 bytes per grid vertex (the grid's own 16 among them) besides
    the surface samples, read a slab at a time: a 2.2 GiB peak at 320³.
    """
    import trimesh
    from scipy import ndimage
    from scipy.spatial import cKDTree

    grid = VoxelGrid(config.resolution, config.bbox_min, config.bbox_max)
    voxel = float(grid.voxel_size.min())
    r1 = config.surface_optical_depth / (grid.density_scale * voxel)
    tm = mesh.trimesh()
    count = int(np.clip(tm.area / voxel**2 * config.samples_per_voxel_area, 1000, 4_000_000))
    samples, face_index = trimesh.sample.sample_surface(tm, count, seed=config.seed)
    barycentric = trimesh.triangles.points_to_barycentric(tm.triangles[face_index], samples)
    albedo = mesh.albedo(face_index, np.clip(barycentric, 0.0, 1.0))

    # Vertices are read a slab of x rows at a time, so memory holds the grid and a few bytes per vertex (its
    # nearest sample, whether it is in the shell and filled), not every vertex's coordinates and distances.
    shape = grid.resolution
    axes = [np.linspace(lo, hi, n) for lo, hi, n in zip(config.bbox_min, config.bbox_max, shape)]
    rows = max(1, _SLAB_VERTICES // (shape[1] * shape[2]))
    slabs = [slice(start, start + rows) for start in range(0, shape[0], rows)]

    def vertices(slab: slice) -> np.ndarray:
        return np.stack(np.meshgrid(axes[0][slab], axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)

    tree = cKDTree(samples)
    nearest = np.empty(shape, dtype=np.int32)  # the nearest sample within the band; len(samples) beyond it
    shell = np.empty(shape, dtype=bool)  # vertices the surface passes near
    for slab in slabs:
        # Bounded queries: a k-d tree over a surface is slow to answer points far from it.
        distance, index = tree.query(vertices(slab), distance_upper_bound=config.band_voxels * voxel, workers=-1)
        nearest[slab] = index.reshape(nearest[slab].shape)
        shell[slab] = (distance <= voxel * np.sqrt(3) / 2).reshape(shell[slab].shape)
    band = nearest < len(samples)
    if not band.any():
        raise MeshError(f"the mesh lies outside the grid box {config.bbox_min}..{config.bbox_max}")
    filled = ndimage.binary_fill_holes(shell)
    # The faces' normals point out of the filled volume whatever their winding (a vertex's cell is centred on it).
    spacing = grid.voxel_size.double().numpy()
    occupied = _occupancy_lookup(filled, np.asarray(config.bbox_min) - spacing / 2, spacing)
    normals = _outward(tm.triangles_center, tm.face_normals, occupied, 2.0 * voxel)[face_index]
    # Beyond the band, the colour of the nearest band vertex (its nearest surface sample's albedo).
    source = ndimage.distance_transform_edt(~band, return_distances=False, return_indices=True)
    features = np.empty((*shape, 4), dtype=np.float32)
    for slab in slabs:
        density = np.where(filled[slab], 3 * r1, -3 * r1).reshape(-1)
        in_band = band[slab].reshape(-1)
        sample = nearest[slab].reshape(-1)[in_band]
        plane = np.einsum("nc,nc->n", vertices(slab)[in_band] - samples[sample], normals[sample])
        density[in_band] = np.clip(-plane / voxel * r1, -3 * r1, 3 * r1)
        features[slab, ..., 0] = density.reshape(features[slab, ..., 0].shape)
        colour = np.clip(albedo[nearest[tuple(source[:, slab])]], _COLOR_EPS, 1 - _COLOR_EPS)
        features[slab, ..., 1:] = np.log(colour / (1 - colour))
    return grid.like(torch.from_numpy(features))


# -------------------------------------------------------------- round trip
def chamfer_distance(a, b, samples: int = 100_000, seed: int = 0) -> float:
    """Symmetric Chamfer distance between two ``trimesh.Trimesh`` surfaces, in their units.

    The mean of nearest-neighbour distances from ``samples`` area-uniform
    points on each surface to the other's points, averaged over both ways.
    """
    import trimesh
    from scipy.spatial import cKDTree

    pa, _ = trimesh.sample.sample_surface(a, samples, seed=seed)
    pb, _ = trimesh.sample.sample_surface(b, samples, seed=seed + 1)
    ab, _ = cKDTree(pb).query(pa, workers=-1)
    ba, _ = cKDTree(pa).query(pb, workers=-1)
    return float((ab.mean() + ba.mean()) / 2)
