"""The paper's evaluation (SPEC §4): ring renders, CLIP similarity / direction, FID, and preservation.

For the initial grid G_i and each edit, :func:`evaluate` renders the same ring
of poses (100 evenly spaced over 360° by default) and computes

* ``clip_sim``: mean over views of cos(CLIP image, CLIP text of the edit
  prompt "a render of <text>");
* ``clip_dir``: mean over views of cos(image_edit − image_recon, text_edit −
  text_source), with source text "a render of a <object>" (the CLIP
  directional similarity the paper reports);
* ``fid_rec`` / ``fid_input``: Fréchet distance between Inception pool
  features of the edit's renders and G_i's renders / the input images;
* ``psnr`` / ``ssim`` against G_i's renders *outside the 3D edit mask* (how
  well a local edit kept the rest; a metric the paper lacks). A pixel is
  excluded when its ray takes a render sample in a grid cell with a masked
  corner vertex. Those are the only cells whose trilinear features a merge
  G_r = M·G_e + (1 − M)·G_i can change, so for a refined grid every kept
  pixel is, by construction, rendered from G_i's features alone: a drop
  there is a real change. Global edits (no mask) are compared on the whole
  image.

Models: CLIP through transformers' ``CLIPModel`` (default
``openai/clip-vit-base-patch32``, as the paper's ViT-B/32), loaded offline-aware
with an error naming the model when it is missing; FID features from a
TorchScript Inception file (``inception-2015-12-05.pt``, the network used by
StyleGAN2-ADA / clean-fid) given by path. :mod:`voxe_core.tiny_eval` builds
random-weight smoke-test stand-ins for both, loaded through the same code.
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Protocol, Sequence

import numpy as np
import torch

from voxe_core.constants import (
    CLIP_MODEL_ID, EVALUATION_RING_ELEVATION, EVALUATION_RING_SIZE, EVALUATION_RING_VIEWS, INCEPTION_FILE,
    MAX_EVALUATION_RING_VIEWS, MAX_RENDER_SIZE, SMOKE_TEST_MARK, TINY_MODEL, inception_path,
)
from voxe_core.devices import PeakMemory, full_precision, resolve_device
from voxe_core.export import iter_views, render_views, to_uint8, turntable_cameras
from voxe_core.grid import VoxelGrid
from voxe_core.guidance.loading import (
    ModelNotAvailableError, download_command, is_out_of_memory, load_clip_tokenizer, loading_errors, local_path,
    no_folder_note, offline_env, tiny_model_note, tokenizer_fits,
)
from voxe_core.guidance.prompts import check_text_length, edit_prompt, tokens_read
from voxe_core.metrics import PSNR_CAP_DB, SSIM_WINDOW, psnr, ssim
from voxe_core.progress import Callbacks, Progress
from voxe_core.refine.storage import check_binary
from voxe_core.render import RenderConfig, render_image

INCEPTION_URL = "https://nvlabs-fi-cdn.nvidia.com/stylegan2-ada-pytorch/pretrained/metrics/inception-2015-12-05.pt"
SOURCE_TEMPLATE = "a render of a {object}"
RING_CHUNK_BYTES = 64 * 2**20
"""G_i's ring views (float pixels) :func:`evaluate` holds at most, to score each edit's views of the same cameras
against: each edit's grid goes to the render device, and has its occupancy built, once for so many views (at
least one), not once a view (~65 MB copied and an occupancy built a view at 160³)."""

# SPEC §4: (prompt template, mode, words naming the edit for the refinement).
PAPER_PROMPTS: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("a {object} wearing big sunglasses", "local", ("sunglasses",)),
    ("a {object} wearing a Christmas sweater", "local", ("sweater",)),
    ("a {object} wearing a birthday party hat", "local", ("party hat",)),
    ("a yarn doll of a {object}", "global", ()),
    ("a wood carving of a {object}", "global", ()),
    ("a claymation {object}", "global", ()),
)


@dataclass(frozen=True)
class ProtocolEdit:
    prompt: str
    mode: str
    edit_words: tuple[str, ...]


def paper_protocol(object_name: str) -> list[ProtocolEdit]:
    """The six edits of SPEC §4 for one object (local ones carry the words the refinement localises)."""
    name = " ".join(str(object_name).split())
    if not name:
        raise ValueError("the object name is empty")
    return [ProtocolEdit(t.format(object=name), mode, words) for t, mode, words in PAPER_PROMPTS]


def source_text(object_name: str) -> str:
    name = " ".join(str(object_name).split())
    if not name:
        raise ValueError("the object name is empty")
    return SOURCE_TEMPLATE.format(object=name)


def check_source_text_length(object_name: str) -> None:
    """ValueError when the source text surely holds more tokens than CLIP's text model reads: a service takes it
    before the evaluation is queued (the scorer's own tokenizer refuses it only once its models are loaded)."""
    check_text_length(source_text(object_name), "the source text", "shorten the object name")


# --------------------------------------------------------------------------- ring renders
def render_ring(grid: VoxelGrid, views: int, elevation_deg: float, size: int, callbacks: Callbacks = Callbacks(),
                device: torch.device | str | None = None, centre: torch.Tensor | None = None):
    """``views`` renders (N, H, W, 3, on the CPU) on the evaluation ring, looking at ``centre`` (None: the origin;
    G_i's ``orbit_centre()`` for all grids of one evaluation, so theirs are the same views), rendered on ``device``."""
    return render_views(grid, turntable_cameras(views, elevation_deg, size, centre=centre), callbacks=callbacks,
                        device=device)


def mask_footprint(grid: VoxelGrid, mask: torch.Tensor, views: int, elevation_deg: float, size: int,
                   centre: torch.Tensor | None = None, callbacks: Callbacks = Callbacks()) -> torch.Tensor:
    """(N, H, W) bool: :func:`iter_mask_footprint`'s views all at once."""
    hits = torch.zeros(views, size, size, dtype=torch.bool)
    for i, view in enumerate(iter_mask_footprint(grid, mask, views, elevation_deg, size, centre, callbacks)):
        hits[i] = view
    return hits


def iter_mask_footprint(grid: VoxelGrid, mask: torch.Tensor, views: int, elevation_deg: float, size: int,
                        centre: torch.Tensor | None = None,
                        callbacks: Callbacks = Callbacks()) -> Iterator[torch.Tensor]:
    """Yields, view by view of the ring, (H, W) bool: pixels whose ray samples a cell with a masked corner vertex.

    ``mask`` (X, Y, Z) bool over ``grid``'s vertices. Rendered through the same
    renderer and ray sampling as the views, over an opaque stand-in of the
    grid's own backbone (``grid.like``: its box, contraction and samples) that
    is dense exactly in those cells, so "no hit" means no sample of that ray saw
    them. The views go a chunk at a time, :func:`ring_chunks`' (those
    :func:`evaluate` scores together): as a chunk's first view is asked for, a
    stand-in (4 floats a vertex and its occupancy, ~70 MB at 160³) is built,
    renders the chunk's views and is let go before that view is yielded, so
    between views only the rest of one chunk's footprints are held, a bit a pixel
    (0.7 MB at most, 1/96 of :data:`RING_CHUNK_BYTES`, or one view's), and
    :func:`evaluate` holds no stand-in and one masked edit's chunk of bits at a
    time, however many are masked. (Built for each view, the stand-in had cost
    ~0.09 s of CPU a view at 160³, 40 % of the view's footprint; the whole ring's
    bits, rendered at the first view, had been held by every masked edit at once:
    47 MB each for 360 views of 1,024², 2.8 GB for 60.)
    ``callbacks`` may cancel before each view is rendered and gets a
    ``Progress("mask footprint", i, N)`` as each view is rendered (a chunk's come
    as its first view is asked for).
    """
    if tuple(mask.shape) != tuple(grid.resolution):
        raise ValueError(f"mask of shape {tuple(mask.shape)} does not fit the grid {grid.resolution}")
    check_binary(mask)  # (a 0.3 mask's stand-in, 300 at its vertices, was as opaque as a 1 mask's)
    cameras = turntable_cameras(views, elevation_deg, size, centre=centre).to(grid.bbox_min.device)
    for chunk in ring_chunks(views, size):
        packed = _footprint_views(grid, mask, cameras, chunk, callbacks)
        for _ in chunk:  # each view's bits let go as it is yielded (its pixels not kept in a local while suspended)
            yield torch.from_numpy(np.unpackbits(packed.pop(0), axis=-1, count=cameras.width).astype(bool))


@torch.no_grad()
def _footprint_views(grid: VoxelGrid, mask: torch.Tensor, cameras, views: range,
                     callbacks: Callbacks) -> list[np.ndarray]:
    """:func:`iter_mask_footprint`'s views ``views`` of ``cameras``, each (H, ceil(W / 8)) uint8, a bit a pixel
    (``np.packbits``), rendered from one stand-in built here and let go, each reported to ``callbacks`` as it is."""
    features = torch.zeros(*grid.resolution, 4, device=grid.bbox_min.device)
    # Raw 1e3 at masked vertices: any sample with a positive trilinear weight on one is near-opaque.
    features[..., 0] = mask.to(features.device, torch.float32) * 1e3
    stand_in = grid.like(features)
    stand_in.activation = "relu"  # raw 0 is no density only under ReLU (softplus would haze every cell)
    config = RenderConfig(sigma_threshold=0.0)  # every cell touching a masked vertex is 'occupied'
    occupancy = stand_in.occupancy(config.sigma_threshold)
    packed = []
    for i in views:
        callbacks.check_cancel("mask footprint")
        hits = (torch.zeros(cameras.height, cameras.width, dtype=torch.bool) if occupancy.empty else
                render_image(stand_in, cameras, i, config, occupancy).opacity.cpu() > 0)
        packed.append(np.packbits(hits.numpy(), axis=-1))
        callbacks.progress(Progress("mask footprint", i + 1, len(cameras)))
    return packed


# --------------------------------------------------------------------------- Fréchet distance
def _sqrt_psd(matrix: np.ndarray) -> np.ndarray:
    """Square root of a symmetric positive semi-definite matrix (eigh; round-off negatives clamped to 0)."""
    symmetric = 0.5 * (matrix + matrix.T)
    values, vectors = np.linalg.eigh(symmetric)
    return (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T


def frechet_distance(mu1, sigma1, mu2, sigma2) -> float:
    """Fréchet distance of two Gaussians: ||mu1 − mu2||² + tr(S1 + S2 − 2 (S1^½ S2 S1^½)^½).

    tr((S1 S2)^½) is computed as the trace of the square root of the symmetric
    PSD product S1^½ S2 S1^½ (the same eigenvalues), by eigendecomposition, so
    singular or rank-deficient covariances (fewer samples than feature
    dimensions, the usual case here) never produce complex parts or NaNs.
    """
    mu1, mu2 = np.asarray(mu1, np.float64), np.asarray(mu2, np.float64)
    s1, s2 = np.atleast_2d(np.asarray(sigma1, np.float64)), np.atleast_2d(np.asarray(sigma2, np.float64))
    if mu1.shape != mu2.shape or s1.shape != s2.shape or s1.shape != (mu1.size, mu1.size):
        raise ValueError(f"mismatched Gaussians: means {mu1.shape} / {mu2.shape}, covariances {s1.shape} / {s2.shape}")
    root1 = _sqrt_psd(s1)
    cross = np.clip(np.linalg.eigvalsh(0.5 * ((root1 @ s2 @ root1) + (root1 @ s2 @ root1).T)), 0.0, None)
    value = float(np.sum((mu1 - mu2) ** 2) + np.trace(s1) + np.trace(s2) - 2.0 * np.sum(np.sqrt(cross)))
    return max(value, 0.0)  # a distance: round-off below zero is zero


def feature_statistics(features) -> tuple[np.ndarray, np.ndarray]:
    """Mean and (N − 1)-normalised covariance of (N, D) features; needs N >= 2."""
    x = np.asarray(features, np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"FID needs at least 2 feature vectors shaped (N, D), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("FID features contain NaN or inf")
    return x.mean(axis=0), np.cov(x, rowvar=False).reshape(x.shape[1], x.shape[1])


def fid_from_features(features_a, features_b) -> float:
    return frechet_distance(*feature_statistics(features_a), *feature_statistics(features_b))


# --------------------------------------------------------------------------- FID features
AfterBatch = Callable[[int], None]  # called with a batch's image count once it is done: progress, a cancel point


class FeatureExtractor(Protocol):
    """Maps images (N, H, W, 3), floats in [0, 1] or uint8, to feature vectors (N, D), calling ``after_batch`` after
    each batch of (at most) ``batch_size`` images."""

    name: str
    batch_size: int

    def features(self, images: torch.Tensor, after_batch: AfterBatch | None = None) -> torch.Tensor:
        ...


Scorer = tuple[Callable[[torch.Tensor, AfterBatch], torch.Tensor], int, AfterBatch]  # score, batch size, hook


class ViewBatches:
    """Views handed over one at a time, scored by each of ``scorers`` (``(score(images, after_batch), batch_size,
    after_batch)``: CLIP's embeddings, FID's features) in batches of its ``batch_size``, held till then as the 8-bit
    pixels they all score (a quarter of a float view) in one buffer they share: the values of the whole ring scored
    at once by each, bit for bit, with the largest batch's pixels held, not the ring's, nor a buffer per scorer
    (CLIP's 32 views and FID's 25 had been 57). ``before_batch`` is called before each batch is scored (a
    cancellation point)."""

    def __init__(self, scorers: Sequence[Scorer], before_batch: Callable[[], None]):
        self.scorers, self.before_batch = scorers, before_batch
        self.capacity = max(batch_size for _, batch_size, _ in scorers)
        self.buffer: torch.Tensor | None = None  # (capacity, H, W, 3) uint8, made at the first view: view n in
        # slot n % capacity
        self.added = 0
        self.unscored = [0] * len(scorers)  # per scorer, the first view it has not scored
        self.scored: list[list[torch.Tensor]] = [[] for _ in scorers]

    def add(self, view: torch.Tensor) -> None:
        if self.buffer is None:
            self.buffer = torch.empty(self.capacity, *view.shape, dtype=torch.uint8)
        # The slot's earlier view (added − capacity) every scorer has scored: each has fewer pending than its batch.
        self.buffer[self.added % self.capacity] = torch.from_numpy(to_uint8(view))
        self.added += 1
        for k, (_, batch_size, _) in enumerate(self.scorers):
            if self.added - self.unscored[k] == batch_size:
                self._score_pending(k)

    def results(self) -> list[torch.Tensor]:
        """Per scorer, (N, D): the scores of every view added, in order; the buffer let go."""
        for k in range(len(self.scorers)):
            self._score_pending(k)
        self.buffer = None
        return [torch.cat(scored) for scored in self.scored]

    def _score_pending(self, k: int) -> None:
        if self.added > self.unscored[k]:
            first = self.unscored[k] % self.capacity
            count = self.added - self.unscored[k]
            # A batch that wraps past the buffer's end is gathered (a copy of that batch alone, while it is scored).
            images = (self.buffer[first : first + count] if first + count <= self.capacity
                      else self.buffer[torch.arange(first, first + count) % self.capacity])
            self.before_batch()
            score, _, after_batch = self.scorers[k]
            self.scored[k].append(score(images, after_batch))
            self.unscored[k] = self.added


class InceptionFeatures:
    """Pool features of a TorchScript Inception file called as ``model(uint8 NCHW, return_features=True)``.

    That is the calling convention of ``inception-2015-12-05.pt`` (StyleGAN2-ADA's
    FID network, 2048 features, resizing to 299 px inside), and of the tiny random
    file :func:`voxe_core.tiny_eval.build_tiny_inception` writes.
    """

    def __init__(self, module: torch.jit.ScriptModule, name: str, device, batch_size: int = 25):
        self.module, self.name, self.device, self.batch_size = module, name, torch.device(device), batch_size

    @classmethod
    def load(cls, path, device=None, batch_size: int = 25) -> "InceptionFeatures":
        given, path = str(path), inception_path(path)
        if given == TINY_MODEL and not path.exists():  # (it had been told to download the real file to "tiny")
            build = (f"python -c \"from voxe_core.tiny_eval import build_tiny_inception; "
                     f"build_tiny_inception('DIR/{INCEPTION_FILE}')\"")
            raise ModelNotAvailableError(f"FID Inception weights not found at {given}: {tiny_model_note(build)}.")
        if not path.is_file():
            raise ModelNotAvailableError(
                f"FID Inception weights not found at {path}: download {INCEPTION_URL} once on a machine with "
                f"internet and pass its path (or a folder holding {INCEPTION_FILE})"
            )
        device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        try:
            module = torch.jit.load(str(path), map_location=device).eval()
        except RuntimeError as exc:
            raise ModelNotAvailableError(f"{path} is not a TorchScript Inception file: {exc}") from exc
        return cls(module, str(path), device, batch_size)

    @torch.no_grad()
    def features(self, images: torch.Tensor, after_batch: AfterBatch | None = None) -> torch.Tensor:
        parts = []
        for start in range(0, len(images), self.batch_size):
            # 8-bit pixels as saved renders hold them (uint8 images as they are: as floats they had all been white)
            batch = torch.from_numpy(to_uint8(images[start : start + self.batch_size])).to(self.device)
            pixels = batch.permute(0, 3, 1, 2).contiguous()
            parts.append(self.module(pixels, return_features=True).reshape(len(batch), -1).double().cpu())
            if after_batch is not None:
                after_batch(len(batch))
        return torch.cat(parts)


# --------------------------------------------------------------------------- CLIP
def _clip_image_processor_class():
    """CLIP's own PIL preprocessing (bicubic resize, centre crop, normalise), as the CLIP scores were defined on.

    transformers >= 5 names the PIL implementation ``CLIPImageProcessorPil`` (its default
    class wants torchvision); older versions have only ``CLIPImageProcessor``, which is it.
    """
    import transformers

    return getattr(transformers, "CLIPImageProcessorPil", None) or transformers.CLIPImageProcessor


class ClipScorer:
    """Normalised CLIP image and text embeddings (transformers ``CLIPModel``).

    Images go through the checkpoint's own image processor as 8-bit pixels, exactly as
    saved renders would, so scores match CLIP's reference preprocessing.
    """

    def __init__(self, model, tokenizer, image_processor, name: str, device, batch_size: int = 32):
        self.model, self.tokenizer, self.name = model.eval().requires_grad_(False), tokenizer, name
        self.image_processor, self.device, self.batch_size = image_processor, torch.device(device), batch_size

    @classmethod
    def from_pretrained(cls, model_id: str = CLIP_MODEL_ID, device=None, local_files_only: bool | None = None):
        """Load a hub id (from the local cache when offline) or a folder; ModelNotAvailableError names the model."""
        from transformers import CLIPModel

        device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        kwargs = {"local_files_only": offline_env() if local_files_only is None else bool(local_files_only)}
        looks_local = model_id.startswith((".", "/", "~")) or os.path.isabs(model_id)
        if looks_local and not Path(model_id).expanduser().is_dir():
            raise ModelNotAvailableError(f"CLIP model folder '{model_id}' does not exist")
        try:
            model = CLIPModel.from_pretrained(model_id, **kwargs)
            tokenizer = load_clip_tokenizer(model_id, **kwargs)
            image_processor = _clip_image_processor_class().from_pretrained(model_id, **kwargs)
        except loading_errors() as exc:
            if is_out_of_memory(exc):
                raise
            raise ModelNotAvailableError(_clip_not_available(model_id, f"{type(exc).__name__}: {exc}")) from exc
        text_vocabulary = model.config.text_config.vocab_size
        if not tokenizer_fits(tokenizer, text_vocabulary):  # or every prompt encodes alike: every CLIP_dir 0
            raise ModelNotAvailableError(_clip_not_available(
                model_id, f"its tokenizer has {len(tokenizer)} tokens for a text model of {text_vocabulary}: "
                          "vocab.json / merges.txt are missing or belong to another model"))
        return cls(model.to(device), tokenizer, image_processor, model_id, device)

    def _preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) floats in [0, 1] -> the processor's normalised (N, 3, S, S) pixel values."""
        pixels = [frame for frame in to_uint8(images)]
        return torch.as_tensor(np.asarray(self.image_processor(images=pixels, return_tensors="np")["pixel_values"]))

    @torch.no_grad()
    def image_embeddings(self, images: torch.Tensor, after_batch: AfterBatch | None = None) -> torch.Tensor:
        """(N, D) unit embeddings of images (N, H, W, 3) in [0, 1]; ``after_batch`` is called after each batch."""
        parts = []
        for start in range(0, len(images), self.batch_size):
            pixels = self._preprocess(images[start : start + self.batch_size]).to(self.device)
            parts.append(_unit(_tensor_of(self.model.get_image_features(pixel_values=pixels)).float().cpu()))
            if after_batch is not None:
                after_batch(len(pixels))
        return torch.cat(parts)

    @torch.no_grad()
    def text_embeddings(self, texts: Sequence[str]) -> torch.Tensor:
        """(N, D) unit embeddings of ``texts``; ValueError for one longer than the text model reads (it had been cut
        off there silently and scored as the shorter text, a long object name's CLIP_dir against another source)."""
        limit = tokens_read(self.tokenizer, self.model.config.text_config.max_position_embeddings)
        tokens = self.tokenizer(list(texts), padding=True, return_tensors="pt")  # uncut
        for text, length in zip(texts, tokens.attention_mask.sum(1).tolist()):
            if length > limit:
                raise ValueError(f"the text {text!r} is {length} tokens; the CLIP text model of {self.name} reads "
                                 f"{limit}, its start and end tokens included: shorten it")
        return _unit(_tensor_of(self.model.get_text_features(**tokens.to(self.device))).float().cpu())


def _clip_not_available(model_id: str, cause: str) -> str:
    """The error text for CLIP weights that cannot be loaded: which model, how to provide it, what failed (a folder
    is told to hold the model: a hub download of its path had been its remedy)."""
    if model_id == TINY_MODEL and local_path(model_id) is None:
        build = "python -c \"from voxe_core.tiny_eval import build_tiny_clip; build_tiny_clip('DIR')\""
        return f"CLIP weights '{model_id}' are not available: {tiny_model_note(build)}."
    remedy = ("that local folder must hold a whole CLIPModel with its tokenizer and image processor"
              if local_path(model_id) is not None else
              f"download them once with `{download_command(model_id, clip=True)}` on a machine with internet and "
              "point HF_HOME at "
              "that cache, or pass a local folder holding a CLIPModel with its tokenizer and image processor")
    return (f"CLIP weights '{model_id}' are not available{no_folder_note(model_id)}: {remedy}. Underlying error: "
            f"{' '.join(cause.split())[:300]}")


def _tensor_of(output) -> torch.Tensor:
    """get_*_features returns a tensor in most transformers versions and an output object in some."""
    return output if isinstance(output, torch.Tensor) else output.pooler_output


def _unit(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rows scaled to unit length, in at least float32; a zero row stays zero (its cosine with anything is 0, not NaN).

    Half precision is widened first: ``eps`` underflows to 0 there, and a zero row would become 0 / 0.
    """
    x = x.to(torch.promote_types(x.dtype, torch.float32))
    return x / x.norm(dim=-1, keepdim=True).clamp_min(eps)


def clip_similarity(image_embeddings: torch.Tensor, text_embedding: torch.Tensor) -> float:
    """Mean cosine between each image embedding (N, D) and one text embedding (D,), in float32 whatever autocast says
    (a caller's bf16 autocast had run the product in bf16: -0.00098 for -0.00094)."""
    with full_precision(image_embeddings, text_embedding):
        return float((_unit(image_embeddings) @ _unit(text_embedding.reshape(-1))).mean())


def clip_direction(edit_images: torch.Tensor, recon_images: torch.Tensor, edit_text: torch.Tensor,
                   source_text_embedding: torch.Tensor) -> float:
    """Mean over view pairs of cos(image_edit − image_recon, text_edit − text_source).

    Embeddings are unit-normalised first (as CLIP compares them). A view whose
    image did not change contributes 0. In float32 whatever autocast says, as :func:`clip_similarity`.
    """
    if edit_images.shape != recon_images.shape:
        raise ValueError(f"CLIP_dir pairs views: {tuple(edit_images.shape)} vs {tuple(recon_images.shape)}")
    image_change = _unit(_unit(edit_images) - _unit(recon_images))
    text_change = _unit(_unit(edit_text.reshape(-1)) - _unit(source_text_embedding.reshape(-1)))
    with full_precision(image_change, text_change):
        return float((image_change @ text_change).mean())


# --------------------------------------------------------------------------- the evaluation
@dataclass
class EvaluateConfig:
    views: int = EVALUATION_RING_VIEWS
    elevation: float = EVALUATION_RING_ELEVATION  # degrees above the horizon
    size: int = EVALUATION_RING_SIZE  # ring render size

    def __post_init__(self):
        # Said "<setting> must ...", as voxe_core.cli.common.said_by_option names the option typed: the one rule of
        # the CLI's --views / --size / --elevation (its option types had refused 0 views, then this 1)
        if not 2 <= self.views <= MAX_EVALUATION_RING_VIEWS:
            raise ValueError(f"views must be between 2 (FID needs two samples) and {MAX_EVALUATION_RING_VIEWS} (the "
                             f"service's limit), got {self.views}")
        if not SSIM_WINDOW <= self.size <= MAX_RENDER_SIZE:
            raise ValueError(f"size must be between {SSIM_WINDOW} px (SSIM's window) and {MAX_RENDER_SIZE} px (the "
                             f"service's limit), got {self.size}")
        if not -90.0 < self.elevation < 90.0:
            raise ValueError(f"elevation must lie strictly between -90 and 90 degrees, got {self.elevation}")


@dataclass
class EditSample:
    """One edit to score: its user prompt, its grid, and the 3D mask of a refined local edit (None: global)."""

    name: str
    prompt: str
    grid: VoxelGrid
    mask: torch.Tensor | None = None


@dataclass
class Evaluation:
    rows: list[dict]  # one per edit: name, prompt, mode and the metrics

    def summary(self) -> dict:
        return {"rows": self.rows, "means": mean_by_mode(self.rows)}


METRICS = ("clip_sim", "clip_dir", "fid_rec", "fid_input", "psnr", "ssim")


def evaluation_steps(edits: Sequence[EditSample], config: EvaluateConfig, fid: FeatureExtractor | None = None,
                     input_images: torch.Tensor | None = None) -> int:
    """The progress total of :func:`evaluate`: one step per view of each pass over the ring.

    The ring renders of G_i and of every edit, the mask footprint of every masked edit, CLIP on every ring, and
    with ``fid`` the Inception features of every ring and input image.
    """
    ring_views = (1 + len(edits)) * config.views
    footprint_views = sum(sample.mask is not None for sample in edits) * config.views
    input_views = len(input_images) if input_images is not None else 0
    fid_images = ring_views + input_views if fid is not None else 0
    return ring_views + footprint_views + ring_views + fid_images


def evaluate(
    initial: VoxelGrid,
    edits: Sequence[EditSample],
    object_name: str,
    clip: ClipScorer,
    fid: FeatureExtractor | None = None,
    input_images: torch.Tensor | None = None,
    config: EvaluateConfig = EvaluateConfig(),
    callbacks: Callbacks = Callbacks(),
    device: torch.device | str | None = None,
    on_ring: Callable[[str | None, int, torch.Tensor], None] | None = None,
) -> Evaluation:
    """Score ``edits`` of ``initial`` on the ring (see the module doc); FID only when ``fid`` is given.

    The rings go a chunk of views at a time (:func:`ring_chunks`): ``initial``'s views of the chunk are rendered
    (once), then each edit's, each scored against ``initial``'s of its camera (PSNR / SSIM outside the footprint,
    rendered beside them), and all let go before the next chunk; CLIP and FID take each grid's views in their
    batches, as 8-bit pixels (one buffer per grid, of the larger batch). So ``initial``'s views of one chunk
    (:data:`RING_CHUNK_BYTES` at most, or one view) and one view of an edit are held at a time, each grid's batch
    pixels and the scores besides (each ring had been held whole, ``initial``'s to the end: 9 GB of floats for 360
    views of 1,024²; every edit's before that, 270 GB for 60 edits), and every ring is rendered once; a masked
    edit's footprints of the chunk are rendered as its first view of the chunk is scored, from a stand-in (4 floats a
    vertex and its occupancy, ~70 MB at 160³, on ``device``) built from its bool mask and let go, and held a bit a
    pixel until scored, so one stand-in and one edit's chunk of footprint bits are alive at a time however many
    edits are masked (each stand-in had been held to the end, all at once: ~4 GB for 60 masked edits at 160³; each
    edit's whole ring of bits, 2.8 GB for 60 at 360 views of 1,024²). The numbers are those of the whole rings
    (``kept_fraction`` the exact ratio rounded to float32, which a float32 mean over a ring past 2^24 pixels had
    missed in its last bits).
    ``on_ring(name, i, render)`` gets each ring render (H, W, 3), to save it, in that order: the first chunk's
    views of ``initial`` (name None), then of each edit in ``edits``' order, then the next chunk's, and so on.

    The ring renders (and the masks' footprints) run on ``device`` (None: where ``initial`` is); ``initial`` moves
    there once, each edit's grid is there, with its occupancy, only while its views of one chunk render (the grid
    given stays where it is). The scorers run where they were loaded. A ring render with a NaN or infinite
    pixel (a diverged grid) is a ValueError naming the grid, as are two edits of one name and, before any render,
    a masked edit whose grid or mask does not fit ``initial``'s vertices and a source text or prompt longer than
    CLIP's text model reads.
    Progress: ("evaluate", i, :func:`evaluation_steps`), one step per view rendered, footprinted or scored, info
    carrying the pass ("stage") and the peak memory so far; cancellation is checked before each of them.
    """
    if not edits:
        raise ValueError("nothing to evaluate: no edits given")
    names = [sample.name for sample in edits]
    if repeated := sorted({name for name in names if names.count(name) > 1}):  # on_ring tells them by name
        raise ValueError(f"edit names must differ (their renders are saved by name): {', '.join(map(repr, repeated))} "
                         "given more than once")
    if fid is not None and input_images is not None and (  # before any render: a torch.cat or TorchScript error
            input_images.dim() != 4 or input_images.shape[-1] != 3 or len(input_images) < 2):  # had come after
        raise ValueError("FID_input needs at least 2 input images shaped (N, H, W, 3), got "
                         f"{tuple(input_images.shape)}")
    for sample in edits:  # before any render: each had been found only when its edit's turn came
        if sample.mask is not None and sample.grid.resolution != initial.resolution:
            raise ValueError(f"edit {sample.name!r}: a masked edit must share the initial grid's resolution "
                             f"{initial.resolution}, got {sample.grid.resolution}")
        if sample.mask is not None and tuple(sample.mask.shape) != initial.resolution:
            raise ValueError(f"edit {sample.name!r}: its mask of shape {tuple(sample.mask.shape)} does not fit the "
                             f"grid's {initial.resolution} vertices")
    device = resolve_device(device if device is not None else initial.bbox_min.device)
    memory = PeakMemory(device).start()
    initial = initial.to(device)
    source = source_text(object_name)
    centre = initial.orbit_centre()
    total = evaluation_steps(edits, config, fid, input_images)
    done = 0

    def step(views: int, stage: str) -> None:
        nonlocal done
        done += views
        callbacks.progress(Progress("evaluate", done, total, info={"stage": stage, **memory.info()}))

    def per_view(stage: str) -> Callbacks:
        """Callbacks of a pass reporting each view as it is done (ring renders, mask footprints)."""
        memory.peak_bytes()  # read before a ring's renders reset the counter
        return Callbacks(on_progress=lambda report: step(1, stage), should_cancel=callbacks.should_cancel)

    def check_cancel() -> None:
        callbacks.check_cancel("evaluate")

    def per_batch(stage: str) -> AfterBatch:
        """The hook of a scoring pass about to start: a cancellation is honoured now and after each batch,
        whose images are steps."""
        callbacks.check_cancel("evaluate")

        def batch_done(images: int) -> None:
            step(images, stage)
            callbacks.check_cancel("evaluate")
        return batch_done

    cameras = turntable_cameras(config.views, config.elevation, config.size, centre=centre)

    def ring(grid: VoxelGrid, label: str, views: range) -> Iterator[tuple[int, torch.Tensor]]:
        """(i, view i) of ``grid``'s ring for each i of ``views``, rendered on ``device`` with one occupancy:
        ``initial`` is there; an edit's grid is put there as a grid sharing its box and backbone (its features not
        copied where they are there already), let go with its occupancy once the views are rendered."""
        if grid is not initial:
            grid = grid.like(grid.features.detach().to(device))
        rendered = iter_views(grid, cameras[views.start:views.stop], callbacks=per_view("ring renders"),
                              device=device)
        for i, view in enumerate(rendered, views.start):
            yield i, _finite_view(view, label, i, config.views)

    texts = clip.text_embeddings([source] + [edit_prompt(e.prompt) for e in edits])  # a text too long: before renders
    input_features = None
    if fid is not None and input_images is not None:
        input_features = fid.features(input_images, per_batch("FID"))
    ring_names = [None] + [sample.name for sample in edits]

    def scorers() -> list[Scorer]:
        """CLIP, then FID if given, as one grid's :class:`ViewBatches` scores its views."""
        clip_scorer = (clip.image_embeddings, clip.batch_size, per_batch("CLIP"))
        return [clip_scorer] if fid is None else [clip_scorer, (fid.features, fid.batch_size, per_batch("FID"))]

    batches = [ViewBatches(scorers(), check_cancel) for _ in ring_names]
    kept = [Preservation(sample, initial, config, centre, per_view("mask footprints")) for sample in edits]

    def take(k: int, i: int, view: torch.Tensor) -> torch.Tensor:
        """Ring k's view i (0: ``initial``'s), given to CLIP, FID and ``on_ring``."""
        batches[k].add(view)
        if on_ring is not None:
            on_ring(ring_names[k], i, view)
        return view

    recon_ring = ring(initial, "the initial grid", range(config.views))  # its occupancy built once
    for chunk in ring_chunks(config.views, config.size):  # G_i's chunk rendered once, each edit's scored against it
        recon_views = [take(0, i, next(recon_ring)[1]) for i in chunk]
        for k, (sample, scores) in enumerate(zip(edits, kept), 1):
            for i, view in ring(sample.grid, f"edit {sample.name!r}", chunk):
                scores.add(take(k, i, view), recon_views[i - chunk.start])
        del recon_views  # (before the next chunk's are rendered)
    recon_clip, *recon_features = batches[0].results()
    rows = []
    for k, sample in enumerate(edits):
        edit_clip, *edit_features = batches[k + 1].results()
        row = {"name": sample.name, "prompt": sample.prompt, "mode": "local" if sample.mask is not None else "global",
               "clip_sim": clip_similarity(edit_clip, texts[k + 1]),
               "clip_dir": clip_direction(edit_clip, recon_clip, texts[k + 1], texts[0])}
        if recon_features:
            row["fid_rec"] = fid_from_features(edit_features[0], recon_features[0])
            row["fid_input"] = (fid_from_features(edit_features[0], input_features) if input_features is not None
                                else None)
        rows.append(row | kept[k].result())
    return Evaluation(rows)


def ring_chunks(views: int, size: int) -> list[range]:
    """A ring's ``views`` of ``size``², in order, in chunks of about one size, each of at most
    :data:`RING_CHUNK_BYTES` of G_i's float views (one view at least): :func:`evaluate` puts each edit's grid on the
    render device once a chunk, and :func:`iter_mask_footprint` builds a masked edit's stand-in once a chunk."""
    most = max(1, RING_CHUNK_BYTES // (size * size * 3 * 4))
    chunks = -(-views // most)
    return [range(j * views // chunks, (j + 1) * views // chunks) for j in range(chunks)]


def _finite_view(view: torch.Tensor, label: str, i: int, views: int) -> torch.Tensor:
    """Ring view ``i`` (H, W, 3) if every pixel is finite, else a ValueError naming the grid (``label``).

    A diverged grid renders NaN, which the scores would read as a masked-out view (PSNR / SSIM),
    black (CLIP) or nothing (FID): it would pass for a perfect edit.
    """
    if not bool(torch.isfinite(view).all()):
        raise ValueError(f"{label}: ring view {i} of {views} has NaN or infinite pixels (the grid has diverged); it "
                         "cannot be scored")
    return view


def preservation(images: Iterable[torch.Tensor], recon: Iterable[torch.Tensor], sample: EditSample,
                 initial: VoxelGrid, config: EvaluateConfig, centre: torch.Tensor | None = None,
                 callbacks: Callbacks = Callbacks()) -> dict:
    """PSNR / SSIM of an edit's ring renders against G_i's, outside the mask's footprint (whole image if no mask).

    ``images``, ``recon``: the (H, W, 3) views of the ring looking at ``centre`` (3,), G_i's ``orbit_centre()``
    (None: computed here; an evaluation of several edits passes the one it rendered them with), as (V, H, W, 3)
    tensors or one at a time. See :class:`Preservation`, which scores them view by view.
    """
    scores = Preservation(sample, initial, config, centre, callbacks)
    for image, initial_view in zip(images, recon):
        scores.add(image, initial_view)
    return scores.result()


class Preservation:
    """:func:`preservation` of one edit, its views and G_i's handed over a pair at a time (:func:`evaluate` renders
    them a chunk of views at a time). Each view is scored on its own: the values of the whole ring at once, bit for
    bit, but SSIM's float64 filter buffers are one view's (~130 times its float pixels: a whole ring at once had
    peaked at 3.2 GB for 32 views of 256²). A masked edit's footprints are rendered a chunk of views at a time
    (:func:`ring_chunks`') as the chunk's first pair comes, from one stand-in let go before that pair is scored
    (:func:`iter_mask_footprint`, given ``callbacks``: progress per view, cancellation): between views an edit holds
    its bool mask and the rest of one chunk's footprint bits, not a stand-in."""

    def __init__(self, sample: EditSample, initial: VoxelGrid, config: EvaluateConfig,
                 centre: torch.Tensor | None = None, callbacks: Callbacks = Callbacks()):
        if sample.mask is None:
            self.footprints, self.region = itertools.repeat(None), "whole image"
        else:
            self.footprints = iter_mask_footprint(initial, sample.mask, config.views, config.elevation, config.size,
                                                  initial.orbit_centre() if centre is None else centre, callbacks)
            self.region = "outside mask"
        self.psnr_values, self.ssim_values, self.kept, self.pixels = [], [], 0, 0

    def add(self, image: torch.Tensor, initial_view: torch.Tensor) -> None:
        """Scores the edit's next (H, W, 3) view against G_i's."""
        footprint = next(self.footprints)
        keep = torch.ones(image.shape[:2], dtype=torch.bool) if footprint is None else ~footprint
        self.psnr_values.append(psnr(image[None], initial_view[None], keep=keep[None]))
        self.ssim_values.append(ssim(image[None], initial_view[None], keep=keep[None]))
        self.kept, self.pixels = self.kept + int(keep.sum()), self.pixels + keep.numel()

    def result(self) -> dict:
        kept_fraction = float(torch.tensor(self.kept / self.pixels, dtype=torch.float32))  # exact, rounded to float32
        return {"psnr": _finite_mean(torch.cat(self.psnr_values)), "ssim": _finite_mean(torch.cat(self.ssim_values)),
                "region": self.region, "kept_fraction": kept_fraction}


def _finite_mean(values: torch.Tensor) -> float | None:
    """Mean over views with a defined value (a view with no kept pixel is NaN and left out); None if none."""
    defined = values[~torch.isnan(values)]
    if defined.numel() == 0:
        return None
    return float(defined.clamp(max=PSNR_CAP_DB).mean())


def mean_by_mode(rows: Sequence[dict]) -> dict:
    """Per mode (local / global / all), the mean of each metric over the rows that have it."""
    out = {}
    for mode in ("local", "global", "all"):
        chosen = [r for r in rows if mode == "all" or r.get("mode") == mode]
        if not chosen:
            continue
        means = {"count": len(chosen)}
        for metric in METRICS:
            values = [r[metric] for r in chosen if isinstance(r.get(metric), (int, float)) and math.isfinite(r[metric])]
            means[metric] = sum(values) / len(values) if values else None
        out[mode] = means
    return out


def smoke_test_roles(clip: ClipScorer, fid: FeatureExtractor | None = None) -> list[str]:
    """Which of the scorers ("CLIP", "FID") are :mod:`voxe_core.tiny_eval`'s random-weight smoke-test models (their
    mark, :data:`~voxe_core.constants.SMOKE_TEST_MARK`, whatever their folder or file is called)."""
    return [role for role, marked in (("CLIP", getattr(clip.model.config, SMOKE_TEST_MARK, False)),
                                      ("FID", getattr(getattr(fid, "module", None), SMOKE_TEST_MARK, False)))
            if marked is True]


def format_table(rows: Sequence[dict], extra_columns: Sequence[str] = (), smoke_test: Sequence[str] = ()) -> str:
    """A Markdown table: one line per row, then the local / global / all means.

    ``smoke_test``: the scorers ("CLIP", "FID") that were the random-weight smoke-test models, said on a line above
    the table (which is read and passed on without what made it: its numbers had passed for CLIP and FID scores)."""
    columns = [*extra_columns, "prompt", "mode", *METRICS]

    def cell(value) -> str:
        if value is None:
            return "–"
        if isinstance(value, float):
            return f"{value:.4f}" if abs(value) < 10 else f"{value:.2f}"
        return " ".join(str(value).split()).replace("|", "\\|")  # a line break would end the row

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    if smoke_test:
        what = "is a random-weight smoke-test model" if len(smoke_test) == 1 else "are random-weight smoke-test models"
        lines[:0] = [f"**SMOKE TEST**: {' and '.join(smoke_test)} {what}: these numbers prove the plumbing only and say "
                     "nothing about the edits' quality.", ""]
    lines += ["| " + " | ".join(cell(row.get(c)) for c in columns) + " |" for row in rows]
    for mode, means in mean_by_mode(rows).items():
        label = {c: "" for c in extra_columns} | {"prompt": f"**mean ({means['count']})**", "mode": mode}
        lines.append("| " + " | ".join(cell(label.get(c, means.get(c))) for c in columns) + " |")
    return "\n".join(lines) + "\n"


__all__ = [
    "INCEPTION_URL", "PAPER_PROMPTS", "METRICS",
    "ClipScorer", "EditSample", "EvaluateConfig", "Evaluation", "FeatureExtractor", "InceptionFeatures",
    "ProtocolEdit", "check_source_text_length", "clip_direction", "clip_similarity", "evaluate", "evaluation_steps",
    "feature_statistics",
    "fid_from_features", "format_table", "frechet_distance", "iter_mask_footprint", "mask_footprint", "mean_by_mode",
    "paper_protocol", "Preservation", "preservation", "render_ring", "smoke_test_roles", "source_text", "ViewBatches",
]
