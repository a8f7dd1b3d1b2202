"""Reconstruction speed against error on NeRF-synthetic mic (200 px, 25 train views, 20 test views).

Each run trains in its own subprocess (so its peak RSS is its own), then renders
the test views and scores them. Training images and ground truth share one
antialiasing filter (``--resample``; bilinear, as the authors' loader, unless
asked), and every run also scores its renders against the other filter's ground
truth. Runs vary the final resolution, the iteration budget and empty-space
skipping; the skipping comparison also renders the same trained grid both ways.
Writes bench/results/reconstruction.json and reconstruction.png (PSNR against
training seconds).

    python bench/reconstruction.py            # the full table (~20 min to > 1 h on 2 cores)
    python bench/reconstruction.py --quick    # a CI-sized subset (~5 min)
    python bench/reconstruction.py --ablations  # one recipe knob at a time (~25 min)
    python bench/reconstruction.py --only fast-160 skip-128  # rerun some; the other results are kept
    python bench/reconstruction.py --resample box --only fast-160  # box-filtered images: row fast-160-box
    python bench/reconstruction.py --only preset-fast  # ReconstructConfig.fast() unchanged (the default)
    python bench/reconstruction.py --only preset-paper preset-paper-all-images  # ReconstructConfig(), ~7 min
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

from voxe_core.data import RESAMPLE_FILTERS
from voxe_core.reconstruct import ReconstructConfig

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data" / "nerf_synthetic_mic"
RESULTS = HERE / "results"

# fast()'s step before 2026-12-05's second change (it takes 8,192 rays at lr 0.04 since).
FAST_4096_RAYS_STEP = {"rays_per_step": 4096, "lr": 0.03}
# scene()'s priors off: what capture fits were before a named preset kept them (2026-12-05); the benches whose capture
# records predate that pin it so a rerun reproduces them.
WITHOUT_CAPTURE_PRIORS = {"tv_density": 0.0, "tv_color": 0.0, "camera_clearance": 0.0}
# As the rows below were measured: that step, each step's rays from every image and the early-stop density pass while
# training (fast() draws from 8 since 2026-12-05, and object fits go without the pass since 90eb259).
MEASURED_AS = {**FAST_4096_RAYS_STEP, "images_per_step": 0, "early_stop": 1e-4}


def as_measured(config: ReconstructConfig) -> ReconstructConfig:
    """``config`` drawing each step's rays from every image, with the early-stop pass while training (``MEASURED_AS``):
    the benches whose object fits predate 2026-12-05 (grid_files, mesh_input, localisation_grids) rerun their records'
    recipe, not today's ``fast()`` (a capture's ``for_backbone("scene")`` fit has both anyway)."""
    return dataclasses.replace(config, images_per_step=MEASURED_AS["images_per_step"],
                               render=dataclasses.replace(config.render, early_stop=MEASURED_AS["early_stop"]))


# The previous fast recipe: the last iterate, lr ×0.1 for the last 20 % of the final stage, one lr for all features.
LAST_ITERATE = {"average_from": 1.0, "lr_drop_fraction": 0.8, "color_lr_scale": 1.0, **MEASURED_AS}
# The recipe for the target: the mean of the final stage's second half, colour at half the lr, lr never dropped.
AVERAGED = {"average_from": 0.5, "color_lr_scale": 0.5, **MEASURED_AS}
# SPEC §1's recipe (20→40→80→160 × 500, lr ×0.9 per stage, ×0.1 at 400), each step's rays drawn from every image
# (ours before) or from 8 drawn at random (the authors' loader, ``ReconstructConfig.images_per_step``'s default).
AUTHORS_RECIPE = LAST_ITERATE
AUTHORS_RECIPE_8_IMAGES = {**LAST_ITERATE, "images_per_step": 8}
# ReconstructConfig() unchanged (the `paper` preset): the recipe at 32,768 rays from 8 images a step, no early-stop pass.
PRESET_PAPER = {**AUTHORS_RECIPE_8_IMAGES, "rays_per_step": 32768, "early_stop": 0.0}
# ReconstructConfig.fast() as it is: what `voxe reconstruct` and jobs fit an object with by default ...
PRESET_FAST = {"resolutions": ReconstructConfig.fast().resolutions}
PRESET_FAST_ITERATIONS = ReconstructConfig.fast().iterations
# ... and as it was before 2026-12-05's second change: twice the steps of half the rays, at lr 0.03.
PRESET_FAST_4096_RAYS = {**PRESET_FAST, **FAST_4096_RAYS_STEP}
PRESET_FAST_4096_RAYS_ITERATIONS = (300, 500, 1200)
# Rows added to compare recipes score the renders that skip empty space only (the dense render compares nothing new).
SKIP_ONLY = {"dense_render": False}


def with_seeds(label: str, final: int, iterations: tuple[int, ...], skipping: bool, overrides: dict,
               seeds: tuple[int, ...] = (0, 1, 2)) -> list[tuple]:
    """The run with each seed (rays, jitter, images; seed 0 keeps the plain label): the spread one recipe lands within."""
    return [(label if seed == 0 else f"{label}-seed{seed}", final, iterations, skipping, {**overrides, "seed": seed})
            for seed in seeds]


FULL_RUNS = [
    # (label, final resolution, per-stage iterations, skipping while training, ReconstructConfig.fast overrides)
    ("fast-64", 64, (300, 1500), True, {**AVERAGED, "early_stop": 0.0}),  # re-run at a8fc17f, without the pass
    ("fast-96", 96, (300, 500, 1500), True, AVERAGED),
    ("fast-128", 128, (300, 500, 2000), True, AVERAGED),
    ("fast-160", 160, (300, 500, 3000), True, AVERAGED),
    ("fast-160-last-iterate", 160, (300, 500, 3000), True, LAST_ITERATE),
    ("fast-160-long", 160, (300, 500, 6000), True, AVERAGED),
    ("authors-recipe", 160, (500, 500, 500, 500), True, AUTHORS_RECIPE),
    *with_seeds("authors-recipe", 160, (500, 500, 500, 500), True, {**AUTHORS_RECIPE, **SKIP_ONLY}, seeds=(1, 2)),
    *with_seeds("authors-recipe-8-images", 160, (500, 500, 500, 500), True, {**AUTHORS_RECIPE_8_IMAGES, **SKIP_ONLY}),
    ("preset-paper", 160, (500, 500, 500, 500), True, {**PRESET_PAPER, **SKIP_ONLY}),
    ("preset-paper-all-images", 160, (500, 500, 500, 500), True, {**PRESET_PAPER, "images_per_step": 0, **SKIP_ONLY}),
    ("dense-128", 128, (300, 500, 800), False, LAST_ITERATE),
    ("skip-128", 128, (300, 500, 800), True, LAST_ITERATE),
    *with_seeds("preset-fast", 128, PRESET_FAST_ITERATIONS, True, {**PRESET_FAST, **SKIP_ONLY}, seeds=tuple(range(6))),
    # The preset before it took 8,192 rays a step ...
    *with_seeds("preset-fast-4096-rays", 128, PRESET_FAST_4096_RAYS_ITERATIONS, True,
                {**PRESET_FAST_4096_RAYS, **SKIP_ONLY}, seeds=tuple(range(6))),
    # ... drawing each step's rays from every image (before it drew from 8: see bench/README.md) ...
    *with_seeds("preset-fast-4096-rays-all-images", 128, PRESET_FAST_4096_RAYS_ITERATIONS, True,
                {**PRESET_FAST_4096_RAYS, "images_per_step": 0}, seeds=tuple(range(6))),
    # ... and so with the early-stop density pass it ran before 90eb259 (the render default's threshold).
    *with_seeds("preset-fast-4096-rays-all-images-early-stop", 128, PRESET_FAST_4096_RAYS_ITERATIONS, True,
                {**PRESET_FAST_4096_RAYS, "images_per_step": 0, "early_stop": 1e-4, **SKIP_ONLY}, seeds=tuple(range(6))),
]
# One knob at a time against the last-iterate recipe at 160³ with 1,500 final-stage iterations (--ablations).
ABLATION_BASE = (160, (300, 500, 1500), True)
ABLATION_RUNS = [
    (f"ablate-{name}", *ABLATION_BASE, {**LAST_ITERATE, **change})
    for name, change in [
        ("none", {}), ("lr-0.01", {"lr": 0.01}), ("lr-0.04", {"lr": 0.04}), ("rays-8192", {"rays_per_step": 8192}),
        ("colour-lr-0.5", {"color_lr_scale": 0.5}), ("colour-lr-2", {"color_lr_scale": 2.0}),
        ("average-half", {"average_from": 0.5, "lr_drop_fraction": 100.0}), ("softplus", {"activation": "softplus"}),
    ]
]
QUICK_RUNS = [  # at fast()'s step before 2026-12-05's second change, as results/quick/ was measured
    ("quick-64", 64, (200, 600), True, FAST_4096_RAYS_STEP),
    ("quick-dense-64", 64, (200, 600), False, FAST_4096_RAYS_STEP),
]


def stage_resolutions(final: int, stages: int) -> tuple[int, ...]:
    return tuple(final // 2 ** (stages - 1 - i) for i in range(stages))


def run_single(
    label: str, final: int, iterations: tuple[int, ...], skipping: bool, overrides: dict, downsample: int,
    resample: str,
) -> dict:
    from voxe_core.data import load_scene
    from voxe_core.metrics import psnr, ssim
    from voxe_core.reconstruct import ReconstructConfig, reconstruct
    from voxe_core.render import RenderConfig, render_image

    torch.set_num_threads(os.cpu_count() or 1)
    train = load_scene(DATA, "train", downsample=downsample, resample=resample)
    test = load_scene(DATA, "test", downsample=downsample, resample=resample)
    # The other antialiasing filter's ground truth, to score the same renders against.
    other = "box" if resample == "bilinear" else "bilinear"
    test_other = load_scene(DATA, "test", downsample=downsample, resample=other)
    stages = len(iterations)
    overrides = dict(overrides)
    dense_render = overrides.pop("dense_render", True)
    early_stop = overrides.pop("early_stop", None)  # the training renders' (RenderConfig.early_stop); None: the recipe's
    if "lr_drop_fraction" in overrides:
        overrides["lr_drop_iteration"] = int(iterations[-1] * overrides.pop("lr_drop_fraction"))
    config = ReconstructConfig.fast(
        resolutions=tuple(overrides.pop("resolutions", stage_resolutions(final, stages))),
        iterations=iterations,
        image_downsample=tuple(2 ** (stages - 1 - i) for i in range(stages)),
        **overrides,
    )
    config.render.skip_empty = skipping
    if early_stop is not None:
        config.render.early_stop = early_stop
    samples = []
    load_before = os.getloadavg()[0]
    cpu_start = process_cpu_seconds()
    start = time.perf_counter()
    grid = reconstruct(train.images, train.cameras, config,
                       callbacks=_sample_counter(samples, config.iterations[-1]))
    seconds = time.perf_counter() - start
    cpu_seconds = process_cpu_seconds() - cpu_start

    result = {
        "scene": "nerf_synthetic_mic", "label": label, "resolution": final, "iterations": sum(iterations),
        "stage_iterations": list(iterations), "skipping": skipping, "seconds": round(seconds, 2),
        # The machine is shared: CPU seconds and the load average say how much of the wall time was ours.
        "cpu_seconds": round(cpu_seconds, 2), "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "rays_per_step": config.rays_per_step, "image_size": train.cameras.width, "resample": resample,
        "images_per_step": config.images_per_step, "early_stop": config.render.early_stop,
        "lr": config.lr, "lr_drop_iteration": config.lr_drop_iteration, "average_from": config.average_from,
        "color_lr_scale": config.color_lr_scale,
        "occupied_fraction": round(grid.occupancy(config.render.sigma_threshold).fraction, 5),
        "train_samples_per_ray_final_stage": round(sum(samples) / max(1, len(samples)), 2),
    }
    for render_skipping in (True, False) if dense_render else (True,):
        render_config = RenderConfig(step_ratio=config.render.step_ratio, skip_empty=render_skipping)
        start = time.perf_counter()
        renders = [render_image(grid, test.cameras, i, render_config) for i in range(len(test.cameras))]
        render_seconds = (time.perf_counter() - start) / len(renders)
        images = torch.stack([r.rgb for r in renders])
        key = "" if render_skipping else "dense_render_"
        result[f"{key}psnr"] = round(float(psnr(images, test.images).mean()), 3)
        result[f"{key}ssim"] = round(float(ssim(images, test.images).mean()), 4)
        result[f"{key}samples_per_ray"] = round(
            sum(r.samples for r in renders) / (len(renders) * test.cameras.width * test.cameras.height), 2
        )
        result[f"{key}render_seconds_per_view"] = round(render_seconds, 3)
        if render_skipping:
            result[f"psnr_{other}_gt"] = round(float(psnr(images, test_other.images).mean()), 3)
            result[f"ssim_{other}_gt"] = round(float(ssim(images, test_other.images).mean()), 4)
    if dense_render:
        result["render_sample_ratio_dense_over_skip"] = round(
            result["dense_render_samples_per_ray"] / max(result["samples_per_ray"], 1e-9), 1
        )
        result["render_time_ratio_dense_over_skip"] = round(
            result["dense_render_render_seconds_per_view"] / result["render_seconds_per_view"], 2
        )
    result["machine"] = f"{os.cpu_count()} CPU cores, torch {torch.__version__}"
    result["commit"] = commit_measured()
    result["measured_on"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return result


def commit_measured() -> str:
    """The code measured: HEAD, marked ``+dirty`` when voxe_core has uncommitted changes."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=HERE.parent, capture_output=True, text=True).stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "voxe_core") else "")


def process_cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _sample_counter(samples: list, final_iterations: int):
    from voxe_core.progress import Callbacks

    def record(progress):
        if progress.iteration > progress.total - final_iterations:
            samples.append(progress.info["samples_per_ray"])

    return Callbacks(on_progress=record)


def plot(runs: list[dict], path: Path) -> None:
    """PSNR against training seconds: report.py's speed-against-error axes (a recipe over seeds as one point)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from report import seed_means, speed_error_axes

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.axhline(30.6, color="grey", lw=0.8, ls="--", label="target 30.6 dB")
    ax.axvline(300, color="grey", lw=0.8, ls=":", label="5 min")
    points = seed_means(runs)
    layout = speed_error_axes(ax, points, x="seconds", y="psnr", hollow=lambda r: not r["skipping"],
                              label=lambda r: r["label"] + (f" ({r['seeds']} seeds)" if r.get("seeds") else ""),
                              xlabel="training wall time (s, 2-core CPU, log scale)", ylabel="mean test PSNR (dB)",
                              title="mic @200 px: PSNR vs training time (hollow: dense)")
    fig.tight_layout(rect=layout)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="CI-sized subset at 100 px")
    parser.add_argument("--ablations", action="store_true", help="one recipe knob at a time (160³, 1,500 final iterations)")
    parser.add_argument("--only", nargs="*", help="labels to run; their results replace those runs in --out")
    parser.add_argument("--resample", choices=RESAMPLE_FILTERS, default=RESAMPLE_FILTERS[0],
                        help="the images' antialiasing filter, for training and ground truth alike "
                             "(bilinear: the authors' loader, as the issue's reference figures)")
    parser.add_argument("--out", type=Path, default=RESULTS / "reconstruction.json")
    parser.add_argument("--single", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(run_single(*json.loads(args.single))))
        return
    if not DATA.is_dir():
        sys.exit(f"mic data not found at {DATA}")
    runs = QUICK_RUNS if args.quick else ABLATION_RUNS if args.ablations else FULL_RUNS
    if args.only:
        runs = [r for r in (QUICK_RUNS if args.quick else FULL_RUNS + ABLATION_RUNS) if r[0] in args.only]
    downsample = 8 if args.quick else 4
    # --only reruns some runs: the others keep their earlier results (each run names its commit and date).
    kept = json.loads(args.out.read_text()) if args.only and args.out.is_file() else []
    # Runs on the box filter are rows of their own beside the default bilinear ones.
    suffix = "" if args.resample == "bilinear" else f"-{args.resample}"
    labels = [r[0] + suffix for r in runs]
    results = [r for r in kept if r["label"] not in labels]
    # Rows of one invocation share its id: their seconds compare (report.py times pairs only within one).
    bench_run = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    for label, (_, final, iterations, skipping, overrides) in zip(labels, runs):
        spec = json.dumps([label, final, list(iterations), skipping, overrides, downsample, args.resample])
        out = subprocess.run([sys.executable, __file__, "--single", spec], capture_output=True, text=True, check=True)
        result = {**json.loads(out.stdout.strip().splitlines()[-1]), "bench_run": bench_run}
        results.append(result)
        print(f'{label:15s} res {final:3d} it {sum(iterations):5d} skip {str(skipping):5s} '
              f'{result["seconds"]:7.1f} s  PSNR {result["psnr"]:.2f}  SSIM {result["ssim"]:.4f}  '
              f'samples/ray {result["samples_per_ray"]:.1f} (dense {result.get("dense_render_samples_per_ray", "-")})  '
              f'render {result["render_seconds_per_view"]:.2f} s/view  RSS {result["peak_rss_mb"]:.0f} MB', flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    order = {r[0]: i for i, r in enumerate(FULL_RUNS + ABLATION_RUNS + QUICK_RUNS)}
    results.sort(key=lambda r: (order.get(r["label"].removesuffix("-box"), len(order)), r["label"]))
    args.out.write_text(json.dumps(results, indent=1))
    plot(results, args.out.with_suffix(".png"))
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
