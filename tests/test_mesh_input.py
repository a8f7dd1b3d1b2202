"""Meshes as input: loading and normalisation, the z-buffer rasteriser, voxelisation and the mesh round trip."""

from __future__ import annotations

import json
import logging
import math
import re
import os
import warnings
from contextlib import ExitStack, contextmanager


import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from captures import DDS_OF_UNKNOWN_PIXEL_FORMAT
from conftest import DATA_ROOT
from voxe_core.cameras import Cameras, look_at
from voxe_core.data import DatasetError, load_scene
from voxe_core.export import extract_mesh
from voxe_core.metrics import psnr
from voxe_core import mesh_input
from voxe_core.mesh_input import (
    DEFAULT_ALBEDO, SHADING_AMBIENT, SHADING_LIGHT, VIEW_RADIUS, MeshError, SurfaceMesh, VoxelizeConfig,
    chamfer_distance, hemisphere_cameras, load_mesh, rasterize, render_mesh_views, sample_texture, shade_mesh, voxelize,
)
from voxe_core.ply_header import PROPERTY_TYPES, read_ply_header
from voxe_core.reconstruct import ReconstructConfig, reconstruct
from voxe_core.render import render_image

SPOT = DATA_ROOT / "meshes" / "spot"
HORSE = DATA_ROOT / "meshes" / "horse" / "horse.obj"
pytestmark = pytest.mark.usefixtures("single_thread")
RED, BLUE = (255, 0, 0, 255), (0, 0, 255, 255)


def _square(y: float, half: float, color) -> trimesh.Trimesh:
    """A square in the plane y = const, x and z in [-half, half], one colour."""
    v = np.array([[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]])
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], vertex_colors=np.tile(color, (4, 1)), process=False)


def _write_ply(path, *meshes) -> str:
    trimesh.util.concatenate(meshes).export(path)
    return str(path)


def _camera_on_minus_y(size: int = 64, distance: float = 4.0) -> Cameras:
    return Cameras.from_fov(look_at(torch.tensor([[0.0, -distance, 0.0]])), 0.6911112070083618, size, size)


# ------------------------------------------------------------------ rasteriser
def test_square_covers_its_projected_area_in_its_vertex_colour(tmp_path):
    degenerate = trimesh.Trimesh([[0, 0, 0], [0, 0, 0], [0.1, 0, 0]], [[0, 1, 2]], process=False)
    mesh = load_mesh(_write_ply(tmp_path / "square.ply", _square(0.0, 1.0, RED), degenerate), up_axis="z")
    cameras = _camera_on_minus_y()
    rgb, alpha = rasterize(mesh, cameras, 0, supersample=4)
    half = VIEW_RADIUS / np.sqrt(2)  # loaded with its corners at VIEW_RADIUS
    side = 2 * float(cameras.fx[0]) * half / 4.0  # pixels spanned by the square at distance 4
    assert float(alpha.sum()) == pytest.approx(side**2, abs=side / 2)  # each edge within half a subsample (1/8 px)
    assert torch.isfinite(rgb).all()
    assert torch.equal(rgb[32, 32], torch.tensor([1.0, 0.0, 0.0])) and torch.equal(rgb[0, 0], torch.ones(3))


@pytest.mark.parametrize("near_first", [True, False])
def test_the_nearer_surface_wins_whatever_the_face_order(tmp_path, near_first):
    near, far = _square(-0.5, 0.5, RED), _square(0.5, 1.0, BLUE)
    mesh = load_mesh(_write_ply(tmp_path / "two.ply", *((near, far) if near_first else (far, near))), up_axis="z")
    cameras = _camera_on_minus_y()
    rgb, _ = rasterize(mesh, cameras, 0)
    # loaded at 0.86 (far corners at VIEW_RADIUS): the far square's half-width 0.86 at distance 4.43 -> 17.3 px;
    # the near one's 0.43 at 3.57 -> 10.8 px
    assert torch.allclose(rgb[32, 32], torch.tensor([1.0, 0.0, 0.0]))
    assert torch.allclose(rgb[32, 32 + 14], torch.tensor([0.0, 0.0, 1.0]))


def test_obj_texture_is_mapped_upright_with_v_up(tmp_path):
    texel = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 255]]], dtype=np.uint8)  # row 0 on top
    Image.fromarray(texel).save(tmp_path / "tex.png")
    (tmp_path / "quad.obj").write_text(
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    )
    mesh = load_mesh(tmp_path / "quad.obj", tmp_path / "tex.png")  # y up: the quad faces +x, its +x is +y
    cameras = Cameras.from_fov(look_at(torch.tensor([[4.0, 0.0, 0.0]])), 0.6911112070083618, 64, 64)
    rgb, _ = rasterize(mesh, cameras, 0)
    assert torch.allclose(rgb[20, 20], torch.tensor([1.0, 0.0, 0.0]))  # top left
    assert torch.allclose(rgb[20, 44], torch.tensor([0.0, 1.0, 0.0]))  # top right
    assert torch.allclose(rgb[44, 20], torch.tensor([0.0, 0.0, 1.0]))  # bottom left
    # bilinear between texel centres, wrapping in u and v outside [0, 1]: 1 is the right border (it had wrapped to 0)
    mid = sample_texture(texel / 255.0, np.array([[0.5, 0.75], [1.25, 0.75], [1.0, 0.75], [0.0, 1.0], [-0.75, 0.75]]))
    assert np.allclose(mid, [[0.5, 0.5, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])


def test_a_given_texture_is_sampled_at_the_files_own_uvs_whatever_its_materials(tmp_path):
    """Two materials (one textured, one a flat Kd) and a group without vt: trimesh's join packs the materials into
    an atlas and rewrites every UV for it; the texture given is sampled at the file's UVs, (0, 0) where it has none."""
    texel = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 255]]], dtype=np.uint8)  # row 0 on top
    Image.fromarray(texel).save(tmp_path / "tex.png")
    (tmp_path / "mix.mtl").write_text("newmtl skin\nKd 1 1 1\nmap_Kd tex.png\nnewmtl paint\nKd 1 1 0\n")
    (tmp_path / "mix.obj").write_text(
        "mtllib mix.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 0 1 1\nv 0 0 2\nv 1 0 2\nv 0 1 2\n"
        "vt 0.25 0.75\nvt 0.75 0.75\n"
        "usemtl skin\nf 1/1 2/1 3/1\nf 4/2 5/2 6/2\nusemtl paint\nf 7 8 9\n")  # at heights 0, 1, 2: red, green, none
    mesh = load_mesh(tmp_path / "mix.obj", tmp_path / "tex.png", up_axis="z")
    centres = mesh.vertices[mesh.faces].mean(1)
    albedo = mesh.albedo(np.arange(len(mesh.faces)), np.full((len(mesh.faces), 3), 1 / 3))[np.argsort(centres[:, 2])]
    assert np.allclose(albedo, [[1, 0, 0], [0, 1, 0], sample_texture(texel / 255.0, np.zeros((1, 2)))[0]])


CUBE_OBJ = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\nusemtl red\n"
            "f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\n"
            "f 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8\n")


def test_an_obj_whose_one_material_writes_a_kd_loads_in_that_colour(tmp_path):
    """trimesh makes no atlas for a single material without an image: a cube the .mtl paints red had loaded grey.
    Without a library, or with a material that writes no Kd, the mesh keeps the default albedo. One colour is no
    shape cue: "auto" shading bakes light and occlusion into either."""
    (tmp_path / "red.mtl").write_text("newmtl red\nKd 0.8 0.1 0.1\n")
    (tmp_path / "red.obj").write_text("mtllib red.mtl\n" + CUBE_OBJ)
    red = load_mesh(tmp_path / "red.obj")
    assert not red.has_colour and np.allclose(red.colour, [0.8, 0.1, 0.1], atol=1 / 255)
    faces = np.arange(len(red.faces))
    centres = np.full((len(faces), 3), 1 / 3)
    assert np.allclose(red.albedo(faces, centres), [0.8, 0.1, 0.1], atol=1 / 255)
    shaded = shade_mesh(red)
    assert shaded.shading is not None and np.allclose(shaded.colour, red.colour)
    lit = shaded.albedo(faces, centres)  # the red, darkened by the bake where the light does not fall
    assert np.allclose(lit / lit[:, :1], [1.0, 0.1 / 0.8, 0.1 / 0.8], atol=0.02) and lit[:, 0].min() < 0.8
    (tmp_path / "plain.obj").write_text(CUBE_OBJ)
    (tmp_path / "shiny.mtl").write_text("newmtl red\nNs 10\n")
    (tmp_path / "shiny.obj").write_text("mtllib shiny.mtl\n" + CUBE_OBJ)
    for name in ("plain.obj", "shiny.obj"):
        grey = load_mesh(tmp_path / name)
        assert not grey.has_colour, name
        assert np.allclose(grey.albedo(faces, np.full((len(faces), 3), 1 / 3)), DEFAULT_ALBEDO)
        assert shade_mesh(grey).shading is not None



def test_a_one_value_kd_is_a_grey_and_keeps_the_librarys_materials(tmp_path):
    """``Kd 0.5`` is (0.5, 0.5, 0.5) by the MTL spec: trimesh had dropped every material of the library for it (or
    for a one-value Ks), the cube loading in the default grey, a map_Kd beside it lost; ``Kd 0`` had loaded in
    trimesh's grey, not black. A Kd of two values, a word or NaN is refused naming the .mtl's line."""
    (tmp_path / "cube.obj").write_text("mtllib cube.mtl\n" + CUBE_OBJ)
    for kd, colour in (("Kd 0.5", 0.5), ("Kd 0", 0.0), ("Kd 0.25\nKs 0.5", 0.25)):
        (tmp_path / "cube.mtl").write_text(f"newmtl red\n{kd}\n")
        assert np.allclose(load_mesh(tmp_path / "cube.obj").colour, [colour] * 3, atol=1 / 255), kd
    Image.fromarray(np.full((2, 2, 3), [0, 0, 255], dtype=np.uint8)).save(tmp_path / "tex.png")
    (tmp_path / "skin.mtl").write_text("newmtl skin\nKd 1\nKs 0.5\nmap_Kd tex.png\nnewmtl grey\nKd 0.5\n")
    (tmp_path / "skin.obj").write_text("mtllib skin.mtl\nusemtl skin\n" + QUAD_WITH_UVS)
    textured = load_mesh(tmp_path / "skin.obj")
    assert textured.has_colour and np.allclose(textured.albedo(np.array([0]), np.full((1, 3), 1 / 3)), [0, 0, 1])
    for kd in ("Kd 0.5 0.2", "Kd spectral red.rfl", "Kd nan"):
        (tmp_path / "cube.mtl").write_text(f"newmtl red\nNs 10\n{kd}\n")
        with pytest.raises(MeshError, match=rf"^cube.mtl line 3: '{kd}': Kd must be one finite number \(a grey "
                                            r"level\) or three \(r g b\)$"):
            load_mesh(tmp_path / "cube.obj")

    for kd, colour in (("Kd\nKd 1 0 0", [1, 0, 0]), ("Kd 0 1 0 # green", [0, 1, 0]), ("Kd 0.5 # grey", [0.5] * 3)):
        (tmp_path / "cube.mtl").write_text(f"newmtl red\n{kd}\n")  # a bare Kd skipped, as trimesh skips it; a
        assert np.allclose(load_mesh(tmp_path / "cube.obj").colour, colour, atol=1 / 255), kd  # comment left out


def test_a_mesh_or_texture_that_is_not_a_readable_file_is_a_mesh_error_naming_it(tmp_path):
    """trimesh had said "string is not a file: `<the full path>`" of a mesh not there or a folder (its file lookup,
    in a folder not there, "not a directory!"), Pillow "[Errno 2] No such file or directory: '<the full path>'" of
    a texture, and an empty PLY was "Not a ply file!"."""
    (tmp_path / "cube.obj").write_text(CUBE_WITH_UVS)
    (tmp_path / "folder.obj").mkdir()
    (tmp_path / "empty.ply").write_bytes(b"")
    (tmp_path / "empty.png").write_bytes(b"")
    for mesh, texture, message in ((tmp_path / "gone" / "cube.obj", None, "cube.obj: no such file"),
                                   (tmp_path / "missing.ply", None, "missing.ply: no such file"),
                                   (tmp_path / "folder.obj", None, "folder.obj: is a folder, not a mesh file"),
                                   (tmp_path / "empty.ply", None, "empty.ply: the file is empty"),
                                   (tmp_path / "cube.obj", tmp_path / "gone.png", "gone.png: no such file"),
                                   (tmp_path / "cube.obj", tmp_path, f"{tmp_path.name}: is a folder, not an image"),
                                   (tmp_path / "cube.obj", tmp_path / "empty.png", "empty.png: the file is empty")):
        with pytest.raises(MeshError) as error:
            load_mesh(mesh, texture)
        assert str(error.value) == message
    (tmp_path / "cube.obj").chmod(0)
    if not os.access(tmp_path / "cube.obj", os.R_OK):  # (root reads it all the same)
        with pytest.raises(MeshError, match=r"^cube.obj: cannot be read: permission denied$"):
            load_mesh(tmp_path / "cube.obj")


CUBE_WITH_UVS = "vt 0.5 0.5\n" + "".join(
    "f " + " ".join(f"{corner}/1" for corner in line.split()[1:]) + "\n" if line.startswith("f ") else line + "\n"
    for line in CUBE_OBJ.splitlines())


def _texcoord_ply(header_comment: str = "") -> str:
    """A tetrahedron's PLY with per-face texture coordinates (texcoord), ``header_comment`` in its header."""
    return ("ply\nformat ascii 1.0\n" + header_comment + "element vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 4\nproperty list uchar int vertex_indices\n"
            "property list uchar float texcoord\nend_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
            + "".join(f"3 {face} 6 0.5 0.5 0.5 0.5 0.5 0.5\n" for face in ("0 2 1", "0 1 3", "0 3 2", "1 2 3")))


@pytest.mark.filterwarnings("ignore:lost.ply. the texture its header names:UserWarning")  # (their own tests below)
@pytest.mark.filterwarnings("ignore:lost.obj. the material library its mtllib names:UserWarning")
def test_uvs_without_a_material_the_file_gives_load_uncoloured(tmp_path):
    """Texture coordinates without a material the file gives (no mtllib, its .mtl missing, a usemtl the library
    does not define; a PLY's texcoord without its TextureFile) had loaded as a 2×2 texture of trimesh's stand-in grey
    (0.39): "coloured", so "auto" shading left the mesh a flat silhouette. Now it is uncoloured, as without vt, even
    where the library defines trimesh's name for its stand-in (material_0). Spot's OBJ without its texture is the
    real case (it has no mtllib)."""
    (tmp_path / "other.mtl").write_text("newmtl material_0\nKd 1 0 0\n")
    (tmp_path / "plain.obj").write_text(CUBE_WITH_UVS)
    (tmp_path / "lost.obj").write_text("mtllib lost.mtl\n" + CUBE_WITH_UVS)
    (tmp_path / "undefined.obj").write_text("mtllib other.mtl\n" + CUBE_WITH_UVS)  # its usemtl red: not defined
    (tmp_path / "bare.ply").write_text(_texcoord_ply())
    (tmp_path / "lost.ply").write_text(_texcoord_ply("comment TextureFile lost.png\n"))
    meshes = {name: load_mesh(tmp_path / name) for name in ("plain.obj", "lost.obj", "undefined.obj", "bare.ply",
                                                            "lost.ply")}
    meshes["spot"] = load_mesh(SPOT / "spot_triangulated.obj")
    for name, mesh in meshes.items():
        assert mesh.texture is None and mesh.uv is None and mesh.colour is None and not mesh.has_colour, name
        faces = np.arange(len(mesh.faces))
        assert np.allclose(mesh.albedo(faces, np.full((len(faces), 3), 1 / 3)), DEFAULT_ALBEDO), name
        assert shade_mesh(mesh).shading is not None, name


_COLOURED_PLY = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 "{vertex}element face 1\nproperty list uchar int vertex_indices\n{face}end_header\n"
                 "0 0 0{v0}\n1 0 0{v1}\n0 1 0{v1}\n3 0 1 2{f}\n")
_FLOAT_RGB = "property float red\nproperty float green\nproperty float blue\n"


@pytest.mark.parametrize("name, text, message", [
    ("nan.obj", "v 0 0 0 nan 0.5 0.5\nv 1 0 0 1 0 0\nv 0 1 0 0 1 0\nf 1 2 3\n",
     "nan.obj: line 1, 'v 0 0 0 nan 0.5 0.5': its vertex colour 'nan 0.5 0.5' is not finite (NaN or Inf), which the "
     "loader would read as black"),
    ("inf.obj", "v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 -inf\nf 1 2 3\n",
     "inf.obj: line 3, 'v 0 1 0 0 0 -inf': its vertex colour '0 0 -inf' is not finite"),
    ("vertex.ply", _COLOURED_PLY.format(vertex=_FLOAT_RGB, face="", v0=" 0.5 nan 0.5", v1=" 1 0 0", f=""),
     "vertex.ply: its vertex colours (green) contain NaN or Inf, which the loader would read as black"),
    ("face.ply", _COLOURED_PLY.format(vertex="", face=_FLOAT_RGB, v0="", v1="", f=" nan 0 0"),
     "face.ply: its face colours (red) contain NaN or Inf, which the loader would read as black"),
])
def test_a_colour_that_is_nan_or_inf_is_refused_naming_it(tmp_path, name, text, message):
    """Regression: a NaN vertex (or face) colour had loaded as black without a word."""
    (tmp_path / name).write_text(text)
    with pytest.raises(MeshError) as err:
        load_mesh(tmp_path / name)
    assert str(err.value).startswith(message)
    (tmp_path / name).write_text(re.sub(r"-?(nan|inf)", "0.25", text))  # a finite colour loads
    assert load_mesh(tmp_path / name).has_colour


def test_a_ply_of_triangle_strips_is_refused_saying_so(tmp_path):
    """Regression: a PLY whose faces are a 'tristrips' element (as VCG and some scanners write them) was refused as
    "no triangles in the file", and beside a face element its strips were dropped without a word. An empty
    tristrips element is nothing lost."""
    head = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    points, strips = "0 0 0\n1 0 0\n0 1 0\n1 1 0\n", "element tristrips {}\nproperty list int int vertex_indices\n"
    faces = "element face 1\nproperty list uchar int vertex_indices\n"
    (tmp_path / "strips.ply").write_text(head + strips.format(1) + "end_header\n" + points + "4 0 1 2 3\n")
    (tmp_path / "both.ply").write_text(head + faces + strips.format(1) + "end_header\n" + points + "3 0 1 2\n"
                                       "3 1 3 2\n")
    for name in ("strips.ply", "both.ply"):
        with pytest.raises(MeshError, match=rf"^{name}: its faces are stored as triangle strips \(a 'tristrips' "
                                            r"element\), which are not read: save the mesh with a 'face' element"):
            load_mesh(tmp_path / name)
    (tmp_path / "none.ply").write_text(head + faces + strips.format(0) + "end_header\n" + points + "3 0 1 2\n")
    assert len(load_mesh(tmp_path / "none.ply").faces) == 1


def test_an_obj_whose_material_library_is_missing_warns_naming_it(tmp_path):
    """Regression: an OBJ whose mtllib names a file not beside it (an upload's .mtl under another name) loaded grey
    without a word; a library found (by its base name, in any case) gives no warning."""
    (tmp_path / "Model_v2.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "lost.obj").write_text("mtllib model.mtl\n" + CUBE_OBJ)
    with pytest.warns(UserWarning) as caught:
        mesh = load_mesh(tmp_path / "lost.obj")
    assert [str(warning.message) for warning in caught] == [
        "lost.obj: the material library its mtllib names, 'model.mtl', is not found beside it; the mesh loads "
        "without its materials"]
    assert not mesh.has_colour and mesh.colour is None
    (tmp_path / "found.obj").write_text("mtllib C:\\exports\\MODEL_V2.MTL\n" + CUBE_OBJ)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.allclose(load_mesh(tmp_path / "found.obj").colour, (1, 0, 0))


def test_a_ply_whose_texture_file_is_missing_warns_once_naming_it(tmp_path, caplog):
    """trimesh had logged "unable to load image!" with a FileNotFoundError's traceback, read as a failure in a
    worker's log (a PLY upload's TextureFile is never stored) though the mesh loads, without its texture."""
    (tmp_path / "lost.ply").write_text(_texcoord_ply("comment TextureFile lost.png\n"))
    filters = list(trimesh.util.log.filters)
    with pytest.warns(UserWarning) as caught:
        mesh = load_mesh(tmp_path / "lost.ply")
    assert [str(warning.message) for warning in caught] == [
        "lost.ply: the texture its header names (TextureFile) cannot be read (FileNotFoundError: lost.png); the mesh "
        "loads without it"]
    assert not mesh.has_colour and not [record for record in caplog.records if record.levelno >= logging.WARNING]
    assert trimesh.util.log.filters == filters


def test_vertex_colours_beside_uvs_without_a_material_are_kept(tmp_path):
    """A file's vertex colours (an OBJ's ``v x y z r g b``, a PLY's red/green/blue) beside texture coordinates that
    no material colours are the mesh's colour: they had been lost with trimesh's stand-in texture."""
    (tmp_path / "coloured.obj").write_text("".join(
        line + " 1 0 0\n" if line.startswith("v ") else line + "\n" for line in CUBE_WITH_UVS.splitlines()))
    (tmp_path / "coloured.ply").write_text(
        _texcoord_ply().replace("property float z\n", "property float z\nproperty uchar red\nproperty uchar green\n"
                                "property uchar blue\n").replace("0 0 0\n1 0 0\n0 1 0\n0 0 1\n",
                                                                  "0 0 0 0 255 0\n1 0 0 0 255 0\n0 1 0 0 255 0\n"
                                                                  "0 0 1 0 255 0\n"))
    for name, colour in (("coloured.obj", [1, 0, 0]), ("coloured.ply", [0, 1, 0])):
        mesh = load_mesh(tmp_path / name)
        assert mesh.has_colour and mesh.texture is None, name
        faces = np.arange(len(mesh.faces))
        assert np.allclose(mesh.albedo(faces, np.full((len(faces), 3), 1 / 3)), colour, atol=1 / 255), name


def test_materials_the_file_wrote_keep_their_colours_by_kd_or_by_image(tmp_path):
    """Two materials by their Kd alone, two by their images (trimesh packs either into one atlas), and a PLY's
    TextureFile: each part keeps its own colour, a texture that "auto" shading leaves as it is."""
    two_parts = ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 0 1 1\nvt 0.25 0.25\nvt 0.75 0.75\n"
                 "usemtl first\nf 1/1 2/1 3/1\nusemtl second\nf 4/2 5/2 6/2\n")  # at heights 0 and 1
    for colour, name in (((255, 0, 0), "red.png"), ((0, 0, 255), "blue.png"), ((0, 255, 0), "green.png")):
        Image.fromarray(np.full((4, 4, 3), colour, dtype=np.uint8)).save(tmp_path / name)
    (tmp_path / "kd.mtl").write_text("newmtl first\nKd 1 0 0\nnewmtl second\nKd 0 0 1\n")
    (tmp_path / "images.mtl").write_text("newmtl first\nmap_Kd red.png\nnewmtl second\nmap_Kd blue.png\n")
    for library in ("kd.mtl", "images.mtl"):
        (tmp_path / "parts.obj").write_text(f"mtllib {library}\n" + two_parts)
        mesh = load_mesh(tmp_path / "parts.obj", up_axis="z")
        assert mesh.texture is not None and shade_mesh(mesh) is mesh, library
        order = np.argsort(mesh.vertices[mesh.faces].mean(1)[:, 2])
        assert np.allclose(mesh.albedo(order, np.full((2, 3), 1 / 3)), [[1, 0, 0], [0, 0, 1]], atol=1e-6), library
    (tmp_path / "green.ply").write_text(_texcoord_ply("comment TextureFile green.png\n"))
    green = load_mesh(tmp_path / "green.ply")
    assert green.has_colour and np.allclose(green.albedo(np.arange(4), np.full((4, 3), 1 / 3)), [0, 1, 0], atol=0.01)


def test_materials_sharing_one_image_share_its_block_in_the_atlas(tmp_path):
    """Exporters give each material its own copy of one image: each had been given a block, the atlas growing by the
    image at every material (64 materials of a 1024² image: 771 MiB, 20 s to load). Blocks are shared by pixels, so
    16 materials naming one 8×8 image and 2 Kd-only ones of one colour make an atlas of two blocks, read exactly."""
    texel = np.random.default_rng(1).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    Image.fromarray(texel).save(tmp_path / "tex.png")
    names = [f"m{k}" for k in range(16)]
    (tmp_path / "shared.mtl").write_text("".join(f"newmtl {n}\nmap_Kd tex.png\n" for n in names)
                                         + "newmtl red\nKd 1 0 0\nnewmtl red2\nKd 1 0 0\n")
    body = "".join(f"v 0 0 {z}\nv 1 0 {z}\nv 0 1 {z}\n" for z in range(18)) + "vt 0.3 0.6\n"
    body += "".join(f"usemtl {n}\nf {3 * z + 1}/1 {3 * z + 2}/1 {3 * z + 3}/1\n"
                    for z, n in enumerate(names + ["red", "red2"]))
    (tmp_path / "shared.obj").write_text("mtllib shared.mtl\n" + body)
    mesh = load_mesh(tmp_path / "shared.obj", up_axis="z")
    assert mesh.texture.shape == (8 + 2, (8 + 2) + (1 + 2), 3)
    order = np.argsort(mesh.vertices[mesh.faces].mean(1)[:, 2])
    albedo = mesh.albedo(order, np.full((18, 3), 1 / 3))
    expected = sample_texture(texel.astype(np.float32) / 255, np.array([[0.3, 0.6]]))
    assert np.allclose(albedo[:16], expected, atol=1e-6) and np.allclose(albedo[16:], [1, 0, 0], atol=1e-6)
    for colour in ("red", "blue"):  # palette images of the same indices (all 0), different palettes: two blocks
        indexed = Image.new("P", (4, 4), 0)
        indexed.putpalette([255, 0, 0] if colour == "red" else [0, 0, 255])
        indexed.save(tmp_path / f"{colour}8.png")
    (tmp_path / "swapped.mtl").write_text("newmtl a\nmap_Kd red8.png\nnewmtl b\nmap_Kd blue8.png\n")
    (tmp_path / "swapped.obj").write_text("mtllib swapped.mtl\n" + "".join(
        f"v 0 0 {z}\nv 1 0 {z}\nv 0 1 {z}\n" for z in range(2)) + "vt 0.5 0.5\nusemtl a\nf 1/1 2/1 3/1\nusemtl b\n"
        "f 4/1 5/1 6/1\n")
    mesh = load_mesh(tmp_path / "swapped.obj", up_axis="z")
    order = np.argsort(mesh.vertices[mesh.faces].mean(1)[:, 2])
    assert np.allclose(mesh.albedo(order, np.full((2, 3), 1 / 3)), [[1, 0, 0], [0, 0, 1]], atol=1e-6)


def test_colour_only_materials_are_their_kd_at_any_uv_and_beside_a_texture_it_is_sampled_as_alone(tmp_path):
    """trimesh's atlas is read by its own texel convention, its blocks padded in black and at times placed past its
    edge: a Kd-only face whose vt lay near its 2×2 block's border had loaded 0.81 red, or black beside a map_Kd
    image, and the image's texels shifted. Each Kd is now its faces' colour wherever their vt lie (none at all
    included), and an image sampled in the atlas reads what it reads alone."""
    texel = np.random.default_rng(0).integers(0, 256, (4, 4, 3), dtype=np.uint8)
    Image.fromarray(texel).save(tmp_path / "tex.png")
    (tmp_path / "paints.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl green\nKd 0 1 0\nnewmtl blue\nKd 0 0 1\n"
                                         "newmtl skin\nmap_Kd tex.png\n")
    corners = [(0, 0), (1, 1), (0.25, 0.25), (1, 0), (0.05, 0.95), (0.75, 0.5)]
    head = ("mtllib paints.mtl\n" + "".join(f"v 0 0 {z}\nv 1 0 {z}\nv 0 1 {z}\n" for z in range(4))
            + "".join(f"vt {u} {v}\n" for u, v in corners))
    red = "usemtl red\nf 1/1 2/2 3/4\n"  # at height 0
    (tmp_path / "paints.obj").write_text(head + red + "usemtl green\nf 4/3 5/2 6/1\nusemtl blue\nf 7 8 9\n")  # 1, 2
    (tmp_path / "mixed.obj").write_text(head + "usemtl skin\nf 10/1 11/5 12/6\n" + red)  # the image's face at 3
    for name, colours in (("paints.obj", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]), ("mixed.obj", [[1, 0, 0]])):
        mesh = load_mesh(tmp_path / name, up_axis="z")
        order = np.argsort(mesh.vertices[mesh.faces].mean(1)[:, 2])
        for face, colour in zip(order, colours):
            for corner in np.eye(3):  # at each of its vertices, whose vt reach the block's border
                assert np.allclose(mesh.albedo(np.array([face]), corner[None]), colour, atol=1e-6), (name, face)
    skin = np.array([order[-1]] * 3)
    assert np.allclose(mesh.albedo(skin, np.eye(3)), sample_texture(texel / 255.0, np.array(corners)[[0, 4, 5]]),
                       atol=1e-6)


def test_parts_without_a_colour_beside_coloured_ones_are_the_default_albedo_or_their_vertex_colours(tmp_path):
    """Faces before any usemtl, under a usemtl the library does not define (with vt: trimesh's stand-in texture) or
    under a material with neither Kd nor image, in a file whose other faces a Kd colours, had been trimesh's grey
    (0.39 or 0.4), not the ``DEFAULT_ALBEDO`` an uncoloured mesh (or a lone such material) loads in; where the
    file gives their vertices colours (``v x y z r g b``), those, which only the faces before any usemtl had kept."""
    (tmp_path / "parts.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl shiny\nNs 10\n")
    body = ("vt 0 0\nvt 1 0\nvt 0 1\nf 4 5 6\nusemtl red\nf 1/1 2/2 3/3\nusemtl nowhere\nf 7/1 8/2 9/3\n"
            "usemtl shiny\nf 10 11 12\n")  # red at height 0, the others at 1, 2 and 3
    for name, rgb, colour in (("plain.obj", "", DEFAULT_ALBEDO), ("blue.obj", " 0 0 1", (0, 0, 1))):
        (tmp_path / name).write_text("mtllib parts.mtl\n" + "".join(
            f"v 0 0 {z}{rgb}\nv 1 0 {z}{rgb}\nv 0 1 {z}{rgb}\n" for z in range(4)) + body)
        mesh = load_mesh(tmp_path / name, up_axis="z")
        order = np.argsort(mesh.vertices[mesh.faces].mean(1)[:, 2])
        assert np.allclose(mesh.albedo(order, np.full((4, 3), 1 / 3)), [(1, 0, 0), colour, colour, colour],
                           atol=1e-6), name


def test_nan_texture_coordinates_are_refused(tmp_path):
    """A NaN vt had loaded and sampled the texture at NaN: given beside the file or named by its .mtl. An .mtl's
    image on a mesh without vt is refused by name."""
    Image.fromarray(np.full((2, 2, 3), 200, dtype=np.uint8)).save(tmp_path / "tex.png")
    (tmp_path / "tex.mtl").write_text("newmtl skin\nmap_Kd tex.png\n")
    quad = "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nvt nan 0\nvt 1 0\nvt 1 1\nusemtl skin\nf 1/1 2/2 3/3\n"
    (tmp_path / "given.obj").write_text(quad)
    (tmp_path / "named.obj").write_text("mtllib tex.mtl\n" + quad)
    with pytest.raises(MeshError, match=r"given.obj: texture coordinates \(vt\) contain NaN or Inf"):
        load_mesh(tmp_path / "given.obj", tmp_path / "tex.png")
    with pytest.raises(MeshError, match=r"named.obj: texture coordinates \(vt\) contain NaN or Inf"):
        load_mesh(tmp_path / "named.obj")
    (tmp_path / "unplaced.obj").write_text("mtllib tex.mtl\nv -1 -1 0\nv 1 -1 0\nv 1 1 0\nusemtl skin\nf 1 2 3\n")
    (tmp_path / "beside.obj").write_text("mtllib tex.mtl\nv -1 -1 0\nv 1 -1 0\nv 1 1 0\nvt 0 0\nf 1/1 2/1 3/1\n"
                                         "usemtl skin\nf 1 2 3\n")  # beside a part with vt: it had loaded the image's centre
    for name in ("unplaced.obj", "beside.obj"):
        with pytest.raises(MeshError, match=rf"^{name}: its .mtl's map_Kd names an image but material 'skin' has no "
                                            r"texture coordinates \(vt\) to place it$"):  # had been refused as NaN vt
            load_mesh(tmp_path / name)


QUAD_WITH_UVS = "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3\n"


def _as_capture(folder, image_name: str):
    """The folder as a one-frame NeRF-synthetic capture of ``image_name``, loaded (``data.load_scene``)."""
    frame = {"file_path": f"./{image_name}", "transform_matrix": np.eye(4).tolist()}
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": [frame]}))
    return load_scene(folder, "train")


def test_a_16_bit_greyscale_texture_keeps_its_values_as_a_capture_does(tmp_path):
    """convert("RGB") clips 16-bit greyscale to white: mid grey had loaded as 1.0."""
    grey = np.array([[0.0, 0.25], [0.5, 1.0]])
    Image.fromarray((grey * 65535).astype(np.uint16)).save(tmp_path / "grey.png")
    assert Image.open(tmp_path / "grey.png").mode == "I;16"
    (tmp_path / "quad.obj").write_text(QUAD_WITH_UVS)
    texture = load_mesh(tmp_path / "quad.obj", tmp_path / "grey.png").texture
    assert np.allclose(texture, np.repeat(grey[..., None], 3, -1), atol=1 / 65535)
    assert np.array_equal(texture, _as_capture(tmp_path, "grey.png").images[0].numpy())


@pytest.mark.parametrize("image, reason", [
    (Image.fromarray(np.full((2, 2), 0.5, np.float32), "F"),
     r"holds floating-point pixels \(Pillow mode F\), whose scale the file does not record"),
    (Image.fromarray(np.full((2, 2), 70000, np.int32), "I"),
     r"holds 32-bit values from 70000 to 70000 \(Pillow mode I\); only 8- and 16-bit images"),
])
def test_textures_refuse_pixels_of_unrecorded_scale_as_captures_do(tmp_path, image, reason):
    """One rule for both (data.image_pixels): a float texture had been taken as 0..1 and a 32-bit one clipped to
    white, where the same image as a capture is refused."""
    image.save(tmp_path / "odd.tif")
    (tmp_path / "quad.obj").write_text(QUAD_WITH_UVS)
    (tmp_path / "odd.mtl").write_text("newmtl skin\nmap_Kd odd.tif\n")
    (tmp_path / "named.obj").write_text("mtllib odd.mtl\nusemtl skin\n" + QUAD_WITH_UVS)
    with pytest.raises(MeshError, match=rf"^odd.tif: the texture image {reason}"):
        load_mesh(tmp_path / "quad.obj", tmp_path / "odd.tif")
    with pytest.raises(MeshError, match=rf"^named.obj \(its .mtl's map_Kd\): the texture image {reason}"):
        load_mesh(tmp_path / "named.obj")
    with pytest.raises(DatasetError, match=rf"image odd.tif {reason}"):
        _as_capture(tmp_path, "odd.tif")


def test_hemisphere_cameras_and_a_view_that_sees_nothing(tmp_path):
    cameras = hemisphere_cameras(100, 16, seed=1)
    assert len(cameras) == 100 and bool((cameras.c2w[:, 2, 3] >= -1e-6).all())
    mesh = load_mesh(_write_ply(tmp_path / "square.ply", _square(0.0, 1.0, RED)), up_axis="z")
    away = Cameras.from_fov(look_at(torch.tensor([[0.0, -4.0, 0.0]]), torch.tensor([0.0, -8.0, 0.0])), 0.7, 8, 8)
    rgb, alpha = rasterize(mesh, away, 0)
    assert torch.equal(rgb, torch.ones(8, 8, 3)) and not alpha.any()


def test_a_box_is_shrunk_into_every_view_and_spot_and_the_horse_are_not(tmp_path):
    """A cube's corners reach sqrt(3) at half-extent 1, outside the views; it is scaled to VIEW_RADIUS instead."""
    trimesh.creation.box((2, 2, 2)).export(tmp_path / "cube.ply")
    cube = load_mesh(tmp_path / "cube.ply", up_axis="z")
    assert np.linalg.norm(cube.vertices, axis=1).max() == pytest.approx(VIEW_RADIUS)
    cameras = hemisphere_cameras(12, 32, seed=0)
    for i in range(len(cameras)):
        _, alpha = rasterize(cube, cameras, i, supersample=1)
        assert float(torch.cat([alpha[0], alpha[-1], alpha[:, 0], alpha[:, -1]]).max()) == 0.0, i
    for mesh in (load_mesh(SPOT / "spot_triangulated.obj"), load_mesh(HORSE)):  # inside it at half-extent 1
        assert np.abs(mesh.vertices).max() == pytest.approx(1.0)


def test_a_ply_coloured_per_face_keeps_each_faces_colour(tmp_path):
    """Face colours become per-corner vertex colours (they had been dropped: the box shaded grey)."""
    box = trimesh.creation.box()
    box.visual.face_colors = np.where(np.arange(12)[:, None] % 2, RED, BLUE)
    box.export(tmp_path / "faces.ply")
    mesh = load_mesh(tmp_path / "faces.ply", up_axis="z")
    albedo = mesh.albedo(np.arange(12), np.full((12, 3), 1 / 3))
    assert mesh.has_colour and np.array_equal(albedo, np.where(np.arange(12)[:, None] % 2, [1, 0, 0], [0, 0, 1]))


def test_vertices_no_face_uses_are_dropped_before_the_box_is_taken(tmp_path):
    """A stray vertex 40 radii away had set the box: the ball shrank to a speck (8 occupied vertices at 64³)."""
    ball = trimesh.creation.icosphere(subdivisions=2)
    colours = np.vstack([np.tile(RED, (len(ball.vertices), 1)), [BLUE]])
    trimesh.Trimesh(np.vstack([ball.vertices, [[40.0, 0.0, 0.0]]]), ball.faces, vertex_colors=colours,
                    process=False).export(tmp_path / "stray.ply")
    mesh = load_mesh(tmp_path / "stray.ply", up_axis="z")
    assert mesh.vertices.shape == ball.vertices.shape and np.allclose(mesh.vertices, ball.vertices)
    assert np.array_equal(mesh.faces, ball.faces)
    assert np.array_equal(mesh.vertex_colors, np.tile([[1.0, 0.0, 0.0]], (len(ball.vertices), 1)))


def test_loading_a_stored_mesh_tells_its_mesh_warnings_and_still_shows_the_others(tmp_path, monkeypatch):
    """The ingest and the voxelize route collect the loader's MeshWarnings (told to the jobs, files named as
    uploaded), recording every warning as they do: any other (numpy's on a degenerate face's normal, Pillow's on a
    large texture) had been dropped, said nowhere, not even in the worker's log. It is shown as before."""
    import json
    import warnings

    from voxe_core.mesh_input import MeshWarning
    from worker import ingest

    (tmp_path / "mesh").mkdir()
    (tmp_path / "mesh" / "names.json").write_text(json.dumps({"mesh.obj": "chair.obj"}))

    def load_stored_mesh(dataset):
        warnings.warn("invalid value encountered in divide", RuntimeWarning)
        warnings.warn("mesh.obj: the material library its mtllib names, 'chair.mtl', is not found beside it",
                      MeshWarning)
        return "the mesh"

    monkeypatch.setattr(ingest, "load_stored_mesh", load_stored_mesh)
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        told = []
        mesh = ingest.load_stored_mesh_telling(tmp_path, told)
    assert (mesh, told) == ("the mesh", ["chair.obj: the material library its mtllib names, 'chair.mtl', is not "
                                         "found beside it"])
    assert [(w.category, str(w.message)) for w in shown] == [(RuntimeWarning, "invalid value encountered in divide")]


def test_a_mesh_scene_stored_before_frames_keeps_the_frame_its_views_were_rendered_in(tmp_path):
    """Its ingest rendered its views with every vertex setting the box and no shrink into the views; its voxelize
    route reads the stored mesh again, which had now been placed otherwise (a cube at 0.75 of its views' size, a
    mesh with a stray vertex 20 times larger). Archives without a frame in options.json keep frame 1."""
    import json

    from worker.ingest import load_stored_mesh

    ball = trimesh.creation.icosphere(subdivisions=1)
    trimesh.Trimesh(np.vstack([ball.vertices, [[40.0, 0.0, 0.0]]]), ball.faces, process=False).export(
        tmp_path / "stray.ply")
    trimesh.creation.box((2, 2, 2)).export(tmp_path / "cube.ply")
    for name, earlier in (("stray", 1 / 20.5), ("cube", 1.0)):  # the largest half-extent of every vertex's box: 1
        stored = tmp_path / name / "mesh"
        stored.mkdir(parents=True)
        (stored / "mesh.ply").write_bytes((tmp_path / f"{name}.ply").read_bytes())
        (stored / "options.json").write_text(json.dumps({"shading": "none", "up_axis": "z"}))
        half_extent = lambda mesh: np.ptp(mesh.vertices, axis=0).max() / 2  # noqa: E731
        assert half_extent(load_stored_mesh(tmp_path / name)) == pytest.approx(earlier), name
        (stored / "options.json").write_text(json.dumps({"shading": "none", "up_axis": "z", "frame": 2}))
        assert half_extent(load_stored_mesh(tmp_path / name)) != pytest.approx(earlier), name
    with pytest.raises(MeshError, match="frame must be one of"):
        load_mesh(tmp_path / "cube.ply", frame=3)


def test_frame_1_boxes_every_vertex_of_the_file_whatever_its_colours(tmp_path):
    """A face-coloured PLY is split into per-face vertices as it loads; frame 1 still boxes the file's own vertices,
    its stray one included (as meshes were placed before frame 2), not the split ones."""
    ball = trimesh.creation.icosphere(subdivisions=1)
    stray = trimesh.Trimesh(np.vstack([ball.vertices, [[40.0, 0.0, 0.0]]]), ball.faces, process=False)
    stray.visual.face_colors = np.tile(RED, (len(ball.faces), 1))
    stray.export(tmp_path / "faces.ply")
    mesh = load_mesh(tmp_path / "faces.ply", up_axis="z", frame=1)
    assert mesh.has_colour and np.ptp(mesh.vertices, axis=0).max() / 2 == pytest.approx(1 / 20.5)


# ------------------------------------------------------------------ loading errors
def test_loading_normalises_and_refuses_bad_files(tmp_path):
    mesh = load_mesh(SPOT / "spot_triangulated.obj", SPOT / "spot_texture.png", extent=0.8)
    assert np.allclose(np.abs(mesh.vertices).max(0).max(), 0.8) and mesh.texture is not None
    assert np.allclose(mesh.vertices.min(0) + mesh.vertices.max(0), 0.0)
    with pytest.raises(MeshError, match=r"cube.stl: unsupported mesh type '.stl'"):
        load_mesh(tmp_path / "cube.stl")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match="points.obj: no triangles"):
        load_mesh(tmp_path / "points.obj")
    (tmp_path / "nan.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="nan.obj: vertex coordinates contain NaN or Inf"):
        load_mesh(tmp_path / "nan.obj")
    (tmp_path / "point.obj").write_text("v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n")
    with pytest.raises(MeshError, match="point.obj: all vertices coincide"):
        load_mesh(tmp_path / "point.obj")
    (tmp_path / "line.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n")
    with pytest.raises(MeshError, match=r"line.obj: every triangle has zero area \(repeated or collinear vertices\)"):
        load_mesh(tmp_path / "line.obj")  # had voxelised to an empty grid, mesh-to-grid exiting 0
    (tmp_path / "fin.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n")
    assert load_mesh(tmp_path / "fin.obj").faces.shape == (2, 3)  # one real triangle is a surface
    (tmp_path / "far.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                      "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                      "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    with pytest.raises(MeshError, match=r"far.ply: a face names vertex 8 of 3$"):
        load_mesh(tmp_path / "far.ply")  # had raised a bare IndexError
    (tmp_path / "negative.ply").write_text((tmp_path / "far.ply").read_text().replace("3 0 1 7", "3 0 1 -5"))
    with pytest.raises(MeshError, match=r"^negative.ply: a face names a negative vertex index, -5$"):
        load_mesh(tmp_path / "negative.ply")  # had been named as "vertex 2 of 3 (or a negative index)"
    ply = _write_ply(tmp_path / "square.ply", _square(0.0, 1.0, RED))
    with pytest.raises(MeshError, match="square.ply: a texture was given but the mesh has no texture coordinates"):
        load_mesh(ply, SPOT / "spot_texture.png")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(MeshError, match="bad.png: cannot read the texture image"):
        load_mesh(SPOT / "spot_triangulated.obj", tmp_path / "bad.png")
    (tmp_path / "odd.png").write_bytes(DDS_OF_UNKNOWN_PIXEL_FORMAT)  # Pillow raises NotImplementedError for it
    with pytest.raises(MeshError, match="odd.png: cannot read the texture image: Unknown pixel format"):
        load_mesh(SPOT / "spot_triangulated.obj", tmp_path / "odd.png")


_TETRAHEDRON_PLY = ("ply\nformat ascii 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\n"
                    "property float z\nelement face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 1 3\n3 0 2 3\n3 1 2 3\n")


@pytest.mark.parametrize("text, message", [
    (_TETRAHEDRON_PLY.format(vertices=4, faces=6), "declares 6 face elements, the file holds 4"),  # had loaded 4
    (_TETRAHEDRON_PLY.format(vertices=4, faces=4)[:-10], "declares 4 face elements, the file holds 3"),  # had 2
    (_TETRAHEDRON_PLY.format(vertices=5, faces=4), "declares 4 face elements, the file holds 3"),  # a face a vertex
])
def test_an_ascii_ply_holding_fewer_rows_than_its_header_declares_is_refused_naming_the_counts(tmp_path, text,
                                                                                                  message):
    """trimesh reads the rows an ASCII PLY holds, one per line, and had loaded a truncated file, or one whose header
    overstates a count, as part of its mesh without a word."""
    (tmp_path / "short.ply").write_text(text)
    with pytest.raises(MeshError) as error:
        load_mesh(tmp_path / "short.ply")
    assert str(error.value) == f"short.ply: its header {message}: it is truncated, or its header overstates a count"


_TRIANGLE_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n"


@pytest.mark.parametrize("lines, message", [
    ("f 1 2 9", "line 8, 'f 1 2 9': a face names vertex 9, of the 3 the file holds"),  # numpy's "index 8 is out of
    ("f -1 -2 -9", "line 8, 'f -1 -2 -9': a face names vertex -9, of the 3 the file holds"),  # bounds for axis 0 ..."
    ("f 0 1 2",  # read as vertex 1: "no triangles" (with another face, a wrong one)
     "line 8, 'f 0 1 2': a face names vertex 0, of the 3 the file holds (an OBJ counts them from 1)"),
    ("f 1/1 2/2 3/4",  # every texture coordinate dropped: the mesh loaded uncoloured (with a texture: "has no vt")
     "line 8, 'f 1/1 2/2 3/4': a face names texture coordinate (vt) 4, of the 3 the file holds"),
    ("f 1/1 2/2 3/0",  # read as vt 1
     "line 8, 'f 1/1 2/2 3/0': a face names texture coordinate (vt) 0, of the 3 the file holds (an OBJ counts them "
     "from 1)"),
    ("f 1 2 99999999999999999999",  # (past int64: the check had raised an OverflowError)
     "line 8, 'f 1 2 99999999999999999999': a face names vertex 99999999999999999999, of the 3 the file holds"),
    ("f 1 2 -99999999999999999999",
     "line 8, 'f 1 2 -99999999999999999999': a face names vertex -99999999999999999999, of the 3 the file holds"),
    ("f 1//1 2/2/1 3/4",  # a corner's vt read after one of none
     "line 8, 'f 1//1 2/2/1 3/4': a face names texture coordinate (vt) 4, of the 3 the file holds"),
    ("f 1 2 x",  # "string or file could not be read to its end due to unmatched data"
     "line 8, 'f 1 2 x': not a face of three or more corners, each v, v/vt, v//vn or v/vt/vn"),
    ("f 1/1/1 2/2/1 3/3/1\nf 1 x",  # (a line of one or two corners trimesh skips, words or not)
     "line 9, 'f 1 x': not a face of three or more corners, each v, v/vt, v//vn or v/vt/vn"),
    ("v 0 0 one\nf 1 2 3", "line 8, 'v 0 0 one': 'one' is not a number"),  # "string or file could not be read ..."
    ("f 1 2 \\\n3\nf 1 2 9",  # numbered as the file's lines, a continued one by its first (had been line 9)
     "line 10, 'f 1 2 9': a face names vertex 9, of the 3 the file holds"),
    ("f -3 -2 -1\nv 1 1 1\nf 1 2 4",  # read as vertices 2, 3 and 4 (an OBJ's -3 is vertex 1 there)
     "line 8, 'f -3 -2 -1': its vertex index -3 counts back from the last before this line, but the loader counts "
     "back from the file's last, and the file has more after this line: write the index positive"),
    ("  f 1 2 3\nf 1 3 2",  # dropped
     "line 8, 'f 1 2 3': indented: the loader reads a f line only where its keyword begins the line"),
    ("f 1 2 3\nf\t1 3 2",  # dropped after the last "f " line ("no triangles" in a file of them alone)
     "line 9, 'f\\t1 3 2': a '\\t' after its keyword: the loader reads a f line only where a space follows it"),
    ("v\t1 1 1\nf 1 2 4",  # not a vertex: "index 3 is out of bounds for axis 0 with size 3"
     "line 8, 'v\\t1 1 1': a '\\t' after its keyword: the loader reads a v line only where a space follows it"),
    ("f 1/1 2/2 3/3\nf 1//1 2//1 3//1",  # the normal's index read as the vt's
     "line 9, 'f 1//1 2//1 3//1': a corner v//vn among corners v/vt (line 8's) in one material's faces: the loader "
     "reads them all as v/vt"),
    ("f 1/1 2/2 3",  # read as the face 1 1 2
     "line 8, 'f 1/1 2/2 3': a corner v among corners v/vt (this line's first) in one material's faces: the loader "
     "reads them all as v/vt"),
    ("vt 0.5\nf 1/4 2/2 3/3",  # every vt read as one value: rendering raised an IndexError
     "line 8, 'vt 0.5': a texture coordinate of 1 value, not 2 (u v): the loader reads every vt as short then"),
    ("v 0 0 1 # top\nf 1 2 4",  # "string or file could not be read to its end due to unmatched data"
     "line 8, 'v 0 0 1 # top': a comment after its values, '# top', which the loader reads as values: put it on a "
     "line of its own"),
    ("f 1 2 3 # a face",  # "invalid literal for int() with base 10: '#'"
     "line 8, 'f 1 2 3 # a face': a comment after its values, '# a face', which the loader reads as values: put it "
     "on a line of its own"),
    ("f 1 2 3\rf 1 3 2",  # one line to the loader
     "line 8, 'f 1 2 3\\rf 1 3 2': a carriage return (CR) alone ends a line within it, where the loader ends lines "
     "only at a line feed (LF, or CR LF): save it with those"),
])
def test_an_obj_naming_what_it_does_not_hold_is_refused_naming_the_line(tmp_path, lines, message):
    (tmp_path / "bad.obj").write_text(_TRIANGLE_OBJ + lines + "\n")
    Image.new("RGB", (4, 4), RED[:3]).save(tmp_path / "red.png")
    for texture in (None, tmp_path / "red.png"):
        with pytest.raises(MeshError) as error:
            load_mesh(tmp_path / "bad.obj", texture)
        assert str(error.value) == f"bad.obj: {message}"


def test_an_obj_of_every_corner_form_loads(tmp_path):
    """Negative indices count back from the last; a normal's index is not checked (the loader reads none)."""
    (tmp_path / "forms.obj").write_text(_TRIANGLE_OBJ + "f 1 2 3\nf 1/1 2/2 3/3\nf -3//1 -2//1 -1//9\n"
                                        "f 1/-3/1  2/2/1 3/3/1 \n")
    mesh = load_mesh(tmp_path / "forms.obj")
    assert len(mesh.faces) == 4 and np.allclose(mesh.vertices[mesh.faces[0]], mesh.vertices[mesh.faces[2]])


@pytest.mark.parametrize("text, faces", [
    ("f 1/1/1 2/2/1 3/3/1\nf\t1/1/1 3/3/1 2/2/1\nf 3/3/1 2/2/1 1/1/1\n", 3),  # a tab: read between "f " lines
    ("f 1/1/1 2/2/1 3/3/1\nf 1/1 3/3 2/2 1/1\n", 3),  # a corner lacking a vn only: read line by line
    ("usemtl a\nf 1/1 2/2 3/3\nusemtl b\nf 1//1 3//1 2//1\nf 1 2 3\nusemtl a\nf 3/3 2/2 1/1\n", 4),  # (by material)
    ("f 1/1/1 2/2/1 3/3/1\nvt 0 0 1\nvt 0.5 0.5 1\nf 1/-1/1 2/-2/1 3/-3/1\n", 2),  # negative after its vt's last
])
def test_an_obj_trimesh_reads_as_written_loads(tmp_path, text, faces):
    """What the OBJ check refuses trimesh misreads, and no more: a face line with a tab after its keyword between
    two "f " lines, corners of different forms in different materials' faces, or differing only in a normal (which
    the loader does not read), a negative index after the last vertex (vt) it counts back from."""
    (tmp_path / "read.obj").write_text(_TRIANGLE_OBJ + text)
    Image.new("RGB", (4, 4), RED[:3]).save(tmp_path / "red.png")
    mesh = load_mesh(tmp_path / "read.obj", tmp_path / "red.png", up_axis="z")
    assert len(mesh.faces) == faces and mesh.uv is not None and np.allclose(mesh.texture, np.asarray(RED[:3]) / 255)


def test_corners_without_vt_among_one_materials_are_refused_where_its_texture_coordinates_colour_the_mesh(tmp_path):
    """trimesh reads a material's face lines of differing lengths line by line, dropping every corner's vt where one
    corner has none: the mesh had loaded uncoloured (a texture given: "has no texture coordinates"). Without a
    texture or a material library the texture coordinates colour nothing: it loads."""
    faces = "f 1/1/1 2/2/1 3/3/1\nf 3 2 1 2\n"
    (tmp_path / "plain.obj").write_text(_TRIANGLE_OBJ + faces)
    (tmp_path / "library.obj").write_text("mtllib library.mtl\n" + _TRIANGLE_OBJ + "usemtl red\n" + faces)
    (tmp_path / "library.mtl").write_text("newmtl red\nmap_Kd red.png\n")
    Image.new("RGB", (4, 4), RED[:3]).save(tmp_path / "red.png")
    for name, texture, line in (("plain.obj", tmp_path / "red.png", 9), ("library.obj", None, 11)):
        with pytest.raises(MeshError) as error:
            load_mesh(tmp_path / name, texture)
        assert str(error.value) == (f"{name}: line {line}, 'f 3 2 1 2': a corner v among corners v/vt/vn (line "
                                    f"{line - 1}'s) in one material's faces: the loader drops every corner's "
                                    "texture coordinates (vt)")
    assert len(load_mesh(tmp_path / "plain.obj").faces) == 3


def test_a_byte_order_mark_is_refused_before_an_obj_line_it_hides_and_read_past_before_a_ply(tmp_path):
    """trimesh reads an OBJ's "\\ufeffv" as no vertex (every index after it one off: "index 3 is out of bounds", or
    a wrong mesh), and reads past one before a PLY's "ply" (whose check had refused it: "its first line is not
    'ply'")."""
    (tmp_path / "marked.obj").write_text("\ufeff" + _TRIANGLE_OBJ + "f 1 2 3\n")
    with pytest.raises(MeshError) as error:
        load_mesh(tmp_path / "marked.obj")
    assert str(error.value) == ("marked.obj: line 1, '\\ufeffv 0 0 0': the file begins with a byte order mark "
                                "(U+FEFF), which the loader reads as part of this line's keyword, 'v': save it as "
                                "UTF-8 without one")
    (tmp_path / "commented.obj").write_text("\ufeff# a comment\n" + _TRIANGLE_OBJ + "f 1 2 3\n")
    assert len(load_mesh(tmp_path / "commented.obj").faces) == 1
    for name, data in (("ascii.ply", _TETRAHEDRON.encode()), ("binary.ply", _TETRAHEDRON_BINARY)):
        (tmp_path / name).write_bytes(b"\xef\xbb\xbf" + data)
        assert len(load_mesh(tmp_path / name).faces) == 4, name
    assert read_ply_header(tmp_path / "binary.ply").complete


def test_an_obj_loads_as_trimesh_reads_its_face_lines_of_fewer_than_three_corners_and_vt_it_does_not_hold(tmp_path):
    """trimesh skips a face line of fewer than three corners (a stray edge, a bare f) and, in a file without vt lines,
    every corner's vt: the mesh loads without them, uncoloured (a texture given: it has no texture coordinates)."""
    vertices = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"
    (tmp_path / "short.obj").write_text(vertices + "f 1 2 3\nf 3 4\nf 4\nf\nf 2 4 3\n")
    (tmp_path / "no_vt.obj").write_text(vertices + "f 1/1 2/2 3/3\nf 2/4/1 4/5/1 3/6/1\n")
    for name in ("short.obj", "no_vt.obj"):
        mesh = load_mesh(tmp_path / name, up_axis="z")
        assert len(mesh.faces) == 2 and mesh.uv is None and mesh.texture is None, name
    Image.new("RGB", (4, 4), RED[:3]).save(tmp_path / "red.png")
    with pytest.raises(MeshError, match=r"^no_vt.obj: a texture was given but the mesh has no texture coordinates "
                                        r"\(vt\)$"):
        load_mesh(tmp_path / "no_vt.obj", tmp_path / "red.png")


_TETRAHEDRON = _TETRAHEDRON_PLY.format(vertices=4, faces=4)
_TETRAHEDRON_BINARY = (_TETRAHEDRON.split("end_header\n")[0].replace("ascii", "binary_little_endian").encode()
                       + b"end_header\n" + np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], "<f4").tobytes()
                       + b"".join(b"\x03" + np.array(face, "<i4").tobytes()
                                  for face in ([0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3])))


def _binary_tetrahedron_counted(count_type: str, first_count: bytes) -> bytes:
    """The binary tetrahedron with its faces' list lengths of ``count_type`` (the other faces' 3) and its first face's
    length the bytes ``first_count``."""
    header, body = _TETRAHEDRON_BINARY.split(b"end_header\n")
    three = np.array([3], PROPERTY_TYPES[count_type]).tobytes()
    faces = [np.array(face, "<i4").tobytes() for face in ([0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3])]
    return (header.replace(b"list uchar", f"list {count_type}".encode()) + b"end_header\n" + body[:48]
            + first_count + faces[0] + b"".join(three + face for face in faces[1:]))


@pytest.mark.parametrize("data, message", [
    (_TETRAHEDRON.replace("end_header\n", ""),  # trimesh: "list index out of range"
     "its header has no end_header line: it is truncated, or not a PLY file"),
    (_TETRAHEDRON.replace("ascii", "binary_middle_endian"),  # "PLY is unexpected length!"
     "its format line is 'format binary_middle_endian 1.0', not 'format' and one of ascii, binary_little_endian, "
     "binary_big_endian (then the version, 1.0)"),
    (_TETRAHEDRON.replace("list uchar int", "list int"),  # "not enough values to unpack (expected 3, got 2)"
     "its header's line 8, 'property list int vertex_indices', is not 'property <type> <name>' nor "
     "'property list <count type> <type> <name>'"),
    (_TETRAHEDRON.replace("float y", "flot y"),  # "'flot'"
     "its header's line 5, 'property flot y': 'flot' is not a property type (char, uchar, short, ushort, int, uint, "
     "float, double, or a sized one: int32 ...)"),
    (_TETRAHEDRON.replace("\n3 0 1 3\n", "\n3 0 1\n"),  # loaded without that face
     "line 15 (face 2), '3 0 1', holds 3 values where its header's properties (and the lengths of its lists) make 4"),
    (_TETRAHEDRON.replace("1 0 0\n", "1 0 x\n"),  # "string or file could not be read to its end due to unmatched data"
     "line 11 (vertex 2): 'x' is not a number"),
    (_TETRAHEDRON.replace("ascii", "binary_little_endian"),  # "PLY is unexpected length!"
     "its format line says binary_little_endian, but its body is text: an ASCII PLY's format line is "
     "'format ascii 1.0'"),
    (_TETRAHEDRON_BINARY.replace(b"binary_little_endian", b"ascii"),  # "'utf-8' codec can't decode byte 0x80 ..."
     "its format line says ascii, but its body is not text: a binary body's format line is "
     "'format binary_little_endian 1.0' (or binary_big_endian)"),
    (_TETRAHEDRON_BINARY[:-5],  # "PLY is unexpected length!" (as for each of these)
     "its body ends within its face element 4, of the 4 its header declares: it is truncated, or its header "
     "overstates a count"),
    (_TETRAHEDRON_BINARY + bytes(7),
     "its body holds 7 bytes past its elements' last (face 4): its header understates a count, or something was "
     "appended"),
    (_TETRAHEDRON_BINARY[:-13] + b"\x04" + np.array([0, 1, 2, 3], "<i4").tobytes(),  # (one as long: a wrong mesh)
     "its face element 4 holds a list of 4 where the first holds 3: the loader reads a binary PLY's lists all as "
     "long as the first (save it as ASCII, or its faces all of one size)"),
    # numpy's reading of the rows had failed: "invalid shape in fixed-type tuple: dimension smaller then zero"
    (_binary_tetrahedron_counted("char", b"\xff"), "its face element 1: a list's length, -1, is not a count"),
    *[(_binary_tetrahedron_counted(count_type, np.array([3], PROPERTY_TYPES[count_type]).tobytes()),  # whole lengths
       f"its header's line 8, 'property list {count_type} int vertex_indices': a binary list's length is of "  # "'('
       f"'{count_type}', not an integer type (uchar, ushort, uint, or a sized one: uint8 ...)")  # was never closed"
      for count_type in ("float", "double", "float16")],
    (_binary_tetrahedron_counted("float", np.array([np.nan], "<f4").tobytes()),  # "cannot convert float NaN to ..."
     "its header's line 8, 'property list float int vertex_indices': a binary list's length is of 'float', not an "
     "integer type (uchar, ushort, uint, or a sized one: uint8 ...)"),
    (_binary_tetrahedron_counted("uint", np.array([4_000_000_000], "<u4").tobytes()),  # "dimension does not fit ..."
     "its face element 1: a list's length, 4000000000, runs past the end of its body (room for 15 items): it is "
     "truncated, or that length is damaged"),
    (_TETRAHEDRON.replace("\n3 0 1 2\n", "\n1e300 0 1 2\n"),  # (had told a count of 301 digits)
     "line 14 (face 1): a list's length, '1e300', runs past its row of 4 values"),
])
def test_a_malformed_ply_is_refused_saying_what_in_it_is_wrong(tmp_path, data, message):
    """trimesh had failed in words of its own (in the comments), or loaded the mesh short of a face."""
    (tmp_path / "bad.ply").write_bytes(data if isinstance(data, bytes) else data.encode())
    with pytest.raises(MeshError) as error:
        load_mesh(tmp_path / "bad.ply")
    assert str(error.value) == f"bad.ply: {message}"


def test_a_binary_ply_loads_as_its_ascii_twin(tmp_path):
    (tmp_path / "binary.ply").write_bytes(_TETRAHEDRON_BINARY)
    (tmp_path / "ascii.ply").write_text(_TETRAHEDRON)
    binary, ascii_ = load_mesh(tmp_path / "binary.ply"), load_mesh(tmp_path / "ascii.ply")
    assert np.array_equal(binary.faces, ascii_.faces) and np.allclose(binary.vertices, ascii_.vertices)


@pytest.mark.parametrize("text, faces", [
    (_TETRAHEDRON_PLY.format(vertices=4, faces=4) + "\n", 4),  # a blank last line
    (_TETRAHEDRON_PLY.format(vertices=4, faces=4).replace("\n", "\r\n"), 4),
    (_TETRAHEDRON_PLY.format(vertices=4, faces=3), 3),  # rows past the counts: trimesh reads the declared ones
    ("PLY" + _TETRAHEDRON_PLY.format(vertices=4, faces=4)[3:], 4),  # (had been refused: "its first line is not 'ply'")
    (_TETRAHEDRON_PLY.format(vertices=4, faces=4).replace("list uchar", "list float"), 4),  # (binary ones are refused)
])
def test_an_ascii_ply_holding_the_rows_its_header_declares_loads(tmp_path, text, faces):
    (tmp_path / "whole.ply").write_bytes(text.encode())
    assert len(load_mesh(tmp_path / "whole.ply").faces) == faces


@pytest.mark.parametrize("unit", [1e-170, 1e155, 1e300])
def test_a_mesh_in_any_float64_unit_is_placed_as_in_unit_one(tmp_path, unit):
    """Placement is scale-free: the view radius's norm of coordinates near 1e-170 had underflowed to 0 (a
    ZeroDivisionError), and at 1e155 overflowed to inf (scaled to nothing, refused as having zero area)."""
    faces = "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    for name, size in (("one.obj", 1.0), ("scaled.obj", unit)):  # text: a PLY's float32 holds neither unit
        (tmp_path / name).write_text(f"v 0 0 0\nv {size!r} 0 0\nv 0 {size!r} 0\nv 0 0 {size!r}\n{faces}")
    expected = load_mesh(tmp_path / "one.obj").vertices
    assert np.allclose(load_mesh(tmp_path / "scaled.obj").vertices, expected, rtol=1e-12, atol=0)
    (tmp_path / "wide.obj").write_text(f"v -1.7e308 0 0\nv 1.7e308 0 0\nv 0 1.7e308 0\nv 0 0 1.7e308\n{faces}")
    assert np.isfinite(load_mesh(tmp_path / "wide.obj").vertices).all()
    (tmp_path / "speck.obj").write_text("v 0 0 0\nv 1e-310 0 0\nv 0 1e-310 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"speck.obj: the mesh's extent, 1e-310, is too small to scale up"):
        load_mesh(tmp_path / "speck.obj")
    for extent in (math.inf, 1e155):  # 1e155 had overflowed squared, a bare OverflowError
        with pytest.raises(MeshError, match=re.escape(f"extent must be positive and finite in float32, got {extent}")):
            load_mesh(tmp_path / "one.obj", extent=extent)
    assert np.isfinite(load_mesh(tmp_path / "wide.obj", extent=3e38).vertices).all()


def test_vertices_of_two_coordinates_are_refused_naming_the_count(tmp_path):
    """trimesh reads an OBJ's "v x y" lines (or a file mixing them with "v x y z") as (V, 2) vertices: placing them
    had raised a bare IndexError (an ingest's failure said no more), with or without a texture."""
    (tmp_path / "flat.obj").write_text("v 0 0\nv 1 0\nv 0 1\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    (tmp_path / "mixed.obj").write_text("v 0 0 0\nv 1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\n")
    Image.new("RGB", (4, 4), RED[:3]).save(tmp_path / "red.png")
    for name, texture in (("flat.obj", None), ("flat.obj", tmp_path / "red.png"), ("mixed.obj", None)):
        with pytest.raises(MeshError, match=rf"{name}: its vertices read as 2 coordinates each, not 3 \(x y z\)"):
            load_mesh(tmp_path / name, texture)


# ------------------------------------------------------------------ voxelisation
@pytest.fixture(scope="module")
def green_sphere(tmp_path_factory):
    sphere = trimesh.creation.icosphere(subdivisions=4)
    sphere.visual.vertex_colors = np.tile([0, 255, 0, 255], (len(sphere.vertices), 1))
    return load_mesh(_write_ply(tmp_path_factory.mktemp("sphere") / "sphere.ply", sphere), up_axis="z")


def test_voxelised_sphere_has_its_surface_at_the_radius_and_renders_like_the_mesh(green_sphere):
    grid = voxelize(green_sphere, VoxelizeConfig(resolution=49))  # voxel 1/16
    radial = torch.linspace(0.8, 1.2, 401)[:, None] * torch.tensor([[0.6, 0.0, 0.8]])
    density, color = grid.query(radial)
    surface = float(radial.norm(dim=-1)[density > 0].max())
    assert surface == pytest.approx(1.0, abs=0.25 / 16)
    assert torch.allclose(color[390], torch.tensor([0.0, 1.0, 0.0]), atol=2e-3)
    cameras = hemisphere_cameras(3, 48, seed=2)
    for i in range(3):
        truth, alpha = rasterize(green_sphere, cameras, i)
        out = render_image(grid, cameras, i)
        iou = float(torch.minimum(out.opacity, alpha).sum() / torch.maximum(out.opacity, alpha).sum())
        assert iou > 0.95 and psnr(out.rgb, truth) > 25.0


@pytest.mark.parametrize("flipped", [slice(None), slice(None, None, 2)], ids=["every face", "half the faces"])
def test_the_winding_does_not_move_the_voxelised_surface(green_sphere, flipped):
    """The tangent planes' sign comes from the filled volume, not the winding (which had made the ball 2 voxels fatter)."""
    faces = green_sphere.faces.copy()
    faces[flipped] = faces[flipped, ::-1]
    config = VoxelizeConfig(resolution=49)  # voxel 1/16
    wound = SurfaceMesh(green_sphere.vertices, faces, vertex_colors=green_sphere.vertex_colors)
    as_wound, outward = (voxelize(mesh, config).features[..., 0] > 0 for mesh in (wound, green_sphere))
    assert int((as_wound ^ outward).sum()) < 1e-3 * int(outward.sum())  # a few: the surface samples differ


def test_voxelising_a_slab_of_vertices_at_a_time_changes_nothing(green_sphere, monkeypatch):
    """voxelize reads the grid's vertices in slabs of x rows (memory); the slabs' bounds must not show."""
    from voxe_core import mesh_input

    whole = voxelize(green_sphere, VoxelizeConfig(resolution=33)).features  # one slab
    monkeypatch.setattr(mesh_input, "_SLAB_VERTICES", 5 * 33 * 33)  # 7 slabs, the last of 3 rows
    assert torch.equal(voxelize(green_sphere, VoxelizeConfig(resolution=33)).features, whole)


def test_mesh_grid_mesh_round_trip_chamfer_is_below_half_a_voxel():
    mesh = load_mesh(SPOT / "spot_triangulated.obj", SPOT / "spot_texture.png")
    grid = voxelize(mesh, VoxelizeConfig(resolution=97))
    voxel = float(grid.voxel_size.min())
    distance = chamfer_distance(mesh.trimesh(), extract_mesh(grid))
    print(f"spot round trip at 97³: Chamfer {distance:.5f} = {distance / voxel:.3f} voxel")
    assert distance < 0.5 * voxel


def test_chamfer_of_concentric_spheres_is_their_gap():
    inner = trimesh.creation.icosphere(subdivisions=4)
    outer = trimesh.creation.icosphere(subdivisions=4, radius=1.1)
    assert chamfer_distance(inner, outer) == pytest.approx(0.1, abs=0.003)
    assert chamfer_distance(inner, inner) < 0.01


def test_rendered_views_reconstruct_the_mesh(green_sphere):
    """Route (a) end to end at toy size: rasterised hemisphere views, then the usual reconstruction."""
    cameras = hemisphere_cameras(16, 24, seed=3)
    images, alphas = render_mesh_views(green_sphere, cameras)
    assert images.shape == (16, 24, 24, 3) and float(alphas.mean()) > 0.1
    config = ReconstructConfig.fast(resolutions=(24,), iterations=(80,), image_downsample=(1,), rays_per_step=1024)
    grid = reconstruct(images[1:], cameras[1:], config)
    assert psnr(render_image(grid, cameras, 0).rgb, images[0]) > 20.0


# ------------------------------------------------------------------ CLI
def test_cli_mesh_to_grid_writes_a_grid_or_names_the_problem(tmp_path, capsys):
    from voxe_core.backbones import load_grid
    from voxe_core.cli import main

    out = tmp_path / "spot.safetensors"
    args = ["mesh-to-grid", str(SPOT / "spot_triangulated.obj"), "--texture", str(SPOT / "spot_texture.png"), "-q"]
    assert main([*args, "--resolution", "24", "--out", str(out)]) == 0
    assert load_grid(out).resolution == (24, 24, 24)
    # by default the grid a mesh scene's job voxelizes: the preset's final resolution and box (it had been 160³)
    from voxe_core.presets import reconstruct_config, reconstruction_params

    service = reconstruct_config(reconstruction_params({}, mesh_scene=True))
    assert main([*args, "--out", str(out)]) == 0
    grid = load_grid(out)
    assert grid.resolution == (service.resolutions[-1],) * 3 and service.resolutions[-1] != 160
    assert torch.equal(grid.bbox_min, torch.as_tensor(service.bbox_min, dtype=torch.float32))
    ply = _write_ply(tmp_path / "square.ply", _square(0.0, 1.0, RED))
    bad = tmp_path / "bad.safetensors"
    assert main(["mesh-to-grid", ply, "--texture", str(SPOT / "spot_texture.png"), "--out", str(bad)]) == 2
    assert "square.ply: a texture was given but the mesh has no texture coordinates" in capsys.readouterr().err
    assert not bad.exists()


def test_mesh_dataset_loads_back_as_the_rasterised_views(tmp_path, green_sphere):
    from voxe_core.mesh_input import write_mesh_dataset

    write_mesh_dataset(green_sphere, tmp_path / "ds", views=3, size=24, test_views=2)
    train, test = load_scene(tmp_path / "ds", "train"), load_scene(tmp_path / "ds", "test")
    assert (len(train), len(test)) == (3, 2) and train.has_alpha
    rgb, alpha = rasterize(green_sphere, train.cameras, 1)
    assert torch.allclose(train.images[1], rgb, atol=1.5 / 255) and torch.allclose(train.alphas[1], alpha, atol=0.6 / 255)


# ------------------------------------------------------------------ service upload
@contextmanager
def _stage(tmp_path, files, mesh_shading=None, mesh_up_axis=None):
    from api.uploads import stage_upload, staging_folder

    with staging_folder(tmp_path / "work") as staging, ExitStack() as opened:
        yield stage_upload(staging, None, [(name, opened.enter_context(open(path, "rb"))) for name, path in files],
                           1 << 30, 100, 8, 1000.0, 1 << 26, mesh_shading, mesh_up_axis)


def _ingest_mesh_upload(tmp_path, files, mesh_shading=None):
    """What the API stores for a mesh upload, then what the worker's ingest makes of it:
    (staged, the stored archive's names, the dataset folder, its image count)."""
    import zipfile

    from worker.ingest import decode, render_mesh

    root = tmp_path / "ingested"
    with _stage(tmp_path, files, mesh_shading) as staged, zipfile.ZipFile(staged.archive) as archive:
        archive.extractall(root)
        stored = archive.namelist()
    render_mesh(root, [])
    decoded = decode(root, 8)
    assert decoded.backbone == "relu_field"  # rendered views: the object on a transparent background
    return staged, stored, root, decoded.count


def test_a_mesh_upload_is_stored_as_its_rendered_views(tmp_path, monkeypatch):
    import zipfile

    from voxe_service import datasets
    from voxe_service.datasets import package

    monkeypatch.setattr(datasets, "MESH_VIEWS", 4)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    staged, stored, root, count = _ingest_mesh_upload(tmp_path, [("spot/spot.obj", SPOT / "spot_triangulated.obj"),
                                                         ("spot/spot.png", SPOT / "spot_texture.png")])
    assert (staged.format, staged.image_count, staged.width, staged.splits) == ("mesh", 4, 32, ["train", "test"])
    # Rendered by the ingest: the upload keeps the mesh, its texture and the names they were uploaded under.
    assert stored == ["mesh/mesh.obj", "mesh/names.json", "mesh/options.json", "mesh/texture.png"]
    assert count == 4
    package(root, tmp_path / "dataset.zip")
    names = zipfile.ZipFile(tmp_path / "dataset.zip").namelist()
    assert {"transforms_train.json", "train/r_003.png", "mesh/mesh.obj", "mesh/texture.png"} <= set(names)


def test_an_obj_coloured_by_its_mtl_keeps_its_colours_in_the_service(tmp_path, monkeypatch):
    """The .mtl is kept beside the mesh under the name mtllib gives it (it had been dropped: the OBJ rendered grey)."""
    from voxe_service import datasets

    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    (tmp_path / "kd.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n")
    (tmp_path / "kd.obj").write_text("mtllib kd.mtl\nv -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\n"
                                     "usemtl red\nf 1 2 3\nusemtl blue\nf 1 3 4\n")
    _, stored, root, _ = _ingest_mesh_upload(tmp_path, [("cube/kd.obj", tmp_path / "kd.obj"),
                                                        ("cube/kd.mtl", tmp_path / "kd.mtl")])
    assert "mesh/kd.mtl" in stored
    scene = load_scene(root, "train")
    surface = scene.images[scene.alphas > 0.999]
    assert float(surface[:, 0].max()) > 0.99 and float(surface[:, 2].max()) > 0.99 and float(surface[:, 1].max()) < 0.01
    # trimesh looks for a library (or an image it names) inside the mesh's folder only
    (tmp_path / "inner").mkdir()
    (tmp_path / "inner" / "up.obj").write_text("mtllib ../kd.mtl\nv -1 0 -1\nv 1 0 -1\nv 1 0 1\nusemtl red\nf 1 2 3\n")
    with pytest.warns(UserWarning, match=r"up.obj: the material library its mtllib names, '../kd.mtl', is not found"):
        assert not load_mesh(tmp_path / "inner" / "up.obj").has_colour


def test_a_bad_mesh_upload_names_the_problem_and_leaves_nothing(tmp_path):
    """File rules are a 422 at once; a mesh that does not load fails the scene's ingest, naming the problem."""
    from api.uploads import UploadError
    from worker.ingest import IngestError

    (tmp_path / "nan.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(IngestError, match="invalid mesh: nan.obj: vertex coordinates contain NaN or Inf"):
        _ingest_mesh_upload(tmp_path, [("nan.obj", tmp_path / "nan.obj")])
    (tmp_path / "cow.png").write_bytes(b"not a png")
    with pytest.raises(IngestError) as info:  # Pillow's message names the file by its path on the worker
        _ingest_mesh_upload(tmp_path / "bad_texture", [("cow.obj", SPOT / "spot_triangulated.obj"),
                                                       ("cow.png", tmp_path / "cow.png")])
    assert str(info.value) == ("invalid mesh: cow.png: cannot read the texture image: cannot identify image file "
                               "'cow.png'")
    with pytest.raises(UploadError, match="several images .'a.png', 'b.png'.; send one texture") as info, \
            _stage(tmp_path, [("m.obj", SPOT / "spot_triangulated.obj"), ("a.png", SPOT / "spot_texture.png"),
                              ("b.png", SPOT / "spot_texture.png")]):
        pass
    assert info.value.status == 422
    with pytest.raises(UploadError, match=r"an image of a kind not read as a texture \('cow.tga'\); send its "
                                          r"texture as .png, .jpg, .jpeg"), \
            _stage(tmp_path, [("m.obj", SPOT / "spot_triangulated.obj"), ("cow.tga", SPOT / "spot_texture.png")]):
        pass
    with _stage(tmp_path, [("m.obj", SPOT / "spot_triangulated.obj"), ("licence.pdf", SPOT / "spot_texture.png"),
                           ("scan.h5", SPOT / "spot_texture.png")]):  # no texture kind: ignored, as before
        pass
    with pytest.raises(UploadError, match="several material libraries .'a.mtl', 'b.mtl'.; send one .mtl"), \
            _stage(tmp_path, [("m.obj", SPOT / "spot_triangulated.obj"), ("a.mtl", tmp_path / "nan.obj"),
                              ("b.mtl", tmp_path / "nan.obj")]):
        pass
    with pytest.raises(UploadError, match="several meshes .'a.obj', 'b.ply'.; send one"), \
            _stage(tmp_path, [("a.obj", SPOT / "spot_triangulated.obj"), ("b.ply", SPOT / "spot_triangulated.obj")]):
        pass
    assert list((tmp_path / "work" / "uploads").iterdir()) == []


def test_a_mesh_upload_whose_mtl_is_not_the_one_mtllib_names_is_refused_naming_both(tmp_path):
    """Regression: an OBJ sent with 'Model_v2.mtl' for its 'mtllib model.mtl' was stored, and the ingest's mesh
    loaded grey without a word. The library found by its base name in another case (as the loader finds it), or
    beside a texture (which colours the mesh instead), is taken."""
    from api.uploads import UploadError

    (tmp_path / "kd.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "m.obj").write_text("mtllib model.mtl\n" + CUBE_OBJ)
    with pytest.raises(UploadError) as info, _stage(tmp_path, [("cube/m.obj", tmp_path / "m.obj"),
                                                               ("cube/Model_v2.mtl", tmp_path / "kd.mtl")]):
        pass
    assert (info.value.status, str(info.value)) == (422, (
        "the OBJ's mtllib names the material library 'model.mtl', but the upload's is 'Model_v2.mtl': the loader "
        "would not find it, and the mesh would load grey; rename the .mtl to 'model.mtl', or write 'mtllib "
        "Model_v2.mtl' in the OBJ"))
    (tmp_path / "win.obj").write_text("mtllib C:\\exports\\MODEL.MTL\n" + CUBE_OBJ)
    _, stored, _, _ = _ingest_mesh_upload(tmp_path / "found", [("win.obj", tmp_path / "win.obj"),
                                                               ("model.mtl", tmp_path / "kd.mtl")])
    assert "mesh/model.mtl" in stored
    with _stage(tmp_path, [("m.obj", tmp_path / "m.obj"), ("Model_v2.mtl", tmp_path / "kd.mtl"),
                           ("skin.png", SPOT / "spot_texture.png")]):
        pass


def test_a_mesh_upload_whose_obj_names_no_mtl_is_refused_naming_the_mtl(tmp_path):
    """Regression: an OBJ with no mtllib line sent with 'kd.mtl' was stored, and the ingest's mesh loaded grey
    without a word (the loader reads only the library an mtllib names). Beside a texture, the .mtl is not read."""
    from api.uploads import UploadError

    (tmp_path / "kd.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "m.obj").write_text(CUBE_OBJ)  # its usemtl red, no mtllib
    with pytest.raises(UploadError) as info, _stage(tmp_path, [("cube/m.obj", tmp_path / "m.obj"),
                                                               ("cube/kd.mtl", tmp_path / "kd.mtl")]):
        pass
    assert (info.value.status, str(info.value)) == (422, (
        "the upload's material library is 'kd.mtl', but the OBJ has no mtllib line naming one: the loader would not "
        "read it, and the mesh would load grey; write 'mtllib kd.mtl' in the OBJ, or send it without the .mtl"))
    with _stage(tmp_path, [("m.obj", tmp_path / "m.obj"), ("kd.mtl", tmp_path / "kd.mtl"),
                           ("skin.png", SPOT / "spot_texture.png")]):
        pass
    assert list((tmp_path / "work" / "uploads").iterdir()) == []
    # The library named as the loader reads it: after a byte order mark too (where trimesh finds it)
    (tmp_path / "bom.obj").write_bytes(b"\xef\xbb\xbfmtllib kd.mtl\n" + CUBE_OBJ.encode())
    _, stored, _, _ = _ingest_mesh_upload(tmp_path / "bom", [("bom.obj", tmp_path / "bom.obj"),
                                                             ("kd.mtl", tmp_path / "kd.mtl")])
    assert "mesh/kd.mtl" in stored
    assert load_mesh(tmp_path / "bom.obj").colour.tolist() == [1.0, 0.0, 0.0]


# ------------------------------------------------------------------ baked shading (meshes without colour)
def _unit_normals(vertices: np.ndarray) -> np.ndarray:
    return vertices / np.linalg.norm(vertices, axis=1, keepdims=True)


@pytest.mark.parametrize("flip_winding", [False, True])
def test_a_ball_is_shaded_by_the_lambert_term_alone(flip_winding):
    """Nothing occludes a convex surface: the shading is ambient + (1 - ambient) max(0, n.l), whatever the winding."""
    ball = trimesh.creation.icosphere(subdivisions=3)
    faces = np.asarray(ball.faces)[:, ::-1].copy() if flip_winding else np.asarray(ball.faces)
    shaded = shade_mesh(SurfaceMesh(np.asarray(ball.vertices), faces))
    light = np.asarray(SHADING_LIGHT) / np.linalg.norm(SHADING_LIGHT)
    expected = SHADING_AMBIENT + (1 - SHADING_AMBIENT) * np.clip(_unit_normals(ball.vertices) @ light, 0, None)
    assert np.abs(shaded.shading - expected).max() < 0.02  # vertex normals of a subdivided icosahedron


def test_occlusion_darkens_a_narrow_gap():
    """Two slabs 0.1 apart: the faces looking into the gap see little sky; the same faces outside see half of it."""
    slabs = [trimesh.creation.box((0.4, 1.6, 1.6), trimesh.transformations.translation_matrix((x, 0, 0)))
             for x in (-0.25, 0.25)]
    mesh = trimesh.util.concatenate(slabs).subdivide_to_size(0.1)
    shaded = shade_mesh(SurfaceMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)), "baked")
    v = mesh.vertices
    middle = (np.abs(v[:, 1]) < 0.5) & (np.abs(v[:, 2]) < 0.5)
    in_gap = middle & np.isclose(np.abs(v[:, 0]), 0.05)
    outside = middle & np.isclose(np.abs(v[:, 0]), 0.45)
    assert in_gap.sum() > 10 and outside.sum() > 10
    assert shaded.shading[in_gap].mean() < 0.5 * shaded.shading[outside].mean()


def test_shading_modes_and_what_auto_picks():
    spot = load_mesh(SPOT / "spot_triangulated.obj", SPOT / "spot_texture.png")
    assert shade_mesh(spot, "auto") is spot and spot.shading is None  # coloured: left as it is
    assert shade_mesh(spot, "baked").shading is not None
    bare = SurfaceMesh(spot.vertices, spot.faces)
    assert shade_mesh(bare, "none") is bare and shade_mesh(bare, "auto").shading is not None
    with pytest.raises(MeshError, match="mesh_shading must be one of auto, baked, none, got 'flat'"):
        shade_mesh(bare, "flat")


@pytest.fixture(scope="module")
def horse():
    return load_mesh(HORSE)


def test_the_horse_has_shape_once_shaded_on_both_routes(horse):
    """The horse has no colour: unshaded it renders and voxelises as one grey; shaded, its surface varies."""
    assert not horse.has_colour
    shaded = shade_mesh(horse)  # auto
    assert shaded.shading is not None and 0.0 <= shaded.shading.min() and shaded.shading.max() <= 1.0
    cameras = hemisphere_cameras(2, 48, seed=3)
    for mesh, flat in ((horse, True), (shaded, False)):
        rgb, alpha = rasterize(mesh, cameras, 0)
        surface = rgb[alpha > 0.999]
        assert len(surface) > 100
        assert (float(surface.std()) < 1e-4) == flat, float(surface.std())
    for mesh, flat in ((horse, True), (shaded, False)):
        grid = voxelize(mesh, VoxelizeConfig(resolution=32))
        features = grid.features.detach()
        colour = torch.sigmoid(features[..., 1:][features[..., 0] > 0])
        assert (float(colour.std()) < 1e-4) == flat, float(colour.std())


def test_mesh_shading_is_stored_with_the_upload_and_honoured_by_the_ingest(tmp_path, monkeypatch):
    import json

    from api.uploads import UploadError
    from voxe_service import datasets

    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    spread = {}
    for mode in ("none", None):  # None: the default, auto
        work = tmp_path / str(mode)
        _, stored, root, _ = _ingest_mesh_upload(work, [("horse.obj", HORSE)], mode)
        assert "mesh/options.json" in stored
        assert json.loads((root / "mesh" / "options.json").read_text()) == {"shading": mode or "auto", "up_axis": "y",
                                                                              "frame": 2}
        scene = load_scene(root, "train")
        spread[mode] = float(scene.images[scene.alphas > 0.999].std())
    assert spread["none"] < 1e-3 < 0.03 < spread[None], spread
    (tmp_path / "images").mkdir()
    Image.new("RGB", (8, 6)).save(tmp_path / "images" / "0.png")
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 8.0, "frames": [{"file_path": "images/0.png", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(UploadError, match="mesh_shading applies to mesh uploads only"), \
            _stage(tmp_path, [("transforms.json", tmp_path / "transforms.json"),
                              ("images/0.png", tmp_path / "images/0.png")], "baked"):
        pass


def test_the_views_a_mesh_ingest_renders_are_those_the_readme_and_max_mesh_faces_say(tmp_path, monkeypatch):
    """MAX_MESH_FACES's docstring said 120 views, README's POST /v1/scenes row 100: the ingest renders 100 training
    views and 20 test views; both now say so, counted here from an ingest (at 16 px, the counts as the service's)."""
    from pathlib import Path

    from voxe_core import mesh_input
    from voxe_service import datasets

    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 16)
    _, _, root, _ = _ingest_mesh_upload(tmp_path, [("horse.obj", HORSE)])
    train, test = (len(json.loads((root / f"transforms_{split}.json").read_text())["frames"])
                   for split in ("train", "test"))
    readme = " ".join((Path(__file__).parent.parent / "README.md").read_text().split())
    said = re.search(r"a mesh is first rendered into 256 px views, (\d+) upper-hemisphere training views and (\d+) "
                     r"test views on the 30° evaluation ring \(the mesh's faces limit: (\d+) renders of every one\)",
                     readme)
    assert said is not None and tuple(map(int, said.groups())) == (train, test, train + test) == (100, 20, 120)
    source = " ".join(Path(mesh_input.__file__).read_text().split())  # (a constant's docstring: in its source only)
    assert (f"renders {train + test} views of every one (``write_mesh_dataset``: ``MESH_VIEWS``, {train} "
            f"upper-hemisphere training views, and {test} test views on the evaluation ring)") in source


def test_an_obj_uploaded_without_its_texture_is_shaded_by_the_ingest(tmp_path, monkeypatch):
    """Spot's OBJ sent alone (its vt and no material) had rendered as one flat grey of trimesh's (0.39): taken for
    coloured, "auto" did not bake. Now its views are the default albedo, shaded."""
    from voxe_service import datasets

    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    _, stored, root, _ = _ingest_mesh_upload(tmp_path, [("spot.obj", SPOT / "spot_triangulated.obj")])
    assert stored == ["mesh/mesh.obj", "mesh/names.json", "mesh/options.json"]
    scene = load_scene(root, "train")
    surface = scene.images[scene.alphas > 0.999]
    assert float(surface.std()) > 0.03 and float(surface.max()) > 0.6, (float(surface.std()), float(surface.max()))


def test_mesh_up_axis_is_stored_with_the_upload_and_honoured_by_the_ingest(tmp_path):
    """Every upload had loaded y-up; a z-up file (CAD, scanners) now says so."""
    import json
    import zipfile

    from api.uploads import UploadError
    from worker.ingest import load_stored_mesh

    spot = [("spot.obj", SPOT / "spot_triangulated.obj"), ("spot.png", SPOT / "spot_texture.png")]
    with _stage(tmp_path, spot, mesh_up_axis="z") as staged, zipfile.ZipFile(staged.archive) as archive:
        archive.extractall(tmp_path / "stored")
    options = json.loads((tmp_path / "stored" / "mesh" / "options.json").read_text())
    assert options == {"shading": "auto", "up_axis": "z", "frame": 2}
    z_up = load_mesh(SPOT / "spot_triangulated.obj", SPOT / "spot_texture.png", up_axis="z")
    assert np.array_equal(load_stored_mesh(tmp_path / "stored").vertices, z_up.vertices)
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 8.0, "frames": []}))
    with pytest.raises(UploadError, match="mesh_up_axis applies to mesh uploads only"), \
            _stage(tmp_path, [("transforms.json", tmp_path / "transforms.json")], mesh_up_axis="z"):
        pass


def test_a_discs_wedges_are_rasterised_along_their_rows_not_over_their_screen_boxes(monkeypatch):
    """A disc's cap is a fan of long thin wedges, each of whose screen boxes is a good part of the image: every pixel
    of every box had been tested against its face (a CAD disc of 4,096 faces took 20 s a view, 40 min an ingest).
    The pixels tested, three cross products each, are counted: the original tested about 160 per sample covered."""
    disc = trimesh.creation.cylinder(radius=1.0, height=0.01, sections=256)
    disc.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # facing the camera on -y
    mesh = SurfaceMesh(np.asarray(disc.vertices), np.asarray(disc.faces))
    cameras, supersample = _camera_on_minus_y(), 2
    products = []
    cross2 = mesh_input._cross2
    monkeypatch.setattr(mesh_input, "_cross2", lambda u, v: products.append(np.size(u) // 2) or cross2(u, v))
    _, alpha = rasterize(mesh, cameras, 0, supersample)
    radius = float(cameras.fx[0]) * 1.0 / 4.0  # pixels, at distance 4
    assert float(alpha.sum()) == pytest.approx(math.pi * radius**2, rel=0.01)
    covered_samples = float(alpha.sum()) * supersample**2
    assert sum(products) < 30 * covered_samples


@pytest.mark.parametrize("written", ["C:\\Users\\me\\Model.mtl", "..\\model.mtl", "MODEL.MTL"])
def test_a_library_and_its_image_named_by_a_windows_path_or_in_another_case_colour_the_mesh(tmp_path, written):
    """Windows exporters write absolute or backslashed paths, and Windows' and macOS' file systems ignore case: the
    .mtl (and its map_Kd image) beside the OBJ had not been found, and the mesh had loaded grey without a word."""
    (tmp_path / "model.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl wood\nmap_Kd D:\\textures\\Wood.PNG\n")
    Image.fromarray(np.full((2, 2, 3), (0, 0, 255), dtype=np.uint8)).save(tmp_path / "wood.png")
    tetrahedron = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvt 1 0\nvt 0 1\n"
    faces = "f 1/1 2/2 3/3\nf 1/1 2/2 4/3\nf 1/1 3/2 4/3\nf 2/1 3/2 4/3\n"
    for material, colour in (("red", [1.0, 0.0, 0.0]), ("wood", [0.0, 0.0, 1.0])):
        (tmp_path / "model.obj").write_text(f"mtllib {written}\n{tetrahedron}usemtl {material}\n{faces}")
        mesh = load_mesh(tmp_path / "model.obj")
        albedo = mesh.colour if mesh.texture is None else mesh.texture.reshape(-1, 3)[0]
        assert albedo is not None and np.allclose(albedo, colour), material


@pytest.mark.parametrize("kind", ["obj", "ply"])
def test_a_mesh_upload_of_more_faces_than_an_ingest_renders_is_refused_at_once(tmp_path, monkeypatch, kind):
    """Its ingest reads, shades and renders every face: a mesh of tens of millions had been taken (the upload's size cap
    allows GBs) for the worker to load whole. The faces are counted from a PLY's header or an OBJ's face lines (one
    straddling the counter's read of a megabyte among them), nothing else read."""
    from api import uploads
    from api.uploads import UploadError

    monkeypatch.setattr(uploads, "MAX_MESH_FACES", 3)
    path = tmp_path / f"box.{kind}"
    trimesh.creation.box().export(path)  # 12 faces
    if kind == "obj":  # a comment line first, so that the megabyte's border falls within the first "\nf "
        text = path.read_text()
        path.write_text("#" * ((1 << 20) - 3 - text.index("\nf ")) + "\n" + text)
        assert path.read_bytes()[(1 << 20) - 2:(1 << 20) + 1] == b"\nf "
    counted = " declares 12 faces" if kind == "ply" else "'s face lines make 12 triangles or more"
    with pytest.raises(UploadError, match=f"the {kind.upper()}{counted}, more than the 3 a mesh upload may hold: "
                                          "decimate it") as refused, _stage(tmp_path, [(path.name, path)]):
        pass
    assert refused.value.status == 413
    monkeypatch.setattr(uploads, "MAX_MESH_FACES", 12)
    with _stage(tmp_path, [(path.name, path)]) as staged:
        assert staged.format == "mesh"


def _fan_vertices(corners: int) -> str:
    """An OBJ's vertex lines: a centre, then ``corners`` vertices about it, every other one lifted a little."""
    rim = np.linspace(0, 2 * np.pi, corners, endpoint=False)
    return "v 0 0 0\n" + "".join(f"v {np.cos(t):.6f} {np.sin(t):.6f} {0.001 * (i % 2)}\n" for i, t in enumerate(rim))


@pytest.mark.parametrize("before_border", [0, 1, 2, 3, 5, 700])
def test_a_mesh_uploads_face_bound_counts_the_triangles_its_polygons_and_tabbed_lines_load_as(
        tmp_path, monkeypatch, before_border):
    """trimesh splits a face of N corners into N - 2 triangles and reads "f<TAB>" lines too: the bound had counted
    "\\nf " lines, so one line of 10 million corners passed it. Here a polygon of 200 corners (198 triangles), whose
    line the counter's first megabyte ends within (``before_border`` bytes after its newline: in the "f", a number,
    after a space), then 50 triangles on tabbed lines (read so between face lines), then one more, are counted as the
    loader's 249 triangles."""
    from api import uploads
    from api.uploads import UploadError

    polygon = "f " + " ".join(str(i) for i in range(2, 202)) + "\n"
    tabbed = "".join(f"f\t1\t{i} {i + 1}\n" for i in range(2, 52)) + "f 1 52 53\n"
    vertices = _fan_vertices(200)
    path = tmp_path / "fan.obj"
    path.write_text(vertices + "#" * ((1 << 20) - before_border - len(vertices) - 1) + "\n" + polygon + tabbed)
    assert path.read_bytes()[(1 << 20) - before_border - 1:][:3] == b"\nf "  # the border is before_border into it
    assert len(load_mesh(path).faces) == 198 + 50 + 1
    monkeypatch.setattr(uploads, "MAX_MESH_FACES", 248)
    with pytest.raises(UploadError, match="the OBJ's face lines make 249 triangles or more, more than the 248") as \
            refused, _stage(tmp_path, [(path.name, path)]):
        pass
    assert refused.value.status == 413
    monkeypatch.setattr(uploads, "MAX_MESH_FACES", 249)
    with _stage(tmp_path, [(path.name, path)]) as staged:
        assert staged.format == "mesh"


@pytest.mark.parametrize("line_end", ["\n", "\r\n"])
@pytest.mark.parametrize("before_border", [0, 1, 2, 3, 700])
def test_a_face_line_continued_by_backslashes_counts_as_the_polygon_it_loads_as(tmp_path, line_end, before_border):
    """The loader joins lines ending in a backslash: a polygon of 200 corners written one corner a line had counted
    as one triangle, so a continued line of 10 million corners passed the bound. Here the first megabyte ends
    ``before_border`` bytes before the first continuation's line end (within its backslash and CR too)."""
    from api.uploads import _obj_triangles

    head = _fan_vertices(200).replace("\n", line_end) + "f 2"
    path = tmp_path / "fan.obj"
    padding = (1 << 20) - before_border - len(head) - len(line_end) - 2
    corners = "".join(f" \\{line_end}{i}" for i in range(3, 202))
    path.write_bytes(f"#{'#' * padding}{line_end}{head}{corners}{line_end}".encode())
    assert len(load_mesh(path).faces) == 198
    assert _obj_triangles(path, 10**6) == 198


def test_a_face_lines_one_long_word_is_counted_in_memory_of_its_chunks_not_its_length(tmp_path):
    """A face line still open at a megabyte's end had carried its whole last word into the next one, so a word of
    16 MB was copied and searched again with every megabyte (time quadratic in its length) and held whole."""
    import tracemalloc

    from api.uploads import _obj_triangles

    path = tmp_path / "long.obj"
    path.write_bytes(b"v 0 0 0\nf 1 " + b"7" * (16 << 20) + b" 1\n")
    tracemalloc.start()
    try:
        assert _obj_triangles(path, 10**6) == 1
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 6 << 20, peak


def test_a_mesh_loading_as_more_triangles_than_the_bound_is_refused_by_its_load(tmp_path, monkeypatch):
    """A PLY's header counts its faces, not their corners, and a binary body's lists are not summed at upload: a
    binary PLY of one polygon of 10 million corners passed the upload's check, for its ingest to render as many
    triangles. load_mesh refuses a mesh loading as more than MAX_MESH_FACES triangles, naming the count."""
    rim = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    vertices = np.concatenate([[[0, 0, 0]], np.stack([np.cos(rim), np.sin(rim), 0.001 * (np.arange(200) % 2)], 1)])
    path = tmp_path / "fan.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 201\nproperty float x\nproperty float y\n"
                     b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                     + vertices.astype("<f4").tobytes() + np.uint8(200).tobytes()
                     + np.arange(1, 201, dtype="<i4").tobytes())
    assert read_ply_header(path).faces == 1
    assert len(load_mesh(path).faces) == 198
    monkeypatch.setattr(mesh_input, "MAX_MESH_FACES", 197)
    with pytest.raises(MeshError, match="fan.ply: it loads as 198 triangles, more than the 197 a mesh may hold"):
        load_mesh(path)


def test_small_compact_faces_are_tested_over_their_boxes_not_cut_into_row_spans(monkeypatch):
    """A row's span costs about what a few of its pixels' tests cost: cut for every face, the horse's 43,730 small
    faces rendered 13-34 % slower than over their boxes. A fine sphere's faces, a few pixels a row, are not cut;
    the render is the same either way."""
    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20,480 faces
    mesh = SurfaceMesh(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    cameras = _camera_on_minus_y()
    rows_spanned = []
    row_span = mesh_input._row_span
    monkeypatch.setattr(mesh_input, "_row_span", lambda tri, *rest: rows_spanned.append(len(tri)) or row_span(tri,
                                                                                                       *rest))
    rgb, alpha = rasterize(mesh, cameras, 0, 2)
    covered_samples = int(alpha.sum()) * 4
    assert sum(rows_spanned) < 0.01 * covered_samples  # (none here; on the original 24,374 rows for 6,616 samples)
    monkeypatch.setattr(mesh_input, "_SPANNED_MISSES_PER_ROW", -1.0)  # every face cut into its rows' spans
    spanned_rgb, spanned_alpha = rasterize(mesh, cameras, 0, 2)
    assert torch.equal(rgb, spanned_rgb) and torch.equal(alpha, spanned_alpha)
