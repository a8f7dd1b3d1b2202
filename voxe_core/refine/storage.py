"""The refinement's files: sparse edit masks and probability grids (versioned safetensors, no pickle).

:func:`save_mask` keeps only the flat indices (int32) of the set voxels plus the
grid shape; :func:`save_probabilities` keeps the probability grids at the
occupied voxels only (indices + values).
"""

from __future__ import annotations

import math

import torch

from voxe_core.tensorio import FormatError, load_tensors, save_tensors

MASK_FORMAT_VERSION = 1
PROBABILITY_FORMAT_VERSION = 1
INDEXABLE_VOXELS = 2**31
"""The files' int32 voxel indices address grids of fewer voxels than this."""


def _set_voxels(mask: torch.Tensor) -> torch.Tensor:
    """(K,) flat indices (int64, C order) of the set voxels of an (X, Y, Z) mask, whose grid the files' int32
    indices can address (beyond 2^31 voxels they had wrapped negative, and the file was refused as damaged)."""
    if mask.dim() != 3:
        raise ValueError(f"expected an (X, Y, Z) mask, got shape {tuple(mask.shape)}")
    if mask.numel() >= INDEXABLE_VOXELS:
        raise ValueError(f"a grid of {tuple(mask.shape)} voxels ({mask.numel():,}) is too large for the files' int32 "
                         f"voxel indices (fewer than {INDEXABLE_VOXELS:,} voxels)")
    return mask.reshape(-1).nonzero().squeeze(-1)


def check_binary(mask: torch.Tensor, name: str = "the mask") -> None:
    """ValueError unless ``mask`` holds only 0 and 1 (or is bool): a soft mask (the edit probabilities?) cast to bool
    is set wherever it is not 0 (a 0.3, or NaN, had taken G_e, been written set or counted in a footprint);
    ``name``: the argument, in the refusal's words."""
    if mask.dtype != torch.bool and not bool(((mask == 0) | (mask == 1)).all()):
        raise ValueError(f"{name} must be binary (bool, or only 0 and 1): a soft mask (the edit probabilities?) "
                         "would count as set wherever it is not 0")


def _are_probabilities(values: torch.Tensor) -> bool:
    """Whether every value is in [0, 1] (NaN fails both comparisons): the rule :func:`load_probabilities` holds a
    file's values to, and :func:`save_probabilities` the values it would write."""
    return not values.numel() or bool(((values >= 0) & (values <= 1)).all())


def save_mask(path, mask: torch.Tensor, meta: dict | None = None) -> None:
    """Sparse mask file: flat indices (int32, C order) of the set voxels plus the grid shape; ValueError for a mask
    that is not binary (:func:`check_binary`)."""
    check_binary(mask)
    mask = mask.detach().cpu().bool()
    indices = _set_voxels(mask).to(torch.int32)
    save_tensors(path, {"indices": indices, "shape": torch.tensor(mask.shape, dtype=torch.int64)},
                 kind="edit_mask", version=MASK_FORMAT_VERSION, meta={"set_voxels": int(indices.numel()), **(meta or {})})


def _indices_and_shape(tensors: dict, path, expected: tuple[int, ...] | None = None,
                       holding: tuple[str, str] = ("a mask", "a mask is of its initial grid"),
                       ) -> tuple[torch.Tensor, tuple[int, int, int]]:
    """The file's flat voxel indices and grid shape, checked before anything the shape's size is allocated: the
    shape ``expected`` where given (a 252-byte file claiming 1290³ voxels had allocated 2 GB before its caller found
    it did not fit the grid; ``holding``: what the file holds and which grid that is of, in that refusal's words),
    indices of an integer dtype (1.7 had been read as 1, true as 1), each within the grid and given once (two values
    for one voxel are no file these functions write)."""
    if "indices" not in tensors or "shape" not in tensors:
        raise FormatError(f"{path}: missing 'indices' or 'shape'")
    stored_shape, indices = tensors["shape"], tensors["indices"]
    for name, tensor in (("shape", stored_shape), ("indices", indices)):
        if tensor.is_floating_point() or tensor.is_complex() or tensor.dtype == torch.bool:
            raise FormatError(f"{path}: '{name}' is {tensor.dtype}, not integers")
    if stored_shape.shape != (3,) or int(stored_shape.min()) < 1:
        raise FormatError(f"{path}: bad grid shape {stored_shape.tolist()}, not 3 positive voxel counts")
    shape = tuple(int(s) for s in stored_shape.tolist())
    if expected is not None and shape != tuple(expected):
        what, of_which_grid = holding
        raise FormatError(f"{path}: {what} of a grid of {shape} voxels, where {tuple(expected)} was expected "
                          f"({of_which_grid}, whose resolution its edited grid shares)")
    total = shape[0] * shape[1] * shape[2]
    if total >= INDEXABLE_VOXELS:  # (a damaged header: it had reached torch.zeros, an overflow or a huge allocation)
        raise FormatError(f"{path}: a grid of {shape} is beyond the int32 voxel indices these files hold")
    indices = indices.long().reshape(-1)
    if indices.numel() and (int(indices.min()) < 0 or int(indices.max()) >= total):
        raise FormatError(f"{path}: voxel indices outside a grid of {shape}")
    ordered = indices.sort().values
    repeats = ordered[1:][ordered[1:] == ordered[:-1]]
    if repeats.numel():
        raise FormatError(f"{path}: voxel index {int(repeats[0])} is given more than once ({repeats.numel()} "
                          "repeats)")
    return indices, shape


def load_mask(path, shape: tuple[int, ...] | None = None) -> torch.Tensor:
    """The (X, Y, Z) bool mask written by :func:`save_mask`; ``shape``: the grid's, which the file must hold."""
    tensors, _ = load_tensors(path, kind="edit_mask", max_version=MASK_FORMAT_VERSION)
    indices, shape = _indices_and_shape(tensors, path, shape)
    mask = torch.zeros(math.prod(shape), dtype=torch.bool)
    mask[indices] = True
    return mask.reshape(shape)


def save_probabilities(path, edit_probability: torch.Tensor, object_probability: torch.Tensor, where: torch.Tensor) -> None:
    """Probability grids stored only at the voxels ``where`` (the graph's nodes): indices + float32 values.
    ValueError, before anything is written, for a ``where`` that is not a binary (X, Y, Z) mask (:func:`check_binary`:
    a soft one had stored every voxel it was not 0 at), a grid that is not of ``where``'s voxels (a smaller ``where``
    had stored the values of other voxels without a word, a larger one failed on an IndexError) or stored values
    :func:`load_probabilities` refuses (a raw attention field had been written, to be refused as it was read)."""
    if where.dim() != 3:
        raise ValueError(f"'where' must be the (X, Y, Z) mask of the voxels to store, got shape {tuple(where.shape)}")
    check_binary(where, "'where'")
    grids = {"edit": ("edit_probability", edit_probability), "object": ("object_probability", object_probability)}
    for name, values in grids.values():
        if tuple(values.shape[:3]) != tuple(where.shape) or values.numel() != where.numel():
            raise ValueError(f"{name} of shape {tuple(values.shape)} is not of the voxels 'where' names, "
                             f"{tuple(where.shape)}")
    where = where.detach().cpu().bool()
    flat = _set_voxels(where)
    stored = {}
    for key, (name, values) in grids.items():
        stored[key] = values.detach().cpu().float().reshape(-1)[flat]
        if not _are_probabilities(stored[key]):
            raise ValueError(f"{name} holds values outside [0, 1] (or NaN) at the voxels 'where' names, which no "
                             "probability is (a raw attention field? its probability is the fields' softmax)")
    tensors = {"indices": flat.to(torch.int32), "shape": torch.tensor(where.shape, dtype=torch.int64), **stored}
    save_tensors(path, tensors, kind="attention_probabilities", version=PROBABILITY_FORMAT_VERSION,
                 meta={"stored_voxels": int(flat.numel())})


def load_probabilities(path, shape: tuple[int, ...] | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(edit, object, where): dense (X, Y, Z) float32 grids, 0 outside ``where`` (the stored voxels); ``shape``: the
    grid's, which the file must hold. Every check comes before the dense grids are allocated (a damaged 'object' had
    been found after 'edit''s grid was, and a file claiming another grid's shape after both were)."""
    tensors, _ = load_tensors(path, kind="attention_probabilities", max_version=PROBABILITY_FORMAT_VERSION)
    indices, shape = _indices_and_shape(tensors, path, shape,
                                        ("probabilities", "probabilities are of their initial grid"))
    stored = {}
    for name in ("edit", "object"):
        values = tensors.get(name)
        if values is None or values.dim() != 1 or values.numel() != indices.numel():  # (K, 1) had passed to fail
            raise FormatError(f"{path}: '{name}' values do not match the stored indices")  # after the allocations
        if not _are_probabilities(values):
            raise FormatError(f"{path}: '{name}' holds values outside [0, 1] (or NaN), which no probability is")
        stored[name] = values.float()
    out = []
    for values in stored.values():
        dense = torch.zeros(math.prod(shape))
        dense[indices] = values
        out.append(dense.reshape(shape))
    where = torch.zeros(math.prod(shape), dtype=torch.bool)
    where[indices] = True
    return out[0], out[1], where.reshape(shape)
