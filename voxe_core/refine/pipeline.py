"""The whole of SPEC §3 (:func:`refine`): maps -> attention grids -> graph cut -> merge (step 5)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch

from voxe_core.cameras import Cameras
from voxe_core.devices import PeakMemory, resolve_device
from voxe_core.grid import VoxelGrid
from voxe_core.guidance.prompts import edit_prompt, prompt_text
from voxe_core.progress import Callbacks, Progress, in_phases
from voxe_core.refine.config import RefineConfig
from voxe_core.refine.cut import GraphCutStats, graph_cut_detailed, graph_nodes, probabilities
from voxe_core.presets import backprojection_chunks
from voxe_core.refine.lifting import attention_occupancy, fit_attention_grids
from voxe_core.refine.maps import attention_cameras, attention_maps_2d, token_groups
from voxe_core.refine.storage import check_binary


@dataclass
class RefineResult:
    refined_grid: VoxelGrid
    mask: torch.Tensor  # (X, Y, Z) bool, True = take G_e
    nodes: torch.Tensor  # (X, Y, Z) bool: the cut's graph nodes, where the probabilities below mean something
    edit_probability: torch.Tensor  # (X, Y, Z) float32
    object_probability: torch.Tensor  # (X, Y, Z) float32
    edit_field: torch.Tensor  # (X, Y, Z, 1) fitted raw values
    object_field: torch.Tensor  # (X, Y, Z, 1)
    cameras: Cameras | None = None  # the poses the maps were taken from
    edit_maps: torch.Tensor | None = None  # (N, H, W) the 2D maps the grids were fitted to
    object_maps: torch.Tensor | None = None
    stats: GraphCutStats | None = None
    info: dict = field(default_factory=dict)


def check_compatible(initial_grid: VoxelGrid, edited_grid: VoxelGrid) -> None:
    """ValueError unless the two grids' raw values mean the same: the merge takes G_i's header (kind, activation,
    density scale; a scene grid's extent, frame, samples) for G_e's voxels too (a softplus edit merged into a ReLU
    grid had changed the edit's densities, a scene grid of another capture's extent or frame had moved them)."""
    if initial_grid.resolution != edited_grid.resolution:
        raise ValueError(f"the initial grid is {initial_grid.resolution} but the edited grid {edited_grid.resolution}")
    if not (torch.equal(initial_grid.bbox_min.cpu(), edited_grid.bbox_min.cpu())
            and torch.equal(initial_grid.bbox_max.cpu(), edited_grid.bbox_max.cpu())):
        raise ValueError(f"the initial grid spans the box {initial_grid.bbox_min.tolist()} to "
                         f"{initial_grid.bbox_max.tolist()} but the edited grid {edited_grid.bbox_min.tolist()} to "
                         f"{edited_grid.bbox_max.tolist()}: is the edit of another reconstruction?")
    if type(initial_grid) is not type(edited_grid):
        raise ValueError(f"the initial grid is a {type(initial_grid).__name__} but the edited grid a "
                         f"{type(edited_grid).__name__}")
    edited = edited_grid.header()
    for name, value in initial_grid.header().items():  # (a scene grid's extent, frame and samples too)
        if edited.get(name) != value:
            raise ValueError(f"the initial grid's {name} is {value!r} but the edited grid's {edited.get(name)!r}: is "
                             "the edit of another reconstruction?")


@torch.no_grad()
def merge(initial_grid: VoxelGrid, edited_grid: VoxelGrid, mask: torch.Tensor) -> VoxelGrid:
    """G_r = M·G_e + (1 − M)·G_i on all features, as a selection: unmasked voxels are G_i's exact bits."""
    check_compatible(initial_grid, edited_grid)
    if tuple(mask.shape) != tuple(initial_grid.resolution):
        raise ValueError(f"mask of shape {tuple(mask.shape)} does not fit the grids {initial_grid.resolution}")
    check_binary(mask)
    m = mask.to(device=initial_grid.features.device, dtype=torch.bool)[..., None]
    merged = torch.where(m, edited_grid.features.detach().to(initial_grid.features.device), initial_grid.features.detach())
    return initial_grid.like(merged)


def fresh_attention_views(guidance, grid: VoxelGrid, prompt: str, edit_words: Sequence[str], config: RefineConfig,
                          centre: torch.Tensor | None = None):
    """``fit_views="fresh"``'s source: per fit step one new random pose (looking at ``centre``) and its maps (one
    diffusion pass each).

    Poses and diffusion noise come from generators of their own (``config.seed`` + 1 and + 2), so the steps see
    neither the start's poses nor its noise again, and the noise is not drawn from the poses' stream.
    """
    poses = torch.Generator().manual_seed(int(config.seed) + 1)  # (torch refuses a numpy seed)
    noise = torch.Generator().manual_seed(int(config.seed) + 2)

    def fresh_view(step: int):
        camera = attention_cameras(config, poses, n=1, centre=centre)
        edit_map, object_map = attention_maps_2d(guidance, grid, camera, prompt, edit_words, config, generator=noise,
                                                 centre=centre)
        return camera, edit_map, object_map

    return fresh_view


def refine(
    initial_grid: VoxelGrid,
    edited_grid: VoxelGrid,
    prompt: str,
    edit_words: Sequence[str],
    guidance,
    config: RefineConfig = RefineConfig(),
    callbacks: Callbacks = Callbacks(),
    device: torch.device | str | None = None,
) -> RefineResult:
    """The whole of SPEC §3: maps -> attention grids -> graph cut -> merge.

    ``prompt`` is the edit's text; the "a render of" prefix is added when
    missing (as the edit stage prompts the model). ``edit_words`` name the
    edit (words or phrases of the prompt, e.g. ``["sunglasses"]`` or
    ``["party hat"]``): ValueError when one is not in ``prompt`` or no other word of it is left to name the object.

    The attention renders, the attention-grid fit and the graph cut's inputs run
    on ``device`` (None: the guidance's, else the edited grid's); both grids are
    moved there once (in place, as ``nn.Module.to``). The last progress report
    carries the stage's peak memory (:class:`voxe_core.devices.PeakMemory`).
    """
    check_compatible(initial_grid, edited_grid)
    device = resolve_device(device if device is not None else getattr(guidance, "device", edited_grid.bbox_min.device))
    memory = PeakMemory(device).start()
    initial_grid, edited_grid = initial_grid.to(device), edited_grid.to(device)
    text = edit_prompt(prompt)
    # Fail on a bad word before rendering anything, read in the user's own text as the model reads it: in ``text``
    # the prefix this stage adds had supplied an edit word ("render") or the words naming the object (a prompt of
    # the edit words alone; its trailing full stop, which the model never reads, too).
    token_groups(guidance, prompt_text(prompt), edit_words)
    attention_occupancy(edited_grid, config)  # and on an empty one
    nodes = graph_nodes(edited_grid, config)  # and on a NaN density, or none the cut's rule counts
    centre = initial_grid.orbit_centre()  # G_i's: the object, wherever it sits
    cameras = attention_cameras(config, centre=centre)
    fresh_view = fresh_attention_views(guidance, edited_grid, text, edit_words, config, centre) \
        if config.fit_views == "fresh" else None
    lift = backprojection_chunks(len(cameras), cameras.height, cameras.width, config.backprojection_stride,
                                 config.render.chunk_rays)
    callbacks = in_phases(callbacks, {"attention_maps": len(cameras), "backprojection": lift,
                                      "attention_grids": config.iterations, "graph_cut": 1})  # one scale: only rises
    edit_maps, object_maps = attention_maps_2d(guidance, edited_grid, cameras, text, edit_words, config, callbacks,
                                               centre=centre)
    edit_field, object_field = fit_attention_grids(edited_grid, cameras, edit_maps, object_maps, config, callbacks,
                                                   fresh_view)
    callbacks.check_cancel("graph_cut")
    mask, stats = graph_cut_detailed(edited_grid, edit_field, object_field, config)
    p_e, p_o = probabilities(edit_field, object_field)
    refined = merge(initial_grid, edited_grid, mask)
    callbacks.progress(Progress("graph_cut", 1, 1, info={"stage": "graph cut", "nodes": stats.nodes,
                                                        "edit_voxels": stats.edit_voxels, **memory.info()}))
    return RefineResult(
        refined, mask, nodes, p_e, p_o, edit_field, object_field, cameras, edit_maps, object_maps, stats,
        info={"prompt": text, "edit_words": list(edit_words) if not isinstance(edit_words, str) else [edit_words]},
    )
