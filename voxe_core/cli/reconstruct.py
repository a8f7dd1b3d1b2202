"""``voxe reconstruct``: fit G_i to posed images (SPEC §1); its recipe options are the job parameters' ``reconstruction``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from voxe_core.cli.common import (
    EXIT_INTERRUPTED, add_device_argument, add_grid_output_arguments, add_view_arguments, check_device, int_list,
    int_list_at_most, load_views, one_or_list, positive_int, positive_int_at_most, run_stage, said_by_option, seed,
    tensor_file, view_params, writable_file,
)
from voxe_core.constants import MAX_GRID_RESOLUTION, MAX_RAYS_PER_STEP, MIN_GRID_RESOLUTION
from voxe_core.presets import (
    BACKBONE,
    BACKBONE_CHOICES,
    RECONSTRUCTION_PRESET,
    RECONSTRUCTION_PRESETS,
    SEED,
    fit_setup,
    reconstruction_key,
    reconstruction_params,
)

CHECKPOINT_EVERY = 100


def add_parsers(commands, common) -> None:
    rec = commands.add_parser("reconstruct", parents=[common], help="fit a voxel grid to posed images (SPEC §1)")
    rec.add_argument("data", type=Path, metavar="DATA_DIR", help="dataset folder: NeRF-synthetic, instant-ngp / nerfstudio transforms.json, or a COLMAP model (sparse/0/ or sparse/ beside images/)")
    rec.add_argument("--out", type=tensor_file, required=True, help="grid file to write (.safetensors)")
    add_grid_output_arguments(rec)
    add_view_arguments(rec, "train")
    add_recipe_arguments(rec)
    rec.add_argument("--checkpoint", type=tensor_file, default=None,
                     help="write a resumable checkpoint here (.safetensors)")
    rec.add_argument("--checkpoint-every", type=positive_int, default=None,
                     help=f"iterations between --checkpoint's writes (default {CHECKPOINT_EVERY})")
    rec.add_argument("--resume", type=Path, default=None, help="continue from this checkpoint")
    rec.add_argument("--backbone", choices=BACKBONE_CHOICES, default=BACKBONE,
                     help="relu_field: objects on a transparent background; scene: captured photos with a "
                          "background (DVGO-style, SPEC §5); auto: from the images' alpha")
    add_device_argument(rec)
    rec.set_defaults(run=cmd_reconstruct)


def add_recipe_arguments(parser: argparse.ArgumentParser) -> None:
    """The reconstruction recipe: the job parameters' ``reconstruction``."""
    parser.add_argument("--preset", choices=RECONSTRUCTION_PRESETS, default=None,
                        help="fast: the CPU budget (40→80→128); paper: the authors' 20→40→80→160 × 500; scene: "
                             "the CPU budget of a scene-backbone fit (48→96); default: scene for a scene-backbone "
                             f"fit, {RECONSTRUCTION_PRESET} otherwise")
    parser.add_argument("--resolution", type=int_list_at_most(MAX_GRID_RESOLUTION, MIN_GRID_RESOLUTION), default=None,
                        metavar="N[,N...]", help="final grid resolution (earlier stages scaled in proportion), or one "
                        f"per stage (the final at least {MIN_GRID_RESOLUTION}; at most {MAX_GRID_RESOLUTION})")
    parser.add_argument("--iterations", type=int_list, default=None, metavar="N[,N...]",
                        help="iterations of the final stage, or one per stage")
    parser.add_argument("--rays", type=positive_int_at_most(MAX_RAYS_PER_STEP), default=None,
                        help=f"rays per step (at most {MAX_RAYS_PER_STEP})")
    parser.add_argument("--seed", type=seed, default=SEED)


RESOLUTION_SETTINGS = {"grid resolutions": "--resolution", "grid resolution": "--resolution"}
"""The grid's and the fit's own refusals of a ``--resolution`` (``said_by_option``): "grid resolutions must be at
least 2, got [2, 2, 0]" had named no option typed."""


def recipe_params(args: argparse.Namespace) -> dict:
    """The job parameters' ``reconstruction`` from the options of ``add_recipe_arguments``."""
    return {"preset": args.preset, "resolution": one_or_list(args.resolution),
            "iterations": one_or_list(args.iterations), "rays_per_step": args.rays, "seed": args.seed}


def job_params(args: argparse.Namespace) -> dict:
    """What ``voxe reconstruct``'s options say, as the service's job parameters."""
    return {**view_params(args), "reconstruction": {**recipe_params(args), "backbone": args.backbone}}


def cmd_reconstruct(args) -> int:
    from voxe_core.reconstruct import CHECKPOINT_FORMAT_VERSION, CHECKPOINT_KIND, reconstruct
    from voxe_core.tensorio import load_header

    if args.checkpoint_every is not None and args.checkpoint is None:  # (it had been taken and ignored)
        raise ValueError("--checkpoint-every sets how often --checkpoint is written; without --checkpoint none is")
    for flag, checkpoint in (("--checkpoint", args.checkpoint), ("--resume", args.resume)):  # (the grid had replaced it)
        if checkpoint is not None and checkpoint.resolve() == args.out.resolve():
            raise ValueError(f"{flag} and --out both name {args.out}: the grid written at the end would replace the "
                             "checkpoint; give the checkpoint a file of its own")
    device = check_device(args)
    for path in (args.out, args.checkpoint):  # before the fit: its --checkpoint folder had not been made at all
        if path is not None:
            writable_file(path)
    params = reconstruction_params(job_params(args))
    with said_by_option(RESOLUTION_SETTINGS):
        reconstruction_key(params)  # iterations that fit no backbone's preset are refused before any data is read
    if args.resume is not None:  # as is a --resume that is no checkpoint (missing, a grid: said after the data)
        load_header(args.resume, CHECKPOINT_KIND, CHECKPOINT_FORMAT_VERSION)
    scene = load_views(args)
    every = CHECKPOINT_EVERY if args.checkpoint_every is None else args.checkpoint_every
    backbone, config, cameras, initial = fit_setup(params, scene.alphas, scene.cameras, every if args.checkpoint else 0,
                                                   split_c2w=scene.split_c2w)
    print(
        f"fitting {len(scene)} {scene.split} images of {scene.cameras.width}x{scene.cameras.height} "
        f"from {args.data} ({backbone} backbone) on {device}: resolutions {list(config.resolutions)}, "
        f"iterations {list(config.iterations)}, {config.rays_per_step} rays/step",
        file=sys.stderr,
    )
    grid = run_stage(
        lambda callbacks: reconstruct(scene.images, cameras, config, callbacks, args.checkpoint, args.resume, initial,
                                      device),
        "reconstruct", "it", config.total_iterations, args.quiet,
    )
    if grid is None:
        hint = f"; resume with --resume {args.checkpoint}" if args.checkpoint and args.checkpoint.is_file() else ""
        print(f"voxe: reconstruction cancelled, nothing written to {args.out}{hint}", file=sys.stderr)
        return EXIT_INTERRUPTED
    grid.save(args.out, dense=args.dense)
    occupancy = grid.occupancy()
    res = "x".join(str(r) for r in grid.resolution)
    print(f"wrote {args.out}: {res} grid, occupied fraction {occupancy.fraction:.4f}")
    return 0
