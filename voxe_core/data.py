"""Posed image sets: NeRF-synthetic, instant-ngp / nerfstudio ``transforms.json``, COLMAP sparse models.

Everything is validated up front so a broken upload fails with one message that
names the file and frame, instead of a NaN loss an hour into a fit. Images come
back float32 in [0, 1], composited on white (SPEC §0), on the CPU.

Lens distortion is read into ``Cameras.distortion`` and applied by the rays
(``voxe_core.cameras``): nerfstudio's ``camera_model`` PINHOLE, OPENCV or
OPENCV_FISHEYE (its reader's SIMPLE_PINHOLE a PINHOLE, SIMPLE_RADIAL and RADIAL OPENCV)
with ``k1..k4, p1, p2`` (top level or per frame); instant-ngp's
``"is_fisheye": true`` is OPENCV_FISHEYE and its ``k1, k2, p1, p2`` without either are
OPENCV. The declared model decides the lens: a fisheye without coefficients is still the
equidistant projection, not a pinhole. A COLMAP model
(``sparse/0/`` as COLMAP's mapper writes it, or ``sparse/`` as its image undistorter does: ``cameras.bin|txt``
and ``images.bin|txt``, images under ``images/``)
is read by ``voxe_core.colmap`` and turned into the same frames (its poses from OpenCV's
camera axes into the OpenGL ones, the world frame kept).
"""

from __future__ import annotations

import json
import math
import os
import re
import unicodedata
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from .cameras import DISTORTION_KEYS, Cameras, fisheye_angles, fold_in_view, undistort_points
from .colmap import MAX_IMAGE_SIDE, ColmapError, read_model

_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "x_fov", "y_fov")
# Each axis's focal, any one key, the first given read as instant-ngp reads them (its read_focal_length): x_fov,
# y_fov (the full field of view in degrees), fl_x, fl_y (pixels), camera_angle_x, camera_angle_y (radians).
_FOCAL_KEYS = (("x_fov", "fl_x", "camera_angle_x"), ("y_fov", "fl_y", "camera_angle_y"))
# nerfstudio's camera_model -> Cameras.distortion_model (None: a pinhole)
CAMERA_MODELS = {"PINHOLE": None, "OPENCV": "opencv", "OPENCV_FISHEYE": "fisheye"}
# The other camera_model names nerfstudio's reader takes (its CAMERA_MODEL_TO_TYPE: perspective cameras whose lens is
# the k1..k4, p1, p2 given), as the model each is here; converters to nerfstudio's format write SIMPLE_PINHOLE.
CAMERA_MODEL_ALIASES = {"SIMPLE_PINHOLE": "PINHOLE", "SIMPLE_RADIAL": "OPENCV", "RADIAL": "OPENCV"}
# instant-ngp's lenses besides its OpenCV ones, by the key that declares them: read as a pinhole, their images had
# been fitted with the wrong rays
_OTHER_INSTANT_NGP_LENSES = {"latlong": "equirectangular (latitude-longitude) lens", "ftheta_p0": "f-theta lens"}
# COLMAP camera models: (their parameter names in order, the nerfstudio camera_model they are)
_COLMAP_MODELS = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), "PINHOLE"),
    "PINHOLE": (("fl_x", "fl_y", "cx", "cy"), "PINHOLE"),
    "SIMPLE_RADIAL": (("f", "cx", "cy", "k1"), "OPENCV"),
    "RADIAL": (("f", "cx", "cy", "k1", "k2"), "OPENCV"),
    "OPENCV": (("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"), "OPENCV"),
    "SIMPLE_RADIAL_FISHEYE": (("f", "cx", "cy", "k1"), "OPENCV_FISHEYE"),
    "RADIAL_FISHEYE": (("f", "cx", "cy", "k1", "k2"), "OPENCV_FISHEYE"),
    "OPENCV_FISHEYE": (("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4"), "OPENCV_FISHEYE"),
}
# Where a COLMAP model is looked for, in turn: the mapper's first model, then the image undistorter's (its
# ``sparse/`` beside the undistorted ``images/``). Both there: sparse/0, which had been read before sparse/ was.
COLMAP_MODEL_DIRS = (Path("sparse") / "0", Path("sparse"))
COLMAP_IMAGE_DIR = "images"
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: y down, z forward -> y up, z backward
_MIN_FOCAL = 1e-3  # pixels; below this the projection is numerically singular
_FLOAT32_MAX = float(np.finfo(np.float32).max)  # Cameras hold float32: a larger magnitude would become inf
_SIXTEEN_BIT_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I")
RESAMPLE_FILTERS = ("bilinear", "box")
_EXIF_ORIENTATION = 0x0112  # the EXIF tag
_QUARTER_TURN_ORIENTATIONS = (5, 6, 7, 8)  # its values that display the stored pixels turned by 90° (5, 7 mirrored)
# The stored image's side each value displays at the top, in camera axes (x right, y up): Pillow's exif_transpose
# turns the left side up for 5 and 6, the right for 7 and 8, the bottom for 3 and 4; 1, 2 and no tag keep +y.
_DISPLAY_UP = {3: (0.0, -1.0, 0.0), 4: (0.0, -1.0, 0.0), 5: (-1.0, 0.0, 0.0), 6: (-1.0, 0.0, 0.0),
               7: (1.0, 0.0, 0.0), 8: (1.0, 0.0, 0.0)}
_STORED_UP = (0.0, 1.0, 0.0)
_IMPLIED_EXTENSIONS = (".png", ".jpg", ".jpeg")  # tried in turn after a file_path as written (``image_candidates``)
_PATH_SHOWN = 100  # characters of a frame's file_path a message shows (a json may hold any number)
JSON_BYTES_PER_FRAME = 16 << 10
"""The most bytes of a transforms json ``load_scene``'s ``max_frames`` lets in per frame: ten times a frame with every
key it reads, written with an indent of 4. A json is read whole before its frames can be counted (36 MB took 9 s of an
upload's check)."""


class DatasetError(ValueError):
    """Bad data on disk. The message names the file and, where relevant, the frame."""

    def __init__(self, message: str, path: str | os.PathLike | None = None, frame: int | None = None):
        super().__init__(message)
        self.path = None if path is None else Path(path)
        self.frame = frame


@dataclass
class Scene:
    """Images (N, H, W, 3) composited on white, their cameras, and what the file recorded."""

    images: torch.Tensor
    alphas: torch.Tensor | None
    cameras: Cameras
    names: list[str]
    format: str
    split: str
    aabb_scale: float | None = None
    # (S, 4, 4) camera-to-world of every frame of the split when max_images kept fewer (None: the cameras are all of
    # it): what tells a subset too narrow to fit from a capture that is (``voxe_core.backbones.prepare_backbone``).
    split_c2w: torch.Tensor | None = None

    @property
    def has_alpha(self) -> bool:
        return self.alphas is not None

    def __len__(self) -> int:
        return self.images.shape[0]


class _Where:
    """Builds DatasetErrors that say which json file and which frame."""

    def __init__(self, json_path: Path, frames: list | None = None, label: str | None = None):
        self.json_path, self.frames = json_path, [] if frames is None else frames
        self.label = label or json_path.name

    def __call__(self, message: str, frame: int | None = None, path=None) -> DatasetError:
        prefix = self.label
        if frame is not None:
            fp = self.frames[frame].get("file_path") if isinstance(self.frames[frame], dict) else None
            prefix += f" frame {frame}" + (f" ({_shown(fp, _PATH_SHOWN)})" if fp is not None else "")
        return DatasetError(f"{prefix}: {message}", path or self.json_path, frame)


def detect_format(root: str | os.PathLike) -> str:
    """'nerf_synthetic' (transforms_{train,val,test}.json), 'instant_ngp' (one transforms.json, also
    nerfstudio's) or 'colmap' (``colmap_model_dir``); a transforms json wins over a COLMAP model."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder (expected a dataset folder with transforms json files)", root)
    if any((root / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        return "nerf_synthetic"
    if (root / "transforms.json").is_file():
        return "instant_ngp"
    if colmap_model_dir(root) is not None:
        return "colmap"
    raise DatasetError(
        f"{root}: no dataset found (expected transforms_train.json for NeRF-synthetic, transforms.json for "
        f"instant-ngp / nerfstudio, or a COLMAP model sparse/0/cameras.bin|txt or sparse/cameras.bin|txt)", root
    )


def colmap_model_dir(root: Path) -> Path | None:
    """The first of ``COLMAP_MODEL_DIRS`` under ``root`` that holds a ``cameras.bin|txt`` (None: neither does)."""
    return next((root / d for d in COLMAP_MODEL_DIRS
                 if any((root / d / f"cameras.{ext}").is_file() for ext in ("bin", "txt"))), None)


def is_dataset_folder(root: str | os.PathLike) -> bool:
    """Whether ``root`` holds a dataset ``load_scene`` recognises (its files are not checked)."""
    try:
        detect_format(root)
    except DatasetError:
        return False
    return True


def load_scene(
    root: str | os.PathLike,
    split: str = "train",
    downsample: int = 1,
    max_images: int | None = None,
    holdout_every: int | None = None,
    confine_paths: bool = False,
    resample: str = "bilinear",
    pixels: bool = True,
    max_frames: int | None = None,
) -> Scene:
    """Load one split of a dataset folder.

    ``downsample`` is an integer factor (images are cropped to a multiple of it at the
    right/bottom, which leaves the principal point where it was). ``resample`` is its
    antialiasing filter on that crop: "bilinear" (a triangle of the factor's width: PIL's
    and torchvision's resize, which the authors' loader uses; where the size is not a
    multiple, theirs resizes the uncropped image by a slightly larger factor) or "box"
    (the mean of each factor x factor block).
    ``holdout_every`` (instant-ngp and COLMAP: one set of frames): frames 0, k, 2k, ... form "test" and the rest
    "train"; NeRF-synthetic's splits are its files, so it is refused there (ignored, a "test" had been the test
    file and a "train" every training frame, whatever was asked). ``max_images`` keeps the first k
    frames of the split. Frame indices in errors are positions in the json's ``frames``.
    ``confine_paths``: refuse a ``file_path`` that leads outside ``root`` (absolute, or up
    through ``..``), so an untrusted upload cannot read other files on the machine.
    ``pixels=False`` (the upload check) decodes each kept image only to find what would refuse it (``_check_image``),
    keeping none: ``images`` is (N, H, W, 0). Its float copies had held a 50-megapixel upload's 1.2 GB or more.
    ``max_frames`` (the upload check: the files the folder holds) refuses a split of more frames than that, which
    cannot each have an image of their own, before checking them one by one: a json of a million frames compresses
    to a few MB, and their checks had held an upload's request for many minutes. A json longer than
    ``JSON_BYTES_PER_FRAME`` times it is refused before it is read.
    """
    if not isinstance(downsample, int) or downsample < 1:
        raise ValueError(f"downsample must be a positive integer, got {downsample!r}")
    if resample not in RESAMPLE_FILTERS:
        raise ValueError(f"resample must be one of {', '.join(RESAMPLE_FILTERS)}, got {resample!r}")
    if max_images is not None and max_images < 1:
        raise ValueError(f"max_images must be at least 1, got {max_images!r}")
    if holdout_every is not None and holdout_every < 2:
        raise ValueError(f"holdout_every must be at least 2, got {holdout_every!r}")
    if not re.fullmatch(r"\w+", split):
        raise ValueError(f"split must be a plain name, got {split!r}")
    root = Path(root)
    fmt = detect_format(root)
    if holdout_every is not None and fmt == "nerf_synthetic":
        raise ValueError(f"holdout_every applies to a capture's single set of frames (instant-ngp, COLMAP); {root} is "
                         f"NeRF-synthetic, whose splits are its transforms_{{train,val,test}}.json: load split "
                         f"'test' (or 'val') without holdout_every")
    if fmt == "colmap":
        json_path, meta = colmap_transforms(root, max_frames)
    else:
        json_path = root / (f"transforms_{split}.json" if fmt == "nerf_synthetic" else "transforms.json")
        meta = _read_json(json_path, max_frames)
    where = _Where(json_path, label=json_path.relative_to(root).as_posix())
    frames = meta.get("frames")
    if "frames" not in meta:
        raise where("'frames' is missing (the list of frames, each with a 'file_path' and a 'transform_matrix')")
    if not isinstance(frames, list):
        raise where(f"'frames' must be a list, got {_shown(frames)}")
    if not frames:
        raise where("empty split: 'frames' has no entries")
    if max_frames is not None and len(frames) > max_frames:
        raise where(f"'frames' lists {len(frames):,} frames, more than the {max_frames:,} files in the dataset "
                    "folder: each frame needs an image of its own")
    where.frames = frames

    top = _check_intrinsics(meta, where, None)
    aabb = _aabb_scale(meta, where)
    top_model = _camera_model(meta, where, None)
    per_frame, paths, models = [], [], []
    first_of: dict[str, int] = {}  # each model's first frame: scanning every earlier frame had cost n² (minutes)
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise where(f"frame entry must be an object, got {_shown(frame)}", i)
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise where(f"missing '{key}'", i)
        if not isinstance(frame["file_path"], str) or not frame["file_path"]:
            raise where(f"'file_path' must be a non-empty string, got {_shown(frame['file_path'])}", i)
        if "\0" in frame["file_path"]:
            raise where("'file_path' contains a NUL character", i)
        if (unnamed := _unnameable(frame["file_path"])) is not None:
            raise where(f"'file_path' holds {unnamed!r}, a lone surrogate (JSON's \\u escape of half a UTF-16 pair), "
                        "which no file name can hold", i)
        file_path = _posix_file_path(frame["file_path"])
        if confine_paths and not _inside(root, file_path):
            raise where("'file_path' leads outside the dataset folder (absolute or through '..')", i)
        merged = _merge_intrinsics(top, _check_intrinsics(frame, where, i))
        if not any(k in merged for keys in _FOCAL_KEYS for k in keys):
            raise where("missing intrinsics: need 'camera_angle_x', 'fl_x' or 'x_fov' (or their y-axis keys, "
                        "'camera_angle_y', 'fl_y' or 'y_fov'), top level or per frame", i)
        model = _camera_model(frame, where, i) or top_model or ("OPENCV" if _distorts(merged) else "PINHOLE")
        _check_distortion(model, merged, where, i)
        # Cameras hold one lens model: a pinhole is an OPENCV lens without terms, but no fisheye lens is a pinhole.
        clash = min((j for m, j in first_of.items() if m != model and "OPENCV_FISHEYE" in (m, model)),
                    default=None)
        if clash is not None:
            other = models[clash] if model == "OPENCV_FISHEYE" else model
            raise where(f"camera_model {model} differs from frame {clash}'s {models[clash]}; the fisheye and the "
                        f"{other} model cannot be mixed in one capture", i)
        per_frame.append(merged)
        paths.append(file_path)
        models.append(model)
        first_of.setdefault(model, i)
    poses = _check_poses(frames, where)
    seen: dict[Path, int] = {}
    for i, p in enumerate(paths):
        key = (find_image(root, p) or root / p).resolve()  # 'images/0' reads 'images/0.png' when only that exists
        if key in seen:
            raise where(f"duplicate file_path (same image as frame {seen[key]})", i)
        seen[key] = i

    split_frames = _split_indices(fmt, split, len(frames), holdout_every, where)
    keep = split_frames[:max_images]

    images, alphas, size, orientations = None, None, None, []
    for slot, i in enumerate(keep):
        arr, (w, h), image_path, orientation = _read_image(root, paths[i], where, i, downsample, pixels)
        orientations.append(orientation)
        _check_stated_size(per_frame[i], w, h, image_path, where, i)
        if size is None:
            size, first = (w, h), i
            if w < downsample or h < downsample:
                raise where(f"image {w}x{h} is smaller than downsample {downsample}", i, image_path)
            hd, wd = h // downsample, w // downsample
            images = torch.empty(len(keep), hd, wd, 3 if pixels else 0)
        elif (w, h) != size:
            raise where(
                f"image size {w}x{h} differs from frame {first} ({_shown(paths[first], _PATH_SHOWN)}) size "
                f"{size[0]}x{size[1]}; all images of a split must share one "
                f"size{quarter_turn_hint(image_path, w, h, *size)}", i, image_path,
            )
        if arr is None:
            continue
        rgb, alpha = _composite_downsampled(arr, downsample, resample)
        images[slot] = torch.from_numpy(rgb)
        if alpha is not None:
            if alphas is None:
                alphas = torch.ones(len(keep), hd, wd)
            alphas[slot] = torch.from_numpy(alpha)

    W, H = size
    intr = np.array([_resolve_intrinsics(per_frame[i], W, H, where, i) for i in keep], dtype=np.float64)
    _check_principal_points(intr[:, 2], intr[:, 3], W, H, keep, where)
    c2w = torch.from_numpy(poses[keep]).float()
    cams = Cameras(c2w, *(torch.from_numpy(intr[:, k]).float() for k in range(4)), W, H)
    distortion_model = CAMERA_MODELS[next((m for m in models if m != "PINHOLE"), "PINHOLE")]
    # An OPENCV lens without terms is a pinhole; a fisheye one still images the angle (r = θ).
    if distortion_model == "fisheye" or (distortion_model == "opencv" and any(_distorts(per_frame[i]) for i in keep)):
        cams.distortion = torch.tensor([[per_frame[i].get(k, 0.0) for k in DISTORTION_KEYS] for i in keep])
        cams.distortion_model = distortion_model
        _check_invertible(cams, keep, where)
    cams.display_up = display_up(orientations)
    if downsample > 1:
        cams.width, cams.height = wd * downsample, hd * downsample  # the crop that was resampled
        cams = cams.scaled(1.0 / downsample)
    split_c2w = torch.from_numpy(poses[split_frames]).float() if len(keep) < len(split_frames) else None
    return Scene(images, alphas, cams, [paths[i] for i in keep], fmt, split, aabb, split_c2w)


def _camera_model(source: dict, where: _Where, frame: int | None) -> str | None:
    """The model ``source`` (top level or one frame) declares, one of ``CAMERA_MODELS`` (an alias as the model it
    is): its ``camera_model``, or OPENCV_FISHEYE for instant-ngp's ``"is_fisheye": true``; None when it declares
    none."""
    model, known = source.get("camera_model"), [*CAMERA_MODELS, *CAMERA_MODEL_ALIASES]
    if model is not None and (not isinstance(model, str) or model not in known):
        raise where(f"camera_model {model!r} is not supported (use one of {', '.join(known)})", frame)
    for key, lens in _OTHER_INSTANT_NGP_LENSES.items():  # its key's presence is the lens, whatever its value
        if key in source:
            raise where(f"'{key}' declares instant-ngp's {lens}, which is not supported (a pinhole, OPENCV or "
                        "OPENCV_FISHEYE lens is)", frame)
    fisheye = source.get("is_fisheye", False)
    if not isinstance(fisheye, bool):
        raise where(f"'is_fisheye' must be true or false, got {fisheye!r}", frame)
    if fisheye and model not in (None, "OPENCV_FISHEYE"):
        raise where(f"'is_fisheye' is true but camera_model is {model}", frame)
    return "OPENCV_FISHEYE" if fisheye else CAMERA_MODEL_ALIASES.get(model, model)


def _merge_intrinsics(top: dict, own: dict) -> dict:
    """A frame's intrinsics (``own``) over the top level's, key by key, except that a frame giving an axis's
    focal (any of its ``_FOCAL_KEYS``) hides all of the top level's keys for that axis: as in instant-ngp,
    a frame's ``camera_angle_x`` overrides a top-level ``fl_x``."""
    hidden = {k for keys in _FOCAL_KEYS if any(k in own for k in keys) for k in keys}
    return {**{k: v for k, v in top.items() if k not in hidden}, **own}


def _distorts(intrinsics: dict) -> bool:
    return any(intrinsics.get(k, 0.0) != 0.0 for k in DISTORTION_KEYS)


def _check_distortion(model: str, intrinsics: dict, where: _Where, frame: int) -> None:
    """Coefficients the model has no use for are refused rather than silently dropped."""
    unused = {"PINHOLE": DISTORTION_KEYS, "OPENCV_FISHEYE": ("p1", "p2")}.get(model, ())
    stray = [f"{k} = {intrinsics[k]:g}" for k in unused if intrinsics.get(k, 0.0) != 0.0]
    if stray:
        raise where(f"camera_model {model} has no such distortion term, but {', '.join(stray)}", frame)


def _check_invertible(cams: Cameras, keep: list[int], where: _Where) -> None:
    """Every camera's lens must give each sampled pixel one ray. Where the distortion folds the image over, a
    second ray also maps back to the pixel and the rays jump across the fold (``undistort_points``: NaN); a
    fisheye's ray may be up to 180° off its axis, not more. An OPENCV lens must also fold no part of the sheet
    holding its axis onto the image (``fold_in_view``): its tangential terms can fold an island between the
    samples, whose caustic's pixels then have several rays though each sample has one."""
    v, u = torch.meshgrid(torch.linspace(0, cams.height, 17, dtype=torch.float64),
                          torch.linspace(0, cams.width, 17, dtype=torch.float64), indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    checked = set()
    for slot, frame in enumerate(keep):
        fx, fy, cx, cy = (float(t[slot]) for t in (cams.fx, cams.fy, cams.cx, cams.cy))
        k = cams.distortion[slot].double()
        lens = (fx, fy, cx, cy, *k.tolist())
        if lens in checked:  # most captures share one lens
            continue
        checked.add(lens)
        xd, yd = (u - cx) / fx, (v - cy) / fy
        if cams.distortion_model == "fisheye":
            theta = fisheye_angles(xd, yd, k)
            if (theta >= math.pi).any():
                widest = int(theta.nan_to_num(0).argmax())
                degrees = math.degrees(float(theta[widest]))
                raise where(f"the fisheye lens images pixel ({float(u[widest]):.0f}, {float(v[widest]):.0f}) "
                            f"{degrees:.0f}° off its axis (a field of view of {2 * degrees:.0f}°), but no ray is "
                            f"more than 180° off it: check the focal length", frame)
            folded = torch.isnan(theta)
        else:
            folded = torch.isnan(undistort_points(xd, yd, k)[0])
        pixel = None
        if folded.any():
            first = int(folded.int().argmax())
            pixel = float(u[first]), float(v[first])
        elif cams.distortion_model == "opencv":
            pixel = fold_in_view(fx, fy, cx, cy, k, cams.width, cams.height)
        if pixel is not None:
            coefficients = ", ".join(f"{n} = {float(c):g}" for n, c in zip(DISTORTION_KEYS, k) if c != 0)
            raise where(f"lens distortion ({coefficients}) folds the image over at pixel ({pixel[0]:.0f}, "
                        f"{pixel[1]:.0f}): its rays there would jump across the fold", frame)


def colmap_transforms(root: Path, max_images: int | None = None) -> tuple[Path, dict]:
    """A COLMAP model as a transforms.json would hold it: (the file errors name, the meta dict).

    Frames are the model's images sorted by name (``images/<name>``), each with its camera's
    intrinsics and distortion and its pose as an OpenGL camera-to-world matrix. ``max_images``: ``read_model``'s.
    """
    model_dir = colmap_model_dir(root)
    if model_dir is None:
        raise DatasetError(f"{root}: no COLMAP model (sparse/0/cameras.bin|txt or sparse/cameras.bin|txt)", root)
    label = model_dir.relative_to(root).as_posix()
    try:
        cameras, images = read_model(model_dir, max_images)
    except ColmapError as e:
        raise DatasetError(f"{label}/{e}", e.path) from None
    images_file = model_dir / ("images.bin" if (model_dir / "cameras.bin").is_file() else "images.txt")
    frames: list[dict] = []
    where = _Where(images_file, frames, label=images_file.relative_to(root).as_posix())
    for image in sorted(images, key=lambda im: im.name):
        frame = {"file_path": f"{COLMAP_IMAGE_DIR}/{image.name}"}
        frames.append(frame)
        camera = cameras.get(image.camera_id)
        if camera is None:
            raise where(f"camera {image.camera_id} is not in {label}/cameras"
                        f"{images_file.suffix}", len(frames) - 1)
        if camera.model not in _COLMAP_MODELS:
            raise where(f"camera {image.camera_id} has COLMAP model {camera.model}, which is not supported (use one "
                        f"of {', '.join(_COLMAP_MODELS)})", len(frames) - 1)
        names, camera_model = _COLMAP_MODELS[camera.model]
        params = dict(zip(names, camera.params))
        if "f" in params:
            params["fl_x"] = params["fl_y"] = params.pop("f")
        frame.update(camera_model=camera_model, w=float(camera.width), h=float(camera.height), **params,
                     transform_matrix=(np.linalg.inv(image.cam_from_world) @ _OPENCV_TO_OPENGL).tolist())
    if not frames:
        raise where("the COLMAP model registers no images")
    return images_file, {"frames": frames}


def _inside(root: Path, file_path: str) -> bool:
    resolved_root = root.resolve()
    return (resolved_root / file_path).resolve().is_relative_to(resolved_root)


def _read_json(path: Path, max_frames: int | None = None) -> dict:
    """The json at ``path``; one longer than ``max_frames`` frames' ``JSON_BYTES_PER_FRAME`` is refused unread."""
    if not path.is_file():
        raise DatasetError(f"{path.name}: not found in {path.parent}", path)
    if max_frames is not None and (size := path.stat().st_size) > max_frames * JSON_BYTES_PER_FRAME:
        raise DatasetError(f"{path.name}: {size:,} bytes, more than the {max_frames * JSON_BYTES_PER_FRAME:,} "
                           f"({JSON_BYTES_PER_FRAME:,} a frame) the {max_frames:,} files in the dataset folder can "
                           "explain: each frame needs an image of its own", path)
    try:
        meta = json.loads(path.read_bytes())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path.name}: invalid JSON at line {e.lineno} column {e.colno} (char {e.pos}): {e.msg}", path) from e
    except (UnicodeDecodeError, OSError, ValueError) as e:  # ValueError: e.g. an integer of over 4,300 digits
        raise DatasetError(f"{path.name}: cannot read as JSON text: {e}", path) from e
    except RecursionError:  # (it had escaped as itself: an upload's check answered 500)
        raise DatasetError(f"{path.name}: its JSON arrays or objects nest too deeply", path) from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{path.name}: top level must be a JSON object, got {type(meta).__name__}", path)
    return meta


def _shown(value, limit: int = 40) -> str:
    """``value``'s repr cut to ``limit`` characters: a message quotes what a file holds, not a 4 MB string of it."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 3]}... ({len(text):,} characters)"


def _number(value, key: str, where: _Where, frame: int | None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise where(f"'{key}' must be a number, got {_shown(value)}", frame)
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float range
        raise where(f"'{key}' is out of range ({str(value)[:20]}..., {len(str(value))} digits)", frame) from None
    if not math.isfinite(number):
        raise where(f"'{key}' is not finite ({value})", frame)
    if abs(number) > _FLOAT32_MAX:
        raise where(f"'{key}' = {number:g} is beyond float32's range (magnitude up to {_FLOAT32_MAX:.3g})", frame)
    return number


def _aabb_scale(meta: dict, where: _Where) -> float | None:
    """The top level's ``aabb_scale`` (None: not given): instant-ngp's scene bound, a multiple of the unit cube, so
    positive; nothing here reads it, but a file holding 0 or a negative one is not the format's."""
    if meta.get("aabb_scale") is None:
        return None
    scale = _number(meta["aabb_scale"], "aabb_scale", where, None)
    if scale <= 0:
        raise where(f"'aabb_scale' = {scale:g} must be positive (the scene's bound as a multiple of the unit cube)")
    return scale


def _check_intrinsics(source: dict, where: _Where, frame: int | None) -> dict[str, float]:
    """Numeric, finite, in-range intrinsics/distortion keys present in ``source`` (top level or one frame)."""
    out = {k: _number(source[k], k, where, frame) for k in _INTRINSIC_KEYS + DISTORTION_KEYS if source.get(k) is not None}
    for k in ("camera_angle_x", "camera_angle_y"):
        if k in out and not 0.0 < out[k] < math.pi:
            raise where(f"'{k}' = {out[k]} is outside (0, pi) radians", frame)
    for k in ("x_fov", "y_fov"):
        if k in out and not 0.0 < out[k] < 180.0:
            raise where(f"'{k}' = {out[k]} is outside (0, 180) degrees", frame)
    for k in ("fl_x", "fl_y"):
        if k in out and out[k] <= 0:
            raise where(f"focal length '{k}' = {out[k]} must be positive", frame)
        if k in out and out[k] < _MIN_FOCAL:
            raise where(f"focal length '{k}' = {out[k]} is near-singular (< {_MIN_FOCAL} pixels)", frame)
    for k in ("w", "h"):
        if k in out and out[k] < 1:
            raise where(f"image size '{k}' = {out[k]} must be at least 1", frame)
        if k in out and not out[k].is_integer():  # it had been rounded to the image's size and taken
            raise where(f"image size '{k}' = {out[k]:g} is not a whole number of pixels", frame)
    return out


def _check_poses(frames: list, where: _Where) -> np.ndarray:
    """(N, 4, 4) float64 camera-to-world, checked to be finite rigid transforms."""
    mats = []
    for i, frame in enumerate(frames):
        entry = _non_number_entry(frame["transform_matrix"])
        if entry is not None:  # numpy reads JSON's true as 1, "1" as 1 and null as NaN
            (row, column), value = entry
            raise where(f"transform_matrix[{row}][{column}] is {_shown(value)}, not a number", i)
        try:
            m = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except OverflowError:  # an integer beyond float range
            raise where("transform_matrix holds an integer too large for a float", i) from None
        except (TypeError, ValueError):
            raise where("transform_matrix is not a numeric 4x4 matrix", i) from None
        if m.shape != (4, 4):
            raise where(f"transform_matrix has shape {m.shape}, expected (4, 4)", i)
        mats.append(m)
    poses = np.stack(mats)
    bad = ~(np.abs(poses) <= _FLOAT32_MAX).all(axis=(1, 2))  # NaN compares false
    if bad.any():
        raise where(f"transform_matrix contains NaN or Inf, or a value beyond float32's range (magnitude up to "
                    f"{_FLOAT32_MAX:.3g})", int(bad.argmax()))
    row_dev = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    if (row_dev > 1e-4).any():
        i = int((row_dev > 1e-4).argmax())
        raise where(f"transform_matrix last row is {poses[i, 3].tolist()}, expected [0, 0, 0, 1]", i)
    rot = poses[:, :3, :3]
    ortho_dev = np.abs(rot.transpose(0, 2, 1) @ rot - np.eye(3)).max(axis=(1, 2))
    if (ortho_dev > 1e-3).any():
        i = int((ortho_dev > 1e-3).argmax())
        raise where(f"rotation is not orthonormal (max |R^T R - I| = {ortho_dev[i]:.3g}); scale or shear in the pose", i)
    det = np.linalg.det(rot)
    if (det <= 0).any():
        i = int((det <= 0).argmax())
        raise where(f"rotation is a reflection, not a rigid rotation (det R = {det[i]:.3g})", i)
    return poses


def _non_number_entry(matrix) -> tuple[tuple[int, int], object] | None:
    """The first entry (its (row, column) and value) of a list of rows that is no JSON number (None: all are, or
    ``matrix`` is no list of rows, which the shape check names)."""
    if not isinstance(matrix, list) or not all(isinstance(row, list) for row in matrix):
        return None
    return next((((r, c), value) for r, row in enumerate(matrix) for c, value in enumerate(row)
                 if isinstance(value, bool) or not isinstance(value, (int, float))), None)


def _split_indices(fmt: str, split: str, n: int, holdout_every: int | None, where: _Where) -> list[int]:
    if fmt == "nerf_synthetic":
        return list(range(n))  # the split is the file
    if split == "all" or (split == "train" and holdout_every is None):
        return list(range(n))
    if split not in ("train", "test"):
        raise where(f"no split {split!r} in a single transforms.json (use 'train', 'test' or 'all')")
    if holdout_every is None:
        raise where("no test split: a single transforms.json (a capture) holds one set of frames; use the split "
                    "'train' or 'all' (voxe: --split train), or load_scene(..., holdout_every=N) to hold every N-th out")
    held = split == "test"
    keep = [i for i in range(n) if (i % holdout_every == 0) == held]
    if not keep:
        raise where(f"empty split: {split!r} with holdout_every={holdout_every} selects none of {n} frames")
    return keep


def _unnameable(file_path: str) -> str | None:
    """The characters of ``file_path`` UTF-8 cannot encode (None: none): a JSON "\\ud800" reads as a lone surrogate,
    on which every lookup of the path had raised a UnicodeEncodeError (an upload's check answered 500). Strictly:
    os.fsencode lets U+DC80..U+DCFF through (its surrogateescape, a name's undecodable bytes), and the "not found"
    that followed, naming the path, could not be encoded in the 422's JSON (a 500 again)."""
    try:
        file_path.encode("utf-8")
    except UnicodeEncodeError as e:
        return e.object[e.start:e.end]
    return None


def _posix_file_path(file_path: str) -> str:
    """A frame's ``file_path`` with Windows' separators as '/', as instant-ngp reads a transforms.json written on
    Windows (so no file name holding a '\\' can be read)."""
    return file_path.replace("\\", "/")


def image_candidates(root: Path, file_path: str) -> list[Path]:
    """Where a frame's image may be: its ``file_path`` (Windows' separators read as '/'), or that with an extension
    implied: ``.png`` (NeRF-synthetic's), ``.jpg`` or ``.jpeg`` (instant-ngp tries these too). The loader's rule, and
    the upload check's. Then the same in the other Unicode normal forms, where they differ: a name written on macOS
    (whose file names are often decomposed, NFD: "é" as "e" and an accent) is the same name to its user as the
    composed (NFC) one a JSON file or another system holds, yet other bytes to Linux, which had found no image."""
    file_path = _posix_file_path(file_path)
    spellings = dict.fromkeys([file_path, *(unicodedata.normalize(form, file_path) for form in ("NFC", "NFD"))])
    return [root / (spelling + extension) for spelling in spellings for extension in ("", *_IMPLIED_EXTENSIONS)]


def image_not_found(root: Path, file_path: str) -> str:
    """The refusal of a frame whose image ``find_image`` does not find, naming the paths tried where its
    ``file_path`` is short enough to show: a longer one had been echoed whole in each of up to 12 of them."""
    if len(file_path) > _PATH_SHOWN:
        return f"image not found (tried as written and with {', '.join(_IMPLIED_EXTENSIONS)} added)"
    return "image not found (tried " + ", ".join(str(p) for p in image_candidates(root, file_path)) + ")"


def find_image(root: Path, file_path: str) -> Path | None:
    """The file a frame's ``file_path`` reads (None: no candidate is there); a candidate whose name the file system
    cannot hold is none (a name's NFD spelling may pass the length limit its NFC one is within). The loader's rule,
    and the upload check's."""
    for path in image_candidates(root, file_path):
        try:
            if path.is_file():
                return path
        except OSError:  # e.g. a name longer than the file system allows: no such image
            continue
    return None


class PixelScaleError(ValueError):
    """An image whose pixels' scale to [0, 1] the file does not record; the message says what it holds."""


def image_pixels(image: Image.Image, alpha: bool = True) -> np.ndarray:
    """A Pillow image as (H, W, 3, or 4 where ``alpha`` and it has one) float32 in [0, 1]; 8- and 16-bit, grey,
    palette and RGB(A) alike. The one rule for capture images and mesh textures (``mesh_input``).

    Floating-point pixels (Pillow's mode F, e.g. a float TIFF) raise ``PixelScaleError``: the file does not say
    their scale (Pillow's own conversions give 0..255, OpenCV's and scikit-image's float images 0..1), and
    convert("RGB") had clipped them to black. So do 32-bit integers beyond 16 bits (mode I), which the 16-bit
    scaling had clipped to white. A 16-bit grey PNG's colour key (its tRNS: the one value that is transparent) is
    its alpha, as Pillow's conversion gives an 8-bit one's. So is a 16-bit RGB PNG's, at the 8 bits Pillow reads
    its colour with (each sample's high byte): Pillow compares those with the 16-bit key, which had missed the key
    colour and keyed others (key 100 a sample of 25600). A colour sharing the key's high bytes is keyed with it: the
    8-bit image cannot tell them apart (an exact match would need a 16-bit RGB decode, which Pillow lacks). Whether
    it is 16-bit shows only before the image loads.
    """
    _check_pixel_scale(image)
    if image.mode in _SIXTEEN_BIT_MODES:
        values = np.asarray(image)
        grey = np.repeat((values.astype(np.float32) / 65535.0)[..., None], 3, axis=2)
        key = image.info.get("transparency")
        if alpha and isinstance(key, int):
            return np.concatenate([grey, (values != key).astype(np.float32)[..., None]], axis=2)
        return grey
    if alpha and image.tile and image.tile[0][3] == "RGB;16B" and isinstance(image.info.get("transparency"), tuple):
        rgb = np.asarray(image)
        keyed = (rgb == np.array(image.info["transparency"]) >> 8).all(axis=-1)
        return np.concatenate([rgb / np.float32(255.0), (~keyed).astype(np.float32)[..., None]], axis=2)
    has_alpha = alpha and ("A" in image.mode or "a" in image.mode or "transparency" in image.info)
    pixels = np.asarray(image.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32)
    pixels /= 255.0  # in place: a second float32 copy of a 50-megapixel image is 800 MB more
    return pixels


def _check_pixel_scale(image: Image.Image) -> None:
    """``PixelScaleError`` for pixels whose scale to [0, 1] the file does not record (``image_pixels``)."""
    if image.mode == "F":
        raise PixelScaleError("holds floating-point pixels (Pillow mode F), whose scale the file does not record: "
                              "save it with 8 or 16 bits per channel")
    if image.mode in _SIXTEEN_BIT_MODES:
        low, high = image.getextrema()
        if not (low >= 0 and high <= 65535):
            raise PixelScaleError(f"holds 32-bit values from {low} to {high} (Pillow mode {image.mode}); only 8- and "
                                  "16-bit images (0..65535) are read")


def _check_image(image: Image.Image, factor: int = 1) -> None:
    """Decode ``image`` to find what ``image_pixels`` would refuse (damaged data, a scale not recorded) holding no
    more than Pillow's own decode, a JPEG's reduced up to ``factor`` times (up to 8) by its DCT scaling (``draft``)."""
    if factor > 1 and min(image.size) >= factor:
        image.draft(None, (image.width // factor, image.height // factor))
    image.load()
    _check_pixel_scale(image)


def _read_image(root: Path, file_path: str, where: _Where, frame: int, factor: int = 1,
                pixels: bool = True) -> tuple[np.ndarray | None, tuple[int, int], Path, int | None]:
    """(H, W, 3 or 4) float32 in [0, 1] (``image_pixels``) as stored (None where not ``pixels``: ``_check_image``
    at ``factor``), its size (W, H), its path and its EXIF orientation (``display_up``); a DatasetError naming the
    file and frame for an image that is missing, damaged, or of a scale it does not record."""
    path = find_image(root, file_path)
    if path is None:
        candidates = image_candidates(root, file_path)
        raise where(image_not_found(root, file_path), frame, candidates[0])
    try:
        with Image.open(path) as im:
            size = im.size  # (as stored: a JPEG's draft reduces it)
            arr = image_pixels(im) if pixels else _check_image(im, factor)
            return arr, size, path, _exif_orientation(im)
    except PixelScaleError as e:
        raise where(f"image {path.name} {e}", frame, path) from None
    except Image.DecompressionBombError as e:
        raise where(f"image {path.name} refused as a decompression bomb: {e}", frame, path) from e
    except (MemoryError, DatasetError):
        raise
    except Exception as e:  # Pillow's plugins raise many kinds on damaged headers (NotImplementedError for DDS's)
        raise where(f"cannot read image {path.name} (not an image or damaged): {e}", frame, path) from e


def _check_stated_size(intrinsics: dict, w: int, h: int, image_path: Path, where: _Where, frame: int) -> None:
    """The frame's ``w`` and ``h``, where given, must be its image's size (as stored)."""
    stated_w, stated_h = intrinsics.get("w", w), intrinsics.get("h", h)
    for key, stated, actual in (("w", stated_w, w), ("h", stated_h, h)):
        if round(stated) != actual:
            raise where(f"image is {w}x{h} but the intrinsics say {key}={stated:g}"
                        f"{quarter_turn_hint(image_path, w, h, stated_w, stated_h)}", frame)


def _exif_orientation(image: Image.Image) -> int | None:
    """The image's EXIF orientation tag (None: none). A damaged EXIF block reads as none, as viewers then show the
    image as stored: its pixels are read all the same."""
    try:
        return image.getexif().get(_EXIF_ORIENTATION)
    except Exception:  # noqa: BLE001 - Pillow's EXIF parser raises many kinds on damaged blocks
        return None


def display_up(orientations: list[int | None]) -> torch.Tensor | None:
    """``Cameras.display_up`` of images with these EXIF orientations: each displayed image's up in camera axes
    (a portrait photo stored landscape, orientation 6, is shown with its stored left side up: -x). None where every
    image is shown upright as stored."""
    ups = [_DISPLAY_UP.get(orientation, _STORED_UP) for orientation in orientations]
    return None if all(up == _STORED_UP for up in ups) else torch.tensor(ups)


def quarter_turn_hint(path: Path, w: int, h: int, expected_w: float, expected_h: float) -> str:
    """For a refusal of an image stored ``w`` x ``h`` where ``expected_w`` x ``expected_h`` was wanted: what explains
    it when that is the size its EXIF orientation displays it at (a quarter turn, as a phone tags a portrait photo
    stored landscape); else nothing. Viewers show such an image turned, but the pixels are read as stored, as COLMAP
    and instant-ngp read them (and pose them). The loader's refusals and the upload check's."""
    if (round(expected_w), round(expected_h)) != (h, w):
        return ""
    try:
        with Image.open(path) as image:
            orientation = _exif_orientation(image)
    except Exception:  # noqa: BLE001 - a hint only: the image itself was read
        return ""
    if orientation not in _QUARTER_TURN_ORIENTATIONS:
        return ""
    return (f" (its EXIF orientation {orientation} displays it turned a quarter, {h}x{w}, but images are read as "
            f"stored, as COLMAP and instant-ngp read them: save it upright without the tag, or give the size, "
            f"intrinsics and pose of the stored pixels)")


def _composite_downsampled(arr: np.ndarray, factor: int, resample: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Downsample premultiplied RGBA, then composite on white.

    Filtering premultiplied colour keeps transparent pixels' (arbitrary) colour out of
    the edges; it equals compositing first and filtering after, without 8-bit rounding.
    ``arr`` is premultiplied in place: the image at full size, whose copies had tripled the upload check's memory.
    """
    h, w = arr.shape[0] // factor, arr.shape[1] // factor
    if arr.shape[2] == 4:
        arr[..., :3] *= arr[..., 3:]
    if factor > 1:
        arr = arr[: h * factor, : w * factor]
        if resample == "box":
            arr = arr.reshape(h, factor, w, factor, -1).mean(axis=(1, 3), dtype=np.float32)
        else:
            planes = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)[None]
            planes = F.interpolate(planes, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
            # Its weights are computed in float32: a constant 1 can come back an ulp above 1.
            arr = np.clip(planes[0].permute(1, 2, 0).numpy(), 0.0, 1.0)
    if arr.shape[2] == 3:
        return np.ascontiguousarray(arr), None
    alpha = arr[..., 3]
    rgb = np.clip(arr[..., :3] + (1.0 - alpha[..., None]), 0.0, 1.0)
    return np.ascontiguousarray(rgb), np.ascontiguousarray(alpha)


def _check_principal_points(cx: np.ndarray, cy: np.ndarray, W: int, H: int, keep: list[int], where: _Where) -> None:
    """A principal point outside the image is a crop's (or intrinsics in another image's pixels): warned once. One
    more than ``MAX_IMAGE_SIDE`` pixels outside is no crop's of an image the readers take (and from about 1e7
    pixels out, neighbouring pixels' float32 rays coincide): refused."""
    outside = np.maximum.reduce([-cx, cx - W, -cy, cy - H, np.zeros_like(cx)])
    slots = np.flatnonzero(outside > 0)
    if not slots.size:
        return
    slot = int(slots[np.argmax(outside[slots])])
    message = (f"principal point ({cx[slot]:g}, {cy[slot]:g}) lies {outside[slot]:g} pixels outside the {W}x{H} "
               f"image")
    if outside[slot] > MAX_IMAGE_SIDE:
        raise where(f"{message}, more than the largest image side read ({MAX_IMAGE_SIDE}): no camera's (check "
                    f"that cx and cy are in pixels of this image)", keep[slot])
    warnings.warn(f"{where(message, keep[slot])} ({slots.size} of {len(keep)} frames' lie outside it): a cropped "
                  f"image's, else check that cx and cy are in pixels of this image", stacklevel=3)


def _focal_from_angle(pixels: int, angle: float) -> float:
    """The focal length in pixels of a field of view of ``angle`` radians across ``pixels``: inf for an angle
    whose tangent vanishes (5e-324 had been a ZeroDivisionError), which the caller refuses as non-finite."""
    half_width = math.tan(0.5 * angle)
    return 0.5 * pixels / half_width if half_width > 0 else math.inf


def _axis_focal(v: dict, keys: tuple[str, str, str], pixels: int) -> float | None:
    """One axis's focal in pixels from the first of its ``_FOCAL_KEYS`` given (None: none is)."""
    degrees, focal, angle = keys
    if degrees in v:
        return _focal_from_angle(pixels, math.radians(v[degrees]))
    if focal in v:
        return v[focal]
    return _focal_from_angle(pixels, v[angle]) if angle in v else None


def _resolve_intrinsics(v: dict, W: int, H: int, where: _Where, frame: int) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy in pixels of the full-size image from ``_merge_intrinsics``'s ``v``: each axis's focal from
    its first ``_FOCAL_KEYS`` given (x_fov over fl_x over camera_angle_x, as instant-ngp reads them), and an axis
    given none takes the other's focal (fy is fx, or fx is fy where only the y axis has one, as instant-ngp reads
    it: such a file had been refused as lacking intrinsics). ``w`` and ``h``: ``_check_stated_size``."""
    fx, fy = (_axis_focal(v, keys, pixels) for keys, pixels in zip(_FOCAL_KEYS, (W, H)))
    fx, fy = (fy if fx is None else fx), (fx if fy is None else fy)
    for name, f in (("fx", fx), ("fy", fy)):
        if not math.isfinite(f) or f < _MIN_FOCAL:
            raise where(f"focal length {name} = {f:.3g} pixels is non-finite or near-singular", frame)
        if f > _FLOAT32_MAX:  # e.g. a camera_angle_x of 1e-300 radians
            raise where(f"focal length {name} = {f:.3g} pixels is beyond float32's range", frame)
    return fx, fy, v.get("cx", W / 2), v.get("cy", H / 2)
