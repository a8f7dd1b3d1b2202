"""Score Distillation Sampling over Stable Diffusion (SPEC §2): :class:`StableDiffusionGuidance`.

SDS (SPEC §2). For renders ``x`` in [0, 1]:

1. resize to ``resolution`` (bilinear, ``align_corners=False``), map to [-1, 1];
2. encode with the VAE *with* gradient; the latent is a *sample* of the VAE
   posterior (``latent_dist.sample(generator)``, as the authors' code does),
   times ``vae.config.scaling_factor`` (0.18215 for SD 1.x/2.x);
3. ``z_t = sqrt(ᾱ_t)·z + sqrt(1 − ᾱ_t)·ε`` with ``ᾱ`` from the checkpoint's
   scheduler and ``ε ~ N(0, I)``;
4. the UNet on the batch ``[unconditional, conditional]`` under
   ``torch.no_grad()`` (its backward pass is never needed);
5. classifier-free guidance ``ε̂ = ε_u + s·(ε_c − ε_u)``;
6. ``grad = w(t)·(ε̂ − ε)`` with ``w(t) = 1 − ᾱ_t``, computed in float32,
   non-finite entries set to 0 (their share is the ``nonfinite_fraction``
   diagnostic: a float16 UNet that overflows everywhere leaves no gradient at all).

The UNet's output is read as its scheduler's ``prediction_type`` says: ε
(``"epsilon"``, SD 1.x and SD 2 base) as it is, v (``"v_prediction"``, e.g.
stabilityai/stable-diffusion-2-1 at 768²) converted to ε first,
``ε̂ = √ᾱ_t·v + √(1 − ᾱ_t)·z_t`` (from ``v = √ᾱ·ε − √(1 − ᾱ)·z`` and
``z_t = √ᾱ·z + √(1 − ᾱ)·ε``), and x̂₀ (``"sample"``) likewise,
``ε̂ = (z_t − √ᾱ_t·x̂₀) / √(1 − ᾱ_t)``; any other type is refused, naming the
model, when the guidance is built (:data:`PREDICTION_TYPES`), as is a UNet the step above cannot drive
(:func:`check_text_to_image`: an inpainting or SD-XL UNet, another text encoder's width).

On CUDA the UNet and VAE run in float16 (``from_pretrained``'s default),
``channels_last``, with PyTorch SDPA attention; the SDS step's UNet forward
replays from a CUDA graph (:mod:`voxe_core.guidance.cuda_graphs`) and its VAE
encoder runs compiled (:mod:`voxe_core.guidance.compiled`). Timing synchronisation
(``sync_timing``) is off unless asked for: without it the ``*_ms`` diagnostics
measure host-side dispatch only.

The gradient is injected with the standard surrogate
``loss = (grad.detach() * latents).sum() / B``: its derivative with respect to the
latents is exactly ``grad / B`` (the mean over the batch's B views, as the authors'
``SpecifyGradient``), so ``loss.backward()`` sends it through the VAE encoder into
whatever made the images. The *value* of this loss means nothing; log the diagnostics
instead.

Cross-attention maps (SPEC §3) come from one more UNet pass with a capturing
processor (:mod:`voxe_core.guidance.attention`).
"""

from __future__ import annotations

import math
import numbers
import os
import time
import warnings
from typing import Callable, Literal, Sequence

import torch
import torch.nn.functional as F

from voxe_core.constants import DEFAULT_ATTENTION_TIMESTEP, DEFAULT_GUIDANCE_SCALE, SDS_MODEL_ID
from voxe_core.devices import full_precision, synchronize
from voxe_core.guidance import Diagnostics
from voxe_core.guidance.attention import AttentionStore, capturing
from voxe_core.guidance.compiled import CompiledEncoder
from voxe_core.guidance.cuda_graphs import GraphedEncoder, GraphedUNet
from voxe_core.guidance.loading import load_stable_diffusion, local_path
from voxe_core.guidance.prompts import tokens_read, word_token_spans


PREDICTION_TYPES = ("epsilon", "v_prediction", "sample")
_EMBEDDING_CACHE_SIZE = 256  # prompts whose text embeddings a guidance keeps


def prediction_type(scheduler, model_id: str = "") -> str:
    """The scheduler's ``prediction_type`` (``"epsilon"`` when it names none); ValueError naming ``model_id`` for one
    SDS cannot use."""
    kind = getattr(getattr(scheduler, "config", None), "prediction_type", None) or "epsilon"
    if kind not in PREDICTION_TYPES:
        raise ValueError(
            f"the scheduler of {model_id or 'the model'} predicts {kind!r}; SDS here supports prediction_type "
            f"{', '.join(map(repr, PREDICTION_TYPES))} (convert the checkpoint or pick another model)"
        )
    return kind


def check_text_to_image(unet, vae, text_encoder, model_id: str = "") -> None:
    """ValueError naming ``model_id`` for parts SDS here cannot drive as it calls them: a UNet whose input or output
    is not the VAE's latents (an inpainting model's 9 channels), one that needs conditioning besides the text (SD-XL's
    ``addition_embed_type``, class labels), or one whose cross-attention reads another width than the text encoder
    gives. Such a model had loaded and failed at the first SDS step with a TypeError or a shape error naming none."""
    config, name = unet.config, model_id or "the model"
    latent = vae.config.latent_channels
    if (config.in_channels, config.out_channels) != (latent, latent):
        raise ValueError(f"the UNet of {name} maps {config.in_channels} channels to {config.out_channels}, its VAE's "
                         f"latents have {latent}: not a text-to-image Stable Diffusion (an inpainting or depth model?)")
    extra = {key: value for key in ("addition_embed_type", "class_embed_type", "num_class_embeds")
             if (value := getattr(config, key, None)) is not None}
    if extra:
        raise ValueError(f"the UNet of {name} needs conditioning besides the text "
                         f"({', '.join(f'{key}={value!r}' for key, value in extra.items())}: SD-XL's time and size "
                         "embeddings, an upscaler's class labels), which SDS here does not give; use a Stable "
                         "Diffusion 1.x / 2.x model")
    dims = config.cross_attention_dim
    dims = list(dims) if isinstance(dims, (list, tuple)) else [dims]
    width = getattr(config, "encoder_hid_dim", None) or dims[0]
    if set(dims) != {dims[0]} or width != text_encoder.config.hidden_size:
        raise ValueError(f"the UNet of {name} reads text embeddings {width} wide (cross_attention_dim "
                         f"{config.cross_attention_dim}), its text encoder gives {text_encoder.config.hidden_size}: "
                         "the parts are of different models")


def epsilon_from_output(output: torch.Tensor, noisy: torch.Tensor, alpha_bar: torch.Tensor, kind: str) -> torch.Tensor:
    """The noise estimate ε̂ from a UNet output of prediction type ``kind`` at ``z_t = noisy`` (float32).

    Examples:
        >>> a, z, eps = torch.tensor(0.64), torch.ones(1), torch.full((1,), 2.0)
        >>> noisy = a.sqrt() * z + (1 - a).sqrt() * eps
        >>> v = a.sqrt() * eps - (1 - a).sqrt() * z
        >>> epsilon_from_output(v, noisy, a, "v_prediction").tolist()
        [2.0]
        >>> epsilon_from_output(z, noisy, a, "sample").tolist()
        [2.0]
    """
    if kind == "epsilon":
        return output
    if kind == "v_prediction":
        return alpha_bar.sqrt() * output + (1.0 - alpha_bar).sqrt() * noisy
    if kind == "sample":
        return (noisy - alpha_bar.sqrt() * output) / (1.0 - alpha_bar).sqrt()
    raise ValueError(f"unknown prediction_type {kind!r}; expected one of {PREDICTION_TYPES}")


def attention_resolution(down_block_types: Sequence[str], latent_side: int) -> int:
    """The query-map side of the cross-attention layers the refinement reads by default (``resolution_filter="auto"``):
    those of the UNet's coarsest down block with cross-attention, which halves the latent side for each down block
    with cross-attention before it. A quarter of the latent side on SD 1.x / 2.x (three such blocks): SPEC's 16×16 for
    SD-1.4's 64×64 latents, 24×24 for a 768-px SD 2.x's 96×96, whose layers have no 16×16 level.

    Examples:
        >>> sd = ["CrossAttnDownBlock2D"] * 3 + ["DownBlock2D"]
        >>> attention_resolution(sd, 64), attention_resolution(sd, 96)
        (16, 24)
        >>> attention_resolution(["CrossAttnDownBlock2D", "DownBlock2D"], 16)  # the tiny smoke-test model
        16
    """
    halvings = sum("CrossAttn" in kind for kind in down_block_types) - 1
    return math.ceil(latent_side / 2 ** max(halvings, 0))


def _check_graph_device(cuda_graphs: bool, device) -> None:
    if cuda_graphs and torch.device(device).type != "cuda":
        raise ValueError(f"cuda_graphs needs a CUDA device; this guidance is on {torch.device(device)}")


def _check_resolution(resolution) -> None:
    """A ``resolution`` override is a positive whole number of pixels: 0 had silently meant the model's own, a
    negative one failed at the first SDS step ("Input and output sizes should be greater than 0"), 2.5 ran as 2."""
    if resolution is not None and (isinstance(resolution, bool) or not isinstance(resolution, numbers.Integral)
                                   or resolution < 1):
        raise ValueError(f"resolution must be a positive whole number of pixels (None: the model's), got {resolution!r}")


def _sync(guidance: "StableDiffusionGuidance") -> None:
    if guidance.sync_timing:
        synchronize(guidance.device)


class StableDiffusionGuidance:
    """:class:`Guidance` over a Stable Diffusion checkpoint (any diffusers-layout SD 1.x / 2.x).

    Build it with :meth:`from_pretrained`. All weights are frozen
    (``requires_grad_(False)``, eval mode); gradients flow only through the
    VAE encoder into the input images.
    """

    def __init__(
        self,
        unet,
        vae,
        text_encoder,
        tokenizer,
        scheduler,
        *,
        model_id: str = "",
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        resolution: int | None = None,
        sync_timing: bool = False,
        cuda_graphs: bool = False,
        compile_encoder: bool = False,
    ):
        from diffusers.models.attention_processor import AttnProcessor2_0

        self.prediction_type = prediction_type(scheduler, model_id)  # refuse an unusable model before moving weights
        check_text_to_image(unet, vae, text_encoder, model_id)
        _check_graph_device(cuda_graphs, device)
        _check_resolution(resolution)

        self.model_id = model_id
        self.device = torch.device(device)
        self.dtype = dtype
        self.unet = unet
        self.vae = vae
        self.text_encoder = text_encoder
        self.tokenizer = tokenizer
        self.scheduler = scheduler
        for module in (unet, vae, text_encoder):
            if next(module.parameters()).dtype != dtype:
                module.to(dtype=dtype)
            module.to(device=self.device)
            module.eval()
            module.requires_grad_(False)
        # PyTorch SDPA everywhere (diffusers' default on torch >= 2); the
        # attention-map pass swaps the cross-attention layers temporarily.
        self.unet.set_attn_processor(AttnProcessor2_0())
        if self.device.type == "cuda":  # NHWC convolutions: faster tensor-core kernels for the fp16 UNet / VAE
            self.unet.to(memory_format=torch.channels_last)
            self.vae.to(memory_format=torch.channels_last)

        self.vae_scale_factor = 2 ** (len(vae.config.block_out_channels) - 1)
        self.resolution = int(resolution or unet.config.sample_size * self.vae_scale_factor)
        self.latent_scale = float(vae.config.scaling_factor)
        shift = getattr(vae.config, "shift_factor", None)
        self.latent_shift = float(shift) if shift is not None else 0.0
        self.num_train_timesteps = int(scheduler.config.num_train_timesteps)
        self.alphas_cumprod = scheduler.alphas_cumprod.to(device=self.device, dtype=torch.float32)
        self.max_length = tokens_read(tokenizer, text_encoder.config.max_position_embeddings)
        self._embedding_cache: dict[str, torch.Tensor] = {}
        # Synchronise CUDA around the timed parts so the *_ms diagnostics are
        # true device times (a few syncs per step, the benchmarks ask for it);
        # off, the timings only measure host-side dispatch.
        self.sync_timing = bool(sync_timing)
        # The SDS step's UNet forward replayed from a CUDA graph (voxe_core.guidance.cuda_graphs); its VAE encoder
        # compiled (voxe_core.guidance.compiled: inductor fuses what a graph would launch at once), else graphed too.
        self._encoder = CompiledEncoder(self._encode_moments) if compile_encoder else self._encode_moments
        self._graphed_unet = GraphedUNet(self._eager_unet) if cuda_graphs else None
        self._graphed_encoder = GraphedEncoder(self._encoder) if cuda_graphs and not compile_encoder else None

    # ------------------------------------------------------------------ loading

    @classmethod
    def from_pretrained(
        cls,
        model: str | os.PathLike = SDS_MODEL_ID,
        device: str | torch.device | None = None,
        dtype: torch.dtype | None = None,
        local_files_only: bool | None = None,
        *,
        revision: str | None = None,
        resolution: int | None = None,
        sync_timing: bool = False,
        cuda_graphs: bool | None = None,
        compile_encoder: bool | None = None,
        on_message: Callable[[str], None] | None = None,
        name: str | None = None,
    ) -> "StableDiffusionGuidance":
        """Load UNet, VAE, CLIP text encoder, tokenizer and noise schedule of ``model``.

        ``model`` is a hub id (resolved through the Hugging Face cache, see
        ``HF_HOME``) or a local folder in the diffusers layout. ``device``
        defaults to CUDA when available, else CPU; ``dtype`` to float16 on CUDA
        and float32 elsewhere. ``local_files_only`` defaults to True when the
        environment sets ``HF_HUB_OFFLINE=1``. Raises
        :class:`ModelNotAvailableError` (naming the model and how to provide it)
        when the weights cannot be found; never substitutes another model.
        ``on_message`` hears "downloading <model> (N GB)" before a first-use download.
        ``name`` is the ``model_id`` an edit checkpoint records and its resume must match (default: ``model``, with
        ``@revision`` when one is given for a hub id; a folder has no revisions, loading ignores it there): a caller
        that resolved a name to a folder of its own machine (the worker's ``tiny``) passes the name, which is the same
        on every machine.
        ``resolution`` overrides the image size derived from the configs
        (``unet.sample_size · 2^(len(vae.block_out_channels) − 1)``, 512 for SD).
        ``cuda_graphs`` replays the SDS step's UNet (and VAE encoder, unless compiled) from CUDA graphs (default:
        on CUDA; :mod:`voxe_core.guidance.cuda_graphs` has the measurement). ``compile_encoder`` compiles the SDS
        step's VAE encoder with ``torch.compile`` (default: on CUDA; :mod:`voxe_core.guidance.compiled`).
        """
        device = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
        if dtype is None:
            dtype = torch.float16 if device.type == "cuda" else torch.float32
        if cuda_graphs is None:
            cuda_graphs = device.type == "cuda"
        if compile_encoder is None:
            compile_encoder = device.type == "cuda"
        _check_graph_device(cuda_graphs, device)  # before the weights load
        _check_resolution(resolution)
        model_str = os.fspath(model)
        unet, vae, text_encoder, tokenizer, scheduler = load_stable_diffusion(
            model_str, dtype, local_files_only, revision, on_message)
        hub_revision = revision if local_path(model_str) is None else None
        return cls(
            unet, vae, text_encoder, tokenizer, scheduler,
            model_id=name or (f"{model_str}@{hub_revision}" if hub_revision else model_str), device=device, dtype=dtype,
            resolution=resolution, sync_timing=sync_timing, cuda_graphs=cuda_graphs, compile_encoder=compile_encoder,
        )

    # ------------------------------------------------------------------ text

    def _tokenize(self, prompts: list[str]) -> torch.Tensor:
        """Token ids (N, max_length), padded; ValueError for a prompt longer than the text encoder reads (it was cut
        off there, and an edit word beyond the cut found nowhere, only when the refinement looked for it)."""
        ids = self.tokenizer(list(prompts), padding="max_length", max_length=self.max_length).input_ids  # uncut
        for prompt, tokens in zip(prompts, ids):
            if len(tokens) > self.max_length:
                raise ValueError(f"the prompt {prompt!r} is {len(tokens)} tokens; the text encoder of "
                                 f"{self.model_id or 'this model'} reads {self.max_length}, its start and end tokens "
                                 "included: shorten it")
        return torch.tensor(ids)

    @torch.no_grad()
    def encode_prompts(self, prompts: list[str]) -> torch.Tensor:
        """CLIP last hidden states ``(len(prompts), max_length, D)`` in the model dtype (cached per prompt).

        Computed outside any autocast the caller is in (the SDS step's asks for the empty prompt's): the cache, keyed
        on the prompt alone, serves every later caller of this guidance."""
        if isinstance(prompts, str):
            prompts = [prompts]
        missing = [p for p in dict.fromkeys(prompts) if p not in self._embedding_cache]
        if missing:
            ids = self._tokenize(missing).to(self.device)
            with full_precision(ids):  # autocast off: the text encoder runs in its own dtype
                hidden = dict(zip(missing, self.text_encoder(ids)[0]))
            found = {p: self._embedding_cache.get(p, hidden.get(p)) for p in prompts}
            if len(self._embedding_cache) + len(missing) > _EMBEDDING_CACHE_SIZE:  # bounded: start afresh
                self._embedding_cache.clear()
            self._embedding_cache.update(hidden)
            return torch.stack([found[p] for p in prompts])
        return torch.stack([self._embedding_cache[p] for p in prompts])

    def unconditional_embedding(self) -> torch.Tensor:
        """Embedding ``(1, max_length, D)`` of the empty prompt."""
        return self.encode_prompts([""])

    def token_spans(self, prompt: str, words: Sequence[str]) -> list[int]:
        """Positions in the padded token sequence of ``prompt`` of every occurrence of each word.

        Positions index the token axis of :meth:`cross_attention_maps` (0 is the
        start token). A multi-token word (or phrase such as ``"party hat"``)
        contributes all its sub-token positions; a word occurring several times
        contributes every occurrence. Only whole words count (an occurrence starts
        a word: "shade" is not found in "lampshade"), and only in the prompt's own
        text, before its view word (``"back"`` is not found in ", back view").
        Sorted, without duplicates. Raises ``ValueError`` when a word does not
        occur in the prompt.
        """
        self._tokenize([prompt])  # a prompt longer than the text encoder reads is refused, naming its length
        return word_token_spans(self.tokenizer, prompt, words)

    def content_token_indices(self, prompt: str) -> list[int]:
        """Positions of the prompt's own tokens: excludes start, end and padding tokens."""
        n = len(self.tokenizer(prompt, add_special_tokens=False, truncation=True, max_length=self.max_length - 2).input_ids)
        return list(range(1, 1 + n))

    # ------------------------------------------------------------------ images / latents

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """``(B,3,H,W)`` in [0,1] → ``(B,3,R,R)`` in [-1,1] at the model resolution, model dtype, on device."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images of shape (B, 3, H, W), got {tuple(images.shape)}")
        x = images.to(device=self.device, dtype=torch.float32)
        if x.shape[-2:] != (self.resolution, self.resolution):
            x = F.interpolate(x, size=(self.resolution, self.resolution), mode="bilinear", align_corners=False)
        return (x * 2.0 - 1.0).to(self.dtype)

    def encode_images(self, images: torch.Tensor, generator: torch.Generator | None = None, sample: bool = True) -> torch.Tensor:
        """VAE latents (scaled by ``scaling_factor``), differentiable w.r.t. ``images``.

        ``sample=True`` draws from the posterior (authors' choice, used by
        :meth:`sds_loss`); ``False`` uses its mean.
        """
        from diffusers.models.autoencoders.vae import DiagonalGaussianDistribution

        x = self.preprocess(images)
        moments = self._graphed_or_eager(self._graphed_encoder, self._encoder, x)
        posterior = DiagonalGaussianDistribution(moments)
        latents = posterior.sample(generator=generator) if sample else posterior.mean
        return (latents - self.latent_shift) * self.latent_scale

    def _noise_like(self, latents: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        from diffusers.utils.torch_utils import randn_tensor

        return randn_tensor(tuple(latents.shape), generator=generator, device=self.device, dtype=torch.float32)

    def _expand_text(self, text_embeddings: torch.Tensor, batch: int) -> torch.Tensor:
        text = text_embeddings.to(device=self.device, dtype=self.dtype)
        if text.ndim == 2:
            text = text[None]
        if text.shape[0] == 1 and batch > 1:
            text = text.expand(batch, *text.shape[1:])
        if text.shape[0] != batch:
            raise ValueError(f"{text.shape[0]} text embeddings for a batch of {batch} images")
        return text

    def _timesteps(self, timesteps, batch: int) -> torch.Tensor:
        """Checked where the time steps were drawn (the host, in the edit loop): no device round trip."""
        t = torch.as_tensor(timesteps).long().reshape(-1)
        if t.numel() == 1 and batch > 1:
            t = t.expand(batch)
        if t.numel() != batch:
            raise ValueError(f"{t.numel()} timesteps for a batch of {batch}")
        if bool(((t < 0) | (t >= self.num_train_timesteps)).any()):
            raise ValueError(f"timesteps must lie in [0, {self.num_train_timesteps - 1}], got {t.tolist()}")
        return t.to(self.device, non_blocking=True)

    @property
    def cuda_graphs(self) -> bool:
        """Whether the SDS step's networks replay from CUDA graphs (off for good once a capture was refused)."""
        return self._graphed_unet is not None

    @property
    def compile_encoder(self) -> bool:
        """Whether the SDS step's VAE encoder runs compiled (off for good once a compile was refused)."""
        return isinstance(self._encoder, CompiledEncoder) and self._encoder.compiled is not None

    @property
    def encoder_compile_seconds(self) -> float | None:
        """How long the first SDS step waited for its encoder's compile (None: not compiled, or not yet)."""
        return self._encoder.compile_seconds if isinstance(self._encoder, CompiledEncoder) else None

    def _graphed_or_eager(self, graphed, eager, *args: torch.Tensor) -> torch.Tensor:
        """``graphed(*args)`` where the graphs can run (CUDA graphs on, no autocast: an edit's ``autocast_dtype``
        runs the eager networks), else ``eager(*args)``. A capture the installed libraries refuse turns the graphs
        off for this guidance with a warning rather than failing every edit."""
        if graphed is not None and not torch.is_autocast_enabled(self.device.type):
            try:
                return graphed(*args)
            except torch.cuda.OutOfMemoryError:
                raise  # the eager networks would not fit either
            except RuntimeError as error:
                warnings.warn(f"CUDA graphs turned off for {self.model_id or 'this guidance'}: {error}", RuntimeWarning,
                              stacklevel=3)
                self._graphed_unet, self._graphed_encoder = None, None
        return eager(*args)

    def _eager_unet(self, sample: torch.Tensor, timestep: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        return self.unet(sample, timestep, encoder_hidden_states=text).sample

    def _encode_moments(self, x: torch.Tensor) -> torch.Tensor:
        return self.vae.encode(x).latent_dist.parameters

    @torch.no_grad()
    def sds_grad_on_latents(
        self,
        latents: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
        noise: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, Diagnostics]:
        """The SDS gradient ``w(t)·(ε̂ − ε)`` on (scaled) latents, float32, non-finite → 0.

        ``noise`` (float32, latent-shaped) overrides the draw from ``generator``.
        ε̂ is the guided UNet output read as :attr:`prediction_type` says.
        Diagnostics: ``unet_ms`` (UNet forward incl. CFG, float), ``t_mean``,
        ``w_mean``, ``grad_norm``, ``nonfinite_fraction`` (the share of the gradient's entries that were infinite or
        NaN and set to 0) (0-dim tensors on the device, not read here).
        """
        z = latents.detach().to(device=self.device, dtype=torch.float32)
        batch = z.shape[0]
        t = self._timesteps(timesteps, batch)
        text = self._expand_text(text_embeddings, batch)
        uncond = self._expand_text(self.unconditional_embedding(), batch)
        eps = self._noise_like(z, generator) if noise is None else noise.to(device=self.device, dtype=torch.float32)

        a = self.alphas_cumprod[t].reshape(batch, 1, 1, 1)
        noisy = a.sqrt() * z + (1.0 - a).sqrt() * eps

        _sync(self)
        t0 = time.perf_counter()
        model_in = torch.cat([noisy, noisy]).to(self.dtype)
        out = self._graphed_or_eager(self._graphed_unet, self._eager_unet, model_in, torch.cat([t, t]),
                                     torch.cat([uncond, text]))
        _sync(self)
        unet_ms = (time.perf_counter() - t0) * 1e3

        out_u, out_c = out.float().chunk(2)
        # CFG is linear, so guiding the raw outputs then converting equals converting each first.
        eps_hat = epsilon_from_output(out_u + float(guidance_scale) * (out_c - out_u), noisy, a, self.prediction_type)
        w = 1.0 - a
        grad = w * (eps_hat - eps)
        finite = torch.isfinite(grad)
        grad = torch.where(finite, grad, 0.0)
        # Left on the device for the caller to read when it reports: a read here would hold the host until the UNet
        # has run, with the backward not yet queued.
        diagnostics = {"unet_ms": unet_ms, "t_mean": t.float().mean(), "w_mean": w.mean(), "grad_norm": grad.norm(),
                       "nonfinite_fraction": 1.0 - finite.float().mean()}
        return grad, diagnostics

    def sds_loss_on_latents(
        self,
        latents: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
        noise: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, Diagnostics]:
        """Surrogate ``(grad.detach() * latents).sum() / B``: d loss / d latents = :meth:`sds_grad_on_latents` / B.

        The mean over the batch's B views (as the authors' ``SpecifyGradient`` takes it), so the regulariser's
        weight (200) balances the same SDS whatever ``batch_size``: a sum had made it 200 / B.
        """
        grad, diagnostics = self.sds_grad_on_latents(latents, text_embeddings, timesteps, guidance_scale, generator, noise)
        loss = (grad.detach() * latents.float()).sum() / latents.shape[0]
        return loss, diagnostics

    def sds_loss(
        self,
        images: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, Diagnostics]:
        """SDS for renders ``images`` ``(B,3,H,W)`` in [0,1] (see the module docstring).

        Returns the surrogate loss (backward it; its value is meaningless) and
        diagnostics: ``vae_encode_ms`` (forward only; the VAE backward runs
        later inside ``loss.backward()``), ``unet_ms``, ``sds_ms`` (total) as
        floats, ``t_mean``, ``w_mean``, ``grad_norm``, ``nonfinite_fraction`` as 0-dim device tensors
        (:data:`~voxe_core.guidance.Diagnostics`). ``generator`` drives both the
        VAE posterior sample and the noise.
        """
        _sync(self)
        t0 = time.perf_counter()
        latents = self.encode_images(images, generator=generator, sample=True)
        _sync(self)
        vae_ms = (time.perf_counter() - t0) * 1e3
        loss, diagnostics = self.sds_loss_on_latents(latents, text_embeddings, timesteps, guidance_scale, generator)
        _sync(self)
        diagnostics = {"vae_encode_ms": vae_ms, **diagnostics, "sds_ms": (time.perf_counter() - t0) * 1e3}
        return loss, diagnostics

    # ------------------------------------------------------------------ cross-attention

    @torch.no_grad()
    def cross_attention_maps(
        self,
        image: torch.Tensor,
        prompt: str,
        timestep: int = DEFAULT_ATTENTION_TIMESTEP,
        resolution_filter: int | Literal["auto"] | None = "auto",
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Cross-attention probabilities per token, ``(max_length, h, w)`` float32 on the model device.

        One UNet pass, conditional prompt only, on the VAE-posterior *mean* of
        ``image`` (``(1,3,H,W)`` in [0,1], resized to :attr:`resolution`) noised
        to ``timestep`` with noise from ``generator``. The probabilities
        ``softmax(QKᵀ/√d)`` are averaged over heads and over the cross-attention
        layers whose query map is ``resolution_filter`` × ``resolution_filter``
        (``"auto"``: :func:`attention_resolution`, 16 on SD-1.4;
        all cross-attention layers when ``None``; maps of coarser layers are
        then bilinearly upsampled to the finest, which keeps each pixel's sum
        at 1). Every pixel's probabilities sum to 1 over the token axis. No
        smoothing or upsampling to the render size is applied here.
        """
        if image.ndim == 3:
            image = image[None]
        if image.shape[0] != 1:
            raise ValueError(f"cross_attention_maps takes one image (1, 3, H, W), got {tuple(image.shape)}")
        latents = self.encode_images(image, sample=False).float()
        t = self._timesteps([int(timestep)], 1)
        eps = self._noise_like(latents, generator)
        a = self.alphas_cumprod[t].reshape(1, 1, 1, 1)
        noisy = a.sqrt() * latents + (1.0 - a).sqrt() * eps
        text = self._expand_text(self.encode_prompts([prompt]), 1)

        if resolution_filter == "auto":
            resolution_filter = attention_resolution(self.unet.config.down_block_types, latents.shape[-1])
        store = AttentionStore(tuple(latents.shape[-2:]), resolution_filter)
        with capturing(self.unet, store):
            self.unet(noisy.to(self.dtype), t, encoder_hidden_states=text)
        return store.average()
