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
    python bench/render_passes.py --precision-fixes --repeats 9  # ~5 min, one thread

Writes bench/results/render_passes.json and .png; prints a table. ``--transmittance`` instead times the packed
transmittance (``volrend.transmittance``: one float64 prefix sum over the pass, its rounding errors added back per
ray) against the prefix sum as it was (without them), interleaved: the scan alone, forward and backward, on a pass of
3,000 opaque rays and a faint one (~10^6 samples, the CPU's pass), and the edit's render + backward on both scenes;
beside it the accuracy bought, the faint ray's pixel and density gradients behind the opaque rays against the ray
alone (bench/results/render_passes_transmittance.json and .png). Times are this CPU's (medians of interleaved
repeats, compared within one scene as ratios), operations are aten calls counted by a dispatch mode (the same on
any device), memory is ``PeakMemory``'s during one render (the process's resident peak on CPU). bench/gpu.py's
section h runs :func:`measure` on the GPU.

``--precision-fixes`` times three float-precision changes of 2026-12-07 against their predecessors (re-implemented
here, swapped in by ``mock``) in alternating pairs, one thread, beside what each bought: (a) ``render_rays`` moving
rays that start farther than the box's diagonal to the box in float64 (5db286d): the edit's render + backward of the
sphere from the edit's cameras (none moved) and along the same lines from 1e5 and 1e7 units, against the same lines'
render from 4 units out; (b) the correlation regulariser as ½‖â − b̂‖² through ``F.mse_loss`` (18e9312) against
1 − â·b̂: reg3d and reg3d_plus forward + backward at 160³, value and gradient against float64 Pearson at G_e = G_i + δ
noise (δ = 0, the edit's first step, 1e-4 and 1e-2); (c) the occupied cells' tight box ending at ``bbox_max``
(e25adf2): ``occupancy_from_cells`` on both scenes' cells, and the opacity of rays lying in the faces of a 38-vertex
grid against the render without skipping (bench/results/render_passes_precision_fixes.json and .png).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from contextlib import ExitStack, nullcontext
from pathlib import Path
from unittest import mock

import torch
from torch.utils._python_dispatch import TorchDispatchMode

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE)]
from edit_step import sphere_grid  # noqa: E402

import voxe_core.render as render_module  # noqa: E402
from voxe_core import losses  # noqa: E402
from voxe_core.cameras import Cameras, camera_rays, random_hemisphere_poses  # noqa: E402
from voxe_core.devices import PeakMemory, full_precision, synchronize  # noqa: E402
from voxe_core.edit import EditConfig  # noqa: E402
from voxe_core.grid import Occupancy, VoxelGrid  # noqa: E402
from voxe_core.losses import CORRELATED_CHANNELS, volumetric_regulariser  # noqa: E402
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


# --precision-fixes: three float-precision changes of 2026-12-07 against their predecessors, re-implemented here.
FAR = (1e5, 1e7)  # the edit's lines, their origins moved back along them this far (float32 origins, as a caller's)


def _not_moved(grid: VoxelGrid, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``render._moved_to_the_box`` before 5db286d, when there was none: every origin rounded to float32 where it is
    (the depth's ``+ shift`` of a zero shift still runs after it: one (N,) ``where``)."""
    return origins, torch.zeros(origins.shape[0], device=origins.device)


def _dot_product_correlation_with(standardised_initial: tuple[torch.Tensor, torch.Tensor], edited: torch.Tensor,
                                  eps: float) -> torch.Tensor:
    """``losses._correlation_loss_with`` before 18e9312: 1 − â·b̂ of the standardised grids in float32."""
    a, _ = standardised_initial
    with full_precision(a, edited):
        b, _ = losses._standardise(edited, eps)
        return 1.0 - (a * b).sum()


def _box_at_the_last_vertex(self: VoxelGrid, cells: torch.Tensor) -> Occupancy:
    """``VoxelGrid.occupancy_from_cells`` before e25adf2: the tight box ends at bbox_min + hi · voxel, which float32
    rounds inside the far face for some lattices."""
    lo, hi = [], []
    for axis in range(3):
        along = cells.any(dim=[a for a in range(3) if a != axis]).to(torch.uint8)
        lo.append(along.argmax())
        hi.append(along.numel() - along.flip(0).argmax())
    vox = self._lattice(cells.device).voxel_size
    occupied = cells.any()
    box_min = torch.where(occupied, self.bbox_min + torch.stack(lo) * vox, self.bbox_min)
    box_max = torch.where(occupied, self.bbox_min + torch.stack(hi) * vox, self.bbox_min)
    return Occupancy(cells, box_min, box_max)


# change -> (what its predecessor replaces, with what)
FIXES = {"far rays moved to the box (5db286d)": (render_module, "_moved_to_the_box", _not_moved),
         "correlation regulariser as ½‖â − b̂‖² (18e9312)": (losses, "_correlation_loss_with",
                                                              _dot_product_correlation_with),
         "tight box ends at bbox_max (e25adf2)": (VoxelGrid, "occupancy_from_cells", _box_at_the_last_vertex)}
VARIANTS_OF_A_FIX = ("default", "before")


def as_it_was(change: str, variant: str):
    """The code of ``change`` as ``variant`` ("default": today's; "before": its predecessor), a context manager."""
    return mock.patch.object(*FIXES[change]) if variant == "before" else nullcontext()


def _relative(value: torch.Tensor, reference: torch.Tensor) -> float:
    """max |value − reference| over the largest |reference| (0 where both are 0)."""
    scale = float(reference.abs().max())
    difference = float((value.double() - reference.double()).abs().max())
    return difference / scale if scale else difference


def _far_lines(rays, distance: float):
    """The edit's lines with float32 origins ``distance`` back along them, and the same (float32) lines' points 4
    units out, as the reference's origins: (far origins, near origins, unit directions)."""
    directions = torch.nn.functional.normalize(rays[1].double(), dim=-1).float()  # as given: float32
    far = (rays[0].double() - distance * directions.double()).float()
    return far, (far.double() + (distance - 4.0) * directions.double()).float(), directions


def _pearson_loss64(initial: torch.Tensor, edited: torch.Tensor, channels) -> tuple[float, torch.Tensor]:
    """The regulariser's value and gradient in float64 (1 − Pearson's r per channel: density + mean of colours)."""
    edited = edited.detach().double().requires_grad_(True)
    terms = []
    for c in channels:
        a, b = initial[..., c].double().reshape(-1), edited[..., c].reshape(-1)
        a, b = a - a.mean(), b - b.mean()
        terms.append(1 - (a * b).sum() / (a.norm() * b.norm()))
    loss = terms[0] + torch.stack(terms[1:]).mean() if len(terms) > 1 else terms[0]
    loss.backward()
    return float(loss.detach()), edited.grad


def rays_in_the_faces(grid: VoxelGrid) -> tuple[torch.Tensor, torch.Tensor]:
    """12 rays (origins, unit directions) lying in the faces of ``grid``'s box, through the middle of each face
    along each of its two axes, from 5 units before the box."""
    low, high = grid.bbox_min, grid.bbox_max
    origins, directions = [], []
    for axis in range(3):
        for face in (low[axis], high[axis]):
            for travel in {0, 1, 2} - {axis}:
                origin = (low + high) / 2
                origin[axis], origin[travel] = face, low[travel] - 5.0
                origins.append(origin)
                directions.append(torch.eye(3)[travel])
    return torch.stack(origins), torch.stack(directions)


def coloured_sphere(resolution: int) -> VoxelGrid:
    """edit_step's sphere with colours varying along x, y and z (reg3d_plus's colour terms are not constant)."""
    grid = sphere_grid(resolution)
    axis = torch.linspace(-1.0, 1.0, resolution)
    with torch.no_grad():
        for c in range(3):
            grid.features[..., 1 + c] = axis.view([-1 if d == c else 1 for d in range(3)])
    return grid


def measure_precision_fixes(repeats: int) -> list[dict]:
    """Per change of :data:`FIXES` and case: today's code and its predecessor timed in alternating pairs (the order
    flipped each round; wall and this process's CPU time), medians and each round's ratio before / default (median,
    min, max), beside each variant's error against a reference and the variants' differences (output and
    gradient). Cases without a timing hold the accuracy alone."""
    rays = edit_rays(EditConfig().render_size)
    sphere, fog = sphere_grid(160), fog_grid(96)
    config = EditConfig().render
    cases: dict[tuple[str, str], dict] = {}  # (change, case) -> {"run": callable or None, "outputs": per variant}

    def add(change: str, case: str, run, outputs, reference=None, inner: int = 1) -> None:
        cases[change, case] = {"run": run, "outputs": outputs, "reference": reference, "inner": inner}

    # (a) the edit's rays through the sphere (radius 4.03: none moved), and the same lines from 1e5 and 1e7 units
    far_rays = "far rays moved to the box (5db286d)"
    sphere.flat_features.requires_grad_(True)
    for distance in (None, *FAR):
        if distance is None:  # reference: today's render of the same rays
            label, lines = "sphere 160³: the edit's rays (none moved)", rays
            truth = render_once(sphere, rays, config)[:2]
        else:  # reference: the same float32 lines from 4 units out, today's render
            far, near, directions = _far_lines(rays, distance)
            label, lines = f"sphere 160³: the same lines from {distance:.0e}", (far, directions)
            truth = render_once(sphere, (near, directions), config)[:2]
        outputs = {}
        for v in VARIANTS_OF_A_FIX:
            with as_it_was(far_rays, v):
                outputs[v] = render_once(sphere, lines, config)[:2]
        add(far_rays, label, lambda lines=lines: backward(sphere, render(sphere, lines, config).rgb), outputs, truth)
    moved = {}
    for v in VARIANTS_OF_A_FIX:  # the origins the renderer goes on with
        with as_it_was(far_rays, v):
            moved[v] = render_module._moved_to_the_box(sphere, *rays)[0], None
    add(far_rays, f"the move alone: {rays[0].shape[0]:,} edit's rays", lambda: render_module._moved_to_the_box(
        sphere, *rays), moved, inner=10)  # (looked up when called: the patched one under "before")
    # (b) the edit's default regulariser (reg3d) and reg3d_plus at 160³, G_e = G_i + δ noise; δ = 0 is the first step
    regulariser = "correlation regulariser as ½‖â − b̂‖² (18e9312)"
    initial = coloured_sphere(160).features.detach()
    noise = torch.randn(initial.shape, generator=torch.Generator().manual_seed(0))
    for kind in ("reg3d", "reg3d_plus"):
        loss_of = volumetric_regulariser(kind, initial)  # G_i standardised once per edit: not timed
        for delta in (1e-4, 0.0, 1e-2):
            edited = (initial + delta * noise).requires_grad_(True)
            outputs = {}
            for v in VARIANTS_OF_A_FIX:
                with as_it_was(regulariser, v):
                    edited.grad = None
                    loss = loss_of(edited)
                    loss.backward()
                    outputs[v] = loss.detach().reshape(1), edited.grad.clone()
            value64, grad64 = _pearson_loss64(initial, edited, CORRELATED_CHANNELS[kind]) if delta else \
                (0.0, torch.zeros(edited.shape, dtype=torch.float64))  # G_e = G_i: exactly 0 and no gradient

            def step(loss_of=loss_of, edited=edited) -> None:
                edited.grad = None
                loss_of(edited).backward()

            # the cost does not depend on the values: timed once per kind
            add(regulariser, f"{kind} 160³: δ = {delta:g}", step if delta == 1e-4 else None, outputs,
                (torch.tensor([value64]), grad64), inner=3)
    # (c) the occupancy's box on both scenes, and rays lying in the faces of a 38-vertex grid
    tight_box = "tight box ends at bbox_max (e25adf2)"
    for label, grid in (("sphere 160³", sphere), ("fog 96³", fog)):
        cells = grid.occupancy(config.sigma_threshold).cells
        outputs = {}
        for v in VARIANTS_OF_A_FIX:
            with as_it_was(tight_box, v):
                box = grid.occupancy_from_cells(cells)
            outputs[v] = torch.cat([box.bbox_min, box.bbox_max]), None
        add(tight_box, f"occupancy_from_cells: {label}'s cells (box corners)",
            lambda grid=grid, cells=cells: grid.occupancy_from_cells(cells), outputs, inner=20)
    faces = VoxelGrid(38, init_density=0.05)  # its last vertex at -1.5 + 37 · 3/37 = 1.4999998 in float32
    faces.flat_features.requires_grad_(True)
    face_rays = rays_in_the_faces(faces)
    outputs = {}
    for v in VARIANTS_OF_A_FIX:
        with as_it_was(tight_box, v):
            out = render(faces, face_rays, config)
            outputs[v] = out.opacity.detach(), backward(faces, out.rgb).clone()
    unskipped = render(faces, face_rays, RenderConfig(**{**config.__dict__, "skip_empty": False}))
    add(tight_box, "38³ uniform grid: 12 rays in its faces (opacity)", None, outputs,
        (unskipped.opacity.detach(), backward(faces, unskipped.rgb).clone()))

    times = {(key, v, clock): [] for key in cases for v in VARIANTS_OF_A_FIX for clock in ("ms", "cpu_ms")}
    for round_ in range(-1, repeats):  # alternating pairs, the order flipped each round; round -1 warms up, untimed
        for key, case in cases.items():
            if case["run"] is None:
                continue
            for v in VARIANTS_OF_A_FIX[:: 1 if round_ % 2 == 0 else -1]:
                with as_it_was(key[0], v):
                    wall, cpu = time.perf_counter(), time.process_time()
                    for _ in range(case["inner"]):
                        case["run"]()
                    if round_ < 0:
                        continue
                    times[key, v, "ms"].append((time.perf_counter() - wall) * 1e3 / case["inner"])
                    times[key, v, "cpu_ms"].append((time.process_time() - cpu) * 1e3 / case["inner"])
    rows = []
    for (change, label), case in cases.items():
        default_out, default_grad = case["outputs"]["default"]
        for v in VARIANTS_OF_A_FIX:
            out, grad = case["outputs"][v]
            row = {"change": change, "case": label, "variant": v}
            for clock in ("cpu_ms", "ms"):
                mine, theirs = times[(change, label), v, clock], times[(change, label), "default", clock]
                ratios = [m / d for m, d in zip(mine, theirs)]
                row[clock] = statistics.median(mine) if mine else None
                row[f"{clock}_ratio_to_default"] = statistics.median(ratios) if ratios else None
                row[f"{clock}_ratio_min_max"] = [min(ratios), max(ratios)] if ratios else None
            truth = case["reference"]
            row["reference_value"] = float(truth[0]) if truth is not None and truth[0].numel() == 1 else None
            row["max_error"] = _relative(out, truth[0]) if truth is not None else None
            row["gradient_error"] = _relative(grad, truth[1]) if truth is not None and grad is not None else None
            row["max_difference_from_default"] = float((out.double() - default_out.double()).abs().max())
            row["gradient_difference_from_default"] = _relative(grad, default_grad) if grad is not None else None
            row["cpu_ms_each"], row["ms_each"] = times[(change, label), v, "cpu_ms"], times[(change, label), v, "ms"]
            rows.append(row)
    return rows


def plot_precision_fixes(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    changes = list(FIXES)
    fig, axes = plt.subplots(2, len(changes), figsize=(6.5 * len(changes), 8))
    for column, change in enumerate(changes):
        mine = [r for r in rows if r["change"] == change]
        labels = list(dict.fromkeys(r["case"] for r in mine))
        speed, error = axes[0, column], axes[1, column]
        timed = [r for r in mine if r["variant"] == "before" and r["cpu_ms"] is not None]
        for j, r in enumerate(timed):
            low, high = r["cpu_ms_ratio_min_max"]
            ratio = r["cpu_ms_ratio_to_default"]
            speed.bar(j, ratio, 0.6, color="C1", yerr=[[ratio - low], [high - ratio]], capsize=3)
            speed.annotate(f"×{ratio:.2f}", (j, high), ha="center", va="bottom", fontsize=7)
        speed.axhline(1.0, color="0.4", lw=0.8)
        speed.set_xticks(range(len(timed)), [r["case"].replace(": ", ":\n", 1) for r in timed], fontsize=6)
        speed.set_ylabel("CPU time before / default (median, bar: rounds' range)")
        speed.set_title(change, fontsize=9)
        width = 0.4
        for i, v in enumerate(VARIANTS_OF_A_FIX):
            vals = [next((r["max_error"] for r in mine if r["case"] == c and r["variant"] == v), None) for c in labels]
            x = [j + (i - 0.5) * width for j in range(len(labels))]
            shown = [max(e, 1e-12) if e is not None else 1e-12 for e in vals]
            error.bar(x, shown, width, color=f"C{0 if v == 'default' else 1}", label=v)
            for xi, e, s in zip(x, vals, shown):
                error.annotate("–" if e is None else f"{e:.1g}", (xi, s), ha="center", va="bottom", fontsize=6)
        error.set_yscale("log")
        error.set_ylim(1e-12, 1e7)
        error.set_xticks(range(len(labels)), [c.replace(": ", ":\n", 1) for c in labels], fontsize=6)
        error.set_ylabel("max error against the reference (relative)")
        error.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def record_precision_fixes(repeats: int, out: Path) -> list[dict]:
    """:func:`measure_precision_fixes`, one thread; saved to ``out`` with a plot."""
    torch.set_num_threads(1)
    load_before = os.getloadavg()[0]
    rows = measure_precision_fixes(repeats)
    record = {"description": "three float-precision changes of 2026-12-07 against their predecessors (far rays moved "
                             "to the box, the correlation regulariser as ½‖â − b̂‖², the tight box ending at bbox_max): "
                             "time in alternating pairs and accuracy; see bench/render_passes.py --precision-fixes",
              "machine": f"{os.cpu_count()} CPU cores, torch {torch.__version__}", "threads": torch.get_num_threads(),
              "load_average_before_after": [load_before, os.getloadavg()[0]], "repeats": repeats,
              "references": {"far rays": "the same float32 lines' render from 4 units out (today's code)",
                             "regulariser": "1 − Pearson's r in float64 of the same values, and its gradient",
                             "tight box": "the render without empty-space skipping (opacity, and the gradient)"},
              "runs": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    plot_precision_fixes(rows, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None,
                        help="default: results/render_passes.json, with --transmittance render_passes_transmittance.json, "
                             "with --precision-fixes render_passes_precision_fixes.json")
    parser.add_argument("--transmittance", action="store_true",
                        help="the packed transmittance against the prefix sum as it was: time and accuracy")
    parser.add_argument("--precision-fixes", action="store_true",
                        help="far rays moved to the box, the correlation regulariser as ½‖â − b̂‖² and the tight box "
                             "at bbox_max, each against its predecessor: time and accuracy")
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    if args.precision_fixes:
        rows = record_precision_fixes(args.repeats, args.out or HERE / "results" / "render_passes_precision_fixes.json")
        for r in rows:
            timing = "" if r["cpu_ms"] is None else (
                f"{r['cpu_ms']:8.1f} CPU ms (x{r['cpu_ms_ratio_to_default']:.2f}, rounds "
                f"x{r['cpu_ms_ratio_min_max'][0]:.2f}-{r['cpu_ms_ratio_min_max'][1]:.2f}; wall "
                f"x{r['ms_ratio_to_default']:.2f})")
            errors = "  ".join(f"{k} {r[k]:.1e}" for k in ("max_error", "gradient_error", "max_difference_from_default",
                                                           "gradient_difference_from_default") if r[k] is not None)
            print(f"{r['case']:52s} {r['variant']:7s} {timing:60s} {errors}")
        return 0
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
