"""A named preset fitted on a capture, with and without ``scene()``'s priors: held-out PSNR against seconds.

A job that names ``fast`` (or ``paper``) on a capture runs that budget as ``ReconstructConfig.for_backbone("scene")``
adapts it: every image drawn, the early-stop pass, ``scene()``'s lr and, since 2026-12-05, its two priors (total
variation over occupied space, free space around the cameras). This fits fox (16× downsampled, every 8th photo
held out, as bench/real_scenes.py) with the named preset as the service resolves it ("priors") and with the priors
turned off ("none"), for each seed the two variants side by side in their own processes of one thread each (so
their times compare as a ratio), and scores the held-out photos and every 6th training view.

    python bench/capture_presets.py                        # fast, seeds 0 and 1: ~35 min on 2 cores
    python bench/capture_presets.py --preset paper --seeds 0

Writes bench/results/capture_presets.json and capture_presets.png.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
DATA = HERE.parent.parent / "shared" / "data" / "fox"
VARIANTS = ("priors", "none")
DOWNSAMPLE, HOLDOUT_EVERY = 16, 8


def fit(preset: str, seed: int, variant: str) -> dict:
    """One fit of ``preset`` on fox as a job resolves it, without the priors for ``variant`` "none"."""
    from reconstruction import WITHOUT_CAPTURE_PRIORS, commit_measured

    from voxe_core.data import load_scene
    from voxe_core.metrics import psnr
    from voxe_core.presets import fit_setup, reconstruction_params
    from voxe_core.reconstruct import reconstruct
    from voxe_core.render import render_image

    torch.set_num_threads(1)
    rec_params = reconstruction_params({"downsample": DOWNSAMPLE, "reconstruction": {"preset": preset, "seed": seed}})
    train = load_scene(DATA, "train", downsample=DOWNSAMPLE, holdout_every=HOLDOUT_EVERY)
    test = load_scene(DATA, "test", downsample=DOWNSAMPLE, holdout_every=HOLDOUT_EVERY)
    backbone, config, cameras, initial = fit_setup(rec_params, train.alphas, train.cameras)
    if variant == "none":
        config = replace(config, **WITHOUT_CAPTURE_PRIORS)
    start = time.perf_counter()
    grid = reconstruct(train.images, cameras, config, initial_grid=initial)
    seconds = time.perf_counter() - start
    held_out = grid.dataset_cameras(test.cameras)
    renders = torch.stack([render_image(grid, held_out, i).rgb for i in range(len(held_out))])
    seen = range(0, len(cameras), 6)
    seen_renders = torch.stack([render_image(grid, cameras, i).rgb for i in seen])
    return {"preset": preset, "seed": seed, "variant": variant, "backbone": backbone, "steps": config.total_iterations,
            "rays_per_step": config.rays_per_step, "tv_density": config.tv_density, "tv_color": config.tv_color,
            "camera_clearance": config.camera_clearance, "seconds": round(seconds, 1), "threads": 1,
            "psnr_held_out": round(float(psnr(renders, test.images).mean()), 3),
            "psnr_training_views": round(float(psnr(seen_renders, train.images[list(seen)]).mean()), 3),
            "commit": commit_measured(), "measured_on": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}


def summary(runs: list[dict]) -> dict:
    """Per seed, the priors' held-out gain (dB) and time ratio over the fit without them."""
    result = {}
    for seed in sorted({r["seed"] for r in runs}):
        pair = {r["variant"]: r for r in runs if r["seed"] == seed}
        if set(pair) == set(VARIANTS):
            result[f"seed{seed}_priors_minus_none_db"] = pair["priors"]["psnr_held_out"] - pair["none"]["psnr_held_out"]
            result[f"seed{seed}_priors_over_none_seconds"] = pair["priors"]["seconds"] / pair["none"]["seconds"]
    return result


def plot(runs: list[dict], path: Path) -> None:
    """Held-out PSNR against seconds (log axis), a marker per variant, each seed's pair joined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    for seed in sorted({r["seed"] for r in runs}):
        pair = sorted((r for r in runs if r["seed"] == seed), key=lambda r: r["variant"])
        ax.plot([r["seconds"] for r in pair], [r["psnr_held_out"] for r in pair], color="grey", lw=0.8, zorder=1)
    for variant, marker in zip(VARIANTS, "o^"):
        chosen = [r for r in runs if r["variant"] == variant]
        ax.scatter([r["seconds"] for r in chosen], [r["psnr_held_out"] for r in chosen], marker=marker, zorder=2,
                   label=f"{variant} (seeds {', '.join(str(r['seed']) for r in chosen)})")
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%d"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%d"))
    for run in runs:
        ax.annotate(f"seed {run['seed']}", (run["seconds"], run["psnr_held_out"]), textcoords="offset points",
                    xytext=(6, -3), fontsize=7)
    ax.margins(x=0.12)
    ax.set_xlabel("training seconds (one thread per fit, log scale)")
    ax.set_ylabel("held-out PSNR (dB)")
    presets = ", ".join(sorted({r["preset"] for r in runs}))
    ax.set_title(f"{presets} on fox as a capture: scene()'s priors or none", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    from report import write_results

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="fast", choices=("fast", "paper"))
    parser.add_argument("--seeds", type=int, nargs="+", default=(0, 1))
    parser.add_argument("--single", nargs=2, metavar=("SEED", "VARIANT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(fit(args.preset, int(args.single[0]), args.single[1])))
        return
    runs = []
    for seed in args.seeds:  # a seed's two variants side by side, each in its own one-thread process
        procs = [subprocess.Popen([sys.executable, __file__, "--preset", args.preset, "--single", str(seed), variant],
                                  stdout=subprocess.PIPE, text=True) for variant in VARIANTS]
        for proc in procs:
            out, _ = proc.communicate()
            if proc.returncode:
                raise SystemExit(f"a fit failed (exit {proc.returncode})")
            runs.append(json.loads(out.strip().splitlines()[-1]))
            print(json.dumps(runs[-1]), flush=True)
    write_results("capture_presets", runs, summary(runs), plot)


if __name__ == "__main__":
    main()
