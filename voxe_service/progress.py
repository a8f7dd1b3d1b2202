"""A job's progress across all its stages, and the time it has left, from measured stage costs.

Each stage's cost is its units of work (fit steps, iterations, rendered views) times seconds per unit on the kind
of device the job runs on (``Job.device``: the worker's). Only the ratios between stages matter, so each table's
stage figures come from one sitting (the CPU's capture factor is a ratio within its own run):

* ``cpu`` (2 CPU cores, torch 2.13 CPU; ``bench/results``), the records re-run at a8fc17f (the fit minutes after
  the others):

  * reconstruct: 27.54 s / 1,000 steps of 8,192 rays (``reconstruction.json``, the default fit
    ``ReconstructConfig.fast()`` on mic: the sitting's 27.47 s for the preset's 2,000 steps of 4,096 rays, now
    ``preset-fast-4096-rays`` (seed 0 as 469c52a recorded it; the file now holds its rerun at 04459e1), times
    the CPU seconds of its 1,000 steps of 8,192 over those, 48.92 / 48.80 on the
    means of six seeds a side in one run). A CPU step costs its rays (``fit_costs.json``: ``paper``'s steps of
    4× the rays cost 3.79× ``fast``'s in one run), a capture's 17.9× an object's per ray (``scene()`` on fox
    against ``fast()`` on mic in that run: its rays cross the scene's background too);
  * edit: 1.888 s per iteration (``edit_step.json``, the SD2-base-shaped UNet at 64 px: the real model's
    cost, not the smoke-test one's);
  * refine: 1.54 s per attention pass (``edit_step.json``'s SD2-base-shaped run at 64 px: render + VAE + UNet
    forward, no backward; the SD-1.4-shaped attention UNet is of its size): one per view, and one more per
    fitting step from the back-projection start (each draws a fresh view, ``RefineConfig.fit_views``); the
    paper's fit from a constant (``lift_start`` constant) reuses the views' maps: 0.030 s per step
    (``segmentation.json``, runs[0]: 12.2 s / 400 fixed-view steps at 96 px, 4,096 rays per step). The
    back-projection and the cut are smaller (a tenth of the service's default refinement, 5% of the paper's fit):
    a back-projection chunk of 32,768 rays as 8.83 of those steps (0.4156 s a chunk against 0.04706 s a step, one
    sitting at 1 thread: ``fit_attention_grids`` on a 64³ sphere, 24 views of 192 px, 4,096 rays a step), the cut
    0.465 s (``segmentation.json``, ``graph_160``: 207,078 nodes, build and solve);
  * export: 0.093 s per rendered view (``reconstruction.json``, ``render_seconds_per_view`` at 200 px).

* ``cuda`` (one H200, full-size random-weight models): one local-edit job through the worker
  (``gpu.json``, section f of call 5): reconstruct 26.1 s for 2,000 steps (``fast`` then: 4,096 rays), edit
  27.5 s for 500 iterations, refine 6.3 s for 32 attention passes, 18 back-projection chunks (32 views of 266²)
  and the cut (a pass: what is left once those two are weighed as below), export 1.7 s for 35 views (4 renders,
  30 turntable frames, the mesh). A GPU step costs its dispatches, not its rays (call 4: ``fast``'s 2,000 steps of
  4,096 rays in 22.9 s, ``paper``'s 2,000 of 32,768 in 22.2 s). Unmeasured there: a capture's fit step (taken
  as an object's), the fixed-view refinement step (taken as a fit step: rays rendered, a loss, Adam), a
  back-projection chunk (taken as a fit step too), the cut (taken as the CPU's: max-flow runs on the host) and an
  evaluation (taken as the export's renders; its CLIP and FID scorers are not counted).

A device this module does not know (``mps``) is weighed as a CPU. A job's stages are all weighed by the device of
the one running: one whose stages move between kinds of device (a mixed pool) is weighed anew, and its fraction
can step back when it moves (a fit done on a GPU weighs far less against a CPU's edit).

A fit is weighed by what it runs (``FitWork``): the recipe the worker records in ``Job.result["fit"]`` as the
fit starts (or as the job starts waiting for another job's fit), else the one the reconstruction's parameters
resolve to (a backbone "auto" before a worker has recorded it: an object's). An edit is weighed by its job's
``iterations`` until G_i's kind is known, then by the count its schedule runs (a capture's scene grid runs 5,000
where the parameters say the objects' 8,000): the reconstruct stage records it in ``Job.result["edit_schedule"]``
with the fit (a finished fit reused: as the stage ends).

The fraction weighs completed stages fully and the current one by the share of its time done (``stage_fraction``:
its units', but the refinement's sub-steps each weighed by their cost a unit). The time left is the
current stage's own estimate (from its iteration rate) plus the later stages' costs, scaled by how fast this
machine runs the current stage against the table's figure for it: the stage's estimate over the table's seconds
for what is left of it. The worker measures that rate from the stage's first progress report, so the time a
stage spends before its first unit of work (loading a model, compiling the encoder, the iterations a resumed
run starts past) does not inflate it. Not while fitting, whose cost per step depends on the scene (how many
samples its rays keep: a capture's ray costs 17.9× an object's), which the later stages' costs do not.

Examples:
    >>> work = FitWork(steps=900, rays_per_step=8192, backbone="relu_field")
    >>> costs = stage_costs(mode="global", params={"iterations": 100, "export": {"views": 0,
    ...                     "turntable_frames": 10, "mesh": False}}, fit=work)
    >>> [(stage, round(seconds, 2)) for stage, seconds in costs]
    [('reconstruct', 24.78), ('edit', 188.75), ('export', 0.93)]
    >>> [(stage, round(seconds, 2)) for stage, seconds in stage_costs(mode="global", params={"iterations": 100,
    ...  "export": {"views": 0, "turntable_frames": 10, "mesh": False}}, fit=work, device="cuda:0")]
    [('reconstruct', 11.76), ('edit', 5.5), ('export', 0.48)]
    >>> round(dict(stage_costs(mode="local", params={}, fit=NO_FIT))["refine"], 2)  # 32 passes, 18 chunks, the cut
    54.58
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

from voxe_core import constants as paper
from voxe_core.presets import BACKBONE_KINDS, ExportConfig, fit_backbone, reconstruct_config, refine_phase_units


class FitWork(NamedTuple):
    """What a job's fit runs: its steps, the rays each draws and the backbone it fits (a capture's rays cost more)."""

    steps: int
    rays_per_step: int
    backbone: str


NO_FIT = FitWork(0, 0, "relu_field")
"""A job that reused a finished fit: nothing to fit or wait for."""


@dataclass(frozen=True)
class DeviceCosts:
    """Seconds per unit of work of each stage on one kind of device, measured in one sitting."""

    fit_step: float
    """A step of ``ReconstructConfig.fast()``'s fit of an object."""
    fit_rays: int | None
    """The rays that step drew, when a step costs its rays (a CPU); None: a step costs its dispatches (a GPU)."""
    edit: float
    refine: float
    """An attention pass."""
    refine_fixed_step: float
    """A fitting step on the views' maps."""
    backprojection_chunk: float
    """A chunk of the refinement's back-projection (``RenderConfig.chunk_rays`` rays)."""
    graph_cut: float
    """The refinement's graph cut."""
    export: float
    """A rendered view (or the mesh)."""
    evaluate: float
    """A rendered view: ring renders dominate an evaluation."""
    fit_backbone: dict[str, float] = field(default_factory=dict)
    """A step's cost over an object's of as many rays, per backbone (others: 1)."""

    def fit_seconds(self, fit: FitWork) -> float:
        step = self.fit_step * self.fit_backbone.get(fit.backbone, 1.0)
        if self.fit_rays is not None:
            step *= fit.rays_per_step / self.fit_rays
        return fit.steps * step


CPU_FIT_STEP = 27.47 * 48.92 / 48.80 / 1000
# fit_costs.json: scene() on fox (133.48 s for 1,200 steps of 2,048 rays) against fast() on mic (23.33 and 26.28 s
# for 1,000 of 8,192, before and after it), per ray of a step, in one run.
SCENE_OVER_OBJECT_RAY = (133.48 / 1200 / 2048) / ((23.33 + 26.28) / 2 / 1000 / 8192)
CUDA_FIT_STEP = 26.137 / 2000
CPU_REFINE_FIXED_STEP = 12.198 / 400
CPU_GRAPH_CUT = 0.465
# The H200 job's refinement less its 18 back-projection chunks and its cut (weighed as below), over its 32 passes.
CUDA_REFINE_PASS = (6.320 - 18 * CUDA_FIT_STEP - CPU_GRAPH_CUT) / 32
DEVICE_COSTS = {
    "cpu": DeviceCosts(
        fit_step=CPU_FIT_STEP, fit_rays=8192, edit=1.8875,
        refine=(170.4 + 138.8 + 1230.4) / 1000, refine_fixed_step=CPU_REFINE_FIXED_STEP,
        backprojection_chunk=CPU_REFINE_FIXED_STEP * 0.4156 / 0.04706, graph_cut=CPU_GRAPH_CUT, export=0.093,
        evaluate=0.093, fit_backbone={"scene": SCENE_OVER_OBJECT_RAY},
    ),
    "cuda": DeviceCosts(
        fit_step=CUDA_FIT_STEP, fit_rays=None, edit=27.496 / 500, refine=CUDA_REFINE_PASS,
        refine_fixed_step=CUDA_FIT_STEP, backprojection_chunk=CUDA_FIT_STEP, graph_cut=CPU_GRAPH_CUT,
        export=1.678 / 35, evaluate=1.678 / 35,
    ),
}


def device_costs(device: str) -> DeviceCosts:
    """The table for a device string as a worker records it ("cpu", "cuda", "cuda:1"; unknown kinds: the CPU's)."""
    return DEVICE_COSTS.get(device.split(":")[0], DEVICE_COSTS["cpu"])


def fit_work(rec_params: dict, recorded: dict | None = None, steps: int | None = None) -> FitWork:
    """What the fit of ``rec_params`` runs: as the worker ``recorded`` it (``Job.result["fit"]``), else as the
    parameters resolve (a backbone "auto": an object's recipe), with ``steps`` once the fit has reported them.

    Examples:
        >>> fit_work({"preset": "paper"})
        FitWork(steps=2000, rays_per_step=32768, backbone='relu_field')
        >>> fit_work({"iterations": [100, 200]}, steps=40)  # only a capture's preset has two stages
        FitWork(steps=40, rays_per_step=2048, backbone='scene')
    """
    if recorded and {"steps", "rays_per_step", "backbone"} <= recorded.keys():
        work = FitWork(recorded["steps"], recorded["rays_per_step"], recorded["backbone"])
    elif rec_params.get("route") == "voxelize":  # one step reported at completion, weighed as one fit step
        work = FitWork(1, DEVICE_COSTS["cpu"].fit_rays, "relu_field")
    else:
        work = _resolved_fit(rec_params)
    return work if steps is None else work._replace(steps=steps)


def _resolved_fit(rec_params: dict) -> FitWork:
    """The recipe ``rec_params`` resolve to for the first backbone that takes them ("auto": an object's, unless only a
    capture's does); parameters that resolve to none (stored before a preset changed) weigh as the default fit."""
    asked = fit_backbone(rec_params)
    for backbone in BACKBONE_KINDS if asked == "auto" else (asked,):
        try:
            config = reconstruct_config(rec_params, backbone=backbone)
        except (ValueError, TypeError):
            continue
        return FitWork(config.total_iterations, config.rays_per_step, backbone)
    return _resolved_fit({})


def stage_costs(*, mode: str, params: dict, fit: FitWork, device: str = "cpu",
                edit_iterations: int | None = None) -> list[tuple[str, float]]:
    """(stage, expected seconds on ``device``) for each stage of a job, in order; ``edit_iterations``: what the
    edit's schedule runs, once it is known (None: the parameters' count)."""
    costs = device_costs(device)
    if mode == "evaluate":
        views = (params.get("evaluation") or params).get("views", 100)
        return [("evaluate", views * costs.evaluate)]
    export = params.get("export") or {}
    views = export.get("views", ExportConfig.views) + export.get("turntable_frames", ExportConfig.turntable_frames)
    edit = next((n for n in (edit_iterations, params.get("iterations")) if n is not None), paper.EDIT_ITERATIONS)
    seconds = {
        "reconstruct": costs.fit_seconds(fit),
        "edit": max(1, edit) * costs.edit,
        "refine": refine_seconds(params, costs),
        "export": max(1, views + (1 if export.get("mesh", ExportConfig.mesh) else 0)) * costs.export,
    }
    stages = ["reconstruct", "edit"] + (["refine"] if mode == "local" else []) + ["export"]
    return [(stage, seconds[stage]) for stage in stages]


def refine_seconds(params: dict, costs: DeviceCosts) -> float:
    """The refinement's cost from the job parameters: every phase it reports (``refine_phase_units``: an attention
    pass per view, the back-projection's chunks, the fitting steps, the cut) times its cost a unit."""
    phases = refine_phase_seconds(_fit_views(params), costs)
    return sum(units * phases[phase] for phase, units in refine_phase_units(params).items())


def _fit_views(params: dict) -> str:
    """``RefineConfig.fit_views`` of the job parameters: the paper's constant start fits on its views' maps
    (``voxe_core.presets.refine_config`` pairs the two so), the back-projection start on a fresh view a step."""
    return "fixed" if (params.get("refine") or {}).get("lift_start") == "constant" else "fresh"


def refine_phase_seconds(fit_views: str, costs: DeviceCosts) -> dict[str, float]:
    """Seconds per unit of each of the refinement's sub-steps (``voxe_core.refine.pipeline.refine``'s phases), its
    fitting steps by ``RefineConfig.fit_views``: a fresh view's step is an attention pass, a fixed one's 1/50 of one
    on a CPU, so the time left in the stage weighs each sub-step's units left by them.

    Examples:
        >>> phases = refine_phase_seconds("fixed", DEVICE_COSTS["cpu"])
        >>> round(phases["attention_maps"] / phases["attention_grids"])
        50
    """
    return {"attention_maps": costs.refine, "backprojection": costs.backprojection_chunk,
            "attention_grids": costs.refine if fit_views == "fresh" else costs.refine_fixed_step,
            "graph_cut": costs.graph_cut}


def stage_fraction(*, stage: str | None, params: dict, device: str, iteration: int, total: int) -> float:
    """The share of the current stage's time done at ``iteration`` of its ``total`` units: the units' share, but for
    the refinement, whose sub-steps count on one scale (``voxe_core.progress.in_phases``: attention passes,
    back-projection chunks, fitting steps, the cut) at very different costs a unit (``refine_phase_seconds``: a
    pass is 50 of the paper's fixed-view steps on a CPU), each weighed by its cost: counted in units, the paper's
    fit was 2% done when its passes, half its time, were. A scale other than its parameters give (a worker of
    another version) counts units.

    Examples:
        >>> paper_fit = {"refine": {"lift_start": "constant", "iterations": 1500}}  # 32 passes, 18 chunks, the cut
        >>> round(stage_fraction(stage="refine", params=paper_fit, device="cpu", iteration=32, total=1551), 2)
        0.49
        >>> stage_fraction(stage="edit", params=paper_fit, device="cpu", iteration=32, total=1551) == 32 / 1551
        True
    """
    if total <= 0:
        return 0.0
    units = min(iteration, total) / total
    if stage != "refine":
        return units
    sizes = refine_phase_units(params)
    if sum(sizes.values()) != total:
        return units
    done = whole = 0.0
    left = min(iteration, total)
    phase_seconds = refine_phase_seconds(_fit_views(params), device_costs(device))
    for phase, size in sizes.items():
        done += min(size, max(0, left)) * phase_seconds[phase]
        whole += size * phase_seconds[phase]
        left -= size
    return done / whole


def overall(*, costs: list[tuple[str, float]], completed: list[str], stage: str | None, stage_fraction: float,
            stage_eta_s: float | None, finished: bool) -> tuple[float, float | None]:
    """(overall progress in [0, 1], seconds left for the whole job or None when unknown).

    Examples:
        >>> costs = [("reconstruct", 10.0), ("edit", 80.0), ("export", 10.0)]
        >>> overall(costs=costs, completed=["reconstruct"], stage="edit", stage_fraction=0.5, stage_eta_s=20.0,
        ...         finished=False)  # edit runs at half the benchmark's time per unit: 20 s left of its 40
        (0.5, 25.0)
    """
    if finished:
        return 1.0, 0.0
    total = sum(seconds for _, seconds in costs) or 1.0
    done = sum(seconds for name, seconds in costs if name in completed)
    current = dict(costs).get(stage, 0.0) if stage not in completed else 0.0
    fraction = min(1.0, max(0.0, (done + current * stage_fraction) / total))
    if stage is None or stage_eta_s is None:
        return fraction, None
    later = [seconds for name, seconds in costs if name not in completed and name != stage]
    speed = 1.0  # this machine's seconds per benchmark second, from the current stage (not a fit: its scene sets it)
    left = current * (1.0 - stage_fraction)  # the table's seconds for the rest of the stage (none: no rate to scale)
    if stage != "reconstruct" and left > 0:
        speed = stage_eta_s / left
    return fraction, stage_eta_s + speed * sum(later)
