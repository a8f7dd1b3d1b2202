"""Dataset loading: real NeRF-synthetic and instant-ngp scenes, and one test per validation error."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from voxe_core.cameras import DISTORTION_KEYS
from voxe_core.data import _INTRINSIC_KEYS, DatasetError, Scene, detect_format, load_scene

import needs
from captures import sixteen_bit_rgb_png
from needs import FOX, MIC

needs_data = needs.needs_data(MIC, FOX)

IDENTITY = np.eye(4).tolist()


def pose(rotation=None, translation=(0.0, 0.0, 4.0)) -> list:
    m = np.eye(4)
    if rotation is not None:
        m[:3, :3] = rotation
    m[:3, 3] = translation
    return m.tolist()


def write_png(path: Path, size=(8, 6), mode="RGBA", color=(255, 0, 0, 128)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new(mode, size, color[: len(mode)] if isinstance(color, tuple) else color).save(path)


def make_synthetic(root: Path, frames: list[dict] | None = None, n: int = 3, split="train", **top) -> Path:
    """A tiny NeRF-synthetic folder; ``frames`` overrides the generated frame list."""
    root.mkdir(parents=True, exist_ok=True)
    if frames is None:
        frames = []
        for i in range(n):
            write_png(root / "train" / f"r_{i}.png")
            frames.append({"file_path": f"./train/r_{i}", "transform_matrix": pose(translation=(0, 0, 4.0 + i))})
    meta = {"camera_angle_x": 0.69, **top, "frames": frames}
    (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def make_ngp(root: Path, n: int = 4, size=(8, 6), **top) -> Path:
    frames = []
    for i in range(n):
        write_png(root / "images" / f"{i:04d}.png", size, mode="RGB", color=(10 * i, 20, 30))
        frames.append({"file_path": f"images/{i:04d}.png", "transform_matrix": pose(translation=(i, 0, 4.0))})
    meta = {"fl_x": 10.0, "w": size[0], "h": size[1], **top, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def assert_names(err: pytest.ExceptionInfo, file_name: str, frame: int | None) -> None:
    message = str(err.value)
    assert file_name in message, message
    if frame is not None:
        assert f"frame {frame}" in message, message
        assert err.value.frame == frame


# ---------------------------------------------------------------- real data


@needs_data
def test_nerf_synthetic_mic_downsampled():
    scene = load_scene(MIC, downsample=8, max_images=3)
    meta = json.loads((MIC / "transforms_train.json").read_text())
    assert isinstance(scene, Scene) and scene.format == "nerf_synthetic" and scene.split == "train"
    assert scene.images.shape == (3, 100, 100, 3) and scene.images.dtype == torch.float32
    assert scene.alphas is not None and scene.alphas.shape == (3, 100, 100) and scene.has_alpha
    assert (scene.cameras.width, scene.cameras.height) == (100, 100)
    focal = 0.5 * 100 / math.tan(0.5 * meta["camera_angle_x"])
    assert torch.allclose(scene.cameras.fx, torch.full((3,), focal), atol=1e-4)
    assert torch.allclose(scene.cameras.fy, torch.full((3,), focal), atol=1e-4)
    assert torch.allclose(scene.cameras.cx, torch.full((3,), 50.0))
    # Transparent background composited on white; everything stays in [0, 1].
    assert torch.all(scene.images[:, 0, 0] == 1.0) and torch.all(scene.alphas[:, 0, 0] == 0.0)
    assert scene.images.min() >= 0.0 and scene.images.max() <= 1.0
    assert scene.images.min() < 0.5  # the microphone itself is dark, not all white
    assert scene.names == [f["file_path"] for f in meta["frames"][:3]]
    expected = torch.tensor(meta["frames"][1]["transform_matrix"], dtype=torch.float32)
    assert torch.allclose(scene.cameras.c2w[1], expected)


@needs_data
def test_instant_ngp_fox_downsampled():
    assert detect_format(FOX) == "instant_ngp"
    meta = json.loads((FOX / "transforms.json").read_text())
    scene = load_scene(FOX, downsample=8, max_images=2)
    assert scene.format == "instant_ngp" and scene.alphas is None and not scene.has_alpha
    assert scene.images.shape == (2, 240, 135, 3)
    assert (scene.cameras.width, scene.cameras.height) == (135, 240)
    assert torch.allclose(scene.cameras.fx, torch.full((2,), meta["fl_x"] / 8))
    assert torch.allclose(scene.cameras.fy, torch.full((2,), meta["fl_y"] / 8))
    assert torch.allclose(scene.cameras.cx, torch.full((2,), meta["cx"] / 8))
    assert torch.allclose(scene.cameras.cy, torch.full((2,), meta["cy"] / 8))
    k1, k2, p1, p2 = (meta[k] for k in ("k1", "k2", "p1", "p2"))
    assert torch.allclose(scene.cameras.distortion, torch.tensor([k1, k2, 0.0, 0.0, p1, p2]).expand(2, 6))
    assert scene.aabb_scale == 4.0
    assert 0.0 <= scene.images.min() and scene.images.max() <= 1.0 and scene.images.std() > 0.05


# ---------------------------------------------------------------- image handling


@pytest.mark.parametrize("resample", ["bilinear", "box"])
def test_downsample_is_premultiplied(tmp_path, resample):
    root = tmp_path / "s"
    (root / "train").mkdir(parents=True)
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[:, :2] = (0, 0, 0, 255)  # opaque black on the left half
    rgba[:, 2:] = (255, 0, 0, 0)  # fully transparent *red* on the right half: its colour must not leak
    Image.fromarray(rgba, "RGBA").save(root / "train" / "r_0.png")
    make_synthetic(root, frames=[{"file_path": "./train/r_0", "transform_matrix": IDENTITY}])
    scene = load_scene(root, downsample=4, resample=resample)
    assert scene.images.shape == (1, 1, 1, 3)
    # half black, half white background: 0.5 grey in every channel (no red tint)
    assert torch.allclose(scene.images[0, 0, 0], torch.full((3,), 0.5))
    assert torch.allclose(scene.alphas[0, 0, 0], torch.tensor(0.5))


def test_bilinear_downsampling_matches_pillow_and_box_does_not(tmp_path):
    """The default filter is PIL's antialiased bilinear resize of the cropped RGBA (the authors' loader), then white."""
    root = tmp_path / "s"
    (root / "train").mkdir(parents=True)
    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (26, 35, 4), dtype=np.uint8)  # not a multiple of 4: cropped to 24 x 32 first
    rgba[..., 3] = np.where(rng.random((26, 35)) < 0.3, 0, rgba[..., 3])  # a third fully transparent
    Image.fromarray(rgba, "RGBA").save(root / "train" / "r_0.png")
    make_synthetic(root, frames=[{"file_path": "./train/r_0", "transform_matrix": IDENTITY}])
    pillow = np.asarray(Image.fromarray(rgba[:24, :32], "RGBA").resize((8, 6), Image.BILINEAR), np.float32) / 255.0
    expected = torch.from_numpy(pillow[..., :3] * pillow[..., 3:] + 1.0 - pillow[..., 3:])
    # Pillow premultiplies in 8 bits; ours is float, so they agree to a few levels of 255.
    error = (load_scene(root, downsample=4).images[0] - expected).abs()
    assert error.max() < 3 / 255 and error.mean() < 1 / 255, (error.max(), error.mean())
    assert (load_scene(root, downsample=4, resample="box").images[0] - expected).abs().mean() > 4 / 255
    with pytest.raises(ValueError, match="resample must be one of bilinear, box"):
        load_scene(root, downsample=4, resample="lanczos")


def test_bilinear_downsampling_keeps_white_at_most_one(tmp_path):
    """Float32 filter weights can sum to an ulp above 1; images stay in [0, 1] all the same."""
    root = tmp_path / "s"
    (root / "train").mkdir(parents=True)
    Image.fromarray(np.full((64, 64, 3), 255, np.uint8), "RGB").save(root / "train" / "r_0.png")
    make_synthetic(root, frames=[{"file_path": "./train/r_0", "transform_matrix": IDENTITY}])
    images = load_scene(root, downsample=4).images
    assert images.max() <= 1.0 and torch.allclose(images, torch.ones_like(images))


def test_odd_size_crops_to_multiple_and_scales_intrinsics(tmp_path):
    root = make_ngp(tmp_path / "s", n=2, size=(9, 7), cx=4.5, cy=3.5)
    scene = load_scene(root, downsample=2)
    assert scene.images.shape == (2, 3, 4, 3)
    assert (scene.cameras.width, scene.cameras.height) == (4, 3)
    assert torch.allclose(scene.cameras.fx, torch.full((2,), 5.0))
    assert torch.allclose(scene.cameras.cx, torch.full((2,), 2.25))


def test_principal_point_outside_the_image_is_warned_and_one_no_image_has_refused(tmp_path):
    """A crop's principal point lies outside its image: kept as given, with one warning; one further out than the
    largest image side read (float32 rays of a 16-pixel image 1e8 pixels out coincide) had loaded silently."""
    with pytest.warns(UserWarning, match=r"^transforms.json frame 0 \('images/0000.png'\): principal point \(-3, 20\) "
                                         r"lies 14 pixels outside the 8x6 image \(2 of 2 frames' lie outside it\)"):
        scene = load_scene(make_ngp(tmp_path / "crop", n=2, cx=-3.0, cy=20.0))
    assert scene.cameras.cx.tolist() == [-3.0, -3.0] and scene.cameras.cy.tolist() == [20.0, 20.0]
    root = make_ngp(tmp_path / "far", n=2, cx=4.0, cy=3.0)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][1]["cy"] = 1e8
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"frame 1 .*principal point \(4, 1e\+08\) lies 1e\+08 pixels outside the "
                                           r"8x6 image, more than the largest image side read \(65536\)") as err:
        load_scene(root)
    assert_names(err, "transforms.json", 1)


def test_greyscale_sixteen_bit_png(tmp_path):
    root = tmp_path / "s"
    (root / "train").mkdir(parents=True)
    grey = np.full((4, 4), 65535, np.uint16)
    grey[0, 0] = 0
    Image.fromarray(grey).save(root / "train" / "r_0.png")
    make_synthetic(root, frames=[{"file_path": "./train/r_0", "transform_matrix": IDENTITY}])
    scene = load_scene(root)
    assert scene.alphas is None and scene.images.shape == (1, 4, 4, 3)
    assert torch.all(scene.images[0, 0, 0] == 0.0) and torch.all(scene.images[0, 1:, 1:] == 1.0)


@pytest.mark.parametrize("key", [(0x1234, 0x5678, 0x9ABC), (100, 100, 100)])
def test_sixteen_bit_rgb_colour_key_is_transparent_at_the_8_bits_the_colour_is_read_with(tmp_path, key):
    """Pillow reads a 16-bit RGB PNG's colour at 8 bits and keeps its colour key at 16: the key colour had stayed
    opaque, and a key of 100 had made samples of 25600 transparent. The key is matched at the 8 bits the colour is
    read with: a colour sharing its high bytes (the last pixel), which the 8-bit image cannot tell from it, is keyed
    too; one a high byte away (the second) is not."""
    near = tuple(k ^ 0xFF for k in key)  # the same high bytes, other low bytes: another colour to the PNG spec
    samples = np.array([[key, (0x1200, 0x5600, 0x9B00), (25600, 25600, 25600), (0, 0, 65535), near]], np.uint16)
    sixteen_bit_rgb_png(tmp_path / "s" / "train" / "r_0.png", samples, key)
    make_synthetic(tmp_path / "s", frames=[{"file_path": "./train/r_0", "transform_matrix": IDENTITY}])
    scene = load_scene(tmp_path / "s")
    assert scene.alphas.tolist() == [[[0.0, 1.0, 1.0, 1.0, 0.0]]]
    assert torch.equal(scene.images[0, 0, 0], torch.ones(3))  # on white
    assert torch.equal(scene.images[0, 0, 1:4],
                       torch.tensor([[0x12, 0x56, 0x9B], [100, 100, 100], [0, 0, 255]]) / 255.0)


def test_sixteen_bit_greyscale_colour_key_is_transparent(tmp_path):
    """A 16-bit grey PNG's tRNS names the value that is transparent, as an 8-bit one's does: it had been read as
    an opaque dark pixel."""
    root = tmp_path / "s"
    (root / "train").mkdir(parents=True)
    grey = np.full((4, 4), 40000, np.uint16)
    grey[0, :2] = 1234
    Image.fromarray(grey).save(root / "train" / "r_0.png", transparency=1234)
    make_synthetic(root, frames=[{"file_path": "./train/r_0", "transform_matrix": IDENTITY}])
    scene = load_scene(root)
    expected_alpha = torch.ones(4, 4)
    expected_alpha[0, :2] = 0.0
    assert torch.equal(scene.alphas[0], expected_alpha)
    assert torch.all(scene.images[0, 0, :2] == 1.0)  # on white
    assert torch.allclose(scene.images[0, 1:], torch.full((3, 4, 3), 40000 / 65535))


@pytest.mark.parametrize("name, image, message", [
    ("r_0.tiff", Image.fromarray(np.full((4, 4), 0.5, np.float32), "F"),
     r"image r_0.tiff holds floating-point pixels \(Pillow mode F\), whose scale the file does not record"),
    ("r_0.tiff", Image.fromarray(np.full((4, 4), 70000, np.int32), "I"),
     r"image r_0.tiff holds 32-bit values from 70000 to 70000 \(Pillow mode I\); only 8- and 16-bit images"),
])
def test_float_and_32_bit_images_are_refused_by_name(tmp_path, name, image, message):
    """A float TIFF had loaded black and 32-bit values white (clipped): neither says how to scale it to [0, 1]."""
    root = tmp_path / "s"
    (root / "train").mkdir(parents=True)
    image.save(root / "train" / name)
    make_synthetic(root, frames=[{"file_path": f"./train/{name}", "transform_matrix": IDENTITY}])
    with pytest.raises(DatasetError, match=message) as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 0)
    assert err.value.path == root / "train" / name


def test_sixteen_bit_values_in_a_32_bit_image_are_read_as_16_bit(tmp_path):
    root = tmp_path / "s"
    (root / "train").mkdir(parents=True)
    Image.fromarray(np.full((4, 4), 16384, np.int32), "I").save(root / "train" / "r_0.tiff")
    make_synthetic(root, frames=[{"file_path": "./train/r_0.tiff", "transform_matrix": IDENTITY}])
    assert torch.allclose(load_scene(root).images, torch.full((1, 4, 4, 3), 16384 / 65535))


def test_camera_angle_y_and_per_frame_overrides(tmp_path):
    root = make_ngp(tmp_path / "s", n=2, size=(8, 6))
    meta = json.loads((root / "transforms.json").read_text())
    del meta["fl_x"]
    meta.update(camera_angle_x=math.pi / 2, camera_angle_y=math.pi / 2)
    meta["frames"][1]["fl_x"] = 7.0
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root)
    assert torch.allclose(scene.cameras.fx, torch.tensor([4.0, 7.0]))  # 0.5*8/tan(pi/4) = 4
    assert torch.allclose(scene.cameras.fy, torch.tensor([3.0, 3.0]))  # 0.5*6/tan(pi/4) = 3: camera_angle_y, not fl_x
    assert scene.cameras.distortion is None


def test_a_frames_own_focal_comes_before_the_top_levels(tmp_path):
    """instant-ngp's precedence: per axis, a frame's fl_* or camera_angle_* before the top level's; fy is fx only
    where neither fl_y nor camera_angle_y is given."""
    root = make_ngp(tmp_path / "a", n=3, size=(8, 6), camera_angle_y=math.pi / 2)  # fl_x 10, fy 0.5*6/tan(pi/4) = 3
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][1]["camera_angle_x"] = math.pi / 2  # fx 0.5*8/tan(pi/4) = 4, over the top level's fl_x
    meta["frames"][2]["fl_y"] = 5.0
    (root / "transforms.json").write_text(json.dumps(meta))
    cameras = load_scene(root).cameras
    assert torch.allclose(cameras.fx, torch.tensor([10.0, 4.0, 10.0]))
    assert torch.allclose(cameras.fy, torch.tensor([3.0, 3.0, 5.0]))
    cameras = load_scene(make_ngp(tmp_path / "b", n=1)).cameras
    assert torch.equal(cameras.fy, cameras.fx)


def test_a_focal_given_for_the_y_axis_alone_is_both_axes_as_instant_ngp_reads_it(tmp_path):
    """instant-ngp takes fl_y or camera_angle_y without an x-axis key as both focals; they had been refused as
    missing intrinsics."""
    root = make_ngp(tmp_path / "a", n=3, size=(8, 6))
    meta = json.loads((root / "transforms.json").read_text())
    del meta["fl_x"]
    meta["camera_angle_y"] = math.pi / 2  # 0.5*6/tan(pi/4) = 3
    meta["frames"][1]["fl_y"] = 5.0
    meta["frames"][2]["fl_x"] = 7.0  # its own x focal; y still the top level's angle
    (root / "transforms.json").write_text(json.dumps(meta))
    cameras = load_scene(root).cameras
    assert torch.allclose(cameras.fx, torch.tensor([3.0, 5.0, 7.0]))
    assert torch.allclose(cameras.fy, torch.tensor([3.0, 5.0, 3.0]))


def test_instant_ngp_fields_of_view_in_degrees_give_the_focal(tmp_path):
    """instant-ngp's x_fov and y_fov: the full field of view in degrees (its fov_to_focal_length), read before fl_*
    and camera_angle_* as it reads them. A file with only these had been refused as missing intrinsics."""
    root = make_ngp(tmp_path / "a", n=3, size=(8, 6))
    meta = json.loads((root / "transforms.json").read_text())
    del meta["fl_x"]
    meta["x_fov"] = 90.0  # 0.5*8/tan(45°) = 4
    meta["frames"][1]["y_fov"] = 60.0  # 0.5*6/tan(30°) = 3*sqrt(3) = 5.196152
    meta["frames"][2]["fl_x"] = 7.0  # a frame's own key for the axis hides the top level's x_fov
    (root / "transforms.json").write_text(json.dumps(meta))
    cameras = load_scene(root).cameras
    assert torch.allclose(cameras.fx, torch.tensor([4.0, 4.0, 7.0]))
    assert torch.allclose(cameras.fy, torch.tensor([4.0, 5.196152, 7.0]))
    meta["fl_x"] = 10.0  # beside x_fov, as instant-ngp: x_fov wins
    (root / "transforms.json").write_text(json.dumps(meta))
    assert torch.allclose(load_scene(root).cameras.fx, torch.tensor([4.0, 4.0, 7.0]))
    meta["frames"][1]["y_fov"] = 180.0
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"frame 1 .*'y_fov' = 180.0 is outside \(0, 180\) degrees"):
        load_scene(root)


def test_holdout_split_semantics(tmp_path):
    root = make_ngp(tmp_path / "s", n=10)
    assert len(load_scene(root)) == 10
    assert len(load_scene(root, split="all", holdout_every=4)) == 10
    train = load_scene(root, split="train", holdout_every=4)
    test = load_scene(root, split="test", holdout_every=4)
    assert test.names == ["images/0000.png", "images/0004.png", "images/0008.png"]
    assert len(train) == 7 and not set(train.names) & set(test.names)
    assert len(load_scene(root, split="train", holdout_every=4, max_images=2)) == 2
    with pytest.raises(DatasetError, match=r"no test split.*use the split 'train' or 'all' \(voxe: --split train\)") as err:
        load_scene(root, split="test")  # (it had named holdout_every, which no voxe command takes)
    assert_names(err, "transforms.json", None)


def test_holdout_every_is_refused_for_nerf_synthetic_whose_splits_are_files(tmp_path):
    """It had been ignored: split 'train' with holdout_every=2 gave every training frame, none held out."""
    root = make_synthetic(tmp_path / "s", n=4)
    assert len(load_scene(root, split="train")) == 4
    for split in ("train", "test"):
        with pytest.raises(ValueError, match=r"holdout_every applies to a capture's .* is NeRF-synthetic, whose "
                                             r"splits are its transforms_\{train,val,test\}.json"):
            load_scene(root, split=split, holdout_every=2)


def test_detect_format(tmp_path):
    assert detect_format(make_synthetic(tmp_path / "a", n=1)) == "nerf_synthetic"
    assert detect_format(make_ngp(tmp_path / "b", n=1)) == "instant_ngp"
    (tmp_path / "c").mkdir()
    with pytest.raises(DatasetError, match="transforms_train.json") as err:
        detect_format(tmp_path / "c")
    assert err.value.path == tmp_path / "c"


# ---------------------------------------------------------------- validation errors


def test_missing_image(tmp_path):
    root = make_synthetic(tmp_path / "s")
    (root / "train" / "r_1.png").unlink()
    with pytest.raises(DatasetError, match="image not found") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 1)
    assert "./train/r_1" in str(err.value)


def test_a_file_path_without_its_extension_finds_a_jpeg(tmp_path):
    """instant-ngp tries .png, .jpg and .jpeg (among others) after a file_path without its extension: only .png had
    been tried, and a capture's JPEGs were not found."""
    root = tmp_path / "j"
    for i, extension in enumerate((".jpg", ".jpeg")):
        write_png(root / "images" / f"{i}{extension}", mode="RGB", color=(200, 100, 50))  # saved as JPEG
    frames = [{"file_path": f"images/{i}", "transform_matrix": pose(translation=(i, 0, 4.0))} for i in range(2)]
    (root / "transforms.json").write_text(json.dumps({"fl_x": 10.0, "frames": frames}))
    scene = load_scene(root)
    assert scene.names == ["images/0", "images/1"]
    assert torch.allclose(scene.images[:, 3, 4], torch.tensor([200.0, 100, 50]) / 255, atol=0.02)


@pytest.mark.parametrize("on_disk, in_json", [("NFD", "NFC"), ("NFC", "NFD")])
def test_an_image_name_in_another_unicode_normal_form_is_found(tmp_path, on_disk, in_json):
    """"café" decomposed (NFD, as macOS often writes file names) and composed (NFC, as most JSON holds it) are one
    name to the user and other bytes to Linux: the image had not been found."""
    import unicodedata

    root = tmp_path / "u"
    name = "images/café_{}.png"
    frames = []
    for i in range(2):
        write_png(root / unicodedata.normalize(on_disk, name.format(i)), mode="RGB", color=(200, 100, 50))
        frames.append({"file_path": unicodedata.normalize(in_json, name.format(i)),
                       "transform_matrix": pose(translation=(i, 0, 4.0))})
    (root / "transforms.json").write_text(json.dumps({"fl_x": 10.0, "frames": frames}))
    scene = load_scene(root)
    assert len(scene.names) == 2
    assert torch.allclose(scene.images[:, 3, 4], torch.tensor([200.0, 100, 50]) / 255, atol=0.01)


def test_unreadable_image(tmp_path):
    root = make_synthetic(tmp_path / "s")
    (root / "train" / "r_2.png").write_bytes(b"this is not a png at all")
    with pytest.raises(DatasetError, match="cannot read image r_2.png") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 2)
    assert err.value.path == root / "train" / "r_2.png"


def test_decompression_bomb_refused(tmp_path, monkeypatch):
    root = make_synthetic(tmp_path / "s", n=1)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 10)  # 48 pixels > 2x the limit
    with pytest.raises(DatasetError, match="decompression bomb") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 0)


def test_mixed_image_sizes(tmp_path):
    root = make_synthetic(tmp_path / "s")
    write_png(root / "train" / "r_2.png", size=(5, 5))
    with pytest.raises(DatasetError, match="image size 5x5 differs from frame 0") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 2)
    assert "8x6" in str(err.value)


def test_size_disagrees_with_intrinsics(tmp_path):
    root = make_ngp(tmp_path / "s", n=2, w=16)
    with pytest.raises(DatasetError, match="w=16") as err:
        load_scene(root)
    assert_names(err, "transforms.json", 0)


def test_a_size_refusal_names_the_exif_orientation_that_turns_the_image(tmp_path):
    """A phone's portrait photo stored landscape, tagged to display turned: read as stored (as COLMAP and instant-ngp
    read it), so a size given as displayed, or an image among upright ones, is refused, now naming the tag."""
    root = make_ngp(tmp_path / "s", n=3, size=(8, 6))
    meta = json.loads((root / "transforms.json").read_text())
    del meta["w"], meta["h"]
    (root / "transforms.json").write_text(json.dumps(meta))
    exif = Image.Exif()
    exif[0x0112] = 6  # displayed rotated 90° clockwise
    Image.new("RGB", (6, 8)).save(root / "images" / "0001.png", exif=exif)  # as displayed: 8x6, the others' size
    with pytest.raises(DatasetError, match=r"size 6x8 differs .* share one size \(its EXIF orientation 6 displays "
                                           r"it turned a quarter, 8x6, but images are read as stored") as err:
        load_scene(root)
    assert_names(err, "transforms.json", 1)
    meta["frames"] = meta["frames"][1:2]
    meta.update(w=6, h=8)
    (root / "transforms.json").write_text(json.dumps(meta))
    assert load_scene(root).images.shape[1:3] == (8, 6)  # its stored pixels, as its size says
    meta.update(w=8, h=6)
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"image is 6x8 but the intrinsics say w=8 \(its EXIF orientation 6"):
        load_scene(root)
    Image.new("RGB", (6, 8)).save(root / "images" / "0001.png")  # untagged: no orientation to name
    with pytest.raises(DatasetError, match=r"image is 6x8 but the intrinsics say w=8$"):
        load_scene(root)


def test_each_images_exif_orientation_gives_its_displayed_up_and_a_damaged_block_none(tmp_path):
    """The cameras carry each image's up as displayed (``Cameras.display_up``, what the scene frame levels by);
    pixels and poses stay as stored. A damaged EXIF block (Pillow raises on it) is no tag: the image still loads."""
    root = make_ngp(tmp_path / "s", n=4, size=(8, 6))
    for i, orientation in enumerate((6, 8, 3)):
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.new("RGB", (8, 6), (10, 20, 30)).save(root / "images" / f"{i:04d}.png", exif=exif)
    Image.new("RGB", (8, 6), (10, 20, 30)).save(root / "images" / "0003.png", exif=b"not an EXIF block")
    scene = load_scene(root, downsample=2)
    assert scene.images.shape == (4, 3, 4, 3)
    expected = torch.tensor([[-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0]])
    assert torch.equal(scene.cameras.display_up, expected)
    assert torch.equal(scene.cameras[1:3].display_up, expected[1:3])
    assert load_scene(root, max_images=1).cameras.display_up.tolist() == [[-1.0, 0, 0]]


def test_nan_in_pose(tmp_path):
    root = make_synthetic(tmp_path / "s")
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"][1]["transform_matrix"][0][3] = float("nan")
    (root / "transforms_train.json").write_text(json.dumps(meta))  # json writes the NaN literal
    with pytest.raises(DatasetError, match="NaN or Inf") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 1)


def test_the_frames_of_a_large_capture_are_checked_in_time_linear_in_their_count(tmp_path):
    """Each frame's lens model was compared with every earlier frame's (time quadratic in the count): 20,000 frames
    (a 3 MB transforms json) took 30 s to check, 40,000 (6 MB, of a few images: the upload's check reads every
    frame's entry before its images) 113 s, an upload request held all along; now 2 and 3 s. Here the last frame's
    NaN is found after every frame's entry was checked."""
    from service_helpers import Deadline

    count = 40_000
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": pose(translation=(0, 0, 4.0 + i % 7))}
              for i in range(count)]
    frames[-1]["transform_matrix"][0][3] = float("nan")
    root = make_synthetic(tmp_path / "s", frames=frames)
    deadline = Deadline(20)  # (the quadratic check took 88-113 s here; the linear one 2-3 s on a loaded machine)
    with pytest.raises(DatasetError, match="NaN or Inf") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", count - 1)
    assert deadline, f"checking {count} frames took {deadline}"


def test_numbers_beyond_float_range_name_frame_and_field(tmp_path):
    """A 400-digit integer fits no float (json reads it; numpy raises OverflowError); 1e39 fits float64 but would
    be inf in the float32 cameras, as would the focal of a camera_angle_x of 1e-300 radians."""
    root = make_ngp(tmp_path / "s", n=2)
    meta = json.loads((root / "transforms.json").read_text())
    for value, message in ((10**400, "transform_matrix holds an integer too large for a float"),
                           (1e39, r"transform_matrix contains NaN or Inf, or a value beyond float32's range")):
        meta["frames"][1]["transform_matrix"][0][3] = value
        (root / "transforms.json").write_text(json.dumps(meta))
        with pytest.raises(DatasetError, match=message) as err:
            load_scene(root)
        assert_names(err, "transforms.json", 1)
    for case, (top, frame, message) in enumerate((
        ({"fl_x": 1e39}, None, r"'fl_x' = 1e\+39 is beyond float32's range"),
        ({"k1": -1e39}, None, r"'k1' = -1e\+39 is beyond float32's range"),
        ({"fl_x": None, "camera_angle_x": 1e-300}, 0,  # null: no fl_x
         r"focal length fx = 8e\+300 pixels is beyond float32's range"),
    )):
        with pytest.raises(DatasetError, match=message) as err:
            load_scene(make_ngp(tmp_path / f"case{case}", n=1, **top))
        assert_names(err, "transforms.json", frame)
        assert err.value.frame == frame


@pytest.mark.parametrize("value", [True, "1", None, "nan"])
def test_a_pose_entry_that_is_no_number_is_refused_naming_frame_and_entry(tmp_path, value):
    """Regression: numpy had read JSON's true and "1" as 1 (the pose taken) and null as NaN (refused as a NaN)."""
    root = make_ngp(tmp_path / "s", n=2)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][1]["transform_matrix"][2][2] = value
    (root / "transforms.json").write_text(json.dumps(meta))
    message = rf"transform_matrix\[2\]\[2\] is {re.escape(repr(value))}, not a number"
    with pytest.raises(DatasetError, match=message) as err:
        load_scene(root)
    assert_names(err, "transforms.json", 1)


def test_a_long_value_in_the_wrong_place_is_quoted_cut_short(tmp_path):
    """A 4 MB string as a pose entry or a focal had been quoted whole in the refusal (a 4 MB 422 from the API)."""
    root = make_ngp(tmp_path / "s", n=2)
    meta = json.loads((root / "transforms.json").read_text())
    for place in ("pose", "focal"):
        frames = [dict(frame) for frame in meta["frames"]]
        if place == "pose":
            frames[1]["transform_matrix"] = [[*row] for row in frames[1]["transform_matrix"]]
            frames[1]["transform_matrix"][0][0] = "x" * 4_000_000
        else:
            frames[1]["fl_x"] = "x" * 4_000_000
        (root / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
        with pytest.raises(DatasetError, match=r"'xxxxx+\.\.\. \(4,000,002 characters\)") as err:
            load_scene(root)
        assert len(str(err.value)) < 200, place


def test_every_numeric_field_refuses_a_boolean_or_a_string_naming_frame_and_field(tmp_path):
    root = make_ngp(tmp_path / "s", n=2)
    meta = json.loads((root / "transforms.json").read_text())
    for key in (*_INTRINSIC_KEYS, *DISTORTION_KEYS):
        for value in (True, "1"):
            frames = [dict(frame) for frame in meta["frames"]]
            frames[1][key] = value
            (root / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
            with pytest.raises(DatasetError, match=f"'{key}' must be a number, got {re.escape(repr(value))}") as err:
                load_scene(root)
            assert_names(err, "transforms.json", 1)


@pytest.mark.parametrize("scale", [0, -4, 0.0])
def test_an_aabb_scale_that_is_not_positive_is_refused(tmp_path, scale):
    """Regression: an aabb_scale of 0 or -4 had been taken into Scene.aabb_scale."""
    with pytest.raises(DatasetError, match=f"'aabb_scale' = {scale:g} must be positive") as err:
        load_scene(make_ngp(tmp_path / "s", n=1, aabb_scale=scale))
    assert_names(err, "transforms.json", None)
    assert load_scene(make_ngp(tmp_path / "ok", n=1, aabb_scale=0.5)).aabb_scale == 0.5


def test_an_image_size_that_is_not_a_whole_number_is_refused(tmp_path):
    """Regression: w = 8.4 had been rounded to the 8-pixel image's width and taken."""
    root = make_ngp(tmp_path / "s", n=2)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][1]["w"] = 8.4
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="image size 'w' = 8.4 is not a whole number of pixels") as err:
        load_scene(root)
    assert_names(err, "transforms.json", 1)
    assert load_scene(make_ngp(tmp_path / "whole", n=1, w=8.0, h=6.0)).cameras.width == 8


def test_pose_not_four_by_four_or_bad_last_row(tmp_path):
    root = make_synthetic(tmp_path / "a")
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"][0]["transform_matrix"] = meta["frames"][0]["transform_matrix"][:3]
    (root / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"shape \(3, 4\)") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 0)

    bad = pose()
    bad[3] = [0.0, 0.0, 1.0, 1.0]
    root = make_synthetic(tmp_path / "b", frames=[{"file_path": "x", "transform_matrix": bad}])
    with pytest.raises(DatasetError, match="last row") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 0)


def test_non_rigid_rotation(tmp_path):
    root = make_synthetic(tmp_path / "s")
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"][2]["transform_matrix"] = pose(rotation=2 * np.eye(3))
    (root / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"not orthonormal \(max \|R\^T R - I\| = 3\)") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 2)


def test_reflection_rotation(tmp_path):
    root = make_synthetic(tmp_path / "s")
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"][1]["transform_matrix"] = pose(rotation=np.diag([1.0, 1.0, -1.0]))
    (root / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"reflection.*det R = -1") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 1)


def test_missing_intrinsics(tmp_path):
    root = make_ngp(tmp_path / "s")
    meta = json.loads((root / "transforms.json").read_text())
    del meta["fl_x"]
    meta["frames"][0]["fl_x"] = 10.0  # frame 0 has its own focal, frame 1 has none
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="missing intrinsics") as err:
        load_scene(root)
    assert_names(err, "transforms.json", 1)


def test_zero_focal(tmp_path):
    root = make_ngp(tmp_path / "a", fl_x=0.0)
    with pytest.raises(DatasetError, match="'fl_x' = 0.0 must be positive") as err:
        load_scene(root)
    assert_names(err, "transforms.json", None)  # a top-level value: no single frame to blame
    assert err.value.frame is None

    root = make_ngp(tmp_path / "b")
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][3]["fl_y"] = 1e-6
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="near-singular") as err:
        load_scene(root)
    assert_names(err, "transforms.json", 3)


def test_bad_camera_angle(tmp_path):
    root = make_synthetic(tmp_path / "a", camera_angle_x=4.0)
    with pytest.raises(DatasetError, match=r"outside \(0, pi\)") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", None)
    root = make_synthetic(tmp_path / "b", camera_angle_x=float("inf"))
    with pytest.raises(DatasetError, match="not finite") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", None)


def test_empty_frames(tmp_path):
    root = make_synthetic(tmp_path / "s", frames=[])
    with pytest.raises(DatasetError, match="empty split") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", None)


@pytest.mark.parametrize("change, frame, message", [
    (lambda m: m.pop("frames"), None, "'frames' is missing (the list of frames, each with a 'file_path' and a "
                                      "'transform_matrix')"),
    (lambda m: m.update(frames=None), None, "'frames' must be a list, got None"),
    (lambda m: m.update(frames={"r_0": {}}), None, "'frames' must be a list, got {'r_0': {}}"),
    (lambda m: m["frames"].__setitem__(2, "train/r_2.png"), 2, "frame entry must be an object, got 'train/r_2.png'"),
    (lambda m: m["frames"][1].update(file_path=None), 1, "'file_path' must be a non-empty string, got None"),
    (lambda m: m["frames"][1].update(file_path=7), 1, "'file_path' must be a non-empty string, got 7"),
])
def test_a_malformed_frames_list_is_refused_showing_what_it_holds(tmp_path, change, frame, message):
    """Regression: these had said "'frames' is missing or not a list", "frame entry is not an object" and
    "'file_path' must be a non-empty string", never what the json held instead."""
    root = make_synthetic(tmp_path / "s")
    meta = json.loads((root / "transforms_train.json").read_text())
    change(meta)
    (root / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError) as err:
        load_scene(root)
    assert str(err.value).endswith(message)
    assert_names(err, "transforms_train.json", frame)


def test_decoding_an_image_holds_one_float_copy_of_it(tmp_path):
    """Regression: the upload check's load (max_images=1, downsample 8) had held three float32 copies of the first
    image at full size (its pixels, them divided by 255, them premultiplied): 2 GB for a 50-megapixel photo, under
    VOXE_MAX_IMAGE_PIXELS. Now one (and the 8-bit one Pillow's pixels pass through); the pixels are as before."""
    import tracemalloc

    import torch.nn.functional as F

    rgba = np.random.default_rng(0).integers(0, 256, (800, 1000, 4), dtype=np.uint8)
    root = make_synthetic(tmp_path / "s", n=1)
    Image.fromarray(rgba, "RGBA").save(root / "train" / "r_0.png")
    pixels = rgba.astype(np.float64) / 255
    pixels[..., :3] *= pixels[..., 3:]
    planes = torch.from_numpy(pixels).permute(2, 0, 1)[None]
    references = {"box": pixels.reshape(100, 8, 125, 8, 4).mean(axis=(1, 3)),
                  "bilinear": F.interpolate(planes, size=(100, 125), mode="bilinear", antialias=True,
                                            align_corners=False)[0].permute(1, 2, 0).clamp(0, 1).numpy()}
    for resample, boxed in references.items():
        tracemalloc.start()
        try:
            scene = load_scene(root, "train", downsample=8, max_images=1, resample=resample)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 1.4 * rgba.size * 4, (resample, peak / (rgba.size * 4))
        expected = np.clip(boxed[..., :3] + 1 - boxed[..., 3:], 0, 1)
        assert np.allclose(scene.images[0].numpy(), expected, atol=1e-5), resample
        assert np.allclose(scene.alphas[0].numpy(), boxed[..., 3], atol=1e-5), resample


def test_invalid_json(tmp_path):
    root = tmp_path / "s"
    root.mkdir()
    (root / "transforms_train.json").write_text('{"camera_angle_x": 0.69,\n "frames": [,]}')
    with pytest.raises(DatasetError, match="invalid JSON at line 2 column 13") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", None)


def test_json_nested_too_deeply_is_a_dataset_error(tmp_path):
    """Regression: json's RecursionError had escaped load_scene (an upload's check answered 500)."""
    root = tmp_path / "s"
    root.mkdir()
    (root / "transforms.json").write_text('{"frames": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(DatasetError, match="transforms.json: its JSON arrays or objects nest too deeply") as err:
        load_scene(root)
    assert_names(err, "transforms.json", None)


def test_missing_split_file(tmp_path):
    root = make_synthetic(tmp_path / "s")
    with pytest.raises(DatasetError, match="not found") as err:
        load_scene(root, split="val")
    assert_names(err, "transforms_val.json", None)


def test_frame_missing_keys(tmp_path):
    root = make_synthetic(tmp_path / "s")
    meta = json.loads((root / "transforms_train.json").read_text())
    del meta["frames"][1]["transform_matrix"]
    (root / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="missing 'transform_matrix'") as err:
        load_scene(root)
    assert_names(err, "transforms_train.json", 1)


def test_duplicate_file_path(tmp_path):
    root = make_synthetic(tmp_path / "s")
    meta = json.loads((root / "transforms_train.json").read_text())
    for same_image in ("train/r_0", "./train/r_0.png"):  # './train/r_0' reads train/r_0.png: the .png is implied
        meta["frames"][2]["file_path"] = same_image
        (root / "transforms_train.json").write_text(json.dumps(meta))
        with pytest.raises(DatasetError, match="duplicate file_path.*frame 0") as err:
            load_scene(root)
        assert_names(err, "transforms_train.json", 2)


def test_windows_separators_in_file_path_are_read_as_instant_ngp_reads_them(tmp_path):
    """instant-ngp reads a transforms.json written on Windows ('images\\0000.png') with '/' separators: its images had
    not been found. An upload's confinement holds for the path as read ('..\\' is '../')."""
    root = make_ngp(tmp_path / "w")
    meta = json.loads((root / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["file_path"] = frame["file_path"].replace("/", "\\")
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root, confine_paths=True)
    assert scene.names == [f"images/{i:04d}.png" for i in range(4)]
    assert torch.allclose(scene.images[:, 0, 0], torch.tensor([[10.0 * i, 20, 30] for i in range(4)]) / 255)
    write_png(tmp_path / "outside" / "0000.png", mode="RGB")
    meta["frames"][1]["file_path"] = "..\\outside\\0000.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="'file_path' leads outside the dataset folder") as err:
        load_scene(root, confine_paths=True)
    assert_names(err, "transforms.json", 1)


def test_confined_paths_stay_inside_the_dataset(tmp_path):
    """A local dataset may reach a sibling folder; an upload (confine_paths) may not, nor by an absolute path."""
    write_png(tmp_path / "shared" / "r_0.png")
    frames = [{"file_path": "../shared/r_0", "transform_matrix": pose()}]
    root = make_synthetic(tmp_path / "s", frames=frames)
    assert len(load_scene(root)) == 1
    with pytest.raises(DatasetError, match="'file_path' leads outside the dataset folder") as err:
        load_scene(root, confine_paths=True)
    assert_names(err, "transforms_train.json", 0)
    frames[0]["file_path"] = str(tmp_path / "shared" / "r_0")
    make_synthetic(root, frames=frames)
    assert len(load_scene(root)) == 1
    with pytest.raises(DatasetError, match="leads outside the dataset folder"):
        load_scene(root, confine_paths=True)
    frames[0]["file_path"] = "./inner/../r_0"  # '..' that stays inside is fine
    write_png(root / "r_0.png")
    (root / "inner").mkdir()
    make_synthetic(root, frames=frames)
    assert load_scene(root, confine_paths=True).names == ["./inner/../r_0"]
    frames[0]["file_path"] = "r_0\x00.png"
    make_synthetic(root, frames=frames)
    with pytest.raises(DatasetError, match="'file_path' contains a NUL character"):
        load_scene(root)
    for surrogate in ("\ud800", "\udc80"):  # JSON's "\ud800": half a surrogate pair, a UnicodeEncodeError (a 500);
        frames[0]["file_path"] = f"r_{surrogate}.png"  # "\udc80" os.fsencode takes (an undecodable byte's escape)
        make_synthetic(root, frames=frames)
        for confine_paths in (False, True):
            with pytest.raises(DatasetError, match=rf"frame 0 .*'file_path' holds {re.escape(repr(surrogate))}, a lone "
                                                   "surrogate"):
                load_scene(root, confine_paths=confine_paths)


def test_bad_arguments_are_value_errors(tmp_path):
    root = make_synthetic(tmp_path / "s")
    for kwargs in ({"downsample": 0}, {"downsample": 1.5}, {"max_images": 0}, {"split": "../x"}):
        with pytest.raises(ValueError) as err:
            load_scene(root, **kwargs)
        assert not isinstance(err.value, DatasetError)


@pytest.mark.parametrize("index", [3, -4])
def test_a_camera_index_out_of_range_names_the_index_and_the_count(index):
    """``cameras[3]`` of three cameras had raised range()'s bare "range object index out of range"."""
    from voxe_core.cameras import Cameras

    cameras = Cameras.from_fov(torch.eye(4).expand(3, 4, 4), 0.7, 8, 8)
    assert torch.equal(cameras[-3].c2w, cameras[0].c2w) and torch.equal(cameras[2].c2w, cameras[-1].c2w)
    with pytest.raises(IndexError, match=rf"^camera {index} out of range: there are 3 cameras$"):
        cameras[index]
