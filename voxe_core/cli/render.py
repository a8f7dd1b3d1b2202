"""``voxe render`` (PNG views: a dataset's cameras, with PSNR / SSIM, or a ring) and ``voxe turntable`` (MP4 / GIF).

Ring and turntable defaults are the export stage's (``voxe_core.presets.ExportConfig``). Rings and turntables
orbit the grid's ``orbit_centre()`` (a capture's object), or another grid's with ``--centre-of`` (an edit's
initial grid, as the service's renders do).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from voxe_core.cli.common import (
    EXIT_INTERRUPTED, add_device_argument, add_view_arguments, check_device, finite_float, load_views, positive_int,
    run_stage, say_grid_notes, staging_folder, view_options_given, writable_file, writable_folder, write_json,
)
from voxe_core.constants import VIDEO_SUFFIXES
from voxe_core.files import head_that_fits, replacing
from voxe_core.presets import ExportConfig


METRICS_FILE = "metrics.json"
MANIFEST_FILE = "render.json"  # the files a run wrote into --out: the only ones a later run into it removes


def add_parsers(commands, common) -> None:
    ren = commands.add_parser("render", parents=[common], help="render PNG views of a grid (dataset cameras or a ring)")
    ren.add_argument("grid", type=Path, metavar="GRID")
    source = ren.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, metavar="DATA_DIR", help="render this dataset split's cameras")
    source.add_argument("--ring", type=positive_int, metavar="N", help="render N views on a 360° ring instead")
    add_view_arguments(ren, "test")
    ren.add_argument("--size", type=positive_int, default=None,
                     help=f"ring view size in pixels (default {ExportConfig.view_size})")
    ren.add_argument("--elevation", type=finite_float, default=None,
                     help=f"ring elevation in degrees (default {ExportConfig.elevation:g})")
    add_centre_argument(ren)
    ren.add_argument("--out", type=Path, required=True, metavar="DIR",
                     help=f"folder of the views (and metrics.json with --data); the files an earlier voxe render "
                          f"listed in its {MANIFEST_FILE} there are replaced, others stay (a run that would write over "
                          f"one is refused)")
    add_device_argument(ren)
    ren.set_defaults(run=cmd_render)

    tt = commands.add_parser("turntable", parents=[common], help="render a 360° turntable video (.mp4 or .gif)")
    tt.add_argument("grid", type=Path, metavar="GRID")
    tt.add_argument("--out", type=Path, required=True, help="video file, .mp4 or .gif")
    tt.add_argument("--frames", type=positive_int, default=ExportConfig.turntable_frames)
    tt.add_argument("--size", type=positive_int, default=ExportConfig.turntable_size)
    tt.add_argument("--elevation", type=finite_float, default=ExportConfig.elevation)
    tt.add_argument("--fps", type=finite_float, default=ExportConfig.fps)
    add_centre_argument(tt)
    add_device_argument(tt)
    tt.set_defaults(run=cmd_turntable)


def add_centre_argument(parser) -> None:
    parser.add_argument("--centre-of", type=Path, default=None, metavar="GRID",
                        help="orbit this grid's orbit centre (e.g. the initial grid of an edit, as the service does) "
                             "instead of the rendered grid's own")


def orbit_centre(args, grid):
    """The point the ring or turntable looks at: ``--centre-of``'s grid's orbit centre, else ``grid``'s."""
    from voxe_core.backbones import load_grid

    return (load_grid(args.centre_of) if args.centre_of is not None else grid).orbit_centre()


def check_elevation(elevation: float) -> None:
    """``--elevation`` past a pole, refused by the option's name before the grid is read: turntable_cameras had
    refused it after, as "a turntable's elevation must lie ...", which ``voxe render --ring`` makes none of."""
    if not -90.0 <= elevation <= 90.0:
        raise ValueError(f"--elevation must lie between -90 and 90 degrees, got {elevation:g}")


def check_renderable(grid, path: Path) -> None:
    """A grid with NaN or infinite features (a damaged file) is refused before any view is made: its views had been
    written with black where the NaN lies, and ``--data``'s scores as "PSNR nan dB", a metrics.json no strict JSON
    reader takes."""
    from voxe_core.reconstruct import check_finite_grid

    check_finite_grid(grid, "the renderer", what=f"the grid {path}", where="every view that sees them")


def cmd_render(args) -> int:
    from voxe_core.backbones import load_grid
    from voxe_core.export import turntable_cameras

    device = check_device(args)
    ring_only = [flag for flag, value in (("--size", args.size), ("--elevation", args.elevation),
                                          ("--centre-of", args.centre_of)) if value is not None]
    if args.data is not None and ring_only:  # (they had been accepted and ignored)
        raise ValueError(f"{', '.join(ring_only)} set the --ring views; --data renders the dataset's own cameras")
    if args.ring is not None and (dataset_only := view_options_given(args)):  # (as were these)
        raise ValueError(f"{', '.join(dataset_only)} set how --data's images are read; --ring reads no dataset "
                         "(--size sets its views' size)")
    if args.elevation is not None:
        check_elevation(args.elevation)
    writable_folder(args.out)
    grid = load_grid(args.grid)
    check_renderable(grid, args.grid)
    notes = say_grid_notes(args, args.grid)
    scene = None
    if args.data is not None:
        scene = load_views(args)
        cameras = grid.dataset_cameras(scene.cameras)
        # (cut to fit a name's 255 bytes: an image named with them had failed "File name too long")
        names = [head_that_fits(f"{i:03d}_{Path(name).stem}", ".png", name) + ".png"
                 for i, name in enumerate(scene.names)]
    else:
        elevation = ExportConfig.elevation if args.elevation is None else args.elevation
        size = ExportConfig.view_size if args.size is None else args.size
        cameras = turntable_cameras(args.ring, elevation, size, centre=orbit_centre(args, grid))
        names = [f"{i:03d}.png" for i in range(args.ring)]
    outputs = names + ([METRICS_FILE] if scene is not None else [])
    for name in outputs:  # (a folder in the way had failed the move, after the whole render)
        writable_file(args.out / name)
    earlier = _refuse_files_not_its_own(args.out, outputs)
    # Each view saved as it is rendered (all had been held first)
    with staging_folder(args.out, "render") as staging:
        scores = run_stage(lambda cb: _render_into(staging, grid, cameras, names, scene, cb, device), "render",
                           "view", len(cameras), args.quiet)
        if scores is None:
            print("voxe: rendering cancelled, nothing written", file=sys.stderr)
            return EXIT_INTERRUPTED
        _replace_manifest(args.out, earlier, outputs, notes)
        for name in names:
            os.replace(staging / name, args.out / name)
    print(f"wrote {len(names)} views to {args.out}")
    if scene is not None:
        _report_metrics(*scores, scene, names, args.out)
    return 0


def _render_into(folder: Path, grid, cameras, names: list[str], scene, callbacks, device):
    """Render each camera and save it as ``folder / names[i]`` before the next is rendered (one view alive, not
    the ring). With ``scene``, each view is scored against its image as it comes: (PSNR per view, SSIM per view or
    None when the views are under SSIM's window); without, (None, None)."""
    import torch

    from voxe_core.export import iter_views, save_png
    from voxe_core.metrics import SSIM_WINDOW, psnr, ssim

    scored = scene is not None
    with_ssim = scored and min(cameras.height, cameras.width) >= SSIM_WINDOW
    psnr_values, ssim_values = [], []
    for i, frame in enumerate(iter_views(grid, cameras, callbacks=callbacks, device=device)):
        save_png(folder / names[i], frame)
        if scored:  # one view at a time: the values of the whole set, but SSIM's float64 buffers are one view's
            psnr_values.append(psnr(frame[None], scene.images[i : i + 1]))
            if with_ssim:
                ssim_values.append(ssim(frame[None], scene.images[i : i + 1]))
    return (torch.cat(psnr_values) if scored else None), (torch.cat(ssim_values) if with_ssim else None)


def _earlier_files(out_dir: Path) -> list | None:
    """The files an earlier run listed in ``out_dir``'s manifest; None where there is none of this command's (no
    file, or a file of the user's own by that name)."""
    try:
        listed = json.loads((out_dir / MANIFEST_FILE).read_text(encoding="utf-8"))
        return list(listed["files"]) if listed.get("written_by") == "voxe render" else None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _refuse_files_not_its_own(out_dir: Path, files: list[str]) -> list | None:
    """ValueError naming a file this run would write over that no earlier run wrote (a user's own render.json,
    metrics.json or 000.png in --out), before rendering: they had been overwritten, where --out's help says files
    no run listed stay. Else the files the earlier run listed (``_earlier_files``), for ``_replace_manifest``."""
    earlier = _earlier_files(out_dir)
    if earlier is None and os.path.lexists(out_dir / MANIFEST_FILE):
        raise ValueError(f"--out: {out_dir / MANIFEST_FILE} is not a manifest voxe render wrote, and a run writes "
                         "its own there; move that file or choose another --out")
    for name in files:
        if os.path.lexists(out_dir / name) and name not in (earlier or []):
            raise ValueError(f"--out: {out_dir / name} was not written by an earlier voxe render (its "
                             f"{MANIFEST_FILE} does not list it), and this run would write over it; move that file "
                             "or choose another --out")
    return earlier


def _replace_manifest(out_dir: Path, earlier: list | None, files: list[str], notes: dict) -> None:
    """Remove the files an earlier run listed in ``out_dir``'s manifest (``earlier``: as read when --out was checked,
    before the render; read again after it, the files of a manifest written meanwhile had gone, unchecked), then list
    ``files``, this run's (before it writes them, so an interrupted run's are listed too). A re-run writing fewer views
    had left the earlier run's beside them; files no run listed (the user's own, whatever their names) stay. ``notes``:
    the grid's (a smoke-test edit's), carried."""
    manifest = out_dir / MANIFEST_FILE
    for name in earlier or []:  # none, or not this command's: none removed
        if isinstance(name, str) and Path(name).name == name and (out_dir / name).is_file():  # (only its own names)
            (out_dir / name).unlink()
    with replacing(manifest) as partial:
        write_json(partial, {"written_by": "voxe render", "files": files, **notes})


def _report_metrics(psnr_values, ssim_values, scene, names, out_dir: Path) -> None:
    """Print and write (metrics.json) the views' PSNR and SSIM (None: views under SSIM's window)."""
    from voxe_core.metrics import PSNR_CAP_DB, SSIM_WINDOW

    per_view_psnr = psnr_values.clamp(max=PSNR_CAP_DB).tolist()  # a view identical to its image: inf
    per_view_ssim = ssim_values.tolist() if ssim_values is not None else None
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
    with replacing(out_dir / METRICS_FILE) as partial:  # whole or not at all: a full disk had left it torn
        write_json(partial, summary)


def cmd_turntable(args) -> int:
    if args.out.suffix.lower() not in VIDEO_SUFFIXES:  # (check_video_output's rule, said naming the option, before
        raise ValueError(f"--out: unsupported video suffix {args.out.suffix!r} for {args.out}; use one of "  # torch)
                         f"{', '.join(VIDEO_SUFFIXES)}")
    from voxe_core.backbones import load_grid
    from voxe_core.export import (
        GIF_MIN_DELAY_CS, check_video_output, check_video_size, gif_timeline, iter_views, turntable_cameras,
        write_video,
    )

    check_video_output(args.out, args.fps)  # fail before rendering, not after
    check_video_size(args.out, args.size, args.size)
    check_elevation(args.elevation)
    device = check_device(args)
    writable_file(args.out)  # (a folder not writable had failed after the render, imageio's traceback beside it)
    grid = load_grid(args.grid)
    check_renderable(grid, args.grid)
    say_grid_notes(args, args.grid)  # (a video carries no note: said on stderr alone)
    cameras = turntable_cameras(args.frames, args.elevation, args.size, centre=orbit_centre(args, grid))
    written = run_stage(  # each frame encoded as it is rendered (a long turntable had been held whole first)
        lambda cb: write_video(args.out, iter_views(grid, cameras, callbacks=cb, device=device), args.fps,
                               n_frames=len(cameras)),
        "turntable", "frame", len(cameras), args.quiet,
    )
    if written is None:
        print("voxe: turntable cancelled, nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    shown = len(gif_timeline(args.frames, args.fps)[0]) if args.out.suffix.lower() == ".gif" else args.frames
    kept = "" if shown == args.frames else (f" ({shown} of them shown: a GIF plays at most "
                                            f"{100 // GIF_MIN_DELAY_CS} fps)")  # (it had said all were in it)
    print(f"wrote {args.out}: {args.frames} frames of {args.size}x{args.size}{kept}")
    return 0
