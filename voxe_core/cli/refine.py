"""``voxe refine``: localise an edit (SPEC §3): 3D cross-attention grids, graph-cut mask, merge with G_i.

The refinement options are the job parameters' ``refine`` and resolve through ``voxe_core.presets.refine_config``.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys
import warnings
from pathlib import Path

from voxe_core import constants as paper
from voxe_core.cli.common import (
    EXIT_INTERRUPTED, EXIT_USAGE, add_grid_output_arguments, add_model_arguments, check_device, finite_float,
    load_guidance, move_staged, non_negative_int, positive_int, positive_int_at_most, remove_earlier_outputs, run_stage, said_by_option, say_grid_notes,
    say_smoke_test, seed, staging_folder,
    writable_file, writable_folder, write_json,
)
from voxe_core.guidance.prompts import (check_edit_words_name_an_edit, check_edit_words_read,
                                        check_no_special_tokens, check_prompt_length, prompt_text)
from voxe_core.presets import LIFT_START, LIFT_STARTS, SEED, refine_config


RING_PREVIEWS = ("attention_edit", "attention_object", "probability_edit", "mask", "refined")
"""The previews rendered on the turntable ring, ``--preview-views`` frames each."""
MAP_PREVIEWS = ("map2d_edit", "map2d_object")
"""The 2D attention maps shown, one frame per view up to ``--preview-views``."""
PREVIEW_FRAME = re.compile(rf"({'|'.join(RING_PREVIEWS + MAP_PREVIEWS)})_\d+\.png")
"""The names of the frames ``voxe refine`` writes under ``renders/``."""
OUTPUT_FILES = ("refined.safetensors", "mask.safetensors", "probabilities.safetensors", "refine.json")
"""Its other outputs (refine.json, which describes them, moved into --out last)."""


def add_parsers(commands, common) -> None:
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
                     help="writes refined.safetensors, mask.safetensors, probabilities.safetensors, renders/*.png and, last, "
                          "refine.json: where it is, the set is whole")
    add_grid_output_arguments(ref)
    add_model_arguments(ref, "--model", "diffusers-layout Stable Diffusion for the cross-attention maps",
                        paper.ATTENTION_MODEL_ID)
    ref.add_argument("--iterations", type=non_negative_int, default=paper.SERVICE_REFINE_ITERATIONS,
                     help=f"attention-grid fitting steps after the back-projection start (the paper: {paper.REFINE_ITERATIONS})")
    ref.add_argument("--lift-start", choices=LIFT_STARTS, default=LIFT_START,
                     help="start of the attention grids: the maps' weighted back-projection, or 0 everywhere (the paper's fit)")
    ref.add_argument("--smoothing-sigma", type=finite_float, default=paper.SERVICE_SMOOTHING_SIGMA,
                     help="Gaussian std (attention cells) of the 2D maps' smoothing (ours before issue 18: 1.0)")
    ref.add_argument("--lr", type=finite_float, default=paper.REFINE_LR, help="Adam's learning rate on the attention grids")
    ref.add_argument("--tv-weight", type=finite_float, default=paper.REFINE_TV_WEIGHT, help="total variation weight of the attention grids")
    ref.add_argument("--render-size", type=positive_int_at_most(paper.MAX_RENDER_SIZE), default=paper.RENDER_SIZE,
                     help=f"render / attention-map size in pixels (at most {paper.MAX_RENDER_SIZE})")
    ref.add_argument("--views", type=positive_int_at_most(paper.MAX_REFINE_VIEWS), default=paper.REFINE_VIEWS,
                     help=f"random upper-hemisphere views for the 2D maps (at most {paper.MAX_REFINE_VIEWS})")
    ref.add_argument("--rays", type=positive_int_at_most(paper.MAX_RAYS_PER_STEP), default=paper.REFINE_RAYS_PER_STEP,
                     help=f"rays per attention-grid step (at most {paper.MAX_RAYS_PER_STEP})")
    ref.add_argument("--edit-seeds", type=non_negative_int, default=paper.EDIT_SEEDS,
                     help="voxels tied to the 'edit' terminal: every voxel with P_edit >= 0.992 max P_edit, topped "
                          "up to this many by the highest P_edit, then only those more likely edit than object "
                          "(the authors' code)")
    ref.add_argument("--object-seeds", type=positive_int, default=paper.SERVICE_OBJECT_SEEDS,
                     help="up to this many voxels tied to the 'object' terminal, drawn at random (--seed) among "
                          f"P_object > P_edit + {paper.SERVICE_OBJECT_SEED_MARGIN} (the authors' code: among "
                          f"P_object > P_edit; the paper's text: the top {paper.OBJECT_SEEDS} by P_object); at least "
                          "1, as the cut has no unary term: without object seeds it keeps every voxel joined to an "
                          "edit seed")
    ref.add_argument("--sigma", type=finite_float, default=paper.CUT_SIGMA, help="colour scale of the graph cut's pairwise weights")
    ref.add_argument("--smoothness", type=finite_float, default=paper.CUT_SMOOTHNESS, help="graph-cut smoothness weight λ")
    ref.add_argument("--no-view-words", action="store_true",
                     help="the edit ran with voxe edit --no-view-words: its attention prompt has none either (as "
                          "the service's view_words does for both stages)")
    ref.add_argument("--preview-views", type=non_negative_int, default=4, help="ring views rendered as PNGs (0: none)")
    ref.add_argument("--seed", type=seed, default=SEED)
    ref.set_defaults(run=cmd_refine)


def job_params(args: argparse.Namespace) -> dict:
    """What ``voxe refine``'s options say, as the service's job parameters."""
    return {"seed": args.seed, "view_words": not args.no_view_words, "refine": {
        "iterations": args.iterations, "lift_start": args.lift_start, "smoothing_sigma": args.smoothing_sigma,
        "lr": args.lr, "tv_weight": args.tv_weight, "render_size": args.render_size,
        "views": args.views, "rays_per_step": args.rays, "edit_seeds": args.edit_seeds,
        "object_seeds": args.object_seeds, "sigma": args.sigma, "smoothness": args.smoothness,
    }}


def cmd_refine(args) -> int:
    from voxe_core.backbones import load_grid
    from voxe_core.refine.pipeline import check_compatible, refine

    words = [w.strip() for w in args.edit_words.split(",") if w.strip()]
    if not words:
        raise ValueError("--edit-words names no word")
    # As the refinement will read them, before the grids are read and the model loads (a download, maybe): a word
    # not in the prompt, or a prompt longer than the text encoder reads, had been said only after that.
    view_words = not args.no_view_words
    check_no_special_tokens(args.prompt, "the edit prompt")
    check_prompt_length(args.prompt, view_words)
    check_edit_words_name_an_edit(prompt_text(args.prompt), words)
    check_edit_words_read(args.prompt, words, view_words)
    check_device(args)
    writable_folder(args.out)
    for name in OUTPUT_FILES:  # (a folder in the way had failed the move, after the whole refinement)
        writable_file(args.out / name)
    writable_folder(args.out / "renders")
    model = args.model or paper.ATTENTION_MODEL_ID
    with said_by_option({"smoothing_sigma": "--smoothing-sigma", "lr": "--lr", "tv_weight": "--tv-weight",
                         "sigma": "--sigma", "smoothness": "--smoothness", "render_size": "--render-size"}):
        config = refine_config(job_params(args), model)
    for name in _preview_frames(args.preview_views, config.views):  # (a folder of a frame's name: the same)
        writable_file(args.out / "renders" / name)
    initial, edited = load_grid(args.initial), load_grid(args.edited)
    check_compatible(initial, edited)
    out = args.out
    with staging_folder(out, "refine") as staging:  # (a run that failed part way had left a mix of two runs' files)
        # The model's note and the edited grid's (a smoke-test edit's: the refined grid is made of it), both kept
        smoke_test = "; ".join(note for note in (say_smoke_test(args, model),
                                                 say_grid_notes(args, args.edited).get("smoke_test")) if note) or None
        guidance = load_guidance(args, model)
        if guidance is None:
            return EXIT_USAGE
        print(f"refining {args.edited} against {args.initial} for {words} of {args.prompt!r} with {model} on "
              f"{guidance.device}: {config.views} views of {config.render_size} px, {config.iterations} iterations",
              file=sys.stderr)
        with warnings.catch_warnings():  # seed shortfalls are reported below from the result
            warnings.filterwarnings("ignore", message=r"only \d+ of \d+ (edit|object) seeds")
            result = run_stage(
                lambda cb: refine(initial, edited, args.prompt, words, guidance, config, cb, device=args.device),
                "refine", "it", None, args.quiet,
            )
        if result is None:
            print("voxe: refinement cancelled, nothing written", file=sys.stderr)
            return EXIT_INTERRUPTED
        stats = dataclasses.asdict(result.stats)
        _write_outputs(staging, result, words, model, config, stats, initial, edited, args, smoke_test)
        _move_outputs(staging, out)
    for note in result.stats.notes:
        print(f"voxe refine: note: {note}", file=sys.stderr)
    if (warning := result.stats.uniform_label()) is not None:  # (as the service's job says it)
        print(f"voxe refine: warning: {warning}", file=sys.stderr)
    print(f"wrote {out}: {stats['edit_voxels']} of {stats['nodes']} occupied voxels take the edit "
          f"({stats['edit_seeds']} edit / {stats['object_seeds']} object seeds)")
    return 0


def _write_outputs(folder: Path, result, words: list[str], model: str, config, stats: dict, initial, edited,
                   args, smoke_test: str | None) -> None:
    """Write the refinement's files into ``folder`` (the staging): the grids, the previews (each view saved as it
    is rendered: all five sets had been held first), then refine.json (``smoke_test``: its note, where the model was
    the random-weight tiny one or the edited grid carried one; the refined grid's header too)."""
    import torch

    from voxe_core.export import save_png, turntable_cameras
    from voxe_core.refine.renders import iter_attention_views, iter_mask_overlays
    from voxe_core.refine.storage import save_mask, save_probabilities
    from voxe_core.tensorio import config_recipe

    result.refined_grid.save(folder / "refined.safetensors", dense=args.dense,
                             notes={"smoke_test": smoke_test} if smoke_test else None)
    save_mask(folder / "mask.safetensors", result.mask, meta={"prompt": result.info["prompt"], "edit_words": words})
    save_probabilities(folder / "probabilities.safetensors", result.edit_probability, result.object_probability,
                       result.nodes)
    renders = folder / "renders"
    renders.mkdir()
    if args.preview_views:
        cameras = turntable_cameras(args.preview_views, 30.0, config.render_size, centre=initial.orbit_centre())
        groups = dict(zip(RING_PREVIEWS, (
            iter_attention_views(edited, result.edit_field, cameras),
            iter_attention_views(edited, result.object_field, cameras),
            iter_attention_views(edited, result.edit_probability, cameras),
            iter_mask_overlays(edited, result.mask, cameras),
            iter_mask_overlays(result.refined_grid, torch.zeros_like(result.mask), cameras, strength=0.0),
        )))
        for name, frames in groups.items():
            for i, frame in enumerate(frames):
                save_png(renders / _frame_name(name, i), frame)
    for i in range(min(args.preview_views, len(result.edit_maps))):
        for name, maps in zip(MAP_PREVIEWS, (result.edit_maps, result.object_maps)):
            save_png(renders / _frame_name(name, i), maps[i].cpu()[..., None].expand(-1, -1, 3))
    summary = {"prompt": result.info["prompt"], "edit_words": words, "model": model,
               "settings": config_recipe(config, ()),  # every one the run used (--sigma, --lift-start, ... had gone unsaid)
               "graph_cut": stats, "masked_voxels": int(result.mask.sum())}
    if smoke_test:
        summary["smoke_test"] = smoke_test
    write_json(folder / "refine.json", summary)


def _frame_name(preview: str, view: int) -> str:
    return f"{preview}_{view:02d}.png"


def _preview_frames(preview_views: int, views: int) -> list[str]:
    """The names of the frames a run writes under ``renders/``: each ring preview's, and a 2D map per view shown."""
    return ([_frame_name(name, i) for name in RING_PREVIEWS for i in range(preview_views)]
            + [_frame_name(name, i) for name in MAP_PREVIEWS for i in range(min(preview_views, views))])


def _move_outputs(staging: Path, out: Path) -> None:
    """Move the whole set from ``staging`` into ``out`` (:func:`move_staged`: refine.json, which describes it, last),
    the earlier previews removed first (fewer --preview-views had left another run's frames beside)."""
    move_staged(staging, out, ("refine.json",), lambda: remove_earlier_outputs(out / "renders", PREVIEW_FRAME))
