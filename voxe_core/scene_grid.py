"""A DVGO-style backbone for unbounded captured scenes (SPEC §5), behind the ReLU-field grid's interface.

Objects on white (NeRF-synthetic) fit a box; a phone capture such as
``../shared/data/fox`` sees a room behind the object. ``SceneGrid`` keeps the
same dense (X, Y, Z, 4) features, activations, occupancy, storage and
``like``/``clone_grid``/``upsampled``, so reconstruction, editing (L_reg3D is
a correlation over the features), refinement (graph cut over voxels, merge)
and checkpoints work unchanged. What differs is where the lattice lives and
how rays are sampled:

* Scene contraction (mip-NeRF 360, with the L∞ norm as DVGO v2 so a cube fits
  it): in units of the foreground half-extent, ``q ↦ q`` inside the cube
  [-1, 1]³ and ``q ↦ (2 − 1/‖q‖∞) q/‖q‖∞`` beyond, so all of space maps into
  [-2, 2]³ and the lattice spans that cube. The foreground keeps a linear
  half of the lattice; the background is ever coarser with distance.
* Sampling: evenly spaced inside the foreground cube (``step_ratio`` voxels,
  as the ReLU-field renderer), evenly between a camera outside the cube and
  the cube, and linear in inverse depth beyond the cube out to
  ``far_ratio`` times the exit distance.
* Background: learned (the contracted shell holds the room); what light still
  passes the last sample is composited on the fixed ``RenderConfig.background``.

The grid works in a canonical frame: scene centre at the origin, z up, the
cameras at the NeRF-synthetic radius, so editing's random upper-hemisphere
poses (radius 4.0311, looking at the origin) see the scene as they see an
object. ``scene_frame`` finds that similarity from the capture's cameras; it is
stored in the grid header so a dataset's cameras can be mapped again later.
"""

from __future__ import annotations

import math

import torch

from voxe_core.cameras import NERF_SYNTHETIC_RADIUS, Cameras
from voxe_core.edit import EditConfig
from voxe_core.grid import Activation, Occupancy, VoxelGrid, default_density_scale
from voxe_core.render import RenderConfig, RenderOutput, optical_depth, ray_box_intersection
from voxe_core.schedule import TimestepSchedule

BACKBONES = ("relu_field", "scene")
SCENE_BACKBONE = "scene"
CONTRACTED_EXTENT = 2.0  # the contraction maps all of space into [-2, 2]^3
OPAQUE_ALPHA = 0.5  # a pixel with alpha below this is transparent background
TRANSPARENT_FRACTION = 0.01  # images with at least this share of transparent pixels are objects on a background
_RAYS_PER_PASS = 4096  # rays evaluated together, bounding the sample tensors of whole-image renders
_UNBOUNDED = 1e6  # world half-extent standing in for "the occupied cells reach into the background"


def contract(points: torch.Tensor) -> torch.Tensor:
    """Scene contraction with the L∞ norm: identity on [-1, 1]³, all of space into (-2, 2)³."""
    norm = points.abs().amax(-1, keepdim=True)
    outside = norm > 1.0
    safe = torch.where(outside, norm, torch.ones_like(norm))
    # Infinite coordinates land on the boundary (±2 on their axes) instead of inf/inf = NaN.
    direction = torch.where(torch.isinf(safe), torch.isinf(points) * points.sign(), points / safe)
    return torch.where(outside, (2.0 - 1.0 / safe) * direction, points)


class SceneGrid(VoxelGrid):
    """The voxel grid over contracted space; the foreground cube is [-foreground_extent, foreground_extent]³."""

    def __init__(
        self,
        resolution: int | tuple[int, int, int] = 160,
        foreground_extent: float = 1.5,
        activation: Activation = "relu",
        density_scale: float | None = None,
        init_density: float = 0.01,
        features: torch.Tensor | None = None,
        near_samples: int = 32,
        far_samples: int = 64,
        far_ratio: float = 1000.0,
        frame: torch.Tensor | None = None,
    ):
        if not (math.isfinite(foreground_extent) and foreground_extent > 0):
            raise ValueError(f"foreground_extent must be a positive length, got {foreground_extent}")
        if near_samples < 1 or far_samples < 1 or not far_ratio > 1:
            raise ValueError("near_samples and far_samples must be >= 1 and far_ratio > 1")
        fg = float(foreground_extent)
        # Density per unit of the canonical frame, scaled as the ReLU-field grid over the same foreground box.
        density_scale = density_scale or default_density_scale((-fg,) * 3, (fg,) * 3)
        super().__init__(resolution, (-CONTRACTED_EXTENT,) * 3, (CONTRACTED_EXTENT,) * 3, activation,
                         density_scale, init_density, features)
        self.foreground_extent = fg
        self.near_samples, self.far_samples, self.far_ratio = int(near_samples), int(far_samples), float(far_ratio)
        self.frame = torch.eye(4) if frame is None else torch.as_tensor(frame, dtype=torch.float32).reshape(4, 4)

    # ------------------------------------------------------------ interface
    def like(self, features: torch.Tensor) -> "SceneGrid":
        return SceneGrid(features.shape[:3], self.foreground_extent, self.activation, self.density_scale,
                         features=features, near_samples=self.near_samples, far_samples=self.far_samples,
                         far_ratio=self.far_ratio, frame=self.frame)

    def header(self) -> dict:
        return {**super().header(), "backbone": SCENE_BACKBONE, "foreground_extent": self.foreground_extent,
                "near_samples": self.near_samples, "far_samples": self.far_samples, "far_ratio": self.far_ratio,
                "frame": self.frame.reshape(-1).tolist()}

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict) -> "SceneGrid":
        return cls(tuple(tensors["features"].shape[:3]), meta["foreground_extent"], meta["activation"],
                   meta["density_scale"], features=tensors["features"], near_samples=meta["near_samples"],
                   far_samples=meta["far_samples"], far_ratio=meta["far_ratio"], frame=meta["frame"])

    def occupancy_from_cells(self, cells: torch.Tensor) -> Occupancy:
        """The cells with their box in the canonical frame (callers cull world rays with it).

        The lattice box is in contracted coordinates; it maps back linearly only
        while it stays inside the foreground cube. Once occupied cells reach the
        background the box is unbounded (a huge cube), which culls nothing.
        """
        lattice = super().occupancy_from_cells(cells)
        if lattice.empty:
            return lattice
        if bool((lattice.bbox_min >= -1.0).all() and (lattice.bbox_max <= 1.0).all()):
            return Occupancy(cells, lattice.bbox_min * self.foreground_extent, lattice.bbox_max * self.foreground_extent)
        return Occupancy(cells, torch.full_like(lattice.bbox_min, -_UNBOUNDED), torch.full_like(lattice.bbox_max, _UNBOUNDED))

    @torch.no_grad()
    def foreground_grid(self) -> VoxelGrid:
        """The foreground cube as a ReLU-field grid in the canonical frame, at this lattice's spacing.

        The contraction is the identity there, so this is the object without its
        background (``export.extract_mesh`` meshes it). Exact when (resolution − 1)
        is a multiple of 4 (the cube's faces fall on lattice vertices), resampled otherwise.
        """
        fg = self.foreground_extent
        n = [(r - 1) // 2 + 1 for r in self.resolution]
        axes = [torch.linspace(-fg, fg, k) for k in n]
        points = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        features = self.interpolate(self.lattice_points(points.to(self.bbox_min.device)))
        return VoxelGrid(tuple(n), (-fg,) * 3, (fg,) * 3, self.activation, self.density_scale,
                         features=features.reshape(*n, 4))

    def lattice_points(self, points: torch.Tensor) -> torch.Tensor:
        """Canonical-frame points -> the contracted coordinates the lattice is indexed by."""
        return contract(points / self.foreground_extent)

    # ------------------------------------------------------------ rendering
    def render_rays(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        config: RenderConfig = RenderConfig(),
        occupancy: Occupancy | None = None,
        generator: torch.Generator | None = None,
        color_features: torch.Tensor | None = None,
        sparse_grad: bool = False,
    ) -> RenderOutput:
        """``voxe_core.render.render_rays`` for this backbone (it dispatches here); same arguments and output."""
        with torch.autocast(origins.device.type, enabled=False):
            if config.skip_empty and occupancy is None:
                occupancy = self.occupancy(config.sigma_threshold)
            offset = (torch.rand(origins.shape[0], generator=generator, device=origins.device) if generator is not None
                      else torch.full((origins.shape[0],), 0.5, device=origins.device))
            parts = [
                self._render_pass(origins[s : s + _RAYS_PER_PASS], directions[s : s + _RAYS_PER_PASS],
                                  offset[s : s + _RAYS_PER_PASS], config, occupancy, color_features, sparse_grad)
                for s in range(0, origins.shape[0], _RAYS_PER_PASS)
            ]
        if not parts:
            channels = 3 if color_features is None else color_features.shape[-1]
            empty = origins.new_zeros(0)
            return RenderOutput(origins.new_zeros(0, channels), empty, empty)
        return RenderOutput(
            torch.cat([p.rgb for p in parts]), torch.cat([p.opacity for p in parts]),
            torch.cat([p.depth for p in parts]), sum(p.samples for p in parts), sum(p.candidates for p in parts),
        )

    def ray_bins(self, origins: torch.Tensor, directions: torch.Tensor, step_ratio: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Bin edges along each ray in canonical units, (N, S+1), and which of the S bins exist.

        Bins partition [0, far] per ray: ``near_samples`` even bins from the
        camera to the foreground cube (empty when the camera is inside it),
        foreground bins of ``step_ratio`` voxels (the last one cut at the
        exit), then ``far_samples`` bins even in inverse depth out to
        ``far_ratio`` times the exit distance. Rays that miss the cube switch
        to inverse depth at their closest approach to the scene centre.
        """
        fg = self.foreground_extent
        unit = torch.ones(3, device=origins.device)
        t_in, t_out = ray_box_intersection(origins, directions, -fg * unit, fg * unit)
        hit = t_out > t_in
        closest = (-(origins * directions).sum(-1)).clamp_min(0.0)
        t_in = torch.where(hit, t_in, closest)
        # Far bins need a positive start: a camera exactly at the exit or the centre starts one voxel out.
        step = step_ratio * float(self.voxel_size.min()) * fg
        t_out = torch.where(hit, t_out, t_in).clamp_min(step)
        n_fg = torch.where(hit, torch.ceil((t_out - t_in) / step), torch.zeros_like(t_in)).long()
        max_fg = int(n_fg.max()) if n_fg.numel() else 0
        u_near = torch.linspace(0.0, 1.0, self.near_samples + 1, device=origins.device)
        near_edges = t_in[:, None] * u_near  # all zero when the camera is inside
        k = torch.arange(1, max_fg + 1, device=origins.device)
        fg_edges = torch.minimum(t_in[:, None] + k * step, t_out[:, None])
        u_far = torch.linspace(0.0, 1.0, self.far_samples + 1, device=origins.device)[1:]
        inverse = (1.0 - u_far) / t_out[:, None] + u_far / (self.far_ratio * t_out[:, None])
        edges = torch.cat([near_edges, fg_edges, 1.0 / inverse], dim=1)
        exists = edges[:, 1:] > edges[:, :-1]
        return edges, exists

    def _render_pass(self, origins, directions, offset, config, occupancy, color_features, sparse_grad) -> RenderOutput:
        device = origins.device
        channels = 3 if color_features is None else color_features.shape[-1]
        background = torch.as_tensor(config.background, dtype=torch.float32, device=device).expand(channels)
        origins = torch.where(torch.isfinite(origins), origins, torch.zeros_like(origins))
        directions = torch.where(torch.isfinite(directions), directions, torch.zeros_like(directions))
        edges, valid = self.ray_bins(origins, directions, config.step_ratio)
        delta = edges[:, 1:] - edges[:, :-1]
        t = edges[:, :-1] + offset[:, None] * delta
        points = self.lattice_points(origins[:, None, :] + t[..., None] * directions[:, None, :])
        candidates = int(valid.sum())
        if config.skip_empty:
            valid = valid & occupancy.occupied(self.cell_index(points))
        index = valid.nonzero(as_tuple=True)
        optical = torch.zeros(valid.shape, device=device)
        color = torch.zeros(*valid.shape, channels, device=device)
        if index[0].numel():
            raw = self.interpolate(points[index], sparse_grad=sparse_grad)
            sigma = self.activate_density(raw[:, 0])
            optical = optical.index_put(index, optical_depth(sigma, delta[index]))
            values = (self.activate_color(raw[:, 1:]) if color_features is None
                      else self.interpolate(points[index], color_features))
            color = color.index_put(index, values.float())
        inclusive = optical.cumsum(-1)
        weights = torch.exp(-(inclusive - optical)) * (-torch.expm1(-optical))
        opacity = weights.sum(-1)
        rgb = (weights[..., None] * color).sum(1) + (1.0 - opacity)[:, None] * background
        depth = (weights * t).sum(-1)
        depth = torch.where(opacity > 1e-6, depth / opacity.clamp_min(1e-6), torch.zeros_like(depth))
        return RenderOutput(rgb, opacity, depth, int(index[0].numel()), candidates)


# ------------------------------------------------------------------ frames
def scene_frame(cameras: Cameras, radius: float = NERF_SYNTHETIC_RADIUS) -> torch.Tensor:
    """Similarity ``canonical_from_world`` (4x4) for a 360° capture.

    Centre: the point nearest (least squares) to every optical axis, i.e. what
    the cameras look at. Up: the cameras' mean +y axis (phones are held
    upright) turned onto +z. Scale: the mean camera distance becomes ``radius``.
    Raises ``ValueError`` when the axes are (nearly) parallel (a forward-facing
    capture has no centre to orbit) or the cameras sit on the centre.
    """
    c2w = cameras.c2w.double()
    position, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    forward = forward / forward.norm(dim=-1, keepdim=True)
    projector = torch.eye(3, dtype=torch.float64) - forward[:, :, None] * forward[:, None, :]
    normal = projector.sum(0)
    if float(torch.linalg.eigvalsh(normal)[0]) < 1e-3 * len(cameras):
        raise ValueError(
            "the cameras' optical axes are (nearly) parallel, so they look at no common centre; "
            "the scene backbone needs a capture around the object"
        )
    centre = torch.linalg.solve(normal, torch.einsum("nij,nj->i", projector, position))
    distance = (position - centre).norm(dim=-1).mean()
    if not float(distance) > 1e-9:
        raise ValueError("the cameras sit on the point they look at; cannot scale the scene")
    up = c2w[:, :3, 1].mean(0)
    up = up / up.norm().clamp_min(1e-12)
    rotation = _rotation_onto_z(up)
    scale = radius / distance
    frame = torch.eye(4, dtype=torch.float64)
    frame[:3, :3] = scale * rotation
    frame[:3, 3] = -scale * rotation @ centre
    return frame.float()


def _rotation_onto_z(v: torch.Tensor) -> torch.Tensor:
    """Rotation matrix taking unit ``v`` onto +z (Rodrigues; a half turn about x for -z)."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=v.dtype)
    axis = torch.linalg.cross(v, z)
    s, c = float(axis.norm()), float(v @ z)
    if s < 1e-9:
        return torch.eye(3, dtype=v.dtype) if c > 0 else torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=v.dtype))
    k = axis / s
    cross = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=v.dtype)
    return torch.eye(3, dtype=v.dtype) + s * cross + (1 - c) * cross @ cross


def apply_frame(cameras: Cameras, frame: torch.Tensor) -> Cameras:
    """``cameras`` moved by the similarity ``frame``; rotations stay orthonormal (the scale goes to the position)."""
    frame = frame.to(cameras.c2w)
    scale = frame[:3, :3].norm(dim=0).mean()
    c2w = cameras.c2w.clone()
    c2w[:, :3, :3] = frame[:3, :3] @ cameras.c2w[:, :3, :3] / scale
    c2w[:, :3, 3] = (frame[:3, :3] @ cameras.c2w[:, :3, 3, None])[..., 0] + frame[:3, 3]
    return Cameras(c2w, cameras.fx, cameras.fy, cameras.cx, cameras.cy, cameras.width, cameras.height)


def dataset_cameras(grid: VoxelGrid, cameras: Cameras) -> Cameras:
    """A dataset's cameras in the frame ``grid`` lives in (a scene grid's canonical frame; object grids: as given)."""
    return apply_frame(cameras, grid.frame) if isinstance(grid, SceneGrid) else cameras


# --------------------------------------------------------------- selection
def detect_backbone(alphas: torch.Tensor | None) -> str:
    """'relu_field' for objects on a transparent background, 'scene' for opaque photos.

    ``alphas`` is ``Scene.alphas`` (None when the images carry no alpha). An
    alpha channel that is opaque nearly everywhere is a photo saved as RGBA.
    """
    if alphas is None or alphas.numel() == 0:
        return SCENE_BACKBONE
    transparent = float((alphas < OPAQUE_ALPHA).float().mean())
    return "relu_field" if transparent >= TRANSPARENT_FRACTION else SCENE_BACKBONE


def prepare_backbone(backbone: str, alphas: torch.Tensor | None, cameras: Cameras, resolution: int):
    """Resolve ``backbone`` ('auto' | 'relu_field' | 'scene') for a loaded scene.

    Returns (name, cameras to fit with, initial grid for ``reconstruct`` or None):
    a scene grid is fitted in the canonical frame of ``scene_frame``, which it records.
    """
    if backbone not in ("auto", *BACKBONES):
        raise ValueError(f"unknown backbone {backbone!r}; use 'auto', 'relu_field' or 'scene'")
    name = detect_backbone(alphas) if backbone == "auto" else backbone
    if name != SCENE_BACKBONE:
        return name, cameras, None
    frame = scene_frame(cameras)
    return name, apply_frame(cameras, frame), SceneGrid(resolution, frame=frame)


def real_scene_edit_config(**overrides) -> EditConfig:
    """SPEC §5's edit schedule for captured scenes: 5000 iterations, annealing from 3000 every 400."""
    schedule = TimestepSchedule(i_start=3000, every=400)
    return EditConfig(**{"iterations": 5000, "schedule": schedule, **overrides})

