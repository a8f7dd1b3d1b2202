"""The SDS step's VAE encoder compiled with ``torch.compile`` (issue 17; on by default on CUDA, ``compile_encoder=False``
off).

After the CUDA graphs (:mod:`voxe_core.guidance.cuda_graphs`) the VAE encoder was the largest part of an SDS step on
the lent H200: 13.8 ms forward and 19.0 ms backward at 512² in fp16 (bench/results/gpu.json, section i), its
GroupNorm, SiLU and convolutions each a separate pass over 512²×128 activations. Inductor fuses them: there the
forward took 6.1 ms and the step 1.13× less time (section j). The compile took 39 s once per guidance in the bench's
process (a worker keeps its guidance loaded until it needs the room: VOXE_GUIDANCE_CACHE_SIZE), against ~65 s saved
over 8,000 iterations.

Only what the SDS step runs is compiled: an encode with gradient, outside autocast. Gradient-free encodes (the
attention maps of a refinement) and autocast run the eager encoder, so they never wait for a compile of their own.
A compile the installed libraries refuse (no Triton, no compiler) turns it off for good with a warning and runs the
eager encoder (not graphed), as a refused CUDA-graph capture does; running out of memory still raises. The backward
compiles lazily, at the first backward, which would be outside that fallback: so the first compiled call of each
input shape runs a forward and a backward on a detached copy first.

Examples:
    >>> double = CompiledEncoder(lambda x: 2 * x, compile=lambda f: f)  # any compiler: torch.compile by default
    >>> x = torch.ones(1, requires_grad=True)
    >>> double(x).sum().backward(); x.grad.tolist()
    [2.0]
"""

from __future__ import annotations

import time
import warnings
from typing import Callable

import torch

Moments = Callable[[torch.Tensor], torch.Tensor]
"""x (B, 3, H, W) in [-1, 1] -> the VAE posterior's moments (B, 2·C, h, w)."""


def _inductor(moments: Moments) -> Moments:
    return torch.compile(moments, dynamic=False)


class CompiledEncoder:
    """``moments(x)`` through ``compile(moments)`` where the SDS step runs it (``x`` with gradient, no autocast), else
    eagerly.

    Args:
        moments: the eager encoder (:data:`Moments`), its weights frozen.
        compile: makes the compiled callable (default: ``torch.compile`` with static shapes, inductor).
    """

    def __init__(self, moments: Moments, compile: Callable[[Moments], Moments] = _inductor):
        self.moments = moments
        self.compiled: Moments | None = compile(moments)
        self._compiled_for: tuple | None = None  # the input whose forward and backward have compiled
        self.compile_seconds: float | None = None  # the latest compile's host time (the first call's wait)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        sds_step = x.requires_grad and torch.is_grad_enabled() and not torch.is_autocast_enabled(x.device.type)
        if self.compiled is None or not sds_step:
            return self.moments(x)
        try:
            key = (tuple(x.shape), x.dtype, x.device)
            if key != self._compiled_for:  # both compiles here, inside the fallback (the backward's is lazy)
                start = time.perf_counter()
                probe = self.compiled(x.detach().clone().requires_grad_(True))
                probe.backward(torch.ones_like(probe))  # a dense gradient, laid out as the SDS step's
                self._compiled_for, self.compile_seconds = key, time.perf_counter() - start
            return self.compiled(x)
        except torch.cuda.OutOfMemoryError:
            raise  # the eager encoder would not fit either
        except RuntimeError as error:  # torch._dynamo's and inductor's failures are RuntimeErrors
            warnings.warn(f"torch.compile turned off for the VAE encoder: {error}", RuntimeWarning, stacklevel=2)
            self.compiled = None
            return self.moments(x)
