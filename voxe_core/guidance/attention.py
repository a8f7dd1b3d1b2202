"""Cross-attention capture (SPEC §3): a diffusers attention processor that records softmax(QKᵀ/√d) per token.

One UNet pass on the noised latent of a render at a fixed timestep with the
conditional prompt only; :class:`CrossAttentionCapture` is installed on the
cross-attention (``attn2``) layers only for the duration of the pass
(:func:`capturing`), every other layer keeps PyTorch SDPA (``AttnProcessor2_0``).
"""

from __future__ import annotations

import contextlib
import math
from typing import Iterator

import torch
import torch.nn.functional as F

from voxe_core.devices import full_precision


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

    def average(self) -> torch.Tensor:
        """The recorded maps of the first image averaged over layers: (tokens, h, w) at the finest layer's size.

        Coarser layers are bilinearly upsampled first, which keeps each pixel's sum
        over tokens at 1. Raises ``ValueError`` when no layer passed the filter.
        """
        if not self.maps:
            available = sorted({hw[0] for hw in self.seen_resolutions if hw[0] == hw[1]})
            raise ValueError(
                f"no cross-attention layer has a {self.resolution_filter}x{self.resolution_filter} query map; "
                f"this model has {sorted(self.seen_resolutions)} (use one of {available} or None)"
            )
        size = max((m.shape[1], m.shape[2]) for m in self.maps)
        total = torch.zeros(1, self.maps[0].shape[-1], *size, device=self.maps[0].device, dtype=torch.float32)
        for m in self.maps:
            m = m.permute(0, 3, 1, 2)  # (1, tokens, h, w)
            if tuple(m.shape[-2:]) != size:
                m = F.interpolate(m, size=size, mode="bilinear", align_corners=False)
            total += m
        return total[0] / len(self.maps)


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

        with full_precision(query):  # (a caller's bf16 autocast had run the bmm and softmax in bf16: maps 3% off)
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


@contextlib.contextmanager
def capturing(unet, store: AttentionStore) -> Iterator[CrossAttentionCapture]:
    """``unet``'s cross-attention (``attn2``) layers record into ``store`` inside the block; the processors are restored after."""
    original = unet.attn_processors
    capture = CrossAttentionCapture(store)
    unet.set_attn_processor({name: (capture if name.endswith("attn2.processor") else proc) for name, proc in original.items()})
    try:
        yield capture
    finally:
        unet.set_attn_processor(original)
