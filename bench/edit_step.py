"""Cost of one editing iteration (SPEC §2), split into render, VAE encode, UNet, backward and optimiser.

Runs the real loop (``voxe_core.edit.edit``) a few iterations per configuration
and averages the per-part timings it reports (``Progress.info``), after warm-up
iterations. Models, all with RANDOM WEIGHTS (nothing can be downloaded here;
the timings are a cost, never a quality):

* ``tiny``: the smoke-test model of ``voxe_core.tiny_sd`` (64² images);
* ``sd2-base-shaped``: UNet, VAE and CLIP text encoder built from the
  Stable Diffusion 2 base configurations written out below (865M + 84M + 340M
  parameters), saved to a temporary folder and loaded through
  ``StableDiffusionGuidance.from_pretrained`` so the same code path runs. A
  real CLIP tokenizer cannot be downloaded: the tiny model's tokenizer files
  stand in (tokenisation cost is negligible and cached per view word).

The grid is an analytic sphere at the paper's 160³ (so dense Adam and
L_reg3D cost what they cost at paper scale).

    python bench/edit_step.py            # CPU: tiny @64², full-size @64² and @128² (~5-10 min on 2 cores)
    python bench/edit_step.py --quick    # CPU: tiny only, into bench/results/quick/
    python bench/edit_step.py --gpu      # CUDA fp16: full-size @512² guidance with 266² renders, tiny @64²
    python bench/edit_step.py --skip-density 32 64   # tiny on a scene grid: skip density built once vs each step

Writes bench/results/edit_step.json (a list of runs) and edit_step.png
(per-run stacked bars), or ``--out`` and the PNG beside it. ``--gpu`` writes
edit_step_gpu.json / .png and ``--quick`` bench/results/quick/ instead, so the
full-size CPU record is kept. Prints a table.

``--skip-density`` times the tiny model's step on a scene grid (the sphere in its
foreground) at each given lattice size, with the per-cell skip density built
once per edit (the loop as it is) against rebuilt every step (as the loop did:
``occupancy_above`` patched to rebuild it), alternating step by step, into
edit_step_skip_density.json: step, render and occupancy medians (the occupancy
timed in both arms), the steps' ratio, and whether the alternating edit ended
on the same features as one built once throughout.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import torch

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
sys.path.insert(0, str(REPO))

PARTS = ("render", "vae", "unet", "backward", "optimizer", "other")
GRID_RESOLUTION = 160
COST_NOTE = "random weights: cost only"


# ---------------------------------------------------------------- models
# What SD 1.4 (the paper's attention model) changes from SD 2 base: CLIP ViT-L/14 text (768 wide, 12 layers),
# 8-head attention everywhere, conv projections.
FAMILIES = {
    "sd2-base": dict(cross_attention_dim=1024, attention_head_dim=(5, 10, 20, 20), use_linear_projection=True,
                     text=dict(hidden_size=1024, intermediate_size=4096, projection_dim=1024, num_hidden_layers=23,
                               num_attention_heads=16, hidden_act="gelu")),
    "sd1.4": dict(cross_attention_dim=768, attention_head_dim=8, use_linear_projection=False,
                  text=dict(hidden_size=768, intermediate_size=3072, projection_dim=768, num_hidden_layers=12,
                            num_attention_heads=12, hidden_act="quick_gelu")),
}


def build_sd2_base_shaped(path: Path, tokenizer_from: Path, dtype: str = "float16", family: str = "sd2-base",
                          device: str = "cpu") -> Path:
    """Random-weight UNet / VAE / CLIP text encoder with Stable Diffusion 2 base's (or ``family``'s) shapes,
    diffusers layout. ``device`` draws the random weights there ("cuda": seconds instead of the CPU's minute for
    1.3 G parameters); they are saved from the host."""
    import diffusers
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    path.mkdir(parents=True, exist_ok=True)
    shutil.copytree(tokenizer_from, path / "tokenizer", dirs_exist_ok=True)
    tokenizer = CLIPTokenizer.from_pretrained(str(path / "tokenizer"))
    save_dtype = getattr(torch, dtype)
    torch.manual_seed(0)
    shapes = FAMILIES[family]

    def save(module: torch.nn.Module, folder: str) -> None:
        module.to(save_dtype).cpu().save_pretrained(str(path / folder))

    with torch.device(device):
        unet = UNet2DConditionModel(
            sample_size=64,
            in_channels=4,
            out_channels=4,
            down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
            up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
            block_out_channels=(320, 640, 1280, 1280),
            layers_per_block=2,
            cross_attention_dim=shapes["cross_attention_dim"],
            attention_head_dim=shapes["attention_head_dim"],
            use_linear_projection=shapes["use_linear_projection"],
            norm_num_groups=32,
            flip_sin_to_cos=True,
            freq_shift=0,
        )
    save(unet, "unet")
    del unet

    with torch.device(device):
        vae = AutoencoderKL(
            in_channels=3,
            out_channels=3,
            down_block_types=("DownEncoderBlock2D",) * 4,
            up_block_types=("UpDecoderBlock2D",) * 4,
            block_out_channels=(128, 256, 512, 512),
            layers_per_block=2,
            latent_channels=4,
            norm_num_groups=32,
            sample_size=512,
            scaling_factor=0.18215,
        )
    save(vae, "vae")
    del vae

    with torch.device(device):
        text = CLIPTextModel(CLIPTextConfig(
            vocab_size=49408,
            max_position_embeddings=77,
            **shapes["text"],
            bos_token_id=tokenizer.bos_token_id,
            eos_token_id=tokenizer.eos_token_id,
            pad_token_id=tokenizer.eos_token_id,
        ))
    save(text, "text_encoder")
    del text

    DDIMScheduler(
        num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
        clip_sample=False, set_alpha_to_one=False, steps_offset=1, prediction_type="epsilon",
    ).save_pretrained(str(path / "scheduler"))
    (path / "model_index.json").write_text(json.dumps({
        "_class_name": "StableDiffusionPipeline",
        "_diffusers_version": diffusers.__version__,
        "_name_or_path": f"{family}-shaped RANDOM WEIGHTS (benchmark only)",
        "scheduler": ["diffusers", "DDIMScheduler"],
        "text_encoder": ["transformers", "CLIPTextModel"],
        "tokenizer": ["transformers", "CLIPTokenizer"],
        "unet": ["diffusers", "UNet2DConditionModel"],
        "vae": ["diffusers", "AutoencoderKL"],
    }, indent=2))
    return path


def sphere_grid(resolution: int, radius: float = 0.8, slope: float = 5.0):
    """Solid sphere, raw density linear in the signed distance (positive inside), reddish colour."""
    from voxe_core.grid import VoxelGrid

    grid = VoxelGrid(resolution)
    return _holding_sphere(grid, torch.linspace(-1.5, 1.5, resolution), float(grid.voxel_size.min()), radius, slope)


def _holding_sphere(grid, axis: torch.Tensor, voxel: float, radius: float, slope: float):
    """``grid`` with a solid sphere of ``radius`` at the origin: raw density ``slope`` per ``voxel`` world units of
    signed distance (positive inside), reddish colour; ``axis`` (resolution,): its vertices' world coordinates
    along each axis."""
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")
    distance = (x * x + y * y + z * z).sqrt()
    with torch.no_grad():
        grid.features[..., 0] = slope * (radius - distance) / voxel
        grid.features[..., 1:] = torch.tensor([2.0, -1.0, -1.0])
    return grid


def scene_sphere_grid(resolution: int, radius: float = 0.8, slope: float = 5.0):
    """``sphere_grid``'s sphere in a scene grid's foreground (the contraction is the identity there; the
    background, farther than the sphere anyway, is measured as if it were not contracted)."""
    from voxe_core.scene_grid import CONTRACTED_EXTENT, SceneGrid

    grid = SceneGrid(resolution)
    fg = grid.foreground_extent
    return _holding_sphere(grid, torch.linspace(-CONTRACTED_EXTENT, CONTRACTED_EXTENT, resolution) * fg,
                           float(grid.voxel_size.min()) * fg, radius, slope)


SKIP_DENSITY_ARMS = ("built_once", "rebuilt_each_step")


def step_arm(step: int) -> str:
    """The arm a step of a ``--skip-density`` edit runs in: ABBA, so the shared machine's drift lands on both alike."""
    return SKIP_DENSITY_ARMS[step % 4 in (1, 2)]


@contextlib.contextmanager
def occupancy_timed_by_arm(sigma_threshold: float, times: list[tuple[str, float]]):
    """Patches a scene grid's ``occupancy_above`` (the edit loop's one call a step) to time itself into ``times``
    as (arm, ms), the arm by :func:`step_arm`: ``built_once`` takes the skip density it is handed (the loop as it is),
    ``rebuilt_each_step`` rebuilds it from the grid first, as the loop did before (``grid.occupancy``; the same
    value, so the edit runs on unchanged)."""
    from voxe_core.scene_grid import SceneGrid

    built_once = SceneGrid.occupancy_above

    @torch.no_grad()
    def occupancy_above(grid, density):
        arm = step_arm(len(times))
        t0 = time.perf_counter()
        occupancy = built_once(grid, grid.skip_density(sigma_threshold) if arm == "rebuilt_each_step" else density)
        times.append((arm, (time.perf_counter() - t0) * 1e3))
        return occupancy

    with mock.patch.object(SceneGrid, "occupancy_above", occupancy_above):
        yield


def time_skip_density(model_path: Path, resolution: int, rounds: int, warm: int, timed: int) -> dict:
    """The tiny model's step on ``scene_sphere_grid(resolution)``, skip density built once against rebuilt each
    step, alternating by step within each of ``rounds`` edits (seeds 0, 1, ...); medians over every timed step of
    an arm. ``same_features``: the first edit ended where one with the skip density built once throughout does."""
    from voxe_core.edit import EditConfig, edit
    from voxe_core.guidance.sds import StableDiffusionGuidance
    from voxe_core.progress import Callbacks

    guidance = StableDiffusionGuidance.from_pretrained(str(model_path), device="cpu", dtype=torch.float32,
                                                       local_files_only=True, resolution=64, sync_timing=True)
    grid = scene_sphere_grid(resolution)
    prompt = "a dog wearing big sunglasses"
    steps, renders, occupancies = ({arm: [] for arm in SKIP_DENSITY_ARMS} for _ in range(3))
    load_before = os.getloadavg()[0]
    for seed in range(rounds):
        config = EditConfig(iterations=warm + timed, render_size=64, seed=seed, sync_timing=True)
        reports, times = [], []
        with occupancy_timed_by_arm(config.render.sigma_threshold, times):
            edited = edit(grid, prompt, guidance, config, Callbacks(on_progress=reports.append))
        if len(times) != len(reports):
            raise RuntimeError(f"the edit built {len(times)} occupancies in {len(reports)} steps: steps cannot be "
                               "told apart by arm")
        for report, (arm, ms) in list(zip(reports, times))[warm:]:
            steps[arm].append(report.info["ms_step"])
            renders[arm].append(report.info["ms_render"])
            occupancies[arm].append(ms)
        if seed == 0:
            alternating = edited
    same_features = torch.equal(alternating.features, edit(grid, prompt, guidance, dataclasses.replace(
        config, seed=0)).features)
    median = {arm: statistics.median(steps[arm]) for arm in SKIP_DENSITY_ARMS}
    return {
        "model": "tiny",
        "grid": "scene",
        "grid_resolution": resolution,
        "ms_occupancy_built_once": statistics.median(occupancies["built_once"]),
        "ms_occupancy_rebuilt_each_step": statistics.median(occupancies["rebuilt_each_step"]),
        "ms_step_built_once": median["built_once"],
        "ms_step_rebuilt_each_step": median["rebuilt_each_step"],
        "time_ratio_built_once_to_rebuilt": median["built_once"] / median["rebuilt_each_step"],
        "ms_saved_per_step": median["rebuilt_each_step"] - median["built_once"],
        "same_features": same_features,
        "ms_render_built_once": statistics.median(renders["built_once"]),
        "ms_render_rebuilt_each_step": statistics.median(renders["rebuilt_each_step"]),
        "render_size": 64,
        "rounds": rounds,
        "iterations_warm": warm,
        "iterations_timed": timed,
        "threads": torch.get_num_threads(),
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "model_note": COST_NOTE,
    }


# ---------------------------------------------------------------- one run
def time_run(label: str, model_path: Path, device: str, dtype: torch.dtype, resolution: int, render_size: int,
             warm: int, timed: int, note: str) -> dict:
    from voxe_core.edit import EditConfig, edit
    from voxe_core.guidance.sds import StableDiffusionGuidance
    from voxe_core.progress import Callbacks

    t0 = time.perf_counter()
    guidance = StableDiffusionGuidance.from_pretrained(
        str(model_path), device=device, dtype=dtype, local_files_only=True, resolution=resolution, sync_timing=True
    )
    load_s = time.perf_counter() - t0
    grid = sphere_grid(GRID_RESOLUTION)
    reports = []
    config = EditConfig(iterations=warm + timed, render_size=render_size, seed=0, sync_timing=True)
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    edit(grid, "a dog wearing big sunglasses", guidance, config, Callbacks(on_progress=reports.append))
    wall = time.perf_counter() - t0
    kept = [r.info for r in reports[warm:]]
    mean = lambda key: statistics.fmean(i[key] for i in kept)  # noqa: E731
    row = {
        "model": label,
        "device": device,
        "dtype": str(dtype).replace("torch.", ""),
        "resolution": resolution,
        "render_size": render_size,
        "grid_resolution": GRID_RESOLUTION,
        "ms_render": mean("ms_render"),
        "ms_vae": mean("ms_vae"),
        "ms_unet": mean("ms_unet"),
        "ms_backward": mean("ms_backward"),
        "ms_optimizer": mean("ms_optimizer"),
        "ms_total": mean("ms_step"),
    }
    ms_regulariser = mean("ms_regulariser")
    row["ms_other"] = row["ms_total"] - sum(row[f"ms_{p}"] for p in PARTS[:-1])
    row["edit_8000_minutes"] = row["ms_total"] * 8000 / 60000
    row.update({
        "ms_total_min": min(i["ms_step"] for i in kept),
        "ms_total_max": max(i["ms_step"] for i in kept),
        "iterations_warm": warm,
        "iterations_timed": timed,
        "ms_regulariser_forward": ms_regulariser,
        "samples_per_ray": mean("samples_per_ray"),
        "model_load_s": load_s,
        "run_wall_s": wall,
        "threads": torch.get_num_threads(),
        "cpu_cores": os.cpu_count(),
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "model_note": COST_NOTE,
        "what_the_timing_buys": note,
    })
    del guidance
    return row


# ---------------------------------------------------------------- output
def print_table(rows: list[dict]) -> None:
    head = (f"{'model':<16} {'dev':<4} {'dtype':<8} {'res':>4} {'rend':>4} | {'render':>8} {'vae':>8} {'unet':>8} "
            f"{'backward':>8} {'optim':>7} {'other':>7} | {'total ms':>9} {'8000 it (min)':>13}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['model']:<16} {r['device']:<4} {r['dtype']:<8} {r['resolution']:>4} {r['render_size']:>4} | "
              f"{r['ms_render']:>8.1f} {r['ms_vae']:>8.1f} {r['ms_unet']:>8.1f} {r['ms_backward']:>8.1f} "
              f"{r['ms_optimizer']:>7.1f} {r['ms_other']:>7.1f} | {r['ms_total']:>9.1f} {r['edit_8000_minutes']:>13.1f}")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['model']} {r['device']} {r['dtype']}\n{r['resolution']}² guidance, {r['render_size']}² render"
              for r in rows]
    colours = ["#4c72b0", "#dd8452", "#c44e52", "#8172b3", "#55a868", "#bbbbbb"]
    fig, ax = plt.subplots(figsize=(10, 1.2 + 0.9 * len(rows)))
    for i, r in enumerate(rows):
        left = 0.0
        for part, colour in zip(PARTS, colours):
            share = max(0.0, r[f"ms_{part}"]) / r["ms_total"] * 100
            ax.barh(i, share, left=left, color=colour, label=part if i == 0 else None)
            left += share
        ax.text(101, i, f"{r['ms_total']:.0f} ms/it\n8000 it: {r['edit_8000_minutes']:.1f} min", va="center",
                fontsize=8)
    ax.set_yticks(range(len(rows)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, 125)
    ax.set_xlabel("share of one editing iteration (%)  —  random-weight models: cost only")
    ax.legend(ncol=len(PARTS), loc="upper center", bbox_to_anchor=(0.45, -0.35 if len(rows) < 3 else -0.18),
              fontsize=8, frameon=False)
    ax.set_title("Vox-E editing step: where the time goes")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_skip_density(rows: list[dict], path: Path) -> None:
    """Per lattice size: the occupancy's and the whole step's medians in both arms, the step ratio and whether the
    features ended the same (the accuracy the saving keeps) written beside them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    x = range(len(rows))
    for ax, part in zip(axes, ("occupancy", "step")):
        for offset, arm, colour in ((-0.2, "built_once", "#4c72b0"), (0.2, "rebuilt_each_step", "#dd8452")):
            ax.bar([i + offset for i in x], [r[f"ms_{part}_{arm}"] for r in rows], width=0.4, color=colour,
                   label=arm.replace("_", " "))
        ax.set_xticks(list(x), [f"{r['grid_resolution']}³" for r in rows])
        ax.set_ylabel(f"{part}, median ms")
        ax.set_title({"occupancy": "the step's occupancy", "step": "the whole step"}[part])
    for i, r in enumerate(rows):
        axes[1].annotate(f"×{r['time_ratio_built_once_to_rebuilt']:.3f}\nsame: {r['same_features']}", (i, 0),
                         xytext=(0, 4), textcoords="offset points", ha="center", fontsize=8, color="white")
    axes[0].legend(fontsize=8, frameon=False)
    fig.suptitle("Scene grid skip density: built once per edit against rebuilt each step (tiny model, CPU)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def default_out(quick: bool, gpu: bool) -> Path:
    """The JSON a run writes unless told (its PNG beside it): a quick run's under results/quick/ (as
    ``bench/report.py --quick``'s), a GPU run's apart from the CPU's, so neither replaces the full-size CPU record."""
    return (RESULTS / "quick" if quick else RESULTS) / f"edit_step{'_gpu' if gpu else ''}.json"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--gpu", action="store_true", help="CUDA fp16, 512² guidance, 266² renders")
    parser.add_argument("--quick", action="store_true", help="tiny model only (default --out: bench/results/quick/)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON to write, the PNG beside it (default: bench/results/edit_step[_gpu].json)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1: on a shared 2-core box OpenMP hand-offs cost more than they give)")
    parser.add_argument("--skip-density", type=int, nargs="+", metavar="RESOLUTION", default=None,
                        help="only the tiny model on scene grids of these sizes, skip density built once vs each step "
                             "(default --out: bench/results/edit_step_skip_density.json)")
    parser.add_argument("--rounds", type=int, default=4, help="--skip-density: edits of 16 timed steps (default 4)")
    parser.add_argument("--build-full", type=Path, default=None, help=argparse.SUPPRESS)  # subprocess entry
    parser.add_argument("--tokenizer-from", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--family", choices=FAMILIES, default="sd2-base", help=argparse.SUPPRESS)
    parser.add_argument("--build-device", default="cpu", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.skip_density is not None and (args.gpu or args.quick or args.rounds < 1 or min(args.skip_density) < 2):
        parser.error("--skip-density is a CPU run of its own (without --gpu or --quick), on lattices of at least "
                     f"2 per axis, at least 1 round: got {args.skip_density}, --rounds {args.rounds}")

    if args.build_full is not None:
        build_sd2_base_shaped(args.build_full, args.tokenizer_from, family=args.family, device=args.build_device)
        return

    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    torch.set_num_threads(max(1, args.threads))
    device = "cuda" if args.gpu else "cpu"
    if args.gpu and not torch.cuda.is_available():
        sys.exit("--gpu needs a CUDA device")
    if args.skip_density is not None:
        out = args.out or RESULTS / "edit_step_skip_density.json"
        with tempfile.TemporaryDirectory(prefix="voxe_edit_bench_") as tmp:
            tiny = build_tiny_stable_diffusion(Path(tmp) / "tiny", seed=0)
            rows = [time_skip_density(tiny, n, args.rounds, 2, 16) for n in args.skip_density]
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"description": "see bench/edit_step.py --skip-density", "runs": rows}, indent=2)
                       + "\n")
        for r in rows:
            print(f"scene grid {r['grid_resolution']}³: {r['ms_step_built_once']:.2f} ms/step built once, "
                  f"{r['ms_step_rebuilt_each_step']:.2f} rebuilt each step (ratio "
                  f"{r['time_ratio_built_once_to_rebuilt']:.3f}); its occupancy {r['ms_occupancy_built_once']:.2f} "
                  f"against {r['ms_occupancy_rebuilt_each_step']:.2f} ms; same features: {r['same_features']}")
        plot_skip_density(rows, out.with_suffix(".png"))
        print(f"wrote {out} and its .png")
        return
    out = args.out or default_out(args.quick, args.gpu)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="voxe_edit_bench_") as tmp:
        tmp = Path(tmp)
        tiny = build_tiny_stable_diffusion(tmp / "tiny", seed=0)
        tiny_note = ("plumbing cost: render, regulariser and dense Adam on a 160³ grid around a toy network; "
                     "nothing about edit quality")
        rows.append(time_run("tiny", tiny, device, torch.float32, 64, 64, 5, 20, tiny_note))
        print_table(rows[-1:])
        if not args.quick:
            t0 = time.perf_counter()
            # Built in a subprocess so its memory is returned before the models are loaded again.
            subprocess.run([sys.executable, __file__, "--build-full", str(tmp / "sd2"), "--tokenizer-from",
                            str(tiny / "tokenizer")], check=True)
            print(f"built the SD-2-base-shaped random model in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
            full_note = ("cost of the real SD-2-base architecture ({}); quality not measured (random weights){}")
            if args.gpu:
                rows.append(time_run("sd2-base-shaped", tmp / "sd2", device, torch.float16, 512, 266, 5, 20,
                                     full_note.format("paper settings: 512² guidance, 266² renders", "")))
            else:
                for res in (64, 128):
                    rows.append(time_run(
                        "sd2-base-shaped", tmp / "sd2", device, torch.float32, res, res, 3, 5,
                        full_note.format(f"{res}² guidance on CPU",
                                         "; real weights would guide poorly this far below their 512² training size"),
                    ))
                    print_table(rows[-1:])
    out.write_text(json.dumps(rows, indent=2) + "\n")
    plot(rows, out.with_suffix(".png"))
    print()
    print_table(rows)
    print(f"\nwrote {out} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
