"""Mesh vertex colours: the grid's colour at the vertex against the colour composited along the inward normal.

``voxe_core.export.extract_mesh`` colours each vertex with what a ray meeting the surface there head-on composites
(``_surface_colours``: ``colour_samples`` samples over ``SURFACE_COLOUR_SPAN``, 1 voxel outside to 3 inside, 8 by
default). Before, it took the grid's colour at the vertex itself ("at-vertex", re-implemented here as the baseline:
the library no longer has it), which on the level set is interpolated with the empty vertices outside. Both run on
grids whose empty vertices are grey, as a fit leaves them: (a) a synthetic red sphere, (b) spot voxelised
(``voxe_core.mesh_input.voxelize``, as bench/mesh_input.py does). Per variant, in one run: extraction seconds (the
whole ``extract_mesh``, marching cubes included; one torch thread by default; min of ``--repeats`` rounds, the
variants alternating within each round, after an untimed warm-up) and its ratio to at-vertex, the same in CPU seconds
(other jobs on the shared cores move it less than wall time), and the colour error against renders: for every opaque
pixel (opacity > 0.999) of ``--views`` turntable views (``render_image`` with ``RenderConfig()``, what
``render_views`` runs per view), the mean over RGB of |colour of the mesh vertex nearest the pixel's expected surface
point - the pixel| in 0-255 levels; its mean and 95th percentile over the pixels. Writes
bench/results/mesh_colours.json and mesh_colours.png.

    python bench/mesh_colours.py                   # 128³, ~1 min on 2 shared cores
    python bench/mesh_colours.py --resolution 64 --repeats 1   # a quick look
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from unittest import mock

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
MESHES = HERE.parent.parent / "shared" / "data" / "meshes"
RESULTS = HERE / "results"
SPOT = ("spot/spot_triangulated.obj", "spot/spot_texture.png")
AT_VERTEX = "at-vertex"
RED_LOGITS = (4.0, -4.0, -4.0)


def grey_outside(grid):
    """The grid with every empty vertex's colour grey (raw 0, sigmoid 0.5), where a fit starts and leaves them."""
    with torch.no_grad():
        grid.features[..., 1:][grid.features[..., 0] <= 0] = 0.0
    return grid


def sphere_grid(resolution: int, radius: float = 0.8):
    """A red ball in the default box, raw density 5 per voxel of depth (the tests' sphere), grey outside."""
    from voxe_core.grid import VoxelGrid

    grid = VoxelGrid(resolution)
    axes = [torch.linspace(float(grid.bbox_min[d]), float(grid.bbox_max[d]), resolution) for d in range(3)]
    distance = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).norm(dim=-1)
    with torch.no_grad():
        grid.features[..., 0] = 5.0 * (radius - distance) / float(grid.voxel_size.min())
        grid.features[..., 1:] = torch.tensor(RED_LOGITS)
    return grey_outside(grid)


def spot_grid(resolution: int):
    from voxe_core.mesh_input import VoxelizeConfig, load_mesh, voxelize

    mesh = load_mesh(MESHES / SPOT[0], MESHES / SPOT[1])
    return grey_outside(voxelize(mesh, VoxelizeConfig(resolution=resolution)))


def at_vertex_colours(grid, verts: np.ndarray, normals: np.ndarray, samples: int) -> np.ndarray:
    """The rule before cc34f95: the grid's colour at the vertex itself (``samples`` and the normals unused)."""
    from voxe_core.export import to_uint8

    return to_uint8(grid.query(torch.tensor(np.asarray(verts), dtype=torch.float32))[1])


def extract(grid, variant):
    """``extract_mesh`` with ``variant``'s colours: at-vertex (its colour rule swapped in) or K samples."""
    from voxe_core import export

    if variant == AT_VERTEX:
        with mock.patch.object(export, "_surface_colours", at_vertex_colours):
            return export.extract_mesh(grid)
    return export.extract_mesh(grid, colour_samples=variant)


def rendered_surface(grid, views: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) expected surface points and (P, 3) uint8 colours of the opaque pixels of ``views`` turntable views."""
    from voxe_core.cameras import camera_rays
    from voxe_core.export import to_uint8, turntable_cameras
    from voxe_core.render import RenderConfig, render_image

    cameras = turntable_cameras(views, 30.0, size)
    occupancy = grid.occupancy(RenderConfig().sigma_threshold)
    points, colours = [], []
    for i in range(views):
        render = render_image(grid, cameras, i, RenderConfig(), occupancy)
        opaque = (render.opacity > 0.999).reshape(-1)
        origins, directions = camera_rays(cameras, i)
        points.append((origins + render.depth.reshape(-1, 1) * directions)[opaque].numpy())
        colours.append(to_uint8(render.rgb.reshape(-1, 3)[opaque]))
    return np.concatenate(points), np.concatenate(colours)


def colour_error(mesh, points: np.ndarray, shown: np.ndarray) -> np.ndarray:
    """Per opaque pixel: mean over RGB of |nearest vertex's colour - pixel| in 0-255 levels."""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(mesh.vertices).query(points)
    vertex = mesh.visual.vertex_colors[nearest, :3].astype(int)
    return np.abs(vertex - shown.astype(int)).mean(1)


def run_grid(name: str, grid, variants: list, args) -> list[dict]:
    points, shown = rendered_surface(grid, args.views, args.size)
    for variant in variants[:2]:  # untimed: the first imports trimesh and scikit-image, the second runs composite
        extract(grid, variant)
    seconds, cpu_seconds = {v: [] for v in variants}, {v: [] for v in variants}
    meshes = {}
    for _ in range(args.repeats):  # alternating: each round runs every variant once, so load drifts hit all alike
        for variant in variants:
            t0, cpu0 = time.perf_counter(), time.process_time()
            meshes[variant] = extract(grid, variant)
            seconds[variant].append(time.perf_counter() - t0)
            cpu_seconds[variant].append(time.process_time() - cpu0)
    base, cpu_base = min(seconds[AT_VERTEX]), min(cpu_seconds[AT_VERTEX])
    rows = []
    for variant in variants:
        error = colour_error(meshes[variant], points, shown)
        rows.append({
            "grid": name, "variant": variant if variant == AT_VERTEX else f"K={variant}",
            "samples": 0 if variant == AT_VERTEX else variant, "resolution": args.resolution, "threads": args.threads,
            "vertices": len(meshes[variant].vertices), "seconds": min(seconds[variant]),
            "ratio_to_at_vertex": min(seconds[variant]) / base, "cpu_seconds": min(cpu_seconds[variant]),
            "cpu_ratio_to_at_vertex": min(cpu_seconds[variant]) / cpu_base, "error_mean": float(error.mean()),
            "error_p95": float(np.percentile(error, 95)), "pixels": len(error), "all_seconds": seconds[variant],
            "all_cpu_seconds": cpu_seconds[variant],
        })
    return rows


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for grid, marker, offset in zip(dict.fromkeys(r["grid"] for r in runs), "os^", ((4, -11), (4, 4), (-24, 4))):
        rows = [r for r in runs if r["grid"] == grid]
        ax.plot([r["seconds"] for r in rows], [r["error_mean"] for r in rows], marker=marker, label=f"{grid} (mean)")
        ax.scatter([r["seconds"] for r in rows], [r["error_p95"] for r in rows], marker=marker, facecolors="none",
                   edgecolors="grey", label=f"{grid} (p95)")
        for r in rows:
            ax.annotate(r["variant"], (r["seconds"], r["error_mean"]), fontsize=7, textcoords="offset points",
                        xytext=offset)
    ax.set_xlabel(f"extract_mesh seconds (min of the repeats, {runs[0]['threads']} torch thread(s), 2 shared cores)")
    ax.set_ylabel("|vertex colour - render| (0-255 levels)")
    ax.set_yscale("symlog", linthresh=1)
    ax.set_title(f"mesh vertex colours at {runs[0]['resolution']}³: at the vertex vs K samples along the normal",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    from report import write_results

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=128, help="both grids' vertices per axis")
    parser.add_argument("--samples", type=int, nargs="+", default=(2, 4, 8), help="colour_samples K to compare")
    parser.add_argument("--repeats", type=int, default=15, help="alternating rounds; each variant's min counts")
    parser.add_argument("--views", type=int, default=6, help="turntable views (elevation 30°) scored")
    parser.add_argument("--size", type=int, default=128, help="pixels per side of each view")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: with two, on the shared cores, a sub-second extraction's wall time "
                             "swung by half between rounds)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    variants = [AT_VERTEX, *args.samples]
    runs = []
    for name, build in (("sphere", sphere_grid), ("spot", spot_grid)):
        t0 = time.perf_counter()
        grid = build(args.resolution)
        print(f"{name}: {args.resolution}³ grid built in {time.perf_counter() - t0:.1f} s", flush=True)
        for row in run_grid(name, grid, variants, args):
            runs.append(row)
            print(f"{name:6s} {row['variant']:9s} {row['vertices']:7d} vertices {row['seconds']:6.2f} s "
                  f"(×{row['ratio_to_at_vertex']:.2f}; CPU {row['cpu_seconds']:.2f} s, "
                  f"×{row['cpu_ratio_to_at_vertex']:.2f})  error mean {row['error_mean']:5.1f}  "
                  f"p95 {row['error_p95']:5.1f} levels", flush=True)
    summary = {"args": vars(args), "load_average": os.getloadavg()}
    for name in dict.fromkeys(r["grid"] for r in runs):
        rows = {r["variant"]: r for r in runs if r["grid"] == name}
        for row in rows.values():
            if row["variant"] != AT_VERTEX:
                summary[f"{name}_{row['variant']}_error_vs_at_vertex"] = (
                    f"{rows[AT_VERTEX]['error_mean']:.1f} -> {row['error_mean']:.1f} levels "
                    f"for {row['ratio_to_at_vertex']:.2f}x the time, {row['cpu_ratio_to_at_vertex']:.2f}x the CPU time")
    write_results("mesh_colours", runs, summary, plot)


if __name__ == "__main__":
    main()
