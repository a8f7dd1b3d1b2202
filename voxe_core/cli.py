"""The ``voxe`` command line: a thin layer of argument parsing over voxe_core.

    voxe reconstruct DATA_DIR --out grid.safetensors [--preset fast|paper] ...
    voxe render GRID --data DATA_DIR --split test --out DIR   |   --ring N --size S
    voxe turntable GRID --out turntable.mp4|.gif [--frames 180] [--size 256] [--elevation 30]
    voxe export-mesh GRID --out mesh.ply|.glb [--level L] [--resolution N]
    voxe refine EDITED_GRID --initial GRID --prompt TEXT --edit-words WORDS --out DIR [--model ID_OR_DIR] ...
    voxe edit GRID --prompt TEXT --out DIR [--model ID_OR_DIR] [--iterations N] [--render-size N] ...
    voxe build-tiny-model DIR      (random-weight SMOKE-TEST Stable Diffusion, plumbing only)
    voxe evaluate GRID --edit EDITED_GRID PROMPT [MASK] ... --object NAME --out DIR [--clip-model ID_OR_DIR] ...
    voxe sweep --api URL --scene SCENE_ID=OBJECT ... [--params JSON] [--evaluation JSON] [--wait]   (the service)

Bad input (dataset, grid file, option values) prints one line on stderr and
exits 2; Ctrl-C during a long stage cancels it cleanly and exits 130.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Iterator, Sequence

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class _Interrupt:
    """SIGINT sets a flag that a stage polls through ``Callbacks.should_cancel``; a second Ctrl-C aborts at once."""

    def __init__(self):
        self.requested = False

    def __call__(self) -> bool:
        return self.requested

    def _handle(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print("\nvoxe: interrupt received, stopping after this step (Ctrl-C again to abort)", file=sys.stderr)

    @contextlib.contextmanager
    def installed(self) -> Iterator["_Interrupt"]:
        if threading.current_thread() is not threading.main_thread():
            yield self  # signal handlers can only be set from the main thread
            return
        previous = signal.signal(signal.SIGINT, self._handle)
        try:
            yield self
        finally:
            signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def progress_callbacks(
    desc: str, unit: str = "it", should_cancel=None, quiet: bool = False, total: int | None = None
):
    """Callbacks whose ``on_progress`` drives one tqdm bar (total and losses taken from each report)."""
    from tqdm import tqdm

    from voxe_core.progress import Callbacks, Progress

    bar = tqdm(desc=desc, unit=unit, total=total, disable=quiet, dynamic_ncols=True, file=sys.stderr)

    def on_progress(report: Progress) -> None:
        if bar.total != report.total:
            bar.total = report.total
        postfix = {k: f"{v:.4f}" for k, v in report.losses.items()}
        for key in ("stage", "resolution"):
            if key in report.info:
                postfix[key] = report.info[key]
        if postfix:
            bar.set_postfix(postfix, refresh=False)
        bar.update(report.iteration - bar.n)

    try:
        yield Callbacks(on_progress=on_progress, should_cancel=should_cancel)
    finally:
        bar.close()


def run_stage(fn, desc: str, unit: str, total: int | None, quiet: bool = False):
    """Run ``fn(callbacks)`` under a progress bar with Ctrl-C wired to cancellation.

    Returns what ``fn`` returns, or None when the user interrupted it (the
    stage raised ``StageCancelled`` at its next cancellation check).
    """
    from voxe_core.progress import StageCancelled

    interrupt = _Interrupt()
    with interrupt.installed(), progress_callbacks(desc, unit, interrupt, quiet, total) as callbacks:
        try:
            return fn(callbacks)
        except StageCancelled:
            return None


def _int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer or a comma-separated list of integers, got {text!r}")
    if not values or any(v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected non-negative integers, got {text!r}")
    return values


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _add_view_arguments(parser: argparse.ArgumentParser, split: str, downsample: int) -> None:
    """Which dataset images a command reads, and how they are downsampled on load."""
    parser.add_argument("--split", default=split)
    parser.add_argument("--downsample", type=_positive_int, default=downsample,
                        help=f"integer image downsampling on load (default {downsample})")
    # voxe_core.data.RESAMPLE_FILTERS, spelt out: importing it here would load torch for --help.
    parser.add_argument("--resample", choices=("bilinear", "box"), default="bilinear",
                        help="the downsampling's antialiasing filter (bilinear: as the authors' loader)")
    parser.add_argument("--max-images", type=_positive_int, default=None, help="use only the first N images")


def _load_views(args: argparse.Namespace):
    from voxe_core.data import load_scene

    return load_scene(args.data, args.split, args.downsample, args.max_images, resample=args.resample)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="voxe", description="Vox-E voxel grids: reconstruct, render, export.")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", "-q", action="store_true", help="no progress bars")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    rec = commands.add_parser("reconstruct", parents=[common], help="fit a voxel grid to posed images (SPEC §1)")
    rec.add_argument("data", type=Path, metavar="DATA_DIR", help="NeRF-synthetic or instant-ngp dataset folder")
    rec.add_argument("--out", type=Path, required=True, help="grid file to write (.safetensors)")
    _add_view_arguments(rec, "train", 4)
    rec.add_argument("--preset", choices=("fast", "paper"), default="fast",
                     help="fast: the CPU budget (40→80→128); paper: the authors' 20→40→80→160 × 500")
    rec.add_argument("--resolution", type=_int_list, default=None, metavar="N[,N...]",
                     help="final grid resolution (earlier stages scaled in proportion), or one per stage")
    rec.add_argument("--iterations", type=_int_list, default=None, metavar="N[,N...]",
                     help="iterations of the final stage, or one per stage")
    rec.add_argument("--rays", type=_positive_int, default=None, help="rays per step")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--checkpoint", type=Path, default=None, help="write a resumable checkpoint here")
    rec.add_argument("--checkpoint-every", type=_positive_int, default=100, help="iterations between checkpoints")
    rec.add_argument("--resume", type=Path, default=None, help="continue from this checkpoint")
    rec.add_argument("--backbone", choices=("auto", "relu_field", "scene"), default="auto",
                     help="relu_field: objects on a transparent background; scene: captured photos with a "
                          "background (DVGO-style, SPEC §5); auto: from the images' alpha")

    ren = commands.add_parser("render", parents=[common], help="render PNG views of a grid (dataset cameras or a ring)")
    ren.add_argument("grid", type=Path, metavar="GRID")
    source = ren.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, metavar="DATA_DIR", help="render this dataset split's cameras")
    source.add_argument("--ring", type=_positive_int, metavar="N", help="render N views on a 360° ring instead")
    _add_view_arguments(ren, "test", 4)
    ren.add_argument("--size", type=_positive_int, default=256, help="ring view size in pixels")
    ren.add_argument("--elevation", type=float, default=30.0, help="ring elevation in degrees")
    ren.add_argument("--out", type=Path, required=True, metavar="DIR")

    tt = commands.add_parser("turntable", parents=[common], help="render a 360° turntable video (.mp4 or .gif)")
    tt.add_argument("grid", type=Path, metavar="GRID")
    tt.add_argument("--out", type=Path, required=True, help="video file, .mp4 or .gif")
    tt.add_argument("--frames", type=_positive_int, default=180)
    tt.add_argument("--size", type=_positive_int, default=256)
    tt.add_argument("--elevation", type=float, default=30.0)
    tt.add_argument("--fps", type=float, default=30.0)

    mesh = commands.add_parser(
        "export-mesh", parents=[common], help="marching-cubes mesh with vertex colours (.ply or .glb)"
    )
    mesh.add_argument("grid", type=Path, metavar="GRID")
    mesh.add_argument("--out", type=Path, required=True, help="mesh file, .ply or .glb")
    mesh.add_argument("--level", type=float, default=None, help="surface density (default ln 2 / voxel size)")
    mesh.add_argument("--resolution", type=_positive_int, default=None, help="resample to N points per axis")
    _add_mesh_input_parser(commands, common)
    _add_edit_parsers(commands, common)
    _add_refine_parser(commands, common)
    _add_evaluate_parser(commands, common)
    _add_sweep_parser(commands, common)
    return parser


def _add_mesh_input_parser(commands, common) -> None:
    mg = commands.add_parser("mesh-to-grid", parents=[common],
                             help="an initial grid from an OBJ (+ texture) or PLY (vertex colours) mesh")
    mg.add_argument("mesh", type=Path, metavar="MESH", help=".obj or .ply")
    mg.add_argument("--texture", type=Path, default=None, help="the OBJ's texture image")
    mg.add_argument("--up", choices=("x", "y", "z"), default="y", help="the mesh file's up axis (OBJ: y)")
    mg.add_argument("--route", choices=("voxelize", "render"), default="voxelize",
                    help="voxelize: write the mesh into the grid; render: reconstruct from rendered views")
    mg.add_argument("--out", type=Path, required=True, help="grid file to write (.safetensors)")
    mg.add_argument("--views", type=_positive_int, default=100, help="render route: upper-hemisphere views")
    mg.add_argument("--size", type=_positive_int, default=200, help="render route: view size in pixels")
    mg.add_argument("--preset", choices=("fast", "paper"), default="fast", help="render route: reconstruction preset")
    mg.add_argument("--resolution", type=_int_list, default=None, metavar="N[,N...]",
                    help="grid resolution (voxelize: default 160; render: as voxe reconstruct)")
    mg.add_argument("--iterations", type=_int_list, default=None, metavar="N[,N...]", help="render route: as voxe reconstruct")
    mg.add_argument("--rays", type=_positive_int, default=None, help="render route: rays per step")
    mg.add_argument("--seed", type=int, default=0)
    mg.set_defaults(checkpoint=None)


def _add_edit_parsers(commands, common) -> None:
    ed = commands.add_parser("edit", parents=[common], help="text-guided editing of a grid with SDS (SPEC §2)")
    ed.add_argument("grid", type=Path, metavar="GRID", help="initial grid G_i (.safetensors)")
    ed.add_argument("--prompt", required=True, help='edit text, e.g. "a dog wearing big sunglasses"')
    ed.add_argument("--out", type=Path, required=True, metavar="DIR",
                    help="writes DIR/edited.safetensors, DIR/checkpoint.safetensors, DIR/previews/*.png")
    ed.add_argument("--model", default=None, metavar="MODEL_ID_OR_PATH",
                    help="diffusers-layout Stable Diffusion: hub id (from the local cache) or folder "
                         "(default stabilityai/stable-diffusion-2-base)")
    ed.add_argument("--offline", action="store_true", help="never contact the hub (as HF_HUB_OFFLINE=1)")
    ed.add_argument("--device", choices=("cpu", "cuda"), default=None, help="default: cuda when available")
    ed.add_argument("--iterations", type=int, default=None, help="default 8000; 5000 with --schedule real-scene")
    ed.add_argument("--render-size", type=_positive_int, default=266, help="training render size in pixels")
    ed.add_argument("--regulariser", default="reg3d",
                    help="reg3d | reg3d_plus | volumetric_l1 | volumetric_l2 | image_l1 | image_l2 (image_* need --data)")
    ed.add_argument("--reg-weight", type=float, default=200.0)
    ed.add_argument("--guidance-scale", type=float, default=100.0)
    ed.add_argument("--schedule", choices=("paper", "authors", "real-scene"), default="paper",
                    help="time-step annealing: paper (floor 0.35), authors' code (floor 0.22), "
                         "real-scene (SPEC §5: 5000 iterations, i_start 3000, f_a 400)")
    ed.add_argument("--no-view-words", action="store_true", help="do not append ', front view' etc. to the prompt")
    ed.add_argument("--autocast", choices=("bf16", "fp16"), default=None, help="run the guidance under autocast")
    ed.add_argument("--seed", type=int, default=0)
    ed.add_argument("--checkpoint-every", type=int, default=250, help="iterations between checkpoints (0: only at the end)")
    ed.add_argument("--resume", type=Path, default=None, metavar="PATH", help="continue from this edit checkpoint")
    ed.add_argument("--preview-every", type=int, default=250, help="iterations between preview PNGs (0: none)")
    ed.add_argument("--data", type=Path, default=None, metavar="DATA_DIR", help="input views for image_l1 / image_l2")
    _add_view_arguments(ed, "train", 3)

    tiny = commands.add_parser(
        "build-tiny-model", parents=[common],
        help="write a tiny random-weight Stable Diffusion (SMOKE-TEST model: plumbing only, never quality)",
    )
    tiny.add_argument("out", type=Path, metavar="DIR")
    tiny.add_argument("--seed", type=int, default=0)


# --------------------------------------------------------------------- commands
def _per_stage(values: list[int], n_stages: int, what: str) -> list[int] | None:
    if len(values) not in (1, n_stages):
        raise ValueError(f"--{what} takes one value or one per stage ({n_stages} stages), got {len(values)}")
    return None if len(values) == 1 else values


def _reconstruct_config(args):
    from voxe_core.reconstruct import ReconstructConfig

    config = ReconstructConfig.fast() if args.preset == "fast" else ReconstructConfig()
    overrides: dict = {"seed": args.seed}
    n = len(config.resolutions)
    if args.resolution is not None:
        explicit = _per_stage(args.resolution, n, "resolution")
        if explicit is None:
            final = args.resolution[0]
            explicit = [max(2, round(final * r / config.resolutions[-1])) for r in config.resolutions[:-1]] + [final]
        if min(explicit) < 2:
            raise ValueError(f"grid resolutions must be at least 2, got {explicit}")
        overrides["resolutions"] = tuple(explicit)
    if args.iterations is not None:
        explicit = _per_stage(args.iterations, n, "iterations")
        overrides["iterations"] = tuple(explicit or [*config.iterations[:-1], args.iterations[0]])
    if args.rays is not None:
        overrides["rays_per_step"] = args.rays
    if args.checkpoint is not None:
        overrides["checkpoint_every"] = args.checkpoint_every
    return dataclasses.replace(config, **overrides)


def cmd_reconstruct(args) -> int:
    from voxe_core.reconstruct import reconstruct
    from voxe_core.scene_grid import prepare_backbone

    config = _reconstruct_config(args)
    scene = _load_views(args)
    backbone, cameras, initial = prepare_backbone(args.backbone, scene.alphas, scene.cameras, config.resolutions[0])
    print(
        f"fitting {len(scene)} {scene.split} images of {scene.cameras.width}x{scene.cameras.height} "
        f"from {args.data} ({backbone} backbone): resolutions {list(config.resolutions)}, "
        f"iterations {list(config.iterations)}, {config.rays_per_step} rays/step",
        file=sys.stderr,
    )
    grid = run_stage(
        lambda callbacks: reconstruct(scene.images, cameras, config, callbacks, args.checkpoint, args.resume, initial),
        "reconstruct", "it", config.total_iterations, args.quiet,
    )
    if grid is None:
        hint = f"; resume with --resume {args.checkpoint}" if args.checkpoint and args.checkpoint.is_file() else ""
        print(f"voxe: reconstruction cancelled, nothing written to {args.out}{hint}", file=sys.stderr)
        return EXIT_INTERRUPTED
    args.out.parent.mkdir(parents=True, exist_ok=True)
    grid.save(args.out)
    occupancy = grid.occupancy()
    res = "x".join(str(r) for r in grid.resolution)
    print(f"wrote {args.out}: {res} grid, occupied fraction {occupancy.fraction:.4f}")
    return 0


def _load_grid(path: Path):
    from voxe_core.grid import VoxelGrid

    return VoxelGrid.load(path)


def cmd_render(args) -> int:
    from voxe_core.export import render_views, save_png, turntable_cameras

    grid = _load_grid(args.grid)
    scene = None
    if args.data is not None:
        from voxe_core.scene_grid import dataset_cameras

        scene = _load_views(args)
        cameras = dataset_cameras(grid, scene.cameras)
        names = [f"{i:03d}_{Path(name).stem}.png" for i, name in enumerate(scene.names)]
    else:
        cameras = turntable_cameras(args.ring, args.elevation, args.size)
        names = [f"{i:03d}.png" for i in range(args.ring)]
    frames = run_stage(lambda cb: render_views(grid, cameras, callbacks=cb), "render", "view", len(cameras), args.quiet)
    if frames is None:
        print("voxe: rendering cancelled", file=sys.stderr)
        return EXIT_INTERRUPTED
    for frame, name in zip(frames, names):
        save_png(args.out / name, frame)
    print(f"wrote {len(names)} views to {args.out}")
    if scene is not None:
        _report_metrics(frames, scene, names, args.out)
    return 0


def _report_metrics(frames, scene, names, out_dir: Path) -> None:
    from voxe_core.metrics import SSIM_WINDOW, psnr, ssim

    per_view_psnr = psnr(frames, scene.images).tolist()
    height, width = frames.shape[1:3]
    per_view_ssim = ssim(frames, scene.images).tolist() if min(height, width) >= SSIM_WINDOW else None
    mean_psnr = sum(per_view_psnr) / len(per_view_psnr)
    line = f"{scene.split}: PSNR {mean_psnr:.2f} dB"
    summary = {"split": scene.split, "views": len(names), "psnr": mean_psnr, "ssim": None,
               "per_view": [{"file": n, "psnr": p} for n, p in zip(names, per_view_psnr)]}
    if per_view_ssim is not None:
        summary["ssim"] = sum(per_view_ssim) / len(per_view_ssim)
        for entry, s in zip(summary["per_view"], per_view_ssim):
            entry["ssim"] = s
        line += f", SSIM {summary['ssim']:.4f}"
    else:
        line += f" (SSIM needs views of at least {SSIM_WINDOW} px)"
    print(f"{line} over {len(names)} views")
    (out_dir / "metrics.json").write_text(json.dumps(summary, indent=2))


def cmd_turntable(args) -> int:
    from voxe_core.export import VIDEO_SUFFIXES, render_views, turntable_cameras, write_video

    if args.out.suffix.lower() not in VIDEO_SUFFIXES:  # fail before rendering, not after
        raise ValueError(f"unsupported video suffix {args.out.suffix!r}; use one of {', '.join(VIDEO_SUFFIXES)}")
    grid = _load_grid(args.grid)
    cameras = turntable_cameras(args.frames, args.elevation, args.size)
    frames = run_stage(
        lambda cb: render_views(grid, cameras, callbacks=cb), "turntable", "frame", len(cameras), args.quiet
    )
    if frames is None:
        print("voxe: turntable cancelled, nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    write_video(args.out, frames, fps=args.fps)
    print(f"wrote {args.out}: {args.frames} frames of {args.size}x{args.size}")
    return 0


def cmd_export_mesh(args) -> int:
    from voxe_core.export import MESH_SUFFIXES, extract_mesh, save_mesh

    if args.out.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"unsupported mesh suffix {args.out.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    grid = _load_grid(args.grid)
    mesh = extract_mesh(grid, level=args.level, resolution=args.resolution)
    save_mesh(mesh, args.out)
    print(f"wrote {args.out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces")
    return 0


def cmd_mesh_to_grid(args) -> int:
    from voxe_core.mesh_input import VoxelizeConfig, hemisphere_cameras, load_mesh, render_mesh_views, voxelize
    from voxe_core.reconstruct import reconstruct

    mesh = load_mesh(args.mesh, args.texture, args.up)
    if args.route == "voxelize":
        if args.resolution is not None and len(args.resolution) != 1:
            raise ValueError(f"--resolution takes one value for the voxelize route, got {len(args.resolution)}")
        resolution = 160 if args.resolution is None else args.resolution[0]
        grid = voxelize(mesh, VoxelizeConfig(resolution=resolution, seed=args.seed))
    else:
        config = _reconstruct_config(args)
        cameras = hemisphere_cameras(args.views, args.size, args.seed)
        images, _ = render_mesh_views(mesh, cameras)
        grid = run_stage(lambda callbacks: reconstruct(images, cameras, config, callbacks),
                         "reconstruct", "it", config.total_iterations, args.quiet)
        if grid is None:
            print(f"voxe: reconstruction cancelled, nothing written to {args.out}", file=sys.stderr)
            return EXIT_INTERRUPTED
    args.out.parent.mkdir(parents=True, exist_ok=True)
    grid.save(args.out)
    print(f"wrote {args.out}: {'x'.join(map(str, grid.resolution))} grid from {args.mesh.name} ({args.route})")
    return 0


def _edit_config(args):
    from voxe_core.edit import EditConfig
    from voxe_core.schedule import TimestepSchedule

    from voxe_core.scene_grid import real_scene_edit_config

    base = real_scene_edit_config() if args.schedule == "real-scene" else EditConfig()
    schedule = TimestepSchedule.authors() if args.schedule == "authors" else base.schedule
    return EditConfig(
        iterations=base.iterations if args.iterations is None else args.iterations, render_size=args.render_size, regulariser=args.regulariser,
        regulariser_weight=args.reg_weight, guidance_scale=args.guidance_scale, schedule=schedule,
        view_words=not args.no_view_words, autocast_dtype=args.autocast, seed=args.seed,
        checkpoint_every=args.checkpoint_every, preview_every=args.preview_every,
    )


def cmd_edit(args) -> int:
    import torch

    from voxe_core.edit import edit
    from voxe_core.export import save_png
    from voxe_core.guidance import SDS_MODEL_ID, ModelNotAvailableError, StableDiffusionGuidance
    from voxe_core.losses import IMAGE_REGULARISERS

    config = _edit_config(args)  # bad options fail before any loading
    if not args.prompt.strip():
        raise ValueError("the edit prompt is empty")
    if config.regulariser in IMAGE_REGULARISERS and args.data is None:
        raise ValueError(f"--regulariser {config.regulariser} compares renders with the input views: pass --data DATA_DIR")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but no CUDA device is available")
    grid = _load_grid(args.grid)
    views = None
    if args.data is not None and config.regulariser in IMAGE_REGULARISERS:
        from voxe_core.scene_grid import dataset_cameras

        scene = _load_views(args)
        views = (scene.images, dataset_cameras(grid, scene.cameras))
    model = args.model or SDS_MODEL_ID
    try:
        guidance = StableDiffusionGuidance.from_pretrained(
            model, device=args.device, local_files_only=True if args.offline else None
        )
    except ModelNotAvailableError as exc:
        print(f"voxe edit: model not available: {exc}", file=sys.stderr)
        return EXIT_USAGE
    args.out.mkdir(parents=True, exist_ok=True)
    checkpoint = args.out / "checkpoint.safetensors"

    def on_preview(iteration: int, image) -> None:
        save_png(args.out / "previews" / f"preview_{iteration:05d}.png", image)

    print(
        f"editing {args.grid} ({'x'.join(map(str, grid.resolution))}) towards {args.prompt!r} with {model} "
        f"on {guidance.device}: {config.iterations} iterations, {config.render_size} px renders, "
        f"{config.regulariser} x {config.regulariser_weight:g}",
        file=sys.stderr,
    )
    edited = run_stage(
        lambda cb: edit(grid, args.prompt, guidance, config, cb, checkpoint, args.resume, views, on_preview),
        "edit", "it", config.iterations, args.quiet,
    )
    if edited is None:
        print(f"voxe: edit cancelled; resume with --resume {checkpoint}", file=sys.stderr)
        return EXIT_INTERRUPTED
    edited.save(args.out / "edited.safetensors")
    print(f"wrote {args.out / 'edited.safetensors'} and {checkpoint}")
    return 0


def cmd_build_tiny_model(args) -> int:
    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    path = build_tiny_stable_diffusion(args.out, seed=args.seed)
    print(
        f"wrote {path}: SMOKE-TEST MODEL with RANDOM WEIGHTS (seed {args.seed}), for plumbing only; "
        f"edits made with it are noise and say nothing about quality. Use it as `voxe edit ... --model {path}`."
    )
    return 0


def _add_refine_parser(commands, common) -> None:
    ref = commands.add_parser(
        "refine", parents=[common],
        help="localise an edit: 3D cross-attention grids, graph-cut mask, merge with the initial grid (SPEC §3)",
    )
    ref.add_argument("edited", type=Path, metavar="EDITED_GRID", help="the edited grid G_e (.safetensors)")
    ref.add_argument("--initial", type=Path, required=True, metavar="GRID", help="the initial grid G_i the edit started from")
    ref.add_argument("--prompt", required=True, help='the edit text, e.g. "a dog wearing big sunglasses"')
    ref.add_argument("--edit-words", required=True, metavar="WORDS",
                     help='comma-separated words or phrases of the prompt that name the edit, e.g. "sunglasses" or "party hat"')
    ref.add_argument("--out", type=Path, required=True, metavar="DIR",
                     help="writes refined.safetensors, mask.safetensors, probabilities.safetensors, refine.json, renders/*.png")
    ref.add_argument("--model", default=None, metavar="MODEL_ID_OR_PATH",
                     help="diffusers-layout Stable Diffusion for the cross-attention maps: hub id (from the local cache) "
                          "or folder (default CompVis/stable-diffusion-v1-4)")
    ref.add_argument("--offline", action="store_true", help="never contact the hub (as HF_HUB_OFFLINE=1)")
    ref.add_argument("--device", choices=("cpu", "cuda"), default=None, help="default: cuda when available")
    ref.add_argument("--iterations", type=int, default=1500, help="attention-grid fitting iterations")
    ref.add_argument("--render-size", type=_positive_int, default=266, help="render / attention-map size in pixels")
    ref.add_argument("--views", type=_positive_int, default=32, help="random upper-hemisphere views for the 2D maps")
    ref.add_argument("--preview-views", type=int, default=4, help="ring views rendered as PNGs (0: none)")
    ref.add_argument("--seed", type=int, default=0)


def cmd_refine(args) -> int:
    import dataclasses as _dc
    import warnings

    import torch

    from voxe_core.export import save_png, turntable_cameras
    from voxe_core.guidance import ATTENTION_MODEL_ID, ModelNotAvailableError, StableDiffusionGuidance
    from voxe_core.refine import (
        RefineConfig, check_compatible, node_mask, refine, render_attention, render_mask_overlay,
        save_mask, save_probabilities,
    )

    if args.iterations < 0 or args.preview_views < 0:
        raise ValueError("--iterations and --preview-views must be non-negative")
    words = [w.strip() for w in args.edit_words.split(",") if w.strip()]
    if not words:
        raise ValueError("--edit-words names no word")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but no CUDA device is available")
    model = args.model or ATTENTION_MODEL_ID
    config = RefineConfig(iterations=args.iterations, render_size=args.render_size, views=args.views,
                          seed=args.seed, attention_model=model)
    initial, edited = _load_grid(args.initial), _load_grid(args.edited)
    check_compatible(initial, edited)
    try:
        guidance = StableDiffusionGuidance.from_pretrained(
            model, device=args.device, local_files_only=True if args.offline else None
        )
    except ModelNotAvailableError as exc:
        print(f"voxe refine: model not available: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(f"refining {args.edited} against {args.initial} for {words} of {args.prompt!r} with {model} on "
          f"{guidance.device}: {config.views} views of {config.render_size} px, {config.iterations} iterations",
          file=sys.stderr)
    with warnings.catch_warnings():  # seed shortfalls are reported below from the result
        warnings.filterwarnings("ignore", message=r"only \d+ of \d+ (edit|object) seeds")
        result = run_stage(
            lambda cb: refine(initial, edited, args.prompt, words, guidance, config, cb),
            "refine", "it", None, args.quiet,
        )
    if result is None:
        print("voxe: refinement cancelled, nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    result.refined_grid.save(out / "refined.safetensors")
    save_mask(out / "mask.safetensors", result.mask, meta={"prompt": result.info["prompt"], "edit_words": words})
    nodes = node_mask(edited, config.node_alpha)
    save_probabilities(out / "probabilities.safetensors", result.edit_probability, result.object_probability, nodes)
    renders = out / "renders"
    if args.preview_views:
        cameras = turntable_cameras(args.preview_views, 30.0, args.render_size)
        groups = {
            "attention_edit": render_attention(edited, result.edit_field, cameras),
            "attention_object": render_attention(edited, result.object_field, cameras),
            "probability_edit": render_attention(edited, result.edit_probability, cameras),
            "mask": render_mask_overlay(edited, result.mask, cameras),
            "refined": render_mask_overlay(result.refined_grid, torch.zeros_like(result.mask), cameras, strength=0.0),
        }
        for name, frames in groups.items():
            for i, frame in enumerate(frames):
                save_png(renders / f"{name}_{i:02d}.png", frame)
    for i in range(min(args.preview_views, len(result.edit_maps))):
        save_png(renders / f"map2d_edit_{i:02d}.png", result.edit_maps[i].cpu()[..., None].expand(-1, -1, 3))
        save_png(renders / f"map2d_object_{i:02d}.png", result.object_maps[i].cpu()[..., None].expand(-1, -1, 3))
    stats = _dc.asdict(result.stats)
    summary = {"prompt": result.info["prompt"], "edit_words": words, "model": model,
               "settings": {"views": config.views, "render_size": config.render_size, "iterations": config.iterations,
                            "seed": config.seed},
               "graph_cut": stats, "masked_voxels": int(result.mask.sum())}
    (out / "refine.json").write_text(json.dumps(summary, indent=2))
    for note in result.stats.notes:
        print(f"voxe refine: note: {note}", file=sys.stderr)
    print(f"wrote {out}: {stats['edit_voxels']} of {stats['nodes']} occupied voxels take the edit "
          f"({stats['edit_seeds']} edit / {stats['object_seeds']} object seeds)")
    return 0


def _add_evaluate_parser(commands, common) -> None:
    ev = commands.add_parser(
        "evaluate", parents=[common],
        help="the paper's metrics on a 360° ring: CLIP_sim, CLIP_dir, FID_rec / FID_input, PSNR / SSIM outside the mask (SPEC §4)",
    )
    ev.add_argument("initial", type=Path, metavar="GRID", help="the initial grid G_i (.safetensors)")
    ev.add_argument("--edit", nargs="+", action="append", required=True, metavar="ARG",
                    help="EDITED_GRID PROMPT [MASK]: an edit, its prompt and, for a refined local edit, "
                         "its mask.safetensors (repeat --edit for several edits)")
    ev.add_argument("--object", required=True, help='what the object is, for the source text "a render of a <object>"')
    ev.add_argument("--out", type=Path, required=True, metavar="DIR",
                    help="writes evaluation.json, evaluation.md and the ring renders ring/<name>/NNN.png")
    ev.add_argument("--clip-model", default=None, metavar="MODEL_ID_OR_PATH",
                    help="transformers CLIPModel: hub id (from the local cache) or folder (default openai/clip-vit-base-patch32)")
    ev.add_argument("--inception", type=Path, default=None, metavar="PATH",
                    help="TorchScript Inception file (inception-2015-12-05.pt) or its folder; without it no FID")
    ev.add_argument("--offline", action="store_true", help="never contact the hub (as HF_HUB_OFFLINE=1)")
    ev.add_argument("--device", choices=("cpu", "cuda"), default=None, help="default: cuda when available")
    ev.add_argument("--data", type=Path, default=None, metavar="DATA_DIR", help="input views for FID_input")
    _add_view_arguments(ev, "train", 3)
    ev.add_argument("--views", type=_positive_int, default=100, help="ring views (the paper: 100)")
    ev.add_argument("--elevation", type=float, default=30.0, help="ring elevation in degrees")
    ev.add_argument("--size", type=_positive_int, default=266, help="ring render size in pixels")


def cmd_evaluate(args) -> int:
    import torch

    from voxe_core.evaluate import (
        CLIP_MODEL_ID, ClipScorer, EditSample, EvaluateConfig, InceptionFeatures, evaluate, format_table, save_png_set,
    )
    from voxe_core.guidance import ModelNotAvailableError
    from voxe_core.refine import load_mask

    config = EvaluateConfig(views=args.views, elevation=args.elevation, size=args.size)
    for values in args.edit:
        if len(values) not in (2, 3):
            raise ValueError(f"--edit takes EDITED_GRID PROMPT [MASK], got {len(values)} values: {values}")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but no CUDA device is available")
    initial = _load_grid(args.initial).to(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    edits = []
    for k, (grid_path, prompt, *mask_path) in enumerate(args.edit):
        mask = load_mask(Path(mask_path[0])) if mask_path else None
        edits.append(EditSample(f"edit{k:02d}", prompt, _load_grid(Path(grid_path)).to(initial.bbox_min.device), mask))
    input_images = None
    if args.data is not None:
        input_images = _load_views(args).images
    model = args.clip_model or CLIP_MODEL_ID
    try:
        clip = ClipScorer.from_pretrained(model, device=args.device, local_files_only=True if args.offline else None)
        fid = InceptionFeatures.load(args.inception, device=args.device) if args.inception is not None else None
    except ModelNotAvailableError as exc:
        print(f"voxe evaluate: model not available: {exc}", file=sys.stderr)
        return EXIT_USAGE
    result = run_stage(
        lambda cb: evaluate(initial, edits, args.object, clip, fid, input_images, config, cb),
        "evaluate", "view", (1 + len(edits)) * config.views, args.quiet,
    )
    if result is None:
        print("voxe: evaluation cancelled, nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    out = args.out
    save_png_set(out / "ring" / "initial", result.initial_frames)
    for name, frames in result.edit_frames.items():
        save_png_set(out / "ring" / name, frames)
    summary = {**result.summary(), "object": args.object, "clip_model": model,
               "inception": str(args.inception) if args.inception else None,
               "ring": {"views": config.views, "elevation": config.elevation, "size": config.size},
               "edits": [{"name": e.name, "grid": str(g[0]), "mask": g[2] if len(g) > 2 else None}
                         for e, g in zip(edits, args.edit)]}
    (out / "evaluation.json").write_text(json.dumps(summary, indent=2))
    table = format_table(result.rows, extra_columns=("name",))
    (out / "evaluation.md").write_text(table)
    print(table, end="")
    return 0


def _scene_object(text: str) -> dict:
    scene_id, sep, name = text.partition("=")
    if not sep or not scene_id.strip() or not name.strip():
        raise argparse.ArgumentTypeError(f"expected SCENE_ID=OBJECT (e.g. 3f2a...=microphone), got {text!r}")
    return {"scene_id": scene_id.strip(), "object": name.strip()}


def _json_object(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"not JSON: {exc}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r}")
    return value


def _add_sweep_parser(commands, common) -> None:
    sw = commands.add_parser(
        "sweep", parents=[common],
        help="submit the paper's protocol to the service: scenes × the six prompts of SPEC §4, each edit evaluated",
    )
    sw.add_argument("--api", default="http://127.0.0.1:8000", metavar="URL", help="the service's base URL")
    sw.add_argument("--scene", type=_scene_object, action="append", required=True, metavar="SCENE_ID=OBJECT",
                    help="an uploaded scene and what its object is called in the prompts (repeat for several)")
    sw.add_argument("--params", type=_json_object, default=None, metavar="JSON", help="edit job params (POST /v1/jobs)")
    sw.add_argument("--evaluation", type=_json_object, default=None, metavar="JSON",
                    help='evaluation params, e.g. \'{"views": 100, "size": 266}\'')
    sw.add_argument("--api-key", default=None, help="API key (default: $VOXE_API_KEY; none needed on a loopback service)")
    sw.add_argument("--wait", action="store_true", help="poll until every job of the sweep is finished")
    sw.add_argument("--poll", type=float, default=10.0, help="seconds between polls with --wait")
    sw.add_argument("--out", type=Path, default=None, metavar="FILE", help="also write the final summary JSON here")


class ServiceError(ValueError):
    """The service answered with an error status (its detail is the message)."""


def _service_call(base: str, path: str, api_key: str | None, body: dict | None = None) -> dict:
    import urllib.error
    import urllib.request

    headers = {"content-type": "application/json", "accept": "application/json"}
    if api_key:
        headers["authorization"] = f"Bearer {api_key}"
    request = urllib.request.Request(base.rstrip("/") + path, headers=headers, method="GET" if body is None else "POST",
                                     data=None if body is None else json.dumps(body).encode())
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            return json.loads(response.read())
    except urllib.error.HTTPError as exc:
        try:
            detail = json.loads(exc.read()).get("detail")
        except (ValueError, AttributeError):
            detail = exc.reason
        raise ServiceError(f"{request.method} {path}: HTTP {exc.code}: {detail}") from None
    except urllib.error.URLError as exc:
        raise ServiceError(f"cannot reach the service at {base}: {exc.reason}") from None


def cmd_sweep(args) -> int:
    import os
    import time

    api_key = args.api_key or os.environ.get("VOXE_API_KEY")
    body = {"scenes": args.scene}
    if args.params is not None:
        body["params"] = args.params
    if args.evaluation is not None:
        body["evaluation"] = args.evaluation
    sweep = _service_call(args.api, "/v1/sweeps", api_key, body)
    print(f"sweep {sweep['id']}: {len(sweep['entries'])} edits of {len(args.scene)} scene(s) queued, each followed by "
          f"its evaluation; GET {args.api.rstrip('/')}/v1/sweeps/{sweep['id']}", file=sys.stderr)
    interrupt = _Interrupt()
    with interrupt.installed():
        while args.wait and sweep["state"] in ("queued", "running") and not interrupt.requested:
            if not args.quiet:
                print(f"sweep {sweep['id']}: {sweep['state']}, jobs {sweep['counts']}", file=sys.stderr)
            time.sleep(args.poll)
            sweep = _service_call(args.api, f"/v1/sweeps/{sweep['id']}", api_key)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(sweep, indent=2))
    print(sweep["table"], end="")
    if interrupt.requested:
        print(f"voxe sweep: stopped waiting; the sweep {sweep['id']} goes on in the service", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


COMMANDS = {
    "reconstruct": cmd_reconstruct,
    "render": cmd_render,
    "turntable": cmd_turntable,
    "export-mesh": cmd_export_mesh,
    "mesh-to-grid": cmd_mesh_to_grid,
    "edit": cmd_edit,
    "build-tiny-model": cmd_build_tiny_model,
    "refine": cmd_refine,
    "evaluate": cmd_evaluate,
    "sweep": cmd_sweep,
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``voxe``; returns the exit status (0 ok, 2 bad input, 130 interrupted)."""
    args = build_parser().parse_args(argv)
    from voxe_core.data import DatasetError
    from voxe_core.tensorio import FormatError

    try:
        return COMMANDS[args.command](args)
    except (DatasetError, FormatError, ValueError, OSError) as exc:
        kind = "dataset error" if isinstance(exc, DatasetError) else "error"
        print(f"voxe {args.command}: {kind}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("\nvoxe: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
