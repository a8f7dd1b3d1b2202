"""The paper's text against the authors' code (issue 18 item 5): graph-cut variants on the localisation ground truth.

One lift per scene and noise level (bench/localisation.py's map model and back-projection lift, 96³), then the
cut under each variant of ``RefineConfig``, all on the same attention grids so the differences are the cut's:

* ``text_5000``: the text's cut with the code's 5,000 object seeds (the service default before this bench);
* ``paper_text``: ``PAPER_TEXT_CUT``, the text throughout (300 / 200 top seeds with P > ½);
* ``authors_code``: ``AUTHORS_CODE_CUT`` — no unary term for unseeded voxels, edit seeds
  P_e ≥ 0.992·max, up to 5,000 random object seeds with P_obj > P_e, w = K·exp(−‖Δc‖/σ), 3×3×3 max-pooled nodes;
* ``default``: ``SERVICE_CUT``, the authors' code with its object seeds drawn among P_obj > P_e + 0.02
  (bench/localisation_seeds.py);
* ``code_<field>``: ``text_5000`` with that one field switched to the code's choice.

IoU is over the text's node set (the code's max-pooled set is a dilation of it, so the same voxels count for
every variant). The grids are voxelised from the meshes (localisation_scenes.py), so this is also the
"mesh-voxelised grid" measurement of issue 18 item 4. ``agreement`` is the IoU of each variant's mask with
``text_5000``'s — the one figure that needs no ground truth.

    python bench/localisation_variants.py            # both scenes, clean + moderate (~4 min)
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings
from pathlib import Path

import torch

from localisation import LEVELS, parse_with_common_arguments, ring_psnrs, scene_maps, write_results
from localisation_scenes import SCENES, build_scene
from segmentation import iou
from voxe_core.constants import SERVICE_OBJECT_SEEDS
from voxe_core.refine.config import AUTHORS_CODE_CUT, PAPER_TEXT_CUT, SERVICE_CUT, RefineConfig
from voxe_core.refine.cut import graph_cut_detailed, node_mask
from voxe_core.refine.lifting import fit_attention_grids
from voxe_core.refine.pipeline import merge

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
SINGLE_SWITCHES = ("edit_seed_rule", "object_seed_rule", "unseeded_unary", "pairwise_weight", "node_rule")
WITH_PSNR = ("text_5000", "paper_text", "authors_code", "default")


def variants(base: RefineConfig) -> dict[str, RefineConfig]:
    """Name -> cut config; every variant keeps ``base``'s lift settings."""
    text_5000 = dataclasses.replace(base, **{**PAPER_TEXT_CUT, "object_seeds": SERVICE_OBJECT_SEEDS})
    out = {
        "text_5000": text_5000,
        "paper_text": dataclasses.replace(base, **PAPER_TEXT_CUT),
        "authors_code": dataclasses.replace(base, **AUTHORS_CODE_CUT),
        "default": dataclasses.replace(base, **SERVICE_CUT),
    }
    for name in SINGLE_SWITCHES:
        out[f"code_{name}"] = dataclasses.replace(text_5000, **{name: AUTHORS_CODE_CUT[name]})
    return out


def measure(scene, level_name: str, seed: int, with_psnr: bool) -> list[dict]:
    base = RefineConfig(iterations=0, render_size=scene.cameras.width, views=len(scene.cameras))
    edit_maps, object_maps = scene_maps(scene, level_name, seed, base)
    t0 = time.perf_counter()
    e, o = fit_attention_grids(scene.edited, scene.cameras, edit_maps, object_maps, base)
    lift_s = time.perf_counter() - t0
    nodes = node_mask(scene.edited)
    rows, reference = [], None
    for name, config in variants(base).items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "only n of 5000 object seeds": expected at 96³
            mask, stats = graph_cut_detailed(scene.edited, e, o, config)
        reference = mask if reference is None else reference
        row = {
            "scene": scene.name, "resolution": scene.truth.shape[0], "noise": level_name, "variant": name,
            "iou": round(iou(mask, scene.truth, nodes), 4), "agreement": round(iou(mask, reference, nodes), 4),
            "predicted_voxels": int((mask & nodes).sum()), "true_voxels": int((scene.truth & nodes).sum()),
            "graph_nodes": stats.nodes, "edit_seeds": stats.edit_seeds, "object_seeds": stats.object_seeds,
            "lift_seconds": round(lift_s, 2), "cut_seconds": round(stats.build_s + stats.solve_s, 3),
        }
        if with_psnr and name in WITH_PSNR:
            row["merged_psnr"], row["preserved_psnr"] = (round(v, 2) for v in ring_psnrs(scene, merge(scene.initial, scene.edited, mask)))
        rows.append(row)
        print(f"{scene.name:16s} {level_name:8s} {name:22s} IoU {row['iou']:.3f} agree {row['agreement']:.3f} "
              f"nodes {stats.nodes:7d} seeds {stats.edit_seeds}/{stats.object_seeds} cut {row['cut_seconds']:.2f}s "
              f"{row.get('merged_psnr', '')} {row.get('preserved_psnr', '')}", flush=True)
    return rows


def plot(runs: list[dict], path: Path,
         title: str = "graph cut: paper's text vs the authors' code, same attention grids (96³)") -> None:
    """IoU bars per variant, one colour per (scene, noise) case."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["variant"] for r in runs))
    cases = list(dict.fromkeys((r["scene"], r["noise"]) for r in runs))
    fig, ax = plt.subplots(figsize=(11, 4))
    width = 0.8 / len(cases)
    for k, case in enumerate(cases):
        ious = [next(r["iou"] for r in runs if (r["scene"], r["noise"]) == case and r["variant"] == n) for n in names]
        ax.bar([i + k * width for i in range(len(names))], ious, width, label=" / ".join(case))
    ax.set_xticks([i + 0.4 - width / 2 for i in range(len(names))], names, rotation=25, ha="right", fontsize=8)
    ax.set_ylabel("3D IoU vs true part")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--levels", nargs="+", default=["clean", "moderate"])
    parser.add_argument("--no-psnr", action="store_true", help="skip the ring renders of the merged grid")
    args = parse_with_common_arguments(parser, RESULTS / "localisation_variants.json")
    start = time.perf_counter()
    runs = []
    for name in SCENES:
        scene = build_scene(name, args.resolution)
        for level in args.levels:
            runs += measure(scene, level, 100 + list(LEVELS).index(level), not args.no_psnr)
    result = {
        "description": "Graph-cut variants (paper's text vs TAU-VAILab/Vox-E's build_graph) on the same lifted "
                       "attention grids of the localisation ground truth; see bench/localisation_variants.py.",
        "settings": {"resolution": args.resolution, "levels": {k: LEVELS[k] for k in args.levels},
                     "authors_code_cut": AUTHORS_CODE_CUT, "service_cut": SERVICE_CUT, "threads": torch.get_num_threads()},
        "runs": runs,
        "total_seconds": round(time.perf_counter() - start, 1),
    }
    write_results(result, args.out, plot)


if __name__ == "__main__":
    main()
