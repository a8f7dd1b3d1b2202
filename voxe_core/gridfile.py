"""Grid files hold only what a scene needs: the vertices of its occupied cells, dilated by a margin.

A grid is 0.7–5 % occupied, yet its dense file is 16 bytes per vertex everywhere
(33.5 MB at 128³). The ``sparse`` layout keeps the vertices of every occupied
cell and of the cells within ``margin`` of one, bit-packed as a mask in C order,
and one ``fill`` value for all the others (their mean). Cells the renderer
renders read only stored vertices, so a loaded grid has the same occupancy
and renders identically; every stored vertex round-trips bit for bit. A
softplus grid's occupied cells are those above the default ``sigma_threshold``
(its density is positive everywhere), so this holds where empty space is
skipped at that threshold or above; a render without skipping sees the faint
density of the cells left out replaced by ``fill``'s.

``fill`` is each file's own. A grid computed from loaded grids and saved (a refinement's merge of the initial and
edited files) leaves out its own vertices and fills them with their mean, so merging the downloaded files again
gives every vertex that file stores exactly, but at those it leaves out the sources' values (their fills; where
the edit thinned the shape, vertices the initial file stored): the same occupancy and renders, and saved, the
same bytes.

Format (format version 2 of ``voxel_grid`` files; version 1 files, dense, still load):

* ``layout: "dense"`` — tensor ``features`` (X, Y, Z, 4) float32;
* ``layout: "sparse"`` — ``stored_bits`` (ceil(X·Y·Z / 8),) uint8, the vertex mask as
  ``numpy.packbits`` writes it (C order, big-endian bits); ``values`` (N, 4) float32,
  the stored vertices in C order; ``fill`` (4,) float32, every other vertex;

both with ``bbox_min``/``bbox_max`` (3,) float32 and, in the JSON header, ``resolution``
and ``layout`` (sparse files also ``margin``). Channel 0 is raw density, 1:4 raw colour.

Examples:
    >>> cells = torch.zeros(7, 7, 7, dtype=torch.bool); cells[3, 3, 3] = True
    >>> int(stored_vertices(cells, margin=1).sum())  # the 3³ cells around it have 4³ corners
    64
    >>> features = torch.randn(8, 8, 8, 4)
    >>> tensors, meta = sparse_tensors(features, cells, margin=1)
    >>> dense = dense_tensors(tensors, meta)["features"]
    >>> bool((dense[stored_vertices(cells, 1)] == features[stored_vertices(cells, 1)]).all())
    True
"""

from __future__ import annotations

import math

import numpy as np
import torch

GRID_FORMAT_VERSION = 2  # 1: dense only, no ``layout`` key
LAYOUTS = ("dense", "sparse")
DEFAULT_MARGIN = 2  # cells kept around the occupied ones (room for an edit's first steps to grow the shape)
CHANNELS = 4  # features per vertex: raw density, then raw colour (3)
MIN_FLOAT_BITS = 16
"""The narrowest float a grid's values are read from or saved in: float8's (torch's float8_* types) lose them (no
zero in e8m0, 3 mantissa bits at most), and torch has no index_copy_ or maximum for them."""


def float_dtype_problem(tensor: torch.Tensor) -> str | None:
    """Why ``tensor``'s dtype holds no grid values, in the words after "<name> is"; None when it does."""
    if not tensor.is_floating_point():  # an integer or bool tensor had been read as features
        return f"{tensor.dtype}, not floating point (the format's float32)"
    if torch.finfo(tensor.dtype).bits < MIN_FLOAT_BITS:
        return (f"{tensor.dtype}, a float of {torch.finfo(tensor.dtype).bits} bits (the format's float32; at least "
                f"{MIN_FLOAT_BITS} are read)")
    return None


def dilate(cells: torch.Tensor, margin: int) -> torch.Tensor:
    """``cells`` (X, Y, Z) bool grown by ``margin`` cells along every axis (a cube, applied axis by axis)."""
    grown = cells.clone()
    for axis in range(3):
        step = grown.clone()
        n = grown.shape[axis]
        for shift in range(1, min(margin, n - 1) + 1):
            step.narrow(axis, shift, n - shift).logical_or_(grown.narrow(axis, 0, n - shift))
            step.narrow(axis, 0, n - shift).logical_or_(grown.narrow(axis, shift, n - shift))
        grown = step
    return grown


def stored_vertices(cells: torch.Tensor, margin: int) -> torch.Tensor:
    """The vertices (X+1, Y+1, Z+1) bool that are corners of a cell within ``margin`` of an occupied cell."""
    kept = dilate(cells, margin)
    vertices = kept.new_zeros([n + 1 for n in kept.shape])
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                vertices[dx: dx + kept.shape[0], dy: dy + kept.shape[1], dz: dz + kept.shape[2]] |= kept
    return vertices


def sparse_tensors(features: torch.Tensor, cells: torch.Tensor, margin: int = DEFAULT_MARGIN,
                   unoccupied_density: float = math.inf) -> tuple[dict, dict]:
    """The sparse layout of ``features`` (X, Y, Z, C) keeping the cells ``cells`` (X-1, Y-1, Z-1) plus ``margin``.

    Returns (tensors, header fields: layout, margin, resolution). ``fill`` is the mean of the vertices left
    out: each of those has a density no occupied cell needs, and a mean of values below a threshold stays below it.
    Its density is at most ``unoccupied_density`` (the highest raw density no cell's threshold counts as occupied:
    ``VoxelGrid.save`` passes it), so no cell is occupied on loading under thresholds that differ per cell (a scene
    grid's background: the mean of densities just under the foreground's threshold had occupied background cells
    whose own is lower). The mean is kept within their range (float32's rounding can leave it). A channel whose
    left-out vertices all hold one value (a loaded file's ``fill``) keeps it exactly, so saving a loaded grid again
    writes the same ``fill`` (float32's mean of N copies is not the value: it had drifted by a few ulps at each
    sparse -> dense -> sparse conversion; a float64 sum, exact, took 10x the mean's time). Where the mean is not
    finite (an infinity, or one NaN spreading to every vertex left out) it is taken again over the values that are
    not NaN, infinities counted as float32's extremes.
    """
    if margin < 0:
        raise ValueError(f"margin must be >= 0 cells, got {margin}")
    if features.dim() != 4:  # (each had failed in the mask's indexing, an IndexError naming neither argument)
        raise ValueError(f"features must be shaped (X, Y, Z, C), got {tuple(features.shape)}")
    expected = tuple(n - 1 for n in features.shape[:3])
    if cells.dtype != torch.bool or tuple(cells.shape) != expected:
        raise ValueError(f"cells must be a bool tensor of shape {expected} (one per cell of features "
                         f"{tuple(features.shape)}), got {cells.dtype} of shape {tuple(cells.shape)}")
    features = features.detach().cpu().float()
    mask = stored_vertices(cells.cpu(), margin)
    dropped = features[~mask]
    fill = features.new_zeros(features.shape[-1])
    if dropped.shape[0]:  # one value in a channel (lowest == highest): that value, not float32's mean of it
        lowest, highest = torch.aminmax(dropped, dim=0)
        fill = torch.where(lowest == highest, lowest, dropped.mean(0).clamp(lowest, highest))
    if not bool(torch.isfinite(fill).all()):  # an infinity, or a NaN among them: the careful mean, only then
        extreme = torch.finfo(torch.float32).max
        dropped.clamp_(-extreme, extreme)  # a copy (mask indexing), clamped in place; NaN stays NaN
        fill = (torch.nansum(dropped, 0, dtype=torch.float64) / (~dropped.isnan()).sum(0).clamp_min(1)).float()
    fill[0] = fill[0].clamp(max=unoccupied_density)
    bits = torch.from_numpy(np.packbits(mask.numpy().reshape(-1)))
    layout = {"layout": "sparse", "margin": int(margin), "resolution": list(features.shape[:3])}
    return {"stored_bits": bits, "values": features[mask], "fill": fill}, layout


def payload_bytes(tensors: dict[str, torch.Tensor]) -> int:
    """Bytes the tensors take in a file (what the sparse and dense layouts are compared by)."""
    return sum(t.numel() * t.element_size() for t in tensors.values())


def dense_tensors(tensors: dict[str, torch.Tensor], meta: dict) -> dict[str, torch.Tensor]:
    """``tensors`` of a grid file with ``features`` (X, Y, Z, C) dense, whichever layout wrote them."""
    layout = meta.get("layout", "dense")
    if layout == "dense":
        return tensors
    if layout != "sparse":
        raise ValueError(f"unknown grid layout {layout!r}; this voxe_core reads {' and '.join(LAYOUTS)}")
    resolution = meta["resolution"]
    if not (isinstance(resolution, (list, tuple)) and len(resolution) == 3
            and all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in resolution)):
        raise ValueError(f"resolution {resolution!r} is not 3 positive vertex counts")
    count = math.prod(resolution)  # Python's integers: numpy's int64 product would wrap
    bits, values, fill = tensors["stored_bits"], tensors["values"], tensors["fill"]
    if bits.dtype != torch.uint8 or bits.dim() != 1:
        raise ValueError(f"stored_bits is {bits.dtype} of shape {tuple(bits.shape)}, not a uint8 vector")
    for name, tensor in (("values", values), ("fill", fill)):
        if problem := float_dtype_problem(tensor):
            raise ValueError(f"{name} is {problem}")
    # The channels checked before anything is expanded: a fill of a million (and values to match) had been repeated
    # at every vertex, gigabytes, before the dense features' shape was found wrong.
    if fill.dim() != 1 or values.dim() != 2 or values.shape[1] != CHANNELS or fill.shape[0] != CHANNELS:
        raise ValueError(f"values {tuple(values.shape)} and fill {tuple(fill.shape)} are not (N, {CHANNELS}) and "
                         f"({CHANNELS},)")
    bits = bits.numpy()
    if bits.size != -(-count // 8):  # exactly the format's ceil(X·Y·Z / 8): a wrong resolution must not fit
        raise ValueError(f"stored_bits holds {bits.size} bytes, not the {-(-count // 8)} of a "
                         f"{'x'.join(map(str, resolution))} grid's mask")
    # Flat indices and one index_copy_: ~4x faster than a boolean-mask assignment at 128³.
    stored = torch.from_numpy(np.flatnonzero(np.unpackbits(bits, count=count)))
    if stored.numel() != values.shape[0]:
        raise ValueError(f"the mask marks {stored.numel()} vertices but {values.shape[0]} values are stored")
    features = fill.to(values.dtype).repeat(count, 1).index_copy_(0, stored, values).view(*resolution, -1)
    rest = {k: v for k, v in tensors.items() if k not in ("stored_bits", "values", "fill")}
    return {**rest, "features": features}
