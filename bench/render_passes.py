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
    python bench/render_passes.py --transmittance --repeats 4   # ~3 min, one thread

Writes bench/results/render_passes.json and .png; prints a table. ``--transmittance`` instead times the packed
transmittance (``volrend.transmittance``: one float64 prefix sum over the pass, its rounding errors added back per
ray) against the prefix sum as it was (without them), interleaved: the scan alone, forward and backward, on a pass of
3,000 opaque rays and a faint one (~10^6 samples, the CPU's pass), and the edit's render + backward on both scenes;
beside it the accuracy bought, the faint ray's pixel and density gradients behind the opaque rays against the ray
alone (bench/results/render_passes_transmittance.json and .png). Times are this CPU's (medians of interleaved
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
from contextlib import ExitStack
from pathlib import Path
from unittest import mock

import torch
from torch.utils._python_dispatch import TorchDispatchMode

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE)]
from edit_step import sphere_grid  # noqa: E402

from voxe_core.cameras import Cameras, camera_rays, random_hemisphere_poses  # noqa: E402
from voxe_core.devices import PeakMemory, synchronize  # noqa: E402
from voxe_core.edit import EditConfig  # noqa: E402
from voxe_core.grid import VoxelGrid  # noqa: E402
from voxe_core.render import RenderConfig, composite, render_rays  # noqa: E402
from voxe_core.volrend import RaySamples, host_reads_are_free, optical_depth, transmittance  # noqa: E402

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


def prefix_sum_transmittance(optical: torch.Tensor, ray: torch.Tensor) -> torch.Tensor:
    """``volrend.transmittance`` as it was at dcfa9ff (what ``--transmittance`` measures it against): each ray's
    depth in front of a sample is the pass's float64 prefix sum less its value at the ray's first sample, rounded
    at the size of the whole pass's sum."""
    nan = optical.isnan()
    if host_reads_are_free(optical.device) and not bool(nan.any()):
        nan = None
    wide = optical.double() if nan is None else optical.double().masked_fill(nan, 0.0)
    before = wide.cumsum(0) - wide
    first = torch.searchsorted(ray, ray)
    t = torch.exp(before.index_select(0, first) - before)
    if nan is not None:
        nans_before = nan.cumsum(0) - nan.long()
        t = t.masked_fill(nans_before > nans_before.index_select(0, first), float("nan"))
    return t.to(optical.dtype)


SCANS = {"default": transmittance, "prefix sum as it was": prefix_sum_transmittance}
FAINT_SAMPLES = 500  # the faint ray's samples behind the opaque rays


def scan(name: str) -> ExitStack:
    """The renderer (its compositing and its early stop) with the transmittance ``name`` (a context manager)."""
    stack = ExitStack()
    for module in ("voxe_core.render", "voxe_core.grid"):
        stack.enter_context(mock.patch(f"{module}.transmittance", SCANS[name]))
    return stack


def faint_ray(opaque_rays: int, faint_samples: int = FAINT_SAMPLES) -> list[torch.Tensor]:
    """A faint ray composited behind ``opaque_rays`` opaque rays in one pass (165–494 samples each at the clamped
    optical depth 1e4: a prefix sum near 1e10 at 3,000): its rgb (3), opacity and depth, and its samples' density
    gradients (of rgb + opacity + depth / 10). The same faint ray whatever ``opaque_rays``."""
    ray, sigma, t, colour = opaque_pass(opaque_rays)
    faint = torch.Generator().manual_seed(4)
    ray = torch.cat([ray, torch.full((faint_samples,), opaque_rays)])
    sigma = torch.cat([sigma, 2.0 * torch.rand(faint_samples, generator=faint)]).requires_grad_()
    t = torch.cat([t, torch.linspace(0.5, 3.0, faint_samples)])
    colour = torch.cat([colour, torch.rand(faint_samples, 3, generator=faint)])
    samples = RaySamples(ray, t, torch.full_like(t, 0.005), torch.zeros(t.shape[0], 3))
    out = composite([samples], lambda points: (sigma, colour), opaque_rays + 1, torch.ones(3))
    (out.rgb[-1].sum() + out.opacity[-1] + 0.1 * out.depth[-1]).backward()
    return [out.rgb[-1].detach(), out.opacity[-1:].detach(), out.depth[-1:].detach(), sigma.grad[-faint_samples:]]


def opaque_pass(opaque_rays: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The samples of :func:`faint_ray`'s opaque rays: ray index, density (1e7 per unit), distance and colour."""
    g = torch.Generator().manual_seed(3)
    lengths = torch.randint(165, 495, (opaque_rays,), generator=g)
    n = int(lengths.sum())
    return (torch.arange(opaque_rays).repeat_interleave(lengths), torch.full((n,), 1e7), torch.rand(n, generator=g),
            torch.rand(n, 3, generator=g))


def measure_transmittance(grid_scenes: dict, rays, repeats: int, opaque_rays: int = 3000) -> dict:
    """Per entry of :data:`SCANS`: the faint ray's errors behind ``opaque_rays`` opaque rays against it alone, the
    scan's own forward + backward ms on that pass (five a round), the edit's render + backward ms per scene (medians of
    ``repeats`` interleaved rounds; wall and this process's CPU time, which other jobs on the shared cores move
    less) and its difference from the default's; time ratios to the default."""
    rows = {name: {"variant": name} for name in SCANS}
    ray, sigma, _, _ = opaque_pass(opaque_rays)
    optical = optical_depth(sigma, torch.full_like(sigma, 0.005)).requires_grad_()
    outputs = {}
    for name in SCANS:
        with scan(name):
            behind, alone = faint_ray(opaque_rays), faint_ray(0)
            rows[name].update({
                "scan_samples": ray.numel(),  # the timed pass: the opaque rays' samples
                "max_relative_error_rgb_opacity_depth": max(float(((b - a).abs() / a.abs()).max())
                                                            for b, a in zip(behind[:3], alone[:3])),
                "max_relative_error_density_gradient": float(((behind[3] - alone[3]).abs() / alone[3].abs()).max()),
                "gradient_error_of_largest_entry": float((behind[3] - alone[3]).abs().max() / alone[3].abs().max())})
            for scene, grid in grid_scenes.items():
                out = render(grid, rays, EditConfig().render)
                outputs[name, scene] = out.rgb.detach(), backward(grid, out.rgb).clone()
    for name in SCANS:
        for scene in grid_scenes:
            rgb, grad = outputs[name, scene]
            reference = outputs["default", scene]
            rows[name][f"{scene}_max_rgb_difference"] = float((rgb - reference[0]).abs().max())
            rows[name][f"{scene}_max_gradient_difference"] = float((grad - reference[1]).abs().max()
                                                                   / reference[1].abs().max())
    times = {(name, part, clock): [] for name in SCANS for part in ("scan", *grid_scenes) for clock in ("ms", "cpu_ms")}

    def timed(name: str, part: str, run) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        run()
        times[name, part, "ms"].append((time.perf_counter() - wall) * 1e3)
        times[name, part, "cpu_ms"].append((time.process_time() - cpu) * 1e3)

    for round_ in range(repeats):  # interleaved, the order flipped each round: drift and order land on both alike
        for name in list(SCANS)[:: 1 if round_ % 2 == 0 else -1]:
            for _ in range(5):  # the scan is short: five times a round
                timed(name, "scan", lambda: SCANS[name](optical, ray).sum().backward())
            with scan(name):
                for scene, grid in grid_scenes.items():
                    timed(name, scene, lambda: backward(grid, render(grid, rays, EditConfig().render).rgb))
    for (name, part, clock), ms in times.items():
        rows[name][f"{part}_{clock}"] = statistics.median(ms)
        rows[name][f"{part}_{clock}_each"] = ms
    for row in rows.values():
        for part in ("scan", *grid_scenes):
            for clock in ("ms", "cpu_ms"):
                row[f"{part}_{clock}_ratio_to_default"] = row[f"{part}_{clock}"] / rows["default"][f"{part}_{clock}"]
    return rows


def plot_transmittance(rows: dict, parts: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (speed, error) = plt.subplots(1, 2, figsize=(12, 4))
    errors = ["max_relative_error_rgb_opacity_depth", "max_relative_error_density_gradient"]
    width = 0.8 / len(rows)
    for i, row in enumerate(rows.values()):
        offset = (i - (len(rows) - 1) / 2) * width
        times = [row[f"{part}_cpu_ms"] for part in parts]
        speed.bar([j + offset for j in range(len(parts))], times, width, color=f"C{i}", label=row["variant"])
        for j, part in enumerate(parts):
            speed.annotate(f"×{row[f'{part}_cpu_ms_ratio_to_default']:.2f}", (j + offset, times[j]), ha="center",
                           va="bottom", fontsize=7)
        shown = [max(row[e], 1e-12) for e in errors]  # 0 drawn at the axis' floor
        error.bar([j + offset for j in range(len(errors))], shown, width, color=f"C{i}", label=row["variant"])
        for j, e in enumerate(errors):
            error.annotate(f"{row[e]:.1g}", (j + offset, shown[j]), ha="center", va="bottom", fontsize=7)
    speed.set_yscale("log")
    speed.set_xticks(range(len(parts)), ["the scan alone\n(10⁶ samples, fwd + bwd)",
                                         *[f"{p}: the edit's\nrender + backward" for p in parts[1:]]])
    speed.set_ylabel("CPU ms, one thread (median of interleaved repeats)")
    speed.set_title("time (labels: ratio to the default)")
    error.set_yscale("log")
    error.set_ylim(1e-12, 1e-2)
    error.set_xticks(range(len(errors)), ["pixel, opacity, depth", "density gradient"])
    error.set_ylabel("max relative error against the ray alone")
    error.set_title("a faint ray behind 3,000 opaque rays in one pass")
    for ax in (speed, error):
        ax.legend(fontsize=8)
        ax.grid(True, axis="y", which="both", color="0.92")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def record_transmittance(repeats: int, out: Path) -> dict:
    """:func:`measure_transmittance` on the edit's rays through both scenes, one thread; saved to ``out`` with a plot."""
    torch.set_num_threads(1)
    rays = edit_rays(EditConfig().render_size)
    scenes = {"sphere": sphere_grid(160), "fog": fog_grid(96)}
    for grid in scenes.values():
        grid.flat_features.requires_grad_(True)
    load_before = os.getloadavg()[0]
    rows = measure_transmittance(scenes, rays, repeats)
    record = {"description": "volrend.transmittance (prefix sum, rounding errors added back per ray) against the "
                             "prefix sum as it was; see bench/render_passes.py --transmittance",
              "machine": f"{os.cpu_count()} CPU cores, torch {torch.__version__}", "threads": torch.get_num_threads(),
              "load_average_before_after": [load_before, os.getloadavg()[0]], "repeats": repeats,
              "rays": rays[0].shape[0], "grids": {"sphere": 160, "fog": 96}, "runs": list(rows.values())}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    plot_transmittance(rows, ["scan", *scenes], out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None,
                        help="default: results/render_passes.json, with --transmittance render_passes_transmittance.json")
    parser.add_argument("--transmittance", action="store_true",
                        help="the packed transmittance against the prefix sum as it was: time and accuracy")
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    if args.transmittance:
        rows = record_transmittance(args.repeats, args.out or HERE / "results" / "render_passes_transmittance.json")
        for r in rows.values():
            times = "  ".join(f"{part} {r[f'{part}_cpu_ms']:7.1f} CPU ms (x{r[f'{part}_cpu_ms_ratio_to_default']:.2f}; wall "
                              f"x{r[f'{part}_ms_ratio_to_default']:.2f})" for part in ("scan", "sphere", "fog"))
            print(f"{r['variant']:22s} {times}  behind 3,000 opaque rays: pixel error "
                  f"{r['max_relative_error_rgb_opacity_depth']:.1e}, density gradient error "
                  f"{r['max_relative_error_density_gradient']:.1e}")
        return 0
    rows = record_scenes(measure, args.repeats, "RenderConfig.samples_per_pass against operations, time, memory and "
                         "output; see bench/render_passes.py", args.out or HERE / "results" / "render_passes.json", plot)
    for r in rows:
        print(f"{r['scene']:6s} {r['samples_per_pass']:>9d}  ops {r['operations']:5d} (x{r['operations_ratio_to_reference']:.2f})"
              f"  {r['ms']:8.1f} ms (x{r['ms_ratio_to_reference']:.2f})  peak {r['peak_memory_gb']:.2f} GiB"
              f"  rgb diff {r['max_rgb_difference']:.1e}  grad diff {r['max_gradient_difference']:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
