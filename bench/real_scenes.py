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
from dataclasses import replace
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


def framed_splits(downsample: int):
    """Fox's train and test splits (every 8th photo held out) and the canonical frame of its training cameras.

    Returns (train scene, test scene, frame (4, 4), train cameras, test cameras), the cameras in that frame.
    """
    from voxe_core.data import load_scene
    from voxe_core.scene_grid import apply_frame, scene_frame

    train = load_scene(DATA, "train", downsample=downsample, holdout_every=8)
    test = load_scene(DATA, "test", downsample=downsample, holdout_every=8)
    frame = scene_frame(train.cameras)  # from all training cameras, as the preset's fit of them would
    return train, test, frame, apply_frame(train.cameras, frame), apply_frame(test.cameras, frame)


def checkpoint_grid(path, config):
    """The grid of a fit's checkpoint at ``path`` and how many of ``config``'s iterations it had done."""
    from voxe_core.backbones import grid_from_state
    from voxe_core.reconstruct import load_checkpoint

    tensors, meta = load_checkpoint(path)
    return grid_from_state(tensors, meta), sum(config.iterations[: meta["stage"]]) + meta["iteration"]


def box_hits(cameras) -> torch.Tensor:
    """(N, H, W) bool: which pixels' rays pass through the object box [-1.5, 1.5]³ of the canonical frame."""
    from voxe_core.cameras import camera_rays
    from voxe_core.grid import DEFAULT_BOX, ray_box_intersection

    box = [torch.tensor(b) for b in DEFAULT_BOX]
    hits = []
    for i in range(len(cameras)):
        origins, directions = camera_rays(cameras, i)
        near, far = ray_box_intersection(origins, directions, *box)
        hits.append((far > near).reshape(cameras.height, cameras.width))
    return torch.stack(hits)


def held_out_scores(grid, images: torch.Tensor, cameras, hits: torch.Tensor) -> dict:
    """Held-out PSNR: the mean of per-view PSNRs, and pooled over the pixels whose rays miss / pass the box."""
    from voxe_core.metrics import psnr
    from voxe_core.render import RenderConfig, render_image

    config = RenderConfig(step_ratio=0.8)
    renders = torch.stack([render_image(grid, cameras, i, config).rgb for i in range(len(cameras))])
    err = (renders - images).square().mean(-1)  # (N, H, W)
    as_psnr = lambda mse: float(-10 * torch.log10(mse))  # noqa: E731
    return {"psnr": float(psnr(renders, images).mean()),
            "psnr_background": as_psnr(err[~hits].mean()), "psnr_through_box": as_psnr(err[hits].mean())}


def run_single(backbone: str, args) -> dict:
    from voxe_core.data import load_scene
    from voxe_core.presets import reconstruct_config, reconstruction_params
    from voxe_core.progress import Callbacks
    from voxe_core.reconstruct import reconstruct
    from voxe_core.scene_grid import SceneGrid

    torch.set_num_threads(os.cpu_count() or 1)
    train, test, frame, train_cams, test_cams = framed_splits(args.downsample)
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
    hits = box_hits(test_cams)
    if args.scene_preset:  # what `voxe reconstruct` and jobs fit a capture with by default
        config = reconstruct_config(reconstruction_params({"reconstruction": {"seed": args.seed}}),
                                    args.eval_every, backbone)
    else:
        config = bench_config(args, checkpoint_every=args.eval_every)
    initial = SceneGrid(config.resolutions[0], frame=frame) if backbone == "scene" else None
    curve, paused, paused_cpu = [], [0.0], [0.0]
    start, cpu_start = time.perf_counter(), time.process_time()

    def evaluate(grid) -> dict:
        scores = held_out_scores(grid, test.images, test_cams, hits)
        if own_test is not None:
            scores["psnr_own_test"] = held_out_scores(grid, *own_test, box_hits(own_test[1]))["psnr"]
        return scores

    def on_checkpoint(path: str) -> None:
        t0, c0 = time.perf_counter(), time.process_time()
        grid, done = checkpoint_grid(path, config)
        curve.append({"iteration": done, "train_s": t0 - start - paused[0], "cpu_s": c0 - cpu_start - paused_cpu[0],
                      **evaluate(grid)})
        paused[0] += time.perf_counter() - t0
        paused_cpu[0] += time.process_time() - c0

    last_stage_samples = []  # samples per ray of the final stage's steps (empty-space skipping's cost)

    def on_progress(report) -> None:
        if report.info["stage"] == len(config.resolutions) - 1:
            last_stage_samples.append(report.info["samples_per_ray"])

    checkpoint = Path(args.scratch) / f"{backbone}.ckpt"
    grid = reconstruct(train_images, train_cams, config, Callbacks(on_progress, on_checkpoint=on_checkpoint),
                       checkpoint_path=checkpoint, initial_grid=initial)
    train_s = time.perf_counter() - start - paused[0]  # cpu_s is read in the result below, before evaluating
    checkpoint.unlink(missing_ok=True)
    cpu_s = time.process_time() - cpu_start - paused_cpu[0]
    t0 = time.perf_counter()
    final_scores = evaluate(grid)
    render_s = (time.perf_counter() - t0) / len(test_cams)
    return {
        "backbone": backbone, "lens": args.lens, "seed": config.seed, "preset": "scene" if args.scene_preset else "bench",
        "resolution": config.resolutions[-1], "resolutions": list(config.resolutions),
        "iterations": list(config.iterations), "rays_per_step": config.rays_per_step,
        "average_from": config.average_from, "early_stop": config.render.early_stop,
        "train_s": train_s, "cpu_s": cpu_s, "load": os.getloadavg(),
        "prepare_s": prepare_s, "render_s_per_view": render_s, **final_scores, "curve": curve,
        "samples_per_ray": sum(last_stage_samples) / len(last_stage_samples),
        "occupied_fraction": grid.occupancy(config.render.sigma_threshold).fraction,
        "grid_bytes": grid.flat_features.numel() * 4,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "image_size": [test_cams.width, test_cams.height], "train_views": len(train), "test_views": len(test),
        "background_pixel_fraction": float((~hits).float().mean()),
    }


def bench_config(args, checkpoint_every: int = 0):
    """The comparison's recipe: two stages (half, then full ``--resolution``), ``--iterations``, ``--rays``, each
    step's rays from every image and rendered as a capture's fit renders (``scene()``'s early stop, which object
    fits go without) at ``scene()``'s lr for both backbones (``ReconstructConfig.for_backbone``), without the
    priors a capture's named preset has kept since 2026-12-05: the recipe the records were measured with."""
    from reconstruction import WITHOUT_CAPTURE_PRIORS

    from voxe_core.reconstruct import ReconstructConfig

    config = ReconstructConfig.fast(resolutions=(args.resolution // 2, args.resolution),
                                    iterations=tuple(args.iterations), image_downsample=(2, 1), rays_per_step=args.rays,
                                    seed=args.seed, checkpoint_every=checkpoint_every).for_backbone("scene")
    return replace(config, **WITHOUT_CAPTURE_PRIORS)


def step_cost(args) -> dict:
    """Cost of one training iteration of each backbone at the same resolution and rays, timed interleaved.

    Both backbones are fitted first (``bench_config``), so the grids have the occupancy a fit has;
    then ``--cost-steps`` rounds each time one ``train_step`` of every variant in turn (ReLU field,
    scene backbone, scene backbone without early stop), from the fitted grid with a fresh optimizer,
    so a change of the machine's load falls on all alike. Wall and process CPU seconds per step, the
    samples per ray, and the L1 loss of the timed steps (the accuracy they run at).
    """
    from voxe_core.reconstruct import _stage_data, make_optimizer, reconstruct, train_step
    from voxe_core.scene_grid import SceneGrid

    torch.set_num_threads(os.cpu_count() or 1)
    train, test, frame, cams, test_cams = framed_splits(args.downsample)
    config = bench_config(args)
    fitted = {"relu_field": reconstruct(train.images, cams, config),
              "scene": reconstruct(train.images, cams, config, initial_grid=SceneGrid(config.resolutions[0], frame=frame))}
    hits = box_hits(test_cams)
    held_out = {name: held_out_scores(grid, test.images, test_cams, hits) for name, grid in fitted.items()}
    rays = _stage_data(train.images, cams, 1)
    variants = {"relu_field": ("relu_field", config.render.early_stop), "scene": ("scene", config.render.early_stop),
                "scene_no_early_stop": ("scene", 0.0)}
    state = {}
    for name, (backbone, early_stop) in variants.items():
        grid = fitted[backbone].clone_grid()
        variant_config = replace(config, render=replace(config.render, early_stop=early_stop))
        state[name] = (grid, make_optimizer(grid, variant_config, config.lr), variant_config,
                       grid.occupancy(config.render.sigma_threshold), torch.Generator().manual_seed(args.seed))
    timings = {name: {"wall_s": [], "cpu_s": [], "samples_per_ray": [], "l1": []} for name in variants}
    load_before = os.getloadavg()
    for round_ in range(args.cost_warmup + args.cost_steps):
        for name, (grid, optimizer, variant_config, occupancy, generator) in state.items():
            t0, c0 = time.perf_counter(), time.process_time()
            losses, out = train_step(grid, optimizer, rays, variant_config, occupancy, generator)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if round_ >= args.cost_warmup:
                record = timings[name]
                record["wall_s"].append(wall)
                record["cpu_s"].append(cpu)
                record["samples_per_ray"].append(out.samples / config.rays_per_step)
                record["l1"].append(float(losses["l1"].detach()))
    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    summary = {name: {key: mean(values) for key, values in record.items()} for name, record in timings.items()}
    relu = summary["relu_field"]
    ratios = {f"{name}_over_relu_{key}": summary[name][key] / relu[key]
              for name in ("scene", "scene_no_early_stop") for key in ("wall_s", "cpu_s")}
    return {"resolution": args.resolution, "rays_per_step": args.rays, "fit_iterations": list(args.iterations),
            "seed": args.seed, "steps": args.cost_steps, "warmup": args.cost_warmup, "threads": torch.get_num_threads(),
            "load_before": load_before, "load_after": os.getloadavg(), "held_out_after_fit": held_out,
            "per_step": summary, **ratios, "timings": timings}


def write_results(key: str, value) -> None:
    """``value`` under ``key`` in bench/results/real_scenes.json, keeping what the other modes wrote there."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / "real_scenes.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    results[key] = value
    path.write_text(json.dumps(results, indent=1))


def plot_seed_curves(runs: list[dict], path: Path) -> None:
    """Held-out PSNR against training seconds per seed (all pixels, rays through the box, background), spread shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("psnr", "all pixels"), ("psnr_through_box", "rays through the box"), ("psnr_background", "background")]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), sharey=True)
    for ax, (key, title) in zip(axes, keys):
        for r in runs:
            ax.plot([p["train_s"] for p in r["curve"]] + [r["train_s"]], [p[key] for p in r["curve"]] + [r[key]],
                    "o-", ms=3, label=f"seed {r['seed']} (final {r[key]:.2f} dB)")
        points = min(len(r["curve"]) for r in runs)
        xs = [sum(r["curve"][i]["train_s"] for r in runs) / len(runs) for i in range(points)]
        lo = [min(r["curve"][i][key] for r in runs) for i in range(points)]
        hi = [max(r["curve"][i][key] for r in runs) for i in range(points)]
        ax.fill_between(xs, lo, hi, alpha=0.2, label="seed spread")
        ax.axhline(24.0, color="grey", ls="--", lw=0.8)
        ax.set_title(title)
        ax.set_xlabel("training seconds")
        ax.legend(fontsize=7)
    axes[0].set_ylabel("held-out PSNR (dB)")
    r = runs[0]
    fig.suptitle(f"fox, scene backbone, default scene preset ({'→'.join(map(str, r['resolutions']))}, "
                 f"{'+'.join(map(str, r['iterations']))} it, {r['rays_per_step']} rays), every 8th view held out")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


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
    parser.add_argument("--step-cost", action="store_true",
                        help="time both backbones' training steps interleaved in one process instead "
                             "(results/real_scenes.json 'step_cost')")
    parser.add_argument("--cost-steps", type=int, default=20, help="timed rounds of --step-cost")
    parser.add_argument("--cost-warmup", type=int, default=3)
    parser.add_argument("--seed-curves", action="store_true",
                        help="the scene backbone with its default preset (what `voxe reconstruct` fits a capture "
                             "with), one run per --seeds; results/real_scenes.json 'seed_curves', real_scenes_seeds.png")
    parser.add_argument("--seeds", type=int, nargs="+", default=(0, 1, 2))
    parser.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--scene-preset", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--lens", choices=LENS_VARIANTS, default="rays", help=argparse.SUPPRESS)
    parser.add_argument("--single", choices=BACKBONE_NAMES, help=argparse.SUPPRESS)
    parser.add_argument("--scratch", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(run_single(args.single, args)))
        return
    if args.step_cost:
        result = step_cost(args)
        print(json.dumps({k: v for k, v in result.items() if k != "timings"}, indent=1))
        write_results("step_cost", result)
        return
    with tempfile.TemporaryDirectory(prefix="real_scenes-") as scratch:  # checkpoints, the undistorted copy
        args.scratch = scratch
        compare(args)


def compare(args) -> None:
    if args.seed_curves:
        runs = [("scene", "rays", seed) for seed in args.seeds]
    elif args.compare_lens:
        runs = [("scene", lens, args.seed) for lens in LENS_VARIANTS]
    else:
        runs = [(b, "rays", args.seed) for b in BACKBONE_NAMES]
    commands = [[sys.executable, __file__, "--single", backbone, "--lens", lens, "--downsample", str(args.downsample),
                 "--resolution", str(args.resolution), "--iterations", *map(str, args.iterations),
                 "--rays", str(args.rays), "--eval-every", str(args.eval_every), "--scratch", args.scratch,
                 "--seed", str(seed), *(["--scene-preset"] if args.seed_curves else [])]
                for backbone, lens, seed in runs]
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
    for (backbone, lens, _), output in zip(runs, outputs):
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
    if args.seed_curves:
        finals = {key: [r[key] for r in results] for key in ("psnr", "psnr_through_box", "psnr_background", "train_s")}
        spread = {key: {"min": min(v), "max": max(v), "mean": sum(v) / len(v)} for key, v in finals.items()}
        print(json.dumps(spread, indent=1))
        write_results("seed_curves", {"runs": results, "final": spread})
        plot_seed_curves(results, RESULTS / "real_scenes_seeds.png")
        return
    if args.compare_lens:
        rays = results[0]
        summary = {f"{r['lens']}_over_rays_train_time": r["train_s"] / rays["train_s"] for r in results[1:]}
        summary.update({f"{r['lens']}_minus_rays_psnr_db": r["psnr"] - rays["psnr"] for r in results[1:]})
        print(json.dumps(summary, indent=1))
        (RESULTS / "lens_distortion.json").write_text(json.dumps({
            "description": "fox's lens distortion ignored, modelled or undistorted; see bench/real_scenes.py "
                           "--compare-lens", "runs": results, "summary": summary}, indent=1))
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
    write_results("runs", results)
    write_results("summary", summary)
    plot(results, RESULTS / "real_scenes.png")


if __name__ == "__main__":
    main()
