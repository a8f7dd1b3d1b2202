"""Ground-truth scenes for bench/localisation.py: a mesh with and without an added part, rendered by Blender.

Scenes (meshes from ``../shared/data/meshes``, normalised by ``voxe_core.mesh_input.load_mesh``):

* ``spot_hat``: Keenan Crane's textured Spot cow wearing a magenta party hat (a cone on her head);
* ``horse_saddlebag``: the grey text2mesh horse with a brown saddlebag (a box) on its flank.

For each, ``blender -b`` (bench/blender_render.py, Cycles, unlit albedo) renders 100 upper-hemisphere
views in the NeRF-synthetic layout (``transforms.json``: ``camera_angle_x`` and c2w per frame, RGBA PNGs)
of the edited object, and a 24-view 360° ring at 30° elevation of the original and the edited object, each
with a per-view coverage image (part red, object green) — the part's and the object's 2D masks.

Grids at ``resolution``: G_i = the object voxelised (``voxelize``); the part voxelised alone; G_e = their
union (per vertex the denser of the two, its colour with it) with a smooth colour drift outside the part:
an edit that touched the whole object, which is what the refinement is there to undo (without it, any
mask would merge to the same grid outside the part). The true 3D part mask: vertices where the part's
density exceeds the object's. Everything is cached under ``bench/.cache/localisation/<scene>``
(gitignored); Blender runs only when the renders are missing.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from voxe_core.cameras import Cameras, random_hemisphere_poses, ring_poses
from voxe_core.constants import NERF_SYNTHETIC_FOV_X
from voxe_core.grid import VoxelGrid
from voxe_core.mesh_input import SurfaceMesh, VoxelizeConfig, load_mesh, voxelize

HERE = Path(__file__).resolve().parent
CACHE = HERE / ".cache" / "localisation"
MESHES = HERE.parent.parent / "shared" / "data" / "meshes"
SIZE = 200
VIEWS = 100
RING = 24
SAMPLES = 16  # Cycles samples per pixel (anti-aliased coverage)


@dataclass(frozen=True)
class SceneSpec:
    name: str
    mesh: str
    texture: str | None
    part: str  # "cone" or "box"
    part_params: tuple  # cone: (cx, cy, base_z, radius, apex_z); box: (cx, cy, cz, sx, sy, sz)
    part_colour: tuple[float, float, float]
    object_colour: tuple[float, float, float] = (0.7, 0.7, 0.7)  # meshes without texture


SCENES = {
    "spot_hat": SceneSpec("spot_hat", "spot/spot_triangulated.obj", "spot/spot_texture.png", "cone",
                          (-0.6, 0.0, 0.78, 0.2, 1.3), (0.85, 0.2, 0.55)),
    "horse_saddlebag": SceneSpec("horse_saddlebag", "horse/horse.obj", None, "box",
                                 (0.27, 0.15, 0.07, 0.14, 0.32, 0.26), (0.45, 0.26, 0.1)),
}


@dataclass
class Scene:
    name: str
    initial: VoxelGrid  # G_i
    edited: VoxelGrid  # G_e
    truth: torch.Tensor  # (X, Y, Z) bool: the part's vertices
    cameras: Cameras  # the 100 hemisphere views
    coverage: torch.Tensor  # (V, H, W, 2) part, object coverage in [0, 1]
    ring: Cameras
    ring_original: torch.Tensor  # (R, H, W, 3) on white
    ring_edited: torch.Tensor
    ring_coverage: torch.Tensor  # (R, H, W, 2)


def part_mesh(spec: SceneSpec):
    import trimesh

    if spec.part == "cone":
        cx, cy, base_z, radius, apex_z = spec.part_params
        mesh = trimesh.creation.cone(radius, apex_z - base_z, sections=48)
        mesh.apply_translation((cx, cy, base_z))
    else:
        cx, cy, cz, sx, sy, sz = spec.part_params
        mesh = trimesh.creation.box((sx, sy, sz))
        mesh.apply_translation((cx, cy, cz))
    colours = np.broadcast_to(np.asarray(spec.part_colour, np.float32), (len(mesh.vertices), 3)).copy()
    return SurfaceMesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), vertex_colors=colours)


def write_obj(path: Path, mesh: SurfaceMesh) -> None:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    if mesh.uv is not None:
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in mesh.uv]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in mesh.faces]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")


def hemisphere_cameras(n: int = VIEWS, size: int = SIZE) -> Cameras:
    c2w, _, _ = random_hemisphere_poses(n, torch.Generator().manual_seed(7))
    return Cameras.from_fov(c2w, NERF_SYNTHETIC_FOV_X, size, size)


def ring_cameras(n: int = RING, size: int = SIZE) -> Cameras:
    return Cameras.from_fov(ring_poses(n), NERF_SYNTHETIC_FOV_X, size, size)


def render_with_blender(spec: SceneSpec, folder: Path, obj: SurfaceMesh, part: SurfaceMesh) -> None:
    if (folder / "done").exists():
        return
    if shutil.which("blender") is None:
        raise SystemExit("bench/localisation needs Blender (Debian's `blender`) to render its ground truth")
    folder.mkdir(parents=True, exist_ok=True)
    write_obj(folder / "object.obj", obj)
    write_obj(folder / "part.obj", part)
    hemi, ring = hemisphere_cameras(), ring_cameras()
    job = {
        "object_obj": str(folder / "object.obj"), "part_obj": str(folder / "part.obj"),
        "object_texture": str(MESHES / spec.texture) if spec.texture else None,
        "object_colour": spec.object_colour, "part_colour": spec.part_colour,
        "size": SIZE, "samples": SAMPLES, "camera_angle_x": NERF_SYNTHETIC_FOV_X, "out": str(folder),
        "views": [{"name": "train", "c2w": hemi.c2w.tolist()},
                  {"name": "ring", "c2w": ring.c2w.tolist(), "original": True}],
    }
    (folder / "job.json").write_text(json.dumps(job))
    # NeRF-synthetic layout of the edited object's hemisphere views
    frames = [{"file_path": f"./train_edited_{i:03d}", "transform_matrix": m} for i, m in enumerate(hemi.c2w.tolist())]
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": NERF_SYNTHETIC_FOV_X, "frames": frames}))
    subprocess.run(["blender", "-b", "--python", str(HERE / "blender_render.py"), "--", str(folder / "job.json")],
                   check=True, stdout=subprocess.DEVNULL)
    (folder / "done").write_text("ok\n")


def _read(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im, dtype=np.float32) / 255.0


def _rgb_on_white(rgba: np.ndarray) -> np.ndarray:
    return rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])


def _stack(folder: Path, pattern: str, n: int, convert) -> torch.Tensor:
    return torch.from_numpy(np.stack([convert(_read(folder / pattern.format(i))) for i in range(n)]))


def drifted(grid: VoxelGrid, keep: torch.Tensor, strength: float = 0.6) -> VoxelGrid:
    """``grid`` with a smooth colour drift (a low-frequency tint, ``strength`` in logit units) outside ``keep``."""
    x, y, z = torch.meshgrid(*[torch.linspace(-1.0, 1.0, n) for n in grid.resolution], indexing="ij")
    tint = torch.stack([torch.sin(3 * x + 1), torch.cos(2 * y + 3 * z), torch.sin(2 * z - x)], -1) * strength
    features = grid.features.detach().clone()
    features[..., 1:] += torch.where(keep[..., None], torch.zeros_like(tint), tint)
    return grid.like(features)


def build_scene(name: str, resolution: int) -> Scene:
    spec = SCENES[name]
    folder = CACHE / name
    obj = load_mesh(MESHES / spec.mesh, MESHES / spec.texture if spec.texture else None, up_axis="y")
    if obj.texture is None:
        obj.vertex_colors = np.broadcast_to(np.asarray(spec.object_colour, np.float32), (len(obj.vertices), 3)).copy()
    part = part_mesh(spec)
    render_with_blender(spec, folder, obj, part)

    grids = folder / f"grids_{resolution}.pt"
    if grids.exists():
        state = torch.load(grids)
    else:
        config = VoxelizeConfig(resolution=resolution)
        g_obj, g_part = voxelize(obj, config), voxelize(part, config)
        d_obj, d_part = g_obj.features[..., 0], g_part.features[..., 0]
        truth = d_part > d_obj
        union = torch.where(truth[..., None], g_part.features, g_obj.features)
        state = {"initial": g_obj.features.detach(), "union": union.detach(), "truth": truth}
        torch.save(state, grids)
    initial = VoxelGrid(resolution)
    initial = initial.like(state["initial"])
    edited = drifted(initial.like(state["union"]), state["truth"])

    def cover(img):
        return img[..., :2].copy()  # (part = red, object = green)

    return Scene(
        name, initial, edited, state["truth"], hemisphere_cameras(),
        _stack(folder, "train_cover_{:03d}.png", VIEWS, cover), ring_cameras(),
        _stack(folder, "ring_original_{:03d}.png", RING, _rgb_on_white),
        _stack(folder, "ring_edited_{:03d}.png", RING, _rgb_on_white),
        _stack(folder, "ring_cover_{:03d}.png", RING, cover),
    )


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="render and voxelise the localisation scenes (cached)")
    parser.add_argument("--resolution", type=int, default=160)
    args = parser.parse_args()
    for scene_name in SCENES:
        s = build_scene(scene_name, args.resolution)
        print(scene_name, "part vertices", int(s.truth.sum()), "coverage", tuple(s.coverage.shape))
