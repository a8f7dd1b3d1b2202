"""Captures as people have them: lens distortion, nerfstudio's camera models, COLMAP sparse models.

The COLMAP model of fox is made here, in a temporary folder, from fox's own transforms.json
(poses turned back into COLMAP's world-to-camera convention, written with pycolmap, the
maintained writer); its images folder is a link to the shared data, never a copy.
"""

from __future__ import annotations

import json
import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from voxe_core.backbones import prepare_backbone
from voxe_core.cameras import (DISTORTION_KEYS, Cameras, _jacobian, camera_rays, distort_points, fisheye_angles,
                               look_at, pixel_rays, undistort_points)
from voxe_core.colmap import ColmapError, read_model
from voxe_core.data import DatasetError, detect_format, is_dataset_folder, load_scene
from voxe_core.scene_grid import scene_frame

import needs
from captures import pose_at, square_capture, write_colmap_model
from needs import FOX, MIC

OPENCV = torch.tensor([0.0578, -0.0805, 0.01, -0.002, -0.00098, 0.00016], dtype=torch.float64)
FISHEYE = torch.tensor([0.05, -0.01, 0.002, -0.0005, 0.0, 0.0], dtype=torch.float64)


# pixels of a 16 x 12 image, corners included: (u, v), (5,) each
PIXELS = (torch.tensor([0.0, 16.0, 0.5, 12.25, 8.0]), torch.tensor([0.0, 12.0, 9.5, 2.0, 6.0]))


def off_axis_degrees(cameras: Cameras, index: int, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(R,) angles between camera ``index``'s rays through pixels (u, v) and its optical axis."""
    _, directions = pixel_rays(cameras, torch.full(u.shape, index), u, v)
    cosine = (directions.double() @ -cameras.c2w[index, :3, 2].double()).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cosine))


def opencv_fisheye_degrees(u: torch.Tensor, v: torch.Tensor, f: float, cx: float, cy: float, k) -> torch.Tensor:
    """The same angles as cv2.fisheye's undistortPoints gives them (OPENCV_FISHEYE, coefficients k1..k4)."""
    import cv2

    camera_matrix = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    pixels = torch.stack([u, v], -1).double().numpy()[None]
    x, y = cv2.fisheye.undistortPoints(pixels, camera_matrix, np.array(k, dtype=np.float64))[0].T
    return torch.rad2deg(torch.atan(torch.from_numpy(np.hypot(x, y))))


def grid_points(extent: float, n: int = 41, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    y, x = torch.meshgrid(torch.linspace(-extent, extent, n, dtype=dtype),
                          torch.linspace(-extent, extent, n, dtype=dtype), indexing="ij")
    return x.reshape(-1), y.reshape(-1)


# ---------------------------------------------------------------- the distortion models


def test_undistort_inverts_distort_both_ways():
    x, y = grid_points(0.8)
    xd, yd = distort_points(x, y, OPENCV)
    ux, uy = undistort_points(xd, yd, OPENCV)
    assert torch.allclose(ux, x, atol=1e-10) and torch.allclose(uy, y, atol=1e-10)
    rx, ry = distort_points(*undistort_points(x, y, OPENCV), OPENCV)
    assert torch.allclose(rx, x, atol=1e-10) and torch.allclose(ry, y, atol=1e-10)


def test_fisheye_angles_invert_distort_both_ways():
    """The fisheye images the point (x, y) at its ray's angle θ = atan r; back, the angle found at a point
    names the image-plane point (tan θ along the point's own direction) that the fisheye images there."""
    x, y = grid_points(0.8)
    r = torch.hypot(x, y)
    theta = fisheye_angles(*distort_points(x, y, FISHEYE, "fisheye"), FISHEYE)
    assert torch.allclose(theta, torch.atan(r), atol=1e-10)
    theta = fisheye_angles(x, y, FISHEYE)
    scale = torch.where(r > 0, torch.tan(theta) / r, torch.ones_like(r))
    rx, ry = distort_points(x * scale, y * scale, FISHEYE, "fisheye")
    assert torch.allclose(rx, x, atol=1e-10) and torch.allclose(ry, y, atol=1e-10)


def test_pinhole_coefficients_are_the_identity():
    x, y = grid_points(1.0)
    zero = torch.zeros(6, dtype=torch.float64)
    assert torch.equal(torch.stack(distort_points(x, y, zero)), torch.stack([x, y]))
    assert torch.equal(torch.stack(undistort_points(x, y, zero)), torch.stack([x, y]))
    # An equidistant fisheye without coefficients images the angle: r_d = atan(r), so its ray's angle is r_d.
    xd, yd = distort_points(x, y, zero, "fisheye")
    assert torch.allclose(torch.hypot(xd, yd), torch.atan(torch.hypot(x, y)), atol=1e-12)
    theta = fisheye_angles(torch.tensor([0.5], dtype=torch.float64), torch.zeros(1, dtype=torch.float64), zero)
    assert abs(float(theta) - 0.5) < 1e-10


def test_radial_only_matches_the_closed_form():
    """k1 only, on the x axis: x_d = x (1 + k1 x²); tangential p1 alone moves y by p1 (r² + 2y²) at x = 0."""
    k = torch.tensor([0.2, 0, 0, 0, 0, 0], dtype=torch.float64)
    x = torch.tensor([0.1, 0.4, -0.7], dtype=torch.float64)
    xd, yd = distort_points(x, torch.zeros_like(x), k)
    assert torch.allclose(xd, x * (1 + 0.2 * x**2)) and torch.equal(yd, torch.zeros_like(x))
    p1 = torch.tensor([0, 0, 0, 0, 0.01, 0], dtype=torch.float64)
    _, yd = distort_points(torch.zeros(1, dtype=torch.float64), torch.tensor([0.5], dtype=torch.float64), p1)
    assert abs(float(yd) - (0.5 + 0.01 * 3 * 0.25)) < 1e-15


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_low_precision_inputs_come_back_in_their_dtype(dtype):
    x, y = grid_points(0.6, 9, dtype)
    ux, uy = undistort_points(x, y, OPENCV.to(dtype))
    assert ux.dtype == dtype and torch.isfinite(ux.float()).all() and torch.isfinite(uy.float()).all()
    exact_x, exact_y = undistort_points(x.double(), y.double(), OPENCV)
    tolerance = {torch.float32: 1e-6, torch.float16: 2e-3, torch.bfloat16: 1e-2}[dtype]
    assert torch.allclose(ux.double(), exact_x, atol=tolerance) and torch.allclose(uy.double(), exact_y, atol=tolerance)


def test_undistorting_nothing_and_the_centre():
    empty = torch.zeros(0, dtype=torch.float64)
    ux, uy = undistort_points(empty, empty, OPENCV)
    assert ux.shape == (0,) and uy.shape == (0,)
    theta = fisheye_angles(torch.zeros(1), torch.zeros(1), FISHEYE.float())
    assert theta.dtype == torch.float32 and float(theta) == 0.0


def test_undistorting_keeps_to_the_branch_that_holds_the_axis():
    """r (1 + k1 r² + k2 r⁴) stops increasing where 1 + 3 k1 r² + 5 k2 r⁴ = 0: an image point beyond that fold's
    image has no ray on the axis's branch (NaN), though a root past the fold maps back to it too."""
    k1, k2 = -0.2251, 0.0224
    k = torch.tensor([k1, k2, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    fold = math.sqrt((-3 * k1 - math.sqrt(9 * k1 * k1 - 20 * k2)) / (10 * k2))  # r ≈ 1.617
    edge = fold * (1 + k1 * fold**2 + k2 * fold**4)  # its image, ≈ 0.913
    xd = torch.tensor([0.0, 0.5, 0.99, 1.01], dtype=torch.float64) * edge
    x, y = undistort_points(xd, torch.zeros_like(xd), k)
    assert torch.isfinite(x[:3]).all() and (x[:3] < fold).all()
    assert torch.allclose(distort_points(x[:3], y[:3], k)[0], xd[:3], atol=1e-12)
    assert torch.isnan(x[3]) and torch.isnan(y[3])


def test_no_undistorted_point_sits_where_the_tangential_terms_fold_the_image():
    """Inside the radial fold, p1 turns the map's Jacobian negative near (1.15, -0.7): a root there is no ray."""
    k = torch.tensor([0.5, -0.2, 0.0, 0.0, 0.1, 0.0], dtype=torch.float64)
    xd, yd = grid_points(1.5, 61)
    x, y = undistort_points(xd, yd, k)
    found = torch.isfinite(x)
    assert found.sum() > 2800 and torch.isnan(y[~found]).all()
    x, y, h = x[found], y[found], 1e-6

    def derivatives(dx, dy):  # of (xd, yd) along (dx, dy), by central differences
        return [(plus - minus) / (2 * h) for plus, minus in zip(distort_points(x + dx, y + dy, k),
                                                                 distort_points(x - dx, y - dy, k))]

    (a, c), (b, d) = derivatives(h, 0.0), derivatives(0.0, h)
    assert (a * d - b * c > 0).all()


def test_a_pixel_near_the_fold_has_the_ray_its_branch_holds():
    """This lens's pixel (152, 5.25) lies inside the fold's image, but its distorted point is nearly at the fold's
    radius, where Newton started from it found nothing: continuing the solution out from the axis reaches
    (1.21634, -0.75621), with the Jacobian positive. Every pixel of the image has its ray."""
    f, cx, cy = 47.7, 55.0, 65.6
    k = torch.tensor([0.442, -0.052, 0.0, 0.0, 0.0016, -0.0033], dtype=torch.float64)
    x, y = undistort_points(torch.tensor([(152 - cx) / f], dtype=torch.float64),
                            torch.tensor([(5.25 - cy) / f], dtype=torch.float64), k)
    assert abs(float(x) - 1.2163360041473645) < 1e-9 and abs(float(y) + 0.7562074771026241) < 1e-9
    xd, yd = distort_points(x, y, k)
    assert abs(float(xd) * f + cx - 152) < 1e-9 and abs(float(yd) * f + cy - 5.25) < 1e-9
    cams = Cameras(torch.eye(4)[None], torch.tensor([f]), torch.tensor([f]), torch.tensor([cx]), torch.tensor([cy]),
                   160, 120, distortion=k.float()[None])
    assert torch.isfinite(camera_rays(cams, 0)[1]).all()


def test_rays_go_through_the_undistorted_point_and_project_back_to_their_pixel():
    c2w = look_at(torch.tensor([[0.0, -4.0, 1.0]]))
    cams = Cameras(c2w, torch.tensor([50.0]), torch.tensor([52.0]), torch.tensor([31.0]), torch.tensor([25.0]),
                   64, 48, distortion=OPENCV.float()[None] * 4)
    origins, directions = camera_rays(cams, 0)
    local = directions @ c2w[0, :3, :3]  # world -> camera (OpenGL axes)
    x, y = local[:, 0] / -local[:, 2], -local[:, 1] / -local[:, 2]  # OpenCV's normalised coordinates
    xd, yd = distort_points(x.double(), y.double(), cams.distortion[0])
    v, u = torch.meshgrid(torch.arange(48) + 0.5, torch.arange(64) + 0.5, indexing="ij")
    assert torch.allclose(xd * 50 + 31, u.reshape(-1).double(), atol=1e-3)
    assert torch.allclose(yd * 52 + 25, v.reshape(-1).double(), atol=1e-3)
    pinhole = camera_rays(cams.undistorted(), 0)[1]
    assert (pinhole - directions).norm(dim=-1).max() > 1e-3  # the distortion did move the rays
    # Indexing, resizing and moving keep the lens: coefficients live in normalised coordinates.
    half = cams.resized(32, 24)
    assert torch.equal(half.distortion, cams.distortion) and half[0].distortion.shape == (1, 6)
    o, d = pixel_rays(half, torch.zeros(1, dtype=torch.long), torch.tensor([15.5]), torch.tensor([12.5]))
    o2, d2 = pixel_rays(cams, torch.zeros(1, dtype=torch.long), torch.tensor([31.0]), torch.tensor([25.0]))
    assert torch.allclose(d, d2, atol=1e-6)


def test_unknown_distortion_model_is_refused():
    with pytest.raises(ValueError, match="distortion_model must be one of opencv, fisheye"):
        Cameras(torch.eye(4)[None], *(torch.ones(1),) * 4, 2, 2, distortion_model="equirectangular")


# ---------------------------------------------------------------- nerfstudio transforms.json


def write_capture(root: Path, n: int = 3, size=(16, 12), frame_extra=None, **top) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        (root / "images").mkdir(exist_ok=True)
        Image.new("RGB", size, (20 * i, 40, 60)).save(root / "images" / f"{i:03d}.png")
        m = np.eye(4)
        m[:3, 3] = (i * 0.1, 0.0, 4.0)
        frames.append({"file_path": f"images/{i:03d}.png", "transform_matrix": m.tolist(),
                       **((frame_extra or {}).get(i, {}))})
    meta = {"fl_x": 14.0, "fl_y": 14.0, "cx": 8.0, "cy": 6.0, "w": size[0], "h": size[1], **top, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def test_nerfstudio_fisheye_with_per_frame_intrinsics(tmp_path):
    root = write_capture(tmp_path / "ns", camera_model="OPENCV_FISHEYE", k1=0.05, k2=-0.01, k3=0.002, k4=-0.0005,
                         frame_extra={1: {"fl_x": 15.0, "k1": 0.04}})
    scene = load_scene(root)
    cams = scene.cameras
    assert cams.distortion_model == "fisheye"
    assert torch.allclose(cams.distortion[0], FISHEYE.float())
    assert torch.allclose(cams.distortion[1], torch.tensor([0.04, -0.01, 0.002, -0.0005, 0.0, 0.0]))
    assert torch.allclose(cams.fx, torch.tensor([14.0, 15.0, 14.0]))


def test_nerfstudio_pinhole_and_zero_distortion_are_pinholes(tmp_path):
    assert load_scene(write_capture(tmp_path / "a", camera_model="PINHOLE")).cameras.distortion is None
    assert load_scene(write_capture(tmp_path / "b", camera_model="OPENCV", k1=0.0, p1=0.0)).cameras.distortion is None


@pytest.mark.parametrize("model, lens", [("SIMPLE_PINHOLE", {}), ("SIMPLE_RADIAL", {"k1": 0.05}),
                                         ("RADIAL", {"k1": 0.05, "k2": -0.01})])
def test_nerfstudio_reads_the_simpler_colmap_model_names_too(tmp_path, model, lens):
    """nerfstudio's reader takes camera_model SIMPLE_PINHOLE, SIMPLE_RADIAL and RADIAL as perspective cameras with
    the k / p keys' distortion, and converters to its format write SIMPLE_PINHOLE: they had been refused. A
    SIMPLE_PINHOLE frame beside an OPENCV one leaves that one's lens as it is."""
    cameras = load_scene(write_capture(tmp_path / "ns", camera_model=model, **lens)).cameras
    if lens:
        assert cameras.distortion_model == "opencv"
        assert torch.allclose(cameras.distortion, torch.tensor([lens.get(k, 0.0) for k in DISTORTION_KEYS]))
    else:
        assert cameras.distortion is None
    assert torch.equal(cameras.fx, torch.full((3,), 14.0))
    mixed = write_capture(tmp_path / "mixed", camera_model=model,
                          frame_extra={1: {"camera_model": "OPENCV", "k1": 0.1}})
    assert torch.allclose(load_scene(mixed).cameras.distortion[1], torch.tensor([0.1, 0, 0, 0, 0, 0]))


def test_instant_ngp_coefficients_without_a_camera_model_are_opencv(tmp_path):
    scene = load_scene(write_capture(tmp_path / "ngp", k1=0.1, p2=0.001))
    assert scene.cameras.distortion_model == "opencv"
    assert torch.allclose(scene.cameras.distortion[2], torch.tensor([0.1, 0, 0, 0, 0, 0.001]))


@pytest.mark.parametrize("per_frame", [False, True])
def test_instant_ngp_is_fisheye_is_the_opencv_fisheye(tmp_path, per_frame):
    """instant-ngp's colmap2nerf.py writes a fisheye camera as "is_fisheye": true with k1..k4 (top level or per
    frame): the rays are cv2.fisheye's, not OPENCV's radial model of the same coefficients."""
    lens = {"is_fisheye": True, "k1": 0.05, "k2": -0.01, "k3": 0.0, "k4": 0.0, "p1": 0.0, "p2": 0.0}
    root = write_capture(tmp_path / "ngp", frame_extra={i: lens for i in range(3)}) if per_frame else \
        write_capture(tmp_path / "ngp", **lens)
    cameras = load_scene(root).cameras
    expected = opencv_fisheye_degrees(*PIXELS, 14.0, 8.0, 6.0, [0.05, -0.01, 0.0, 0.0])
    assert cameras.distortion_model == "fisheye"
    assert torch.allclose(off_axis_degrees(cameras, 1, *PIXELS), expected, atol=1e-3)


@pytest.mark.parametrize("model, params", [("SIMPLE_RADIAL_FISHEYE", [14.0, 8.0, 6.0, 0.0]),
                                           ("OPENCV_FISHEYE", [14.0, 14.0, 8.0, 6.0, 0.0, 0.0, 0.0, 0.0])])
def test_a_fisheye_without_coefficients_is_equidistant_not_a_pinhole(tmp_path, model, params):
    """θ = r: a corner pixel of this 16 x 12 image is 40.9° off axis, where a pinhole's atan(r) is 35.5°."""
    import pycolmap

    root = square_capture(tmp_path)
    write_colmap_model(root / "sparse" / "0", [(model, 16, 12, params)],
                       [(f"{i}.png", 0, pose_at(i)) for i in range(3)])
    camera = pycolmap.Reconstruction(str(root / "sparse" / "0")).cameras[1]
    x, y = camera.cam_from_img(torch.stack(PIXELS, -1).double().numpy()).T
    expected = torch.rad2deg(torch.atan(torch.from_numpy(np.hypot(x, y))))
    assert torch.allclose(off_axis_degrees(load_scene(root).cameras, 2, *PIXELS), expected, atol=1e-3)
    nerfstudio = load_scene(write_capture(tmp_path / "ns", camera_model="OPENCV_FISHEYE")).cameras
    assert torch.allclose(off_axis_degrees(nerfstudio, 0, *PIXELS), expected, atol=1e-3)


def test_a_fisheye_sees_past_90_degrees_but_no_ray_is_past_180(tmp_path):
    """An ideal equidistant fisheye (θ = r / f) at f = 60 over 160 x 120 sees 191° across its diagonal: its corner's
    ray is 100 / 60 rad (95.5°) off axis, on no point of the image plane (it had been refused as a fold). At f = 30
    the corner would be 191° off axis, where no ray is."""
    capture = dict(size=(160, 120), camera_model="OPENCV_FISHEYE", cx=80.0, cy=60.0, w=160, h=120)
    wide = load_scene(write_capture(tmp_path / "wide", fl_x=60.0, fl_y=60.0, **capture)).cameras
    u, v = torch.tensor([0.0, 160.0, 80.0, 0.0, 80.0]), torch.tensor([0.0, 120.0, 0.0, 60.0, 60.0])
    expected = torch.hypot(u - 80, v - 60).double() / 60
    assert torch.allclose(torch.deg2rad(off_axis_degrees(wide, 0, u, v)), expected, atol=1e-5)
    with pytest.raises(DatasetError, match=r"fisheye lens images pixel \(0, 0\) 191° off its axis \(a field of "
                                           r"view of 382°\), but no ray is more than 180° off it"):
        load_scene(write_capture(tmp_path / "wider", fl_x=30.0, fl_y=30.0, **capture))


@pytest.mark.parametrize("top, frame_extra, frame, message", [
    ({"camera_model": "EQUIRECTANGULAR"}, None, None, "camera_model 'EQUIRECTANGULAR' is not supported"),
    ({}, {2: {"camera_model": "FISHEYE"}}, 2, "camera_model 'FISHEYE' is not supported"),
    ({}, {1: {"camera_model": ["OPENCV"]}}, 1, r"camera_model \['OPENCV'\] is not supported"),
    ({"camera_model": "OPENCV"}, {1: {"camera_model": "OPENCV_FISHEYE"}}, 1,
     "camera_model OPENCV_FISHEYE differs from frame 0's OPENCV; the fisheye and the OPENCV model cannot be mixed"),
    ({"camera_model": "OPENCV_FISHEYE"}, {2: {"camera_model": "PINHOLE"}}, 2,
     "camera_model PINHOLE differs from frame 0's OPENCV_FISHEYE; the fisheye and the PINHOLE model cannot be mixed"),
    ({"is_fisheye": 1}, None, None, "'is_fisheye' must be true or false, got 1"),
    ({}, {1: {"camera_model": "OPENCV", "is_fisheye": True}}, 1, "'is_fisheye' is true but camera_model is OPENCV"),
    ({"camera_model": "PINHOLE", "k1": 0.2}, None, 0, "camera_model PINHOLE has no such distortion term, but k1 = 0.2"),
    ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, None, 0, "OPENCV_FISHEYE has no such distortion term, but p1"),
    ({"camera_model": "OPENCV", "k2": "0.1"}, None, None, "'k2' must be a number"),
    ({"camera_model": "OPENCV"}, {1: {"k1": float("nan")}}, 1, "'k1' is not finite"),
    ({"camera_model": "OPENCV", "k1": -3.0}, None, 0, r"distortion \(k1 = -3\) folds the image over at pixel \(0, 0\)"),
    ({"latlong": True}, None, None, r"'latlong' declares instant-ngp's equirectangular \(latitude-longitude\) lens, "
                                   "which is not supported"),
    ({}, {1: {f"ftheta_p{i}": 0.1 for i in range(5)}}, 1, "'ftheta_p0' declares instant-ngp's f-theta lens"),
])
def test_bad_lens_names_file_frame_and_problem(tmp_path, top, frame_extra, frame, message):
    root = write_capture(tmp_path / "bad", frame_extra=frame_extra, **top)
    with pytest.raises(DatasetError, match=message) as err:
        load_scene(root)
    prefix = "transforms.json" + (f" frame {frame} ('images/{frame:03d}.png')" if frame is not None else ":")
    assert str(err.value).startswith(prefix), str(err.value)
    assert err.value.frame == frame


def test_a_lens_that_folds_inside_its_image_is_refused_and_one_that_nearly_does_loads(tmp_path):
    """k1 = -0.2251, k2 = 0.0224 at f = 101.75 fold 93 px from the centre of 160 x 120 (its corner: 100 px), where the
    corner rays had jumped 10° in 2 px; k1 = -0.3379, k2 = 0.0515 at f = 55.2 never folds (9 k1² < 20 k2) and had been
    refused when Newton did not converge in time."""
    capture = dict(size=(160, 120), camera_model="OPENCV", cx=80.0, cy=60.0, w=160, h=120)
    folded = write_capture(tmp_path / "folded", fl_x=101.75, fl_y=101.75, k1=-0.2251, k2=0.0224, **capture)
    with pytest.raises(DatasetError, match=r"k2 = 0.0224\) folds the image over at pixel \(0, 0\)"):
        load_scene(folded)
    near = load_scene(write_capture(tmp_path / "near", fl_x=55.2, fl_y=55.2, k1=-0.3379, k2=0.0515, **capture)).cameras
    corners = torch.tensor([0.0, 160.0]), torch.tensor([0.0, 120.0])
    _, directions = pixel_rays(near, torch.zeros(2, dtype=torch.long), *corners)
    local = directions.double() @ near.c2w[0, :3, :3].double()  # world -> camera (OpenGL axes)
    xd, yd = distort_points(local[:, 0] / -local[:, 2], local[:, 1] / local[:, 2], near.distortion[0].double())
    assert torch.allclose(xd * 55.2 + 80, corners[0].double(), atol=1e-3)
    assert torch.allclose(yd * 55.2 + 60, corners[1].double(), atol=1e-3)



def test_a_lens_whose_tangential_terms_fold_an_island_into_its_image_is_refused(tmp_path):
    """k1 = -0.1611, k2 = 0.0227, p1 = 0.0321, p2 = -0.0468 at f = 57.5, c = (56.7, 23) give each of the load's
    17 x 17 samples a ray, but between them the Jacobian turns negative on an island (its radial part never
    folds), whose caustic lies in the 160 x 120 image: pixels there have several rays. k1 = 0.442, k2 = -0.052,
    p1 = 0.0016, p2 = -0.0033 at f = 47.7 folds only outside its image, and loads, as does p1 = 0.0032,
    p2 = -0.0047 alone."""
    f, cx, cy, k = 57.5, 56.7, 23.0, torch.tensor([-0.1611, 0.0227, 0.0, 0.0, 0.0321, -0.0468], dtype=torch.float64)
    v, u = torch.meshgrid(torch.linspace(0, 120, 17, dtype=torch.float64),
                          torch.linspace(0, 160, 17, dtype=torch.float64), indexing="ij")
    assert torch.isfinite(undistort_points((u.reshape(-1) - cx) / f, (v.reshape(-1) - cy) / f, k)[0]).all()
    x, y = grid_points(1.8, 361)
    a, b, d = _jacobian(torch.stack([x, y], -1), k.expand(len(x), 6))
    xd, yd = distort_points(x, y, k)
    island = (a * d - b * b < 0) & (xd * f + cx > 0) & (xd * f + cx < 160) & (yd * f + cy > 0)
    assert island.any()  # imaged in view, where the map folds, though its radial part never does (9 k1² < 20 k2)
    capture = dict(size=(160, 120), camera_model="OPENCV", w=160, h=120, n=1)
    folded = write_capture(tmp_path / "folded", fl_x=f, fl_y=f, cx=cx, cy=cy, k1=-0.1611, k2=0.0227, p1=0.0321,
                           p2=-0.0468, **capture)
    with pytest.raises(DatasetError, match=r"transforms.json frame 0 \('images/000.png'\): lens distortion \(k1 = "
                                           r"-0.1611, k2 = 0.0227, p1 = 0.0321, p2 = -0.0468\) folds the image "
                                           r"over at pixel \((\d+), (\d+)\)") as err:
        load_scene(folded)
    pixel = torch.tensor([float(c) for c in re.search(r"pixel \((\d+), (\d+)\)", str(err.value)).groups()])
    caustic = torch.stack([xd[island] * f + cx, yd[island] * f + cy], -1)
    assert float((caustic - pixel.double()).norm(dim=-1).min()) < 1.5  # named: a pixel the island is imaged on
    fine = write_capture(tmp_path / "fine", fl_x=47.7, fl_y=47.7, cx=55.0, cy=65.6, k1=0.442, k2=-0.052, p1=0.0016,
                         p2=-0.0033, **capture)
    assert load_scene(fine).cameras.distortion is not None
    tangential = write_capture(tmp_path / "tangential", fl_x=f, fl_y=f, cx=cx, cy=cy, p1=0.0032, p2=-0.0047, **capture)
    assert load_scene(tangential).cameras.distortion is not None  # it folds only far out of view

@needs.needs_data(FOX)
def test_fox_distortion_is_applied():
    meta = json.loads((FOX / "transforms.json").read_text())
    cams = load_scene(FOX, downsample=16, max_images=2).cameras
    assert cams.distortion_model == "opencv"
    expected = torch.tensor([meta["k1"], meta["k2"], 0.0, 0.0, meta["p1"], meta["p2"]])
    assert torch.allclose(cams.distortion, expected.expand(2, 6))


# ---------------------------------------------------------------- COLMAP sparse models


def fox_as_colmap(root: Path, binary: bool, count: int = 3, step: int = 1) -> Path:
    """fox's first ``count`` frames (every ``step``-th) as a COLMAP model, its images folder a link to the data."""
    meta = json.loads((FOX / "transforms.json").read_text())
    params = [meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["k1"], meta["k2"], meta["p1"], meta["p2"]]
    frames = meta["frames"][::step][:count]
    images = [(Path(f["file_path"]).name, 0, np.array(f["transform_matrix"])) for f in frames]
    write_colmap_model(root / "sparse" / "0", [("OPENCV", int(meta["w"]), int(meta["h"]), params)], images, binary)
    (root / "images").symlink_to(FOX / "images", target_is_directory=True)
    return root


@needs.needs_data(FOX)
@pytest.mark.parametrize("binary", [True, False])
def test_colmap_model_of_fox_loads_as_its_transforms(tmp_path, binary):
    root = fox_as_colmap(tmp_path / "fox_colmap", binary)
    assert detect_format(root) == "colmap" and is_dataset_folder(root)
    colmap = load_scene(root, downsample=16)
    ngp = load_scene(FOX, downsample=16, max_images=3)
    assert colmap.format == "colmap" and colmap.names == ["images/0001.jpg", "images/0002.jpg", "images/0003.jpg"]
    assert torch.equal(colmap.images, ngp.images)
    a, b = colmap.cameras, ngp.cameras
    assert torch.allclose(a.c2w, b.c2w, atol=1e-5)
    for key in ("fx", "fy", "cx", "cy", "distortion"):
        assert torch.allclose(getattr(a, key), getattr(b, key), atol=1e-5), key
    assert (a.width, a.height, a.distortion_model) == (b.width, b.height, "opencv")
    held = load_scene(root, "test", downsample=16, holdout_every=2)
    assert held.names == ["images/0001.jpg", "images/0003.jpg"]


def test_colmap_simple_models_share_a_focal_and_fisheye_keeps_its_terms(tmp_path):
    root = square_capture(tmp_path)
    write_colmap_model(root / "sparse" / "0", [("SIMPLE_RADIAL", 16, 12, [13.0, 8.0, 6.0, 0.03]),
                                               ("SIMPLE_PINHOLE", 16, 12, [12.0, 8.0, 6.0])],
                       [(f"{i}.png", i % 2, pose_at(i)) for i in (0, 2)])
    cams = load_scene(root).cameras
    assert torch.allclose(cams.fx, torch.tensor([13.0, 13.0])) and torch.equal(cams.fx, cams.fy)
    assert torch.allclose(cams.distortion, torch.tensor([0.03, 0, 0, 0, 0, 0]).expand(2, 6))
    root2 = square_capture(tmp_path / "fish")
    write_colmap_model(root2 / "sparse" / "0", [("OPENCV_FISHEYE", 16, 12, [9.0, 9.5, 8.0, 6.0, *FISHEYE[:4].tolist()])],
                       [(f"{i}.png", 0, pose_at(i)) for i in range(3)], binary=False)
    cams = load_scene(root2).cameras
    assert cams.distortion_model == "fisheye" and torch.allclose(cams.distortion[1], FISHEYE.float())


def test_colmap_errors_name_file_frame_and_problem(tmp_path):
    root = square_capture(tmp_path)
    write_colmap_model(root / "sparse" / "0", [("PINHOLE", 16, 12, [12.0, 12.0, 8.0, 6.0]),
                                               ("FULL_OPENCV", 16, 12, [12.0, 12.0, 8.0, 6.0] + [0.0] * 8)],
                       [("0.png", 0, pose_at(0)), ("1.png", 1, pose_at(1))])
    with pytest.raises(DatasetError, match=r"^sparse/0/images.bin frame 1 \('images/1.png'\): camera 2 has COLMAP model "
                                           "FULL_OPENCV, which is not supported"):
        load_scene(root)

    root = square_capture(tmp_path / "mixed")
    write_colmap_model(root / "sparse" / "0", [("PINHOLE", 16, 12, [12.0, 12.0, 8.0, 6.0]),
                                               ("OPENCV_FISHEYE", 16, 12, [12.0, 12.0, 8.0, 6.0, 0.01, 0.0, 0.0, 0.0])],
                       [("0.png", 0, pose_at(0)), ("1.png", 1, pose_at(1))])
    with pytest.raises(DatasetError, match=r"^sparse/0/images.bin frame 1 \('images/1.png'\): camera_model "
                                           "OPENCV_FISHEYE differs from frame 0's PINHOLE; the fisheye and the "
                                           "PINHOLE model cannot be mixed in one capture"):
        load_scene(root)

    root = square_capture(tmp_path / "float32")
    write_colmap_model(root / "sparse" / "0", [("SIMPLE_PINHOLE", 16, 12, [1e39, 8.0, 6.0])],
                       [("0.png", 0, pose_at(0))])
    with pytest.raises(DatasetError, match=r"^sparse/0/images.bin frame 0 \('images/0.png'\): 'fl_x' = 1e\+39 is "
                                           "beyond float32's range"):
        load_scene(root)

    root = square_capture(tmp_path / "missing")
    write_colmap_model(root / "sparse" / "0", [("PINHOLE", 16, 12, [12.0, 12.0, 8.0, 6.0])],
                       [("0.png", 0, pose_at(0)), ("7.png", 0, pose_at(1))])
    with pytest.raises(DatasetError, match=r"^sparse/0/images.bin frame 1 \('images/7.png'\): image not found"):
        load_scene(root)

    root = square_capture(tmp_path / "size")
    write_colmap_model(root / "sparse" / "0", [("PINHOLE", 32, 12, [12.0, 12.0, 8.0, 6.0])],
                       [("0.png", 0, pose_at(0))])
    with pytest.raises(DatasetError, match=r"^sparse/0/images.bin frame 0 \('images/0.png'\): image is 16x12 but the "
                                           "intrinsics say w=32"):
        load_scene(root)

    model = root / "sparse" / "0"
    (model / "points3D.bin").unlink()  # not needed
    (model / "frames.bin").unlink()  # nor COLMAP 4's rigs and frames
    (model / "rigs.bin").unlink()
    (model / "cameras.bin").write_bytes((model / "cameras.bin").read_bytes()[:-3])
    with pytest.raises(DatasetError, match=r"^sparse/0/cameras.bin: truncated at byte 32 \(reading camera 1's 4 "):
        load_scene(root)
    (model / "cameras.bin").unlink()
    with pytest.raises(DatasetError, match=r"no dataset found"):
        load_scene(root)


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_model_in_sparse_itself_is_read_as_the_image_undistorter_writes_it(tmp_path, binary):
    """COLMAP's image undistorter writes its model to ``sparse/`` itself (no ``0/``): it had been no dataset. Where
    both are, ``sparse/0`` (the mapper's) is read."""
    root = square_capture(tmp_path)
    write_colmap_model(root / "sparse", [("PINHOLE", 16, 12, [12.0, 13.0, 8.0, 6.0])],
                       [(f"{i}.png", 0, pose_at(i)) for i in range(3)], binary)
    assert detect_format(root) == "colmap" and is_dataset_folder(root)
    scene = load_scene(root)
    assert scene.names == ["images/0.png", "images/1.png", "images/2.png"]
    assert torch.allclose(scene.cameras.fy, torch.tensor(13.0)) and scene.cameras.distortion is None
    assert torch.allclose(scene.cameras.c2w[2], torch.from_numpy(pose_at(2)).float(), atol=1e-6)
    (root / "images" / "1.png").unlink()
    with pytest.raises(DatasetError, match=r"^sparse/images.(bin|txt) frame 1 \('images/1.png'\): image not found"):
        load_scene(root)
    write_colmap_model(root / "sparse" / "0", [("PINHOLE", 16, 12, [12.0, 12.0, 8.0, 6.0])],
                       [(f"{i}.png", 0, pose_at(i)) for i in (0, 2)], binary)
    assert load_scene(root).names == ["images/0.png", "images/2.png"]


def test_poses_in_opencv_axes_are_refused_by_the_scene_frame(tmp_path):
    """A transforms.json of OpenCV-axis matrices loads (they are rigid) but every camera faces away from the centre
    its axes meet: the scene frame names the likely mix-up rather than framing what lies behind the cameras."""
    angles = torch.arange(8) * (2 * math.pi / 8)
    ring = look_at(torch.stack([4.0 * angles.cos(), 4.0 * angles.sin(), torch.ones(8)], -1)).double().numpy()
    root = square_capture(tmp_path, n=8)

    def cameras_of(camera_axes: np.ndarray) -> Cameras:
        frames = [{"file_path": f"images/{i}.png", "transform_matrix": (c2w @ camera_axes).tolist()}
                  for i, c2w in enumerate(ring)]
        (root / "transforms.json").write_text(json.dumps({"fl_x": 14.0, "frames": frames}))
        return load_scene(root).cameras

    assert torch.allclose(scene_frame(cameras_of(np.eye(4)))[:3, 3], torch.zeros(3), atol=1e-4)  # about the origin
    opencv_axes = cameras_of(np.diag([1.0, -1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match=r"lies behind 8 of 8 cameras: either the capture looks outward .* or the "
                                         r"poses hold OpenCV camera axes"):
        scene_frame(opencv_axes)


def test_relu_field_refuses_a_box_its_cameras_do_not_aim_at():
    """An object on a transparent background gets the ReLU field and its fixed box about the origin; a COLMAP or
    instant-ngp world frame can hold the object anywhere (here at (20, 10, 5)), where that box sees nothing."""
    angles = torch.arange(8) * (2 * math.pi / 8)
    around = torch.stack([30.0 * angles.cos(), 30.0 * angles.sin(), torch.full((8,), 8.0)], -1)
    alphas = torch.zeros(8, 4, 4)
    alphas[:, 1:3, 1:3] = 1.0  # an object on a transparent background: 'auto' is relu_field
    target = torch.tensor([20.0, 10.0, 5.0])
    elsewhere = Cameras.from_fov(look_at(around + target, target), 0.7, 4, 4)
    with pytest.raises(ValueError, match=r"the optical axes of only 0 of 8 cameras pass through the relu_field "
                                         r"backbone's box .*; use the scene backbone"):
        prepare_backbone("auto", alphas, elsewhere, 16)
    centred = Cameras.from_fov(look_at(around), 0.7, 4, 4)
    name, fit_cameras, initial = prepare_backbone("auto", alphas, centred, 16)
    assert name == "relu_field" and fit_cameras is centred and initial is None


@pytest.mark.parametrize("backbone", ["relu_field", "scene"])
def test_cameras_all_at_one_position_are_refused_for_either_backbone(backbone):
    """Views from one point hold no parallax: here a ring's rotations with their translations lost, at the origin
    (inside the ReLU field's box, which its aim check had passed) and away from it. One camera is no such capture."""
    ring = look_at(torch.stack([4.0 * torch.arange(6).cos(), 4.0 * torch.arange(6).sin(), torch.full((6,), 1.0)], -1))
    for position in ([0.0, 0.0, 0.0], [0.0, 0.0, 4.0]):
        c2w = ring.clone()
        c2w[:, :3, 3] = torch.tensor(position)
        with pytest.raises(ValueError, match=r"all 6 cameras sit at one position .*no parallax"):
            prepare_backbone(backbone, None, Cameras.from_fov(c2w, 0.7, 4, 4), 16)
    c2w[1:, :3, 3] = ring[1:, :3, 3]  # only the first sits there: a capture with its translations
    prepare_backbone(backbone, None, Cameras.from_fov(c2w, 0.7, 4, 4), 16)
    prepare_backbone("relu_field", None, Cameras.from_fov(ring[:1], 0.7, 4, 4), 16)


@needs.needs_data(MIC)
@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_nerf_synthetic_cameras_aim_at_the_relu_field_box(split):
    meta = json.loads((MIC / f"transforms_{split}.json").read_text())
    c2w = torch.tensor([frame["transform_matrix"] for frame in meta["frames"]])
    cameras = Cameras.from_fov(c2w, meta["camera_angle_x"], 800, 800)
    name, fit_cameras, _ = prepare_backbone("relu_field", None, cameras, 16)
    assert name == "relu_field" and fit_cameras is cameras


def test_transforms_json_wins_over_a_colmap_model_beside_it(tmp_path):
    root = write_capture(tmp_path / "both")
    write_colmap_model(root / "sparse" / "0", [("PINHOLE", 16, 12, [12.0, 12.0, 8.0, 6.0])], [("000.png", 0, pose_at(0))])
    assert detect_format(root) == "instant_ngp"
    assert not is_dataset_folder(tmp_path / "nothing_here")


def small_model(tmp_path: Path, binary: bool = True) -> Path:
    return write_colmap_model(tmp_path / "m", [("OPENCV", 16, 12, [9.0, 9.5, 8.0, 6.0, 0.01, 0.0, 0.0, 0.0])],
                              [("a.png", 0, pose_at(0)), ("b.png", 0, pose_at(1))], binary)


def test_colmap_reader_matches_pycolmap_and_refuses_every_truncation(tmp_path):
    import pycolmap

    model = small_model(tmp_path)
    cameras, images = read_model(model)
    theirs = pycolmap.Reconstruction(str(model))
    assert cameras[1].model == "OPENCV" and cameras[1].params == list(theirs.cameras[1].params)
    for image in images:
        ref = next(im for im in theirs.images.values() if im.name == image.name)
        assert np.allclose(image.cam_from_world[:3], ref.cam_from_world().matrix(), atol=1e-12)
    for name in ("cameras.bin", "images.bin"):
        whole = (model / name).read_bytes()
        for cut in range(len(whole)):
            (model / name).write_bytes(whole[:cut])
            with pytest.raises(ColmapError, match=rf"^{name}: (truncated at byte|claims|image name at byte)"):
                read_model(model)
        (model / name).write_bytes(whole + b"\0")
        with pytest.raises(ColmapError, match=rf"^{name}: 1 unexpected bytes after the last entry"):
            read_model(model)
        (model / name).write_bytes(struct.pack("<Q", 2**62) + whole[8:])
        with pytest.raises(ColmapError, match=rf"^{name}: claims {2**62} (cameras|images) at byte 0"):
            read_model(model)
        (model / name).write_bytes(whole)


def test_colmap_text_errors_name_the_line(tmp_path):
    model = small_model(tmp_path, binary=False)
    cameras_txt = (model / "cameras.txt").read_text()
    images_txt = (model / "images.txt").read_text()
    header_lines = sum(line.startswith("#") for line in cameras_txt.splitlines())
    assert read_model(model)[1][1].name == "b.png"
    for bad, message in (("1 OPENCV 16 12 9 9.5 8 6", "camera model OPENCV has 8 parameters, got 4"),
                         ("1 KANNALA 16 12 9", "unknown camera model 'KANNALA'"),
                         ("1 PINHOLE 16 twelve 9 9 8 6", "image size 'twelve' is not an integer"),
                         ("1 PINHOLE 16 12 9 nan 8 6", r"parameters \[9.0, nan, 8.0, 6.0\] are not all finite"),
                         ("1 PINHOLE 1" + "0" * 400 + " 12 9 9 8 6", r"image size 10{400}x12 must lie within 1x1 "
                                                                      r"and 65536x65536")):
        (model / "cameras.txt").write_text("# c\n" * header_lines + bad + "\n")
        with pytest.raises(ColmapError, match=rf"^cameras.txt: line {header_lines + 1}: {message}"):
            read_model(model)
    (model / "cameras.txt").write_text(cameras_txt)
    lines = images_txt.splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    image_a, rest = lines[:first + 1], lines[first + 2:]
    assert lines[first + 1] == "" and len(rest) == 2  # a.png's line, its points (none), b.png's line, its points
    # Without points lines, b.png's line would be read as a.png's points and b.png lost.
    for bad, message in ((image_a + rest[:1], "got 10 fields"),
                         (image_a + ["3.5 2.5 x"] + rest, "POINT3D_ID 'x' is not an integer")):
        (model / "images.txt").write_text("\n".join(bad) + "\n")
        with pytest.raises(ColmapError, match=rf"^images.txt: line {first + 2}: .*{message}"):
            read_model(model)
    fields = lines[first].split()
    lines[first] = " ".join(fields[:1] + ["2", "0", "0", "0"] + fields[5:])
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ColmapError, match=rf"^images.txt: line {first + 1}: image 1 \('a.png'\): rotation "
                                          r"quaternion \[2.0, 0.0, 0.0, 0.0\] has norm 2, not 1"):
        read_model(model)


def test_colmap_text_reads_what_colmap_reads_and_names_a_byte_order_mark(tmp_path):
    """COLMAP (pycolmap 4.2.1) reads indented comments and runs of spaces or tabs between fields, and refuses a
    file starting with a byte order mark; an indented comment had been read as a camera or an image."""
    model = small_model(tmp_path, binary=False)
    cameras_txt, images_txt = (model / "cameras.txt").read_text(), (model / "images.txt").read_text()
    lines = images_txt.splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    spaced = [lines[first].replace(" ", "  "), lines[first + 1], "  # b.png next", "\t# and its points after it",
              *lines[first + 2:]]
    (model / "cameras.txt").write_text("  # indented\n" + cameras_txt.replace(" ", " \t "))
    (model / "images.txt").write_text("\n".join(lines[:first] + spaced) + "\n")
    cameras, images = read_model(model)
    assert cameras[1].params == [9.0, 9.5, 8.0, 6.0, 0.01, 0.0, 0.0, 0.0] and [im.name for im in images] == ["a.png",
                                                                                                              "b.png"]
    assert np.allclose(images[0].cam_from_world, read_model(small_model(tmp_path / "plain", False))[1][0].cam_from_world)
    (model / "cameras.txt").write_text("\ufeff" + cameras_txt)
    with pytest.raises(ColmapError, match=r"^cameras.txt: starts with a UTF-8 byte order mark"):
        read_model(model)


def test_colmap_text_keeps_an_image_name_as_written(tmp_path):
    """Regression: NAME had been rebuilt from whitespace-split fields, so 'my  photo a.png' (as COLMAP writes it)
    was read as 'my photo a.png', a file the capture does not hold. NAME is the rest of the line after CAMERA_ID
    (COLMAP trims the line's ends)."""
    model = write_colmap_model(tmp_path / "m", [("PINHOLE", 16, 12, [12.0, 12.0, 8.0, 6.0])],
                               [("my  photo a.png", 0, pose_at(0)), ("b\t c.png", 0, pose_at(1))], binary=False)
    assert [image.name for image in read_model(model)[1]] == ["my  photo a.png", "b\t c.png"]
    lines = (model / "images.txt").read_text().splitlines()
    (model / "images.txt").write_text("\n".join(line.replace(" ", "\t ", 9) + " \r" if line.endswith(".png") else line
                                                for line in lines) + "\n")
    assert [image.name for image in read_model(model)[1]] == ["my  photo a.png", "b\t c.png"]


def test_colmap_images_sharing_an_id_are_refused_naming_it(tmp_path):
    """Regression: two images with one id were both kept (COLMAP refuses such a model: "Check failed:
    images_.emplace(image_id, ...)")."""
    model = small_model(tmp_path / "b")
    whole = (model / "images.bin").read_bytes()
    second = whole.index(b"b.png\0") - 64  # its IMAGE_ID, 4 + 7 * 8 + 4 bytes before its name
    assert struct.unpack_from("<i", whole, second) == (2,)
    (model / "images.bin").write_bytes(whole[:second] + struct.pack("<i", 1) + whole[second + 4:])
    with pytest.raises(ColmapError, match=rf"^images.bin: image 1 \('b.png'\) at byte {second}: duplicate image id "
                                          r"\('a.png' has it too\)$"):
        read_model(model)
    model = small_model(tmp_path / "t", binary=False)
    lines = (model / "images.txt").read_text().splitlines()
    second = next(i for i, line in enumerate(lines) if line.startswith("2 "))
    lines[second] = "1" + lines[second][1:]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ColmapError, match=rf"^images.txt: line {second + 1}: duplicate image id 1 \('b.png'; line "
                                          rf"{second - 1}'s 'a.png' has it too\)$"):
        read_model(model)


def test_colmap_points2d_lines_as_colmap_writes_them_are_not_parsed_value_by_value(tmp_path, monkeypatch):
    """The POINTS2D[] check had parsed every X, Y and POINT3D_ID, most of images.txt's read time; a line of plain
    decimals (COLMAP's) now passes in one match. Any other line is parsed value by value as before: it passes
    (nan, 1_000, +3) or fails naming its first bad value."""
    from voxe_core import colmap

    model = small_model(tmp_path, binary=False)
    lines = (model / "images.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    parse, parsed = colmap._parse, []

    def counted(kind, field: str, what: str, line: int, path: Path):
        parsed.append(what)
        return parse(kind, field, what, line, path)

    monkeypatch.setattr(colmap, "_parse", counted)
    for points, value_by_value in (("1.5 2.25 -1  3 4 7\t1e-05 -2.5E+3 12 ", False), ("", False),
                                   ("nan 1_000 +3", True)):
        lines[first + 1] = points
        (model / "images.txt").write_text("\n".join(lines) + "\n")
        parsed.clear()
        assert [image.name for image in read_model(model)[1]] == ["a.png", "b.png"]
        assert ("POINTS2D X" in parsed) == value_by_value, points
    for points, message in (("1.5 2.5 -1 3 4", "got 5 fields"),
                            ("1.5 2.5 -1 3 4 7.0", "POINT3D_ID '7.0' is not an integer"),
                            ("1.5 2.5 -1 3 4e 7", "POINTS2D Y '4e' is not a number")):
        lines[first + 1] = points
        (model / "images.txt").write_text("\n".join(lines) + "\n")
        with pytest.raises(ColmapError, match=rf"^images.txt: line {first + 2}: .*{message}"):
            read_model(model)


@needs.needs_data(FOX)
def test_cli_reconstructs_a_colmap_capture(tmp_path, capsys):
    from voxe_core.backbones import load_grid
    from voxe_core.cli import main

    root = fox_as_colmap(tmp_path / "fox_colmap", binary=True, count=5, step=10)  # views around the fox
    out = tmp_path / "fox.safetensors"
    args = ["--downsample", "16", "--resolution", "16", "--iterations", "2", "--rays", "64", "-q"]
    assert main(["reconstruct", str(root), "--out", str(out), *args]) == 0
    grid = load_grid(out)
    assert type(grid).__name__ == "SceneGrid" and torch.isfinite(grid.features).all()  # photos: the scene backbone
