"""The paper's text against the authors' code (issue 18 item 5): 2D-map and fit variants on the localisation ground truth.

bench/localisation.py's scenes (mesh-voxelised, 96³; the maps of ``--views`` 32 of the hemisphere views at 100 px)
and map model; the cut is the default (``SERVICE_CUT``)
everywhere, so the differences are the maps' or the fit's. ``--part maps``: per variant the lattice maps are
post-processed under its ``RefineConfig`` and lifted by the back-projection (0 steps):

* ``authors_code``: ``AUTHORS_CODE_MAPS``: 3×3 σ 0.5 smoothing before and after upsampling, raw maps;
* ``paper_text``: ``PAPER_TEXT_MAPS``: σ 1 Gaussian (radius 3σ) once, min-max normalised maps;
* ``code_but_<field>``: the code's maps with that one choice the text's (``smoothing``: σ 0.5 with the whole
  Gaussian once, this project's setting before this bench; ``map_scale``: min-max);
* ``raw_edit_x0.3`` / ``raw_object_x0.3``: raw maps with the edit (object) lattice scaled by 0.3 — real
  cross-attention gives the two maps different scales, which raw maps keep and min-max removes.

Max vs mean over the edit tokens, the view word in the prompt and the end-of-text token among the object tokens
change nothing here (one synthetic edit map, no prompt): the bench cannot tell them apart.

``--part fit``: maps as the default; the back-projection start then ``--steps`` Adam steps under each of
``fit_views`` × ``fit_pixels``. "fresh" draws a random view of the 100 Blender views (at the same size) per step with fresh map
noise (the diffusion pass's stand-in: a new seed of the level's degradation) and fits all its pixels.

    python bench/localisation_maps_fit.py --part maps    # ~10 min
    python bench/localisation_maps_fit.py --part fit     # ~10 min (moderate maps)
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings
from pathlib import Path

import torch

from localisation import LEVELS, fewer_views, lattice_maps, parse_with_common_arguments, ring_psnrs, scene_maps, write_results
from localisation_scenes import SCENES, build_scene
from localisation_variants import plot
from segmentation import iou
from voxe_core.refine.config import AUTHORS_CODE_MAPS, PAPER_TEXT_MAPS, RefineConfig
from voxe_core.refine.cut import graph_cut_detailed, node_mask
from voxe_core.refine.lifting import fit_attention_grids
from voxe_core.refine.maps import postprocess_maps
from voxe_core.refine.pipeline import merge

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
TEXT_SMOOTHING = dict(smoothing_kernel="3sigma", smooth_upsampled=False)  # σ 0.5 kept: the pre-bench setting


def map_variants(base: RefineConfig) -> dict[str, tuple[RefineConfig, float, float]]:
    """Name -> (config, edit lattice scale, object lattice scale)."""
    return {
        "authors_code": (dataclasses.replace(base, **AUTHORS_CODE_MAPS), 1.0, 1.0),
        "paper_text": (dataclasses.replace(base, **PAPER_TEXT_MAPS), 1.0, 1.0),
        "code_but_smoothing": (dataclasses.replace(base, **{**AUTHORS_CODE_MAPS, **TEXT_SMOOTHING}), 1.0, 1.0),
        "code_but_map_scale": (dataclasses.replace(base, **{**AUTHORS_CODE_MAPS, "map_scale": "minmax"}), 1.0, 1.0),
        "raw_edit_x0.3": (dataclasses.replace(base, **AUTHORS_CODE_MAPS), 0.3, 1.0),
        "raw_object_x0.3": (dataclasses.replace(base, **AUTHORS_CODE_MAPS), 1.0, 0.3),
    }


FIT_VARIANTS = {"backprojection_only": None, "fixed_all": ("fixed", "all"), "fixed_positive": ("fixed", "rendered_positive"),
                "fresh_all": ("fresh", "all"), "fresh_positive": ("fresh", "rendered_positive")}


def cut_row(scene, nodes, e, o, config, extra: dict, with_psnr: bool) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "only n of 5000 object seeds": expected at 96³
        mask, stats = graph_cut_detailed(scene.edited, e, o, config)
    row = {"scene": scene.name, "resolution": scene.truth.shape[0], **extra,
           "iou": round(iou(mask, scene.truth, nodes), 4), "predicted_voxels": int((mask & nodes).sum()),
           "true_voxels": int((scene.truth & nodes).sum()), "cut_seconds": round(stats.build_s + stats.solve_s, 3)}
    if with_psnr:
        row["merged_psnr"], row["preserved_psnr"] = (round(v, 2) for v in ring_psnrs(scene, merge(scene.initial, scene.edited, mask)))
    print("  ".join(f"{k} {v}" for k, v in row.items() if k not in ("resolution",)), flush=True)
    return row


def measure_maps(scene, level: str, seed: int, with_psnr: bool) -> list[dict]:
    base = RefineConfig(iterations=0, render_size=scene.cameras.width, views=len(scene.cameras))
    nodes = node_mask(scene.edited)
    edit_cells, object_cells = lattice_maps(scene.coverage, LEVELS[level], seed)
    size = (scene.cameras.height, scene.cameras.width)
    rows = []
    for name, (config, edit_scale, object_scale) in map_variants(base).items():
        t0 = time.perf_counter()
        edit_maps = postprocess_maps(edit_scale * edit_cells, size, config)
        object_maps = postprocess_maps(object_scale * object_cells, size, config)
        maps_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        e, o = fit_attention_grids(scene.edited, scene.cameras, edit_maps, object_maps, config)
        lift_s = time.perf_counter() - t0
        rows.append(cut_row(scene, nodes, e, o, config, {"noise": level, "variant": name, "maps_seconds": round(maps_s, 3),
                                                          "lift_seconds": round(lift_s, 2)},
                            with_psnr and name in ("authors_code", "paper_text")))
    return rows


def measure_fit(scene, pool, level: str, seed: int, steps: int, with_psnr: bool, map_scale: str) -> list[dict]:
    """``pool``: the scene with all its views, the fresh steps' source."""
    base = RefineConfig(render_size=scene.cameras.width, views=len(scene.cameras), map_scale=map_scale)
    nodes = node_mask(scene.edited)
    size = (scene.cameras.height, scene.cameras.width)
    edit_maps, object_maps = scene_maps(scene, level, seed, base)

    def fresh_view(step: int):
        view = int(torch.randint(len(pool.cameras), (), generator=draws))
        e_cells, o_cells = lattice_maps(pool.coverage[view:view + 1], LEVELS[level], 10_000 + step)
        return pool.cameras[view].resized(*size[::-1]), postprocess_maps(e_cells, size, base), postprocess_maps(o_cells, size, base)

    rows = []
    for name, choice in FIT_VARIANTS.items():
        config = dataclasses.replace(base, iterations=0) if choice is None else \
            dataclasses.replace(base, iterations=steps, fit_views=choice[0], fit_pixels=choice[1])
        draws = torch.Generator().manual_seed(seed)
        t0 = time.perf_counter()
        e, o = fit_attention_grids(scene.edited, scene.cameras, edit_maps, object_maps, config, fresh_view=fresh_view)
        lift_s = time.perf_counter() - t0
        rows.append(cut_row(scene, nodes, e, o, config, {"noise": level, "variant": name, "steps": config.iterations,
                                                          "lift_seconds": round(lift_s, 2)}, with_psnr))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part", choices=["maps", "fit"], required=True)
    parser.add_argument("--levels", nargs="+", default=None, help="default: clean moderate (maps), moderate (fit)")
    parser.add_argument("--steps", type=int, default=150, help="Adam steps of the fit variants")
    parser.add_argument("--views", type=int, default=32)
    parser.add_argument("--view-size", type=int, default=100)
    parser.add_argument("--no-psnr", action="store_true")
    parser.add_argument("--map-scale", choices=["raw", "minmax"], default=RefineConfig.map_scale,
                        help="the fit part's RefineConfig.map_scale (localisation_fit_variants.json: raw, "
                             "localisation_fit_variants_minmax_maps.json: minmax)")
    args = parse_with_common_arguments(parser, None, threads=2)
    levels = args.levels or (["clean", "moderate"] if args.part == "maps" else ["moderate"])
    # the fit part's min-max run has its own file beside the raw-map one the README's table quotes
    minmax_fit = args.part == "fit" and args.map_scale == "minmax"
    out = args.out or RESULTS / f"localisation_{args.part}_variants{'_minmax_maps' if minmax_fit else ''}.json"
    start = time.perf_counter()
    runs = []
    for name in SCENES:
        pool = build_scene(name, args.resolution)
        scene = fewer_views(pool, args.views, args.view_size)
        for level in levels:
            seed = 100 + list(LEVELS).index(level)
            runs += measure_maps(scene, level, seed, not args.no_psnr) if args.part == "maps" else \
                measure_fit(scene, pool, level, seed, args.steps, not args.no_psnr, args.map_scale)
    result = {
        "description": f"2D-map / fit variants (paper's text vs TAU-VAILab/Vox-E) on the localisation ground truth, "
                       f"part {args.part}; see bench/localisation_maps_fit.py.",
        "settings": {"resolution": args.resolution, "levels": {k: LEVELS[k] for k in levels}, "steps": args.steps, "views": args.views,
                     "view_size": args.view_size,
                     "authors_code_maps": AUTHORS_CODE_MAPS, "paper_text_maps": PAPER_TEXT_MAPS,
                     "refine_config": {k: v for k, v in vars(RefineConfig(map_scale=args.map_scale)).items()
                                       if k != "render"},
                     "threads": torch.get_num_threads()},
        "runs": runs,
        "total_seconds": round(time.perf_counter() - start, 1),
    }
    title = f"2D {args.part}: paper's text vs the authors' code (default cut, 96³)"
    write_results(result, out, lambda runs, path: plot(runs, path, title))


if __name__ == "__main__":
    main()
