"""A job's progress across all its stages, and the time it has left, from measured stage costs.

Each stage's cost is its units of work (iterations, rendered views) times seconds per unit measured
by the benchmarks in ``bench/results`` (2 CPU cores, torch 2.13 CPU), the three records below re-run in one sitting (at
a8fc17f, the fit minutes after the others): only their ratios matter, so figures from different sittings would
misweigh the stages:

* reconstruct: 27.54 s / 1,000 iterations (``reconstruction.json``, the default fit ``ReconstructConfig.fast()`` on
  mic: the sitting's 27.47 s for the preset's 2,000 steps of 4,096 rays, now ``preset-fast-4096-rays``, times the CPU
  seconds of its 1,000 steps of 8,192 over those, 48.92 / 48.80 on the means of six seeds a side in one run);
* edit: 1.888 s per iteration (``edit_step.json``, the SD2-base-shaped UNet at 64 px: the real model's
  cost, not the smoke-test one's);
* refine: 1.54 s per attention pass (``edit_step.json``'s SD2-base-shaped run at 64 px: render + VAE + UNet
  forward, no backward; the SD-1.4-shaped attention UNet is of its size): one per view, and one more per fitting
  step from the back-projection start (each draws a fresh view, ``RefineConfig.fit_views``); the paper's fit from a
  constant (``lift_start`` constant) reuses the views' maps: 0.030 s per step (``segmentation.json``, runs[0]:
  12.2 s / 400 fixed-view steps at 96 px, 4,096 rays per step). The back-projection and the cut are small beside them;
* export: 0.093 s per rendered view (``reconstruction.json``, ``render_seconds_per_view`` at 200 px).

An edit is weighed by its job's ``iterations`` until G_i's kind is known, then by the count its schedule runs (a
capture's scene grid runs 5,000 where the parameters say the objects' 8,000): the reconstruct stage records it in
``Job.result["edit_schedule"]`` as it ends.

The fraction weighs completed stages fully and the current one by its own progress. The time left
is the current stage's own estimate (from its iteration rate) plus the later stages' costs, scaled
by how fast this machine ran the current stage against the benchmark's figure for it.

Examples:
    >>> weights = stage_costs(mode="global", params={"iterations": 100, "export": {"views": 0,
    ...                       "turntable_frames": 10, "mesh": False}}, reconstruction_units=900)
    >>> [(stage, round(seconds, 2)) for stage, seconds in weights]
    [('reconstruct', 24.78), ('edit', 188.75), ('export', 0.93)]
    >>> dict(stage_costs(mode="local", params={}, reconstruction_units=1))["refine"]  # 32 views, 0 fitting steps
    49.2672
"""

from __future__ import annotations

from voxe_core import constants as paper
from voxe_core.presets import ExportConfig

SECONDS_PER_UNIT = {
    "reconstruct": 27.47 * 48.92 / 48.80 / 1000,
    "edit": 1.8875,
    "refine": (170.4 + 138.8 + 1230.4) / 1000,  # an attention pass
    "refine_fixed_step": 12.198 / 400,  # a fitting step on the views' maps
    "export": 0.093,
    "evaluate": 0.093,  # ring renders dominate an evaluation
}
FAST_RECONSTRUCTION_ITERATIONS = 150 + 250 + 600  # ReconstructConfig.fast(): what a queued job expects


def stage_costs(*, mode: str, params: dict, reconstruction_units: int | None,
                edit_iterations: int | None = None) -> list[tuple[str, float]]:
    """(stage, expected seconds) for each stage of a job, in order; ``edit_iterations``: what the edit's schedule
    runs, once it is known (None: the parameters' count)."""
    if mode == "evaluate":
        views = (params.get("evaluation") or params).get("views", 100)
        return [("evaluate", views * SECONDS_PER_UNIT["evaluate"])]
    export = params.get("export") or {}
    views = export.get("views", ExportConfig.views) + export.get("turntable_frames", ExportConfig.turntable_frames)
    edit = next((n for n in (edit_iterations, params.get("iterations")) if n is not None), paper.EDIT_ITERATIONS)
    seconds = {
        "reconstruct": max(1, reconstruction_units or FAST_RECONSTRUCTION_ITERATIONS) * SECONDS_PER_UNIT["reconstruct"],
        "edit": max(1, edit) * SECONDS_PER_UNIT["edit"],
        "refine": refine_seconds(params.get("refine") or {}),
        "export": max(1, views + (1 if export.get("mesh", ExportConfig.mesh) else 0)) * SECONDS_PER_UNIT["export"],
    }
    stages = ["reconstruct", "edit"] + (["refine"] if mode == "local" else []) + ["export"]
    return [(stage, seconds[stage]) for stage in stages]


def refine_seconds(refine: dict) -> float:
    """The refinement's cost from the job parameters' ``refine``: an attention pass per view, and per fitting step
    one more pass from the back-projection start (fresh views) or a fixed-view step from the paper's constant
    start (``voxe_core.presets.refine_config`` pairs the two so)."""
    views = refine.get("views") or paper.REFINE_VIEWS
    steps = refine.get("iterations")
    steps = paper.SERVICE_REFINE_ITERATIONS if steps is None else steps
    if refine.get("lift_start") == "constant":
        return views * SECONDS_PER_UNIT["refine"] + steps * SECONDS_PER_UNIT["refine_fixed_step"]
    return (views + steps) * SECONDS_PER_UNIT["refine"]


def overall(*, costs: list[tuple[str, float]], completed: list[str], stage: str | None, stage_fraction: float,
            stage_eta_s: float | None, stage_elapsed_s: float | None, finished: bool) -> tuple[float, float | None]:
    """(overall progress in [0, 1], seconds left for the whole job or None when unknown).

    Examples:
        >>> costs = [("reconstruct", 10.0), ("edit", 80.0), ("export", 10.0)]
        >>> overall(costs=costs, completed=["reconstruct"], stage="edit", stage_fraction=0.5, stage_eta_s=20.0,
        ...         stage_elapsed_s=20.0, finished=False)  # edit ran at half the benchmark's time per unit
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
    speed = 1.0  # this machine's seconds per benchmark second, from the current stage
    if stage_elapsed_s and stage_fraction > 0 and current > 0:
        speed = stage_elapsed_s / (current * stage_fraction)
    return fraction, stage_eta_s + speed * sum(later)
