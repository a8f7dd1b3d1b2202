"""CUDA graphs for the SDS step's fixed-shape networks (issue 17, opt in: ``cuda_graphs=True``).

On the lent H200 an SDS step's UNet forward took 35 ms in fp16 and 45 ms in fp32 (bench/results/gpu.json): a
time that barely depends on the arithmetic is the host launching the UNet's many small kernels one by one. A CUDA
graph records those launches once and replays them as one. Each network is captured per input shape (and dtype),
the first time that shape is seen, after warm-up iterations on a side stream (PyTorch's recipe); a replay reads
its inputs from static buffers the call copies into, so the graph holds the weights as they were at capture: move,
cast or re-layout the model and the graphs must be built again (a new guidance does).

* :class:`GraphedUNet`: the UNet's forward without gradient (the SDS UNet pass never needs one);
* :class:`GraphedEncoder`: the VAE encoder's posterior moments, forward and backward
  (``torch.cuda.make_graphed_callables``), since the SDS gradient flows through it into the renders.

Both need a CUDA device and run outside autocast (graphs cannot replay autocast's cast cache).

Examples:
    >>> guidance = StableDiffusionGuidance.from_pretrained(model, device="cuda", cuda_graphs=True)  # doctest: +SKIP
    >>> loss, _ = guidance.sds_loss(renders, text, timesteps)  # doctest: +SKIP
    >>> # the first call per shape captures (after warm-up), later ones replay; a host tensor is refused:
    >>> GraphedUNet(unet=None)(torch.zeros(2, 4, 8, 8), torch.zeros(2), torch.zeros(2, 77, 8))
    Traceback (most recent call last):
    ValueError: CUDA graphs need a CUDA device, got a tensor on cpu
"""

from __future__ import annotations

from typing import Callable

import torch

WARMUP_ITERATIONS = 3
"""Eager iterations on a side stream before a capture: kernels chosen, workspaces and caches allocated."""


def _check_capturable(tensor: torch.Tensor) -> None:
    if tensor.device.type != "cuda":
        raise ValueError(f"CUDA graphs need a CUDA device, got a tensor on {tensor.device}")
    if torch.is_autocast_enabled(tensor.device.type):
        raise ValueError("CUDA graphs cannot run under autocast: run the guidance in its own dtype instead")


class GraphedUNet:
    """``unet(sample, timestep, encoder_hidden_states).sample`` replayed from a graph per input shape.

    Args:
        unet: a diffusers ``UNet2DConditionModel`` on a CUDA device, its weights frozen.

    Call with ``sample`` ``(B, C, h, w)``, ``timestep`` ``(B,)`` and ``encoder_hidden_states`` ``(B, L, D)``, all on
    the UNet's device; returns ``(B, C, h, w)`` in the UNet's dtype, a tensor of the caller's own (not the graph's
    output buffer, which the next replay overwrites).
    """

    def __init__(self, unet):
        self.unet = unet
        self._graphs: dict[tuple, tuple[tuple[torch.Tensor, ...], torch.Tensor, torch.cuda.CUDAGraph]] = {}

    @property
    def captured_shapes(self) -> list[tuple]:
        return list(self._graphs)

    @torch.no_grad()
    def __call__(self, sample: torch.Tensor, timestep: torch.Tensor, encoder_hidden_states: torch.Tensor) -> torch.Tensor:
        args = (sample, timestep, encoder_hidden_states)
        key = tuple((tuple(a.shape), a.dtype) for a in args)
        if key not in self._graphs:
            _check_capturable(sample)
            self._graphs[key] = self._capture(args)
        inputs, output, graph = self._graphs[key]
        for static, given in zip(inputs, args):
            static.copy_(given)
        graph.replay()
        return output.clone()

    def _capture(self, args: tuple[torch.Tensor, ...]):
        inputs = tuple(a.clone() for a in args)

        def forward() -> torch.Tensor:
            return self.unet(inputs[0], inputs[1], encoder_hidden_states=inputs[2]).sample

        device = inputs[0].device
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(WARMUP_ITERATIONS):
                forward()
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            output = forward()
        return inputs, output, graph


class GraphedEncoder:
    """The VAE encoder's posterior moments ``(B, 2·C, h, w)`` of ``x`` ``(B, 3, H, W)`` in [-1, 1], differentiable
    with respect to ``x``: a forward and a backward graph per input shape (``torch.cuda.make_graphed_callables``).
    An ``x`` without gradient runs eagerly (nothing to record a backward of).

    Args:
        vae: a diffusers ``AutoencoderKL`` on a CUDA device, its weights frozen.
    """

    def __init__(self, vae):
        self.vae = vae
        self._callables: dict[tuple, Callable[[torch.Tensor], torch.Tensor]] = {}

    @property
    def captured_shapes(self) -> list[tuple]:
        return list(self._callables)

    def moments(self, x: torch.Tensor) -> torch.Tensor:
        """Eager: what the graphs record."""
        return self.vae.encode(x).latent_dist.parameters

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if not (x.requires_grad and torch.is_grad_enabled()):
            return self.moments(x)  # no backward to record (the attention pass's encode): eager
        key = (tuple(x.shape), x.dtype)
        if key not in self._callables:
            _check_capturable(x)
            sample = torch.zeros_like(x).requires_grad_(True)
            self._callables[key] = torch.cuda.make_graphed_callables(self.moments, (sample,))
        return self._callables[key](x)
