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

``--compare-lens`` instead trains the scene backbone three times on fox's distorted photos
(k1, k2, p1, p2) and writes bench/results/lens_distortion.json and .png:
``rays`` casts each ray through its distorted pixel (``voxe_core.cameras``, the default),
``undistort`` trains pinhole cameras on images undistorted once at full size with OpenCV
(``initUndistortRectifyMap`` + bilinear ``remap``, the same intrinsics, replicated border),
``ignore`` treats the photos as pinhole. All are scored on the original held-out photos,
rendered through the true lens (``ignore``: as the pinhole it assumed); ``undistort`` is also
scored on its own undistorted held-out images.

    python bench/real_scenes.py             # ~15 min on 2 shared cores (67x120 px, 64³)
    python bench/real_scenes.py --compare-lens --resolution 96 --iterations 200 600 --rays 2048
    python bench/real_scenes.py --compare-lens --parallel   # all three at once (a shared, loaded machine)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data" / "fox"
RESULTS = HERE / "results"
BACKBONE_NAMES = ("scene", "relu_field")
LENS_VARIANTS = ("rays", "undistort", "ignore")


def undistorted_copy(scratch: Path) -> Path:
    """fox with every photo undistorted once at full size (OpenCV), as a pinhole dataset in ``scratch``."""
    import cv2
    import numpy as np

    meta = json.loads((DATA / "transforms.json").read_text())
    K = np.array([[meta["fl_x"], 0, meta["cx"]], [0, meta["fl_y"], meta["cy"]], [0, 0, 1]])
    coefficients = np.array([meta.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
    size = (int(meta["w"]), int(meta["h"]))
    map_x, map_y = cv2.initUndistortRectifyMap(K, coefficients, None, K, size, cv2.CV_32FC1)
    root = scratch / "fox_undistorted"
    (root / "images").mkdir(parents=True, exist_ok=True)
    for frame in meta["frames"]:
        target = root / "images" / (Path(frame["file_path"]).stem + ".png")
        if not target.is_file():
            photo = cv2.imread(str(DATA / frame["file_path"]), cv2.IMREAD_COLOR)
            cv2.imwrite(str(target), cv2.remap(photo, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        frame["file_path"] = "images/" + target.name
    for k in ("k1", "k2", "k3", "k4", "p1", "p2"):
        meta.pop(k, None)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


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
    train_images, own_test = train.images, None  # own_test: a variant's own held-out (images, cameras)
    prepare_s = 0.0  # undistorting the photos, once before training
    if args.lens == "ignore":
        train_cams, test_cams = train_cams.undistorted(), test_cams.undistorted()
    elif args.lens == "undistort":
        t0 = time.perf_counter()
        root = undistorted_copy(Path(args.scratch))
        prepare_s = time.perf_counter() - t0
        train_images = load_scene(root, "train", downsample=args.downsample, holdout_every=8).images
        own_test = (load_scene(root, "test", downsample=args.downsample, holdout_every=8).images,
                    test_cams.undistorted())
        train_cams = train_cams.undistorted()
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
        scores = {"psnr": float(psnr(renders, test.images).mean()),
                  "psnr_background": as_psnr(err[~hits].mean()), "psnr_through_box": as_psnr(err[hits].mean())}
        if own_test is not None:
            images, cams = own_test
            own = torch.stack([render_image(grid, cams, i, render_config).rgb for i in range(len(cams))])
            scores["psnr_own_test"] = float(psnr(own, images).mean())
        return scores

    def on_checkpoint(path: str) -> None:
        t0 = time.perf_counter()
        tensors, meta = load_tensors(path, kind="reconstruction_checkpoint", max_version=CHECKPOINT_FORMAT_VERSION)
        grid = grid_from_state(tensors, meta)
        done = sum(config.iterations[: meta["stage"]]) + meta["iteration"]
        curve.append({"iteration": done, "train_s": t0 - start - paused[0], **evaluate(grid)})
        paused[0] += time.perf_counter() - t0

    checkpoint = Path(args.scratch) / f"{backbone}.ckpt"
    grid = reconstruct(train_images, train_cams, config, Callbacks(on_checkpoint=on_checkpoint),
                       checkpoint_path=checkpoint, initial_grid=initial)
    train_s = time.perf_counter() - start - paused[0]
    checkpoint.unlink(missing_ok=True)
    t0 = time.perf_counter()
    final_scores = evaluate(grid)
    render_s = (time.perf_counter() - t0) / len(test_cams)
    return {
        "backbone": backbone, "lens": args.lens, "resolution": final, "iterations": list(args.iterations), "rays_per_step": args.rays,
        "train_s": train_s, "prepare_s": prepare_s, "render_s_per_view": render_s, **final_scores, "curve": curve,
        "grid_bytes": grid.flat_features.numel() * 4,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "image_size": [test_cams.width, test_cams.height], "train_views": len(train), "test_views": len(test),
        "background_pixel_fraction": float((~hits).float().mean()),
    }


def plot(results: list[dict], path: Path, key: str = "backbone") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bars) = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        xs = [p["train_s"] for p in r["curve"]] + [r["train_s"]]
        ys = [p["psnr"] for p in r["curve"]] + [r["psnr"]]
        ax.plot(xs, ys, "o-", label=f"{r[key]} {r['resolution']}³ ({r['peak_rss_mib']:.0f} MiB peak)")
    ax.set_xlabel("training seconds (2 shared cores)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("fox, every 8th view held out")
    ax.legend()
    labels = ["all pixels", "background (rays miss the box)", "rays through the box"]
    keys = ["psnr", "psnr_background", "psnr_through_box"]
    width = 0.8 / len(results)
    for k, r in enumerate(results):
        bars.bar([i + k * width for i in range(3)], [r[name] for name in keys], width, label=r[key])
    bars.set_xticks([i + width * (len(results) - 1) / 2 for i in range(3)], labels, fontsize=8)
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
    parser.add_argument("--compare-lens", action="store_true",
                        help="the scene backbone with each lens variant (rays, undistort, ignore) instead")
    parser.add_argument("--parallel", action="store_true",
                        help="run the variants at once: on a machine loaded by others they share its cores alike "
                             "(sequential runs would each meet a different load)")
    parser.add_argument("--lens", choices=LENS_VARIANTS, default="rays", help=argparse.SUPPRESS)
    parser.add_argument("--single", choices=BACKBONE_NAMES, help=argparse.SUPPRESS)
    parser.add_argument("--scratch", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(run_single(args.single, args)))
        return
    with tempfile.TemporaryDirectory(prefix="real_scenes-") as scratch:  # checkpoints, the undistorted copy
        args.scratch = scratch
        compare(args)


def compare(args) -> None:
    runs = [("scene", lens) for lens in LENS_VARIANTS] if args.compare_lens else [(b, "rays") for b in BACKBONE_NAMES]
    commands = [[sys.executable, __file__, "--single", backbone, "--lens", lens, "--downsample", str(args.downsample),
                 "--resolution", str(args.resolution), "--iterations", *map(str, args.iterations),
                 "--rays", str(args.rays), "--eval-every", str(args.eval_every), "--scratch", args.scratch]
                for backbone, lens in runs]
    prepare_s = None
    if args.parallel:
        if args.compare_lens:  # undistort before the runs start, so no run's clock includes another's preprocessing
            t0 = time.perf_counter()
            undistorted_copy(Path(args.scratch))
            prepare_s = time.perf_counter() - t0
        processes = [subprocess.Popen(c, stdout=subprocess.PIPE, text=True, cwd=HERE.parent) for c in commands]
        outputs = [process.communicate()[0] for process in processes]
        if any(process.returncode for process in processes):
            raise SystemExit("a run failed")
    else:
        outputs = [subprocess.run(c, check=True, stdout=subprocess.PIPE, text=True, cwd=HERE.parent).stdout
                   for c in commands]
    results = []
    for (backbone, lens), output in zip(runs, outputs):
        result = json.loads(output.strip().splitlines()[-1])
        result["parallel"] = args.parallel
        if lens == "undistort" and prepare_s is not None:
            result["prepare_s"] = prepare_s
        results.append(result)
        own = f", own undistorted test {result['psnr_own_test']:.2f}" if "psnr_own_test" in result else ""
        print(f"{backbone:10s} {lens:9s} {result['train_s']:7.1f} s  PSNR {result['psnr']:.2f} dB "
              f"(background {result['psnr_background']:.2f}, through box {result['psnr_through_box']:.2f}{own})  "
              f"render {result['render_s_per_view']:.2f} s/view  peak {result['peak_rss_mib']:.0f} MiB")
    RESULTS.mkdir(exist_ok=True)
    if args.compare_lens:
        rays = results[0]
        summary = {f"{r['lens']}_over_rays_train_time": r["train_s"] / rays["train_s"] for r in results[1:]}
        summary.update({f"{r['lens']}_minus_rays_psnr_db": r["psnr"] - rays["psnr"] for r in results[1:]})
        print(json.dumps(summary, indent=1))
        (RESULTS / "lens_distortion.json").write_text(json.dumps({"runs": results, "summary": summary}, indent=1))
        plot(results, RESULTS / "lens_distortion.png", key="lens")
        return
    scene, relu = results
    summary = {
        "scene_over_relu_train_time": scene["train_s"] / relu["train_s"],
        "scene_minus_relu_psnr_db": scene["psnr"] - relu["psnr"],
        "scene_minus_relu_background_psnr_db": scene["psnr_background"] - relu["psnr_background"],
        "scene_minus_relu_through_box_psnr_db": scene["psnr_through_box"] - relu["psnr_through_box"],
    }
    print(json.dumps(summary, indent=1))
    (RESULTS / "real_scenes.json").write_text(json.dumps({"runs": results, "summary": summary}, indent=1))
    plot(results, RESULTS / "real_scenes.png")


if __name__ == "__main__":
    main()
