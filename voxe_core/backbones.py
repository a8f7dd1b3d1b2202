"""The grid backbones by name: a registry, the one loader of saved grids, and the choice of a backbone for a capture.

* ``relu_field`` (:class:`~voxe_core.grid.VoxelGrid`): objects on a transparent background (SPEC §1);
* ``scene`` (:class:`~voxe_core.scene_grid.SceneGrid`): captured 360° photos with a background (SPEC §5).

Every saved grid names its backbone in its header (``kind``; files written before
the key existed are ReLU-field grids), so :func:`load_grid` returns the right class
without the grid modules knowing each other.

Examples:
    >>> grid = BACKBONES["scene"](8)
    >>> import tempfile, os
    >>> path = os.path.join(tempfile.mkdtemp(), "g.safetensors")
    >>> grid.save(path)
    >>> type(load_grid(path)).__name__
    'SceneGrid'
"""

from __future__ import annotations

import torch

from voxe_core.cameras import Cameras
from voxe_core.constants import FLOAT32_MAX
from voxe_core.grid import DEFAULT_BOX, GRID_KIND, VoxelGrid, ray_box_intersection
from voxe_core.gridfile import GRID_FORMAT_VERSION, dense_tensors, float_dtype_problem
from voxe_core.scene_grid import SceneGrid, apply_frame, scene_frame
from voxe_core.tensorio import FormatError, load_header, load_tensors

BACKBONES: dict[str, type[VoxelGrid]] = {cls.kind: cls for cls in (VoxelGrid, SceneGrid)}
BACKBONE_CHOICES = ("auto", *BACKBONES)  # what a user may ask for: presets.BACKBONE_CHOICES (which cannot import this)
OPAQUE_ALPHA = 0.5  # a pixel with alpha below this is transparent background
TRANSPARENT_FRACTION = 0.01  # images with at least this share of transparent pixels are objects on a background
AIMED_AT_BOX_FRACTION = 0.5  # a ReLU-field fit needs at least this share of the optical axes through its box
_COINCIDENT = 1e-6  # cameras this close (relative to their distance from the origin, or 1) are at one position


def find_backbone(name: str) -> type[VoxelGrid]:
    """The grid class registered as ``name`` (ValueError naming the known ones otherwise)."""
    try:
        return BACKBONES[name]
    except (KeyError, TypeError):  # TypeError: a damaged header's list or object, unhashable
        raise ValueError(f"unknown backbone {name!r}; use {' or '.join(map(repr, BACKBONES))}") from None


def grid_from_state(tensors: dict[str, torch.Tensor], meta: dict) -> VoxelGrid:
    """A grid of the backbone its header names, from saved tensors (grid files and checkpoints alike)."""
    kind = meta.get("backbone", VoxelGrid.kind)
    try:
        cls = find_backbone(kind)
    except ValueError as exc:
        raise FormatError(f"the grid's header names {exc}") from None
    try:
        tensors = dense_tensors(tensors, meta)
    except KeyError as exc:  # a tensor or field the layout needs: the bare key alone had been the message
        raise FormatError(f"damaged sparse grid: no {exc} in the file") from None
    except ValueError as exc:
        raise FormatError(f"damaged sparse grid: {exc}") from None
    for name in ("features", "bbox_min", "bbox_max"):  # bool, integer or float8 ones had been read as floats
        if name in tensors and (problem := float_dtype_problem(tensors[name])):
            raise FormatError(f"damaged grid: {name} is {problem}")
    features = tensors.get("features")
    if features is not None and (features.dim() != 4 or features.shape[-1] != 4):
        raise FormatError(f"damaged grid: features of shape {tuple(features.shape)}, not (X, Y, Z, 4)")
    resolution = meta.get("resolution")  # (a dense file's had gone unread: a grid of another size had loaded; a
    if features is not None and "resolution" in meta and resolution != list(features.shape[:3]):  # null, unchecked)
        raise FormatError(f"damaged grid: its header's resolution {resolution!r} is not its features' "
                          f"{list(features.shape[:3])}")
    for name in ("bbox_min", "bbox_max"):
        if name in tensors and tuple(tensors[name].shape) != (3,):
            raise FormatError(f"damaged grid: {name} of shape {tuple(tensors[name].shape)}, not (3,)")
    scale = meta.get("density_scale")  # compared, not converted: a whole number past float64's range (10**400)
    if "density_scale" in meta and not (isinstance(scale, (int, float)) and not isinstance(scale, bool)  # true: 1
                                  and 0 < scale <= FLOAT32_MAX):  # had escaped as "int too large to convert to float"
        raise FormatError(f"damaged grid: density_scale {scale!r} is not a positive number finite in float32 (every "
                          "density would be wrong)")
    try:
        return cls.from_state(tensors, meta)
    except FormatError:  # what the class names itself
        raise
    except KeyError as exc:  # a header without its tensors (or fields): a bare KeyError had reached the CLI
        raise FormatError(f"damaged grid: no {exc} in the file") from None
    except (TypeError, ValueError, RuntimeError) as exc:  # a header field of the wrong type or value
        raise FormatError(f"damaged grid: {exc}") from None


def load_grid(path) -> VoxelGrid:
    """The grid saved at ``path`` by ``VoxelGrid.save``, of whichever backbone and layout (dense or sparse) wrote it.

    Raises ``FormatError`` (naming the file) for a missing, unreadable or newer-format file.
    """
    tensors, meta = load_tensors(path, kind=GRID_KIND, max_version=GRID_FORMAT_VERSION)
    try:
        return grid_from_state(tensors, meta)
    except FormatError as exc:
        raise FormatError(f"{path}: {exc}") from None


GRID_NOTES = ("smoke_test",)
"""The header entries ``VoxelGrid.save``'s ``notes`` write on what made a grid (``voxe edit``'s ``smoke_test``)."""


def grid_notes(path) -> dict:
    """The notes (:data:`GRID_NOTES`) the grid file at ``path`` carries, read from its header: :func:`load_grid` passes
    over them, so a command writing a grid or a manifest from a grid had dropped them."""
    meta = load_header(path, kind=GRID_KIND, max_version=GRID_FORMAT_VERSION)
    return {key: meta[key] for key in GRID_NOTES if key in meta}


def detect_backbone(alphas: torch.Tensor | None) -> str:
    """'relu_field' for objects on a transparent background, 'scene' for opaque photos.

    ``alphas`` is ``Scene.alphas`` (None when the images carry no alpha). An
    alpha channel that is opaque nearly everywhere is a photo saved as RGBA.
    """
    if alphas is None or alphas.numel() == 0:
        return SceneGrid.kind
    transparent = float((alphas < OPAQUE_ALPHA).float().mean())
    return VoxelGrid.kind if transparent >= TRANSPARENT_FRACTION else SceneGrid.kind


def resolve_backbone(backbone: str, alphas: torch.Tensor | None) -> str:
    """The backbone kind ``backbone`` ('auto' | 'relu_field' | 'scene') means for images with ``alphas``
    (what picks the fit's default preset, ``voxe_core.presets.reconstruct_config``)."""
    if backbone not in BACKBONE_CHOICES:
        raise ValueError(f"unknown backbone {backbone!r}; use {', '.join(map(repr, BACKBONE_CHOICES[:-1]))} "
                         f"or {BACKBONE_CHOICES[-1]!r}")
    return detect_backbone(alphas) if backbone == "auto" else backbone


def prepare_backbone(backbone: str, alphas: torch.Tensor | None, cameras: Cameras, resolution: int,
                     split_c2w: torch.Tensor | None = None):
    """Resolve ``backbone`` ('auto' | 'relu_field' | 'scene') for a loaded scene.

    Returns (name, cameras to fit with, initial grid for ``reconstruct`` or None):
    a scene grid is fitted in the canonical frame of ``scene_frame``, which it records; a ReLU field in the
    capture's own frame, which must hold the object in its box (``_check_cameras_see_box``).
    ``split_c2w``: the split's every camera-to-world when ``cameras`` are the first ``max_images`` of it
    (``Scene.split_c2w``); a refusal the whole split would pass names ``max_images``, not the capture.
    """
    name = resolve_backbone(backbone, alphas)
    try:
        frame = _capture_frame(name, cameras)
    except ValueError as exc:
        if split_c2w is None:
            raise
        try:
            _capture_frame(name, Cameras.from_fov(split_c2w, 1.0, 1, 1))  # (the checks read the poses alone)
        except ValueError:
            raise exc from None
        raise ValueError(f"max_images keeps the first {len(cameras)} of the split's {len(split_c2w)} frames, too few "
                         f"to fit from where the whole split would do: raise it, or leave it out (of those "
                         f"{len(cameras)}: {exc})") from None
    if frame is None:
        return name, cameras, None
    return name, apply_frame(cameras, frame), SceneGrid(resolution, frame=frame)


def _capture_frame(name: str, cameras: Cameras) -> torch.Tensor | None:
    """The scene frame a ``name`` backbone fits ``cameras`` in (None: a ReLU field's, the capture's own); ValueError
    for cameras it cannot fit from."""
    _check_cameras_apart(cameras)
    if name != SceneGrid.kind:
        _check_cameras_see_box(cameras)
        return None
    return scene_frame(cameras)


def _check_cameras_apart(cameras: Cameras) -> None:
    """ValueError when two or more cameras all sit at one position (to float32's rounding of it): their views hold
    no parallax, so no fit can place anything in depth. A ReLU field had fitted such a capture (its cameras inside
    the box pass ``_check_cameras_see_box``) and the scene frame named it cameras "on the point they look at"."""
    if len(cameras) < 2:
        return
    positions = cameras.c2w[:, :3, 3].double()
    spread = float((positions - positions.mean(0)).norm(dim=-1).max())
    if spread <= _COINCIDENT * max(1.0, float(positions.norm(dim=-1).max())):
        x, y, z = positions[0].tolist()
        raise ValueError(f"all {len(cameras)} cameras sit at one position ({x:.4g}, {y:.4g}, {z:.4g}): views from one "
                         "point hold no parallax, so no fit can place anything in depth (have the poses lost their "
                         "translations?)")


def _check_cameras_see_box(cameras: Cameras) -> None:
    """ValueError unless the optical axes of at least ``AIMED_AT_BOX_FRACTION`` of ``cameras`` pass through the
    ReLU field's box (``DEFAULT_BOX``, in world units).

    NeRF-synthetic captures aim every camera at the origin; a COLMAP or instant-ngp model's world frame is
    wherever its reconstruction put it, and a ReLU field there would fit empty space.
    """
    box_min, box_max = (torch.tensor(corner).to(cameras.c2w) for corner in DEFAULT_BOX)
    near, far = ray_box_intersection(cameras.c2w[:, :3, 3], -cameras.c2w[:, :3, 2], box_min, box_max)
    aimed = int((far > near).sum())
    if aimed < AIMED_AT_BOX_FRACTION * len(cameras):
        raise ValueError(
            f"the optical axes of only {aimed} of {len(cameras)} cameras pass through the relu_field backbone's box "
            f"{list(DEFAULT_BOX[0])} to {list(DEFAULT_BOX[1])}: the capture's frame does not hold the object in "
            "that box; use the scene backbone (backbone 'scene'), which frames the capture by its cameras"
        )
