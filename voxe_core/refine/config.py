"""The refinement's hyper-parameters (SPEC §3) and its one error."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Literal

from voxe_core.cameras import check_angle, check_fov_x, check_render_size
from voxe_core.constants import (
    ATTENTION_MODEL_ID,
    CUT_SIGMA,
    CUT_SMOOTHNESS,
    DEFAULT_ATTENTION_TIMESTEP,
    DIFFUSION_TIMESTEPS,
    EDIT_SEEDS,
    FLOAT32_MAX,
    MAX_REFINE_VIEWS,
    MAX_SEED,
    NERF_SYNTHETIC_FOV_X,
    OBJECT_SEEDS,
    REFINE_BACKPROJECTION_STRIDE,
    REFINE_ITERATIONS,
    REFINE_LR,
    REFINE_RAYS_PER_STEP,
    REFINE_TV_WEIGHT,
    REFINE_VIEWS,
    SERVICE_OBJECT_SEED_MARGIN,
    SERVICE_OBJECT_SEEDS,
    SERVICE_REFINE_ITERATIONS,
    SERVICE_SMOOTHING_SIGMA,
    RENDER_SIZE,
)
from voxe_core.guidance.prompts import AUTHORS_FRONT_AZIMUTH_DEG
from voxe_core.render import RenderConfig
from voxe_core.tensorio import check_flags, check_numbers


MAX_ATTENTION_LR = FLOAT32_MAX * (1 - 0.9)
"""The largest lr of the attention-grid fit: torch's Adam (betas (0.9, 0.999)) takes its first step as lr / (1 - 0.9)."""


class SegmentationError(ValueError):
    """The graph cut cannot run: nothing occupied, no seeds, or mismatched inputs."""


@dataclass
class RefineConfig:
    """Defaults are the paper's / the authors' (SPEC §3) unless marked otherwise.

    The graph cut's defaults are the authors' code's (``AUTHORS_CODE_CUT``; issue 18: mean IoU 0.985 against
    the text's 0.848 on bench/localisation_variants.py's ground truth) but for the margin of its random object
    seeds (``SERVICE_CUT``: 0.991); ``PAPER_TEXT_CUT`` restores the text's.
    The 2D maps' defaults are the authors' code's but for their scale (``SERVICE_MAPS``: min-max, measured
    better on every ground truth; ``AUTHORS_CODE_MAPS``, ``PAPER_TEXT_MAPS``), and the fit's are the code's (a
    fresh view per step, L1 where the render is > 0); ``PAPER_TEXT_FIT`` / ``AUTHORS_CODE_FIT`` name both fits
    (README: the refine note).
    """

    # 2D cross-attention maps
    timestep: int = DEFAULT_ATTENTION_TIMESTEP  # t = 200 of 1000
    # keep only the cross-attention layers whose query maps are this side; "auto": the model's (guidance.sds's
    # attention_resolution: a quarter of the latent side on SD 1.x / 2.x, SPEC's 16x16 on SD-1.4, where a fixed 16 finds
    # no layer on a 768-px SD 2.x); None: every layer
    resolution_filter: int | Literal["auto"] | None = "auto"
    smoothing_sigma: float = SERVICE_SMOOTHING_SIGMA  # std in attention-map pixels; 0 = none (ours before issue 18: 1.0)
    # "3x3": a 3x3 kernel (the code's); "3sigma": radius ceil(3 sigma), the whole Gaussian (ours before issue 18)
    smoothing_kernel: Literal["3x3", "3sigma"] = "3x3"
    smooth_upsampled: bool = True  # smooth again after the bilinear upsampling, same kernel (the code)
    # "raw": the attention probabilities as they come, edit and object maps on one scale (the code); "minmax": each
    # map stretched to [0, 1] on its own (the text as we read it). Measured both ways in one run
    # (bench/localisation_maps_fit.py, results/localisation_maps_variants.json, the code's maps but the scale): min-max
    # cut better on all 4 reconstructed-scene cases (IoU 0.92/0.93/0.77/0.68 -> 0.98/1.00/0.97/0.98), raw maps fall to
    # 0.34/0.27/0/0 when the edit word draws 0.3x the object's attention, and on the fox capture
    # (localisation_grids.py --case fox) raw scored 0.07 against min-max's 0.74, so min-max is the default
    map_scale: Literal["raw", "minmax"] = "minmax"
    edit_token_reduce: Literal["mean", "max"] = "max"  # how the edit words' sub-tokens combine (the code: max)
    # "content": the prompt's words minus the edit's; "through_end": also the first end-of-text token (the code)
    object_tokens: Literal["content", "through_end"] = "through_end"
    view_word_prompt: bool = True  # ", front view" etc. from each view's pose in the attention prompt, as in the edit
    front_azimuth_deg: float = AUTHORS_FRONT_AZIMUTH_DEG  # the object's front for the view word (EditConfig's)
    render_size: int = RENDER_SIZE  # pixels of the renders (paper: 800 px / 3)
    views: int = REFINE_VIEWS  # random upper-hemisphere poses (ours; the authors use the training views)
    fov_x: float = NERF_SYNTHETIC_FOV_X
    # 3D attention grids
    iterations: int = SERVICE_REFINE_ITERATIONS  # after the back-projection start; the paper: REFINE_ITERATIONS (1500)
    lr: float = REFINE_LR
    tv_weight: float = REFINE_TV_WEIGHT
    init_value: float = 0.0  # start of lift_start="constant"; see the voxe_core.refine docstring; the authors use -20
    lift_start: Literal["backprojection", "constant"] = "backprojection"  # ours; "constant": the paper's fit
    backprojection_prior: float = 0.1  # pseudo-weight of "no attention" (0) in the back-projection's average
    backprojection_stride: int = REFINE_BACKPROJECTION_STRIDE  # every n-th pixel row and column per view
    rays_per_step: int = REFINE_RAYS_PER_STEP
    # "fresh": every step a new random pose and diffusion pass, all its pixels (the code; one UNet pass per step;
    # better on bench/localisation_maps_fit.py); "fixed": rays_per_step pixels of the `views` maps (ours before)
    fit_views: Literal["fixed", "fresh"] = "fresh"
    # "all": L1 over every pixel whose ray meets the object's box (ours); "rendered_positive": only pixels whose
    # rendered attention is > 0 (the code; it needs a start that renders positive: the back-projection)
    fit_pixels: Literal["all", "rendered_positive"] = "rendered_positive"
    render: RenderConfig = field(default_factory=lambda: RenderConfig(background=(0.0,)))
    # graph cut
    edit_seeds: int = EDIT_SEEDS
    object_seeds: int = SERVICE_OBJECT_SEEDS  # the authors' code's count; the paper's text: OBJECT_SEEDS (200)
    # "top": the edit_seeds highest P_e among P_e > 1/2 (the paper's text); "relative": every node with
    # P_e >= edit_seed_ratio * max P_e, at least the top edit_seeds by P_e (the authors' code, build_graph)
    edit_seed_rule: Literal["top", "relative"] = "relative"
    edit_seed_ratio: float = 0.992
    # "top": the object_seeds highest P_obj among P_obj > 1/2 (the text); "random": up to object_seeds nodes drawn
    # at random (``seed``) among P_obj > P_e, the top object_seed_fallback by P_obj when none qualify (the code)
    object_seed_rule: Literal["top", "random"] = "random"
    # "random" draws among P_obj > P_e + this margin (the code: 0; ours: SERVICE_OBJECT_SEED_MARGIN). Voxels no view
    # resolves sit at P ≈ 1/2 on either side, inside the edited part too; a draw that lands a few seeds there cuts
    # the part in two (bench/localisation_seeds.py: the fox's hat at IoU 0.29–0.34 for 2 draws in 30, the default
    # seed 0 one of them, 0.71–0.76 for the others)
    object_seed_margin: float = SERVICE_OBJECT_SEED_MARGIN
    object_seed_fallback: int = OBJECT_SEEDS
    # unary −log P for the voxels no seed fixes (the text), or "none": only seeds pull (the code comments it out)
    unseeded_unary: Literal["log_probability", "none"] = "none"
    # With no unary, a piece of the graph that holds no seed (a detached part or floater the draw missed, or every
    # piece when smoothness is 0) costs nothing either way and max-flow leaves it on the edit side: "edit" keeps
    # that (the code); "preference" (ours) gives it the label its voxels favour together, Σ log P_e vs Σ log P_obj
    unseeded_pieces: Literal["edit", "preference"] = "preference"
    # "gaussian": λ·exp(−‖Δc‖²/2σ²) (the text); "exp_distance": λ·exp(−‖Δc‖/σ), the L2 distance (the code)
    pairwise_weight: Literal["gaussian", "exp_distance"] = "exp_distance"
    sigma: float = CUT_SIGMA  # colour scale of the pairwise weights
    smoothness: float = CUT_SMOOTHNESS  # lambda
    node_alpha: float = 0.01  # a vertex is a node when one voxel of its density is this opaque
    # "alpha": the node_alpha test above (ours); "maxpool": the 3x3x3 max-pooled ReLU density is > 0 (the code)
    node_rule: Literal["alpha", "maxpool"] = "maxpool"
    # misc
    seed: int = 0
    # A label of the run only: the refinement reads the attention maps of the guidance it is given and never loads
    # this one; the CLI (``voxe refine --model``) and the worker set it to the model they load.
    attention_model: str = ATTENTION_MODEL_ID

    def __post_init__(self):
        # As EditConfig's: a value of another type had been taken, and run the opposite of what was asked
        # (view_word_prompt="false", a true string, put view words in the prompt) or failed naming no setting
        # (render=None: "'NoneType' object has no attribute 'background'").
        check_flags(self, ("view_word_prompt", "smooth_upsampled"))
        if not isinstance(self.render, RenderConfig):
            raise ValueError(f"render must be a RenderConfig, got {self.render!r}")
        check_numbers(self, ("smoothing_sigma", "front_azimuth_deg", "fov_x", "lr", "tv_weight", "init_value",
                             "backprojection_prior", "edit_seed_ratio", "object_seed_margin", "sigma", "smoothness",
                             "node_alpha"))
        if self.lift_start not in ("backprojection", "constant"):
            raise ValueError(f"lift_start must be 'backprojection' or 'constant', got {self.lift_start!r}")
        if not 0 <= self.backprojection_prior <= FLOAT32_MAX:  # as "not in range": NaN fails every comparison
            raise ValueError(f"backprojection_prior must be non-negative and finite in float32, got "
                             f"{self.backprojection_prior}")
        if self.edit_seed_rule not in ("top", "relative"):
            raise ValueError(f"edit_seed_rule must be 'top' or 'relative', got {self.edit_seed_rule!r}")
        if not 0.0 < self.edit_seed_ratio <= 1.0:
            raise ValueError(f"edit_seed_ratio must lie in (0, 1], got {self.edit_seed_ratio}")
        for name, allowed in (("object_seed_rule", ("top", "random")), ("unseeded_unary", ("log_probability", "none")),
                              ("unseeded_pieces", ("edit", "preference")),
                              ("pairwise_weight", ("gaussian", "exp_distance")), ("node_rule", ("alpha", "maxpool")),
                              ("smoothing_kernel", ("3x3", "3sigma")), ("map_scale", ("raw", "minmax")),
                              ("object_tokens", ("content", "through_end")), ("fit_views", ("fixed", "fresh")),
                              ("fit_pixels", ("all", "rendered_positive"))):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")
        # (True, an int to isinstance, had been read as 1: no layer has a 1x1 query map, refused after a render)
        if not (self.resolution_filter in ("auto", None)
                or (isinstance(self.resolution_filter, numbers.Integral) and not isinstance(self.resolution_filter, bool)
                    and self.resolution_filter >= 1)):
            raise ValueError(f"resolution_filter must be 'auto', None or a positive number of query-map pixels, got "
                             f"{self.resolution_filter!r}")
        if self.edit_token_reduce not in ("mean", "max"):
            raise ValueError(f"edit_token_reduce must be 'mean' or 'max', got {self.edit_token_reduce!r}")
        for name in ("timestep", "render_size", "views", "iterations", "backprojection_stride", "rays_per_step",
                     "edit_seeds", "object_seeds", "object_seed_fallback", "seed"):
            value = getattr(self, name)  # (a stride of 1.5 had read a lattice of every third pixel)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"{name} must be a whole number, got {value!r}")
        if not 0 <= self.timestep < DIFFUSION_TIMESTEPS:  # (the model had refused it, after the first view's render)
            raise ValueError(f"timestep must lie in [0, {DIFFUSION_TIMESTEPS - 1}] (a step of the diffusion model's "
                             f"noise schedule; the default: {DEFAULT_ATTENTION_TIMESTEP}), got {self.timestep}")
        check_render_size(self.render_size)
        if self.views > MAX_REFINE_VIEWS:  # (as for render_size: views=100000 had gone on to render and attend each)
            raise ValueError(f"views must be at most {MAX_REFINE_VIEWS} (the service's and the CLI's limit), got "
                             f"{self.views}")
        for name in ("views", "rays_per_step", "backprojection_stride"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.backprojection_stride >= self.render_size:  # (it had lifted nothing, for the cut to find "no seeds")
            raise ValueError(f"backprojection_stride must be below render_size ({self.render_size} px), got "
                             f"{self.backprojection_stride}: the back-projection would read at most one pixel of each "
                             f"view, so it lifts next to nothing (the default: {REFINE_BACKPROJECTION_STRIDE})")
        for name in ("iterations", "edit_seeds", "object_seeds", "object_seed_fallback"):
            if getattr(self, name) < 0:  # (one message for all four had named neither the setting nor its value)
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)}")
        # As "not in range": NaN fails every comparison, so "x <= 0" let it through (a NaN sigma made the flow NaN).
        # A smoothness beyond float32's range had made the cut's float32 weights infinite (max-flow never returned);
        # near float64's largest their sum still makes the seeds' capacity and the flow infinite ("Infinity" in
        # refine.json, which is no JSON).
        # Each by its name and value (voxe refine says it by the option's: one message for all three had named none).
        if not 0 < self.sigma < math.inf:
            raise ValueError(f"sigma must be positive and finite, got {self.sigma}")
        if not 0 <= self.smoothness <= FLOAT32_MAX:
            raise ValueError(f"smoothness must be non-negative and at most {FLOAT32_MAX:.4g}, got {self.smoothness}")
        if not 0 <= self.smoothing_sigma < math.inf:
            raise ValueError(f"smoothing_sigma must be non-negative and finite, got {self.smoothing_sigma}")
        # (a kernel of 2·ceil(3σ) + 1 taps: σ = 1e4 had taken 38 s a 266 px view, 1e12 asked for 48 TB). The advice
        # is the largest σ accepted, in full: rounded (5.66667 for 17/3) it can be refused itself.
        if self.smoothing_kernel == "3sigma" and math.ceil(3.0 * self.smoothing_sigma) >= self.render_size:
            raise ValueError(f"smoothing_kernel='3sigma' spans ceil(3 sigma) = {math.ceil(3.0 * self.smoothing_sigma)} "
                             f"px either side at smoothing_sigma {self.smoothing_sigma}, past the render_size "
                             f"({self.render_size} px) maps it smooths: use a smoothing_sigma of at most "
                             f"{(self.render_size - 1) / 3} or smoothing_kernel='3x3'")
        if self.fit_pixels == "rendered_positive" and self.iterations and self.lift_start == "constant" \
                and self.init_value <= 0:
            raise ValueError("fit_pixels='rendered_positive' fits nothing from a constant start <= 0 (nothing renders "
                             "positive, so no pixel is ever counted): use lift_start='backprojection' or fit_pixels='all'")
        if self.lift_start == "constant" and not self.iterations:  # (it had failed at the cut, after every map)
            raise ValueError(f"lift_start='constant' with iterations=0 leaves both attention grids at their constant "
                             f"start everywhere: no voxel is more likely edit than object, so the cut has no seeds; "
                             f"fit them (iterations > 0; the paper: {REFINE_ITERATIONS}) or use "
                             "lift_start='backprojection'")
        if not 0 < self.lr < math.inf:
            raise ValueError(f"lr must be positive and finite, got {self.lr}")
        if not 0 <= self.tv_weight < math.inf:
            raise ValueError(f"tv_weight must be non-negative and finite, got {self.tv_weight}")
        if not math.isfinite(self.init_value):
            raise ValueError(f"init_value must be a finite number, got {self.init_value}")
        # In the float32 the fit runs in: an lr or init_value past it (1e39) had passed here and failed the fit, after
        # every attention pass, as a RuntimeError naming no setting ("value cannot be converted to type float
        # without overflow"), a tv_weight made both grids NaN. So had an lr within a tenth of it: torch's Adam (the
        # fit's, betas (0.9, 0.999)) takes its first step as lr / (1 - 0.9) in float32.
        if self.lr > MAX_ATTENTION_LR:
            raise ValueError(f"lr must be at most {MAX_ATTENTION_LR:.4g} (Adam's first step, ten times it, finite in "
                             f"float32), got {self.lr}")
        for name in ("tv_weight", "init_value"):
            if abs(getattr(self, name)) > FLOAT32_MAX:
                raise ValueError(f"{name} must be at most {FLOAT32_MAX:.4g} in size (finite in float32), got "
                                 f"{getattr(self, name)}")
        # Nothing but seeds labels a voxel without a unary term, and these ask for none (the cut had blamed the grids,
        # "none of the occupied voxels is more likely edit than object", after every attention pass).
        if (self.unseeded_unary == "none" and self.edit_seed_rule == "top" and not self.edit_seeds
                and not self.object_seeds):
            raise ValueError("edit_seeds=0 and object_seeds=0 under edit_seed_rule='top' seed no voxel, and with "
                             "unseeded_unary='none' nothing else labels one, so the cut would be undefined: ask for "
                             "seeds, or use unseeded_unary='log_probability'")
        if not 0.0 <= self.object_seed_margin < 1.0:
            raise ValueError(f"object_seed_margin must lie in [0, 1), got {self.object_seed_margin}")
        if len(self.render.background) not in (1, 2):  # (a RenderConfig's default white had crashed the fit)
            raise ValueError(f"render.background is the attention fields' value where a ray meets nothing, one number "
                             f"for both or one per field (0.0: no attention), got {self.render.background}: pass "
                             "RenderConfig(..., background=(0.0,))")
        if not 0.0 < self.node_alpha < 1.0:
            raise ValueError(f"node_alpha must lie in (0, 1), got {self.node_alpha}")
        check_fov_x(self.fov_x, self.render_size)
        check_angle("front_azimuth_deg", self.front_azimuth_deg)
        if not 0 <= self.seed <= MAX_SEED:  # (-1 had run every attention pass, then failed in the cut's numpy draw)
            raise ValueError(f"seed must lie in [0, {MAX_SEED}] (the service's and the CLI's range), got {self.seed}")


AUTHORS_CODE_CUT = dict(edit_seed_rule="relative", object_seeds=SERVICE_OBJECT_SEEDS, object_seed_rule="random",
                        unseeded_unary="none", pairwise_weight="exp_distance", sigma=CUT_SIGMA,
                        smoothness=CUT_SMOOTHNESS, node_rule="maxpool", object_seed_margin=0.0,
                        unseeded_pieces="edit")
"""The graph cut of TAU-VAILab/Vox-E's ``build_graph`` (issue 18 item 5)."""

SERVICE_CUT = {**AUTHORS_CODE_CUT, "object_seed_margin": SERVICE_OBJECT_SEED_MARGIN, "unseeded_pieces": "preference"}
"""The defaults: the code's cut, its random object seeds drawn clear of P ≈ ½ (``object_seed_margin``'s comment), a
piece no seed reaches labelled by its probabilities rather than left to the edit side (``unseeded_pieces``)."""

PAPER_TEXT_CUT = dict(edit_seed_rule="top", object_seeds=OBJECT_SEEDS, object_seed_rule="top",
                      unseeded_unary="log_probability", pairwise_weight="gaussian", node_rule="alpha",
                      object_seed_margin=0.0)
"""The paper's text: ``dataclasses.replace(config, **PAPER_TEXT_CUT)`` (no margin: a switch to random seeds from
it draws as the code does)."""

AUTHORS_CODE_MAPS = dict(edit_token_reduce="max", view_word_prompt=True, object_tokens="through_end",
                         smoothing_sigma=SERVICE_SMOOTHING_SIGMA, smoothing_kernel="3x3", smooth_upsampled=True,
                         map_scale="raw")
"""The 2D maps of TAU-VAILab/Vox-E (``attn_grid_trainer.py``, ``cross_attn.py``; issue 18 item 5): raw scale, where the
defaults (``SERVICE_MAPS``) min-max normalise."""

SERVICE_MAPS = {**AUTHORS_CODE_MAPS, "map_scale": "minmax"}
"""The defaults: the code's maps, min-max normalised (``map_scale``'s comment says why)."""

PAPER_TEXT_MAPS = dict(edit_token_reduce="mean", view_word_prompt=False, object_tokens="content",
                       smoothing_sigma=1.0, smoothing_kernel="3sigma", smooth_upsampled=False, map_scale="minmax")
"""The paper's text as this project read it before issue 18 (a small Gaussian, maps in [0, 1])."""

AUTHORS_CODE_FIT = dict(lift_start="backprojection", fit_views="fresh", fit_pixels="rendered_positive",
                        iterations=REFINE_ITERATIONS)
"""The code's fit (a fresh pose and diffusion pass per step, 1,500 steps, L1 where the render is > 0) from
the back-projection start (the code's −20 start renders nothing positive, so its masked L1 could not move it)."""

PAPER_TEXT_FIT = dict(lift_start="constant", fit_views="fixed", fit_pixels="all", iterations=REFINE_ITERATIONS)
"""The paper's text: 1,500 steps from a constant over fixed views, plain L1."""
