"""Small captures made in code for the tests: image folders and COLMAP models written with pycolmap, a 16-bit RGB
PNG, and a file Pillow cannot read."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
from PIL import Image


DDS_OF_UNKNOWN_PIXEL_FORMAT = (b"DDS " + struct.pack("<7I", 124, 0x1007, 16, 16, 0, 0, 0) + bytes(44)
                               + struct.pack("<8I", 32, *[0] * 7) + bytes(20))
"""A DDS header Pillow opens and then refuses with NotImplementedError (not among its usual OSError / ValueError)."""


def write_colmap_model(model_dir: Path, cameras: list[tuple[str, int, int, list[float]]],
                       images: list[tuple[str, int, np.ndarray]], binary: bool = True) -> Path:
    """``cameras``: (COLMAP model name, width, height, params); ``images``: (name, camera index, 4x4 OpenGL c2w)."""
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    for camera_id, (model, width, height, params) in enumerate(cameras, start=1):
        camera = pycolmap.Camera.create_from_model_name(camera_id, model, 1.0, width, height)
        camera.params = params
        reconstruction.add_camera_with_trivial_rig(camera)
    for image_id, (name, camera_index, c2w) in enumerate(images, start=1):
        w2c = np.linalg.inv(c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenGL axes -> OpenCV's, then invert
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        image = pycolmap.Image(name=name, camera_id=camera_index + 1, image_id=image_id)
        reconstruction.add_image_with_trivial_frame(image, pose)
    model_dir.mkdir(parents=True, exist_ok=True)
    (reconstruction.write_binary if binary else reconstruction.write_text)(str(model_dir))
    return model_dir


def square_capture(tmp_path: Path, n: int = 3, size=(16, 12)) -> Path:
    root = tmp_path / "cap"
    (root / "images").mkdir(parents=True)
    for i in range(n):
        Image.new("RGB", size, (30 * i, 50, 70)).save(root / "images" / f"{i}.png")
    return root


def pose_at(x: float) -> np.ndarray:
    c2w = np.eye(4)
    c2w[:3, 3] = (x, 0.0, 4.0)
    return c2w




def sixteen_bit_rgb_png(path: Path, samples: np.ndarray, colour_key: tuple[int, int, int]) -> None:
    """An (H, W, 3) uint16 image as a 16-bit RGB PNG with a tRNS colour key: Pillow writes RGB at 8 bits only."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    height, width = samples.shape[:2]
    rows = b"".join(b"\0" + row.astype(">u2").tobytes() for row in samples)  # filter type 0 (none) per row
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, 2, 0, 0, 0))
                     + chunk(b"tRNS", struct.pack(">3H", *colour_key)) + chunk(b"IDAT", zlib.compress(rows))
                     + chunk(b"IEND", b""))
