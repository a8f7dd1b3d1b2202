"""``voxe evaluate``: the paper's metrics on a 360° ring (SPEC §4): CLIP_sim, CLIP_dir, FID, PSNR / SSIM outside the mask."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from voxe_core.cli.common import (
    EXIT_INTERRUPTED, EXIT_USAGE, add_model_arguments, add_view_arguments, check_device, finite_float, load_views,
    move_staged, remove_earlier_outputs, run_stage, said_by_option, staging_folder, view_options_given, whole_number,
    writable_file, writable_folder, write_json,
)
from voxe_core.constants import (
    CLIP_MODEL_ID, EVALUATION_RING_ELEVATION, EVALUATION_RING_SIZE, EVALUATION_RING_VIEWS, INCEPTION_FILE,
    MAX_EVALUATION_RING_VIEWS, MAX_RENDER_SIZE,
)


def add_parsers(commands, common) -> None:
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
                    help="writes the ring renders ring/<name>/NNN.png, then evaluation.json and evaluation.md "
                         "(replacing those of an earlier run there; evaluation.json there: the set is whole)")
    add_model_arguments(ev, "--clip-model", "transformers CLIPModel", CLIP_MODEL_ID)
    ev.add_argument("--inception", type=Path, default=None, metavar="PATH",
                    help=f"TorchScript Inception file ({INCEPTION_FILE}) or its folder; without it no FID")
    ev.add_argument("--data", type=Path, default=None, metavar="DATA_DIR",
                    help="input views for FID_input (with --inception)")
    add_view_arguments(ev, "train")
    ev.add_argument("--views", type=whole_number, default=EVALUATION_RING_VIEWS,
                    help=f"ring views, at most {MAX_EVALUATION_RING_VIEWS} (default {EVALUATION_RING_VIEWS}: the paper's)")
    ev.add_argument("--elevation", type=finite_float, default=EVALUATION_RING_ELEVATION,
                    help=f"ring elevation in degrees (default {EVALUATION_RING_ELEVATION:g})")
    ev.add_argument("--size", type=whole_number, default=EVALUATION_RING_SIZE,
                    help=f"ring render size in pixels, at most {MAX_RENDER_SIZE} (default {EVALUATION_RING_SIZE})")
    ev.set_defaults(run=cmd_evaluate)


def cmd_evaluate(args) -> int:
    from voxe_core.backbones import load_grid
    from voxe_core.evaluate import (
        ClipScorer, EditSample, EvaluateConfig, InceptionFeatures, check_source_text_length, evaluate,
        evaluation_steps, format_table, smoke_test_roles,
    )
    from voxe_core.export import save_png
    from voxe_core.guidance.prompts import check_no_special_tokens, check_prompt_length
    from voxe_core.guidance.loading import ModelNotAvailableError
    from voxe_core.refine.storage import load_mask

    with said_by_option({"views": "--views", "elevation": "--elevation", "size": "--size"}):  # (EvaluateConfig's rule)
        config = EvaluateConfig(views=args.views, elevation=args.elevation, size=args.size)
    for values in args.edit:
        if len(values) not in (2, 3):
            raise ValueError(f"--edit takes EDITED_GRID PROMPT [MASK], got {len(values)} values: {values}")
        check_no_special_tokens(values[1], f"the prompt of {values[0]}")
        check_prompt_length(values[1], view_words=False)  # texts CLIP cannot read: before any grid or model is read
    check_no_special_tokens(args.object, "--object")
    check_source_text_length(args.object)
    if args.data is None and (dataset_only := view_options_given(args)):
        raise ValueError(f"{', '.join(dataset_only)} set how --data's images are read (for FID_input); "
                         "without --data none are")
    if args.data is not None and args.inception is None:  # its images had been read and compared with nothing
        raise ValueError("--data gives the input images FID_input compares with; without --inception no FID is "
                         "computed")
    device = check_device(args)
    writable_folder(args.out)
    initial = load_grid(args.initial)
    edits = []
    for k, (grid_path, prompt, *mask_path) in enumerate(args.edit):
        mask = load_mask(Path(mask_path[0]), initial.resolution) if mask_path else None
        edits.append(EditSample(f"edit{k:02d}", prompt, load_grid(Path(grid_path)), mask))
    # Every output path checked now: a folder in the way had failed the move, after the whole evaluation
    for path in (args.out / "evaluation.json", args.out / "evaluation.md",
                 *(args.out / "ring" / name / f"{i:03d}.png"
                   for name in ("initial", *(e.name for e in edits)) for i in range(config.views))):
        writable_file(path)
    input_images = None
    if args.data is not None:
        input_images = load_views(args).images
    model = args.clip_model or CLIP_MODEL_ID
    try:
        clip = ClipScorer.from_pretrained(model, device=args.device, local_files_only=True if args.offline else None)
        fid = InceptionFeatures.load(args.inception, device=args.device) if args.inception is not None else None
    except ModelNotAvailableError as exc:
        print(f"voxe evaluate: model not available: {exc}", file=sys.stderr)
        return EXIT_USAGE
    out = args.out
    # Each ring view saved as it is scored (all had been held to the end)
    with staging_folder(out, "evaluate") as staging:
        result = run_stage(
            lambda cb: evaluate(initial, edits, args.object, clip, fid, input_images, config, cb, device=device,
                                on_ring=lambda name, i, view: save_png(
                                    staging / "ring" / (name or "initial") / f"{i:03d}.png", view)),
            "evaluate", "view", evaluation_steps(edits, config, fid, input_images), args.quiet,
        )
        if result is None:
            print("voxe: evaluation cancelled, nothing written", file=sys.stderr)
            return EXIT_INTERRUPTED
        smoke_test = smoke_test_roles(clip, fid)
        summary = {**result.summary(), "object": args.object, "clip_model": model,
                   "inception": str(args.inception) if args.inception else None, "smoke_test": smoke_test,
                   "ring": {"views": config.views, "elevation": config.elevation, "size": config.size},
                   "edits": [{"name": e.name, "grid": str(g[0]), "mask": g[2] if len(g) > 2 else None}
                             for e, g in zip(edits, args.edit)]}
        table = format_table(result.rows, extra_columns=("name",), smoke_test=smoke_test)
        # Written whole into the staging first: a full disk there leaves --out as it was (it had left the
        # earlier run's summaries torn, then none beside this run's ring renders)
        write_json(staging / "evaluation.json", summary)
        (staging / "evaluation.md").write_text(table, encoding="utf-8")  # (its "–", its prompts: whatever the locale)
        move_staged(staging, out, ("evaluation.md", "evaluation.json"), lambda: clear_ring_renders(out / "ring"))
    print(table, end="")
    return 0


RING_SET_NAME = re.compile(r"initial|edit\d{2,}")  # the ring/<name>/ folders this command writes
RING_FRAME_NAME = re.compile(r"\d+\.png")  # and the frames in them


def clear_ring_renders(ring: Path) -> None:
    """Delete the ring renders an earlier ``voxe evaluate`` wrote under ``ring`` (ring/initial/, ring/editNN/ NNN.png).

    A re-run into the same --out with fewer views or edits would otherwise leave frames its
    evaluation.json does not describe. Only files of the names this command writes go; a folder is
    removed once nothing else is left in it.
    """
    if not ring.is_dir():
        return
    for folder in ring.iterdir():
        if not (folder.is_dir() and RING_SET_NAME.fullmatch(folder.name)):
            continue
        remove_earlier_outputs(folder, RING_FRAME_NAME)
        if not any(folder.iterdir()):
            folder.rmdir()
