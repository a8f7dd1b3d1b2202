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
poses (radius 4.0311) see the scene as they see an object. ``scene_frame`` finds
that similarity from the capture's cameras; it is stored in the grid header so a
dataset's cameras can be mapped again later (:meth:`SceneGrid.dataset_cameras`).
The cameras' centre need not be the object's: poses and turntables look at
:meth:`SceneGrid.orbit_centre`, the foreground's matter centre.

What the renderer, the mesh export and the loaders need from a backbone are
methods ``SceneGrid`` overrides (``ray_samples``, ``dataset_cameras``,
``foreground_grid``, ``orbit_centre``, ``object_vertices``, ``from_state``);
``voxe_core.backbones`` finds the class of a saved grid by its ``kind``.
"""

from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import replace
from typing import Iterator

import torch

from voxe_core.cameras import Cameras
from voxe_core.constants import FLOAT32_MAX, NERF_SYNTHETIC_RADIUS
from voxe_core.devices import full_precision
from voxe_core.grid import Activation, Occupancy, VoxelGrid, default_density_scale, ray_box_intersection
from voxe_core.tensorio import FormatError, is_number
from voxe_core.volrend import RaySamples

CONTRACTED_EXTENT = 2.0  # the contraction maps all of space into [-2, 2]^3
_RAYS_PER_PASS = 4096  # rays sampled together, bounding the (rays, bins) tensors of whole-image renders
_UNBOUNDED = 1e6  # world half-extent standing in for "the occupied cells reach into the background"
MAX_FAR_RATIO = 1e6  # the far bins reach this times the exit distance at most: past ~1e38 its float32 product overflowed
_NEAR_FAR_BINS_PER_PASS = 2 * 1024 * _RAYS_PER_PASS
"""The near and far bins a pass holds at most: 4,096 rays of up to 1024 of each, 16 times the default far bins (at
1024 each a 64x64 render held 2.9 GB on the CPU, 0.4 GB at the defaults). A grid with more bins (an older version
took any count) samples fewer rays a pass."""
MAX_NEAR_FAR_SAMPLES = _NEAR_FAR_BINS_PER_PASS // 2
"""The most ``near_samples`` or ``far_samples`` a scene grid takes: both at most fill a pass with one ray. 1e12 near
bins had loaded from a file and failed its render, allocating 4 TB."""
UP_AGREEMENT = 1.5
"""The length the mean of N cameras' unit image up axes must reach, times sqrt(N) (at most 0.5: an upright ring up to
60° above the horizon's), for ``scene_frame`` to take it as up: the mean of N axes rolled every way (a top-down capture
turned about its axes) is about 1 / sqrt(N) long, a direction of chance."""
UPRIGHT_TOLERANCE_DEG = 30.0
"""How far a camera's image up may be rolled from its view's upright one for ``scene_frame`` to count the capture
upright about its short mean up axis (an upright ring high above or below the object), and take that mean silently."""
EARLY_STOP_CAP = 1e-6
"""The scene sampler stops rays at transmittance min(``early_stop``, this). Behind the cut lies the
room, not the white background the compositor puts there, so the density gradient of the last kept
samples (whose far bins are hundreds of units long) takes the sign of (their colour − white) instead
of (their colour − the room's) with a weight ~ the cut; Adam scales a wrong sign to a full step. On
tests/test_real_scenes.py's room (17³, 120 / 400 iterations) a cut at 1e-4 fitted 16.1 / 17.0 dB,
at 1e-6 31.6 / 36.8 dB, none 31.7 / 37.1 dB."""


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

    kind = "scene"
    lattice_sampled = False  # its own contracted bins

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
        # A file's header is read through here: its extent of 1e300 (past float32) had loaded and failed the render,
        # JSON's true had been 1; its sample count of 2.9 had been cut to 2, of 1e300 (or 1e12) failed the render.
        # A string or null had been "'<' not supported between instances of 'int' and 'str'", naming no field.
        if not is_number(foreground_extent) or not 0 < foreground_extent <= FLOAT32_MAX:
            raise ValueError(f"foreground_extent must be a positive length, finite in float32, got "
                             f"{foreground_extent!r}")
        for name, count in (("near_samples", near_samples), ("far_samples", far_samples)):
            if isinstance(count, bool) or not isinstance(count, numbers.Integral):
                raise ValueError(f"{name} must be a whole number, got {count!r}")
            if count > MAX_NEAR_FAR_SAMPLES:
                raise ValueError(f"{name} must be at most {MAX_NEAR_FAR_SAMPLES} (MAX_NEAR_FAR_SAMPLES), got {count}")
        # far_ratio "not in range": an infinite one made the last far bin infinite, and an empty ray's render NaN;
        # so did a finite one whose float32 product with the exit distance overflowed (3e38, or 1e38 times 4).
        if near_samples < 1 or far_samples < 1 or not (is_number(far_ratio) and 1 < far_ratio <= MAX_FAR_RATIO):
            raise ValueError(f"near_samples and far_samples must be >= 1 and far_ratio in (1, {MAX_FAR_RATIO:g}], "
                             f"got {near_samples}, {far_samples}, {far_ratio!r}")
        fg = float(foreground_extent)
        # Density per unit of the canonical frame, scaled as the ReLU-field grid over the same foreground box.
        density_scale = default_density_scale((-fg,) * 3, (fg,) * 3) if density_scale is None else density_scale
        super().__init__(resolution, (-CONTRACTED_EXTENT,) * 3, (CONTRACTED_EXTENT,) * 3, activation,
                         density_scale, init_density, features)
        self.foreground_extent = fg
        self.near_samples, self.far_samples, self.far_ratio = int(near_samples), int(far_samples), float(far_ratio)
        self.frame = torch.eye(4) if frame is None else _similarity(frame)

    # ------------------------------------------------------------ interface
    def like(self, features: torch.Tensor) -> "SceneGrid":
        return SceneGrid(features.shape[:3], self.foreground_extent, self.activation, self.density_scale,
                         features=features, near_samples=self.near_samples, far_samples=self.far_samples,
                         far_ratio=self.far_ratio, frame=self.frame)

    def header(self) -> dict:
        return {**super().header(), "foreground_extent": self.foreground_extent,
                "near_samples": self.near_samples, "far_samples": self.far_samples, "far_ratio": self.far_ratio,
                "frame": self.frame.reshape(-1).tolist()}

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict) -> "SceneGrid":
        """The grid a file or checkpoint holds. One saved before far_ratio was bounded may lie past the bound: named
        so, not refused as damaged."""
        far_ratio = meta["far_ratio"]
        if isinstance(far_ratio, float) and far_ratio > MAX_FAR_RATIO:  # (what a version wrote: float(far_ratio))
            raise FormatError(f"far_ratio {far_ratio:g} is above the largest this version supports "
                              f"({MAX_FAR_RATIO:g}), as a scene grid an older version saved may be: refit the scene "
                              f"with this one")
        return cls(tuple(tensors["features"].shape[:3]), meta["foreground_extent"], meta["activation"],
                   meta["density_scale"], features=tensors["features"], near_samples=meta["near_samples"],
                   far_samples=meta["far_samples"], far_ratio=meta["far_ratio"],
                   frame=_similarity(meta["frame"]))  # (a null one, which no version wrote, had loaded as no frame)

    def skip_density(self, sigma_threshold: float) -> torch.Tensor:
        """``VoxelGrid.skip_density`` in the foreground cube, lowered in each background cell by how far it
        stretches in the world.

        A cell whose farthest point has contracted L∞ norm r > 1 spans at most 1/(2 − r)² times a
        foreground cell's world length (the inverse contraction's largest stretch, radial), so its
        density is multiplied by (2 − r)²: no cell is skipped with more optical depth along a ray than a
        foreground cell can hold, and none of the outermost shell (r = 2, reaching infinity) that holds
        any (more than empty space's, under softplus). One density for all had skipped far bins hundreds of
        units long: a uniform 3.3e-4 rendered opacity 0 instead of 0.84.
        """
        density = super().skip_density(sigma_threshold)
        features = self.flat_features
        # On the grid's device, at least as wide as its dtype (a float64 grid's densities are compared in float64).
        device, dtype = features.device, torch.promote_types(features.dtype, torch.float32)
        per_axis = []  # (2 − r)² falls as r grows: at r = the largest |coordinate|, the least of the axes' factors
        for n in self.resolution:
            vertices = torch.linspace(-CONTRACTED_EXTENT, CONTRACTED_EXTENT, n, dtype=dtype, device=device).abs()
            farthest = torch.maximum(vertices[:-1], vertices[1:])
            per_axis.append(density * (CONTRACTED_EXTENT - farthest).clamp(max=1.0).square())
        # At least what empty space activates to: softplus is never 0, and its whole outermost shell had counted
        # as occupied (an object's sparse file 15x larger, nothing culled). Activated as the cells are, in the grid's
        # dtype on its device: a float32 value from the host fell a last bit short of a float64 grid's empty space
        # (the shell occupied again), as a device's own softplus may fall.
        none = self.activate_density(torch.tensor(self.empty_raw_density, dtype=features.dtype, device=device))
        return torch.minimum(torch.minimum(per_axis[0][:, None, None], per_axis[1][None, :, None]),
                             per_axis[2][None, None, :]).clamp_min(none)

    def occupancy_from_cells(self, cells: torch.Tensor) -> Occupancy:
        """The cells with their box in the canonical frame (callers cull world rays with it).

        The lattice box is in contracted coordinates; it maps back linearly only
        while it stays inside the foreground cube. Once occupied cells reach the
        background the box is unbounded (a huge cube), which culls nothing.
        """
        lattice = super().occupancy_from_cells(cells)
        # Chosen on the device (no host read: the edit loop builds one occupancy per iteration).
        inside = (lattice.bbox_min >= -1.0).all() & (lattice.bbox_max <= 1.0).all()
        unbounded = torch.full_like(lattice.bbox_min, _UNBOUNDED)
        box_min = torch.where(inside, lattice.bbox_min * self.foreground_extent, -unbounded)
        box_max = torch.where(inside, lattice.bbox_max * self.foreground_extent, unbounded)
        occupied = cells.any()  # an empty mask keeps the lattice's empty box
        return Occupancy(cells, torch.where(occupied, box_min, lattice.bbox_min),
                         torch.where(occupied, box_max, lattice.bbox_max))

    @torch.no_grad()
    def foreground_grid(self) -> VoxelGrid:
        """The foreground cube as a ReLU-field grid in the canonical frame, at this lattice's spacing.

        The contraction is the identity there, so this is the object without its
        background (``export.extract_mesh`` meshes it). Exact when (resolution − 1)
        is a multiple of 4 (the cube's faces fall on lattice vertices), resampled otherwise; at least 2 vertices per
        axis (a lattice of 2 has its cube between its vertices, and a grid needs 2). In float32 whatever autocast says
        (a caller's bf16 autocast had run the interpolation's bmm in bf16: features 0.011 off, and the orbit centre,
        the mesh and the edit's camera check read them).
        """
        fg = self.foreground_extent
        n = [max(2, (r - 1) // 2 + 1) for r in self.resolution]
        axes = [torch.linspace(-fg, fg, k) for k in n]
        points = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        with full_precision(self.features):
            features = self.interpolate(self.lattice_points(points.to(self.bbox_min.device)))
        return VoxelGrid(tuple(n), (-fg,) * 3, (fg,) * 3, self.activation, self.density_scale,
                         features=features.reshape(*n, 4))

    def lattice_points(self, points: torch.Tensor) -> torch.Tensor:
        """Canonical-frame points -> the contracted coordinates the lattice is indexed by."""
        return contract(points / self.foreground_extent)

    def vertex_positions(self) -> torch.Tensor:
        """The vertices in the canonical frame (uncontracted; the lattice's outer faces lie at infinity)."""
        lattice = super().vertex_positions()
        norm = lattice.abs().amax(-1, keepdim=True)
        outside = norm > 1.0
        stretch = torch.where(outside, 1.0 / (norm * (CONTRACTED_EXTENT - norm)), torch.ones_like(norm))
        return lattice * stretch * self.foreground_extent

    def dataset_cameras(self, cameras: Cameras) -> Cameras:
        """A capture's cameras moved into this grid's canonical frame."""
        return apply_frame(cameras, self.frame)

    def orbit_centre(self) -> torch.Tensor:
        """The foreground's ``matter_centre()``: the frame's origin is where the cameras look, not always where
        the object sits."""
        return self.foreground_grid().matter_centre()

    def object_vertices(self) -> torch.Tensor:
        """The foreground cube's vertices (contracted coordinates in [-1, 1]³): the shell beyond is the room."""
        inside = [torch.linspace(-CONTRACTED_EXTENT, CONTRACTED_EXTENT, n, device=self.bbox_min.device).abs()
                  <= 1.0 + 1e-6 for n in self.resolution]
        return inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]

    # ------------------------------------------------------------ sampling
    def ray_samples(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        offsets: torch.Tensor,
        step_ratio: float,
        occupancy: Occupancy | None = None,
        samples_per_pass: int = 1 << 20,
        early_stop: float = 0.0,
    ) -> Iterator[RaySamples]:
        """``VoxelGrid.ray_samples`` for this backbone: one sample per bin of :meth:`ray_bins`, at ``offsets`` (N,) within it.

        Rays go in groups of 4,096, fewer past 2 x 1024 near and far bins (their bins are laid out densely first);
        ``samples_per_pass`` is not used. Points are returned contracted (the
        lattice's coordinates); with an ``occupancy`` only those in occupied cells are kept.
        ``early_stop`` > 0 drops, as the ReLU field's sampler does (``VoxelGrid._stop_early``),
        the samples behind the point where a ray's transmittance falls below min(``early_stop``,
        ``EARLY_STOP_CAP``): together they weigh less than that in the render. On fox most rays
        end on the room's walls well before the last far bin (bench/real_scenes.py --step-cost).
        A non-finite origin or direction, or a zero direction, is no ray (no samples: the background), as in
        the ReLU field's slab test (``ray_box_intersection``).
        """
        early_stop = min(early_stop, EARLY_STOP_CAP)
        is_ray = (torch.isfinite(origins).all(-1) & torch.isfinite(directions).all(-1)
                  & (directions.abs().amax(-1) >= 1e-12))
        # Zeroed, a ray that is none gets finite bins, and none of them is kept.
        origins = torch.where(is_ray[:, None], origins, 0.0)
        directions = torch.where(is_ray[:, None], directions, 0.0)
        rays = max(1, min(_RAYS_PER_PASS, _NEAR_FAR_BINS_PER_PASS // (self.near_samples + self.far_samples)))
        for s in range(0, origins.shape[0], rays):
            o, d = origins[s : s + rays], directions[s : s + rays]
            edges, valid = self.ray_bins(o, d, step_ratio)
            valid = valid & is_ray[s : s + rays, None]
            delta = edges[:, 1:] - edges[:, :-1]
            t = edges[:, :-1] + offsets[s : s + rays, None] * delta
            points = self.lattice_points(o[:, None, :] + t[..., None] * d[:, None, :])
            candidates = int(valid.sum())
            if occupancy is not None:
                valid = valid & occupancy.occupied(self.cell_index(points))
            ray, bin_ = valid.nonzero(as_tuple=True)  # row-major: ray by ray, in marching order
            samples = RaySamples(ray + s, t[ray, bin_], delta[ray, bin_], points[ray, bin_], candidates)
            yield self._stop_early(samples, early_stop) if early_stop > 0 and ray.numel() else samples

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

# ------------------------------------------------------------------ frames
def _similarity(frame) -> torch.Tensor:
    """``frame`` as the (4, 4) float32 similarity ``scene_frame`` makes (a positive scale times a rotation, then a
    translation), ValueError otherwise: a file's NaN, zero or 1e300 frame had loaded, and every camera
    ``apply_frame`` moved with it was NaN."""
    if isinstance(frame, torch.Tensor) and frame.dtype == torch.bool or _holds_a_bool(frame):
        raise ValueError("frame must hold numbers, not booleans (a file's true and false had been read as 1 and 0)")
    try:  # torch's own words had been the message: "shape '[4, 4]' is invalid for input of size 3"
        matrix = torch.as_tensor(frame, dtype=torch.float64).reshape(4, 4)
    except OverflowError:  # a whole number past float64's range (10**400): Python's words, no field, had escaped
        raise ValueError(f"frame must be finite in float32, got {str(frame)[:200]}") from None
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"frame must be 16 numbers (a 4x4 matrix), got {str(frame)[:200]}") from None
    if not bool((matrix.abs() <= FLOAT32_MAX).all()):  # NaN fails the comparison
        raise ValueError(f"frame must be finite in float32, got {matrix.tolist()}")
    linear = matrix[:3, :3]
    scale = float(linear.norm(dim=0).mean())
    rotation = linear / scale if scale > 0 else linear
    deviation = float((rotation.T @ rotation - torch.eye(3, dtype=torch.float64)).abs().max())
    if not (scale > 0 and deviation <= 1e-4 and float(torch.linalg.det(rotation)) > 0
            and matrix[3].tolist() == [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"frame must be a similarity (a positive scale times a rotation, then a translation; last "
                         f"row 0, 0, 0, 1), got {matrix.tolist()}")
    return matrix.float()


def _holds_a_bool(value) -> bool:
    """Whether a (nested) list of a file's header holds a boolean anywhere."""
    return isinstance(value, bool) or isinstance(value, (list, tuple)) and any(map(_holds_a_bool, value))


def scene_frame(cameras: Cameras, radius: float = NERF_SYNTHETIC_RADIUS) -> torch.Tensor:
    """Similarity ``canonical_from_world`` (4x4) for a 360° capture.

    Centre: the point nearest (least squares) to every optical axis, i.e. what
    the cameras look at. Up: the cameras' mean image up axis as the images are
    displayed (phones are held upright; ``Cameras.display_up``: +y unless an EXIF
    orientation turns the image: a portrait photo stored landscape had put up
    sideways, and edits' views rolled 90°) turned onto +z; where those cancel out (``UP_AGREEMENT``: images rolled every
    way), opposite the cameras' mean view direction, with a warning, unless every camera is upright about their short
    mean (``UPRIGHT_TOLERANCE_DEG``: a ring high above the object). Scale: the mean camera
    distance becomes ``radius``.
    Raises ``ValueError`` for a single camera, when the axes are (nearly) parallel (a forward-facing
    capture has no centre to orbit), the centre lies behind most cameras (poses
    in OpenCV's camera axes, which look down +z) or the cameras sit on the centre.
    """
    if len(cameras) == 1:  # its one axis had been called "parallel" axes
        raise ValueError("a single camera has no centre to orbit: the scene backbone needs views from around the "
                         "object")
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
    depth = ((centre - position) * forward).sum(-1)  # the centre's, along each optical axis
    behind = int((depth <= 0).sum())
    if behind > len(cameras) / 2:
        raise ValueError(
            f"the point the cameras' optical axes meet lies behind {behind} of {len(cameras)} cameras: either the "
            "capture looks outward or its views fan out (there is no object to orbit), or the poses hold OpenCV "
            "camera axes (x right, y down, looking down +z) where OpenGL's (y up, looking down -z) are expected; "
            "only in that case multiply each camera-to-world matrix by diag(1, -1, -1, 1)"
        )
    image_up = c2w.new_tensor([0.0, 1.0, 0.0]) if cameras.display_up is None else cameras.display_up.double()
    ups = torch.einsum("nij,nj->ni", c2w[:, :3, :3], image_up.expand(len(cameras), 3))
    up = ups.mean(0)
    if float(up.norm()) < min(0.5, UP_AGREEMENT / math.sqrt(len(cameras))) and not _upright_about(up, ups, forward):
        # (40 cameras 5-30° off the vertical, each rolled at random, had set the scene on its side, no word said)
        look_down = -forward.mean(0)  # cameras above what they look at: up is opposite their mean view
        clearly_opposite = float(up @ look_down) < -0.5 * float(up.norm() * look_down.norm())  # upright, from below
        if float(look_down.norm()) > float(up.norm()) and not clearly_opposite:
            warnings.warn(f"the cameras' image up axes cancel out (their mean is {float(up.norm()):.2f} long: images "
                          "rolled every way, or a capture from straight above): up is taken opposite their mean view "
                          "direction", stacklevel=2)
            up = look_down
        else:
            warnings.warn(f"the cameras' image up axes cancel out (their mean is {float(up.norm()):.2f} long: images "
                          "rolled every way), and their views give no better one: up is taken as that mean, which may "
                          "be a direction of chance (edits' views rolled or tilted)", stacklevel=2)
    up = up / up.norm().clamp_min(1e-12)
    rotation = _rotation_onto_z(up)
    scale = radius / distance
    frame = torch.eye(4, dtype=torch.float64)
    frame[:3, :3] = scale * rotation
    frame[:3, 3] = -scale * rotation @ centre
    return frame.float()


def _upright_about(up: torch.Tensor, ups: torch.Tensor, forward: torch.Tensor) -> bool:
    """Whether every camera's image up ``ups`` (N, 3) is within ``UPRIGHT_TOLERANCE_DEG`` of its view's upright one
    about ``up`` (a camera looking along it is upright at any roll): then the mean of the axes is short only because the
    views look steeply down (or up) at the object, and is up. An upright ring 70° above the horizon had been told that
    its image up axes cancel out (images rolled every way, or a capture from straight above)."""
    if not float(up.norm()) > 0:
        return False
    direction = up / up.norm()
    upright = direction - (forward @ direction)[:, None] * forward  # its length: the sine of the view's angle to up
    agreement = (ups * upright).sum(-1)
    return bool((agreement >= math.cos(math.radians(UPRIGHT_TOLERANCE_DEG)) * upright.norm(dim=-1) - 1e-9).all())


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
    return replace(cameras, c2w=c2w)  # intrinsics and lens distortion do not depend on the frame
