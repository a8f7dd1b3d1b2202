"""Local-edit localisation on rendered ground truth: lifting + graph cut against a true 3D part mask.

Scenes: bench/localisation_scenes.py (Blender renders of Spot + party hat and horse + saddlebag, voxelised
G_i / G_e and the true part mask). The 2D maps are made from each view's true coverage (part → edit map,
rest of the object → object map), the way real cross-attention degrades it, per level:

* pooled to the 16×16 attention lattice (area mean) — every level, "clean" is only this;
* blur on the lattice (std ``blur`` cells) and Gaussian noise per cell (std ``noise``);
* leakage: ``leak`` × the object's coverage added to the edit map;
* spurious blobs: in a fraction ``blobs`` of the views a blob (amplitude 0.6, 1.5 cells) on the silhouette;
* weak or missing response: in a fraction ``weak`` of the views the edit map is scaled by U(0, 0.5);

then smoothed, upsampled and min-max normalised by the pipeline's own ``postprocess_maps``.
Methods (3D IoU against the true part over the graph's nodes): ``graph_cut``, ``threshold`` (P_e > 1/2)
and ``vote_2d`` (bench/segmentation.py's per-view vote, no lifting). Lifts: ``backprojection`` (the
default start, ``--iterations`` Adam steps after it, 0 = the back-projection is the answer) and, once
per scene at ``--paper-level``, ``paper_fit`` (constant start, 1,500 steps, the paper's). The merged
grid G_r is rendered on every other view of the 24-view ring: ``merged_psnr`` against Blender's render of the edited object,
``preserved_psnr`` against the original outside the part's 2D mask (G_e carries a colour drift outside
the part, so a mask that takes too much loses preserved PSNR, one that takes too little loses merged PSNR).

At ``--paper-level`` every ``--iterations`` value runs (others: the first only). Grids are 96³ by default
(the full run took 677 s on this shared 2-core box, 279 s of it the paper fit), plus one back-projection
run at ``--timing-resolution`` 160³ for the lift's time there (the Blender renders are 200 px either way).

    python bench/localisation.py           # both scenes, three levels
    python bench/localisation.py --quick   # spot only, moderate, 96³, no paper fit
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from localisation_scenes import SCENES, build_scene
from segmentation import iou, vote_2d
from voxe_core.constants import OBJECT_SEEDS
from voxe_core.refine.config import PAPER_TEXT_FIT, RefineConfig
from voxe_core.refine.cut import graph_cut_detailed, node_mask, probabilities
from voxe_core.refine.lifting import fit_attention_grids
from voxe_core.refine.maps import postprocess_maps
from voxe_core.refine.pipeline import merge
from voxe_core.render import render_image

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
LEVELS = {
    "clean": dict(blur=0.0, noise=0.0, leak=0.0, blobs=0.0, weak=0.0),
    "moderate": dict(blur=0.5, noise=0.05, leak=0.15, blobs=0.1, weak=0.1),
    "hard": dict(blur=1.0, noise=0.1, leak=0.3, blobs=0.25, weak=0.2),
}
LATTICE = 16


def lattice_maps(coverage: torch.Tensor, level: dict, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, H, W, 2) part/object coverage -> (edit, object) maps (V, 16, 16) as the model's level says."""
    from voxe_core.refine.maps import gaussian_blur2d

    gen = torch.Generator().manual_seed(seed)
    cells = F.adaptive_avg_pool2d(coverage.permute(0, 3, 1, 2), LATTICE)  # (V, 2, 16, 16)
    edit, obj = cells[:, 0].clone(), cells[:, 1].clone()
    edit = edit + level["leak"] * obj
    yy, xx = torch.meshgrid(torch.arange(LATTICE), torch.arange(LATTICE), indexing="ij")
    for v in range(len(edit)):
        if torch.rand((), generator=gen) < level["blobs"]:
            sil = (obj[v] > 0.5).nonzero()
            if len(sil):
                cy, cx = sil[torch.randint(0, len(sil), (), generator=gen)].tolist()
                edit[v] = edit[v] + 0.6 * torch.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 1.5**2))
        if torch.rand((), generator=gen) < level["weak"]:
            edit[v] = edit[v] * 0.5 * torch.rand((), generator=gen)
    both = gaussian_blur2d(torch.stack([edit, obj], 1), level["blur"])
    both = (both + level["noise"] * torch.randn(both.shape, generator=gen)).clamp_min(0.0)
    return both[:, 0], both[:, 1]


def scene_maps(scene, level_name: str, seed: int, config) -> tuple[torch.Tensor, torch.Tensor]:
    """Edit and object maps (V, H, W) of ``scene``'s views at noise level ``level_name``: ``lattice_maps``, then
    the pipeline's own ``postprocess_maps`` under ``config``."""
    edit_cells, object_cells = lattice_maps(scene.coverage, LEVELS[level_name], seed)
    size = (scene.cameras.height, scene.cameras.width)
    return postprocess_maps(edit_cells, size, config), postprocess_maps(object_cells, size, config)


def fewer_views(scene, views: int, size: int):
    """``scene`` with its first ``views`` hemisphere views at ``size`` px (coverage kept at Blender's size: the maps
    are pooled to the 16×16 lattice first); a different name, so its cached vote renders are its own."""
    cameras = scene.cameras[:views].resized(size, size)
    return dataclasses.replace(scene, name=f"{scene.name}_{views}v{size}", cameras=cameras, coverage=scene.coverage[:views])


def psnr(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor | None = None) -> float:
    err = (a - b).pow(2).mean(-1)
    mse = err.mean() if where is None else err[where].mean()
    return float(-10 * torch.log10(mse.clamp_min(1e-10)))


RING_EVERY = 2  # every other of the 24 ring views (12, 30° apart): renders of G_r dominate the run otherwise


def ring_psnrs(scene, merged) -> tuple[float, float]:
    views = range(0, len(scene.ring), RING_EVERY)
    renders = torch.stack([render_image(merged, scene.ring, i).rgb for i in views])
    outside = scene.ring_coverage[::RING_EVERY, ..., 0] < 0.5
    return psnr(renders, scene.ring_edited[::RING_EVERY]), psnr(renders, scene.ring_original[::RING_EVERY], outside)


def hemisphere_views(scene, resolution):
    """Opacity and depth (V, H, W) of G_e in the hemisphere views (the 2D vote needs them), cached."""
    from localisation_scenes import CACHE

    path = CACHE / scene.name / f"views_{resolution}.pt"
    if not path.exists():
        views = [render_image(scene.edited, scene.cameras, i) for i in range(len(scene.cameras))]
        torch.save((torch.stack([v.opacity for v in views]), torch.stack([v.depth for v in views])), path)
    return torch.load(path)


def run(scene, level_name, config, lift_name, seed, nodes, views_info):
    t0 = time.perf_counter()
    edit_maps, object_maps = scene_maps(scene, level_name, seed, config)
    maps_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    e, o = fit_attention_grids(scene.edited, scene.cameras, edit_maps, object_maps, config)
    lift_s = time.perf_counter() - t0
    mask, stats = graph_cut_detailed(scene.edited, e, o, config)
    cut_s = stats.build_s + stats.solve_s
    p_e, _ = probabilities(e, o)
    t0 = time.perf_counter()
    voted, _ = vote_2d(scene.edited, nodes, scene.cameras, edit_maps, object_maps, *views_info) if views_info else (mask, 0)
    vote_s = time.perf_counter() - t0
    rows = []
    paper_seeds, paper_stats = graph_cut_detailed(scene.edited, e, o, dataclasses.replace(config, object_seeds=OBJECT_SEEDS))
    methods = [("graph_cut", mask, cut_s), ("graph_cut_200_object_seeds", paper_seeds, paper_stats.build_s + paper_stats.solve_s),
               ("threshold", (p_e > 0.5) & nodes, 0.0), ("vote_2d", voted, vote_s)]
    for method, pred, secs in methods:
        if method != "graph_cut" and (lift_name != "backprojection" or config.iterations):
            continue
        t1 = time.perf_counter()
        merged_psnr, preserved_psnr = ring_psnrs(scene, merge(scene.initial, scene.edited, pred))
        rows.append({
            "scene": scene.name, "resolution": scene.truth.shape[0], "noise": level_name, "method": method, "lift": lift_name,
            "iterations": config.iterations, "iou": round(iou(pred, scene.truth, nodes), 4),
            "predicted_voxels": int((pred & nodes).sum()), "true_voxels": int((scene.truth & nodes).sum()),
            "maps_seconds": round(maps_s, 3), "lift_seconds": round(lift_s, 2) if method != "vote_2d" else 0.0,
            "cut_seconds": round(secs, 3) if method != "threshold" else 0.0,
            "merge_render_seconds": round(time.perf_counter() - t1, 2),
            "merged_psnr": round(merged_psnr, 2), "preserved_psnr": round(preserved_psnr, 2),
        })
        print(f"{scene.name:16s} {level_name:8s} {lift_name:14s} it={config.iterations:4d} {method:9s} "
              f"IoU {rows[-1]['iou']:.3f} lift {lift_s:6.1f}s cut {secs:5.2f}s merged {merged_psnr:5.2f} dB "
              f"preserved {preserved_psnr:5.2f} dB", flush=True)
    return rows


def plot(runs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    levels = list(LEVELS)
    for k, scene in enumerate(sorted({r["scene"] for r in runs})):
        for method, colour in (("graph_cut", "C0"), ("threshold", "C1"), ("vote_2d", "C2")):
            sel = [r for r in runs if r["scene"] == scene and r["method"] == method and r["lift"] == "backprojection"
               and r["iterations"] == 0 and r["resolution"] == runs[0]["resolution"]]
            pts = sorted((levels.index(r["noise"]), r["iou"]) for r in sel)
            if pts:
                axes[0].plot(*zip(*pts), ["-", "--"][k % 2], marker="o", color=colour, label=f"{method} ({scene})")
        paper = [r for r in runs if r["scene"] == scene and r["lift"] == "paper_fit"]
        for r in paper:
            axes[0].plot(levels.index(r["noise"]), r["iou"], "k*", ms=10, label=f"paper fit ({scene})")
    axes[0].set_xticks(range(len(levels)), levels)
    axes[0].set_ylabel("3D IoU vs true part")
    axes[0].set_ylim(0, 1)
    axes[0].axhline(0.9, color="grey", lw=0.8, ls=":")
    axes[0].legend(fontsize=6)
    for r in runs:
        if r["method"] == "graph_cut":
            axes[1].scatter(r["lift_seconds"], r["iou"], color="k" if r["lift"] == "paper_fit" else "C0", s=12)
    axes[1].set_xscale("log")
    axes[1].set_xlabel("lift seconds (log)")
    axes[1].set_ylabel("graph-cut IoU")
    axes[1].set_title("black: paper's 1,500-step fit")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--iterations", type=int, nargs="+", default=[0, 100],
                        help="Adam steps after the back-projection (each value is a run)")
    parser.add_argument("--paper-level", default="moderate", help="level of the paper-fit run per scene, or 'none'")
    parser.add_argument("--paper-scenes", nargs="*", default=["spot_hat"], help="scenes of the paper-fit run")
    parser.add_argument("--timing-resolution", type=int, default=160,
                        help="one more back-projection run (spot_hat, moderate, no 2D vote) at this resolution; 0: none")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (more stall on a shared, loaded box)")
    parser.add_argument("--out", type=Path, default=RESULTS / "localisation.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scenes = ["spot_hat"] if args.quick else list(SCENES)
    levels = ["moderate"] if args.quick else list(LEVELS)
    if args.quick:
        args.iterations, args.paper_level = [0], "none"
    start = time.perf_counter()
    runs = []
    for name in scenes:
        scene = build_scene(name, args.resolution)
        nodes = node_mask(scene.edited)
        views_info = hemisphere_views(scene, args.resolution)
        for k, level in enumerate(levels):
            for iterations in (args.iterations if level == args.paper_level else args.iterations[:1]):
                config = RefineConfig(iterations=iterations, render_size=scene.cameras.width, views=len(scene.cameras),
                                      fit_views="fixed")
                runs += run(scene, level, config, "backprojection", 100 + k, nodes, views_info)
            if level == args.paper_level and name in args.paper_scenes:
                config = RefineConfig(render_size=scene.cameras.width, views=len(scene.cameras), **PAPER_TEXT_FIT)
                runs += run(scene, level, config, "paper_fit", 100 + k, nodes, views_info)
    if args.timing_resolution and not args.quick:
        scene = build_scene("spot_hat", args.timing_resolution)
        config = RefineConfig(iterations=0, render_size=scene.cameras.width, views=len(scene.cameras))
        runs += [r for r in run(scene, "moderate", config, "backprojection", 101, node_mask(scene.edited), None)
                 if r["method"].startswith("graph_cut")]
    result = {
        "description": "3D IoU of the edit mask against the true part of Blender-rendered meshes, ring PSNR of the "
                       "merged grid, seconds per step; see bench/localisation.py for the map model.",
        "settings": {"resolution": args.resolution, "views": 100, "render_size": 200, "ring_views": 24 // RING_EVERY,
                     "levels": LEVELS, "threads": torch.get_num_threads(),
                     "refine_config": {k: v for k, v in vars(RefineConfig()).items() if k != "render"}},
        "runs": runs,
        "total_seconds": round(time.perf_counter() - start, 1),
    }
    write_results(result, args.out, plot)


def parse_with_common_arguments(parser: argparse.ArgumentParser, out: Path | None, threads: int = 1) -> argparse.Namespace:
    """``parser``'s arguments plus --resolution (96), --threads and --out; torch's thread count set from them."""
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--threads", type=int, default=threads, help="torch threads (more stall on a shared, loaded box)")
    parser.add_argument("--out", type=Path, default=out)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    return args


def write_results(result: dict, out: Path, plot_runs) -> None:
    """``result`` as JSON at ``out`` and ``plot_runs(result["runs"], <out>.png)`` beside it."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    plot_runs(result["runs"], out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')} in {result['total_seconds']} s")


if __name__ == "__main__":
    main()
