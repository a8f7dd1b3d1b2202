"""Choosing the scene preset's priors on fox without looking at its held-out views.

Every 8th training view from the 4th on (frames 3, 11, …, 43 of the training split: 5 views) is split off as a
validation set; each variant fits the other 38 with ``ReconstructConfig.scene()``'s schedule and its own
priors (``VARIANTS``: total variation weights, camera clearance, final resolution), and reports validation PSNR
(all pixels / rays through the object box / background) every ``--eval-every`` iterations, the PSNR of every
6th fitting view (how far it overfits), and at the end the held-out views' PSNR and each view's own PSNR.
The preset's weights were picked by the validation column; the held-out column is reported, not used.
Writes bench/results/real_scenes_priors.json (merged per variant) and real_scenes_priors.png.

    python bench/real_scenes_priors.py --variants none tv tv_clear_0.4_strong --parallel   # ~12 min each, loaded
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from real_scenes import RESULTS, box_hits, checkpoint_grid, framed_splits, held_out_scores

PRIORS_OFF = dict(tv_density=0.0, tv_color=0.0, camera_clearance=0.0)
VARIANTS: dict[str, dict] = {
    "none": dict(PRIORS_OFF, iterations=(300, 900)),
    "tv": dict(PRIORS_OFF, tv_density=1e-3, tv_color=1e-2, iterations=(300, 900)),
    "tv_strong": dict(PRIORS_OFF, tv_density=1e-2, tv_color=5e-2),
    "tv_colour_strong": dict(PRIORS_OFF, tv_density=1e-3, tv_color=1e-1),
    "tv_128": dict(PRIORS_OFF, tv_density=1e-3, tv_color=1e-2, resolutions=(64, 128)),
    "tv_clear_0.15": dict(tv_density=1e-3, tv_color=1e-2, camera_clearance=0.15),
    "tv_clear_0.25": dict(tv_density=1e-3, tv_color=1e-2, camera_clearance=0.25),
    "tv_strong_clear_0.25": dict(tv_density=1e-2, tv_color=5e-2, camera_clearance=0.25),
    "tv_clear_0.4": dict(tv_density=1e-3, tv_color=1e-2, camera_clearance=0.4),
    "tv_clear_0.5": dict(tv_density=1e-3, tv_color=1e-2, camera_clearance=0.5),
    "tv_strong_clear_0.4": dict(tv_density=1e-2, tv_color=5e-2, camera_clearance=0.4),  # the preset's choice
    # ... with each step's rays from 8 random views (the paper preset's ``images_per_step``) instead of every view
    "tv_strong_clear_0.4_8_images": dict(tv_density=1e-2, tv_color=5e-2, camera_clearance=0.4, images_per_step=8),
}
"""Overrides of ``ReconstructConfig.scene(iterations=(300, 600))``, the variants measured."""


def rounded(scores: dict) -> dict:
    return {key: round(value, 2) for key, value in scores.items()}


def run_variant(name: str, args) -> dict:
    from voxe_core.metrics import psnr
    from voxe_core.progress import Callbacks
    from voxe_core.reconstruct import ReconstructConfig, reconstruct
    from voxe_core.render import RenderConfig, render_image
    from voxe_core.scene_grid import SceneGrid

    torch.set_num_threads(args.threads)
    train, test, frame, cams, test_cams = framed_splits(16)
    validation = [i for i in range(len(cams)) if i % 8 == 3]
    fitting = [i for i in range(len(cams)) if i % 8 != 3]
    val = (train.images[validation], cams[torch.tensor(validation)])
    fit_images, fit_cams = train.images[fitting], cams[torch.tensor(fitting)]
    seen = (fit_images[::6], fit_cams[torch.arange(0, len(fitting), 6)])
    val_hits, seen_hits, test_hits = box_hits(val[1]), box_hits(seen[1]), box_hits(test_cams)
    overrides = {"iterations": (300, 600), **VARIANTS[name]}
    config = ReconstructConfig.scene(**overrides, seed=args.seed, checkpoint_every=args.eval_every)
    curve, paused = [], [0.0]
    start = time.perf_counter()

    def on_checkpoint(path: str) -> None:
        t0 = time.perf_counter()
        grid, done = checkpoint_grid(path, config)
        curve.append({"iteration": done,
                      "train_s": round(t0 - start - paused[0], 1),
                      "validation": rounded(held_out_scores(grid, *val, val_hits)),
                      "fitting_views_psnr": round(held_out_scores(grid, *seen, seen_hits)["psnr"], 2)})
        paused[0] += time.perf_counter() - t0

    checkpoint = Path(args.scratch) / f"{name}.ckpt"
    grid = reconstruct(fit_images, fit_cams, config, Callbacks(on_checkpoint=on_checkpoint), checkpoint_path=checkpoint,
                       initial_grid=SceneGrid(config.resolutions[0], frame=frame))
    train_s = time.perf_counter() - start - paused[0]
    checkpoint.unlink(missing_ok=True)

    def per_view(images, cameras) -> list[float]:
        return [round(float(psnr(render_image(grid, cameras, i, RenderConfig(step_ratio=0.8)).rgb, images[i])), 1)
                for i in range(len(cameras))]

    return {"variant": name, "overrides": {k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items()},
            "seed": args.seed, "threads": args.threads, "train_s": round(train_s, 1), "load": os.getloadavg(),
            "validation": rounded(held_out_scores(grid, *val, val_hits)),
            "fitting_views_psnr": round(held_out_scores(grid, *seen, seen_hits)["psnr"], 2),
            "held_out": rounded(held_out_scores(grid, test.images, test_cams, test_hits)),
            "validation_per_view": per_view(*val), "held_out_per_view": per_view(test.images, test_cams),
            "curve": curve}


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bars) = plt.subplots(1, 2, figsize=(13, 4.5))
    for k, (name, r) in enumerate(results.items()):
        ax.plot([p["iteration"] for p in r["curve"]] + [sum(r["overrides"]["iterations"])],
                [p["validation"]["psnr"] for p in r["curve"]] + [r["validation"]["psnr"]], "o-", ms=3, label=name,
                color=plt.cm.tab20(k % 20))
    ax.set_xlabel("iteration (final point: the averaged grid)")
    ax.set_ylabel("validation PSNR (dB)")
    ax.legend(fontsize=7)
    names = list(results)
    for k, (key, label) in enumerate([("validation", "validation"), ("held_out", "held-out (not used to choose)")]):
        bars.bar([i + 0.4 * k for i in range(len(names))], [results[n][key]["psnr"] for n in names], 0.4, label=label)
    bars.bar([i + 0.2 for i in range(len(names))], [results[n]["fitting_views_psnr"] for n in names], 0.8,
             fill=False, edgecolor="grey", label="fitting views")
    bars.set_xticks([i + 0.2 for i in range(len(names))], names, rotation=35, ha="right", fontsize=7)
    bars.set_ylim(10, 30)
    bars.set_ylabel("final PSNR (dB)")
    bars.legend(fontsize=7)
    fig.suptitle("fox, scene backbone: priors chosen on 5 views split off the training set (16× downsampled)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=["none", "tv_strong_clear_0.4"])
    parser.add_argument("--parallel", action="store_true", help="all variants at once, so the machine's load falls on all")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per variant")
    parser.add_argument("--eval-every", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--single", choices=list(VARIANTS), help=argparse.SUPPRESS)
    parser.add_argument("--scratch", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(run_variant(args.single, args)))
        return
    with tempfile.TemporaryDirectory(prefix="real_scenes_priors-") as scratch:
        commands = [[sys.executable, __file__, "--single", name, "--threads", str(args.threads), "--seed", str(args.seed),
                     "--eval-every", str(args.eval_every), "--scratch", scratch] for name in args.variants]
        if args.parallel:
            processes = [subprocess.Popen(c, stdout=subprocess.PIPE, text=True) for c in commands]
            outputs = [p.communicate()[0] for p in processes]
            for process in processes:  # as check=True does below: a variant that failed is not read as a result
                if process.returncode:
                    raise subprocess.CalledProcessError(process.returncode, process.args)
        else:
            outputs = [subprocess.run(c, check=True, stdout=subprocess.PIPE, text=True).stdout for c in commands]
    path = RESULTS / "real_scenes_priors.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    for output in outputs:
        r = json.loads(output.strip().splitlines()[-1])
        results[r["variant"]] = r
        print(f"{r['variant']:24s} validation {r['validation']['psnr']:5.2f} dB  held-out {r['held_out']['psnr']:5.2f} dB"
              f"  fitting views {r['fitting_views_psnr']:5.2f} dB  {r['train_s']:6.1f} s")
    RESULTS.mkdir(exist_ok=True)
    path.write_text(json.dumps(results, indent=1))
    plot(results, RESULTS / "real_scenes_priors.png")


if __name__ == "__main__":
    main()
