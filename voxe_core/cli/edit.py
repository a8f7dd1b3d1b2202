"""``voxe edit`` (text-guided SDS editing, SPEC §2; SPEC §5's schedule for scene grids) and ``voxe build-tiny-model``.

The edit options are the job parameters of the service (``api.schemas.JobParams``) and resolve through
``voxe_core.presets.edit_config``, as the worker's do.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from voxe_core import constants as paper
from voxe_core.cli.common import (
    EXIT_INTERRUPTED, EXIT_USAGE, add_grid_output_arguments, add_model_arguments, add_view_arguments, check_device, finite_float, load_guidance,
    load_views, non_negative_int, positive_int, positive_int_at_most, remove_earlier_outputs, run_stage, said_by_option, say_smoke_test, seed, view_options_given,
    writable_folder,
)
from voxe_core.guidance.prompts import check_no_special_tokens, check_prompt_length, names_something
from voxe_core.presets import BATCH_SIZE, EDIT_SCHEDULES, PREVIEW_EVERY, SEED, TIMESTEP_SCHEDULES, edit_config

_SCENE = EDIT_SCHEDULES["scene"]
PREVIEW_NAME = re.compile(r"preview_\d{5,}\.png")
"""The names of the previews ``voxe edit`` writes under ``previews/`` (``preview_{iteration:05d}.png``)."""


def add_parsers(commands, common) -> None:
    ed = commands.add_parser("edit", parents=[common], help="text-guided editing of a grid with SDS (SPEC §2)")
    ed.add_argument("grid", type=Path, metavar="GRID", help="initial grid G_i (.safetensors)")
    ed.add_argument("--prompt", required=True, help='edit text, e.g. "a dog wearing big sunglasses"')
    ed.add_argument("--out", type=Path, required=True, metavar="DIR",
                    help="writes DIR/edited.safetensors (when the edit ends), DIR/checkpoint.safetensors, "
                         "DIR/previews/*.png (an earlier run's result, checkpoint and previews there removed first, "
                         "unless --resume continues it)")
    add_grid_output_arguments(ed)
    add_model_arguments(ed, "--model", "diffusers-layout Stable Diffusion", paper.SDS_MODEL_ID)
    ed.add_argument("--no-cuda-graphs", dest="cuda_graphs", action="store_false",
                    help="run the SDS step's UNet (and the VAE encoder, when not compiled) eagerly on CUDA (default: "
                         "replayed from CUDA graphs)")
    ed.add_argument("--no-compile-encoder", dest="compile_encoder", action="store_false",
                    help="leave the SDS step's VAE encoder uncompiled (and graphed) on CUDA (default: torch.compile, "
                         "which the first iteration waits for)")
    ed.add_argument("--fused-marcher", action="store_true",
                    help="march the renders in one Triton kernel on CUDA (voxe_core.fused_render; default: the packed "
                         "renderer, until it is measured on a GPU)")
    ed.add_argument("--iterations", type=non_negative_int, default=None,
                    help=f"default {paper.EDIT_ITERATIONS}; on a scene-backbone grid {paper.EDIT_ITERATIONS} means SPEC "
                         f"§5's {_SCENE.iterations}, as in the service's jobs (any other count runs as given)")
    ed.add_argument("--render-size", type=positive_int_at_most(paper.MAX_RENDER_SIZE), default=paper.RENDER_SIZE,
                    help=f"training render size in pixels (at most {paper.MAX_RENDER_SIZE})")
    ed.add_argument("--lr", type=finite_float, default=paper.EDIT_LR, help="Adam's learning rate")
    ed.add_argument("--regulariser", default=paper.DEFAULT_REGULARISER,
                    help="reg3d | reg3d_plus | volumetric_l1 | volumetric_l2 | image_l1 | image_l2 (image_* need --data)")
    ed.add_argument("--reg-weight", type=finite_float, default=paper.DEFAULT_REGULARISER_WEIGHT)
    ed.add_argument("--guidance-scale", type=finite_float, default=paper.DEFAULT_GUIDANCE_SCALE)
    ed.add_argument("--schedule", choices=TIMESTEP_SCHEDULES, default=TIMESTEP_SCHEDULES[0],
                    help="time-step annealing floor: paper 0.35, authors' code 0.22; a scene-backbone grid "
                         f"anneals from iteration {_SCENE.i_start} every {_SCENE.every} instead (SPEC §5)")
    ed.add_argument("--batch-size", type=positive_int, default=BATCH_SIZE, help="poses (renders) per iteration")
    ed.add_argument("--no-view-words", action="store_true", help="do not append ', front view' etc. to the prompt")
    ed.add_argument("--autocast", choices=("bf16", "fp16"), default=None, help="run the guidance under autocast")
    ed.add_argument("--seed", type=seed, default=SEED)
    ed.add_argument("--checkpoint-every", type=non_negative_int, default=250,
                    help="iterations between checkpoints (0: only at the end; Ctrl-C or SIGTERM writes one where "
                         "it stops the edit, whatever this is)")
    ed.add_argument("--resume", type=Path, default=None, metavar="PATH", help="continue from this edit checkpoint")
    ed.add_argument("--preview-every", type=non_negative_int, default=PREVIEW_EVERY,
                    help="iterations between preview PNGs (0: none)")
    ed.add_argument("--data", type=Path, default=None, metavar="DATA_DIR", help="input views for image_l1 / image_l2")
    add_view_arguments(ed, "train")
    ed.set_defaults(run=cmd_edit)

    tiny = commands.add_parser(
        "build-tiny-model", parents=[common],
        help="write a tiny random-weight Stable Diffusion (SMOKE-TEST model: plumbing only, never quality)",
    )
    tiny.add_argument("out", type=Path, metavar="DIR")
    tiny.add_argument("--seed", type=seed, default=0)
    tiny.set_defaults(run=cmd_build_tiny_model)


def job_params(args: argparse.Namespace) -> dict:
    """What ``voxe edit``'s options say, as the service's job parameters."""
    return {
        "iterations": args.iterations, "render_size": args.render_size, "guidance_scale": args.guidance_scale,
        "lr": args.lr, "regulariser": args.regulariser, "regulariser_weight": args.reg_weight,
        "timestep_schedule": args.schedule, "view_words": not args.no_view_words, "batch_size": args.batch_size,
        "autocast": args.autocast, "seed": args.seed, "preview_every": args.preview_every,
    }


def cmd_edit(args) -> int:
    from voxe_core.backbones import load_grid
    from voxe_core.edit import check_resume, edit
    from voxe_core.export import save_png
    from voxe_core.losses import IMAGE_REGULARISERS

    if not args.prompt.strip():
        raise ValueError("the edit prompt is empty")
    if not names_something(args.prompt):  # (as the service refuses it; it had run a whole edit towards "---")
        raise ValueError(f"the edit prompt {args.prompt!r} has no words: nothing in it names anything (a word, number "
                         "or symbol such as an emoji does; punctuation alone does not)")
    check_no_special_tokens(args.prompt, "the edit prompt")
    check_prompt_length(args.prompt, not args.no_view_words)  # (had been said after the model's load, a download maybe)
    check_device(args)  # before the grid is read: a device this machine lacks had been said only after it
    grid = load_grid(args.grid)
    with said_by_option({"lr": "--lr", "regulariser_weight": "--reg-weight", "guidance_scale": "--guidance-scale",
                         "render_size": "--render-size", "batch_size": "--batch-size"}):
        config = edit_config(job_params(args), grid.kind, args.checkpoint_every)  # (before the model loads)
    config.render.fused = args.fused_marcher
    if config.regulariser in IMAGE_REGULARISERS and args.data is None:
        raise ValueError(f"--regulariser {config.regulariser} compares renders with the input views: pass --data DATA_DIR")
    if args.data is not None and config.regulariser not in IMAGE_REGULARISERS:  # (it had been taken and ignored)
        raise ValueError(f"--data gives the input views of --regulariser {' / '.join(IMAGE_REGULARISERS)}; "
                         f"{config.regulariser} reads none")
    if args.data is None and (dataset_only := view_options_given(args)):  # (as had these)
        raise ValueError(f"{', '.join(dataset_only)} set how --data's images are read; without --data none are")
    model = args.model or paper.SDS_MODEL_ID
    writable_folder(args.out)  # (an --out that is a file or not writable had been said after the model loaded)
    views = None
    if args.data is not None:
        scene = load_views(args)
        views = (scene.images, grid.dataset_cameras(scene.cameras))
    # A --resume that is no edit checkpoint (missing, a grid), or another job's (grid, prompt, model, recipe, input
    # views), had waited for the model's load.
    if args.resume is not None:
        check_resume(args.resume, grid, args.prompt, config, model, views)
    smoke_test = say_smoke_test(args, model)
    guidance = load_guidance(args, model, cuda_graphs=None if args.cuda_graphs else False,
                             compile_encoder=None if args.compile_encoder else False)
    if guidance is None:
        return EXIT_USAGE
    checkpoint = args.out / "checkpoint.safetensors"
    if args.resume is None:  # a fresh edit: an earlier run's previews (other iterations, another prompt) had stayed
        remove_earlier_outputs(args.out / "previews", PREVIEW_NAME)  # beside its own; a resumed one keeps its own
        # and its result and checkpoint, which a run failing or cancelled had left beside this one's as if this run's
        # (the cancel hint naming that checkpoint to resume); the grid being edited stays: a user's input
        for earlier in (args.out / "edited.safetensors", checkpoint):
            if earlier.is_file() and not earlier.samefile(args.grid):
                earlier.unlink()

    def on_preview(iteration: int, image) -> None:
        save_png(args.out / "previews" / f"preview_{iteration:05d}.png", image)

    print(
        f"editing {args.grid} ({'x'.join(map(str, grid.resolution))}, {grid.kind} backbone) towards {args.prompt!r} "
        f"with {model} on {guidance.device}: {config.iterations} iterations, {config.render_size} px renders, "
        f"{config.regulariser} x {config.regulariser_weight:g}",
        file=sys.stderr,
    )
    edited = run_stage(
        lambda cb: edit(grid, args.prompt, guidance, config, cb, checkpoint, args.resume, views, on_preview,
                        device=args.device),
        "edit", "it", config.iterations, args.quiet,
    )
    if edited is None:
        hint = f"; resume with --resume {checkpoint}" if checkpoint.is_file() else " before its first step"
        print(f"voxe: edit cancelled{hint}", file=sys.stderr)
        return EXIT_INTERRUPTED
    edited.save(args.out / "edited.safetensors", dense=args.dense,
                notes={"smoke_test": smoke_test} if smoke_test else None)
    print(f"wrote {args.out / 'edited.safetensors'} and {checkpoint}")
    return 0


def cmd_build_tiny_model(args) -> int:
    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    path = build_tiny_stable_diffusion(writable_folder(args.out), seed=args.seed)
    print(
        f"wrote {path}: SMOKE-TEST MODEL with RANDOM WEIGHTS (seed {args.seed}), for plumbing only; "
        f"edits made with it are noise and say nothing about quality. Use it as `voxe edit ... --model {path}`."
    )
    return 0
