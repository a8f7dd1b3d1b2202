"""Job parameters (the API's JSON, see api.schemas.JobParams) -> voxe_core stage configs: the one place presets resolve."""

from __future__ import annotations

import dataclasses
import hashlib
import json

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # voxe_core is imported where it is used, so importing this module stays light
    from voxe_core.edit import EditConfig
    from voxe_core.reconstruct import ReconstructConfig
    from voxe_core.refine import RefineConfig


def reconstruction_route(params: dict, mesh_scene: bool) -> str:
    """'fit' or 'voxelize': "auto" voxelizes a mesh scene (faster and closer to the mesh, bench/results/mesh_input.json)
    unless the scene backbone was asked for, and fits everything else."""
    rec = params.get("reconstruction") or {}
    route = rec.get("route", "auto")
    if route == "auto":
        return "voxelize" if mesh_scene and rec.get("backbone", "auto") != "scene" else "fit"
    return route


def reconstruction_params(params: dict, mesh_scene: bool = False) -> dict:
    """The part of a job's parameters that determines G_i (the reconstruction cache key)."""
    rec = dict(params.get("reconstruction") or {})
    # "auto" (and route "fit") add nothing, so jobs that leave them out and jobs that name them share a fit.
    backbone = {} if rec.get("backbone", "auto") == "auto" else {"backbone": rec["backbone"]}
    route = reconstruction_route(params, mesh_scene)
    return {
        **backbone,
        **({} if route == "fit" else {"route": route}),
        "split": "train",
        "downsample": int(params.get("downsample", 3)),
        "resample": params.get("resample", "bilinear"),
        "max_images": params.get("max_images"),
        "preset": rec.get("preset", "fast"),
        "resolution": rec.get("resolution"),
        "iterations": rec.get("iterations"),
        "rays_per_step": rec.get("rays_per_step"),
        "seed": int(rec.get("seed", 0)),
    }


def reconstruction_key(rec_params: dict) -> str:
    """A hash of the parameters and of the recipe they resolve to today, so that a fit cached
    before voxe_core's presets or defaults changed is refitted rather than reused.

    Raises ValueError for parameters that resolve to no recipe (as ``reconstruct_config``).
    """
    recipe = dataclasses.asdict(reconstruct_config(rec_params, checkpoint_every=0))
    # How often progress is saved and how much memory a pass may hold: not what is fitted.
    del recipe["checkpoint_every"], recipe["render"]["samples_per_pass"], recipe["render"]["chunk_rays"]
    payload = {"params": rec_params, "recipe": recipe}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def reconstruct_config(rec_params: dict, checkpoint_every: int) -> "ReconstructConfig":
    """As ``voxe reconstruct``: a preset, then the final resolution / iterations (one value or one per stage)."""
    from voxe_core.reconstruct import ReconstructConfig

    config = ReconstructConfig.fast() if rec_params["preset"] == "fast" else ReconstructConfig()
    n = len(config.resolutions)
    overrides: dict = {"seed": rec_params["seed"], "checkpoint_every": checkpoint_every}
    if rec_params.get("resolution") is not None:
        final = int(rec_params["resolution"])
        overrides["resolutions"] = tuple(
            [max(2, round(final * r / config.resolutions[-1])) for r in config.resolutions[:-1]] + [final]
        )
    iterations = rec_params.get("iterations")
    if iterations is not None:
        values = [iterations] if isinstance(iterations, int) else list(iterations)
        if len(values) == 1:
            values = [*config.iterations[:-1], values[0]]
        elif len(values) != n:
            raise ValueError(f"reconstruction.iterations takes one value or one per stage ({n} stages), got {len(values)}")
        overrides["iterations"] = tuple(values)
    if rec_params.get("rays_per_step") is not None:
        overrides["rays_per_step"] = int(rec_params["rays_per_step"])
    return dataclasses.replace(config, **overrides)


def edit_config(params: dict, checkpoint_every: int) -> "EditConfig":
    from voxe_core.edit import EditConfig
    from voxe_core.schedule import TimestepSchedule

    schedule = TimestepSchedule.authors() if params.get("timestep_schedule") == "authors" else TimestepSchedule()
    return EditConfig(
        iterations=params["iterations"],
        render_size=params["render_size"],
        guidance_scale=params["guidance_scale"],
        lr=params["lr"],
        regulariser=params["regulariser"],
        regulariser_weight=params["regulariser_weight"],
        schedule=schedule,
        batch_size=params.get("batch_size", 1),
        autocast_dtype=params.get("autocast"),
        seed=params["seed"],
        preview_every=params.get("preview_every", 0),
        checkpoint_every=checkpoint_every,
    )


def refine_config(params: dict, attention_model: str) -> "RefineConfig":
    from voxe_core.refine import RefineConfig

    refine = params.get("refine") or {}
    return RefineConfig(
        iterations=refine.get("iterations", 1500),
        lr=refine.get("lr", 0.035),
        tv_weight=refine.get("tv_weight", 0.01),
        render_size=refine.get("render_size") or params["render_size"],
        views=refine.get("views", 32),
        rays_per_step=refine.get("rays_per_step", 8192),
        edit_seeds=refine.get("edit_seeds", 300),
        object_seeds=refine.get("object_seeds", 200),
        sigma=refine.get("sigma", 0.1),
        smoothness=refine.get("smoothness", 5.0),
        seed=params["seed"],
        attention_model=attention_model,
    )
