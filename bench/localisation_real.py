"""The text-vs-code graph cut on a real-scene grid (issue 18 item 4): ../shared/data/fox, reconstructed here.

A real capture has no true edited part, so the bench designates one: the top fifth of the reconstructed
fox's graph nodes by height (the scene frame's z is up). Its coverage in every training view is the part
mask rendered through the grid's own density (the rest of the nodes: the object's), and from there the maps
follow bench/localisation.py's model (16×16 lattice, clean and moderate degradation). So the grid, its
density, its colours, its floaters and its views are real; the part is a made-up one, and IoU says how well
each cut recovers it. ``agreement`` (IoU of a variant's mask with ``text_5000``'s) and seconds need no
ground truth at all. G_e is the reconstructed grid (no edit is run), so there is no ring PSNR here.

    python bench/localisation_real.py    # ~3 min: a 96³ scene-grid fit of the fox (cached) + 2 lifts
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from types import SimpleNamespace

import torch

from localisation_scenes import CACHE
from localisation_variants import measure
from voxe_core.data import load_scene
from voxe_core.reconstruct import ReconstructConfig, reconstruct
from voxe_core.refine.cut import node_mask
from voxe_core.refine.renders import render_feature_views
from voxe_core.scene_grid import SceneGrid, apply_frame, scene_frame

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data" / "fox"
PART_FRACTION = 0.2  # the highest fifth of the nodes


def fox_grid(cameras, images, frame, resolution: int, iterations: tuple[int, int]) -> SceneGrid:
    """The fox as a scene grid (bench/real_scenes.py's settings), cached under bench/.cache."""
    path = CACHE / f"fox_{resolution}.pt"
    if path.exists():
        return torch.load(path, weights_only=False)
    config = ReconstructConfig.fast(resolutions=(resolution // 2, resolution), iterations=iterations,
                                    image_downsample=(2, 1), rays_per_step=1024)
    grid = reconstruct(images, cameras, config, initial_grid=SceneGrid(resolution // 2, frame=frame))
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(grid, path)
    return grid


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--iterations", type=int, nargs=2, default=(200, 600))
    parser.add_argument("--downsample", type=int, default=16)
    parser.add_argument("--levels", nargs="+", default=["clean", "moderate"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "localisation_real.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    train = load_scene(DATA, "train", downsample=args.downsample, holdout_every=8)
    frame = scene_frame(train.cameras)
    cameras = apply_frame(train.cameras, frame)
    t0 = time.perf_counter()
    grid = fox_grid(cameras, train.images, frame, args.resolution, tuple(args.iterations))
    fit_s = time.perf_counter() - t0
    nodes = node_mask(grid)
    height = torch.arange(grid.resolution[2], dtype=torch.float32).expand(grid.resolution)
    cutoff = torch.quantile(height[nodes], 1.0 - PART_FRACTION)
    part = nodes & (height >= cutoff)
    with torch.no_grad():
        coverage = render_feature_views(grid, cameras, torch.stack([part, nodes & ~part], -1).float())
    scene = SimpleNamespace(name="fox_top_fifth", edited=grid, truth=part, cameras=cameras, coverage=coverage.clamp(0, 1))
    runs = []
    for k, level in enumerate(args.levels):
        runs += measure(scene, level, 100 + k, with_psnr=False)
    result = {
        "description": "Graph-cut variants on a reconstructed real scene (fox) with a designated part (the top fifth "
                       "of its nodes by height); see bench/localisation_real.py.",
        "settings": {"resolution": args.resolution, "iterations": list(args.iterations), "views": len(cameras),
                     "image_size": [cameras.width, cameras.height], "part_fraction": PART_FRACTION,
                     "grid_fit_seconds": round(fit_s, 1), "threads": torch.get_num_threads()},
        "runs": runs,
        "total_seconds": round(time.perf_counter() - start, 1),
    }
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out} in {result['total_seconds']} s")


if __name__ == "__main__":
    main()
