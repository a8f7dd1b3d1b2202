"""Lifting + graph cut (SPEC §3) measured against an exactly known 3D edit region.

Scene: an analytic "cow" (ellipsoid body, spherical head, black spots on a
white coat) wearing a cone "party hat" on its head. Every vertex is owned by
the part whose signed-distance-like field is largest there, so the true edit
region (the hat's vertices) is known exactly on the grid lattice. Two
variants: ``distinct`` (blue hat: colour edges help the cut) and ``same``
(hat in the coat's white: only the attention grids can separate it).

2D "attention" maps are synthesised from the truth: the hat indicator rendered
as a grey value over the object's density (edit) and the rest of the object
(object), then corrupted with strength n ∈ NOISE_LEVELS:

* attention resolution: area-downsampled to 16x16 and bilinearly upsampled
  (n > 0), as real cross-attention maps are 16x16;
* Gaussian blur of std n·0.1·size pixels;
* additive Gaussian noise of std n per 16x16 attention cell (spatially
  correlated, like attention noise), upsampled;
* a random per-view shift (view inconsistency) of std n·0.06·size pixels,
  the same for both maps of a view;
* spurious blobs (the paper's kangaroo-tail example): in a fraction n of the
  views a bright blob on a random point of the silhouette is added to the edit
  map and removed from the object map (token probabilities sum to one);

then clipped and min-max normalised like the real maps. The maps are lifted
with :func:`voxe_core.refine.lifting.fit_attention_grids` and cut with
:func:`voxe_core.refine.cut.graph_cut_detailed`. Methods compared, by 3D IoU of
the predicted edit voxels against the truth over the occupied voxels (the
graph's nodes); ``iou_surface`` restricts to nodes seen by at least one view:

* ``graph_cut``: the full method;
* ``threshold_3d``: P_e > 1/2 from the lifted grids, no cut;
* ``vote_2d``: no lifting: a node votes "edit" in each view where it is
  visible (its distance from the camera at most 0.75 voxel beyond the
  rendered depth at its pixel, on the silhouette; 0.75 gave this baseline
  its best IoU on clean maps among 0.5 / 0.75 / 1 / 1.5 / 2 voxels) and the
  edit map exceeds the object map at its pixel; it is an edit voxel when a
  strict majority of its visible views vote so. Nodes no view sees take the
  label of the nearest seen node.

The maps depend on the geometry only, so each corruption draw is lifted once
and cut with both colourings; ``--repeats`` draws per level (default 2),
``summary`` holds the means.

``segmentation_views.png`` shows, for the distinct scene at n = 0.2, four
views of: the object, the corrupted 2D edit map, the lifted edit grid, P_e,
the graph-cut mask (red) and the true region (red).

Also timed (``graph_160``): the graph build + solve at 160³ on the same
scene with noisy truth-derived fields, best of 3; ``graph_160_stress`` adds
noisier fields, the same-colour hat and a uniform sphere filling 27% of the
box (1.08 M nodes). And the storage of the sparse mask and
probability files against dense ones. Writes bench/results/segmentation.json
and segmentation.png.

    python bench/segmentation.py            # ~7-9 min on 2 CPU cores (one thread)
    python bench/segmentation.py --quick    # one noise level, smaller fit
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from voxe_core.cameras import Cameras, random_hemisphere_poses
from voxe_core.grid import VoxelGrid
from voxe_core.refine.config import RefineConfig
from voxe_core.refine.cut import graph_cut_detailed, node_mask, probabilities
from voxe_core.refine.lifting import fit_attention_grids
from voxe_core.refine.maps import gaussian_blur2d, normalize_maps
from voxe_core.refine.renders import render_feature_views
from voxe_core.refine.storage import save_mask, save_probabilities
from voxe_core.render import render_image
from voxe_core.tensorio import save_tensors

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
NOISE_LEVELS = (0.0, 0.1, 0.2, 0.4, 0.6)
WHITE, BLACK, BLUE = (0.92, 0.92, 0.9), (0.08, 0.07, 0.07), (0.15, 0.35, 0.9)
SLOPE = 5.0  # raw density per voxel of depth (sharp, opaque surfaces like a fitted ReLU field)


# ------------------------------------------------------------------ scene
def _logit(c):
    c = torch.as_tensor(c, dtype=torch.float32)
    return torch.log(c / (1 - c))


def cow_with_hat(resolution: int, variant: str = "distinct") -> tuple[VoxelGrid, torch.Tensor]:
    """(grid, truth): truth (X, Y, Z) bool marks the vertices owned by the hat."""
    grid = VoxelGrid(resolution)
    axes = [torch.linspace(float(grid.bbox_min[d]), float(grid.bbox_max[d]), resolution) for d in range(3)]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    p = torch.stack([x, y, z], -1)

    def ellipsoid(center, radii):
        q = (p - torch.tensor(center)) / torch.tensor(radii)
        return (q.norm(dim=-1) - 1.0) * min(radii)  # ~signed distance, negative inside

    def cone(apex, base_z, base_r):
        ax, ay, az = apex
        h = az - base_z
        rho = ((x - ax) ** 2 + (y - ay) ** 2).sqrt()
        radius = base_r * (az - z) / h
        side = (rho - radius) * h / math.hypot(h, base_r)
        return torch.maximum(torch.maximum(side, base_z - z), z - az)

    body = ellipsoid((-0.15, 0.0, -0.25), (0.95, 0.5, 0.45))
    head = ellipsoid((0.8, 0.0, 0.2), (0.36, 0.3, 0.32))
    legs = [ellipsoid((sx, sy, -0.75), (0.13, 0.13, 0.3)) for sx in (-0.75, 0.45) for sy in (-0.28, 0.28)]
    hat = cone((0.8, 0.0, 1.05), 0.38, 0.3)
    cow = torch.minimum(body, head)
    for leg in legs:
        cow = torch.minimum(cow, leg)
    sdf = torch.minimum(cow, hat)
    truth = hat < cow
    with torch.no_grad():
        grid.features[..., 0] = SLOPE * (-sdf) / float(grid.voxel_size.min())
        colour = torch.tensor(WHITE).expand(*sdf.shape, 3).clone()
        spots = ((-0.5, 0.25, -0.05, 0.22), (0.0, -0.3, -0.1, 0.25), (-0.9, -0.1, 0.1, 0.2), (0.2, 0.2, 0.15, 0.17),
                 (0.95, 0.2, 0.3, 0.12))
        for sx, sy, sz, r in spots:
            inside = ((p - torch.tensor([sx, sy, sz])).norm(dim=-1) < r) & ~truth
            colour[inside] = torch.tensor(BLACK)
        if variant == "distinct":
            colour[truth] = torch.tensor(BLUE)
        elif variant != "same":
            raise ValueError(variant)
        grid.features[..., 1:] = _logit(colour)
    return grid, truth


# ------------------------------------------------------------------ synthetic attention
def shift_image(img: torch.Tensor, dx: float, dy: float) -> torch.Tensor:
    """Translate (C, H, W) by (dx, dy) pixels, bilinear, zero fill."""
    c, h, w = img.shape
    theta = torch.tensor([[1.0, 0.0, -2.0 * dx / w], [0.0, 1.0, -2.0 * dy / h]])[None]
    grid = F.affine_grid(theta, (1, c, h, w), align_corners=False)
    return F.grid_sample(img[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0]


def corrupt(edit: torch.Tensor, obj: torch.Tensor, opacity: torch.Tensor, noise: float, gen: torch.Generator):
    """Corrupted, normalised (edit, object) maps of one view (see the module docstring)."""
    size = edit.shape[-1]
    maps = torch.stack([edit, obj])
    if noise > 0:
        sil = (opacity > 0.5).nonzero()
        if sil.numel() and torch.rand((), generator=gen) < noise:  # spurious blob
            cy, cx = sil[torch.randint(0, sil.shape[0], (), generator=gen)].tolist()
            yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
            blob = torch.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * (0.06 * size) ** 2)) * opacity
            maps[0] = torch.maximum(maps[0], blob)
            maps[1] = maps[1] * (1 - blob)
        maps = gaussian_blur2d(maps, noise * 0.1 * size)
        cells = F.adaptive_avg_pool2d(maps[None], 16)[0]
        cells = cells + noise * torch.randn(cells.shape, generator=gen)
        maps = F.interpolate(cells[None], size=(size, size), mode="bilinear", align_corners=False)[0]
        dx, dy = (noise * 0.06 * size * torch.randn(2, generator=gen)).tolist()
        maps = shift_image(maps, dx, dy)
    maps = maps.clamp(0.0, 1.0)
    return normalize_maps(maps)


def synthetic_maps(grid, truth, cameras, noise, seed):
    clean = render_feature_views(grid, cameras, torch.stack([truth.float(), 1 - truth.float()], -1), background=(0.0,))
    gen = torch.Generator().manual_seed(seed)
    edit_maps, object_maps, opacities, depths = [], [], [], []
    for i in range(len(cameras)):
        out = render_image(grid, cameras, i)
        opacities.append(out.opacity)
        depths.append(out.depth)
        e, o = corrupt(clean[i, ..., 0], clean[i, ..., 1], out.opacity, noise, gen)
        edit_maps.append(e)
        object_maps.append(o)
    return torch.stack(edit_maps), torch.stack(object_maps), torch.stack(opacities), torch.stack(depths)


# ------------------------------------------------------------------ per-view 2D baseline
def project(cameras: Cameras, points: torch.Tensor):
    """Pixel (u, v) and ray distance t of world points in every camera: each (N_cams, P); u, v are NaN behind it."""
    r = cameras.c2w[:, :3, :3]
    o = cameras.c2w[:, :3, 3]
    local = torch.einsum("nji,npj->npi", r, points[None] - o[:, None])  # R^T (p - o)
    depth = -local[..., 2]
    behind = torch.where(depth > 0, 0.0, torch.nan)  # a point behind a camera projects to no pixel of it
    u = cameras.cx[:, None] + cameras.fx[:, None] * local[..., 0] / depth + behind
    v = cameras.cy[:, None] - cameras.fy[:, None] * local[..., 1] / depth + behind
    return u, v, (points[None] - o[:, None]).norm(dim=-1)


def vote_2d(grid, nodes, cameras, edit_maps, object_maps, opacities, depths):
    """(predicted edit nodes, visible nodes), both (X, Y, Z) bool; see the module docstring."""
    from scipy.ndimage import distance_transform_edt

    idx = nodes.nonzero()
    lattice = grid.vertex_positions().reshape(*grid.resolution, 3)  # the cameras' frame (a scene grid: uncontracted)
    points = lattice[tuple(idx.T)]
    u, v, t = project(cameras, points)
    h, w = cameras.height, cameras.width
    # a scene grid's outer vertices lie at infinity and project() gives NaN behind a camera: -1 is no pixel
    u, v = u.nan_to_num(nan=-1.0, posinf=-1.0, neginf=-1.0), v.nan_to_num(nan=-1.0, posinf=-1.0, neginf=-1.0)
    ui, vi = u.floor().long(), v.floor().long()
    inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    ui, vi = ui.clamp(0, w - 1), vi.clamp(0, h - 1)
    views = torch.arange(len(cameras))[:, None].expand_as(ui)
    centre = [n // 2 for n in grid.resolution]  # the lattice spacing where the object sits, in the cameras' frame
    spacing = min(float((lattice[tuple(centre[:a] + [centre[a] + 1] + centre[a + 1:])] - lattice[tuple(centre)]).norm())
                  for a in range(3))
    tol = 0.75 * spacing
    visible = inside & (opacities[views, vi, ui] > 0.5) & (t <= depths[views, vi, ui] + tol)
    says_edit = edit_maps[views, vi, ui] > object_maps[views, vi, ui]
    n_visible = visible.sum(0)
    n_edit = (visible & says_edit).sum(0)
    label = 2 * n_edit > n_visible
    seen = n_visible > 0
    vis_grid = torch.zeros_like(nodes)
    vis_grid[tuple(idx[seen].T)] = True
    lab_grid = torch.zeros_like(nodes)
    lab_grid[tuple(idx[seen & label].T)] = True
    _, nearest = distance_transform_edt(~vis_grid.numpy(), return_indices=True)
    filled = torch.from_numpy(lab_grid.numpy()[tuple(nearest)])
    return filled & nodes, vis_grid


def iou(pred: torch.Tensor, truth: torch.Tensor, over: torch.Tensor) -> float:
    p, t = pred & over, truth & over
    union = int((p | t).sum())
    return float(int((p & t).sum()) / union) if union else 1.0


# ------------------------------------------------------------------ runs
def run_level(grids, truth, nodes, cameras, noise, config, seed):
    """One corruption level: the maps and the lifted grids depend on geometry only, so they are
    computed once and cut with each colouring in ``grids`` ({scene: grid}, same density)."""
    geometry = next(iter(grids.values()))
    edit_maps, object_maps, opac, depth = synthetic_maps(geometry, truth, cameras, noise, seed)
    t0 = time.perf_counter()
    e, o = fit_attention_grids(geometry, cameras, edit_maps, object_maps, config)
    fit_s = time.perf_counter() - t0
    p_e, _ = probabilities(e, o)
    t1 = time.perf_counter()
    voted, visible = vote_2d(geometry, nodes, cameras, edit_maps, object_maps, opac, depth)
    vote_s = time.perf_counter() - t1

    def row(method, scene, pred, secs):
        return {"method": method, "scene": scene, "noise": noise, "iou": iou(pred, truth, nodes),
                "iou_surface": iou(pred, truth, visible & nodes), "seconds": round(secs, 3),
                "predicted_voxels": int((pred & nodes).sum())}

    rows, masks = [], {}
    for scene, grid in grids.items():
        mask, stats = graph_cut_detailed(grid, e, o, config)
        masks[scene] = mask
        rows.append(row("graph_cut", scene, mask, fit_s + stats.build_s + stats.solve_s))
        rows[-1]["cut"] = {k: v for k, v in dataclasses.asdict(stats).items() if k != "notes"} | {"notes": stats.notes}
    rows.append(row("threshold_3d", "any", (p_e > 0.5) & nodes, fit_s))
    rows.append(row("vote_2d", "any", voted, vote_s))
    return rows, {"edit_maps": edit_maps, "edit_field": e, "p_edit": p_e, "masks": masks}


def views_figure(grid, truth, cameras, artefacts, path, n_views=4):
    """Rows: object, corrupted 2D edit map, lifted edit grid, P_e, graph-cut mask (red), true region (red)."""
    from voxe_core.export import render_views, save_png
    from voxe_core.refine.renders import iter_attention_views, iter_mask_overlays

    cams = cameras[0:n_views]
    rows = [
        render_views(grid, cams),
        artefacts["edit_maps"][:n_views, ..., None].expand(-1, -1, -1, 3),
        iter_attention_views(grid, artefacts["edit_field"], cams),
        iter_attention_views(grid, artefacts["p_edit"], cams),
        iter_mask_overlays(grid, artefacts["masks"]["distinct"], cams),
        iter_mask_overlays(grid, truth, cams),
    ]
    save_png(path, torch.cat([torch.cat(list(r), dim=1) for r in rows], dim=0))


def time_graph(grid, truth, field_noise: float, seed: int = 0, repeats: int = 3) -> tuple[dict, torch.Tensor]:
    """Best-of-``repeats`` build and solve times of the cut on ``grid`` with noisy truth-derived fields."""
    gen = torch.Generator().manual_seed(seed)
    noise = field_noise * torch.randn(truth.shape, generator=gen)
    e = truth.float() + noise
    o = 1.0 - truth.float() - noise
    config = RefineConfig()
    best = None
    for _ in range(repeats):
        mask, stats = graph_cut_detailed(grid, e, o, config)
        if best is None or stats.build_s + stats.solve_s < best.build_s + best.solve_s:
            best = stats
    nodes = node_mask(grid, config.node_alpha)
    return {
        "resolution": list(grid.resolution), "field_noise": field_noise, "nodes": best.nodes, "edges": best.edges,
        "occupied_fraction": round(best.nodes / truth.numel(), 4),
        "build_s": round(best.build_s, 4), "solve_s": round(best.solve_s, 4),
        "total_s": round(best.build_s + best.solve_s, 4), "repeats": repeats,
        "iou_vs_truth": round(iou(mask, truth, nodes), 4), "threads": torch.get_num_threads(),
    }, mask


def big_sphere(resolution: int = 160, radius: float = 1.2) -> tuple[VoxelGrid, torch.Tensor]:
    """Stress case: a uniformly coloured sphere filling 27% of the box, top cap as the 'edit'."""
    grid = VoxelGrid(resolution)
    axes = torch.linspace(-1.5, 1.5, resolution)
    x, y, z = torch.meshgrid(axes, axes, axes, indexing="ij")
    d = (x**2 + y**2 + z**2).sqrt()
    with torch.no_grad():
        grid.features[..., 0] = SLOPE * (radius - d) / float(grid.voxel_size.min())
        grid.features[..., 1:] = _logit(WHITE)
    return grid, z > 0.6


def storage(grid, truth, mask) -> dict:
    nodes = node_mask(grid)
    p = torch.rand(truth.shape, generator=torch.Generator().manual_seed(0))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_mask(tmp / "mask.safetensors", mask)
        save_tensors(tmp / "mask_dense.safetensors", {"mask": mask.to(torch.uint8)}, kind="dense", version=1, meta={})
        save_probabilities(tmp / "prob.safetensors", p, 1 - p, nodes)
        save_tensors(tmp / "prob_dense.safetensors", {"edit": p, "object": 1 - p}, kind="dense", version=1, meta={})
        sizes = {f.stem: f.stat().st_size for f in tmp.iterdir()}
    return {
        "resolution": list(grid.resolution), "mask_voxels": int(mask.sum()), "nodes": int(nodes.sum()),
        "mask_sparse_bytes": sizes["mask"], "mask_dense_bytes": sizes["mask_dense"],
        "mask_ratio": round(sizes["mask"] / sizes["mask_dense"], 5),
        "probabilities_sparse_bytes": sizes["prob"], "probabilities_dense_bytes": sizes["prob_dense"],
        "probabilities_ratio": round(sizes["prob"] / sizes["prob_dense"], 5),
    }


def plot(runs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    styles = {"distinct": "-", "same": "--"}
    colours = {"graph_cut": "C0", "threshold_3d": "C1", "vote_2d": "C2"}
    for scene in sorted({r["scene"] for r in runs}):
        for method in colours:
            pts = sorted((r["noise"], r["iou_mean"]) for r in runs if r["scene"] == scene and r["method"] == method)
            if pts:
                label = method if scene == "any" else f"{method} ({scene} hat colour)"
                ax.plot(*zip(*pts), styles.get(scene, "-"), marker="o", color=colours[method], label=label)
    ax.axhline(0.9, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("map corruption strength n")
    ax.set_ylabel("3D IoU vs true edit region (mean of draws)")
    ax.set_ylim(0, 1.02)
    ax.set_title("Edit localisation against ground truth")
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=2, help="corruption draws per noise level")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: the fit's ops are small, and OpenMP threads stall on a busy box)")
    parser.add_argument("--out", type=Path, default=RESULTS / "segmentation.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    levels = (0.2,) if args.quick else NOISE_LEVELS
    if args.quick:
        args.repeats = 1
    iterations = 150 if args.quick else args.iterations
    config = RefineConfig(iterations=iterations, rays_per_step=4096, render_size=args.size, views=args.views,
                          fit_views="fixed")
    c2w, _, _ = random_hemisphere_poses(args.views, torch.Generator().manual_seed(1))
    cameras = Cameras.from_fov(c2w, config.fov_x, args.size, args.size)

    start = time.perf_counter()
    runs = []
    grids = {}
    for variant in ("distinct", "same"):
        grids[variant], truth = cow_with_hat(args.resolution, variant)
    nodes = node_mask(grids["distinct"], config.node_alpha)
    scene = {"nodes": int(nodes.sum()), "true_edit_voxels": int((truth & nodes).sum())}
    for k, noise in enumerate(levels):
        for repeat in range(args.repeats):
            rows, artefacts = run_level(grids, truth, nodes, cameras, noise, config, seed=100 + 10 * k + repeat)
            if noise == 0.2 and repeat == 0:
                views_figure(grids["distinct"], truth, cameras, artefacts, args.out.with_name("segmentation_views.png"))
            for r in rows:
                r["repeat"] = repeat
                print(f"n={noise:.1f} #{repeat} {r['method']:12s} {r['scene']:8s} IoU {r['iou']:.3f} "
                      f"(surface {r['iou_surface']:.3f}) {r['seconds']:.1f}s", flush=True)
            runs += rows
    summary = []
    for key in sorted({(r["method"], r["scene"], r["noise"]) for r in runs}):
        sel = [r for r in runs if (r["method"], r["scene"], r["noise"]) == key]
        summary.append({"method": key[0], "scene": key[1], "noise": key[2], "repeats": len(sel),
                        "iou_mean": round(sum(r["iou"] for r in sel) / len(sel), 4),
                        "iou_min": round(min(r["iou"] for r in sel), 4),
                        "iou_surface_mean": round(sum(r["iou_surface"] for r in sel) / len(sel), 4)})
    big_grid, big_truth = cow_with_hat(160)
    graph, big_mask = time_graph(big_grid, big_truth, 0.3)
    stress = [time_graph(big_grid, big_truth, 1.0)[0], time_graph(cow_with_hat(160, "same")[0], big_truth, 1.0)[0],
              time_graph(*big_sphere(), 1.0)[0]]
    stress[0]["case"], stress[1]["case"], stress[2]["case"] = (
        "cow, field noise 1.0", "cow, same-colour hat, field noise 1.0", "uniform sphere r=1.2 (27% occupied)")
    for g in [graph, *stress]:
        print(f"graph 160³ (noise {g['field_noise']}): {g['nodes']} nodes, {g['edges']} edges, "
              f"build {g['build_s']:.3f}s, solve {g['solve_s']:.3f}s", flush=True)
    store = storage(big_grid, big_truth, big_mask)
    print(f"storage: mask {store['mask_sparse_bytes']} B sparse vs {store['mask_dense_bytes']} B dense "
          f"(ratio {store['mask_ratio']}); probabilities ratio {store['probabilities_ratio']}", flush=True)
    result = {
        "description": "3D IoU of the predicted edit region against the exact hat region of an analytic scene; "
                       "see bench/segmentation.py for the corruption model and the methods.",
        "settings": {"resolution": args.resolution, "views": args.views, "render_size": args.size,
                     "iterations": iterations, "rays_per_step": config.rays_per_step, "lr": config.lr,
                     "tv_weight": config.tv_weight, "init_value": config.init_value,
                     "edit_seeds": config.edit_seeds, "object_seeds": config.object_seeds,
                     "sigma": config.sigma, "smoothness": config.smoothness, "node_alpha": config.node_alpha,
                     "threads": torch.get_num_threads()},
        "scene": scene,
        "summary": summary,
        "runs": runs,
        "graph_160": graph,
        "graph_160_stress": stress,
        "storage_160": store,
        "total_seconds": round(time.perf_counter() - start, 1),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    plot(summary, args.out.with_suffix(".png"))
    print(f"wrote {args.out} and {args.out.with_suffix('.png')} in {result['total_seconds']} s")


if __name__ == "__main__":
    main()
