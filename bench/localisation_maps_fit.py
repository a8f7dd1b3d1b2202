"""The paper's text against the authors' code (issue 18 item 5): 2D-map and fit variants on the localisation ground truth.

bench/localisation.py's scenes (mesh-voxelised, 96³) and map model; the cut is the default (``AUTHORS_CODE_CUT``)
everywhere, so the differences are the maps' or the fit's. ``--part maps``: per variant the lattice maps are
post-processed under its ``RefineConfig`` and lifted by the back-projection (0 steps):

* ``authors_code``: ``AUTHORS_CODE_MAPS`` (the default): 3×3 σ 0.5 smoothing before and after upsampling, raw maps;
* ``paper_text``: ``PAPER_TEXT_MAPS``: σ 1 Gaussian (radius 3σ) once, min-max normalised maps;
* ``code_but_<field>``: the code's maps with that one choice the text's (``smoothing``: σ 0.5 with the whole
  Gaussian once, this project's setting before this bench; ``map_scale``: min-max);
* ``raw_edit_x0.3`` / ``raw_object_x0.3``: raw maps with the edit (object) lattice scaled by 0.3 — real
  cross-attention gives the two maps different scales, which raw maps keep and min-max removes.

Max vs mean over the edit tokens, the view word in the prompt and the end-of-text token among the object tokens
change nothing here (one synthetic edit map, no prompt): the bench cannot tell them apart.

``--part fit``: maps as the default; the back-projection start then ``--steps`` Adam steps under each of
``fit_views`` × ``fit_pixels``. "fresh" draws a random view of the 100 Blender views per step with fresh map
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

from localisation import LEVELS, lattice_maps, ring_psnrs, write_results
from localisation_scenes import SCENES, build_scene
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


def measure_fit(scene, level: str, seed: int, steps: int, with_psnr: bool) -> list[dict]:
    base = RefineConfig(render_size=scene.cameras.width, views=len(scene.cameras))
    nodes = node_mask(scene.edited)
    edit_cells, object_cells = lattice_maps(scene.coverage, LEVELS[level], seed)
    size = (scene.cameras.height, scene.cameras.width)
    edit_maps, object_maps = postprocess_maps(edit_cells, size, base), postprocess_maps(object_cells, size, base)

    def fresh_view(step: int):
        view = int(torch.randint(len(scene.cameras), (), generator=draws))
        e_cells, o_cells = lattice_maps(scene.coverage[view:view + 1], LEVELS[level], 10_000 + step)
        return scene.cameras[view], postprocess_maps(e_cells, size, base), postprocess_maps(o_cells, size, base)

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


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["variant"] for r in runs))
    cases = list(dict.fromkeys((r["scene"], r["noise"]) for r in runs))
    fig, ax = plt.subplots(figsize=(10, 4))
    width = 0.8 / len(cases)
    for k, case in enumerate(cases):
        ious = [next(r["iou"] for r in runs if (r["scene"], r["noise"]) == case and r["variant"] == n) for n in names]
        ax.bar([i + k * width for i in range(len(names))], ious, width, label=" / ".join(case))
    ax.set_xticks([i + 0.4 - width / 2 for i in range(len(names))], names, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("3D IoU vs true part")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax.set_title("2D maps / fit: paper's text vs the authors' code (default cut, 96³)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part", choices=["maps", "fit"], required=True)
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--levels", nargs="+", default=None, help="default: clean moderate (maps), moderate (fit)")
    parser.add_argument("--steps", type=int, default=150, help="Adam steps of the fit variants")
    parser.add_argument("--no-psnr", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    levels = args.levels or (["clean", "moderate"] if args.part == "maps" else ["moderate"])
    out = args.out or RESULTS / f"localisation_{args.part}_variants.json"
    start = time.perf_counter()
    runs = []
    for name in SCENES:
        scene = build_scene(name, args.resolution)
        for level in levels:
            seed = 100 + list(LEVELS).index(level)
            runs += measure_maps(scene, level, seed, not args.no_psnr) if args.part == "maps" else \
                measure_fit(scene, level, seed, args.steps, not args.no_psnr)
    result = {
        "description": f"2D-map / fit variants (paper's text vs TAU-VAILab/Vox-E) on the localisation ground truth, "
                       f"part {args.part}; see bench/localisation_maps_fit.py.",
        "settings": {"resolution": args.resolution, "levels": {k: LEVELS[k] for k in levels}, "steps": args.steps,
                     "authors_code_maps": AUTHORS_CODE_MAPS, "paper_text_maps": PAPER_TEXT_MAPS,
                     "threads": torch.get_num_threads()},
        "runs": runs,
        "total_seconds": round(time.perf_counter() - start, 1),
    }
    write_results(result, out, plot)


if __name__ == "__main__":
    main()
