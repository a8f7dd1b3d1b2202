"""Cameras in the NeRF / OpenGL convention, their lens distortion, and the poses the method draws.

Camera-to-world matrices look down -z with +y up; pixel centres sit at i + 0.5.
Ray directions are unit length so ray parameters are world distances.
Lens distortion (OpenCV's radial-tangential model or its fisheye model, as COLMAP and
nerfstudio record them) is applied by casting each ray through the undistorted point
of its pixel (a fisheye's at its angle off the axis, so up to 180°): the distortion is
inverted by Newton's method in float64 per ray, so the images are used as captured (no
resampling blur, no lost border).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from voxe_core.constants import FLOAT32_MAX, MAX_RENDER_SIZE, MIN_RENDER_SIZE, NERF_SYNTHETIC_RADIUS
from voxe_core.devices import full_precision


DISTORTION_MODELS = ("opencv", "fisheye")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")  # the columns of ``Cameras.distortion``
_NEWTON_STEPS = 50
_RADIAL_STEPS = 30  # of Newton's start's one-dimensional solve (only a start: Newton then refines it)
_NEWTON_HALVINGS = 30  # of a step that would leave the lens's fold or not reduce the residual
_NEWTON_TOLERANCE = 1e-12  # in normalised image coordinates (about 1e-9 pixels)
_NEWTON_CONVERGED = 1e-9  # a point left farther than this from its image has no ray (NaN)
_FOLD_DIRECTIONS = 64  # first directions of ``fold_in_view``
_FOLD_LEVELS = 40  # halvings of its sectors that are still undecided
POSE_TOLERANCE = 1e-3  # of a camera's distance to its target: how far float32's rounding may move it (look_at)


@dataclass
class Cameras:
    """A batch of cameras sharing one image size (and one distortion model, if any).

    ``distortion`` (N, 6) holds ``DISTORTION_KEYS`` per camera in OpenCV's normalised
    coordinates (x right, y down, unit focal length), so resizing leaves it unchanged.
    ``distortion_model``: "opencv" (radial k1..k4 as 1 + k1 r² + ... + k4 r⁸, tangential
    p1, p2: OpenCV's and nerfstudio's OPENCV) or "fisheye" (θ_d = θ (1 + k1 θ² + ... + k4 θ⁸),
    OpenCV's and nerfstudio's OPENCV_FISHEYE; p1, p2 unused). None: a pinhole.
    ``display_up`` (N, 3): each image's up as it is displayed, in camera axes (x right, y up, z back): a phone's
    portrait photo stored landscape with an EXIF orientation is shown a quarter turn round, its up then the stored
    image's -x or +x (``voxe_core.data.display_up``). None: every image's +y, its stored up. It tells only which
    way is up (``voxe_core.scene_grid.scene_frame``): the rays are those of the stored pixels.
    """

    c2w: torch.Tensor  # (N, 4, 4) float32
    fx: torch.Tensor  # (N,)
    fy: torch.Tensor  # (N,)
    cx: torch.Tensor  # (N,)
    cy: torch.Tensor  # (N,)
    width: int
    height: int
    distortion: torch.Tensor | None = None  # (N, 6) float32, DISTORTION_KEYS
    distortion_model: str = "opencv"
    display_up: torch.Tensor | None = None  # (N, 3) float32

    def __post_init__(self):
        if self.distortion_model not in DISTORTION_MODELS:
            raise ValueError(f"distortion_model must be one of {', '.join(DISTORTION_MODELS)}, "
                             f"got {self.distortion_model!r}")

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, index) -> "Cameras":
        """The cameras at ``index`` (any tensor index); an int keeps one, counting from the end when negative."""
        if isinstance(index, int):
            if not -len(self) <= index < len(self):
                raise IndexError(f"camera {index} out of range: there are {len(self)} cameras")
            position = index % len(self)
            index = slice(position, position + 1)
        return replace(
            self, c2w=self.c2w[index], fx=self.fx[index], fy=self.fy[index], cx=self.cx[index], cy=self.cy[index],
            distortion=None if self.distortion is None else self.distortion[index],
            display_up=None if self.display_up is None else self.display_up[index],
        )

    @staticmethod
    def from_fov(c2w: torch.Tensor, fov_x: float, width: int, height: int) -> "Cameras":
        """NeRF-synthetic intrinsics: focal = 0.5 W / tan(0.5 fov_x), centred principal point."""
        focal = check_fov_x(fov_x, width)
        c2w = torch.as_tensor(c2w, dtype=torch.float32)
        if c2w.dim() == 2:
            c2w = c2w[None]
        n = c2w.shape[0]
        full = lambda v: torch.full((n,), float(v))  # noqa: E731
        return Cameras(c2w, full(focal), full(focal), full(width / 2), full(height / 2), width, height)

    def scaled(self, factor: float) -> "Cameras":
        """Cameras for images resized by ``factor`` (0.25 = downsample 4)."""
        return self.resized(max(1, int(round(self.width * factor))), max(1, int(round(self.height * factor))))

    def resized(self, width: int, height: int) -> "Cameras":
        """Cameras for images resampled to ``width`` x ``height`` over the same field of view."""
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy,
                       width=width, height=height)

    def to(self, device) -> "Cameras":
        return replace(
            self, c2w=self.c2w.to(device), fx=self.fx.to(device), fy=self.fy.to(device), cx=self.cx.to(device),
            cy=self.cy.to(device), distortion=None if self.distortion is None else self.distortion.to(device),
            display_up=None if self.display_up is None else self.display_up.to(device),
        )

    def undistorted(self) -> "Cameras":
        """The same cameras as pinholes (distortion ignored)."""
        return replace(self, distortion=None)


def check_angle(name: str, degrees: float) -> None:
    """ValueError naming the setting ``name`` unless ``degrees`` is a finite angle: a NaN or infinite one had failed
    only deep in the poses ("camera positions must be finite"), or read every pose as a "side" view (a NaN front)."""
    if not math.isfinite(degrees):
        raise ValueError(f"{name} must be a finite angle in degrees, got {degrees}")


def check_fov_x(fov_x: float, width: int | None = None) -> float | None:
    """ValueError unless ``fov_x`` is a horizontal field of view in (0, π) radians: at 0 the focal is infinite, at π
    zero, and past π negative (a mirrored camera). Given the image's ``width`` in pixels, also unless its focal length
    there fits float32, which it returns (the stages' configs check their render size's, so such an angle is refused
    as they are made, not at their first render)."""
    if not 0 < fov_x < math.pi:  # as "not in range": NaN fails every comparison
        raise ValueError(f"fov_x must be in (0, pi) radians, got {fov_x}")
    if width is None:
        return None
    # A vanishing angle's focal overflows float32 (1e-40 had failed in torch.full, "value cannot be converted
    # to type float without overflow") or divides by a tangent of 0 (5e-324: a ZeroDivisionError).
    half_width = math.tan(0.5 * fov_x)
    focal = 0.5 * width / half_width if half_width > 0 else math.inf
    if not focal <= FLOAT32_MAX:
        raise ValueError(f"fov_x {fov_x} radians is too narrow: its focal length across {width} pixels, "
                         f"{focal:.3g}, is beyond float32's range (3.4e38)")
    return focal


def check_render_size(render_size: int) -> None:
    """ValueError naming ``render_size`` unless it lies in [MIN_RENDER_SIZE, MAX_RENDER_SIZE] pixels, the bounds of the
    edit's and the refinement's renders (the service's and the CLI's too). Above, nothing is gained (the guidance
    and the attention maps work at 768 px at most) and memory runs out: a 50,000 px side, 2.5e9 rays a render, had
    been taken as the config was made, to fail only at the first render."""
    if render_size < MIN_RENDER_SIZE:
        raise ValueError(f"render_size must be at least {MIN_RENDER_SIZE} px, got {render_size}")
    if render_size > MAX_RENDER_SIZE:
        raise ValueError(f"render_size must be at most {MAX_RENDER_SIZE} px (the service's and the CLI's limit), got "
                         f"{render_size}")


def check_views(images: torch.Tensor, cameras: Cameras, what: str = "images") -> None:
    """ValueError unless ``images`` are (N, H, W, 3) floating-point RGB in [0, 1], one per camera at its size: an
    RGBA or grey image had failed deep in a reshape, and 8-bit values (0..255) fitted every pixel to white."""
    if images.ndim != 4 or images.shape[-1] != 3 or not images.is_floating_point():
        raise ValueError(f"{what} must be (N, H, W, 3) floating-point RGB in [0, 1] on white, got "
                         f"{tuple(images.shape)} {images.dtype}")
    if images.shape[0] != len(cameras) or tuple(images.shape[1:3]) != (cameras.height, cameras.width):
        raise ValueError(f"{images.shape[0]} {what} of {tuple(images.shape[1:3])} do not match "
                         f"{len(cameras)} cameras of {(cameras.height, cameras.width)}")
    if images.shape[0] and 0 in images.shape[1:3]:  # (a fit had failed resampling them: adaptive_avg_pool2d's error)
        raise ValueError(f"{what} of {images.shape[1]}x{images.shape[2]} pixels hold no pixel to fit")
    if images.numel():
        low, high = images.aminmax()
        if not (low >= 0 and high <= 1):  # as "not in range": NaN fails every comparison
            raise ValueError(f"{what} must hold values in [0, 1] (8-bit values divided by 255), got values from "
                             f"{float(low):g} to {float(high):g}")


def camera_rays(cameras: Cameras, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit directions, (H*W, 3) each, row-major over the image."""
    device = cameras.c2w.device
    j, i = torch.meshgrid(
        torch.arange(cameras.height, device=device, dtype=torch.float32) + 0.5,
        torch.arange(cameras.width, device=device, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    return pixel_rays(cameras, torch.full_like(i, index, dtype=torch.long).reshape(-1), i.reshape(-1), j.reshape(-1))


def pixel_rays(
    cameras: Cameras, camera_index: torch.Tensor, u: torch.Tensor, v: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through image coordinates (u right, v down, in pixels) of the given cameras.

    With lens distortion, each ray goes through the point whose distorted image is (u, v); a fisheye's leaves at
    its angle θ, as (sin θ x / r, sin θ y / r, cos θ), so past 90° too, where no point of the image plane lies on
    it (θ ≥ 180°: NaN). In the cameras' precision whatever autocast says: under bf16 autocast the rotation's einsum
    had made them bf16, up to 0.0075 rad (9 pixels of an 800 px view) off, and a fit under it (the reconstruction's
    rays, the attention grids') had trained every pixel's colour along another pixel's ray.
    """
    with full_precision(cameras.c2w):
        return _pixel_rays(cameras, camera_index, u, v)


def _pixel_rays(
    cameras: Cameras, camera_index: torch.Tensor, u: torch.Tensor, v: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    fx, fy = cameras.fx[camera_index], cameras.fy[camera_index]
    cx, cy = cameras.cx[camera_index], cameras.cy[camera_index]
    x, y = (u - cx) / fx, (v - cy) / fy
    z = torch.ones_like(x)
    if cameras.distortion is not None and cameras.distortion_model == "fisheye":
        theta = fisheye_angles(x, y, cameras.distortion, camera_index)
        theta = theta.masked_fill(theta >= math.pi, math.nan)
        theta_d = torch.hypot(x, y)
        scale = torch.where(theta_d > 0, theta.sin() / theta_d, torch.ones_like(theta))
        x, y, z = x * scale, y * scale, theta.cos()
    elif cameras.distortion is not None:
        x, y = undistort_points(x, y, cameras.distortion, camera_index)
    local = torch.stack([x, -y, -z], dim=-1)
    c2w = cameras.c2w[camera_index]
    directions = torch.einsum("nij,nj->ni", c2w[:, :3, :3], local)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    origins = c2w[:, :3, 3].expand_as(directions)
    return origins.contiguous(), directions


def distort_points(
    x: torch.Tensor, y: torch.Tensor, coefficients: torch.Tensor, model: str = "opencv"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the lens images the normalised point (x, y) (OpenCV axes: y down, z forward).

    ``x``, ``y``: (R,); ``coefficients``: (R, 6) or (6,), ``DISTORTION_KEYS``. Computed in the
    inputs' dtype.

    Examples:
        >>> import torch
        >>> k = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
        >>> xd, yd = distort_points(torch.tensor([0.5]), torch.tensor([0.0]), k)
        >>> round(float(xd), 4)  # 0.5 * (1 + 0.1 * 0.25)
        0.5125
    """
    k1, k2, k3, k4, p1, p2 = coefficients.to(x).expand(x.shape + (6,)).unbind(-1)
    r2 = x * x + y * y
    if model == "fisheye":
        r = r2.sqrt()
        theta = torch.atan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        ratio = torch.where(r > 1e-12, theta_d / r.clamp_min(1e-12), torch.ones_like(r))
        return x * ratio, y * ratio
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xy = x * y
    return (x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy)


def undistort_points(
    xd: torch.Tensor, yd: torch.Tensor, coefficients: torch.Tensor, lens: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The normalised points that OPENCV's ``distort_points`` takes to (xd, yd): Newton's method in float64.

    ``xd``, ``yd``: (R,); ``coefficients``: (R, 6) or (6,), or (C, 6) with ``lens`` (R,) naming each point's row
    (a capture's few lenses are then analysed once, not once per point). Returns the inputs' dtype. (A fisheye's
    rays come from their angles, ``fisheye_angles``: they may lie past 90°, where no image-plane point is.) Only
    the branch that holds the optical axis counts: a point past the lens's fold (where the radial map stops
    increasing), where the map's Jacobian is not positive, or where Newton did not converge comes back NaN.

    Examples:
        >>> import torch
        >>> k = torch.tensor([0.1, -0.05, 0.0, 0.0, 0.001, -0.002])
        >>> x, y = undistort_points(*distort_points(torch.tensor([0.3]), torch.tensor([-0.2]), k), k)
        >>> round(float(x), 6), round(float(y), 6)
        (0.3, -0.2)
    """
    x, y = _invert_radial_tangential(xd.double(), yd.double(), coefficients.double().reshape(-1, 6), lens)
    return x.to(xd.dtype), y.to(yd.dtype)


def fisheye_angles(
    xd: torch.Tensor, yd: torch.Tensor, coefficients: torch.Tensor, lens: torch.Tensor | None = None
) -> torch.Tensor:
    """(R,) the angle θ off the optical axis of the ray a fisheye images at each normalised point (xd, yd): its
    θ_d = θ (1 + k1 θ² + ... + k4 θ⁸) inverted, in the inputs' dtype (``coefficients``, ``lens``: as
    ``undistort_points`` takes them). NaN past the lens's fold or unconverged; θ ≥ π is no ray, for callers to
    refuse.

    Examples:
        >>> import torch
        >>> round(float(fisheye_angles(torch.tensor([2.0]), torch.tensor([0.0]), torch.zeros(6))), 6)  # equidistant
        2.0
    """
    table = coefficients.double().reshape(-1, 6)
    # θ_d(θ) is OPENCV's radial map of the angle: invert it on the vector θ (x, y) / r.
    radial = torch.cat([table[:, :4], torch.zeros_like(table[:, 4:])], 1)  # p1, p2: unused by the fisheye
    return torch.hypot(*_invert_radial_tangential(xd.double(), yd.double(), radial, lens)).to(xd.dtype)


def _invert_radial_tangential(
    xd: torch.Tensor, yd: torch.Tensor, table: torch.Tensor, lens: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """OPENCV's model inverted inside its fold, float64 (``undistort_points``' contract, NaN included).

    Newton with its exact Jacobian from the radial-only inverse (``_radial_start``), each step halved while it would
    leave the fold or not reduce the residual, so the iterates stay on the branch that holds the optical axis: past
    the fold a second root also maps back to the pixel, and its rays jump.
    Each step works only on the points not yet converged, nor stuck.
    """
    lens = torch.arange(len(table), device=xd.device).expand(xd.shape) if lens is None else lens
    fold, coefficients = _radial_folds(table)[lens], table[lens]
    target = torch.stack([xd.double(), yd.double()], -1)
    point = _radial_start(target, coefficients, fold)
    error = _residual(point, target, coefficients)
    stuck = torch.zeros_like(fold, dtype=torch.bool)
    for _ in range(_NEWTON_STEPS):
        active = ((error.norm(dim=-1) >= _NEWTON_TOLERANCE) & ~stuck).nonzero()[:, 0]
        if len(active) == 0:
            break
        point[active], error[active], stuck[active] = _newton_step(
            point[active], error[active], target[active], coefficients[active], fold[active])
    a, b, d = _jacobian(point, coefficients)
    lost = (error.norm(dim=-1) > _NEWTON_CONVERGED) | (a * d - b * b <= 0)
    return point.masked_fill(lost[:, None], math.nan).unbind(-1)


def _radial_start(target: torch.Tensor, coefficients: torch.Tensor, fold: torch.Tensor) -> torch.Tensor:
    """Newton's start for (R, 2) targets: each on its own ray from the axis, at the radius whose radial-only image
    has the target's radius, taken on the monotone branch inside the fold (its edge where the target lies past
    the fold's image). The target itself is no start: near or past the fold its Jacobian is nearly singular and
    Newton from there finds nothing, or the far branch's root, though the axis's branch has one.

    The radius solves ρ (1 + k1 ρ² + ... + k4 ρ⁸) = |target| by Newton kept inside a bracket that bisection
    narrows where Newton would leave it (the radial map increases on [0, √fold), so the bracket always holds the
    root there).
    """
    k1, k2, k3, k4 = coefficients[:, :4].unbind(-1)
    goal = target.norm(dim=-1)
    low, high = torch.zeros_like(goal), fold.sqrt()  # inf where the lens never folds
    radius = torch.minimum(goal, 0.5 * high)
    for _ in range(_RADIAL_STEPS):
        s = radius * radius
        excess = radius * (1 + s * (k1 + s * (k2 + s * (k3 + s * k4)))) - goal
        if not bool((excess.abs() > _NEWTON_TOLERANCE).any()):
            break
        slope = 1 + s * (3 * k1 + s * (5 * k2 + s * (7 * k3 + s * 9 * k4)))
        low, high = torch.where(excess < 0, radius, low), torch.where(excess > 0, radius, high)
        radius = radius - excess / slope
        radius = torch.where((radius >= low) & (radius <= high), radius, 0.5 * (low + high))
    return target * torch.where(goal > 0, radius / goal, torch.zeros_like(goal))[:, None]


def _newton_step(point, error, target, coefficients, fold):
    """One Newton step of (R, 2) points, each halved while it would leave the fold or not reduce the residual:
    the new points, their residuals, and whether a point was refused every halving (it stays, and would again).
    Each halving works only on the points still refused (one stubborn point had redone them all)."""
    a, b, d = _jacobian(point, coefficients)
    det = a * d - b * b
    det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
    rx, ry = error.unbind(-1)
    step = torch.stack([d * rx - b * ry, a * ry - b * rx], -1) / det[:, None]
    norm = error.norm(dim=-1)
    new_point = point - step
    new_error = _residual(new_point, target, coefficients)
    taken = (new_point.square().sum(-1) < fold) & (new_error.norm(dim=-1) <= norm)
    point, error = torch.where(taken[:, None], new_point, point), torch.where(taken[:, None], new_error, error)
    pending = (~taken).nonzero()[:, 0]
    for halving in range(1, _NEWTON_HALVINGS):
        if len(pending) == 0:
            break
        new_point = point[pending] - 0.5**halving * step[pending]
        new_error = _residual(new_point, target[pending], coefficients[pending])
        taken = (new_point.square().sum(-1) < fold[pending]) & (new_error.norm(dim=-1) <= norm[pending])
        point[pending[taken]], error[pending[taken]] = new_point[taken], new_error[taken]
        pending = pending[~taken]
    refused = torch.zeros_like(norm, dtype=torch.bool)
    refused[pending] = True
    return point, error, refused


def _residual(point: torch.Tensor, target: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
    return torch.stack(distort_points(*point.unbind(-1), coefficients), -1) - target


def _jacobian(point: torch.Tensor, coefficients: torch.Tensor):
    """OPENCV's distortion Jacobian at (R, 2) points: (a, b, d) of the symmetric [[a, b], [b, d]]."""
    x, y = point.unbind(-1)
    k1, k2, k3, k4, p1, p2 = coefficients.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    slope = k1 + r2 * (2 * k2 + r2 * (3 * k3 + r2 * 4 * k4))  # d radial / d r²
    return (radial + 2 * x * x * slope + 2 * p1 * y + 6 * p2 * x,
            2 * x * y * slope + 2 * p1 * x + 2 * p2 * y,
            radial + 2 * y * y * slope + 6 * p1 * y + 2 * p2 * x)


def _radial_folds(table: torch.Tensor) -> torch.Tensor:
    """(C,) for each row of ``table`` (C, 6), the r² where the radial map r (1 + k1 r² + ... + k4 r⁸) first stops
    increasing (inf: it never does). Inside it each image point has one ray; past it the image folds over.

    The map's slope is p(s) = 1 + 3 k1 s + 5 k2 s² + 7 k3 s³ + 9 k4 s⁴ (s = r²); its roots are 1 / the roots of the
    monic s⁴ p(1/s), whose companion matrix needs no leading coefficient to be non-zero.
    """
    finite = torch.isfinite(table).all(-1)
    k1, k2, k3, k4 = table.detach().cpu().where(finite.cpu()[:, None], 0).unbind(-1)[:4]
    companion = torch.zeros(len(table), 4, 4, dtype=torch.float64)
    companion[:, 1:, :3] = torch.eye(3, dtype=torch.float64)
    companion[:, :, 3] = -torch.stack([9 * k4, 7 * k3, 5 * k2, 3 * k1], -1)
    roots = torch.linalg.eigvals(companion)
    # A double root (p touching zero: a fold) can come back as a pair with a tiny imaginary part.
    real = (roots.imag.abs() <= 1e-6 * roots.abs()) & (roots.real > 0)
    largest = torch.where(real, roots.real, torch.zeros_like(roots.real)).amax(-1)
    return (1 / largest).to(table.device).where(finite, math.nan)


def fold_in_view(fx: float, fy: float, cx: float, cy: float, coefficients: torch.Tensor, width: int,
                 height: int) -> tuple[float, float] | None:
    """A pixel of the image [0, width] x [0, height] onto which an OPENCV lens folds the sheet holding its optical
    axis (None: it folds none), for a load to refuse the lens: the pixels near that caustic have several rays.

    The sheet: along each direction u from the axis, the points r u with r < ρ(u), ρ(u) the smallest positive root
    of g(r) = det J(r u) (J the map's Jacobian; det J(0) = 1), capped at the radial fold (``_radial_folds``), past
    which ``undistort_points`` gives no ray. Its fold points are the ρ(u) u short of that cap: there det J = 0
    first, and an island where det J < 0 inside the radial fold (tangential terms) counts wherever its caustic
    lies, though every sampled pixel has its ray. Along a direction g is a polynomial of degree 16 in r, so ρ is
    exact per direction; between directions, |∂g/∂φ| ≤ G(r), a polynomial majorant in r alone
    (``_fold_majorants``). So over the sector |φ - φ_i| ≤ h/2, det J vanishes only at radii where
    g_i - (h/2) G ≤ 0 ≤ g_i + (h/2) G, and every fold point lies short of ρ⁺, the first root of g_i + (h/2) G
    (there g ≤ 0): the roots of both bound intervals [r₀, r₁] that hold them all (a direction grazing an island
    leaves one short interval about the grazing point, not all of [ρ(φ_i), ρ⁺]). The lens moves points by at most
    ‖J‖ ≤ K(r) per unit of radius and r K(r) per radian, so an interval's fold points are imaged within
    K(r₁) ((r₁ - r₀) / 2 + r₁ h / 2) of the image of its middle point. A sector whose disks all miss the image is
    done; one whose exact fold point lands in the image is refused; the rest are halved, up to
    ``_FOLD_LEVELS`` times (still undecided then: a caustic touching the image's edge, or a direction tangent to the
    fold curve; refused). A sheet that the radial fold never caps is searched out to ``_beyond_view``, past which
    nothing lands in view. Exact up to float64 rounding of the roots.
    """
    k = coefficients.double().cpu()
    low = torch.tensor([-cx / fx, -cy / fy], dtype=torch.float64)
    high = torch.tensor([(width - cx) / fx, (height - cy) / fy], dtype=torch.float64)
    cap = math.sqrt(float(_radial_folds(k[None])[0]))
    if math.isinf(cap):
        cap = _beyond_view(k, float(torch.maximum(low.abs(), high.abs()).norm()))
    majorant, norm_bound = _fold_majorants(k)
    step = 2 * math.pi / _FOLD_DIRECTIONS
    angles = (torch.arange(_FOLD_DIRECTIONS, dtype=torch.float64) + 0.5) * step
    for _ in range(_FOLD_LEVELS):
        u = torch.stack([angles.cos(), angles.sin()], -1)
        g = _jacobian_determinant_along(u, k)
        fold = _first_root(g).clamp_max(cap)
        fold_point = torch.stack(distort_points(fold * u[:, 0], fold * u[:, 1], k), -1)
        landed = (fold < cap) & ((fold_point >= low) & (fold_point <= high)).all(-1)
        if landed.any():
            x, y = fold_point[int(landed.int().argmax())].tolist()
            return x * fx + cx, y * fy + cy
        spread = 0.5 * step * majorant
        below, above = g - spread, g + spread
        above_roots = _positive_roots(above)
        far = above_roots.amin(-1).clamp_max(cap)
        ends = torch.cat([torch.zeros_like(far)[:, None], _positive_roots(below), above_roots,
                          far[:, None]], -1).minimum(far[:, None]).sort(-1).values
        start, stop = ends[:, :-1], ends[:, 1:]
        middle = 0.5 * (start + stop)
        candidate = (_polyval(below.T[..., None], middle) <= 0) & (_polyval(above.T[..., None], middle) >= 0)
        candidate &= start < cap
        centre = torch.stack(distort_points(middle * u[:, :1], middle * u[:, 1:], k), -1)
        reach = _polyval(norm_bound, stop) * (0.5 * (stop - start) + 0.5 * stop * step)
        gap = ((low - centre).clamp_min(0) + (centre - high).clamp_min(0)).norm(dim=-1)
        open_ = candidate & (gap <= reach)
        if not open_.any():
            return None
        sector = open_.any(-1)
        angles, step = torch.cat([angles[sector] - 0.25 * step, angles[sector] + 0.25 * step]), 0.5 * step
    x, y = torch.maximum(torch.minimum(centre[open_][0], high), low).tolist()
    return x * fx + cx, y * fy + cy


def _beyond_view(k: torch.Tensor, reach: float) -> float:
    """A radius past which a lens that never folds radially (r R(r²) increasing) images every point farther than
    ``reach`` from the axis, so no fold point past it lands in view: the tangential part is r² (p̃ + 2 (u·p̃) u),
    p̃ = (p2, p1), of length between |p| r² and 3 |p| r², so |D(r u)| ≥ r R(r²) - 3 |p| r² (which grows without
    bound when any k is non-zero) and ≥ |p| r² - r R(r²) (when none is); past the largest root of the one that
    grows, it exceeds ``reach``."""
    k1, k2, k3, k4 = k[:4].tolist()
    p = float(torch.hypot(k[4], k[5]))
    if any(k[:4]):
        bound = [-reach, 1.0, -3 * p, k1, 0.0, k2, 0.0, k3, 0.0, k4]
    else:
        bound = [-reach, -1.0, p]
    while bound[-1] == 0:
        bound.pop()
    reversed_bound = torch.tensor(bound[::-1], dtype=torch.float64) / bound[-1]  # its roots: 1 / the bound's
    return 1 / float(_first_root(reversed_bound[None])[0])


def _jacobian_determinant_along(u: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """(N, 17) the coefficients (in r, lowest first) of det J(r u) along unit directions ``u`` (N, 2), J as
    ``_jacobian``'s. Expanding a d - b² there, with s = r², R(s) = 1 + k1 s + ... + k4 s⁴ and e = u·(p2, p1):
    det J = R (R + 2 s R') + 4 r e (2 R + s R') + r² (16 e² - 4 |p|²), the direction entering through e alone."""
    radial, slope = _radial_polynomials(k[:4])
    e = u[:, :1] * k[5] + u[:, 1:] * k[4]
    along = torch.zeros(len(u), 17, dtype=torch.float64)
    along += _polymul(radial, radial + 2 * slope)
    along[:, 1:10] += 4 * e * (2 * radial + slope)
    along[:, 2:3] += 16 * e * e - 4 * float(k[4] ** 2 + k[5] ** 2)
    return along


def _fold_majorants(k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Coefficients (in r, non-negative) of G(r) ≥ |∂ det J / ∂φ| and K(r) ≥ ‖J‖ on the circle of radius r.

    G: det J varies with φ through e alone (``_jacobian_determinant_along``), de/dφ = u^⊥·(p2, p1) and |e| are at
    most |p|, so G = |p| (4 r (2 R̄ + s R̄') + 32 |p| r²), R̄ being R with |k|. K: the symmetric J's norm is at most
    its largest row sum, with |a|, |d| ≤ R̄ + 2 s R̄' + 6 |p| r and |b| ≤ s R̄' + 2 |p| r (``_jacobian``)."""
    radial, slope = _radial_polynomials(k[:4].abs())
    p = float(torch.hypot(k[4], k[5]))
    majorant = torch.zeros(17, dtype=torch.float64)
    majorant[1:10] = 4 * p * (2 * radial + slope)
    majorant[2] += 32 * p * p
    norm_bound = radial + 3 * slope
    norm_bound[1] += 8 * p
    return majorant, norm_bound


def _radial_polynomials(k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The coefficients (in r, lowest first, 9 each) of R(r²) = 1 + k1 r² + ... + k4 r⁸ and of r² R'(r²)."""
    k1, k2, k3, k4 = k.tolist()
    return (torch.tensor([1.0, 0, k1, 0, k2, 0, k3, 0, k4], dtype=torch.float64),
            torch.tensor([0.0, 0, k1, 0, 2 * k2, 0, 3 * k3, 0, 4 * k4], dtype=torch.float64))


def _polymul(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """The product of two polynomials given by their coefficients, lowest first."""
    product = torch.zeros(len(p) + len(q) - 1, dtype=torch.float64)
    for power, coefficient in enumerate(p.tolist()):
        product[power:power + len(q)] += coefficient * q
    return product


def _polyval(p: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Polynomial ``p`` (coefficients lowest first, along its first dimension) at ``r``, by Horner's rule."""
    value = torch.zeros_like(r)
    for coefficient in p.flip(0):
        value = value * r + coefficient
    return value


def _first_root(g: torch.Tensor) -> torch.Tensor:
    """(N,) the smallest positive root of each polynomial g (N, n) (lowest coefficient first, g(0) = 1; inf: none)."""
    return _positive_roots(g).amin(-1)


def _positive_roots(g: torch.Tensor) -> torch.Tensor:
    """(N, n - 1) the positive roots of each polynomial g (N, n) (lowest coefficient first, g(0) = 1), inf in the
    other places: 1 / those of the monic reversed polynomial, its companion matrix's eigenvalues. A pair with a
    tiny imaginary part counts (g touching zero)."""
    n = g.shape[-1] - 1
    companion = torch.zeros(len(g), n, n, dtype=torch.float64)
    companion[:, 1:, :-1] = torch.eye(n - 1, dtype=torch.float64)
    companion[:, :, -1] = -g[:, 1:].flip(-1)
    roots = torch.linalg.eigvals(companion)
    real = (roots.imag.abs() <= 1e-6 * roots.abs()) & (roots.real > 0)
    return 1 / torch.where(real, roots.real, torch.zeros_like(roots.real))


def look_at(eye: torch.Tensor, target: torch.Tensor | None = None, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """Camera-to-world matrices (N, 4, 4, float32) placing cameras at ``eye`` looking at ``target``.

    A camera on the ``up`` axis through its target has no defined azimuth: its right vector is +x (+y when it
    looks along x). Computed in float64 from the positions as given (float32's norm overflows past about 1.8e19
    and underflows below 1e-19: such cameras had been called "at their target"). Raises ``ValueError`` for a
    non-finite eye or target, a camera at its target (no view direction), and a camera a float32 pose cannot
    place: beyond float32's range, or so far from the origin for its distance to the target that rounding its
    position moves it by more than ``POSE_TOLERANCE`` of that distance (a ring of radius 4 around a point more
    than about 6.7e4 from the origin; at 1e7 float32 had moved its cameras by up to an eighth of the radius).

    Examples:
        >>> look_at(torch.tensor([[3.0, 0, 0]]), up=(1.0, 0, 0))[0, :3, :3].det().item()  # on the up axis: a rotation
        1.0
    """
    eye = torch.as_tensor(eye, dtype=torch.float64).reshape(-1, 3)
    target = torch.zeros_like(eye) if target is None else torch.as_tensor(target, dtype=torch.float64).expand_as(eye)
    up_vec = torch.as_tensor(up, dtype=torch.float64).expand_as(eye)
    for name, points in (("eye", eye), ("target", target)):  # within float32's range: so is their distance
        if not bool(torch.isfinite(points).all()):
            raise ValueError(f"camera positions and targets must be finite, got {name} {points.tolist()}")
        if bool((points.abs() > torch.finfo(torch.float32).max).any()):
            raise ValueError(f"camera positions and targets must lie within float32's range (3.4e38), got {name} "
                             f"{points.tolist()}")
    back = eye - target
    distance = back.norm(dim=-1, keepdim=True)
    at_target = ~(distance[:, 0] > 0)
    if bool(at_target.any()):
        i = int(at_target.nonzero()[0])
        raise ValueError(f"a camera at its target has no view direction: eye {eye[i].tolist()}, target "
                         f"{target[i].tolist()}")
    farthest = eye.abs().amax(dim=-1)
    rounding = farthest * 2.0 ** -24  # float32's rounding of the position: at most half a step
    unplaceable = rounding > POSE_TOLERANCE * distance[:, 0]
    if bool(unplaceable.any()):
        i = int(unplaceable.nonzero()[0])
        raise ValueError(f"a camera at {eye[i].tolist()} looking at {target[i].tolist()} from "
                         f"{float(distance[i]):.3g} away cannot be placed by a float32 pose (which rounds its "
                         f"position by up to {float(rounding[i]):.3g}): move the scene's origin near its object")
    back = back / distance
    right = torch.cross(up_vec, back, dim=-1)
    degenerate = right.norm(dim=-1) < 1e-6
    for axis in torch.eye(3, dtype=torch.float64)[:2]:  # +x off the view direction, or +y where that leaves nothing
        off_axis = axis - (back * axis).sum(-1, keepdim=True) * back
        right = torch.where((degenerate & (off_axis.norm(dim=-1) >= 1e-3))[:, None], off_axis, right)
        degenerate = right.norm(dim=-1) < 1e-6
    right = right / right.norm(dim=-1, keepdim=True)
    cam_up = torch.cross(back, right, dim=-1)
    c2w = torch.eye(4, dtype=torch.float64).repeat(eye.shape[0], 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, cam_up, back, eye
    return c2w.float()


POLE_COSINE = 1e-6
"""A pose whose elevation's cosine is below this sits at a pole for :func:`spherical_poses` (look_at's own test)."""


def spherical_poses(
    elevation_deg: torch.Tensor, azimuth_deg: torch.Tensor, radius: float = NERF_SYNTHETIC_RADIUS,
    centre: torch.Tensor | None = None,
) -> torch.Tensor:
    """Poses on a sphere around ``centre`` (None: the origin), looking at it (elevation above the xy-plane, z up).

    The centre is where the object sits (``VoxelGrid.orbit_centre``): a capture's object need not sit at its
    frame's origin, and an orbit about the origin would swing it across the image.

    A pose at a pole (elevation ±90°, where ``look_at`` has no azimuth to go by) is turned by its azimuth as the
    poses just off the pole are: a ring at 90° had been one pose repeated, a turntable of identical frames.
    """
    el, az = torch.deg2rad(torch.as_tensor(elevation_deg, dtype=torch.float32)), torch.deg2rad(
        torch.as_tensor(azimuth_deg, dtype=torch.float32)
    )
    eye = radius * torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], dim=-1)
    # At a pole, up is the image up the poses approaching it have, -sin(el)·(cos az, sin az) (z up elsewhere).
    pole = (el.cos().abs() < POLE_COSINE).unsqueeze(-1)
    below = -el.sin().sign()
    pole_up = torch.stack([below * az.cos(), below * az.sin(), torch.zeros_like(below * az)], dim=-1)
    up = torch.where(pole, pole_up, eye.new_tensor([0.0, 0.0, 1.0])).double().reshape(-1, 3)
    if centre is None:
        return look_at(eye, up=up)
    centre = torch.as_tensor(centre, dtype=torch.float64).reshape(3)
    return look_at(eye.double() + centre, centre, up=up)  # float64: float32 had rounded a far centre's ring away


def random_hemisphere_poses(
    n: int,
    generator: torch.Generator | None = None,
    radius: float = NERF_SYNTHETIC_RADIUS,
    min_zenith_deg: float = 15.0,
    max_zenith_deg: float = 90.0,
    centre: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Upper-hemisphere training poses as the authors draw them (zenith uniform in [15°, 90°]), around ``centre``.

    Returns (c2w, elevation_deg, azimuth_deg) so callers can pick a view word.
    """
    zenith = min_zenith_deg + (max_zenith_deg - min_zenith_deg) * torch.rand(n, generator=generator)
    azimuth = 360.0 * torch.rand(n, generator=generator)
    elevation = 90.0 - zenith
    return spherical_poses(elevation, azimuth, radius, centre), elevation, azimuth


def ring_poses(
    n: int, elevation_deg: float = 30.0, radius: float = NERF_SYNTHETIC_RADIUS, centre: torch.Tensor | None = None
) -> torch.Tensor:
    """``n`` poses evenly spaced on a 360° ring around ``centre`` (turntables and the evaluation protocol)."""
    azimuth = torch.arange(n, dtype=torch.float32) * (360.0 / n)
    return spherical_poses(torch.full((n,), float(elevation_deg)), azimuth, radius, centre)
