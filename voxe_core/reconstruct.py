"""Stage 1: fit a voxel grid G_i to posed images (coarse-to-fine, L1, Adam).

Defaults are the authors' recipe (SPEC §1): 20³ → 40³ → 80³ → 160³ with
trilinear upsampling between stages, 500 iterations each, 32,768 rays per step
drawn from 8 random images (their data loader's batches), images downsampled
8/4/2/1, Adam lr 0.03 decayed ×0.9 per stage and ×0.1 at iteration 400 of each
stage. ``ReconstructConfig.fast()`` is the budget this project measured on a
2-core CPU (bench/reconstruction.py's preset-fast: mic 30.70 dB / SSIM 0.975
in 25 s, 47 CPU s, its six seeds 30.63–30.70 dB).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from voxe_core.backbones import grid_from_state
from voxe_core.cameras import Cameras, check_views, pixel_rays
from voxe_core.constants import FLOAT32_MAX, MAX_SEED
from voxe_core.devices import PeakMemory, full_precision, resolve_device
from voxe_core.grid import Activation, Occupancy, VoxelGrid
from voxe_core.losses import sampled_total_variation
from voxe_core.progress import Callbacks, Progress, StageCancelled
from voxe_core.render import RenderConfig, render_rays
from voxe_core.tensorio import FormatError, check_numbers, config_recipe, load_tensors, recipe_changes, save_tensors

CHECKPOINT_FORMAT_VERSION = 1
CHECKPOINT_KIND = "reconstruction_checkpoint"

PER_STAGE_FIELDS = ("resolutions", "iterations", "image_downsample")
"""ReconstructConfig's fields of one entry per stage (tuples, lists, arrays: any sequence)."""
COUNT_FIELDS = ("resolutions", "iterations", "image_downsample", "rays_per_step", "images_per_step",
                "lr_drop_iteration", "occupancy_every", "average_every", "tv_voxels", "seed", "checkpoint_every")
"""ReconstructConfig's fields that count (voxels, iterations, rays, images) or seed: whole numbers, per stage for
the tuples."""


class FitDiverged(ArithmeticError):
    """A reconstruction step's loss was NaN or infinite, or so were the grid's features where a checkpoint was to be
    written or a stage ended: steps past float32's range (an ``lr`` or ``color_lr_scale`` far beyond the recipe's)."""


@dataclass
class ReconstructConfig:
    resolutions: tuple[int, ...] = (20, 40, 80, 160)
    iterations: tuple[int, ...] = (500, 500, 500, 500)  # per stage
    image_downsample: tuple[int, ...] = (8, 4, 2, 1)  # per stage, relative to the given images
    rays_per_step: int = 32768
    # Each step's rays come from this many images drawn at random, as the authors' loader's batches of 8 images;
    # 0: from all images. The recipe on mic at 200 px (bench/reconstruction.py): 30.18 -> 31.07 dB at 32,768 rays,
    # 29.53-29.91 -> 30.41-30.46 dB at 4,096 over three seeds; fast() at 4,096 rays over six seeds 30.46 -> 30.68 dB,
    # its seeds' spread 0.69 -> 0.13 dB. scene() stays at 0: 8 cost fox 0.7 dB of validation PSNR
    # (bench/real_scenes_priors.py).
    images_per_step: int = 8
    lr: float = 0.03
    lr_stage_decay: float = 0.9
    lr_drop_iteration: int = 400  # within each stage
    lr_drop_factor: float = 0.1
    color_lr_scale: float = 1.0  # colour features' lr relative to ``lr`` (density keeps ``lr``)
    activation: Activation = "relu"
    init_density: float = 0.01
    bbox_min: tuple[float, float, float] = (-1.5, -1.5, -1.5)
    bbox_max: tuple[float, float, float] = (1.5, 1.5, 1.5)
    # No early-stop density pass: an object fit's rays end a few samples past the surface, so the pass kept 92 % of
    # mic's samples at 128³ and cost more than it saved (bench/reconstruction.py: preset-fast-4096-rays-all-images
    # against its -early-stop twin). scene() keeps it: fox's rays go on through the room, and it dropped half of them.
    render: RenderConfig = field(default_factory=lambda: RenderConfig(step_ratio=0.8, early_stop=0.0))
    occupancy_every: int = 16  # iterations between occupancy refreshes
    # Polyak averaging: from this fraction of the final stage on, the result is the mean of the
    # grid's iterates (one every ``average_every`` iterations) rather than the last one. 1.0: off.
    average_from: float = 1.0
    average_every: int = 8
    # Total variation of the raw features over occupied space (``losses.sampled_total_variation``),
    # weighted per channel group and estimated from ``tv_voxels`` voxels a step. The authors' recipe
    # has none (SPEC §1); a capture's few views need it (``scene()``).
    tv_density: float = 0.0
    tv_color: float = 0.0
    tv_voxels: int = 8192
    # Free space around the cameras: density stays 0 within this fraction of each camera's distance to
    # the grid frame's origin (a phone was there, so nothing opaque was). Few views cannot tell a far
    # room from a cloud just beside another camera's position, which then fills that view; 0: off.
    camera_clearance: float = 0.0
    seed: int = 0
    checkpoint_every: int = 0  # 0: no checkpoints

    def __post_init__(self):
        for name in PER_STAGE_FIELDS:  # (an int had failed len() below, a TypeError naming no setting)
            if isinstance(getattr(self, name), (numbers.Number, str)) or not isinstance(getattr(self, name), Iterable):
                raise ValueError(f"{name} takes one whole number per stage, got {getattr(self, name)!r}")
        n = len(self.resolutions)
        if not (len(self.iterations) == len(self.image_downsample) == n) or n == 0:
            raise ValueError(f"resolutions, iterations and image_downsample need one entry per stage, got "
                             f"{list(self.resolutions)}, {list(self.iterations)} and {list(self.image_downsample)}")
        # As EditConfig's: 2.5 rays, iterations or voxels (or True) had passed the range checks below and failed
        # inside the fit (a TypeError from torch.randint or range(), after the earlier stages' work), or run
        # (checkpoint_every 0.5: a checkpoint every step); a seed of 2**64 had overflowed the generator's seed.
        for name in COUNT_FIELDS:
            value = getattr(self, name)
            if any(isinstance(v, bool) or not isinstance(v, numbers.Integral)
                   for v in (value if name in PER_STAGE_FIELDS else (value,))):
                raise ValueError(f"{name} takes whole numbers, got {value!r}")
        # As RefineConfig's and EditConfig's: a string (YAML 1.1 reads 3e-2 as one) had failed a range test below naming
        # no setting ("'<' not supported between instances of 'int' and 'str'"), True had run as 1 (lr=True: lr 1),
        # and render=None failed at the fit's start ("'NoneType' object has no attribute 'skip_empty'").
        check_numbers(self, ("lr", "lr_stage_decay", "lr_drop_factor", "color_lr_scale", "init_density",
                             "average_from", "tv_density", "tv_color", "camera_clearance"))
        if not isinstance(self.render, RenderConfig):
            raise ValueError(f"render must be a RenderConfig, got {self.render!r}")
        if not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"seed must lie in [0, {MAX_SEED}] (the service's and the CLI's range), got {self.seed}")
        if self.rays_per_step < 1:
            raise ValueError(f"rays_per_step must be >= 1, got {self.rays_per_step}")
        if any(i < 0 for i in self.iterations):
            raise ValueError(f"iterations must be >= 0 per stage, got {list(self.iterations)}")
        if not any(self.iterations):  # (the untrained grid had been returned, stored and edited as the fit)
            raise ValueError(f"iterations are 0 in every stage ({list(self.iterations)}): the fit would take no step and "
                             "return its initial grid untrained (its init_density everywhere, a fog); give a stage "
                             "steps")
        if min(self.resolutions) < 2:  # as a grid's own refusal, but before any stage has run
            raise ValueError(f"grid resolutions must be at least 2, got {list(self.resolutions)}")
        if min(self.image_downsample) < 1:  # 0 had divided by zero after the earlier stages' work, -1 fitted 1x1 px
            raise ValueError(f"image_downsample must be >= 1 per stage (1: the images as given), "
                             f"got {list(self.image_downsample)}")
        # As "not in range" (NaN fails every comparison), in the float32 the steps are taken in: a NaN factor or
        # colour scale had made every feature NaN from its first step on, 1e39 had been inf there.
        if not 0 < self.lr <= FLOAT32_MAX:
            raise ValueError(f"lr must be positive and finite, got {self.lr}")
        for name in ("lr_stage_decay", "lr_drop_factor"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"{name} must lie in (0, 1] (a factor the lr is multiplied by), got "
                                 f"{getattr(self, name)}")
        if not 0 <= self.color_lr_scale <= FLOAT32_MAX or not abs(self.init_density) <= FLOAT32_MAX:
            raise ValueError(f"color_lr_scale must be >= 0 and init_density a number (both finite in float32), got "
                             f"{self.color_lr_scale} and {self.init_density}")
        if self.occupancy_every < 1 or self.checkpoint_every < 0:
            raise ValueError(f"occupancy_every must be >= 1 and checkpoint_every >= 0 (0: none), got "
                             f"{self.occupancy_every} and {self.checkpoint_every}")
        if self.images_per_step < 0:
            raise ValueError(f"images_per_step must be >= 0 (0: all images), got {self.images_per_step}")
        if not 0.0 <= self.average_from <= 1.0 or self.average_every < 1:
            raise ValueError(f"average_from must lie in [0, 1] and average_every be >= 1, got {self.average_from} "
                             f"and {self.average_every}")
        if not (0 <= self.tv_density <= FLOAT32_MAX and 0 <= self.tv_color <= FLOAT32_MAX) or self.tv_voxels < 1:
            raise ValueError(f"tv_density and tv_color must be >= 0 and finite, and tv_voxels >= 1, got "
                             f"{self.tv_density}, {self.tv_color} and {self.tv_voxels}")
        if not 0 <= self.camera_clearance < 1:
            raise ValueError(f"camera_clearance must lie in [0, 1), got {self.camera_clearance}")

    @classmethod
    def fast(cls, **overrides) -> "ReconstructConfig":
        """The CPU budget of the service: three stages, 1,000 steps of 8,192 rays from 8 images, lr 0.04 never dropped.

        The samples of the 2,000 steps of 4,096 rays at lr 0.03 it took before, in half the steps: on mic
        (bench/reconstruction.py's preset-fast against preset-fast-4096-rays, six seeds a side in one run) 30.67
        against 30.68 dB and 48.9 against 48.8 CPU s, and half the steps a launch-bound GPU pays for (a step there
        costs its dispatches, not its samples). At lr 0.03 the larger steps lost 0.08 dB; 16,384 rays × 500 steps
        lost 0.05 dB at lr 0.05 or 0.07 (scratch runs).

        bench/reconstruction.py's fast-160 adds ``average_from=0.5, color_lr_scale=0.5`` at
        40→80→160 (see bench/README.md); they stay off here because short fits (a few hundred
        iterations) lose more from averaging their early iterates than they gain.
        """
        base = dict(
            resolutions=(40, 80, 128),
            iterations=(150, 250, 600),
            image_downsample=(4, 2, 1),
            rays_per_step=8192,
            lr=0.04,
            lr_drop_iteration=1_000_000,
        )
        base.update(overrides)
        return cls(**base)

    @classmethod
    def scene(cls, **overrides) -> "ReconstructConfig":
        """The CPU budget for a scene-backbone fit of a capture (SPEC §5), what ``voxe reconstruct`` and jobs get
        for one by default: two stages 48³ → 96³, 2,048 rays per step, the final stage's second half averaged,
        total variation over occupied space and free space around the cameras.

        Sized on fox by bench/real_scenes.py (every 8th view held out, 16× downsampled; figures in
        bench/README.md "Real scenes"). Without the two priors fox's held-out PSNR stopped near 19–21 dB
        after ~200 final-stage iterations while the training views went on to 28 dB: a camera between two
        training views sat inside a cloud the fit had put there to paint the room seen past it. The weights
        were chosen on views split off the training set (never the held-out ones); with them fox's held-out
        PSNR is 26.1–26.3 dB over three seeds after 143–160 s of training on 2 CPU cores.
        """
        base = dict(
            resolutions=(48, 96),
            iterations=(300, 900),
            image_downsample=(2, 1),
            rays_per_step=2048,
            images_per_step=0,
            lr_drop_iteration=1_000_000,
            average_from=0.5,
            tv_density=1e-2,
            tv_color=5e-2,
            camera_clearance=0.4,
            render=RenderConfig(step_ratio=0.8, early_stop=RenderConfig.early_stop),
        )
        base.update(overrides)
        return cls(**base)

    def for_backbone(self, backbone: str) -> "ReconstructConfig":
        """This recipe drawn, rendered and regularised as a fit of a ``backbone`` grid needs: a capture's ("scene")
        rays go on through the room, so it keeps ``scene()``'s early-stop pass (half of fox's samples dropped),
        every-image draw (8 images cost fox 0.7 dB), lr and priors whichever budget it runs; an object's recipe is
        left as it is. Fitting fox with ``fast()`` as a capture (16× downsampled, seeds 0 / 1, held-out PSNR):

        * the lr: ``fast()``'s 0.04 was tuned on an object (mic); 19.60 / 20.68 dB at 0.04 against 22.00 / 21.49
          at 0.03 (the 4,096-ray recipe it replaced: 21.92 / 20.18; scratch runs);
        * the priors (total variation over occupied space, free space around the cameras): 26.49 / 26.19 dB with
          them against 22.01 / 21.50 without, in 1.08× / 1.13× the time (bench/capture_presets.py, each seed's
          pair side by side); the training views 29.3 / 29.0 against 29.9 / 30.4 dB: without them the fit paints
          the room seen past a camera into clouds in front of the others, as ``scene()``'s docstring tells.

        Examples:
            >>> fast = ReconstructConfig.fast()
            >>> capture = fast.for_backbone("scene")
            >>> (fast.images_per_step, fast.render.early_stop, fast.lr, fast.tv_density, fast.camera_clearance)
            (8, 0.0, 0.04, 0.0, 0.0)
            >>> (capture.images_per_step, capture.render.early_stop, capture.lr, capture.tv_density,
            ...  capture.camera_clearance)
            (0, 0.0001, 0.03, 0.01, 0.4)
        """
        if backbone != "scene":
            return self
        capture = ReconstructConfig.scene()
        return replace(self, images_per_step=capture.images_per_step, lr=capture.lr, tv_density=capture.tv_density,
                       tv_color=capture.tv_color, camera_clearance=capture.camera_clearance,
                       render=replace(self.render, early_stop=capture.render.early_stop))

    @property
    def total_iterations(self) -> int:
        return sum(self.iterations)

    def recipe(self) -> dict:
        """The fields a resumed fit must share with its checkpoint's, and a stored fit with its cache key
        (``presets.reconstruction_key``), as JSON values: every one but how often checkpoints are written and how
        much a render pass holds (the device's: a fit may resume on another worker)."""
        return config_recipe(self, ("checkpoint_every",))


def _stage_data(images: torch.Tensor, cameras: Cameras, downsample: int):
    """All rays and target colours of the images resampled for one stage, per image: origins, directions and
    colours, each (N, H·W, 3).

    Coarse stages average blocks of the loaded images (already antialiased by the loader's
    filter); the final stage (downsample 1) trains on the loaded images themselves.
    """
    n, h, w, _ = images.shape
    device = images.device
    height, width = max(1, h // downsample), max(1, w // downsample)
    if (height, width) != (h, w):
        images = F.interpolate(images.permute(0, 3, 1, 2), size=(height, width), mode="area").permute(0, 2, 3, 1)
    cams = cameras.resized(width, height)
    cam_index = torch.arange(n, device=device).repeat_interleave(height * width)
    v, u = torch.meshgrid(torch.arange(height, device=device) + 0.5, torch.arange(width, device=device) + 0.5,
                          indexing="ij")
    origins, directions = pixel_rays(cams, cam_index, u.reshape(-1).repeat(n), v.reshape(-1).repeat(n))
    return origins.view(n, -1, 3), directions.view(n, -1, 3), images.reshape(n, -1, 3).contiguous()


def ray_batch(config: ReconstructConfig, images: int, pixels: int, generator: torch.Generator,
              device: torch.device) -> torch.Tensor:
    """(rays_per_step,) indices into a stage's images·pixels rays, drawn with replacement from every image or,
    with ``config.images_per_step``, from that many distinct images drawn at random.

    Examples:
        >>> config = ReconstructConfig(rays_per_step=6, images_per_step=1)
        >>> batch = ray_batch(config, 4, 100, torch.Generator().manual_seed(0), torch.device("cpu"))
        >>> len(set((batch // 100).tolist()))  # all six from one image
        1
    """
    if not config.images_per_step or config.images_per_step >= images:
        return torch.randint(0, images * pixels, (config.rays_per_step,), generator=generator, device=device)
    chosen = torch.randperm(images, generator=generator, device=device)[: config.images_per_step]
    picks = torch.randint(0, config.images_per_step * pixels, (config.rays_per_step,), generator=generator,
                          device=device)
    return chosen[picks // pixels] * pixels + picks % pixels


def _sampling_generator(device: torch.device, seed: int) -> torch.Generator:
    """The seeded generator of ray batches and jitter, on the device they are drawn on (no host round trip)."""
    return torch.Generator(device=device).manual_seed(seed)


def _learning_rate(config: ReconstructConfig, stage: int, iteration: int) -> float:
    lr = config.lr * config.lr_stage_decay**stage
    return lr * config.lr_drop_factor if iteration >= config.lr_drop_iteration else lr


class RowSparseAdam(torch.optim.Optimizer):
    """Lazy Adam (as ``torch.optim.SparseAdam``) for one 2-D parameter with sparse row gradients.

    The L1 loss reaches the grid only through sampled points, so dense Adam
    would spend most of each step on empty space. Here a step costs the rows
    the batch touched: the gradient's entries are summed per distinct row, and
    only those rows' moments and values change. Moments of untouched rows are
    not decayed (the lazy-Adam semantics).
    """

    def __init__(
        self, param: torch.nn.Parameter, lr: float, betas=(0.9, 0.999), eps: float = 1e-8,
        column_lr_scale: torch.Tensor | None = None,
    ):
        super().__init__([param], dict(lr=lr, betas=betas, eps=eps))
        self.param = param
        self.column_lr_scale = column_lr_scale  # (C,) multiplier of each column's step, None: all 1
        state = self.state[param]
        state["step"] = 0
        state["exp_avg"] = torch.zeros_like(param)
        state["exp_avg_sq"] = torch.zeros_like(param)
        # Row -> scratch slot; lets a step find its distinct rows in time linear in the
        # gradient's entries instead of scanning every row of the grid.
        self._slot = torch.zeros(param.shape[0], dtype=torch.long, device=param.device)

    def _distinct_rows(self, index: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows, summed gradient per row) of an uncoalesced sparse gradient."""
        order = torch.arange(index.numel(), device=index.device)
        self._slot.scatter_(0, index, order)  # one writer per row wins, which one does not matter
        rows = index.masked_select(self._slot.index_select(0, index) == order)
        self._slot.index_copy_(0, rows, torch.arange(rows.numel(), device=index.device))
        # Summed column-major: index_add_ along the long axis is several times faster on the CPU.
        summed = values.new_zeros(values.shape[1], rows.numel())
        return rows, summed.index_add_(1, self._slot.index_select(0, index), values.t()).t()

    @torch.no_grad()
    def step(self, closure=None):
        grad = self.param.grad
        if grad is None:
            return None
        if grad.is_sparse:
            rows, g = self._distinct_rows(grad._indices()[0], grad._values())
        else:
            rows = torch.arange(self.param.shape[0], device=self.param.device)
            g = grad
        group, state = self.param_groups[0], self.state[self.param]
        beta1, beta2 = group["betas"]
        state["step"] += 1
        step = state["step"]
        m = state["exp_avg"].index_select(0, rows).mul_(beta1).add_(g, alpha=1 - beta1)
        v = state["exp_avg_sq"].index_select(0, rows).mul_(beta2).addcmul_(g, g, value=1 - beta2)
        state["exp_avg"].index_copy_(0, rows, m)
        state["exp_avg_sq"].index_copy_(0, rows, v)
        step_size = group["lr"] * (1 - beta2**step) ** 0.5 / (1 - beta1**step)
        update = m / v.sqrt().add_(group["eps"] * (1 - beta2**step) ** 0.5)
        if self.column_lr_scale is not None:
            update.mul_(self.column_lr_scale)
        # Rows are distinct, so a gather and a copy replace the (slower) scatter-add.
        self.param.index_copy_(0, rows, self.param.index_select(0, rows).add_(update, alpha=-step_size))
        return None


def make_optimizer(grid: VoxelGrid, config: ReconstructConfig, lr: float) -> RowSparseAdam:
    scale = None
    if config.color_lr_scale != 1.0:
        scale = torch.full((grid.flat_features.shape[1],), config.color_lr_scale, device=grid.flat_features.device)
        scale[0] = 1.0
    return RowSparseAdam(grid.flat_features, lr=lr, column_lr_scale=scale)


class _IterateAverage:
    """Running mean of the final stage's iterates: it cancels the batch noise the last iterate carries."""

    def __init__(self, config: ReconstructConfig, stage: int):
        self.start = int(config.average_from * config.iterations[-1])
        self.every = config.average_every
        self.active = config.average_from < 1.0 and stage == len(config.iterations) - 1
        self.total: torch.Tensor | None = None
        self.count = 0

    def after_step(self, grid: VoxelGrid, iteration: int) -> None:
        if self.active and iteration >= self.start and (iteration - self.start) % self.every == 0:
            features = grid.flat_features.detach()
            self.total = features.clone() if self.total is None else self.total.add_(features)
            self.count += 1

    def finish(self, grid: VoxelGrid) -> None:
        if self.count:
            with torch.no_grad():
                grid.flat_features.copy_(self.total / self.count)

    def state_tensors(self) -> dict[str, torch.Tensor]:
        if self.total is None:
            return {}
        return {"average_total": self.total, "average_count": torch.tensor([self.count])}

    def load(self, tensors: dict[str, torch.Tensor]) -> None:
        """Go on from a checkpoint's running sum, taken over (not copied: it is the average's own from here on); none
        when this stage averages nothing (a checkpoint older than recipes, resumed with averaging off)."""
        if self.active and "average_total" in tensors:
            self.total, self.count = tensors["average_total"], int(tensors["average_count"])


def train_step(
    grid: VoxelGrid,
    optimizer: RowSparseAdam,
    rays: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    config: ReconstructConfig,
    occupancy,
    generator: torch.Generator,
    clear_rows: torch.Tensor | None = None,
):
    """One iteration: ``config.rays_per_step`` rays drawn from ``rays`` (origins, directions and target colours,
    each (N, P, 3): N images of P pixels; :func:`ray_batch`), rendered with jitter, L1 loss, one optimizer step.
    Returns (losses, render output): losses ``l1`` (the photometric L1) and, with total variation on, ``tv`` (its
    weighted term) and ``total`` (their sum, the loss minimised), 0-d tensors.
    ``clear_rows`` (K,): feature rows whose density is then projected back to none (:func:`camera_clear_rows`).

    The whole of an iteration's cost, so bench/real_scenes.py times exactly this for both backbones.
    """
    origins, directions, targets = (r.reshape(-1, 3) for r in rays)
    batch = ray_batch(config, rays[2].shape[0], rays[2].shape[1], generator, targets.device)
    out = render_rays(grid, origins[batch], directions[batch], config.render, occupancy, generator, sparse_grad=True)
    loss = l1 = (out.rgb - targets[batch]).abs().mean()
    losses = {"l1": l1}
    if config.tv_density or config.tv_color:
        tv = sampled_total_variation(grid.flat_features, grid.resolution, occupancy.flat_cells(), config.tv_voxels,
                                     generator)
        tv = config.tv_density * tv[0] + config.tv_color * tv[1:].mean()
        loss = l1 + tv
        losses.update(tv=tv, total=loss)
    optimizer.zero_grad()
    # No sample in occupied space (e.g. an object-free, all-white scene whose density has
    # died): the batch rendered pure background, nothing here depends on the grid.
    if loss.requires_grad:
        with full_precision(loss):  # (under a caller's autocast the render's backward had run its products in bf16)
            loss.backward()
        optimizer.step()
    if clear_rows is not None and clear_rows.numel():
        with torch.no_grad():
            density = grid.flat_features[:, 0]
            density.index_copy_(0, clear_rows, density.index_select(0, clear_rows).clamp(max=grid.empty_raw_density))
    return losses, out


def camera_clear_rows(grid: VoxelGrid, cameras: Cameras, clearance: float) -> torch.Tensor | None:
    """The grid's feature rows within ``clearance`` × (camera's distance to the origin) of any camera; None when 0."""
    if not clearance:
        return None
    centres = cameras.c2w[:, :3, 3]
    return grid.rows_within(centres, clearance * centres.norm(dim=-1))


def check_finite_grid(grid: VoxelGrid, carried_into: str, what: str = "the initial grid",
                      where: str = "every step") -> None:
    """ValueError unless every feature of ``grid`` (``what``: a run's initial grid) is finite, naming how many vertices
    are not and what ``carried_into`` (its renders, a regulariser) would carry their NaN into (``where``: every step
    of the run)."""
    if nonfinite := int((~grid.features.detach().isfinite()).any(-1).sum()):
        raise ValueError(f"{what} has non-finite (NaN or infinite) features at {nonfinite} of its "
                         f"{math.prod(grid.resolution)} vertices, which {carried_into} would carry into {where} "
                         "(a damaged grid file?)")


def _diverged(config: ReconstructConfig, stage: int, done: int, what: str) -> str:
    return (f"the reconstruction diverged by iteration {done} (stage {stage + 1} of {len(config.resolutions)}): {what}; "
            f"its steps overflowed float32: lower lr or color_lr_scale (now {config.lr:g} and "
            f"{config.color_lr_scale:g}); not saved")


def check_fit_finite(grid: VoxelGrid, config: ReconstructConfig, stage: int, done: int) -> None:
    """FitDiverged unless every feature of the fit's grid is finite: a step whose loss was finite can still overflow
    its update (a NaN grid had been returned, saved and blamed on its file by the edit that refused it)."""
    if nonfinite := int((~grid.flat_features.detach().isfinite()).any(-1).sum()):
        raise FitDiverged(_diverged(config, stage, done, f"the grid holds NaN or infinite features at {nonfinite} of "
                                    f"its {grid.flat_features.shape[0]} vertices"))


def renders_nothing(grid: VoxelGrid, render: RenderConfig, skip_density: float | torch.Tensor | None = None) -> bool:
    """Whether every render of ``grid`` under ``render`` is the background: a ReLU field with no positive density
    anywhere (or, where empty cells are skipped, none above the skip threshold: ``skip_density``, where the caller
    has built it). No loss on its renders has a gradient then (ReLU's is 0 below 0, a skipped cell is never
    sampled), so no fitting step changes what it shows."""
    if not render.skip_empty:
        return grid.occupancy_above(0.0).empty
    return grid.occupancy_above(grid.skip_density(render.sigma_threshold) if skip_density is None else
                                skip_density).empty


def views_summary(images: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """What a checkpoint records of the views its fit sees, so that it resumes only a fit to them: per view (a row of
    the (N, 66) float64 result, (N, 72) with lens terms), its mean colour over a 4 x 4 grid of blocks, the image
    size and its camera (pose, focal lengths, principal point, lens terms).

    Values compared within a tolerance (:func:`same_views`), not a hash: a capture's images resampled on another
    worker differ in their last bits (torch's CPU vector paths), and a hash had refused such a worker its
    checkpoint. Another dataset, split, downsampling or image count differs far beyond them.
    """
    blocks = F.adaptive_avg_pool2d(images.detach().permute(0, 3, 1, 2), 4).flatten(1).to("cpu", torch.float64)
    size = torch.tensor([[cameras.width, cameras.height]], dtype=torch.float64).expand(len(images), 2)
    camera = [cameras.c2w[:, :3, :].flatten(1), cameras.fx[:, None], cameras.fy[:, None], cameras.cx[:, None],
              cameras.cy[:, None], *(() if cameras.distortion is None else (cameras.distortion,))]
    return torch.cat([blocks, size, *(part.detach().to("cpu", torch.float64) for part in camera)], dim=1)


def same_views(recorded: torch.Tensor, summary: torch.Tensor) -> bool:
    """Whether two :func:`views_summary` describe the same views (to 1e-4: far above the last bits of a float32 mean
    over a block, far below another image's)."""
    return recorded.shape == summary.shape and torch.allclose(recorded.double(), summary, rtol=1e-4, atol=1e-4)


def save_checkpoint(
    path, grid, optimizer, generator, occupancy_cells, stage: int, iteration: int, average: _IterateAverage | None = None,
    recipe: dict | None = None, views: torch.Tensor | None = None,
) -> None:
    """Everything a fit goes on from (grid, Adam's state, generator, occupancy, the iterate average), where it stands,
    the :meth:`ReconstructConfig.recipe` it was made with and the :func:`views_summary` of what it fits
    (tensorio, no pickle)."""
    state = optimizer.state[grid.flat_features]
    tensors = {
        **(average.state_tensors() if average is not None else {}),
        **grid.state_tensors(),
        "adam_exp_avg": state["exp_avg"],
        "adam_exp_avg_sq": state["exp_avg_sq"],
        "adam_step": torch.tensor([int(state["step"])]),
        "rng_state": generator.get_state(),
        "occupancy": occupancy_cells.to(torch.uint8),
        **({} if views is None else {"views": views}),
    }
    meta = {**grid.header(), "stage": stage, "iteration": iteration, "device": generator.device.type,
            **({} if recipe is None else {"recipe": recipe})}
    save_tensors(path, tensors, kind=CHECKPOINT_KIND, version=CHECKPOINT_FORMAT_VERSION, meta=meta)


def checkpoint_at_cancel(callbacks: Callbacks, stage: str, write: Callable[[], None]) -> None:
    """``write()`` the checkpoint a canceled stage takes of its steps since its last, as a best effort: one that cannot
    be written (the disk full, a service's storage refusing it or out of reach) is said (``callbacks.warning``; an
    OSError by its words, not its path), the earlier checkpoint standing, and the cancel stays a cancel. Raised, that
    error had replaced it: a service's job failed (and its shared fit), or given back to end canceled only later."""
    try:
        write()
    except Exception as exc:  # noqa: BLE001 - see the docstring
        words = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        callbacks.warning(stage, f"the checkpoint at the cancel could not be written ({type(exc).__name__}: {words}): "
                          "the earlier checkpoint stands")


def load_checkpoint(path) -> tuple[dict[str, torch.Tensor], dict]:
    """The tensors and header ``save_checkpoint`` wrote (``grid_from_state`` makes its grid)."""
    return load_tensors(path, kind=CHECKPOINT_KIND, max_version=CHECKPOINT_FORMAT_VERSION)


def _reseeded_generator(device: torch.device, seed: int, stage: int, iteration: int) -> torch.Generator:
    """The sampling generator of a fit resumed on another device type than its checkpoint's, whose generator state
    means nothing here (a CPU one is 5,056 bytes of Mersenne Twister, a CUDA one a 16-byte Philox seed and offset):
    seeded from the seed and where the fit stands, so that resume is reproducible, if not the uninterrupted run."""
    return _sampling_generator(device, hash((seed, stage, iteration)) % 2**63)


def _resume(path, config: ReconstructConfig, device: torch.device, views: torch.Tensor):
    """What a fit resumed from the checkpoint at ``path`` starts from: its grid, sampling generator, stage and
    iteration, and the optimizer, occupancy and average tensors its stage takes over (:func:`_take_over`), on
    ``device``. Nothing else of the file outlives the call. FormatError for a checkpoint that cannot be applied
    (the worker then starts the fit over, the CLI exits 2), such as one of a fit to other views than those of
    ``views`` (another dataset's, split's or downsampling's had gone on silently; a checkpoint older than
    the field resumes, as one older than recipes)."""
    tensors, meta = load_checkpoint(path)
    if "views" in tensors and not same_views(tensors["views"], views):
        raise FormatError(f"{path}: the checkpoint is of a fit to other images or cameras (another dataset, split, "
                          "downsampling or image count): resume with the views it was made from, or start afresh")
    grid = grid_from_state(tensors, meta)
    try:
        stage, iteration = int(meta["stage"]), int(meta["iteration"])
        if meta.get("device", device.type) == device.type:  # (a checkpoint older than the field: taken as this one's)
            generator = _sampling_generator(device, config.seed)
            generator.set_state(tensors["rng_state"])
        else:
            generator = _reseeded_generator(device, config.seed, stage, iteration)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:  # RuntimeError: a generator state of another size
        raise FormatError(f"{path}: damaged checkpoint: {type(exc).__name__}: {exc}") from None
    flat, cells = tuple(grid.flat_features.shape), tuple(r - 1 for r in grid.resolution)
    shapes = {"adam_exp_avg": flat, "adam_exp_avg_sq": flat, "adam_step": (1,), "occupancy": cells,
              **({"average_total": flat, "average_count": (1,)} if "average_total" in tensors else {})}
    for name, shape in shapes.items():  # checked here: a wrong one had failed deep inside the first step
        if name not in tensors or tuple(tensors[name].shape) != shape:
            found = f"shape {tuple(tensors[name].shape)}" if name in tensors else "nothing"
            raise FormatError(f"{path}: damaged checkpoint: its {name} holds {found}, not shape {shape}")
    # As an edit's resume: a NaN here had gone on through every step (a NaN cell is occupied, so rendered) and the
    # fit returned a NaN grid as its result. The rule an edit's save keeps: the first moment finite, the second in
    # [0, +inf] (a finite gradient whose square overflowed leaves +inf, which Adam goes on from). The sum holds at
    # least one iterate and at most one a step: a count of 0 had dropped the average silently, a negative one
    # negated the grid, 2.5 been taken as 2 and NaN failed the resume as a ValueError.
    averaged = "average_total" not in tensors or float(tensors["average_count"]).is_integer() \
        and 1 <= float(tensors["average_count"]) <= iteration
    finite = {"features": grid.flat_features.isfinite().all(), "adam_exp_avg": tensors["adam_exp_avg"].isfinite().all(),
              "adam_exp_avg_sq": (tensors["adam_exp_avg_sq"] >= 0).all(),
              "average_total": "average_total" not in tensors or tensors["average_total"].isfinite().all(),
              "average_count": averaged}
    if unresumable := [name for name, ok in finite.items() if not bool(ok)]:
        raise FormatError(f"{path}: checkpoint holds {', '.join(unresumable)} no fit leaves (NaN or infinite features, "
                          "first Adam moments or iterate sums, NaN or negative second moments, a count of iterates "
                          "summed that is not a whole number from 1 to the stage's iteration): damaged, or saved by "
                          "a run that had diverged; start afresh")
    stages = len(config.resolutions)
    if not (stage < stages and grid.resolution == (config.resolutions[stage],) * 3
            and iteration <= config.iterations[stage]):  # it had gone on with the checkpoint's grid
        raise FormatError(  # (as a damaged checkpoint: the worker starts the fit over, the CLI exits 2)
            f"{path}: the checkpoint is at iteration {iteration} of stage {stage} with a "
            f"{'x'.join(map(str, grid.resolution))} grid, which this recipe ({stages} stages, resolutions "
            f"{list(config.resolutions)}, iterations {list(config.iterations)}) does not reach: resume with the "
            "recipe that wrote it")
    # Another seed, lr, averaging, TV... had gone on silently; a checkpoint older than recipes resumes, as edit's.
    if changed := recipe_changes(path, meta, config):
        raise ValueError(f"{path}: checkpoint was made with another recipe: {', '.join(changed)}; resume with its "
                         "settings, or start afresh")
    state = {name: tensors[name].to(device) for name in shapes}
    return grid.to(device), generator, stage, iteration, state


def _take_over(state: dict[str, torch.Tensor], grid: VoxelGrid, optimizer: RowSparseAdam, average: _IterateAverage,
               iteration: int) -> Occupancy:
    """A resumed stage's Adam moments and iterate average from its checkpoint's tensors, handed over rather than
    copied (a copy beside them had held twice the grid's memory until the fit returned); returns its occupancy."""
    if iteration > 0:
        optimizer.state[grid.flat_features].update(
            step=int(state["adam_step"]), exp_avg=state["adam_exp_avg"], exp_avg_sq=state["adam_exp_avg_sq"])
    average.load(state)
    return grid.occupancy_from_cells(state["occupancy"].bool())


def reconstruct(
    images: torch.Tensor,
    cameras: Cameras,
    config: ReconstructConfig = ReconstructConfig(),
    callbacks: Callbacks = Callbacks(),
    checkpoint_path: str | Path | None = None,
    resume_from: str | Path | None = None,
    initial_grid: VoxelGrid | None = None,
    device: torch.device | str = "cpu",
) -> VoxelGrid:
    """Fit G_i to ``images`` (N, H, W, 3), floating-point RGB in [0, 1] on white, seen from ``cameras``.

    ``initial_grid`` (e.g. a ``SceneGrid`` at ``config.resolutions[0]``) replaces the fresh
    ReLU-field grid; its type, box and activation win over ``config.bbox_*`` and ``activation``.
    Everything runs on ``device``: images, cameras and the grid move there once, the rays of
    each stage are built there, and the sampling generator lives there (so CPU and CUDA runs
    of one seed draw different rays). The returned grid lives on ``device``. Progress losses
    are :func:`train_step`'s (``l1``; with total variation on, also ``tv`` and ``total``); its info
    carries the stage's peak memory (:class:`voxe_core.devices.PeakMemory`). ``resume_from``
    resumes on any device: a checkpoint written on another device type (CPU, CUDA) holds a
    generator state this one cannot take, so the run goes on drawing from a generator seeded
    from ``config.seed`` and where the checkpoint stands, reproducibly but not as the
    uninterrupted run would have (runs on two device types never draw alike). Cancellation is
    checked before each iteration (``StageCancelled``); with ``checkpoint_path`` set, a cancelled
    run writes a checkpoint before it stops (through ``callbacks``, as the periodic ones; a best effort:
    :func:`checkpoint_at_cancel`). A step whose loss is NaN or infinite, or a grid that is so where a stage ends or a
    checkpoint is due, is :class:`FitDiverged` (nothing returned or written).

    Determinism: a run is reproducible under ``config.seed`` on the CPU; on CUDA only as far as
    the kernels are deterministic: the compositing's and the gradients' scatter-adds
    (``index_add``) add atomically in any order, so runs differ at float32 rounding unless
    ``torch.use_deterministic_algorithms`` is on.
    """
    if images.shape[0] == 0:
        raise ValueError("no training images: a reconstruction needs at least one posed view")
    check_views(images, cameras)
    device = resolve_device(device)
    memory = PeakMemory(device).start()
    views = views_summary(images, cameras) if (checkpoint_path or resume_from) else None
    images, cameras = images.to(device, torch.float32), cameras.to(device)
    # As an edit's and a resume's: its NaN had gone on through every step (a NaN cell is occupied, so rendered) and
    # the fit returned a NaN grid as its result.
    if initial_grid is not None and resume_from is None:
        check_finite_grid(initial_grid, "its renders")
    if resume_from is None:
        start_stage, start_iteration, resumed = 0, 0, None
        generator = _sampling_generator(device, config.seed)
        grid = initial_grid if initial_grid is not None else VoxelGrid(
            config.resolutions[0], config.bbox_min, config.bbox_max, config.activation, init_density=config.init_density
        )
        # Looked at where the grid was made, before it moves: its steps had all been run, the grid left as it was.
        if renders_nothing(grid, config.render):
            hint = "" if initial_grid is not None else "; init_density <= 0?"
            raise ValueError("the fit's initial grid has no density its renders sample (a ReLU field with no positive "
                             f"density, or none above the render's sigma_threshold{hint}): no step of the fit would "
                             "have a gradient")
        grid = grid.to(device)
    else:
        grid, generator, start_stage, start_iteration, resumed = _resume(resume_from, config, device, views)

    def checkpoint(stage: int, iteration: int) -> None:
        check_fit_finite(grid, config, stage, done)  # (a cancel's too: its refusal is said, the earlier one stands)
        save_checkpoint(checkpoint_path, grid, optimizer, generator, occupancy.cells, stage, iteration, average,
                        config.recipe(), views)
        callbacks.checkpoint_written(str(checkpoint_path))

    total = config.total_iterations
    done = last_checkpoint = sum(config.iterations[:start_stage]) + start_iteration
    # A fit turned transparent (the fast preset on few views can drive every density below zero in its first coarse
    # steps) had run the rest of its stage and every later stage, the finest and dearest, with no gradient: it stops
    # at the stage start or the step that finds it so, (stage, steps of it run), its grid at the final resolution
    # as the steps left would have returned it.
    stopped_at = None
    for stage in range(start_stage, len(config.resolutions)):
        if grid.resolution != (config.resolutions[stage],) * 3:  # (a resumed grid is at its stage's: _resume)
            grid = grid.upsampled(config.resolutions[stage])
        # (The first stage run is the fit's start, checked above before the grid went to its device; a resumed stage
        # goes on as it was.)
        if stage > start_stage and renders_nothing(grid, config.render):
            stopped_at = (stage, 0)
            break
        optimizer = make_optimizer(grid, config, _learning_rate(config, stage, 0))
        average = _IterateAverage(config, stage)
        if resumed is None:
            first, occupancy = 0, grid.occupancy(config.render.sigma_threshold)
        else:  # the resumed stage: its state handed over, then no reference to the checkpoint's tensors is kept
            first, occupancy = start_iteration, _take_over(resumed, grid, optimizer, average, start_iteration)
            resumed = None
        rays = _stage_data(images, cameras, config.image_downsample[stage])
        clear_rows = camera_clear_rows(grid, cameras, config.camera_clearance)
        for iteration in range(first, config.iterations[stage]):
            try:
                callbacks.check_cancel("reconstruct")
            except StageCancelled:  # the steps since the last checkpoint are kept for a resume
                if checkpoint_path is not None and done != last_checkpoint:
                    checkpoint_at_cancel(callbacks, "reconstruct", lambda: checkpoint(stage, iteration))
                raise
            # Not at 0 (built just above); a run resumed on a refresh iteration refreshes as the uninterrupted one did.
            if iteration % config.occupancy_every == 0 and iteration > 0:
                occupancy = grid.occupancy(config.render.sigma_threshold)
            for group in optimizer.param_groups:
                group["lr"] = _learning_rate(config, stage, iteration)
            losses, out = train_step(grid, optimizer, rays, config, occupancy, generator, clear_rows)
            done += 1
            average.after_step(grid, iteration)
            values = dict(zip(losses, torch.stack([loss.detach() for loss in losses.values()]).tolist()))
            if not all(map(math.isfinite, values.values())):
                raise FitDiverged(_diverged(config, stage, done, f"its loss is {values}"))
            callbacks.progress(Progress(
                "reconstruct", done, total, values,
                {"stage": stage, "resolution": config.resolutions[stage],
                 "samples_per_ray": out.samples / config.rays_per_step, **memory.info()},
            ))
            if checkpoint_path is not None and config.checkpoint_every and done % config.checkpoint_every == 0:
                checkpoint(stage, iteration + 1)
                last_checkpoint = done
            # Within a stage, looked at only when the batch rendered nothing at all (a read of its opacity the
            # step's progress has already waited for; a full-grid check then), and not once the stage's iterates
            # are averaged: the steps left would still have weighed on the grid it returns.
            if not average.count and not bool(out.opacity.any()) and renders_nothing(grid, config.render):
                stopped_at = (stage, iteration + 1)
                break
        if stopped_at is not None:
            break
        average.finish(grid)
        check_fit_finite(grid, config, stage, done)
    if stopped_at is not None and grid.resolution != (config.resolutions[-1],) * 3:
        grid = grid.upsampled(config.resolutions[-1])
    if stopped_at is not None or renders_nothing(grid, config.render):  # its edit refuses it: said where it ran
        stopped = ""
        if stopped_at is not None:
            stopped_stage, steps = stopped_at
            within = f", after {steps} of its {config.iterations[stopped_stage]} steps" if steps else ""
            stopped = (f" (stopped at stage {stopped_stage + 1} of {len(config.resolutions)}{within}: none of the "
                       "steps left would have had a gradient)")
        callbacks.warning("reconstruct", "the fit ends with no density its renders sample (no positive density "
                          "anywhere, or none above the render's sigma_threshold): the reconstruction is transparent, "
                          "every render of it the background (views that show nothing but the background, or a fit "
                          f"that failed); an edit of it is refused{stopped}")
    return grid
