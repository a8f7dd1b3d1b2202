"""Cameras in the NeRF / OpenGL convention, their lens distortion, and the poses the method draws.

Camera-to-world matrices look down -z with +y up; pixel centres sit at i + 0.5.
Ray directions are unit length so ray parameters are world distances.
Lens distortion (OpenCV's radial-tangential model or its fisheye model, as COLMAP and
nerfstudio record them) is applied by casting each ray through the undistorted point
of its pixel: the distortion is inverted by Newton's method in float64 per ray, so the
images are used as captured (no resampling blur, no lost border).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from voxe_core.constants import NERF_SYNTHETIC_RADIUS


DISTORTION_MODELS = ("opencv", "fisheye")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")  # the columns of ``Cameras.distortion``
_NEWTON_STEPS = 20
_NEWTON_TOLERANCE = 1e-12  # in normalised image coordinates (about 1e-9 pixels)


@dataclass
class Cameras:
    """A batch of cameras sharing one image size (and one distortion model, if any).

    ``distortion`` (N, 6) holds ``DISTORTION_KEYS`` per camera in OpenCV's normalised
    coordinates (x right, y down, unit focal length), so resizing leaves it unchanged.
    ``distortion_model``: "opencv" (radial k1..k4 as 1 + k1 r² + ... + k4 r⁸, tangential
    p1, p2: OpenCV's and nerfstudio's OPENCV) or "fisheye" (θ_d = θ (1 + k1 θ² + ... + k4 θ⁸),
    OpenCV's and nerfstudio's OPENCV_FISHEYE; p1, p2 unused). None: a pinhole.
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

    def __post_init__(self):
        if self.distortion_model not in DISTORTION_MODELS:
            raise ValueError(f"distortion_model must be one of {', '.join(DISTORTION_MODELS)}, "
                             f"got {self.distortion_model!r}")

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, index) -> "Cameras":
        if isinstance(index, int):
            index = slice(index, index + 1)
        return replace(
            self, c2w=self.c2w[index], fx=self.fx[index], fy=self.fy[index], cx=self.cx[index], cy=self.cy[index],
            distortion=None if self.distortion is None else self.distortion[index],
        )

    @staticmethod
    def from_fov(c2w: torch.Tensor, fov_x: float, width: int, height: int) -> "Cameras":
        """NeRF-synthetic intrinsics: focal = 0.5 W / tan(0.5 fov_x), centred principal point."""
        c2w = torch.as_tensor(c2w, dtype=torch.float32)
        if c2w.dim() == 2:
            c2w = c2w[None]
        n = c2w.shape[0]
        focal = 0.5 * width / math.tan(0.5 * fov_x)
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
        )

    def undistorted(self) -> "Cameras":
        """The same cameras as pinholes (distortion ignored)."""
        return replace(self, distortion=None)


def check_views(images: torch.Tensor, cameras: Cameras, what: str = "images") -> None:
    """ValueError unless ``images`` are (N, H, W, 3) floating-point RGB in [0, 1], one per camera at its size: an
    RGBA or grey image had failed deep in a reshape, and 8-bit values (0..255) fitted every pixel to white."""
    if images.ndim != 4 or images.shape[-1] != 3 or not images.is_floating_point():
        raise ValueError(f"{what} must be (N, H, W, 3) floating-point RGB in [0, 1] on white, got "
                         f"{tuple(images.shape)} {images.dtype}")
    if images.shape[0] != len(cameras) or tuple(images.shape[1:3]) != (cameras.height, cameras.width):
        raise ValueError(f"{images.shape[0]} {what} of {tuple(images.shape[1:3])} do not match "
                         f"{len(cameras)} cameras of {(cameras.height, cameras.width)}")
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

    With lens distortion, each ray goes through the point whose distorted image is (u, v).
    """
    fx, fy = cameras.fx[camera_index], cameras.fy[camera_index]
    cx, cy = cameras.cx[camera_index], cameras.cy[camera_index]
    x, y = (u - cx) / fx, (v - cy) / fy
    if cameras.distortion is not None:
        x, y = undistort_points(x, y, cameras.distortion[camera_index], cameras.distortion_model)
    local = torch.stack([x, -y, -torch.ones_like(u)], dim=-1)
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
    xd: torch.Tensor, yd: torch.Tensor, coefficients: torch.Tensor, model: str = "opencv"
) -> tuple[torch.Tensor, torch.Tensor]:
    """The normalised points that ``distort_points`` takes to (xd, yd): Newton's method in float64.

    ``xd``, ``yd``: (R,); ``coefficients``: (R, 6) or (6,). Returns the inputs' dtype. OpenCV's
    model is inverted in 2-D with its exact Jacobian, the fisheye in 1-D on the angle θ (as
    OpenCV does); both start at the distorted point, within the basin for real lenses. A
    point no ray images (θ ≥ 90°) comes back NaN.

    Examples:
        >>> import torch
        >>> k = torch.tensor([0.1, -0.05, 0.0, 0.0, 0.001, -0.002])
        >>> x, y = undistort_points(*distort_points(torch.tensor([0.3]), torch.tensor([-0.2]), k), k)
        >>> round(float(x), 6), round(float(y), 6)
        (0.3, -0.2)
    """
    k1, k2, k3, k4, p1, p2 = coefficients.double().expand(xd.shape + (6,)).unbind(-1)
    target_x, target_y = xd.double(), yd.double()
    if model == "fisheye":
        theta_d = torch.hypot(target_x, target_y)
        theta = theta_d.clone()
        for _ in range(_NEWTON_STEPS):
            t2 = theta * theta
            residual = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            if residual.numel() == 0 or float(residual.abs().max()) < _NEWTON_TOLERANCE:
                break
            slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            theta = theta - residual / slope
        scale = torch.where(theta_d > 1e-12, torch.tan(theta) / theta_d.clamp_min(1e-12), torch.ones_like(theta))
        scale = torch.where((theta >= 0) & (theta < 0.5 * math.pi), scale, torch.full_like(scale, math.nan))
        return (target_x * scale).to(xd.dtype), (target_y * scale).to(yd.dtype)
    x, y = target_x.clone(), target_y.clone()
    for _ in range(_NEWTON_STEPS):
        fx, fy = distort_points(x, y, coefficients.double(), model)
        rx, ry = fx - target_x, fy - target_y
        if rx.numel() == 0 or max(float(rx.abs().max()), float(ry.abs().max())) < _NEWTON_TOLERANCE:
            break
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
        slope = k1 + r2 * (2 * k2 + r2 * (3 * k3 + r2 * 4 * k4))  # d radial / d r²
        a = radial + 2 * x * x * slope + 2 * p1 * y + 6 * p2 * x  # J = [[a, b], [c, d]]
        b = 2 * x * y * slope + 2 * p1 * x + 2 * p2 * y
        c = 2 * x * y * slope + 2 * p1 * x + 2 * p2 * y
        d = radial + 2 * y * y * slope + 6 * p1 * y + 2 * p2 * x
        det = a * d - b * c
        det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
        x, y = x - (d * rx - b * ry) / det, y - (a * ry - c * rx) / det
    return x.to(xd.dtype), y.to(yd.dtype)


def look_at(eye: torch.Tensor, target: torch.Tensor | None = None, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """Camera-to-world matrices (N, 4, 4) placing cameras at ``eye`` looking at ``target``.

    A camera on the ``up`` axis through its target has no defined azimuth: its right vector is +x (+y when it
    looks along x). Raises ``ValueError`` for a camera at its target or a non-finite one: no view direction.

    Examples:
        >>> look_at(torch.tensor([[3.0, 0, 0]]), up=(1.0, 0, 0))[0, :3, :3].det().item()  # on the up axis: a rotation
        1.0
    """
    eye = torch.as_tensor(eye, dtype=torch.float32).reshape(-1, 3)
    target = torch.zeros_like(eye) if target is None else torch.as_tensor(target, dtype=torch.float32).expand_as(eye)
    up_vec = torch.as_tensor(up, dtype=torch.float32).expand_as(eye)
    back = eye - target
    distance = back.norm(dim=-1, keepdim=True)
    if not bool(((distance > 0) & torch.isfinite(distance)).all()):
        raise ValueError(f"a camera at its target (or not finite) has no view direction: eye {eye.tolist()}, "
                         f"target {target.tolist()}")
    back = back / distance
    right = torch.cross(up_vec, back, dim=-1)
    degenerate = right.norm(dim=-1) < 1e-6
    for axis in torch.eye(3)[:2]:  # +x off the view direction, or +y where that leaves nothing
        off_axis = axis - (back * axis).sum(-1, keepdim=True) * back
        right = torch.where((degenerate & (off_axis.norm(dim=-1) >= 1e-3))[:, None], off_axis, right)
        degenerate = right.norm(dim=-1) < 1e-6
    right = right / right.norm(dim=-1, keepdim=True)
    cam_up = torch.cross(back, right, dim=-1)
    c2w = torch.eye(4).repeat(eye.shape[0], 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, cam_up, back, eye
    return c2w


def spherical_poses(
    elevation_deg: torch.Tensor, azimuth_deg: torch.Tensor, radius: float = NERF_SYNTHETIC_RADIUS,
    centre: torch.Tensor | None = None,
) -> torch.Tensor:
    """Poses on a sphere around ``centre`` (None: the origin), looking at it (elevation above the xy-plane, z up).

    The centre is where the object sits (``VoxelGrid.orbit_centre``): a capture's object need not sit at its
    frame's origin, and an orbit about the origin would swing it across the image.
    """
    el, az = torch.deg2rad(torch.as_tensor(elevation_deg, dtype=torch.float32)), torch.deg2rad(
        torch.as_tensor(azimuth_deg, dtype=torch.float32)
    )
    eye = radius * torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], dim=-1)
    if centre is None:
        return look_at(eye)
    centre = torch.as_tensor(centre, dtype=torch.float32).reshape(3)
    return look_at(eye + centre, centre)


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
