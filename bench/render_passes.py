"""How many lattice samples the renderer holds per pass (``RenderConfig.samples_per_pass``) against the operations it
dispatches, its time, its memory and its output, for one editing render (266² rays through a 160³ grid, forward and
backward, stratified jitter), on two scenes:

* ``sphere``: an opaque object (the edit's case; bench/edit_step.py's sphere), few occupied cells per ray;
* ``fog``: a thin density in every cell of a 96³ grid (a dense, semi-transparent scene: every lattice sample is a
  candidate and is evaluated; 96³ keeps this CPU's run short).

The renderer groups consecutive rays so that each group's lattice samples fit in one pass; each group repeats the
sampler's, the early stop's and the compositing's operations. On the lent H200 the edit's render (31 ms) is bound
by the host dispatching operations, not by arithmetic (bench/results/gpu.json): the operation count is what a GPU
pays per pass. Groups hold whole rays and draw nothing of their own, so the output must not move at all.

    python bench/render_passes.py            # ~5 min on 2 cores

Writes bench/results/render_passes.json and .png; prints a table. Times are this CPU's (medians of interleaved
repeats, compared within one scene as ratios), operations are aten calls counted by a dispatch mode (the same on
any device), memory is ``PeakMemory``'s during one render (the process's resident peak on CPU). bench/gpu.py's
section h runs :func:`measure` on the GPU.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE)]
from edit_step import sphere_grid  # noqa: E402

from voxe_core.cameras import Cameras, camera_rays, random_hemisphere_poses  # noqa: E402
from voxe_core.devices import PeakMemory, synchronize  # noqa: E402
from voxe_core.edit import EditConfig  # noqa: E402
from voxe_core.grid import VoxelGrid  # noqa: E402
from voxe_core.render import RenderConfig, render_rays  # noqa: E402

PASSES = (1 << 20, 1 << 21, 1 << 22, 1 << 23)  # the first: the CPU's default (RenderConfig.pass_samples), the reference


class CountOps(TorchDispatchMode):
    """Counts the aten operations dispatched inside it."""

    def __init__(self):
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += 1
        return func(*args, **(kwargs or {}))


def fog_grid(resolution: int) -> VoxelGrid:
    """A thin, grey density in every cell: each ray crosses the whole box, transmittance never falls to the stop."""
    grid = VoxelGrid(resolution)
    with torch.no_grad():
        grid.features[..., 0] = 0.02 / float(grid.voxel_size.min())
        grid.features[..., 1:] = 0.0
    return grid


def render(grid: VoxelGrid, rays, config: RenderConfig, seed: int = 0):
    """One jittered render of ``rays`` (origins, directions), with its graph."""
    origins, directions = rays
    generator = torch.Generator(origins.device).manual_seed(seed)
    return render_rays(grid, origins, directions, config, grid.occupancy(config.sigma_threshold), generator)


def backward(grid: VoxelGrid, rgb: torch.Tensor) -> torch.Tensor:
    """The grid's feature gradient of a fixed weighting of the render ``rgb`` (N, 3)."""
    grid.flat_features.grad = None
    weights = torch.linspace(0.5, 1.5, rgb.shape[0], device=rgb.device)
    (rgb * weights[:, None]).sum().backward()
    return grid.flat_features.grad


def render_once(grid: VoxelGrid, rays, config: RenderConfig, seed: int = 0):
    """(rgb (N, 3), the grid's feature gradient, samples) of one jittered render and its backward."""
    out = render(grid, rays, config, seed)
    return out.rgb.detach(), backward(grid, out.rgb).clone(), out.samples


def measure(name: str, grid: VoxelGrid, rays, repeats: int, device: str = "cpu", passes=PASSES) -> list[dict]:
    """One row per ``passes`` entry: operations, samples, peak memory, output differences against the first entry
    and the median time of ``repeats`` interleaved renders (each row's ``*_ratio_to_reference`` against the first)."""
    base = EditConfig().render
    configs = {spp: RenderConfig(**{**base.__dict__, "samples_per_pass": spp}) for spp in passes}
    rows = measure_configs(grid, rays, repeats, device, configs)
    return [{"scene": name, "samples_per_pass": spp, **row} for spp, row in rows.items()]


def measure_configs(grid: VoxelGrid, rays, repeats: int, device: str, configs: dict) -> dict:
    """Per entry of ``configs`` (key -> RenderConfig): operations, samples, whether the fused marcher rendered it, peak
    memory, output differences against the first entry and the median time of ``repeats`` interleaved renders with
    their backward (ratios to the first's)."""
    device = torch.device(device)
    grid = grid.to(device)
    rays = tuple(r.to(device) for r in rays)
    grid.flat_features.requires_grad_(True)
    rows, reference = {}, None
    for key, config in configs.items():  # operations, memory and output: one untimed render each
        memory = PeakMemory(device).start()
        with CountOps() as ops:
            rgb, grad, samples = render_once(grid, rays, config)
        peak = memory.info()
        reference = reference or (rgb, grad)
        rows[key] = {"operations": ops.count, "samples": int(samples),
                     "marched_fused": isinstance(samples, torch.Tensor),  # the fused marcher's count is a tensor
                     "device": str(device), "peak_memory_gb": peak["peak_memory_gb"],
                     "peak_memory_kind": peak["peak_memory_kind"],
                     "max_rgb_difference": float((rgb - reference[0]).abs().max()),
                     # relative to the largest entry: groups add the gradient into the grid in another order
                     "max_gradient_difference": float((grad - reference[1]).abs().max() / reference[1].abs().max()),
                     "ms": []}
    for _ in range(repeats):  # interleaved, so the shared machine's drift lands on every variant alike
        for key, config in configs.items():
            synchronize(device)
            start = time.perf_counter()
            render_once(grid, rays, config)
            synchronize(device)
            rows[key]["ms"].append((time.perf_counter() - start) * 1e3)
    first = next(iter(rows.values()))
    first_ms = statistics.median(first["ms"])
    for row in rows.values():
        row["ms"] = statistics.median(row["ms"])
        row["ms_ratio_to_reference"] = row["ms"] / first_ms
        row["operations_ratio_to_reference"] = row["operations"] / first["operations"]
    return rows


def edit_rays(size: int):
    """Rays (origins, directions), (size², 3) each, of one pose the edit draws around the origin."""
    config = EditConfig()
    c2w, _, _ = random_hemisphere_poses(1, torch.Generator().manual_seed(0), config.radius, config.min_zenith_deg,
                                        config.max_zenith_deg, torch.zeros(3))
    return camera_rays(Cameras.from_fov(c2w, config.fov_x, size, size), 0)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ops, ms) = plt.subplots(1, 2, figsize=(11, 4))
    for scene, marker in (("sphere", "o"), ("fog", "s")):
        mine = [r for r in rows if r["scene"] == scene]
        x = [r["samples_per_pass"] for r in mine]
        ops.plot(x, [r["operations"] for r in mine], marker=marker, label=scene)
        ms.plot(x, [r["ms"] for r in mine], marker=marker, label=scene)
        for r in mine:
            ms.annotate(f" {r['peak_memory_gb']:.1f} GiB", (r["samples_per_pass"], r["ms"]), fontsize=7)
    for ax, label in ((ops, "aten operations per render + backward"), (ms, "ms per render + backward (CPU, median)")):
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("samples_per_pass (log₂)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", color="0.92")
        ax.legend(fontsize=8)
    ops.set_title("operations dispatched (what a launch-bound GPU pays)")
    ms.set_title(f"time on {rows[0]['device'] if rows else '?'}; labels: peak memory")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def record_scenes(measure, repeats: int, description: str, out: Path, plot) -> list[dict]:
    """``measure(scene, grid, rays, repeats)`` on the edit's rays through both scenes (sphere 160³, fog 96³): its rows,
    saved to ``out`` (JSON) with ``plot``'s figure beside it."""
    size = EditConfig().render_size
    rays = edit_rays(size)
    rows = measure("sphere", sphere_grid(160), rays, repeats) + measure("fog", fog_grid(96), rays, repeats)
    record = {"description": description, "machine": f"{os.cpu_count()} CPU cores, torch {torch.__version__}",
              "rays": size * size, "grids": {"sphere": 160, "fog": 96}, "runs": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    plot(rows, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "render_passes.json")
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    rows = record_scenes(measure, args.repeats, "RenderConfig.samples_per_pass against operations, time, memory and "
                         "output; see bench/render_passes.py", args.out, plot)
    for r in rows:
        print(f"{r['scene']:6s} {r['samples_per_pass']:>9d}  ops {r['operations']:5d} (x{r['operations_ratio_to_reference']:.2f})"
              f"  {r['ms']:8.1f} ms (x{r['ms_ratio_to_reference']:.2f})  peak {r['peak_memory_gb']:.2f} GiB"
              f"  rgb diff {r['max_rgb_difference']:.1e}  grad diff {r['max_gradient_difference']:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
