"""The stored scene archive: one zip per scene, the dataset folder at its root.

The API packs what it accepted (``scenes/<id>/dataset.zip`` for images; ``scenes/<id>/upload.zip``
holding only ``mesh/`` for a mesh); the worker's ingest decodes it, renders a mesh into a
NeRF-synthetic dataset beside ``mesh/`` and packs that as the mesh scene's archive, under a key of
the run's own (``scenes/<id>/dataset-<run>.zip``; ``dataset.zip`` for scenes made ready before).
Jobs read ``Scene.storage_key``, always the dataset archive once the scene is ready.
"""

from __future__ import annotations

import zipfile
from pathlib import Path, PurePosixPath

from voxe_core.presets import MESH_VIEW_SIZE, MESH_VIEWS  # noqa: F401 - what an ingest renders a mesh into

IGNORED = ("__MACOSX", ".DS_Store", "Thumbs.db")
STORED_SUFFIXES = {".png", ".jpg", ".jpeg", ".webp", ".exr", ".zip", ".gz"}  # already compressed
DATASET_ARCHIVE = "dataset.zip"
UPLOAD_ARCHIVE = "upload.zip"  # a mesh upload before its ingest rendered it
MESH_FORMAT = "mesh"  # a scene's format when it was uploaded as a mesh (its archive: the renders + MESH_FOLDER)
MESH_FOLDER = "mesh"  # the uploaded mesh as ``mesh.obj`` / ``mesh.ply``, its texture and an OBJ's .mtl beside it
MESH_NAMES = "names.json"  # in MESH_FOLDER: {kept name: the name it was uploaded under}
# in MESH_FOLDER: {"shading": "auto" | "baked" | "none", "up_axis": "x" | "y" | "z", "frame": voxe_core.mesh_input.MESH_FRAMES}
MESH_OPTIONS = "options.json"
UNPACKED_MARK = ".complete"
"""The file a scene's dataset folder is renamed into place with once a worker unpacked it whole, and that each stage
reading it locks shared (``worker.runtime.scene_dataset``): an upload's dataset folder may hold a file of that name
(written over), not a folder."""


def ignored(path: PurePosixPath) -> bool:
    """Desktop debris (macOS resource forks, thumbnails) that is neither checked nor stored."""
    return any(part in IGNORED or part.startswith("._") for part in path.parts)


def package(root: Path, archive: Path) -> None:
    """Pack the dataset folder (images stored, text deflated) with the folder at the archive root."""
    with zipfile.ZipFile(archive, "w") as zf:
        for path in sorted(root.rglob("*")):
            if path.is_file() and not ignored(PurePosixPath(path.name)):
                compress = zipfile.ZIP_STORED if path.suffix.lower() in STORED_SUFFIXES else zipfile.ZIP_DEFLATED
                zf.write(path, path.relative_to(root).as_posix(), compress_type=compress)


def unpacked_bytes(archive: Path) -> int:
    """What the stored archive's files take unpacked, as its entries declare it (the service's own archive)."""
    with zipfile.ZipFile(archive) as zf:
        return sum(info.file_size for info in zf.infolist())


def unpack(archive: Path, dest: Path) -> Path:
    """Unpack a stored archive (the service's own, checked when it was packed) into ``dest``."""
    with zipfile.ZipFile(archive) as zf:
        zf.extractall(dest)
    return dest
