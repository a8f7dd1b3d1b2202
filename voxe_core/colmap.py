"""A strict reader for COLMAP sparse models' cameras and images (``.bin`` or ``.txt``).

Why not pycolmap's reader: uploads are untrusted, and pycolmap 4.2.1 hangs with its memory
growing on some damaged files (of 48 randomly truncated, bit-flipped or count-inflated copies
of a model it wrote, 7 never returned: a truncated ``images.bin`` or a damaged
``points3D.bin``) and read 7 truncated ``cameras.bin`` without complaint. pycolmap stays the
tests' writer: ``tests/test_real_inputs.py`` reads what it writes, binary and text.
This reader needs only the cameras and the image poses (``points3D`` is not read),
bounds every count by the bytes left, and names the file and the byte offset or line
of what it cannot read. COLMAP 4's ``rigs`` and ``frames`` files are not needed: its
``images`` file still holds each image's pose.
"""

from __future__ import annotations

import math
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# COLMAP's camera models: id -> (name, number of parameters)
CAMERA_MODEL_IDS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_PARAM_COUNTS = {name: count for name, count in CAMERA_MODEL_IDS.values()}
_MAX_NAME_BYTES = 4096
MAX_IMAGE_SIDE = 65536  # pixels: a camera beyond it is a damaged file (and overflows float conversions)
_DECIMAL, _INTEGER = r"-?[0-9]+(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?", r"-?[0-9]+"
_POINT2D = rf"{_DECIMAL}[ \t]+{_DECIMAL}[ \t]+{_INTEGER}"
# A POINTS2D[] line as COLMAP writes it: every line it matches passes the value-by-value check, in one C-level pass.
_PLAIN_POINTS2D = re.compile(rf"[ \t]*(?:{_POINT2D}(?:[ \t]+{_POINT2D})*)?[ \t]*")


class ColmapError(ValueError):
    """A COLMAP file that cannot be read; the message names the file and where in it."""

    def __init__(self, message: str, path: Path):
        super().__init__(f"{path.name}: {message}")
        self.path = path


@dataclass
class ColmapCamera:
    model: str
    width: int
    height: int
    params: list[float]


@dataclass
class ColmapImage:
    name: str
    camera_id: int
    cam_from_world: np.ndarray  # (4, 4) float64: world -> camera in OpenCV axes (x right, y down, z forward)


def read_model(model_dir: str | os.PathLike,
               max_images: int | None = None) -> tuple[dict[int, ColmapCamera], list[ColmapImage]]:
    """Cameras by id and images of ``model_dir`` (``cameras.bin`` + ``images.bin``, else the ``.txt`` pair).

    ``max_images`` (an upload's check: the files its dataset folder holds) refuses an images file listing more images
    before any is read: an upload's 300,000 (a 25 MB images.bin, 1.3 MB deflated) had been read and made frames for
    37 s. So it does a cameras file listing more cameras (each is one image's, or shared by several): 1,000,000 in a
    56 MB cameras.bin had been parsed in 8.7 s and 450 MB."""
    model_dir = Path(model_dir)
    ext = "bin" if (model_dir / "cameras.bin").is_file() else "txt"
    cameras_path, images_path = model_dir / f"cameras.{ext}", model_dir / f"images.{ext}"
    for path in (cameras_path, images_path):
        if not path.is_file():
            raise ColmapError(f"not found in {model_dir} (a COLMAP sparse model needs cameras.{ext} and "
                              f"images.{ext})", path)
    if ext == "bin":
        return _read_cameras_bin(cameras_path, max_images), _read_images_bin(images_path, max_images)
    return _read_cameras_txt(cameras_path, max_images), _read_images_txt(images_path, max_images)


def _check_image_count(count: int, max_images: int | None, path: Path) -> None:
    if max_images is not None and count > max_images:
        raise ColmapError(f"lists {count:,} images, more than the {max_images:,} files in the dataset folder: each "
                          "image needs a file of its own", path)


def _check_camera_count(count: int, max_images: int | None, path: Path) -> None:
    if max_images is not None and count > max_images:
        raise ColmapError(f"lists {count:,} cameras, more than the {max_images:,} files in the dataset folder: each "
                          "camera is one image's or shared by several, so there are never more cameras than images",
                          path)


class _Bytes:
    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, fmt: str, what: str):
        size = struct.calcsize(fmt)
        if self.at + size > len(self.data):
            raise ColmapError(f"truncated at byte {self.at} (reading {what})", self.path)
        values = struct.unpack_from(fmt, self.data, self.at)
        self.at += size
        return values

    def count(self, item_bytes: int, what: str) -> int:
        (n,) = self.take("<Q", f"the number of {what}")
        if n * item_bytes > len(self.data) - self.at:
            raise ColmapError(f"claims {n} {what} at byte {self.at - 8}, more than the file's "
                              f"{len(self.data) - self.at} remaining bytes can hold", self.path)
        return n

    def name(self) -> str:
        end = self.data.find(b"\0", self.at, self.at + _MAX_NAME_BYTES)
        if end < 0:
            raise ColmapError(f"image name at byte {self.at} is not NUL-terminated within {_MAX_NAME_BYTES} bytes",
                              self.path)
        raw, self.at = self.data[self.at:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ColmapError(f"image name at byte {self.at - len(raw) - 1} is not UTF-8", self.path) from None


def _camera(model: str, width: int, height: int, params: list[float], where: str, path: Path) -> ColmapCamera:
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise ColmapError(f"{where}: image size {width}x{height} must lie within 1x1 and "
                          f"{MAX_IMAGE_SIDE}x{MAX_IMAGE_SIDE}", path)
    if not all(math.isfinite(p) for p in params):
        raise ColmapError(f"{where}: parameters {params} are not all finite", path)
    return ColmapCamera(model, width, height, params)


def _pose(values: tuple, where: str, path: Path) -> np.ndarray:
    qw, qx, qy, qz, tx, ty, tz = values
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (np.isfinite(q).all() and math.isfinite(tx) and math.isfinite(ty) and math.isfinite(tz)):
        raise ColmapError(f"{where}: pose (quaternion {q.tolist()}, translation {[tx, ty, tz]}) is not finite", path)
    if abs(norm - 1.0) > 1e-3:
        raise ColmapError(f"{where}: rotation quaternion {q.tolist()} has norm {norm:.4g}, not 1", path)
    w, x, y, z = q / norm
    matrix = np.eye(4)
    matrix[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    matrix[:3, 3] = (tx, ty, tz)
    return matrix


def _read_cameras_bin(path: Path, max_images: int | None = None) -> dict[int, ColmapCamera]:
    reader, cameras = _Bytes(path), {}
    count = reader.count(24, "cameras")
    _check_camera_count(count, max_images, path)
    for _ in range(count):
        start = reader.at
        camera_id, model_id, width, height = reader.take("<iiQQ", "a camera")
        if model_id not in CAMERA_MODEL_IDS:
            raise ColmapError(f"camera {camera_id} at byte {start}: unknown camera model id {model_id}", path)
        model, n = CAMERA_MODEL_IDS[model_id]
        params = list(reader.take(f"<{n}d", f"camera {camera_id}'s {n} parameters"))
        if camera_id in cameras:
            raise ColmapError(f"camera {camera_id} at byte {start}: duplicate camera id", path)
        cameras[camera_id] = _camera(model, width, height, params, f"camera {camera_id}", path)
    _check_consumed(reader)
    return cameras


def _read_images_bin(path: Path, max_images: int | None = None) -> list[ColmapImage]:
    reader, images, seen = _Bytes(path), [], {}
    count = reader.count(64, "images")
    _check_image_count(count, max_images, path)
    for _ in range(count):
        start = reader.at
        (image_id,) = reader.take("<i", "an image id")
        pose = reader.take("<7d", f"image {image_id}'s pose")
        (camera_id,) = reader.take("<i", f"image {image_id}'s camera id")
        name = reader.name()
        if image_id in seen:
            raise ColmapError(f"image {image_id} ({name!r}) at byte {start}: duplicate image id "
                              f"({seen[image_id]!r} has it too)", path)
        seen[image_id] = name
        points = reader.count(24, f"2-D points of image {image_id}")
        reader.at += 24 * points  # (x, y, point3D id) each: not needed
        images.append(ColmapImage(name, camera_id, _pose(pose, f"image {image_id} ({name!r}) at byte {start}", path)))
    _check_consumed(reader)
    return images


def _check_consumed(reader: _Bytes) -> None:
    if reader.at != len(reader.data):
        raise ColmapError(f"{len(reader.data) - reader.at} unexpected bytes after the last entry (byte {reader.at})",
                          reader.path)


def _text_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the non-comment lines; blank lines kept (images.txt's empty point lists). As COLMAP
    reads them: a comment may be indented, and a byte order mark is refused (COLMAP would read it as the first
    field)."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ColmapError(f"not UTF-8 text: {e}", path) from None
    if text.startswith("\ufeff"):
        raise ColmapError("starts with a UTF-8 byte order mark, which COLMAP cannot read either: "
                          "save the file without one", path)
    return [(i, line) for i, line in enumerate(text.splitlines(), start=1) if not line.lstrip().startswith("#")]


def _parse(kind, field: str, what: str, line: int, path: Path):
    try:
        return kind(field)
    except ValueError:
        raise ColmapError(f"line {line}: {what} {field!r} is not {'a number' if kind is float else 'an integer'}",
                          path) from None


def _read_cameras_txt(path: Path, max_images: int | None = None) -> dict[int, ColmapCamera]:
    lines, cameras = [(line, text) for line, text in _text_lines(path) if text.strip()], {}
    _check_camera_count(len(lines), max_images, path)
    for line, text in lines:
        fields = text.split()
        if len(fields) < 4:
            raise ColmapError(f"line {line}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {len(fields)} fields",
                              path)
        camera_id = _parse(int, fields[0], "camera id", line, path)
        model = fields[1]
        if model not in _PARAM_COUNTS:
            raise ColmapError(f"line {line}: unknown camera model {model!r}", path)
        params = [_parse(float, f, "parameter", line, path) for f in fields[4:]]
        if len(params) != _PARAM_COUNTS[model]:
            raise ColmapError(f"line {line}: camera model {model} has {_PARAM_COUNTS[model]} parameters, "
                              f"got {len(params)}", path)
        if camera_id in cameras:
            raise ColmapError(f"line {line}: duplicate camera id {camera_id}", path)
        width, height = (_parse(int, f, "image size", line, path) for f in fields[2:4])
        cameras[camera_id] = _camera(model, width, height, params, f"line {line}", path)
    return cameras


def _read_images_txt(path: Path, max_images: int | None = None) -> list[ColmapImage]:
    lines, images, seen = _text_lines(path), [], {}
    while lines and not lines[-1][1].strip():
        lines.pop()
    _check_image_count((len(lines) + 1) // 2, max_images, path)  # (each image's line, then its points' line)
    for (line, text), (points_line, points) in zip(lines[::2], lines[1::2] + [(0, "")]):
        fields = text.split(maxsplit=9)  # NAME is the rest of the line, its runs of spaces kept
        if len(fields) < 10:
            raise ColmapError(f"line {line}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                              f"got {len(fields)} fields", path)
        _check_points_line(points_line, points, line, path)
        image_id = _parse(int, fields[0], "image id", line, path)
        pose = tuple(_parse(float, f, "pose value", line, path) for f in fields[1:8])
        camera_id = _parse(int, fields[8], "camera id", line, path)
        name = fields[9].rstrip()
        if image_id in seen:
            raise ColmapError(f"line {line}: duplicate image id {image_id} ({name!r}; line {seen[image_id][0]}'s "
                              f"{seen[image_id][1]!r} has it too)", path)
        seen[image_id] = line, name
        images.append(ColmapImage(name, camera_id, _pose(pose, f"line {line}: image {image_id} ({name!r})", path)))
    return images


def _check_points_line(line: int, text: str, image_line: int, path: Path) -> None:
    """The POINTS2D[] line after an image's line: (X, Y, POINT3D_ID) triples, or none. Not kept, but checked: in a
    file without these lines, each image's line would be taken for the previous image's points. Value by value
    (naming the first bad one) only where the line is not plainly COLMAP's: parsing every value had cost more
    than the rest of the read together."""
    if _PLAIN_POINTS2D.fullmatch(text):
        return
    fields = text.split()
    if len(fields) % 3:
        raise ColmapError(f"line {line}: expected the POINTS2D[] of the image on line {image_line} as X Y POINT3D_ID "
                          f"triples (or an empty line), got {len(fields)} fields", path)
    for x, y, point3d_id in zip(fields[::3], fields[1::3], fields[2::3]):
        _parse(float, x, "POINTS2D X", line, path)
        _parse(float, y, "POINTS2D Y", line, path)
        _parse(int, point3d_id, "POINT3D_ID", line, path)
