"""Pinhole cameras in the NeRF / OpenGL convention and the poses the method draws.

Camera-to-world matrices look down -z with +y up; pixel centres sit at i + 0.5.
Ray directions are unit length so ray parameters are world distances.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from voxe_core.constants import NERF_SYNTHETIC_RADIUS


@dataclass
class Cameras:
    """A batch of pinhole cameras sharing one image size."""

    c2w: torch.Tensor  # (N, 4, 4) float32
    fx: torch.Tensor  # (N,)
    fy: torch.Tensor  # (N,)
    cx: torch.Tensor  # (N,)
    cy: torch.Tensor  # (N,)
    width: int
    height: int

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, index) -> "Cameras":
        if isinstance(index, int):
            index = slice(index, index + 1)
        return Cameras(
            self.c2w[index], self.fx[index], self.fy[index], self.cx[index], self.cy[index],
            self.width, self.height,
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
        return Cameras(self.c2w, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    def to(self, device) -> "Cameras":
        return Cameras(
            self.c2w.to(device), self.fx.to(device), self.fy.to(device), self.cx.to(device),
            self.cy.to(device), self.width, self.height,
        )


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
    """Rays through image coordinates (u right, v down, in pixels) of the given cameras."""
    fx, fy = cameras.fx[camera_index], cameras.fy[camera_index]
    cx, cy = cameras.cx[camera_index], cameras.cy[camera_index]
    local = torch.stack([(u - cx) / fx, -(v - cy) / fy, -torch.ones_like(u)], dim=-1)
    c2w = cameras.c2w[camera_index]
    directions = torch.einsum("nij,nj->ni", c2w[:, :3, :3], local)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    origins = c2w[:, :3, 3].expand_as(directions)
    return origins.contiguous(), directions


def look_at(eye: torch.Tensor, target: torch.Tensor | None = None, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """Camera-to-world matrices (N, 4, 4) placing cameras at ``eye`` looking at ``target``."""
    eye = torch.as_tensor(eye, dtype=torch.float32).reshape(-1, 3)
    target = torch.zeros_like(eye) if target is None else torch.as_tensor(target, dtype=torch.float32).expand_as(eye)
    up_vec = torch.as_tensor(up, dtype=torch.float32).expand_as(eye)
    back = eye - target
    back = back / back.norm(dim=-1, keepdim=True)
    right = torch.cross(up_vec, back, dim=-1)
    # A camera on the up axis has no defined azimuth: pick +x as its right vector.
    degenerate = right.norm(dim=-1) < 1e-6
    right[degenerate] = torch.tensor([1.0, 0.0, 0.0])
    right = right / right.norm(dim=-1, keepdim=True)
    cam_up = torch.cross(back, right, dim=-1)
    c2w = torch.eye(4).repeat(eye.shape[0], 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, cam_up, back, eye
    return c2w


def spherical_poses(
    elevation_deg: torch.Tensor, azimuth_deg: torch.Tensor, radius: float = NERF_SYNTHETIC_RADIUS
) -> torch.Tensor:
    """Poses on a sphere around the origin (elevation above the xy-plane, z up)."""
    el, az = torch.deg2rad(torch.as_tensor(elevation_deg, dtype=torch.float32)), torch.deg2rad(
        torch.as_tensor(azimuth_deg, dtype=torch.float32)
    )
    eye = radius * torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], dim=-1)
    return look_at(eye)


def random_hemisphere_poses(
    n: int,
    generator: torch.Generator | None = None,
    radius: float = NERF_SYNTHETIC_RADIUS,
    min_zenith_deg: float = 15.0,
    max_zenith_deg: float = 90.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Upper-hemisphere training poses as the authors draw them (zenith uniform in [15°, 90°]).

    Returns (c2w, elevation_deg, azimuth_deg) so callers can pick a view word.
    """
    zenith = min_zenith_deg + (max_zenith_deg - min_zenith_deg) * torch.rand(n, generator=generator)
    azimuth = 360.0 * torch.rand(n, generator=generator)
    elevation = 90.0 - zenith
    return spherical_poses(elevation, azimuth, radius), elevation, azimuth


def ring_poses(
    n: int, elevation_deg: float = 30.0, radius: float = NERF_SYNTHETIC_RADIUS
) -> torch.Tensor:
    """``n`` poses evenly spaced on a 360° ring (turntables and the evaluation protocol)."""
    azimuth = torch.arange(n, dtype=torch.float32) * (360.0 / n)
    return spherical_poses(torch.full((n,), float(elevation_deg)), azimuth, radius)
