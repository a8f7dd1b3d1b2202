"""The trilinear interpolation inside the edit's render, in variants timed as ratios in one run: the default
(``voxe_core.grid``'s weighted gather: ``F.embedding``, batched matrix products, and a backward that adds into the
grid with one ``index_add_``) against

* ``embedding backward``: ``F.embedding``'s own dense backward (what the default replaced: on the CPU one small
  add per index, each thread scanning every index for its rows; on CUDA a sort of the indices, then sums);
* ``mul-sum forward``: the eight corners weighed by a broadcast multiply and a sum instead of the batched
  (1 × 8) @ (8 × 4) matrix products (slower on this CPU; a GPU's batched GEMM on 2M tiny matrices may not be),

on bench/render_passes.py's two scenes (the edit's 266² rays; an opaque sphere at 160³, fog at 96³), each render
and backward at the device's default pass size:

* time of the forward and of the backward (medians of interleaved repeats), and their ratios to the default;
* what autograd keeps for the backward (bytes of the saved tensors, the same on any device), and the peak memory
  (a GPU's per variant; on the CPU the process's resident peak so far, which only grows from row to row);
* the render and gradient against the default's: on the CPU every variant adds in index order (0 difference); on
  a GPU ``index_add_``'s atomic adds run in another order (float32 rounding).

    python bench/interpolation.py     # ~2 min on 2 cores

Writes bench/results/interpolation.json and .png; prints a table. bench/gpu.py's section h runs :func:`measure` on
the GPU.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from contextlib import nullcontext
from pathlib import Path
from unittest import mock

import torch
import torch.nn.functional as F

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE)]
from render_passes import backward, record_scenes, render  # noqa: E402

from voxe_core import grid as grid_module  # noqa: E402
from voxe_core.devices import PeakMemory, synchronize  # noqa: E402
from voxe_core.edit import EditConfig  # noqa: E402
from voxe_core.grid import VoxelGrid  # noqa: E402


def _mul_sum(weights: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """The corners weighed by a broadcast multiply and a sum, instead of batched matrix products."""
    return (weights[..., None] * values).sum(1)


def _embedding_gather(table: torch.Tensor, index: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """The gather as it was: the values through ``F.embedding`` and its own backward, weighed as the default weighs."""
    return grid_module._weigh_corners(weights, F.embedding(index, table))


# variant -> (what it replaces, with what); the default replaces nothing
VARIANTS = {"default": None, "embedding backward": (grid_module._WeightedGather, "apply", _embedding_gather),
            "mul-sum forward": (grid_module, "_weigh_corners", _mul_sum)}


def variant(name: str):
    """The renderer's interpolation as the variant ``name`` computes it (a context manager)."""
    return mock.patch.object(*VARIANTS[name]) if VARIANTS[name] else nullcontext()


def _saved_bytes(run) -> tuple[object, int]:
    """``run()``'s result and the bytes of the distinct storages autograd saved for its backward."""
    storages: dict[int, int] = {}

    def pack(tensor: torch.Tensor) -> torch.Tensor:
        storage = tensor.untyped_storage()
        storages[storage.data_ptr()] = storage.nbytes()
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        result = run()
    return result, sum(storages.values())


def measure(name: str, grid: VoxelGrid, rays, repeats: int, device: str = "cpu") -> list[dict]:
    """One row per entry of :data:`VARIANTS`: forward and backward ms (medians of ``repeats`` interleaved), bytes
    saved for the backward, peak memory, and the render's and gradient's differences from the default's."""
    device = torch.device(device)
    grid = grid.to(device)
    rays = tuple(r.to(device) for r in rays)
    grid.flat_features.requires_grad_(True)
    config = EditConfig().render
    rows, outputs = {}, {}
    for label in VARIANTS:  # memory and output: one untimed render each
        memory = PeakMemory(device).start()
        with variant(label):
            out, saved = _saved_bytes(lambda: render(grid, rays, config))
            outputs[label] = out.rgb.detach(), backward(grid, out.rgb).clone()
        peak = memory.info()
        rows[label] = {"scene": name, "variant": label, "samples": out.samples, "device": str(device),
                       "saved_for_backward_mb": saved / 2**20, "peak_memory_gb": peak["peak_memory_gb"],
                       "peak_memory_kind": peak["peak_memory_kind"], "forward_ms": [], "backward_ms": []}
    reference = outputs["default"]
    for label, (rgb, grad) in outputs.items():
        rows[label]["max_rgb_difference"] = float((rgb - reference[0]).abs().max())
        rows[label]["max_gradient_difference"] = float((grad - reference[1]).abs().max() / reference[1].abs().max())
    for _ in range(repeats):  # interleaved: the shared machine's drift lands on every variant alike
        for label in VARIANTS:
            with variant(label):
                synchronize(device)
                start = time.perf_counter()
                out = render(grid, rays, config)
                synchronize(device)
                middle = time.perf_counter()
                backward(grid, out.rgb)
                synchronize(device)
            rows[label]["forward_ms"].append((middle - start) * 1e3)
            rows[label]["backward_ms"].append((time.perf_counter() - middle) * 1e3)
    for row in rows.values():
        row["forward_ms"], row["backward_ms"] = statistics.median(row["forward_ms"]), statistics.median(row["backward_ms"])
        row["ms"] = row["forward_ms"] + row["backward_ms"]
    default = rows["default"]
    for row in rows.values():
        row["forward_ratio_to_default"] = row["forward_ms"] / default["forward_ms"]
        row["backward_ratio_to_default"] = row["backward_ms"] / default["backward_ms"]
        row["ms_ratio_to_default"] = row["ms"] / default["ms"]
    return list(rows.values())


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / len(VARIANTS)
    for i, label in enumerate(VARIANTS):
        mine = [next(r for r in rows if r["scene"] == s and r["variant"] == label) for s in scenes]
        x = [j + (i - (len(VARIANTS) - 1) / 2) * width for j in range(len(scenes))]
        ax.bar(x, [r["forward_ms"] for r in mine], width, color=f"C{i}", alpha=0.45)
        ax.bar(x, [r["backward_ms"] for r in mine], width, bottom=[r["forward_ms"] for r in mine], color=f"C{i}",
               label=f"{label} (light: forward, dark: backward)")
        for xi, r in zip(x, mine):
            ax.annotate(f"×{r['ms_ratio_to_default']:.2f}", (xi, r["ms"]), ha="center", va="bottom", fontsize=7)
    ax.set_xticks(range(len(scenes)), [f"{s}\n{next(r['samples'] for r in rows if r['scene'] == s):,} grid evaluations"
                                       for s in scenes])
    ax.set_ylabel(f"ms per render + backward ({rows[0]['device'] if rows else '?'}, median)")
    ax.set_title("the interpolation in the edit's render: variants against the default (labels: time ratio)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "interpolation.json")
    args = parser.parse_args(argv)
    rows = record_scenes(measure, args.repeats, "the interpolation in the edit's render, variants against the default; "
                         "see bench/interpolation.py", args.out, plot)
    for r in rows:
        print(f"{r['scene']:6s} {r['variant']:18s} {r['samples']:>9d} evaluations  forward {r['forward_ms']:7.1f} ms "
              f"(x{r['forward_ratio_to_default']:.2f})  backward {r['backward_ms']:7.1f} ms "
              f"(x{r['backward_ratio_to_default']:.2f})  total x{r['ms_ratio_to_default']:.2f}  saved "
              f"{r['saved_for_backward_mb']:.0f} MB  rgb diff {r['max_rgb_difference']:.1e}  grad diff "
              f"{r['max_gradient_difference']:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
