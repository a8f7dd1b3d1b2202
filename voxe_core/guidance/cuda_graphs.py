"""CUDA graphs for the SDS step's fixed-shape networks (issue 17; on by default on CUDA, ``cuda_graphs=False`` off).

On the lent H200 an SDS step's eager UNet forward took 48 ms in fp16 and as long at batch 8 as at batch 2
(bench/results/gpu.json): the host launching the UNet's many small kernels one by one sets the pace, not the
arithmetic. A CUDA graph records those launches once and replays them as one (there: 10 ms, the SDS gradient
bit-identical). A network is captured the first time an input shape (and dtype) is seen, after warm-up iterations
on a side stream (PyTorch's recipe), on the inputs' device; only the latest shape is kept, so a worker that meets
another batch size captures again rather than holding one memory pool per shape. A replay reads its inputs from
static buffers the call copies into and runs on the storage the weights had at capture: move, cast or re-layout the
model afterwards and the graphs must be dropped (build a new guidance).

* :class:`GraphedUNet`: the UNet's forward without gradient (the SDS UNet pass never needs one);
* :class:`GraphedEncoder`: the VAE encoder's posterior moments, forward and backward
  (``torch.cuda.make_graphed_callables``), since the SDS gradient flows through it into the renders; used where the
  encoder is not compiled (:mod:`voxe_core.guidance.compiled`, the default on CUDA, fuses its launches instead).

Both need a CUDA device and run outside autocast (graphs cannot replay autocast's cast cache).

Examples:
    >>> guidance = StableDiffusionGuidance.from_pretrained(model, device="cuda")  # doctest: +SKIP
    >>> loss, _ = guidance.sds_loss(renders, text, timesteps)  # doctest: +SKIP
    >>> # the first call per shape captures (after warm-up), later ones replay; a host tensor is refused:
    >>> GraphedUNet(forward=None)(torch.zeros(2, 4, 8, 8), torch.zeros(2), torch.zeros(2, 77, 8))
    Traceback (most recent call last):
    ValueError: CUDA graphs need a CUDA device, got a tensor on cpu
"""

from __future__ import annotations

from typing import Callable

import torch

WARMUP_ITERATIONS = 3
"""Eager iterations on a side stream before a capture: kernels chosen, workspaces and caches allocated."""

UNetForward = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
"""(sample (B, C, h, w), timestep (B,), text embeddings (B, L, D)) -> the UNet's output (B, C, h, w)."""


def _check_capturable(tensor: torch.Tensor) -> None:
    if tensor.device.type != "cuda":
        raise ValueError(f"CUDA graphs need a CUDA device, got a tensor on {tensor.device}")
    if torch.is_autocast_enabled(tensor.device.type):
        raise ValueError("CUDA graphs cannot run under autocast: run the guidance in its own dtype instead")


def _shape_key(*tensors: torch.Tensor) -> tuple:
    return tuple((tuple(t.shape), t.dtype) for t in tensors)


class GraphedUNet:
    """``forward(sample, timestep, text)`` replayed from a graph of the latest input shape.

    Args:
        forward: the eager UNet forward (:data:`UNetForward`), its weights frozen on a CUDA device.

    Call with the forward's arguments, all on that device; returns the output as a tensor of the caller's own
    (not the graph's output buffer, which the next replay overwrites).
    """

    def __init__(self, forward: UNetForward):
        self.forward = forward
        self._key: tuple | None = None
        self._graph: tuple[tuple[torch.Tensor, ...], torch.Tensor, torch.cuda.CUDAGraph] | None = None

    @torch.no_grad()
    def __call__(self, sample: torch.Tensor, timestep: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
        args = (sample, timestep, text)
        key = _shape_key(*args)
        if key != self._key:
            _check_capturable(sample)
            self._key, self._graph = None, None  # the previous shape's pool goes before the next is taken
            self._graph, self._key = self._capture(args), key
        inputs, output, graph = self._graph
        for static, given in zip(inputs, args):
            static.copy_(given)
        graph.replay()
        return output.clone()

    def _capture(self, args: tuple[torch.Tensor, ...]):
        inputs = tuple(a.clone() for a in args)
        device = inputs[0].device
        with torch.cuda.device(device):  # the capture stream and the warm-up on the inputs' device, not device 0
            side = torch.cuda.Stream(device)
            side.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(side):
                for _ in range(WARMUP_ITERATIONS):
                    self.forward(*inputs)
            torch.cuda.current_stream(device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                output = self.forward(*inputs)
        return inputs, output, graph


class GraphedEncoder:
    """``moments(x)``, the VAE encoder's posterior moments ``(B, 2·C, h, w)`` of ``x`` ``(B, 3, H, W)`` in [-1, 1],
    differentiable with respect to ``x``: a forward and a backward graph of the latest input shape
    (``torch.cuda.make_graphed_callables``). An ``x`` without gradient runs eagerly (no backward to record).

    The backward graph replays from the activations of the latest forward: one forward per backward, as the SDS
    step does (a second encode before the first one's backward would give the first the second's gradient).

    Args:
        moments: the eager encoder, ``x -> moments``, its weights frozen on a CUDA device.
    """

    def __init__(self, moments: Callable[[torch.Tensor], torch.Tensor]):
        self.moments = moments
        self._key: tuple | None = None
        self._graphed: Callable[[torch.Tensor], torch.Tensor] | None = None

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if not (x.requires_grad and torch.is_grad_enabled()):
            return self.moments(x)
        key = _shape_key(x)
        if key != self._key:
            _check_capturable(x)
            self._key, self._graphed = None, None
            sample = torch.zeros_like(x).requires_grad_(True)
            with torch.cuda.device(x.device):
                self._graphed = torch.cuda.make_graphed_callables(self.moments, (sample,))
            self._key = key
        return self._graphed(x).clone()  # the graph's output buffer is the next replay's
