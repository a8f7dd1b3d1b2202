"""Steps 3 and 4: per-voxel probabilities and the graph cut that labels G_e's occupied voxels (SPEC §3).

P_e, P_obj = softmax of the two attention values per voxel (in log space);
Boykov–Kolmogorov max-flow (PyMaxflow) on a graph built vectorised: unary
costs −log P of the label, seeds tied to their terminal, and 6-neighbour
pairwise weights λ·exp(−‖c_p − c_q‖² / 2σ²) on G_e's colours. Each of the authors'
code's differences (refinement_functions.py::build_graph) is a RefineConfig choice;
``AUTHORS_CODE_CUT`` sets them all; the defaults (``SERVICE_CUT``) are the code's but for a margin on its
random object seeds and the label of a piece no seed reaches.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from voxe_core.grid import VoxelGrid
from voxe_core.refine.config import RefineConfig, SegmentationError


@dataclass
class GraphCutStats:
    nodes: int
    edges: int
    edit_seeds: int
    object_seeds: int
    edit_voxels: int
    flow: float
    unseeded_voxels: int  # nodes relabelled in seedless pieces: only with unseeded_pieces="preference", no unary
    build_s: float
    solve_s: float
    notes: list[str] = field(default_factory=list)

    def uniform_label(self) -> str | None:
        """A warning when the cut gave every node one label, so the refinement localised nothing (a refined grid
        equal to G_i, or G_e wherever it is occupied); None when it kept some of the nodes and not others."""
        if self.edit_voxels == 0:
            return (f"the graph cut kept none of the edited grid's {self.nodes} occupied voxels: the refined grid is "
                    "the initial grid, the edit undone")
        if self.edit_voxels == self.nodes:
            return (f"the graph cut kept all {self.nodes} occupied voxels of the edited grid: the edit is not "
                    "localised (the refined grid takes the edited grid at every one of them)")
        return None


def _scalar_field(values: torch.Tensor, shape: tuple[int, int, int], name: str) -> torch.Tensor:
    if values.dim() == 4 and values.shape[-1] == 1:
        values = values[..., 0]
    if tuple(values.shape) != tuple(shape):
        raise SegmentationError(f"{name} of shape {tuple(values.shape)} does not fit the grid {tuple(shape)}")
    return values


def log_probabilities(edit_field: torch.Tensor, object_field: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(log P_e, log P_obj) = log-softmax of the two values per voxel, in float64 (finite for any finite input)."""
    e = edit_field.double()
    o = object_field.double()
    if e.dim() == 4 and e.shape[-1] == 1:
        e, o = e[..., 0], o[..., 0]
    logs = torch.log_softmax(torch.stack([e, o]), dim=0)
    return logs[0], logs[1]


# The two attention grids fitted from one start differ on CUDA by the order atomic adds sum their gradients in: a
# few float32 ulps (at most 3 over 1500 fitting steps with the sums reordered on the CPU). A preference worth seeding
# on is orders of magnitude larger; this many ulps of the values' scale is the line between them.
ROUNDING_ULPS = 16


def prefer_neither(edit_values: torch.Tensor, object_values: torch.Tensor) -> bool:
    """Whether the two attention fields (or maps) are equal everywhere but for float32 rounding: within
    :data:`ROUNDING_ULPS` ulps of their scale, the larger of 1 (the maps' range, [0, 1]) and their largest magnitude.
    A NaN or infinity differs from anything."""
    edit_values, object_values = edit_values.detach().double(), object_values.detach().double()
    scale = max(1.0, float(torch.maximum(edit_values.abs().max(), object_values.abs().max())))
    tolerance = ROUNDING_ULPS * torch.finfo(torch.float32).eps * scale
    return bool(((edit_values - object_values).abs() <= tolerance).all())


def probabilities(edit_field: torch.Tensor, object_field: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(P_e, P_obj) float32 per voxel: softmax of the two fields' values."""
    log_e, log_o = log_probabilities(edit_field, object_field)
    return log_e.exp().float(), log_o.exp().float()


def node_mask(grid: VoxelGrid, node_alpha: float = 0.01, rule: str = "alpha") -> torch.Tensor:
    """(X, Y, Z) bool: the graph's nodes, among the grid's ``object_vertices()`` (a capture's foreground: a local
    edit is of the object, never of the room the contracted background holds).

    ``rule="alpha"``: vertices whose activated density would make one voxel length ``node_alpha``
    opaque, σ·Δ ≥ −ln(1 − node_alpha) with Δ the smallest voxel edge, so the test means the same at
    every resolution and box size. ``rule="maxpool"`` (the authors' code): vertices whose 3×3×3
    max-pooled ReLU density (raw × scale, for either activation) is > 0 — the occupied set dilated by one.

    Examples:
        >>> grid = VoxelGrid(resolution=8)
        >>> grid.features.data[..., 0] = -1.0  # empty, but for one dense vertex
        >>> grid.features.data[4, 4, 4, 0] = 10.0
        >>> int(node_mask(grid).sum()), int(node_mask(grid, rule="maxpool").sum())  # maxpool: its 3×3×3 block
        (1, 27)

    Raises :class:`SegmentationError` when a vertex the test reads has a NaN density: NaN is neither occupied
    nor empty (it had dropped out of the nodes silently, under "maxpool" with its whole 3×3×3 block).
    """
    raw = grid.features[..., 0].detach()
    vertices = read = grid.object_vertices()
    if rule == "maxpool":
        read = F.max_pool3d(vertices[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    nan = int((torch.isnan(raw) & read).sum())
    if nan:
        raise SegmentationError(
            f"the edited grid's density is NaN at {nan} of the {int(read.sum())} vertices the node test reads, so "
            "which voxels are occupied (the graph's nodes) is undefined there (a diverged edit or a corrupted grid?)"
        )
    if rule == "maxpool":
        pooled = F.max_pool3d((raw * grid.density_scale)[None, None], 3, stride=1, padding=1)[0, 0]
        return (pooled > 0) & vertices
    sigma = grid.activate_density(raw)
    threshold = -math.log1p(-node_alpha) / float(grid.voxel_size.min())
    return (sigma >= threshold) & vertices


def pairwise_weights(diff: np.ndarray, config: RefineConfig) -> np.ndarray:
    """(E,) float64 weights of neighbour pairs from their colour differences (E, 3).

    ``"gaussian"`` (the text): λ·exp(−‖Δc‖²/2σ²); ``"exp_distance"`` (the code): λ·exp(−‖Δc‖/σ). Both from
    ‖Δc‖/σ in float64, so every positive σ gives weights in [0, λ]: in the colours' float32 a σ below float32's
    range had become 0 (σ² below it, for the text's) and equal colours 0/0, a NaN weight that made every
    capacity NaN and every node an edit. (Weights below float32's range, which it had rounded to 0 so that those
    edges split the graph before max-flow, now join their pieces: the cut decides them, as the energy says.)

    Examples:
        >>> weights = pairwise_weights(np.array([[0.1, 0.0, 0.0]]), RefineConfig(pairwise_weight="exp_distance"))
        >>> round(float(weights[0]), 4)  # λ·e⁻¹ with λ = 5, σ = 0.1
        1.8394
    """
    with np.errstate(over="ignore"):  # ‖Δc‖/σ past float64 (or its square): inf, its weight the 0 it tends to
        scaled = np.sqrt((diff * diff).sum(-1, dtype=np.float64)) / config.sigma  # (no float64 copy of diff)
        if config.pairwise_weight == "exp_distance":
            return config.smoothness * np.exp(-scaled)
        return config.smoothness * np.exp(-0.5 * scaled**2)


def _top_seeds(score: np.ndarray, candidates: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` highest ``score`` among ``candidates`` (ties: lower index first)."""
    idx = np.flatnonzero(candidates)
    if idx.size == 0 or count <= 0:
        return idx[:0]
    order = np.lexsort((idx, -score[idx]))  # primary: score descending, then index ascending
    return idx[order[:count]]


def object_seed_indices(p_e: np.ndarray, p_o: np.ndarray, config: RefineConfig) -> np.ndarray:
    """Indices of the object seeds among the nodes, by ``config.object_seed_rule`` (see RefineConfig)."""
    if config.object_seeds == 0:
        return np.zeros(0, np.int64)
    if config.object_seed_rule == "random":
        idx = np.flatnonzero(p_o > p_e + config.object_seed_margin)
        if idx.size == 0:
            return _top_seeds(p_o, np.ones_like(p_o, bool), config.object_seed_fallback)
        rng = np.random.default_rng(config.seed)
        return np.sort(rng.choice(idx, size=min(idx.size, config.object_seeds), replace=False))
    return _top_seeds(p_o, p_o > 0.5, config.object_seeds)


def _node_test(config: RefineConfig) -> str:
    """What no vertex passed, in ``config.node_rule``'s words."""
    if config.node_rule == "maxpool":
        return "no vertex of the edited grid's foreground has a positive density"
    return f"the edited grid's density never makes a voxel {config.node_alpha:.0%} opaque"


def graph_nodes(grid: VoxelGrid, config: RefineConfig) -> torch.Tensor:
    """(X, Y, Z) bool on the CPU: :func:`node_mask` by ``config``'s rule; :class:`SegmentationError` when no vertex
    is a node (``refine`` asks before its first attention pass)."""
    nodes = node_mask(grid, config.node_alpha, config.node_rule).cpu()
    if not nodes.any():
        raise SegmentationError(
            f"no occupied voxels: {_node_test(config)}, so there is nothing to segment "
            "(is it an empty or untrained grid?)"
        )
    return nodes


def graph_pieces(nodes: np.ndarray, heads: np.ndarray, tails: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N,) the piece of each node: nodes joined by pairwise edges of positive weight share one.

    Every edge joins 6-neighbour nodes, so while all weights are positive the pieces are the node mask's
    6-connected components (``scipy.ndimage.label``, a pass over the lattice); a zero weight (smoothness 0, or
    an underflow) cuts its edge, and the pieces come from the graph itself (sparse connected components).

    Args:
        nodes: (X, Y, Z) bool, the graph's nodes (numbered in its raster order).
        heads, tails, weights: (E,) the pairwise edges.
    """
    if (weights > 0).all():
        from scipy import ndimage

        lattice, _ = ndimage.label(nodes, structure=ndimage.generate_binary_structure(3, 1))
        return lattice[nodes] - 1
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = int(nodes.sum())
    joined = weights > 0
    adjacency = coo_matrix((np.ones(int(joined.sum())), (heads[joined], tails[joined])), shape=(n, n))
    return connected_components(adjacency, directed=False)[1]


def label_unseeded_pieces(edit_side: np.ndarray, piece: np.ndarray, seeds: np.ndarray, log_e: np.ndarray,
                          log_o: np.ndarray) -> tuple[np.ndarray, int]:
    """Each piece of the graph (``graph_pieces``) holding none of ``seeds`` takes the label its voxels favour
    together (Σ log P_e > Σ log P_obj: edit): with no unary such a piece costs nothing either way, and max-flow
    would leave it on the source (edit) side whatever its probabilities.

    Args:
        edit_side: (N,) bool, max-flow's labels. piece: (N,) each node's piece.
        seeds: (S,) node indices tied to either terminal. log_e, log_o: (N,) log P_e, log P_obj.

    Returns:
        (N,) bool labels, and how many nodes lie in unseeded pieces.

    Examples:
        >>> labels, moved = label_unseeded_pieces(np.ones(4, bool), np.array([0, 0, 1, 1]), np.array([0]),
        ...                                       np.log([.9, .9, .2, .4]), np.log([.1, .1, .8, .6]))
        >>> labels.tolist(), moved  # nodes 2-3 form a seedless piece that favours the object
        ([True, True, False, False], 2)
    """
    count = int(piece.max()) + 1
    seeded = np.zeros(count, bool)
    seeded[piece[seeds]] = True
    unseeded = ~seeded[piece]
    favours_edit = np.bincount(piece, weights=log_e - log_o, minlength=count) > 0
    labels = edit_side.copy()
    labels[unseeded] = favours_edit[piece[unseeded]]
    return labels, int(unseeded.sum())


def graph_cut_detailed(
    grid: VoxelGrid,
    edit_field: torch.Tensor,
    object_field: torch.Tensor,
    config: RefineConfig = RefineConfig(),
) -> tuple[torch.Tensor, GraphCutStats]:
    """Binary edit mask (X, Y, Z) of the occupied voxels of ``grid`` (G_e), and what the cut did.

    Energy (the text, ``PAPER_TEXT_CUT``): Σ_p −log P_{l_p}(p) + λ Σ_{p~q, l_p≠l_q} exp(−‖c_p − c_q‖²/2σ²),
    minimised exactly by max-flow; the defaults are the authors' code's (``AUTHORS_CODE_CUT``: no unary
    for unseeded voxels, λ·exp(−‖Δc‖/σ), random object seeds, max-pooled nodes; see RefineConfig), the object
    seeds drawn among P_obj > P_e + ``object_seed_margin`` and a piece no seed reaches labelled by its
    probabilities (``SERVICE_CUT``).

    Edit seeds: every node within ``edit_seed_ratio`` of the largest P_e, topped up to ``edit_seeds`` by the
    highest P_e, then only those with P_e > P_obj (``edit_seed_rule="relative"``, the code); or the
    ``edit_seeds`` highest P_e among P_e > ½ ("top", the text). Object seeds (``object_seed_indices``): up to
    ``object_seeds`` drawn at random (``seed``) among P_obj > P_e + margin, or when none qualifies the
    ``object_seed_fallback`` highest P_obj whatever their preference ("random"); or the ``object_seeds``
    highest P_obj among P_obj > ½ ("top"). A node in both sets stays an edit seed. When fewer seeds
    than asked qualify, the available ones are used and ``stats.notes`` (and a warning) says so; with the unary term
    (``unseeded_unary="log_probability"``) none need to (counts of 0 too): the energy labels every voxel.
    Raises :class:`SegmentationError` when no node is occupied, when the grid's density is NaN where
    ``node_mask`` reads it, when a field or the grid's colour is not finite at a node, when no node qualifies
    as a seed of either label and there is no unary term, or when the grids carry no preference anywhere (e.g.
    all-equal probabilities).
    """
    import maxflow

    t0 = time.perf_counter()
    shape = grid.resolution
    edit_field = _scalar_field(edit_field, shape, "edit_field")
    object_field = _scalar_field(object_field, shape, "object_field")
    nodes = graph_nodes(grid, config)
    n = int(nodes.sum())
    edit_field, object_field = edit_field.detach().cpu(), object_field.detach().cpu()
    log_e, log_o = log_probabilities(edit_field, object_field)
    nodes_np = nodes.numpy()
    log_e = log_e.numpy()[nodes_np]
    log_o = log_o.numpy()[nodes_np]
    colors = torch.sigmoid(grid.features[..., 1:4].detach().float()).cpu().numpy()
    # One non-finite capacity would make the seeds' "infinite" capacity NaN and every node an edit.
    for name, values in (("edit_field", log_e), ("object_field", log_o), ("grid colour", colors[nodes_np])):
        bad = int((~np.isfinite(values)).reshape(n, -1).any(1).sum())
        if bad:
            raise SegmentationError(
                f"{name} is not finite (NaN or infinite) at {bad} of the {n} occupied voxels, so the cut is "
                "undefined there (a diverged edit or attention-grid fit?)"
            )
    p_e, p_o = np.exp(log_e), np.exp(log_o)

    notes: list[str] = []
    if config.edit_seed_rule == "relative":
        edit_seeds = np.union1d(np.flatnonzero(p_e >= config.edit_seed_ratio * p_e.max()),
                                _top_seeds(p_e, np.ones_like(p_e, bool), config.edit_seeds))
        edit_seeds = edit_seeds[p_e[edit_seeds] > p_o[edit_seeds]]  # never a voxel the object claims more
    else:
        edit_seeds = _top_seeds(p_e, p_e > 0.5, config.edit_seeds)
    object_seeds = np.setdiff1d(object_seed_indices(p_e, p_o, config), edit_seeds)  # a fallback may overlap
    # (a fallback seeds no preference; on CUDA equal grids differ by rounding alone). With a unary term the energy
    # labels every voxel without seeds (seed counts of 0 had been refused here, blaming grids that differed).
    seedless = edit_seeds.size + object_seeds.size == 0 and config.unseeded_unary == "none"
    if seedless or prefer_neither(edit_field[nodes], object_field[nodes]):
        raise SegmentationError(
            f"no seeds: none of the {n} occupied voxels is more likely edit than object or the reverse "
            "(the attention grids are equal everywhere: too few fitting iterations, or maps that do not tell "
            "the edit from the object), so the edit region is undefined"
        )
    for label, got, wanted in (("edit", edit_seeds.size, config.edit_seeds), ("object", object_seeds.size, config.object_seeds)):
        if got < wanted:
            notes.append(f"only {got} of {wanted} {label} seeds qualified")

    # unary terms: the source side is "edit", so the source edge is cut (paid) when p ends up "object"
    cap_source = -log_o if config.unseeded_unary == "log_probability" else np.zeros(n)
    cap_sink = -log_e if config.unseeded_unary == "log_probability" else np.zeros(n)

    # pairwise terms along all three axes between occupied neighbours
    ids = np.full(shape, -1, dtype=np.int64)
    ids[nodes_np] = np.arange(n)
    heads, tails, weights = [], [], []
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        pair = nodes_np[lo] & nodes_np[hi]
        if not pair.any():
            continue
        diff = colors[lo][pair] - colors[hi][pair]
        heads.append(ids[lo][pair])
        tails.append(ids[hi][pair])
        weights.append(pairwise_weights(diff, config))
    i = np.concatenate(heads) if heads else np.zeros(0, np.int64)
    j = np.concatenate(tails) if tails else np.zeros(0, np.int64)
    w = np.concatenate(weights) if weights else np.zeros(0)

    # "infinite" seed capacity: more than every finite capacity together, so no finite cut severs a seed
    big = float(cap_source.sum() + cap_sink.sum() + 2.0 * w.sum() + 1.0)
    cap_source[edit_seeds], cap_sink[edit_seeds] = big, 0.0
    cap_source[object_seeds], cap_sink[object_seeds] = 0.0, big

    graph = maxflow.Graph[float](n, max(1, i.size))
    node_ids = graph.add_nodes(n)
    if i.size:
        graph.add_edges(i, j, w, w)
    graph.add_grid_tedges(np.asarray(node_ids), cap_source, cap_sink)
    build_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    flow = graph.maxflow()
    edit_side, unseeded = ~graph.get_grid_segments(np.asarray(node_ids)), 0  # get_grid_segments: True on the sink
    if config.unseeded_unary == "none" and config.unseeded_pieces == "preference":
        edit_side, unseeded = label_unseeded_pieces(edit_side, graph_pieces(nodes_np, i, j, w),
                                                    np.concatenate([edit_seeds, object_seeds]), log_e, log_o)
    solve_s = time.perf_counter() - t1

    mask = np.zeros(shape, dtype=bool)
    mask[nodes_np] = edit_side
    for note in notes:
        warnings.warn(note, stacklevel=2)
    stats = GraphCutStats(
        nodes=n, edges=int(i.size), edit_seeds=int(edit_seeds.size), object_seeds=int(object_seeds.size),
        edit_voxels=int(edit_side.sum()), flow=float(flow), unseeded_voxels=unseeded, build_s=build_s,
        solve_s=solve_s, notes=notes,
    )
    return torch.from_numpy(mask).to(grid.bbox_min.device), stats


def graph_cut(
    grid: VoxelGrid, edit_field: torch.Tensor, object_field: torch.Tensor, config: RefineConfig = RefineConfig()
) -> torch.Tensor:
    """The edit mask (X, Y, Z) bool of :func:`graph_cut_detailed`."""
    return graph_cut_detailed(grid, edit_field, object_field, config)[0]
