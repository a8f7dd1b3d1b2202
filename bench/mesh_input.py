"""Mesh input, route (a) against route (b), on ../shared/data/meshes/spot (textured OBJ) and horse (untextured OBJ).

(a) rasterise posed upper-hemisphere views (100, as the paper did in Blender)
and reconstruct as usual; (b) voxelise the mesh straight into G_i. Both are
scored in the same run against ground-truth mesh renders from a held-out
ring (elevation 30°, the evaluation turntable): PSNR, and seconds spent
(rendering the views and fitting for (a), voxelising for (b)); plus the
Chamfer distance of each grid's marching-cubes mesh to the input (the round
trip). Horse has no texture: its renders are a flat albedo, so its PSNR is a
silhouette score. Writes bench/results/mesh_input.json and mesh_input.png.

    python bench/mesh_input.py          # ~10 min on 2 shared cores (100 views of 100 px, 96³)
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
MESHES = HERE.parent.parent / "shared" / "data" / "meshes"
RESULTS = HERE / "results"
INPUTS = {
    "spot": ("spot/spot_triangulated.obj", "spot/spot_texture.png"),
    "horse": ("horse/horse.obj", None),
}


def score(grid, mesh, truth, cameras) -> dict:
    from voxe_core.export import extract_mesh, render_views
    from voxe_core.mesh_input import chamfer_distance
    from voxe_core.metrics import psnr, ssim

    renders = render_views(grid, cameras)
    try:
        chamfer = chamfer_distance(mesh.trimesh(), extract_mesh(grid))
    except ValueError:  # no surface at the default level: an under-fitted grid
        chamfer = float("nan")
    return {
        "psnr": float(psnr(renders, truth).mean()),
        "ssim": float(ssim(renders, truth).mean()),
        "chamfer": chamfer,
        "voxel": float(grid.voxel_size.min()),
    }


def run_mesh(name: str, args) -> list[dict]:
    from reconstruction import as_measured

    from voxe_core.cameras import ring_poses
    from voxe_core.cameras import Cameras
    from voxe_core.constants import NERF_SYNTHETIC_FOV_X
    from voxe_core.mesh_input import VoxelizeConfig, hemisphere_cameras, load_mesh, render_mesh_views, voxelize
    from voxe_core.reconstruct import ReconstructConfig, reconstruct

    obj, texture = INPUTS[name]
    mesh = load_mesh(MESHES / obj, None if texture is None else MESHES / texture)
    ring = Cameras.from_fov(ring_poses(args.test_views, 30.0), NERF_SYNTHETIC_FOV_X, args.size, args.size)
    truth, _ = render_mesh_views(mesh, ring)
    rows = []

    t0 = time.perf_counter()
    cameras = hemisphere_cameras(args.views, args.size, seed=0)
    images, _ = render_mesh_views(mesh, cameras)
    render_s = time.perf_counter() - t0
    final = args.resolution
    # lr 0.03, every image's rays, the early-stop pass: fast()'s before 2026-12-05, what the records were measured with.
    config = as_measured(ReconstructConfig.fast(resolutions=(final // 2, final), iterations=tuple(args.iterations),
                                                image_downsample=(2, 1), rays_per_step=args.rays, lr=0.03))
    t0 = time.perf_counter()
    grid = reconstruct(images, cameras, config)
    fit_s = time.perf_counter() - t0
    rows.append({"mesh": name, "route": "a: render views + reconstruct", "resolution": final,
                 "seconds": render_s + fit_s, "render_views_s": render_s, "reconstruct_s": fit_s,
                 **score(grid, mesh, truth, ring)})

    for resolution in sorted({final, args.voxelize_resolution}):
        t0 = time.perf_counter()
        grid = voxelize(mesh, VoxelizeConfig(resolution=resolution))
        seconds = time.perf_counter() - t0
        rows.append({"mesh": name, "route": "b: voxelise", "resolution": resolution, "seconds": seconds,
                     **score(grid, mesh, truth, ring)})
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, marker in zip(INPUTS, "os"):
        for route, color in (("a", "tab:blue"), ("b", "tab:orange")):
            sel = [r for r in rows if r["mesh"] == name and r["route"].startswith(route)]
            ax.scatter([r["seconds"] for r in sel], [r["psnr"] for r in sel], c=color, marker=marker,
                       label=f"{name}, route {route}")
            for r in sel:
                ax.annotate(f"{r['resolution']}³", (r["seconds"], r["psnr"]), fontsize=7,
                            textcoords="offset points", xytext=(4, 4))
    ax.set_xscale("log")
    ax.set_xlabel("seconds to G_i (2 shared cores)")
    ax.set_ylabel("PSNR against mesh renders (dB)")
    ax.set_title("mesh input: (a) render + reconstruct vs (b) voxelise")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--test-views", type=int, default=20)
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--voxelize-resolution", type=int, default=160)
    parser.add_argument("--iterations", type=int, nargs=2, default=(200, 500))
    parser.add_argument("--rays", type=int, default=2048)
    args = parser.parse_args()
    torch.set_num_threads(os.cpu_count() or 1)
    rows = []
    for name in INPUTS:
        for row in run_mesh(name, args):
            rows.append(row)
            print(f"{row['mesh']:6s} {row['route']:30s} {row['resolution']:4d}³ {row['seconds']:8.1f} s  "
                  f"PSNR {row['psnr']:.2f} dB  SSIM {row['ssim']:.3f}  Chamfer {row['chamfer']:.4f} "
                  f"({row['chamfer'] / row['voxel']:.2f} voxel)")
    summary = {}
    for name in INPUTS:
        a = next(r for r in rows if r["mesh"] == name and r["route"].startswith("a"))
        b = next(r for r in rows if r["mesh"] == name and r["route"].startswith("b") and r["resolution"] == a["resolution"])
        summary[name] = {"b_minus_a_psnr_db": b["psnr"] - a["psnr"], "a_over_b_seconds": a["seconds"] / b["seconds"]}
    print(json.dumps(summary, indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "mesh_input.json").write_text(json.dumps({"args": vars(args), "rows": rows, "summary": summary}, indent=1))
    plot(rows, RESULTS / "mesh_input.png")


if __name__ == "__main__":
    main()
