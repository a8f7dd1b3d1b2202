"""Both backbones on a real capture: ../shared/data/fox, every 8th image held out (SPEC §5).

Each backbone trains in its own subprocess (its peak RSS is its own) in the
canonical scene frame (``scene_frame``: centre at the origin, z up, cameras at
radius 4.0311), so the ReLU-field grid's object box [-1.5, 1.5]³ is the scene
backbone's foreground cube. Both grids hold the same number of vertices.
Every ``--eval-every`` iterations a checkpoint is rendered on the held-out
views (that time is not counted as training): PSNR against training seconds.
Held-out pixels are split by geometry: rays that miss the object box
("background", which a ReLU field can only paint white) and rays through it.
Writes bench/results/real_scenes.json and real_scenes.png.

    python bench/real_scenes.py             # ~15 min on 2 shared cores (67x120 px, 64³)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data" / "fox"
RESULTS = HERE / "results"
BACKBONE_NAMES = ("scene", "relu_field")


def run_single(backbone: str, args) -> dict:
    from voxe_core.backbones import grid_from_state
    from voxe_core.cameras import camera_rays
    from voxe_core.data import load_scene
    from voxe_core.grid import DEFAULT_BOX, ray_box_intersection
    from voxe_core.metrics import psnr
    from voxe_core.progress import Callbacks
    from voxe_core.reconstruct import CHECKPOINT_FORMAT_VERSION, ReconstructConfig, reconstruct
    from voxe_core.render import RenderConfig, render_image
    from voxe_core.scene_grid import SceneGrid, apply_frame, scene_frame
    from voxe_core.tensorio import load_tensors

    torch.set_num_threads(os.cpu_count() or 1)
    train = load_scene(DATA, "train", downsample=args.downsample, holdout_every=8)
    test = load_scene(DATA, "test", downsample=args.downsample, holdout_every=8)
    frame = scene_frame(train.cameras)
    train_cams, test_cams = apply_frame(train.cameras, frame), apply_frame(test.cameras, frame)
    box = [torch.tensor(b) for b in DEFAULT_BOX]
    hits = []
    for i in range(len(test_cams)):
        origins, directions = camera_rays(test_cams, i)
        near, far = ray_box_intersection(origins, directions, *box)
        hits.append((far > near).reshape(test_cams.height, test_cams.width))
    hits = torch.stack(hits)
    final = args.resolution
    resolutions = (final // 2, final)
    config = ReconstructConfig.fast(resolutions=resolutions, iterations=tuple(args.iterations),
                                    image_downsample=(2, 1), rays_per_step=args.rays, checkpoint_every=args.eval_every)
    initial = SceneGrid(resolutions[0], frame=frame) if backbone == "scene" else None
    render_config = RenderConfig(step_ratio=0.8)
    curve, paused = [], [0.0]
    start = time.perf_counter()

    def evaluate(grid) -> dict:
        renders = torch.stack([render_image(grid, test_cams, i, render_config).rgb for i in range(len(test_cams))])
        err = (renders - test.images).square().mean(-1)  # (N, H, W)
        as_psnr = lambda mse: float(-10 * torch.log10(mse))  # noqa: E731
        return {"psnr": float(psnr(renders, test.images).mean()),
                "psnr_background": as_psnr(err[~hits].mean()), "psnr_through_box": as_psnr(err[hits].mean())}

    def on_checkpoint(path: str) -> None:
        t0 = time.perf_counter()
        tensors, meta = load_tensors(path, kind="reconstruction_checkpoint", max_version=CHECKPOINT_FORMAT_VERSION)
        grid = grid_from_state(tensors, meta)
        done = sum(config.iterations[: meta["stage"]]) + meta["iteration"]
        curve.append({"iteration": done, "train_s": t0 - start - paused[0], **evaluate(grid)})
        paused[0] += time.perf_counter() - t0

    checkpoint = Path(args.scratch) / f"{backbone}.ckpt"
    grid = reconstruct(train.images, train_cams, config, Callbacks(on_checkpoint=on_checkpoint),
                       checkpoint_path=checkpoint, initial_grid=initial)
    train_s = time.perf_counter() - start - paused[0]
    checkpoint.unlink(missing_ok=True)
    t0 = time.perf_counter()
    final_scores = evaluate(grid)
    render_s = (time.perf_counter() - t0) / len(test_cams)
    return {
        "backbone": backbone, "resolution": final, "iterations": list(args.iterations), "rays_per_step": args.rays,
        "train_s": train_s, "render_s_per_view": render_s, **final_scores, "curve": curve,
        "grid_bytes": grid.flat_features.numel() * 4,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "image_size": [test_cams.width, test_cams.height], "train_views": len(train), "test_views": len(test),
        "background_pixel_fraction": float((~hits).float().mean()),
    }


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bars) = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        xs = [p["train_s"] for p in r["curve"]] + [r["train_s"]]
        ys = [p["psnr"] for p in r["curve"]] + [r["psnr"]]
        ax.plot(xs, ys, "o-", label=f"{r['backbone']} {r['resolution']}³ ({r['peak_rss_mib']:.0f} MiB peak)")
    ax.set_xlabel("training seconds (2 shared cores)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("fox, every 8th view held out")
    ax.legend()
    labels = ["all pixels", "background (rays miss the box)", "rays through the box"]
    keys = ["psnr", "psnr_background", "psnr_through_box"]
    width = 0.38
    for k, r in enumerate(results):
        bars.bar([i + k * width for i in range(3)], [r[key] for key in keys], width, label=r["backbone"])
    bars.set_xticks([i + width / 2 for i in range(3)], labels, fontsize=8)
    bars.set_ylabel("final held-out PSNR (dB)")
    bars.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--downsample", type=int, default=16)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--iterations", type=int, nargs=2, default=(100, 200))
    parser.add_argument("--rays", type=int, default=1024)
    parser.add_argument("--eval-every", type=int, default=100)
    parser.add_argument("--single", choices=BACKBONE_NAMES, help=argparse.SUPPRESS)
    parser.add_argument("--scratch", default="/tmp", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(run_single(args.single, args)))
        return
    results = []
    for backbone in BACKBONE_NAMES:
        command = [sys.executable, __file__, "--single", backbone, "--downsample", str(args.downsample),
                   "--resolution", str(args.resolution), "--iterations", *map(str, args.iterations),
                   "--rays", str(args.rays), "--eval-every", str(args.eval_every)]
        out = subprocess.run(command, check=True, stdout=subprocess.PIPE, text=True, cwd=HERE.parent)
        result = json.loads(out.stdout.strip().splitlines()[-1])
        results.append(result)
        print(f"{backbone:10s} {result['train_s']:7.1f} s  PSNR {result['psnr']:.2f} dB "
              f"(background {result['psnr_background']:.2f}, through box {result['psnr_through_box']:.2f})  "
              f"render {result['render_s_per_view']:.2f} s/view  peak {result['peak_rss_mib']:.0f} MiB")
    scene, relu = results
    summary = {
        "scene_over_relu_train_time": scene["train_s"] / relu["train_s"],
        "scene_minus_relu_psnr_db": scene["psnr"] - relu["psnr"],
        "scene_minus_relu_background_psnr_db": scene["psnr_background"] - relu["psnr_background"],
        "scene_minus_relu_through_box_psnr_db": scene["psnr_through_box"] - relu["psnr_through_box"],
    }
    print(json.dumps(summary, indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "real_scenes.json").write_text(json.dumps({"runs": results, "summary": summary}, indent=1))
    plot(results, RESULTS / "real_scenes.png")


if __name__ == "__main__":
    main()
