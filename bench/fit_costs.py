"""What a fit step costs with each reconstruction preset on the CPU, in one run: the service's progress weights.

A job's reconstruct stage is weighed by its fit's steps times a step's cost (``voxe_service/progress.py``), and a
step of ``paper`` (32,768 rays at up to 160³) or ``scene`` (a capture's background as well) costs far more than one
of ``fast``. Each preset is fitted here as a job's reconstruct stage fits it (``voxe_core.presets``: the job's
default parameters, backbone and recipe resolved by ``fit_setup``) on the kind of scene it is for: ``fast`` and
``paper`` on mic (an object), ``scene`` on fox (a phone capture, every 8th photo held out). ``fast`` runs first and
last and the reference is their mean, so the ratios hold over the machine's load during the run. Beside each
time, the held-out PSNR the fit bought.

    python bench/fit_costs.py    # ~8 min on 2 cores

Writes bench/results/fit_costs.json and fit_costs.png.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
DATA = HERE.parent.parent / "shared" / "data"
MIC = "nerf_synthetic_mic"
CASES = [("fast", MIC), ("paper", MIC), ("scene", "fox"), ("fast", MIC)]
HOLDOUT_EVERY = {"fox": 8}  # a capture has no test split: every 8th photo is held out (SPEC §5)


def fit(preset: str, scene_name: str) -> dict:
    """One fit of ``preset`` on ``scene_name`` as a job's reconstruct stage runs it, timed, scored on held-out views."""
    from reconstruction import commit_measured, process_cpu_seconds

    from voxe_core.data import load_scene
    from voxe_core.metrics import psnr
    from voxe_core.presets import fit_setup, reconstruction_params
    from voxe_core.reconstruct import reconstruct
    from voxe_core.render import render_image

    rec_params = reconstruction_params({"reconstruction": {"preset": preset}})
    holdout = HOLDOUT_EVERY.get(scene_name)
    load = dict(downsample=rec_params["downsample"], resample=rec_params["resample"], holdout_every=holdout)
    train = load_scene(DATA / scene_name, "train", **load)
    test = load_scene(DATA / scene_name, "test", **load)
    backbone, config, cameras, initial = fit_setup(rec_params, train.alphas, train.cameras)
    cpu_start, start = process_cpu_seconds(), time.perf_counter()
    grid = reconstruct(train.images, cameras, config, initial_grid=initial)
    seconds, cpu_seconds = time.perf_counter() - start, process_cpu_seconds() - cpu_start
    test_cameras = grid.dataset_cameras(test.cameras)
    renders = torch.stack([render_image(grid, test_cameras, i).rgb for i in range(len(test_cameras))])
    steps = config.total_iterations
    return {
        "preset": preset, "scene": scene_name, "backbone": backbone, "steps": steps,
        "rays_per_step": config.rays_per_step, "resolutions": list(config.resolutions),
        "image_size": [train.cameras.width, train.cameras.height], "train_views": len(train.cameras),
        "test_views": len(test_cameras), "seconds": round(seconds, 2), "cpu_seconds": round(cpu_seconds, 2),
        "seconds_per_step": seconds / steps, "psnr": round(float(psnr(renders, test.images).mean()), 3),
        "commit": commit_measured(), "machine": f"{os.cpu_count()} CPU cores, torch {torch.__version__}",
        "measured_on": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def summary(runs: list[dict]) -> dict:
    """Each other preset's step and ray over ``fast``'s (the mean of its runs): a ray's price is what progress
    weighs a CPU fit step by (``voxe_service/progress.py``); ``paper``'s says how well rays alone predict a step."""
    fast = [r for r in runs if r["preset"] == "fast"]
    step = sum(r["seconds_per_step"] for r in fast) / len(fast)
    ray = sum(r["seconds_per_step"] / r["rays_per_step"] for r in fast) / len(fast)
    result = {"fast_seconds_per_step": step,
              "fast_runs_spread": max(r["seconds_per_step"] for r in fast) / min(r["seconds_per_step"] for r in fast)}
    for run in runs:
        if run["preset"] != "fast":
            result[f"{run['preset']}_step_over_fast"] = run["seconds_per_step"] / step
            result[f"{run['preset']}_ray_over_fast"] = run["seconds_per_step"] / run["rays_per_step"] / ray
    return result


def plot(runs: list[dict], path: Path) -> None:
    """Seconds per step of each fit and its price per ray over ``fast``'s, with its seconds and held-out PSNR."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fast = [r["seconds_per_step"] / r["rays_per_step"] for r in runs if r["preset"] == "fast"]
    per_ray = [r["seconds_per_step"] / r["rays_per_step"] / (sum(fast) / len(fast)) for r in runs]
    labels = [f"{r['preset']} on {r['scene']}\n{r['steps']:,} steps × {r['rays_per_step']:,} rays" for r in runs]
    colours = ["C0" if r["preset"] == "fast" else "C1" for r in runs]
    fig, (steps, rays) = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    y = list(range(len(runs)))
    steps.barh(y, [r["seconds_per_step"] * 1e3 for r in runs], color=colours)
    for i, r in zip(y, runs):
        steps.text(r["seconds_per_step"] * 1e3, i, f" {r['seconds']:.0f} s, {r['psnr']:.2f} dB held out",
                   va="center", fontsize=8)
    steps.set_xlim(right=max(r["seconds_per_step"] for r in runs) * 1e3 * 1.9)
    steps.set_xlabel("ms per fit step (2-core CPU)")
    steps.set_yticks(y, labels, fontsize=8)
    steps.invert_yaxis()
    rays.barh(y, per_ray, color=colours)
    for i, value in zip(y, per_ray):
        rays.text(value, i, f" {value:.2f}×", va="center", fontsize=8)
    rays.set_xlim(right=max(per_ray) * 1.25)
    rays.set_xlabel("cost per ray of a step, over fast's (their mean)")
    fig.suptitle("a fit step's cost by preset, one run (the service's progress weights)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    from report import write_results

    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args(argv)
    torch.set_num_threads(os.cpu_count() or 1)
    runs = []
    for preset, scene_name in CASES:
        runs.append(fit(preset, scene_name))
        print(json.dumps(runs[-1]), flush=True)
    write_results("fit_costs", runs, summary(runs), plot)


if __name__ == "__main__":
    main()
