"""Diffusion guidance behind one small, model-agnostic interface (paper §3.2, §3.3).

The editing loop only needs three things from a text-to-image diffusion model:
text embeddings, the Score Distillation Sampling (SDS) gradient for a batch of
renders, and (for the spatial refinement) per-token cross-attention maps.
:class:`Guidance` is that interface; :class:`StableDiffusionGuidance` implements
it over diffusers' ``UNet2DConditionModel`` / ``AutoencoderKL`` and
transformers' CLIP text encoder, for any checkpoint in the diffusers layout
(hub id or local folder). Model-specific code stays in this module, as
diffusers keeps it behind its pipelines.

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
   non-finite entries set to 0.

The gradient is injected with the standard surrogate
``loss = (grad.detach() * latents).sum()``: its derivative with respect to the
latents is exactly ``grad`` (summed, not averaged, over the batch), so
``loss.backward()`` sends ``grad`` through the VAE encoder into whatever made
the images. The *value* of this loss means nothing; log the diagnostics
instead.

Cross-attention maps (SPEC §3). One UNet pass on the noised latent of a render
at a fixed timestep with the conditional prompt only; a capturing attention
processor (:class:`CrossAttentionCapture`, a diffusers ``AttnProcessor``)
is installed on the cross-attention (``attn2``) layers only for the duration
of the pass, every other layer keeps PyTorch SDPA (``AttnProcessor2_0``).
"""

from __future__ import annotations

import math
import os
import time
from typing import Protocol, Sequence, runtime_checkable

import torch
import torch.nn.functional as F

from voxe_core.constants import ATTENTION_MODEL_ID, SDS_MODEL_ID  # noqa: F401 - re-exported

DEFAULT_GUIDANCE_SCALE = 100.0
DEFAULT_ATTENTION_TIMESTEP = 200
RENDER_PREFIX = "a render of"
VIEW_WORDS = ("front", "side", "back", "overhead")

_DIFFUSERS_LAYOUT = "model_index.json, unet/, vae/, text_encoder/, tokenizer/, scheduler/"


class ModelNotAvailableError(RuntimeError):
    """The requested diffusion weights cannot be loaded (not cached, offline, or incomplete)."""


# --------------------------------------------------------------------------- prompts


def view_word(elevation_deg: float, azimuth_deg: float) -> str:
    """The view word for a camera pose, as the authors append to the prompt.

    ``overhead`` when the elevation above the horizon is more than 60°; else by
    azimuth (degrees, any range, 0 = the object's front in the caller's pose
    convention): ``front`` when within ±45° of 0, ``back`` within ±45° of 180,
    ``side`` otherwise. Boundaries (exactly ±45°, ±135°) go to front/back.
    """
    if elevation_deg > 60.0:
        return "overhead"
    az = (float(azimuth_deg) + 180.0) % 360.0 - 180.0  # [-180, 180)
    if abs(az) <= 45.0:
        return "front"
    if abs(az) >= 135.0:
        return "back"
    return "side"


def edit_prompt(user_text: str, view_word: str | None = None) -> str:
    """``"a render of <text>[, <view> view]"`` (SPEC §2).

    Whitespace is collapsed and trailing full stops dropped. The prefix is not
    doubled when the user already wrote it (any case). ``view_word`` is one of
    :data:`VIEW_WORDS` or ``None`` for no view suffix.
    """
    text = " ".join(str(user_text).split()).rstrip(". ").strip()
    if not text:
        raise ValueError("the edit prompt is empty")
    if text.lower() == RENDER_PREFIX:
        raise ValueError("the edit prompt has only the prefix 'a render of' and no content")
    if not text.lower().startswith(RENDER_PREFIX + " "):
        text = f"{RENDER_PREFIX} {text}"
    if view_word is not None:
        if view_word not in VIEW_WORDS:
            raise ValueError(f"unknown view word {view_word!r}; expected one of {VIEW_WORDS}")
        text = f"{text}, {view_word} view"
    return text


# --------------------------------------------------------------------------- interface


@runtime_checkable
class Guidance(Protocol):
    """What the editing and refinement stages need from a text-to-image diffusion model."""

    resolution: int
    """Square image size (pixels) the model works at; renders are resized to it."""

    num_train_timesteps: int
    """Length of the model's training noise schedule (1000 for SD)."""

    def encode_prompts(self, prompts: list[str]) -> torch.Tensor:
        """Text embeddings ``(len(prompts), L, D)`` for conditioning."""
        ...

    def unconditional_embedding(self) -> torch.Tensor:
        """Embedding ``(1, L, D)`` of the empty prompt (classifier-free guidance)."""
        ...

    def sds_loss(
        self,
        images: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Scalar surrogate loss whose latent gradient is ``w(t)(ε̂ − ε)``, plus diagnostics."""
        ...

    def cross_attention_maps(
        self,
        image: torch.Tensor,
        prompt: str,
        timestep: int = DEFAULT_ATTENTION_TIMESTEP,
        resolution_filter: int | None = 16,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Per-token cross-attention probabilities ``(tokens, h, w)``, summing to 1 per pixel."""
        ...

    def token_spans(self, prompt: str, words: Sequence[str]) -> list[int]:
        """Token positions (in the padded prompt) of every occurrence of each word."""
        ...


# --------------------------------------------------------------------------- attention capture


class AttentionStore:
    """Accumulates head-averaged cross-attention probabilities per layer during one UNet pass."""

    def __init__(self, latent_hw: tuple[int, int], resolution_filter: int | None):
        self.latent_hw = latent_hw
        self.resolution_filter = resolution_filter
        self.maps: list[torch.Tensor] = []  # each (B, h, w, tokens), float32
        self.seen_resolutions: set[tuple[int, int]] = set()

    def layer_hw(self, sequence_length: int) -> tuple[int, int]:
        """Spatial size of a layer's query map from its length, given the latent size."""
        h, w = self.latent_hw
        for k in range(8):
            f = 2**k
            lh, lw = math.ceil(h / f), math.ceil(w / f)
            if lh * lw == sequence_length:
                return lh, lw
        side = math.isqrt(sequence_length)
        if side * side == sequence_length:
            return side, side
        raise ValueError(f"cannot infer the query map size of a layer with {sequence_length} positions")

    def wants(self, hw: tuple[int, int]) -> bool:
        self.seen_resolutions.add(hw)
        return self.resolution_filter is None or hw == (self.resolution_filter, self.resolution_filter)

    def add(self, probs: torch.Tensor, heads: int, hw: tuple[int, int]) -> None:
        # probs: (B*heads, h*w, tokens)
        bh, n, tokens = probs.shape
        mean = probs.reshape(bh // heads, heads, n, tokens).mean(dim=1)
        self.maps.append(mean.reshape(bh // heads, hw[0], hw[1], tokens))


class CrossAttentionCapture:
    """Attention processor that records ``softmax(QKᵀ/√d)`` of a cross-attention layer.

    It computes attention explicitly (as diffusers' ``AttnProcessor``), records
    the head-averaged probabilities in float32 in its :class:`AttentionStore`
    when the layer's query map passes the store's resolution filter, and
    returns the same output as the default processor. Layers the filter
    rejects go through the fast SDPA processor unchanged.
    """

    def __init__(self, store: AttentionStore):
        from diffusers.models.attention_processor import AttnProcessor2_0

        self.store = store
        self._fast = AttnProcessor2_0()

    def __call__(
        self,
        attn,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor | None = None,
        attention_mask: torch.Tensor | None = None,
        temb: torch.Tensor | None = None,
        *args,
        **kwargs,
    ) -> torch.Tensor:
        if encoder_hidden_states is None or hidden_states.ndim != 3 or attn.spatial_norm is not None:
            # not a text cross-attention of a transformer block: nothing to record
            return self._fast(attn, hidden_states, encoder_hidden_states, attention_mask, temb, *args, **kwargs)
        hw = self.store.layer_hw(hidden_states.shape[1])
        if not self.store.wants(hw):
            return self._fast(attn, hidden_states, encoder_hidden_states, attention_mask, temb, *args, **kwargs)

        residual = hidden_states
        batch_size, _, _ = encoder_hidden_states.shape
        attention_mask = attn.prepare_attention_mask(attention_mask, encoder_hidden_states.shape[1], batch_size)
        if attn.group_norm is not None:
            hidden_states = attn.group_norm(hidden_states.transpose(1, 2)).transpose(1, 2)
        query = attn.to_q(hidden_states)
        if attn.norm_cross:
            encoder_hidden_states = attn.norm_encoder_hidden_states(encoder_hidden_states)
        key = attn.to_k(encoder_hidden_states)
        value = attn.to_v(encoder_hidden_states)

        query = attn.head_to_batch_dim(query)
        key = attn.head_to_batch_dim(key)
        value = attn.head_to_batch_dim(value)

        scores = torch.bmm(query.float(), key.float().transpose(-1, -2)) * attn.scale
        if attention_mask is not None:
            scores = scores + attention_mask.float()
        probs = scores.softmax(dim=-1)
        self.store.add(probs, attn.heads, hw)

        hidden_states = torch.bmm(probs.to(value.dtype), value)
        hidden_states = attn.batch_to_head_dim(hidden_states)
        hidden_states = attn.to_out[0](hidden_states)
        hidden_states = attn.to_out[1](hidden_states)
        if attn.residual_connection:
            hidden_states = hidden_states + residual
        return hidden_states / attn.rescale_output_factor


# --------------------------------------------------------------------------- Stable Diffusion


def _offline_env() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


def _not_available_message(model: str, cause: BaseException | None) -> str:
    msg = (
        f"Stable Diffusion weights '{model}' are not available offline: download them once with "
        f"`huggingface-cli download {model}` (or `hf download {model}`) on a machine with internet and "
        f"point HF_HOME at that cache, or pass a local folder in the diffusers layout ({_DIFFUSERS_LAYOUT})."
    )
    if cause is not None:
        detail = " ".join(str(cause).split())
        if len(detail) > 400:
            detail = detail[:400] + "..."
        msg += f" Underlying error: {type(cause).__name__}: {detail}"
    return msg


def _loading_errors() -> tuple[type[BaseException], ...]:
    errors: list[type[BaseException]] = [OSError]
    try:
        from huggingface_hub.errors import HFValidationError, HfHubHTTPError

        errors += [HFValidationError, HfHubHTTPError]
    except ImportError:  # pragma: no cover - very old huggingface_hub
        pass
    try:
        import httpx

        errors.append(httpx.HTTPError)
    except ImportError:  # pragma: no cover
        pass
    return tuple(errors)


def _sync(guidance: "StableDiffusionGuidance") -> None:
    if guidance.sync_timing and guidance.device.type == "cuda":
        torch.cuda.synchronize(guidance.device)


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
        sync_timing: bool = True,
    ):
        from diffusers.models.attention_processor import AttnProcessor2_0

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

        self.vae_scale_factor = 2 ** (len(vae.config.block_out_channels) - 1)
        self.resolution = int(resolution or unet.config.sample_size * self.vae_scale_factor)
        self.latent_scale = float(vae.config.scaling_factor)
        shift = getattr(vae.config, "shift_factor", None)
        self.latent_shift = float(shift) if shift is not None else 0.0
        self.num_train_timesteps = int(scheduler.config.num_train_timesteps)
        self.alphas_cumprod = scheduler.alphas_cumprod.to(device=self.device, dtype=torch.float32)
        self.max_length = int(min(tokenizer.model_max_length, text_encoder.config.max_position_embeddings))
        self._embedding_cache: dict[str, torch.Tensor] = {}
        # Synchronise CUDA around the timed parts so the *_ms diagnostics are
        # true device times (a few syncs per step); set False to skip them, the
        # timings then only measure host-side dispatch.
        self.sync_timing = bool(sync_timing)

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
        sync_timing: bool = True,
    ) -> "StableDiffusionGuidance":
        """Load UNet, VAE, CLIP text encoder, tokenizer and noise schedule of ``model``.

        ``model`` is a hub id (resolved through the Hugging Face cache, see
        ``HF_HOME``) or a local folder in the diffusers layout. ``device``
        defaults to CUDA when available, else CPU; ``dtype`` to float16 on CUDA
        and float32 elsewhere. ``local_files_only`` defaults to True when the
        environment sets ``HF_HUB_OFFLINE=1``. Raises
        :class:`ModelNotAvailableError` (naming the model and how to provide it)
        when the weights cannot be found; never substitutes another model.
        ``resolution`` overrides the image size derived from the configs
        (``unet.sample_size · 2^(len(vae.block_out_channels) − 1)``, 512 for SD).
        """
        from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTokenizer

        model_str = os.fspath(model)
        device = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
        if dtype is None:
            dtype = torch.float16 if device.type == "cuda" else torch.float32
        if local_files_only is None:
            local_files_only = _offline_env()
        kwargs = {"local_files_only": bool(local_files_only)}
        if revision is not None:
            kwargs["revision"] = revision

        looks_local = os.path.isabs(model_str) or model_str.startswith(".") or os.path.exists(model_str)
        if looks_local and not os.path.isdir(model_str):
            raise ModelNotAvailableError(_not_available_message(model_str, FileNotFoundError(f"no folder {model_str}")))

        try:
            unet = UNet2DConditionModel.from_pretrained(model_str, subfolder="unet", torch_dtype=dtype, **kwargs)
            vae = AutoencoderKL.from_pretrained(model_str, subfolder="vae", torch_dtype=dtype, **kwargs)
            text_encoder = CLIPTextModel.from_pretrained(model_str, subfolder="text_encoder", dtype=dtype, **kwargs)
            tokenizer = CLIPTokenizer.from_pretrained(model_str, subfolder="tokenizer", **kwargs)
            scheduler = DDIMScheduler.from_pretrained(model_str, subfolder="scheduler", **kwargs)
        except _loading_errors() as exc:
            raise ModelNotAvailableError(_not_available_message(model_str, exc)) from exc
        # transformers >= 5 returns an empty tokenizer instead of failing when
        # the tokenizer files are missing: check it is the real one.
        if len(tokenizer) <= 3 or len(tokenizer) > text_encoder.config.vocab_size + 16:
            raise ModelNotAvailableError(
                _not_available_message(
                    model_str,
                    OSError(f"tokenizer/ has {len(tokenizer)} tokens but the text encoder expects "
                            f"{text_encoder.config.vocab_size}: tokenizer files missing or wrong"),
                )
            )
        return cls(
            unet, vae, text_encoder, tokenizer, scheduler,
            model_id=model_str, device=device, dtype=dtype, resolution=resolution, sync_timing=sync_timing,
        )

    # ------------------------------------------------------------------ text

    def _tokenize(self, prompts: list[str]) -> torch.Tensor:
        return self.tokenizer(
            list(prompts),
            padding="max_length",
            max_length=self.max_length,
            truncation=True,
            return_tensors="pt",
        ).input_ids

    @torch.no_grad()
    def encode_prompts(self, prompts: list[str]) -> torch.Tensor:
        """CLIP last hidden states ``(len(prompts), max_length, D)`` in the model dtype (cached per prompt)."""
        if isinstance(prompts, str):
            prompts = [prompts]
        missing = [p for p in dict.fromkeys(prompts) if p not in self._embedding_cache]
        if missing:
            ids = self._tokenize(missing).to(self.device)
            hidden = self.text_encoder(ids)[0]
            for p, h in zip(missing, hidden):
                if len(self._embedding_cache) > 256:
                    self._embedding_cache.clear()
                self._embedding_cache[p] = h
        return torch.stack([self._embedding_cache[p] for p in prompts])

    def unconditional_embedding(self) -> torch.Tensor:
        """Embedding ``(1, max_length, D)`` of the empty prompt."""
        return self.encode_prompts([""])

    def token_spans(self, prompt: str, words: Sequence[str]) -> list[int]:
        """Positions in the padded token sequence of ``prompt`` of every occurrence of each word.

        Positions index the token axis of :meth:`cross_attention_maps` (0 is the
        start token). A multi-token word (or phrase such as ``"party hat"``)
        contributes all its sub-token positions; a word occurring several times
        contributes every occurrence. Sorted, without duplicates. Raises
        ``ValueError`` when a word does not occur in the prompt.
        """
        if isinstance(words, str):
            words = [words]
        ids = self._tokenize([prompt])[0].tolist()
        positions: set[int] = set()
        for word in words:
            sub = self.tokenizer(word, add_special_tokens=False).input_ids
            if not sub:
                raise ValueError(f"{word!r} has no tokens")
            found = [i for i in range(len(ids) - len(sub) + 1) if ids[i : i + len(sub)] == sub]
            if not found:
                raise ValueError(f"{word!r} does not occur in the prompt {prompt!r} (tokens {self.tokenizer.tokenize(prompt)})")
            for i in found:
                positions.update(range(i, i + len(sub)))
        return sorted(positions)

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
        posterior = self.vae.encode(self.preprocess(images)).latent_dist
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
        t = torch.as_tensor(timesteps, device=self.device).long().reshape(-1)
        if t.numel() == 1 and batch > 1:
            t = t.expand(batch)
        if t.numel() != batch:
            raise ValueError(f"{t.numel()} timesteps for a batch of {batch}")
        if bool(((t < 0) | (t >= self.num_train_timesteps)).any()):
            raise ValueError(f"timesteps must lie in [0, {self.num_train_timesteps - 1}], got {t.tolist()}")
        return t

    @torch.no_grad()
    def sds_grad_on_latents(
        self,
        latents: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
        noise: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """The SDS gradient ``w(t)·(ε̂ − ε)`` on (scaled) latents, float32, non-finite → 0.

        ``noise`` (float32, latent-shaped) overrides the draw from ``generator``.
        Diagnostics: ``unet_ms`` (UNet forward incl. CFG), ``t_mean``,
        ``w_mean``, ``grad_norm``.
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
        out = self.unet(model_in, torch.cat([t, t]), encoder_hidden_states=torch.cat([uncond, text])).sample
        _sync(self)
        unet_ms = (time.perf_counter() - t0) * 1e3

        eps_u, eps_c = out.float().chunk(2)
        eps_hat = eps_u + float(guidance_scale) * (eps_c - eps_u)
        w = 1.0 - a
        grad = torch.nan_to_num(w * (eps_hat - eps), nan=0.0, posinf=0.0, neginf=0.0)
        # one device->host copy for all scalar diagnostics
        t_mean, w_mean, grad_norm = torch.stack([t.float().mean(), w.mean(), grad.norm()]).tolist()
        diagnostics = {"unet_ms": unet_ms, "t_mean": t_mean, "w_mean": w_mean, "grad_norm": grad_norm}
        return grad, diagnostics

    def sds_loss_on_latents(
        self,
        latents: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
        noise: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Surrogate ``(grad.detach() * latents).sum()``: d loss / d latents = :meth:`sds_grad_on_latents`."""
        grad, diagnostics = self.sds_grad_on_latents(latents, text_embeddings, timesteps, guidance_scale, generator, noise)
        loss = (grad.detach() * latents.float()).sum()
        return loss, diagnostics

    def sds_loss(
        self,
        images: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """SDS for renders ``images`` ``(B,3,H,W)`` in [0,1] (see the module docstring).

        Returns the surrogate loss (backward it; its value is meaningless) and
        diagnostics as floats: ``vae_encode_ms`` (forward only; the VAE backward
        runs later inside ``loss.backward()``), ``unet_ms``, ``sds_ms`` (total),
        ``t_mean``, ``w_mean``, ``grad_norm``. ``generator`` drives both the VAE
        posterior sample and the noise.
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
        resolution_filter: int | None = 16,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Cross-attention probabilities per token, ``(max_length, h, w)`` float32 on the model device.

        One UNet pass, conditional prompt only, on the VAE-posterior *mean* of
        ``image`` (``(1,3,H,W)`` in [0,1], resized to :attr:`resolution`) noised
        to ``timestep`` with noise from ``generator``. The probabilities
        ``softmax(QKᵀ/√d)`` are averaged over heads and over the cross-attention
        layers whose query map is ``resolution_filter`` × ``resolution_filter``
        (all cross-attention layers when ``None``; maps of coarser layers are
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

        store = AttentionStore(tuple(latents.shape[-2:]), resolution_filter)
        original = self.unet.attn_processors
        capture = CrossAttentionCapture(store)
        self.unet.set_attn_processor(
            {name: (capture if name.endswith("attn2.processor") else proc) for name, proc in original.items()}
        )
        try:
            self.unet(noisy.to(self.dtype), t, encoder_hidden_states=text)
        finally:
            self.unet.set_attn_processor(original)

        if not store.maps:
            available = sorted({hw[0] for hw in store.seen_resolutions if hw[0] == hw[1]})
            raise ValueError(
                f"no cross-attention layer has a {resolution_filter}x{resolution_filter} query map; "
                f"this model has {sorted(store.seen_resolutions)} (use one of {available} or None)"
            )
        size = max((m.shape[1], m.shape[2]) for m in store.maps)
        total = torch.zeros(1, store.maps[0].shape[-1], *size, device=self.device, dtype=torch.float32)
        for m in store.maps:
            m = m.permute(0, 3, 1, 2)  # (1, tokens, h, w)
            if tuple(m.shape[-2:]) != size:
                m = F.interpolate(m, size=size, mode="bilinear", align_corners=False)
            total += m
        return total[0] / len(store.maps)


__all__ = [
    "ATTENTION_MODEL_ID",
    "AttentionStore",
    "CrossAttentionCapture",
    "DEFAULT_ATTENTION_TIMESTEP",
    "DEFAULT_GUIDANCE_SCALE",
    "Guidance",
    "ModelNotAvailableError",
    "RENDER_PREFIX",
    "SDS_MODEL_ID",
    "StableDiffusionGuidance",
    "VIEW_WORDS",
    "edit_prompt",
    "view_word",
]
