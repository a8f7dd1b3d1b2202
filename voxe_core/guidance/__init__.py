"""Diffusion guidance behind one small, model-agnostic interface (paper §3.2, §3.3).

The editing loop only needs three things from a text-to-image diffusion model:
text embeddings, the Score Distillation Sampling (SDS) gradient for a batch of
renders, and (for the spatial refinement) per-token cross-attention maps.
:class:`Guidance` is that interface, the type every stage that takes a model
names. The package holds one module per concept:

* :mod:`~voxe_core.guidance.prompts`: "a render of <text>, <view> view" (SPEC §2);
* :mod:`~voxe_core.guidance.loading`: finding diffusers-layout weights, the clear error when they are missing;
* :mod:`~voxe_core.guidance.attention`: the attention processor that records cross-attention maps (SPEC §3);
* :mod:`~voxe_core.guidance.sds`: :class:`~voxe_core.guidance.sds.StableDiffusionGuidance`, the
  interface over diffusers' Stable Diffusion parts, and its SDS gradient.

This module imports neither torch nor diffusers (only the annotations name torch).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal, Protocol, Sequence, runtime_checkable

from voxe_core.constants import DEFAULT_ATTENTION_TIMESTEP, DEFAULT_GUIDANCE_SCALE

if TYPE_CHECKING:
    import torch


Diagnostics = dict[str, "float | torch.Tensor"]
"""An SDS step's diagnostics by name: host timings as floats, values computed on the device as 0-dim tensors there,
which the caller reads when it reports (one read for all of them, after the step's work is queued)."""


@runtime_checkable
class Guidance(Protocol):
    """What the editing and refinement stages need from a text-to-image diffusion model.

    Every member is one the stages call or read. They also read ``device`` (where to run; default: the grids') and
    ``model_id`` (recorded in the edit's checkpoint; a resume with another is refused) when a guidance has them.
    """

    num_train_timesteps: int
    """Length of the model's training noise schedule (1000 for SD)."""

    dtype: torch.dtype
    """The dtype the model runs in: an edit refuses CPU autocast (bfloat16) for a float16 one, which would fail."""

    def encode_prompts(self, prompts: list[str]) -> torch.Tensor:
        """Text embeddings ``(len(prompts), L, D)`` for conditioning."""
        ...

    def sds_loss(
        self,
        images: torch.Tensor,
        text_embeddings: torch.Tensor,
        timesteps: torch.Tensor,
        guidance_scale: float = DEFAULT_GUIDANCE_SCALE,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, Diagnostics]:
        """Scalar surrogate loss whose latent gradient is ``w(t)(ε̂ − ε) / B`` (the mean over the batch's B renders),
        plus diagnostics."""
        ...

    def cross_attention_maps(
        self,
        image: torch.Tensor,
        prompt: str,
        timestep: int = DEFAULT_ATTENTION_TIMESTEP,
        resolution_filter: int | Literal["auto"] | None = "auto",
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Per-token cross-attention probabilities ``(tokens, h, w)``, summing to 1 per pixel, from the layers whose
        query maps are ``resolution_filter`` square (``"auto"``: the model's choice, SPEC's 16 on SD-1.4; None: all)."""
        ...

    def token_spans(self, prompt: str, words: Sequence[str]) -> list[int]:
        """Token positions (in the padded prompt) of every whole-word occurrence of each word before the view word."""
        ...

    def content_token_indices(self, prompt: str) -> list[int]:
        """Token positions of the prompt's own tokens (no start, end or padding tokens)."""
        ...
