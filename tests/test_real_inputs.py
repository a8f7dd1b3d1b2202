"""Captures as people have them: lens distortion, nerfstudio's camera models, COLMAP sparse models.

The COLMAP model of fox is made here, in a temporary folder, from fox's own transforms.json
(poses turned back into COLMAP's world-to-camera convention, written with pycolmap, the
maintained writer); its images folder is a link to the shared data, never a copy.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from voxe_core.cameras import Cameras, camera_rays, distort_points, look_at, pixel_rays, undistort_points
from voxe_core.colmap import ColmapError, read_model
from voxe_core.data import DatasetError, detect_format, is_dataset_folder, load_scene

import needs
from captures import pose_at, square_capture, write_colmap_model
from needs import FOX

OPENCV = torch.tensor([0.0578, -0.0805, 0.01, -0.002, -0.00098, 0.00016], dtype=torch.float64)
FISHEYE = torch.tensor([0.05, -0.01, 0.002, -0.0005, 0.0, 0.0], dtype=torch.float64)


def grid_points(extent: float, n: int = 41, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    y, x = torch.meshgrid(torch.linspace(-extent, extent, n, dtype=dtype),
                          torch.linspace(-extent, extent, n, dtype=dtype), indexing="ij")
    return x.reshape(-1), y.reshape(-1)


# ---------------------------------------------------------------- the distortion models


@pytest.mark.parametrize("model, k", [("opencv", OPENCV), ("fisheye", FISHEYE)])
def test_undistort_inverts_distort_both_ways(model, k):
    x, y = grid_points(0.8)
    xd, yd = distort_points(x, y, k, model)
    ux, uy = undistort_points(xd, yd, k, model)
    assert torch.allclose(ux, x, atol=1e-10) and torch.allclose(uy, y, atol=1e-10)
    rx, ry = distort_points(*undistort_points(x, y, k, model), k, model)
    assert torch.allclose(rx, x, atol=1e-10) and torch.allclose(ry, y, atol=1e-10)


def test_pinhole_coefficients_are_the_identity():
    x, y = grid_points(1.0)
    zero = torch.zeros(6, dtype=torch.float64)
    for model in ("opencv",):
        assert torch.equal(torch.stack(distort_points(x, y, zero, model)), torch.stack([x, y]))
        assert torch.equal(torch.stack(undistort_points(x, y, zero, model)), torch.stack([x, y]))
    # An equidistant fisheye without coefficients images the angle: r_d = atan(r), so undistorting is tan.
    xd, yd = distort_points(x, y, zero, "fisheye")
    assert torch.allclose(torch.hypot(xd, yd), torch.atan(torch.hypot(x, y)), atol=1e-12)
    ux, _ = undistort_points(torch.tensor([0.5], dtype=torch.float64), torch.zeros(1, dtype=torch.float64), zero,
                             "fisheye")
    assert abs(float(ux) - math.tan(0.5)) < 1e-10


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
    ux, uy = undistort_points(x, y, OPENCV.to(dtype), "opencv")
    assert ux.dtype == dtype and torch.isfinite(ux.float()).all() and torch.isfinite(uy.float()).all()
    exact_x, exact_y = undistort_points(x.double(), y.double(), OPENCV, "opencv")
    tolerance = {torch.float32: 1e-6, torch.float16: 2e-3, torch.bfloat16: 1e-2}[dtype]
    assert torch.allclose(ux.double(), exact_x, atol=tolerance) and torch.allclose(uy.double(), exact_y, atol=tolerance)


def test_undistorting_nothing_and_the_centre():
    empty = torch.zeros(0, dtype=torch.float64)
    ux, uy = undistort_points(empty, empty, OPENCV)
    assert ux.shape == (0,) and uy.shape == (0,)
    ux, uy = undistort_points(torch.zeros(1), torch.zeros(1), FISHEYE.float(), "fisheye")
    assert float(ux) == 0.0 and float(uy) == 0.0


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


def test_instant_ngp_coefficients_without_a_camera_model_are_opencv(tmp_path):
    scene = load_scene(write_capture(tmp_path / "ngp", k1=0.1, p2=0.001))
    assert scene.cameras.distortion_model == "opencv"
    assert torch.allclose(scene.cameras.distortion[2], torch.tensor([0.1, 0, 0, 0, 0, 0.001]))


@pytest.mark.parametrize("top, frame_extra, frame, message", [
    ({"camera_model": "EQUIRECTANGULAR"}, None, None, "camera_model 'EQUIRECTANGULAR' is not supported"),
    ({}, {2: {"camera_model": "FISHEYE"}}, 2, "camera_model 'FISHEYE' is not supported"),
    ({}, {1: {"camera_model": ["OPENCV"]}}, 1, r"camera_model \['OPENCV'\] is not supported"),
    ({"camera_model": "OPENCV"}, {1: {"camera_model": "OPENCV_FISHEYE"}}, 1,
     "camera_model OPENCV_FISHEYE differs from frame 0's OPENCV; the fisheye and the OPENCV model cannot be mixed"),
    ({"camera_model": "PINHOLE", "k1": 0.2}, None, 0, "camera_model PINHOLE has no such distortion term, but k1 = 0.2"),
    ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, None, 0, "OPENCV_FISHEYE has no such distortion term, but p1"),
    ({"camera_model": "OPENCV", "k2": "0.1"}, None, None, "'k2' must be a number"),
    ({"camera_model": "OPENCV"}, {1: {"k1": float("nan")}}, 1, "'k1' is not finite"),
    ({"camera_model": "OPENCV", "k1": -3.0}, None, 0, "cannot be inverted at pixel"),
])
def test_bad_lens_names_file_frame_and_problem(tmp_path, top, frame_extra, frame, message):
    root = write_capture(tmp_path / "bad", frame_extra=frame_extra, **top)
    with pytest.raises(DatasetError, match=message) as err:
        load_scene(root)
    prefix = "transforms.json" + (f" frame {frame} ('images/{frame:03d}.png')" if frame is not None else ":")
    assert str(err.value).startswith(prefix), str(err.value)
    assert err.value.frame == frame


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
                         ("1 PINHOLE 16 twelve 9 9 8 6", "image size 'twelve' is not a integer"),
                         ("1 PINHOLE 16 12 9 nan 8 6", r"parameters \[9.0, nan, 8.0, 6.0\] are not all finite"),
                         ("1 PINHOLE 1" + "0" * 400 + " 12 9 9 8 6", r"image size 10{400}x12 must lie within 1x1 "
                                                                      r"and 65536x65536")):
        (model / "cameras.txt").write_text("# c\n" * header_lines + bad + "\n")
        with pytest.raises(ColmapError, match=rf"^cameras.txt: line {header_lines + 1}: {message}"):
            read_model(model)
    (model / "cameras.txt").write_text(cameras_txt)
    lines = images_txt.splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    fields = lines[first].split()
    lines[first] = " ".join(fields[:1] + ["2", "0", "0", "0"] + fields[5:])
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ColmapError, match=rf"^images.txt: line {first + 1}: image 1 \('a.png'\): rotation "
                                          r"quaternion \[2.0, 0.0, 0.0, 0.0\] has norm 2, not 1"):
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
