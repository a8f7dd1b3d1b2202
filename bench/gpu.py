"""The GPU path measured in one run (issue 17): edit-step speed-ups as ratios, an edit loop, reconstruction,
refinement, a whole local-edit job through the worker, and each stage's peak memory.

Models have RANDOM WEIGHTS (nothing can be downloaded on the device machine; the cost of a network does not
depend on its weights): ``sd2-base-shaped`` (SDS) and ``sd1.4-shaped`` (attention) are built from the real
architectures by ``bench/edit_step.py``'s builder, fp16, 512² guidance. Timings are costs, never quality.

    python bench/gpu.py            # CUDA, full size: ~8 min on one H200 before section l (--skip: in parts)
    bash bench/gpu_carry.sh        # here: the wheels and mic views the lent GPU machine lacks, in .gpu_carry/
    bash bench/gpu_device.sh       # there (device tool: carry [".gpu_carry"]): installs them, runs this script
    python bench/gpu.py --smoke    # CPU, tiny sizes: every section but g and j end to end in about two minutes,
                                   # ~60 s of it l's kernels in Triton's interpreter (tests/test_bench_gpu.py runs
                                   # all but l, and l smaller); its figures mean nothing

Sections (each one's failure is recorded in its run, the others still run; the JSON is rewritten after each):

a. ``edit_step``: one SDS editing step split into render / VAE / UNet / backward / optimiser (timing
   synchronisation on, so the parts are device times), for the baseline (fp32, contiguous memory, for-each
   Adam) and each speed-up added in turn (fp16, channels_last, fused Adam, timing synchronisation off); the
   step's wall time (one synchronisation per run, not per part) and its ratio to the baseline; what fp16 costs in
   accuracy: each variant's SDS gradient, encoder latents and image gradient against the baseline's on the same
   inputs (``sds_grad_relative_difference`` ..., as sections g and j compare with the eager guidance);
b. ``edit_loop``: >= 500 iterations of the default edit at 160³: ms per step, the projected 8,000-iteration
   minutes (``--fused-marcher``: with the fused ray marcher, section l);
c. ``reconstruction``: mic with the ``fast`` and ``paper`` presets on the device: seconds, test PSNR / SSIM
   (scored as bench/reconstruction.py scores them, at its 200 px; the 2026-12-04 record trained at 266 px), and
   ``fast`` again with the early-stop density pass object fits dropped, and with twice the steps of half the rays at
   lr 0.03 (the preset before 2026-12-05's second change; rows ``variant``, ``seconds_over_default``);
d. ``refinement``: the attention pass over the views, the attention-grid fit and the graph cut at 160³;
e. every run carries ``peak_memory_gb`` (the stage's ``torch.cuda.max_memory_allocated``, GiB); sections g and j
   load one guidance at a time, so a variant's peak is its own model's (``memory_left_before_load_gb``: what was
   still allocated when it loaded, 0 where nothing of an earlier model survived);
f. ``job``: one local-edit job (reconstruct -> edit -> refine -> export) through the worker's task bodies on an
   embedded service, the SDS model the full-size random one; iterations reduced (``job_iterations``) to fit
   the 8 minutes: its seconds are projected to 8,000 iterations from (b)'s ms per step;
h. ``render_passes``: bench/render_passes.py's measurement on the device (the edit's render and backward at each
   ``RenderConfig.samples_per_pass``: operations, time, memory, output differences), then
   bench/interpolation.py's (``interpolation`` rows: the default interpolation against ``F.embedding``'s own
   backward (a sort on CUDA), whose place ``index_add_``'s atomic adds took, and against a multiply-and-sum forward);
g. ``cuda_graphs`` (CUDA only): the SDS step's UNet and VAE encoder replayed from CUDA graphs against the eager
   default, in one section: agreement on the same inputs, step and per-part times, the capture's warm-up, a
   ``loop_iterations`` loop, and the eager UNet at batch 2 against 8 (launch-bound or not);
i. ``edit_step`` with the renderer's passes at the device's default size against 2^20 and 2^23, and at the default
   without early stopping (``early_stop=0``: no density probe), interleaved, with per-part device times (the
   backward split where the gradient reaches the renders);
j. ``edit_step`` (CUDA only) with the VAE encoder compiled (``torch.compile``) or not, graphed or not: warm-up
   (the compile), per-part times, agreement with the eager guidance;
l. ``fused_render``: the fused ray marcher (``RenderConfig.fused``: one Triton kernel marches and composites each
   ray, another adds its gradient; voxe_core.fused_render) against the packed renderer: the edit's render and
   backward on section h's scenes (operations, time, memory, the render's and gradient's differences), and the
   default step against the fused one interleaved with per-part times (on the CPU its kernels run in Triton's
   interpreter: ~60 s at the smoke sizes, figures that mean nothing); ``--fused-marcher`` runs sections b and f with
   it (their rows say ``fused_marcher``, which bench/report.py keeps out of issue 17's targets while the packed
   renderer is the default);
k. ``step_profile``: ``torch.profiler`` over ``timed`` default steps: the device's busy time against the wall
   time (below 1: the host's launching and reading back sets the pace, not the arithmetic), kernel launches and
   host synchronisations per step, and the kernels and host operations that take the most time.

Sections run in the order a, b, c, d, h, g, i, l, k, j, f: the whole job last, the longest and, with a compile in its
worker, the least predictable (each section's runs are saved as it ends). A SIGTERM (bench/gpu_device.sh's
``timeout``, ``GPU_BENCH_SECONDS``) ends the section in flight with a row saying so and what it had measured (the
job's stages so far), and the later sections do not start.

``--skip a,b,c --keep bench/results/gpu.json`` re-runs the other sections in a later call on the device and keeps
the earlier call's runs of the skipped ones (each run names its ``section``; kept ones say so).

Writes bench/results/gpu.json (``{"runs": [...]}``; each run has ``name``, ``kind``, ``device``, ``dtype``,
``model``, ``peak_memory_gb`` and, per kind, ``ms_step`` / ``edit_8000_minutes``, ``seconds`` / ``psnr`` /
``ssim`` or ``seconds``) and gpu.png; ``--smoke`` writes gpu_smoke.json / .png instead.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
sys.path[:0] = [str(REPO), str(HERE), str(REPO / "tests")]
from needs import MIC  # noqa: E402 - ../shared/data, or $VOXE_DATA_ROOT (bench/gpu_device.sh on the GPU machine)

from voxe_core.devices import synchronize  # noqa: E402

PROMPT, EDIT_WORDS = "a dog wearing big sunglasses", ["sunglasses"]


@dataclass
class Profile:
    """Sizes of one run of the script: the full GPU benchmark or the CPU smoke run."""

    device: str
    dtype: torch.dtype
    guidance_resolution: int
    render_size: int
    grid_resolution: int
    warm: int
    timed: int
    loop_iterations: int
    job_iterations: int
    reconstruction: dict  # preset name -> job parameters' "reconstruction" (None: the preset as it is)
    downsample: int  # the job's images (3: the paper's 266 px)
    reconstruction_downsample: int  # (c)'s, as bench/reconstruction.py (4: 200 px), so PSNRs compare
    max_images: int | None
    refine: dict
    export: dict
    fused_marcher: bool = False  # sections b and f: the edit's renders through the fused marcher (--fused-marcher)

    @classmethod
    def full(cls) -> "Profile":
        return cls("cuda", torch.float16, 512, 266, 160, 5, 20, 500, 500,
                   {"fast": {"preset": "fast"}, "paper": {"preset": "paper"}}, 3, 4, None, {},
                   {"views": 4, "turntable_frames": 30, "gif": False})

    @classmethod
    def smoke(cls) -> "Profile":
        tiny_fit = {"resolution": 24, "iterations": 20, "rays_per_step": 1024}  # enough for an occupied G_i
        return cls("cpu", torch.float32, 64, 24, 24, 1, 2, 3, 2,
                   {"fast": {"preset": "fast", **tiny_fit}, "paper": {"preset": "paper", **tiny_fit}}, 16, 16, 8,
                   {"views": 4, "iterations": 20, "render_size": 64, "rays_per_step": 2048},
                   {"views": 1, "view_size": 32, "turntable_frames": 4, "turntable_size": 32, "gif": False,
                    "mesh_resolution": 32})


def _peak(reports, key: str = "peak_memory_gb") -> float | None:
    values = [r.info[key] for r in reports if r.info.get(key) is not None]
    return max(values) if values else None


def _peaks(reports) -> dict:
    """Peak memory allocated and reserved (the latter counts the CUDA graphs' pools, which replays leave out)."""
    return {"peak_memory_gb": _peak(reports), "peak_memory_reserved_gb": _peak(reports, "peak_memory_reserved_gb")}


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).replace("torch.", "")


SDS_MODEL = "sd2-base-shaped (random weights)"
EDIT_PARTS = ("render", "vae", "unet", "backward", "backward_guidance", "backward_render", "optimizer")


def _step_row(name: str, profile: Profile, dtype: torch.dtype, ms_step: float, reports, parts=None, **extra) -> dict:
    """An ``edit_step`` run: ms per step, its 8,000-iteration minutes, peak memory of ``reports`` and, from
    ``parts`` (reports of a run with timing synchronisation), each part's mean device time."""
    row = {"name": f"edit_step {name}", "kind": "edit_step", "device": profile.device, "dtype": _dtype_name(dtype),
           "model": SDS_MODEL, "ms_step": ms_step, "edit_8000_minutes": ms_step * 8000 / 60000,
           **_peaks(reports + (parts or [])), **extra}
    for part in EDIT_PARTS if parts else ():
        if all(f"ms_{part}" in r.info for r in parts):
            row[f"ms_{part}"] = sum(r.info[f"ms_{part}"] for r in parts) / len(parts)
    return row


def _warm_up(guidance, profile: Profile, **render) -> float:
    """Seconds of ``profile.warm`` default iterations (``render``: :func:`_edit_run`'s): where kernels are picked,
    graphs captured and compiles run."""
    start = time.perf_counter()
    _edit_run(guidance, profile, profile.warm, sync=False, **render)
    return time.perf_counter() - start


def _measured_step(guidance, profile: Profile) -> tuple[float, list, list, float]:
    """(ms per step, its reports, the reports of a run with timing synchronisation, warm-up seconds) of the default
    edit after ``profile.warm`` iterations (captures and compiles happen there, timed apart)."""
    warm_seconds = _warm_up(guidance, profile)
    parts, _ = _edit_run(guidance, profile, profile.timed, sync=True)
    timed, wall = _edit_run(guidance, profile, profile.timed, sync=False)
    return wall * 1e3 / profile.timed, timed, parts, warm_seconds


def _loop_row(guidance, profile: Profile, name: str, fused: bool = False, **extra) -> dict:
    """An ``edit`` run: ``loop_iterations`` default iterations after warm-up (timed apart: compile and captures), timed
    as one; ``fused``: with the fused ray marcher."""
    warm_seconds = _warm_up(guidance, profile, fused=fused)
    reports, wall = _edit_run(guidance, profile, profile.loop_iterations, sync=False, fused=fused)
    ms_step = wall * 1e3 / profile.loop_iterations
    return {"name": name, "kind": "edit", "device": profile.device, "dtype": _dtype_name(profile.dtype),
            "model": SDS_MODEL, "iterations": profile.loop_iterations, "seconds": wall,
            "iterations_per_second": profile.loop_iterations / wall, "ms_step": ms_step,
            "edit_8000_minutes": ms_step * 8000 / 60000, "warm_seconds": warm_seconds, "warm_iterations": profile.warm,
            **_marched(reports), **_peaks(reports), **extra}


def _marched(reports) -> dict:
    """Samples per ray, and whether every render went through the fused marcher (as the edit reports them)."""
    return {"samples_per_ray": sum(r.info["samples_per_ray"] for r in reports) / len(reports),
            "fused_marcher": all(r.info["fused_marcher"] for r in reports)}


def _relative_difference(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.float() - b.float()).abs().max() / b.float().abs().max().clamp_min(1e-12))


def _agreement_outputs(guidance, profile: Profile) -> dict[str, torch.Tensor]:
    """What two guidances of one model are compared on (:func:`_agreement`), on inputs drawn from seed 0 (the same for
    every guidance): SDS gradients on two different latents (on a graphed guidance the second a replay reading new
    inputs), the encoder's posterior mean and the gradient it sends back to the images. Copies: a graph's replay
    overwrites its outputs."""
    generator = torch.Generator(profile.device).manual_seed(0)
    size = profile.guidance_resolution // guidance.vae_scale_factor
    channels = guidance.unet.config.in_channels
    text = guidance.encode_prompts([PROMPT])
    outputs = {}
    for t in (500, 200):
        latents, noise = (torch.randn(1, channels, size, size, device=profile.device, generator=generator)
                          for _ in range(2))
        outputs[f"sds_grad_t{t}"] = guidance.sds_grad_on_latents(latents, text, [t], noise=noise)[0].detach().clone()
    images = torch.rand(1, 3, profile.render_size, profile.render_size, device=profile.device, generator=generator)
    weights = torch.randn(1, channels, size, size, device=profile.device, generator=generator)
    images.requires_grad_(True)
    latents = guidance.encode_images(images, sample=False)
    (latents.float() * weights).sum().backward()
    outputs["encoder_latents"], outputs["encoder_image_grad"] = latents.detach().clone(), images.grad
    return outputs


def _agreement(outputs: dict[str, torch.Tensor], reference: dict[str, torch.Tensor]) -> dict:
    """Largest differences, relative to the reference's largest entry, between a guidance's
    :func:`_agreement_outputs` and its reference's (the eager guidance's; section a: the fp32 baseline's)."""
    def differs(key: str) -> float:
        return _relative_difference(outputs[key], reference[key])

    return {"sds_grad_relative_difference": max(differs(k) for k in reference if k.startswith("sds_grad")),
            "encoder_latents_relative_difference": differs("encoder_latents"),
            "encoder_image_grad_relative_difference": differs("encoder_image_grad")}


def _free_device_memory(profile: Profile) -> float | None:
    """Hand the dropped models' memory back and start the peak afresh, before the next model loads; the GiB still
    allocated then (None on the CPU), which the next variant's row records: above zero, something of an earlier model
    is still alive and counts in its peak."""
    gc.collect()
    if profile.device != "cuda":
        return None
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    return torch.cuda.memory_allocated() / 2**30


def _variant_row(name: str, guidance, profile: Profile, **extra) -> dict:
    """An ``edit_step`` run of ``guidance``'s default step (:func:`_measured_step`: the warm-up, where graphs are
    captured and compiles run, timed apart)."""
    ms_step, timed, parts, warm_seconds = _measured_step(guidance, profile)
    return _step_row(name, profile, profile.dtype, ms_step, timed, parts, cuda_graphs=guidance.cuda_graphs,
                     warm_seconds=warm_seconds, warm_iterations=profile.warm, **extra)


def _guidance(path: Path, profile: Profile, dtype: torch.dtype, cuda_graphs: bool | None = None,
              compile_encoder: bool | None = None):
    from voxe_core.guidance.sds import StableDiffusionGuidance

    return StableDiffusionGuidance.from_pretrained(str(path), device=profile.device, dtype=dtype, local_files_only=True,
                                                   resolution=profile.guidance_resolution, cuda_graphs=cuda_graphs,
                                                   compile_encoder=compile_encoder)


@contextlib.contextmanager
def _adam(fused: bool):
    """The edit's Adam as it is (fused where the device has the kernels) or the for-each one it replaced."""
    import voxe_core.edit

    real = voxe_core.edit._make_adam
    if not fused:
        voxe_core.edit._make_adam = lambda param, config: torch.optim.Adam(
            [param], lr=config.lr, betas=tuple(config.betas), foreach=True)
    try:
        yield
    finally:
        voxe_core.edit._make_adam = real


def _channels_last(guidance, enabled: bool) -> None:
    layout = torch.channels_last if enabled else torch.contiguous_format
    guidance.unet.to(memory_format=layout)
    guidance.vae.to(memory_format=layout)


def _edit_run(guidance, profile: Profile, iterations: int, sync: bool,
              after_iteration: Callable[[], None] | None = None, **render):
    """(reports, wall seconds) of ``iterations`` default edit iterations on the 160³ sphere (one sync at the end);
    ``render`` replaces fields of the renderer's config (``samples_per_pass``, ``early_stop``, ``fused``);
    ``after_iteration`` is called as each iteration reports."""
    from edit_step import sphere_grid

    from voxe_core.edit import EditConfig, edit
    from voxe_core.progress import Callbacks

    reports = []
    guidance.sync_timing = sync
    config = EditConfig(iterations=iterations, render_size=profile.render_size, sync_timing=sync)
    config.render = dataclasses.replace(config.render, **render)
    grid = sphere_grid(profile.grid_resolution)
    synchronize(profile.device)
    start = time.perf_counter()

    def on_progress(report) -> None:
        reports.append(report)
        if after_iteration is not None:
            after_iteration()

    edit(grid, PROMPT, guidance, config, Callbacks(on_progress=on_progress), device=profile.device)
    synchronize(profile.device)
    return reports, time.perf_counter() - start


# ---------------------------------------------------------------- (a), (b)
STEP_VARIANTS = (  # each adds one change to the one before
    ("baseline: fp32, contiguous, for-each Adam, timing sync", dict(half=False, channels_last=False, fused=False, sync=True)),
    ("+ fp16 UNet/VAE", dict(half=True, channels_last=False, fused=False, sync=True)),
    ("+ channels_last", dict(half=True, channels_last=True, fused=False, sync=True)),
    ("+ fused Adam", dict(half=True, channels_last=True, fused=True, sync=True)),
    ("+ no timing sync (the default)", dict(half=True, channels_last=True, fused=True, sync=False)),
)


def edit_step_runs(sd2: Path, profile: Profile) -> list[dict]:
    """Each variant's step as a ratio to the baseline's, and what its dtype costs in accuracy: its
    :func:`_agreement` with the fp32 baseline's outputs, in this run. The outputs are computed once per state of the
    guidance (dtype, memory layout): fused Adam and the timing sync leave it as it was, and each variant had computed
    them again."""
    rows, baseline, reference = [], None, None
    loaded, outputs_of = {}, {}
    for name, variant in STEP_VARIANTS:
        dtype = profile.dtype if variant["half"] else torch.float32
        if dtype not in loaded:
            loaded.clear()  # one model in memory at a time
            _free_device_memory(profile)
            loaded[dtype] = _guidance(sd2, profile, dtype, cuda_graphs=False, compile_encoder=False)  # (g), (j): the rest
        guidance = loaded[dtype]
        if profile.device == "cuda":
            _channels_last(guidance, variant["channels_last"])
        with _adam(variant["fused"]):
            _edit_run(guidance, profile, profile.warm, variant["sync"])  # kernels picked, caches filled
            timed, wall = _edit_run(guidance, profile, profile.timed, variant["sync"])
        ms_step = wall * 1e3 / profile.timed
        # per-part device times where the variant synchronises
        row = _step_row(name, profile, dtype, ms_step, timed, timed if variant["sync"] else None, **variant)
        baseline = baseline or ms_step
        row["speedup_over_baseline"] = baseline / ms_step
        state = (dtype, profile.device == "cuda" and variant["channels_last"])
        if state not in outputs_of:
            outputs_of[state] = _agreement_outputs(guidance, profile)
        reference = reference or outputs_of[state]
        row.update(_agreement(outputs_of[state], reference))
        rows.append(row)
    return rows


def edit_loop_run(sd2: Path, profile: Profile) -> dict:
    """The default edit (the guidance as ``from_pretrained`` makes it: channels_last and CUDA graphs on CUDA)."""
    guidance = _guidance(sd2, profile, profile.dtype)
    marcher = ", fused marcher" if profile.fused_marcher else ""
    return _loop_row(guidance, profile,
                     f"edit_loop {profile.loop_iterations} iterations at {profile.grid_resolution}³{marcher}",
                     fused=profile.fused_marcher, render_size=profile.render_size, guidance_resolution=profile.guidance_resolution,
                     cuda_graphs=guidance.cuda_graphs, compile_encoder=guidance.compile_encoder,
                     encoder_compile_seconds=guidance.encoder_compile_seconds)


# ---------------------------------------------------------------- (c)
def reconstruction_runs(profile: Profile, data: Path) -> list[dict]:
    """Each preset's fit, and ``fast``'s variants: what the early-stop density pass object fits no longer make
    (``ReconstructConfig.render``) and the twice-as-many steps it no longer takes cost on the device, as ratios in
    this run."""
    from voxe_core.data import load_scene
    from voxe_core.metrics import psnr, ssim
    from voxe_core.presets import reconstruct_config, reconstruction_params
    from voxe_core.progress import Callbacks
    from voxe_core.reconstruct import reconstruct
    from voxe_core.render import RenderConfig, render_image

    train = load_scene(data, "train", profile.reconstruction_downsample, profile.max_images)
    test = load_scene(data, "test", profile.reconstruction_downsample, profile.max_images)

    def fit(name: str, preset: str, config) -> dict:
        reports = []
        synchronize(profile.device)
        start = time.perf_counter()
        grid = reconstruct(train.images, train.cameras, config, Callbacks(on_progress=reports.append),
                           device=profile.device)
        synchronize(profile.device)
        seconds = time.perf_counter() - start
        render = RenderConfig(step_ratio=config.render.step_ratio)
        cameras = test.cameras.to(profile.device)
        images = torch.stack([render_image(grid, cameras, i, render).rgb.cpu() for i in range(len(cameras))])
        return {"name": name, "kind": "reconstruction", "device": profile.device, "dtype": "float32",
                "model": f"ReLU-field grid {config.resolutions[-1]}³", "preset": preset, "seconds": seconds,
                "iterations": config.total_iterations, "rays_per_step": config.rays_per_step, "lr": config.lr,
                "images_per_step": config.images_per_step, "early_stop": config.render.early_stop,
                "psnr": float(psnr(images, test.images).mean()), "ssim": float(ssim(images, test.images).mean()),
                **_peaks(reports), "image_size": train.cameras.width}

    configs = {preset: reconstruct_config(reconstruction_params({"reconstruction": params}), 0)
               for preset, params in profile.reconstruction.items()}
    # Untimed: the device's first fit loads its kernels, which would otherwise count against the first timed one.
    first = next(iter(configs.values()))
    reconstruct(train.images, train.cameras, dataclasses.replace(first, iterations=(10,) * len(first.iterations)),
                device=profile.device)
    # What `fast` is timed against on the device: the density pass object fits dropped, and the preset before it took
    # half the steps of twice the rays (the same samples; the same PSNR and time on the CPU, bench/reconstruction.py).
    fast_variants = {
        "the early-stop pass": lambda c: dataclasses.replace(
            c, render=dataclasses.replace(c.render, early_stop=RenderConfig.early_stop)),
        "twice the steps of half the rays at lr 0.03": lambda c: dataclasses.replace(
            c, rays_per_step=c.rays_per_step // 2, lr=0.03, iterations=tuple(2 * n for n in c.iterations)),
    }
    rows = []
    for preset, config in configs.items():
        default = fit(f"reconstruction mic {preset}", preset, config)
        rows.append(default)
        for name, change in fast_variants.items() if preset == "fast" else ():
            variant = fit(f"reconstruction mic {preset}, {name}", preset, change(config))
            rows.append({**variant, "variant": name, "seconds_over_default": variant["seconds"] / default["seconds"]})
    return rows


# ---------------------------------------------------------------- (d)
def refinement_run(sd14: Path, profile: Profile) -> dict:
    from edit_step import sphere_grid

    from voxe_core.progress import Callbacks
    from voxe_core.refine.config import RefineConfig
    from voxe_core.refine.pipeline import refine

    guidance = _guidance(sd14, profile, profile.dtype)
    initial = sphere_grid(profile.grid_resolution)
    edited = initial.clone_grid()
    with torch.no_grad():  # an "edit": a second sphere beside the first
        shifted = sphere_grid(profile.grid_resolution, radius=0.4).features.roll(profile.grid_resolution // 4, 0)
        edited.features.copy_(torch.maximum(edited.features, shifted))
    marks: dict[str, float] = {}
    reports = []

    def on_progress(report) -> None:
        reports.append(report)
        marks[report.stage] = time.perf_counter()

    synchronize(profile.device)
    start = time.perf_counter()
    result = refine(initial, edited, PROMPT, EDIT_WORDS, guidance, RefineConfig(**profile.refine),
                    Callbacks(on_progress=on_progress), device=profile.device)
    synchronize(profile.device)
    seconds = time.perf_counter() - start
    maps_end = marks.get("attention_maps", start)
    return {"name": f"refinement at {profile.grid_resolution}³", "kind": "refinement", "device": profile.device,
            "dtype": _dtype_name(profile.dtype), "model": "sd1.4-shaped (random weights)",
            "seconds": seconds, "seconds_attention_maps": maps_end - start,
            "seconds_backprojection": marks.get("backprojection", maps_end) - maps_end,
            "seconds_grids_and_cut": start + seconds - maps_end,  # the lift or fit, then the cut
            "edit_voxels": int(result.mask.sum()), **_peaks(reports)}


# ---------------------------------------------------------------- (f)
def job_run(sd2: Path, sd14: Path, profile: Profile, data: Path, root: Path, loop_ms_step: float | None,
            progress: dict | None = None) -> dict:
    """The job's run; ``progress["seconds_per_stage"]`` holds the stages done so far (what a cut-off call keeps)."""
    from fastapi.testclient import TestClient
    from service_helpers import ingest, reset_service_caches, service_env, small_mic, zip_folder

    env = service_env(root, VOXE_SDS_MODEL=str(sd2), VOXE_ATTENTION_MODEL=str(sd14), VOXE_DEVICE=profile.device,
                      VOXE_FUSED_MARCHER=str(profile.fused_marcher).lower())
    saved = {key: os.environ.get(key) for key in env}
    os.environ.update(env)
    reset_service_caches()
    try:
        from api.main import create_app
        from worker import tasks

        archive = zip_folder(small_mic(root / "mic", frames=profile.max_images or 100), root / "mic.zip", prefix="mic")
        params = {"downsample": profile.downsample, "iterations": profile.job_iterations,
                  "reconstruction": profile.reconstruction["fast"], "refine": profile.refine,
                  "export": profile.export}
        with TestClient(create_app()) as client, open(archive, "rb") as handle:
            scene = client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")}).json()
            ingest(scene["id"])
            job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": PROMPT, "mode": "local",
                                                "edit_words": EDIT_WORDS, "params": params}).json()
            seconds = {}
            if progress is not None:
                progress["seconds_per_stage"] = seconds
            for stage, task in (("reconstruct", tasks.reconstruct_task), ("edit", tasks.edit_task),
                                ("refine", tasks.refine_task), ("export", tasks.export_task)):
                start = time.perf_counter()
                outcome = task.apply(args=(job["id"],)).get()
                seconds[stage] = time.perf_counter() - start
                if outcome.get("state") != "done":
                    raise RuntimeError(f"{stage}: {client.get('/v1/jobs/' + job['id']).json().get('error')}")
            done = client.get(f"/v1/jobs/{job['id']}").json()
    finally:
        for key, value in saved.items():
            os.environ.pop(key, None) if value is None else os.environ.__setitem__(key, value)
        reset_service_caches()
    total = sum(seconds.values())
    projected = None
    if loop_ms_step is not None:
        projected = total + (8000 - profile.job_iterations) * loop_ms_step / 1e3
    memory = (done.get("result") or {}).get("peak_memory_gb", {})
    marcher = ", fused marcher" if profile.fused_marcher else ""
    return {"name": f"local-edit job through the worker{marcher}", "kind": "job", "device": profile.device,
            "fused_marcher": profile.fused_marcher,
            "dtype": _dtype_name(profile.dtype),
            "model": "sd2-base-shaped SDS + sd1.4-shaped attention (random weights)", "seconds": total,
            "seconds_per_stage": seconds, "edit_iterations": profile.job_iterations,
            "seconds_projected_8000_iterations": projected, "state": done["state"],
            "peak_memory_gb": max(memory.values()) if memory else None, "peak_memory_gb_per_stage": memory,
            "encoder_compile_seconds": (done.get("result") or {}).get("encoder_compile_seconds"),
            "fit": (done.get("result") or {}).get("fit")}  # the fit's steps: voxe_service.progress's CUDA table


# ---------------------------------------------------------------- (h)
def render_pass_runs(profile: Profile) -> list[dict]:
    """bench/render_passes.py on the device: the edit's render and its backward at each ``samples_per_pass`` (fewer,
    larger passes dispatch fewer operations: what a launch-bound GPU pays), on an object and on fog; then
    bench/interpolation.py's variants on the same scenes (is a GPU's batched GEMM on millions of 1 × 8 matrices, or
    are its atomic adds into the grid, slower than what they replaced?)."""
    import interpolation
    import render_passes
    from edit_step import sphere_grid

    rays = render_passes.edit_rays(profile.render_size)
    repeats = max(1, profile.timed // 4)
    scenes = {"sphere": sphere_grid(profile.grid_resolution), "fog": render_passes.fog_grid(profile.grid_resolution // 2)}
    passes = [r for scene, grid in scenes.items() for r in render_passes.measure(scene, grid, rays, repeats, profile.device)]
    variants = [r for scene, grid in scenes.items()
                for r in interpolation.measure(scene, grid, rays, repeats, profile.device)]
    return [{"name": f"render {r['scene']}, samples_per_pass {r['samples_per_pass']}", "kind": "render_passes",
             "dtype": "float32", "model": "ReLU-field grid", **r} for r in passes] + \
        [{"name": f"interpolation {r['scene']}, {r['variant']}", "kind": "interpolation", "dtype": "float32",
          "model": "ReLU-field grid", **r} for r in variants]


# ---------------------------------------------------------------- (g)
@torch.no_grad()
def _unet_ms(guidance, profile: Profile, batch: int, repeats: int = 10) -> float:
    size = profile.guidance_resolution // guidance.vae_scale_factor
    sample = torch.randn(batch, guidance.unet.config.in_channels, size, size, device=profile.device,
                         dtype=guidance.dtype)
    t = torch.full((batch,), 500, device=profile.device)
    text = guidance.encode_prompts([PROMPT]).to(profile.device, guidance.dtype).expand(batch, -1, -1)
    for _ in range(2):
        guidance.unet(sample, t, encoder_hidden_states=text)
    synchronize(profile.device)
    start = time.perf_counter()
    for _ in range(repeats):
        guidance.unet(sample, t, encoder_hidden_states=text)
    synchronize(profile.device)
    return (time.perf_counter() - start) * 1e3 / repeats


def _same_call_baseline(runs: list[dict]) -> float | None:
    """Section a's fp32 baseline (ms per step) where this call measured it; None where it did not, or where its row
    was kept from an earlier call: a ratio to that would compare two device calls (another process, another state
    of the machine), not two variants in one run."""
    return next((r["ms_step"] for r in runs if r.get("section") == "a" and "ms_step" in r
                 and not r.get("kept_from_earlier_call")), None)


def cuda_graph_runs(sd2: Path, profile: Profile, baseline_ms: float | None) -> list[dict]:
    """CUDA graphs (voxe_core.guidance.cuda_graphs) against the eager default in one section: their agreement on
    the same inputs, the step (the capture inside its warm-up, timed apart), per-part device times, a
    ``loop_iterations`` loop, and the eager UNet forward at batch 2 and 8 (a time that barely grows with the
    batch is the host launching kernels, which graphs remove). Each guidance is measured alone in memory, the eager
    one's agreement outputs kept for the graphed one. ``baseline_ms``: :func:`_same_call_baseline`; the steps'
    ``speedup_over_baseline`` only where it is not None."""
    left = _free_device_memory(profile)
    eager = _guidance(sd2, profile, profile.dtype, cuda_graphs=False, compile_encoder=False)
    eager_row = _variant_row("eager (cuda_graphs=False)", eager, profile, memory_left_before_load_gb=left)
    reference = _agreement_outputs(eager, profile)
    batch2, batch8 = _unet_ms(eager, profile, 2), _unet_ms(eager, profile, 8)
    del eager  # one guidance loaded at a time: each step's peak is its own model's
    left = _free_device_memory(profile)
    graphed = _guidance(sd2, profile, profile.dtype, cuda_graphs=True, compile_encoder=False)  # (j) compiles
    graphed_row = _variant_row("+ CUDA graphs (UNet, VAE encoder)", graphed, profile,  # the capture in the warm-up
                               memory_left_before_load_gb=left)
    graphed_row.update(_agreement(_agreement_outputs(graphed, profile), reference))
    for row in (eager_row, graphed_row):
        row["speedup_over_eager"] = eager_row["ms_step"] / row["ms_step"]
        if baseline_ms:
            row["speedup_over_baseline"] = baseline_ms / row["ms_step"]
    loop = _loop_row(graphed, profile,
                     f"edit_loop {profile.loop_iterations} iterations at {profile.grid_resolution}³, CUDA graphs",
                     cuda_graphs=True, memory_left_before_load_gb=left)
    return [eager_row, graphed_row, loop,
            {"name": "eager UNet forward, batch 2 against 8", "kind": "diagnostic", "device": profile.device,
             "dtype": _dtype_name(profile.dtype), "model": SDS_MODEL, "peak_memory_gb": None,
             "ms_unet_batch_2": batch2, "ms_unet_batch_8": batch8, "batch_8_over_batch_2": batch8 / batch2}]


# ---------------------------------------------------------------- (i)
def step_pass_runs(sd2: Path, profile: Profile) -> list[dict]:
    """The default step (CUDA graphs where they run) with the renderer's passes at the device's default against
    2^20 (the CPU's) and 2^23, and at the default without early stopping (no density probe before the render: fewer
    operations and host reads, more samples with gradient), interleaved (:func:`_interleaved_steps`)."""
    from voxe_core.render import RenderConfig

    guidance = _guidance(sd2, profile, profile.dtype)
    default = RenderConfig().pass_samples(torch.device(profile.device))
    variants = {}
    for size in dict.fromkeys((1 << 20, default, 1 << 23)):
        name = f"samples_per_pass 2^{size.bit_length() - 1}" + (" (default)" if size == default else "")
        variants[name] = dict(samples_per_pass=size)
    variants[f"samples_per_pass 2^{default.bit_length() - 1}, early_stop 0"] = dict(samples_per_pass=default,
                                                                                    early_stop=0.0)
    rows = _interleaved_steps(guidance, profile, variants)
    for row, render in zip(rows, variants.values()):
        row.update(samples_per_pass=render["samples_per_pass"],
                   early_stop=render.get("early_stop", RenderConfig().early_stop))
        row["speedup_over_2_20"] = rows[0]["ms_step"] / row["ms_step"]
    return rows


def _interleaved_steps(guidance, profile: Profile, variants: dict[str, dict]) -> list[dict]:
    """One ``edit_step`` row per variant (name -> the renderer's fields it replaces), the variants warmed up and then
    timed in interleaved halves (the machine's drift lands on each alike), each with per-part device times (the
    backward split where the gradient reaches the renders) and without synchronisation."""
    for render in variants.values():
        _edit_run(guidance, profile, profile.warm, sync=False, **render)
    timings = {name: [] for name in variants}
    parts = {name: [] for name in variants}
    for _ in range(2):
        for name, render in variants.items():
            parts[name] += _edit_run(guidance, profile, profile.timed // 2, sync=True, **render)[0]
            timings[name].append(_edit_run(guidance, profile, profile.timed // 2, sync=False, **render))
    rows = []
    for name in variants:
        reports = [r for run, _ in timings[name] for r in run]
        ms_step = sum(wall for _, wall in timings[name]) * 1e3 / len(reports)
        rows.append(_step_row(name, profile, profile.dtype, ms_step, reports, parts[name],
                              cuda_graphs=guidance.cuda_graphs, **_marched(reports)))
    return rows


# ---------------------------------------------------------------- (l)
def fused_marcher_runs(sd2: Path, profile: Profile) -> list[dict]:
    """The fused ray marcher (``RenderConfig.fused``, voxe_core.fused_render) against the packed renderer: the edit's
    render and its backward on bench/render_passes.py's sphere and fog (operations, time, memory, the render's and
    gradient's differences from the packed ones, whether the fused path ran), and the default step against the fused
    one (:func:`_interleaved_steps`). Its loop is section b's with ``--fused-marcher``."""
    import render_passes
    from edit_step import sphere_grid

    from voxe_core.edit import EditConfig

    rays = render_passes.edit_rays(profile.render_size)
    packed = EditConfig().render
    configs = {"packed": packed, "fused": dataclasses.replace(packed, fused=True)}
    scenes = {"sphere": sphere_grid(profile.grid_resolution), "fog": render_passes.fog_grid(profile.grid_resolution // 2)}
    rows = []
    for scene, grid in scenes.items():
        measured = render_passes.measure_configs(grid, rays, max(1, profile.timed // 4), profile.device, configs)
        rows += [{"name": f"render {scene}, {marcher} marcher", "kind": "fused_render", "dtype": "float32",
                  "model": "ReLU-field grid", "scene": scene, "marcher": marcher, **row}
                 for marcher, row in measured.items()]
    guidance = _guidance(sd2, profile, profile.dtype)
    steps = _interleaved_steps(guidance, profile, {"packed marcher (the default)": {}, "fused marcher": dict(fused=True)})
    for row in steps:
        row["speedup_over_packed"] = steps[0]["ms_step"] / row["ms_step"]
    return rows + steps


# ---------------------------------------------------------------- (k)
KERNEL_LAUNCHES = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx", "cudaGraphLaunch")
HOST_SYNCHRONISATIONS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize")


def _per_step(events, steps: int, time_key: str, top: int = 12) -> list[dict]:
    """The ``top`` events by ``time_key`` (µs in all steps): name, ms and calls per step."""
    ranked = sorted(events, key=lambda e: getattr(e, time_key), reverse=True)[:top]
    return [{"name": e.key[:120], "ms_per_step": getattr(e, time_key) / 1e3 / steps, "calls_per_step": e.count / steps}
            for e in ranked]


def step_profile_run(sd2: Path, profile: Profile) -> dict:
    """Where the default step's time goes: ``torch.profiler`` over ``profile.timed`` steps after warm-up, from the
    end of the run's second iteration on (its setup, first prompt encodings and the tracer's start left out). The
    profiler's own overhead lengthens the host's share, so ``profiled_ms_step`` is not the step's speed (b, i).
    ``aten_calls_per_step`` counts nested calls too (``aten::linear`` and the ``aten::addmm`` inside it); kernels
    are summed over streams, annotation ranges (an optimizer step, a compiled graph's call) left out."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, schedule
    from torch.profiler import profile as profiled

    guidance = _guidance(sd2, profile, profile.dtype)
    _warm_up(guidance, profile)
    cuda = profile.device == "cuda"
    steps = profile.timed
    ends = []  # when each iteration reported: the profiled steps are the last ``steps``

    with profiled(activities=[ProfilerActivity.CPU] + [ProfilerActivity.CUDA] * cuda,
                  schedule=schedule(wait=1, warmup=1, active=steps)) as recorded:  # warmup: the tracer's own start
        reports, _ = _edit_run(guidance, profile, steps + 2, sync=False,
                               after_iteration=lambda: (ends.append(time.perf_counter()), recorded.step()))
    events = [e for e in recorded.key_averages() if not getattr(e, "is_user_annotation", False)]
    kernels = [e for e in events if e.device_type != DeviceType.CPU]
    host_ops = [e for e in events if e.device_type == DeviceType.CPU and e.key.startswith("aten::")]
    ms_step = (ends[-1] - ends[-1 - steps]) * 1e3 / steps
    busy_ms = sum(e.self_device_time_total for e in kernels) / 1e3 / steps if cuda else None
    return {"name": "edit_step profiled (torch.profiler, the default step)", "kind": "step_profile",
            "device": profile.device, "dtype": _dtype_name(profile.dtype), "model": SDS_MODEL,
            "profiled_ms_step": ms_step, "device_busy_ms_per_step": busy_ms,
            "device_busy_fraction": None if busy_ms is None else busy_ms / ms_step,
            "kernel_launches_per_step": sum(e.count for e in events if e.key in KERNEL_LAUNCHES) / steps,
            "host_synchronisations_per_step": sum(e.count for e in events if e.key in HOST_SYNCHRONISATIONS) / steps,
            "aten_calls_per_step": sum(e.count for e in host_ops) / steps,
            "top_kernels": _per_step(kernels, steps, "self_device_time_total"),
            "top_host_operations": _per_step(host_ops, steps, "self_cpu_time_total"),
            "cuda_graphs": guidance.cuda_graphs, **_peaks(reports)}


# ---------------------------------------------------------------- (j)
ENCODER_VARIANTS = (  # (name, from_pretrained's compile_encoder, graph the compiled encoder too)
    ("CUDA graphs, eager encoder graphed (call 4's default)", False, False),
    ("CUDA graphs on the UNet, compiled encoder (the default)", None, False),
    ("CUDA graphs on the UNet, compiled encoder graphed", None, True),
)


def compiled_encoder_runs(sd2: Path, profile: Profile) -> list[dict]:
    """The VAE encoder compiled (``torch.compile``, voxe_core.guidance.compiled) against the graphed eager one, in
    one section: each variant's warm-up (its compile inside, on inductor's caches as the earlier sections left them),
    the step with per-part device times and without synchronisation, and the agreement of the compiled variants with
    the fully eager guidance on the same inputs (its outputs kept, the guidance dropped before the variants load). A
    variant's failure is recorded in its row."""
    reference = _agreement_outputs(_guidance(sd2, profile, profile.dtype, cuda_graphs=False, compile_encoder=False),
                                   profile)
    rows = []
    for name, compile_encoder, graph_compiled in ENCODER_VARIANTS:
        try:
            rows.append(_encoder_variant_row(sd2, profile, name, compile_encoder, graph_compiled, reference))
        except Exception as exc:  # noqa: BLE001 - the other variants still run
            traceback.print_exc()
            rows.append({"name": f"edit_step {name}", "kind": "edit_step", "device": profile.device,
                         "error": f"{type(exc).__name__}: {exc}"})
    eager_encoder = rows[0].get("ms_step")
    for row in rows[1:]:
        if eager_encoder and "ms_step" in row:
            row["speedup_over_eager_encoder"] = eager_encoder / row["ms_step"]
    return rows


def _encoder_variant_row(sd2: Path, profile: Profile, name: str, compile_encoder: bool | None, graph_compiled: bool,
                         reference: dict) -> dict:
    """One variant of section j, its guidance the only one loaded (and dropped on return): its peak is its own."""
    from voxe_core.guidance.cuda_graphs import GraphedEncoder

    left = _free_device_memory(profile)
    guidance = _guidance(sd2, profile, profile.dtype, compile_encoder=compile_encoder)
    if graph_compiled:
        guidance._graphed_encoder = GraphedEncoder(guidance._encoder)
    row = _variant_row(name, guidance, profile, compile_encoder=guidance.compile_encoder,  # the compile in the warm-up
                       graphed_encoder=guidance._graphed_encoder is not None, memory_left_before_load_gb=left)
    row["encoder_compile_seconds"] = guidance.encoder_compile_seconds
    if guidance.compile_encoder:
        row.update(_agreement(_agreement_outputs(guidance, profile), reference))
    return row


# ---------------------------------------------------------------- output
def _plot_label(run: dict) -> str:
    """A run's name with what tells equal names apart: its device call and whether the CUDA graphs ran."""
    label = run["name"].removeprefix("edit_step ")
    if run.get("cuda_graphs") and "CUDA graphs" not in label:
        label += ", CUDA graphs"
    return label + (f" [call {run['call']}]" if run.get("call") else "")


def _memory_text(run: dict) -> str:
    """Reserved peak where recorded; the allocated one unless graphs ran (replays allocate nothing)."""
    if run.get("peak_memory_reserved_gb") is not None:
        return f", {run['peak_memory_reserved_gb']:.1f} GiB reserved"
    if run.get("peak_memory_gb") is not None and not run.get("cuda_graphs"):
        return f", {run['peak_memory_gb']:.1f} GiB"
    return ""


# A step's ratio to its own section's reference, measured in the same call (the first a row has is shown).
SAME_CALL_RATIOS = (("speedup_over_baseline", "fp32 baseline"), ("speedup_over_eager", "eager"),
                    ("speedup_over_eager_encoder", "eager encoder"), ("speedup_over_2_20", "2^20 passes"),
                    ("speedup_over_packed", "packed marcher"))


def _rows_on_log_axis(ax, values: list[float], notes: list[str], labels: list[str], style: dict, xlabel: str,
                      title: str) -> None:
    """One point a row on a log axis (steps and stages span tens of milliseconds to minutes), each noted right of
    it, with room for the notes: plain numbers on the axis."""
    from matplotlib.ticker import FuncFormatter

    ax.scatter(values, range(len(values)), zorder=3, **style)
    for i, (value, note) in enumerate(zip(values, notes)):
        ax.annotate(f"  {note}", (value, i), va="center", fontsize=8)
    ax.set_yticks(range(len(labels)), labels, fontsize=8)
    ax.invert_yaxis()
    if values:  # a log axis needs a point
        ax.set_xscale("log")
        ax.set_xlim(min(values) / 1.5, max(values) * 6)
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:.0e}"[0] in "25" else ""))
    ax.grid(True, which="both", axis="x", color="0.92")
    ax.set_xlabel(xlabel)
    ax.set_title(title)


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r for r in runs if r.get("kind") == "edit_step" and "ms_step" in r]
    timed = [r for r in runs if r.get("kind") not in ("edit_step", "render_passes") and r.get("seconds") is not None
             and "error" not in r]
    fig, (left, right) = plt.subplots(1, 2, figsize=(15, 1.5 + 0.45 * max(len(steps), len(timed), 1)))
    ratios = [next((f"  ×{r[key]:.2f} vs {against}" for key, against in SAME_CALL_RATIOS if key in r), "") for r in steps]
    _rows_on_log_axis(left, [r["ms_step"] for r in steps],
                      [f"{r['ms_step']:.0f} ms{ratio}" for r, ratio in zip(steps, ratios)],
                      [_plot_label(r) for r in steps], {"color": "#4c72b0"}, "ms per editing step (log scale)",
                      "edit step (×: speed-up within its section's call)")
    _rows_on_log_axis(right, [r["seconds"] for r in timed], [f"{r['seconds']:.1f} s{_memory_text(r)}" for r in timed],
                      [_plot_label(r) for r in timed], {"color": "#dd8452", "marker": "^"}, "seconds (log scale)",
                      f"stages on {runs[0]['device'] if runs else '?'}\n(random weights: costs only)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


class CallTimeLimit(Exception):
    """SIGTERM from the call's time limit: the section in flight records what it has, the later ones do not run."""


SECTION_OF_KIND = {"edit_step": "a", "edit": "b", "reconstruction": "c", "refinement": "d", "job": "f"}


def _section_of(run: dict) -> str:
    """The section that made ``run`` (records written before runs named it: by kind)."""
    return run.get("section") or SECTION_OF_KIND.get(run["kind"], "?")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--smoke", action="store_true", help="CPU, tiny sizes: check the script end to end")
    parser.add_argument("--data", type=Path, default=MIC, help="the nerf_synthetic mic folder")
    parser.add_argument("--out", type=Path, default=None, help="JSON to write (default bench/results/gpu[_smoke].json)")
    parser.add_argument("--skip", default="", help="comma-separated sections to leave out (a,b,c,d,f,h,g,i,l,k,j)")
    parser.add_argument("--fused-marcher", action="store_true",
                        help="sections b and f with the fused ray marcher (VOXE_FUSED_MARCHER for the job's worker); "
                             "their rows say so")
    parser.add_argument("--call", type=int, default=None,
                        help="number of this call on the device: tags its runs (an earlier call's keep theirs)")
    parser.add_argument("--call-note", default=None, help="what this call ran, recorded under the header's calls")
    parser.add_argument("--keep", type=Path, default=None,
                        help="an earlier call's JSON whose runs of the skipped sections are kept (a later call on the "
                             "device re-running the others)")
    args = parser.parse_args(argv)
    profile = dataclasses.replace(Profile.smoke() if args.smoke else Profile.full(), fused_marcher=args.fused_marcher)
    if args.smoke:  # toy-sized ops: OpenMP hand-offs between threads would cost more than they give
        torch.set_num_threads(1)
        os.environ.setdefault("TRITON_INTERPRET", "1")  # section l's kernels on this CPU (before diffusers imports Triton)
    if profile.device == "cuda" and not torch.cuda.is_available():
        print("bench/gpu.py needs a CUDA device (or --smoke)", file=sys.stderr)
        return 2
    out = args.out or RESULTS / ("gpu_smoke.json" if args.smoke else "gpu.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, args.skip.split(",")))
    runs: list[dict] = []
    calls = {}
    if args.keep is not None:
        kept = json.loads(args.keep.read_text())
        runs = [{**r, "section": _section_of(r), "kept_from_earlier_call": True} for r in kept["runs"]
                if _section_of(r) in skip]
        calls = kept.get("calls", {})
    if args.call is not None:
        calls[str(args.call)] = args.call_note or f"sections run: all but {','.join(sorted(skip)) or 'none'}"
    tag = {"call": args.call} if args.call is not None else {}
    started = time.perf_counter()
    header = {"device": torch.cuda.get_device_name() if profile.device == "cuda" else f"{os.cpu_count()} CPU cores",
              "torch": torch.__version__, "smoke": args.smoke, "skipped": sorted(skip),
              "kept_from": str(args.keep) if args.keep else None, "calls": calls,
              "note": "random-weight models: costs only; peak_memory_gb is max_memory_allocated (GiB) on CUDA, "
                      "process RSS peak on CPU"}

    def save() -> None:  # whole or not at all: a SIGTERM may land in the middle
        partial = out.with_suffix(".json.partial")
        partial.write_text(json.dumps({**header, "wall_seconds": time.perf_counter() - started, "runs": runs}, indent=2))
        partial.replace(out)

    terminated: list[CallTimeLimit] = []  # the call's time limit (`timeout` in bench/gpu_device.sh) sent SIGTERM

    def on_sigterm(signum, frame):
        terminated.append(CallTimeLimit("terminated by the call's time limit (SIGTERM)"))
        raise terminated[0]

    def section(name: str, kind: str, body, progress: dict | None = None) -> None:
        """Runs ``body`` and records its runs, or its failure with what ``progress`` holds by then; after a
        SIGTERM the section in flight records that and the later ones do not start."""
        if name in skip or terminated:
            return
        t0 = time.perf_counter()
        try:
            produced = body()
            runs.extend({**r, "section": name, **tag} for r in (produced if isinstance(produced, list) else [produced]))
        except Exception as exc:  # noqa: BLE001 - one section's failure must not lose the others
            traceback.print_exc()
            exc = terminated[0] if terminated else exc  # what the worker's task made of it said otherwise
            error = f"{type(exc).__name__}: {exc}"
            runs.append({"name": f"section {name} failed", "kind": kind, "section": name, "device": profile.device,
                         "error": error, "seconds": time.perf_counter() - t0, **(progress or {}), **tag})
        print(f"section {name} ({kind}): {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        save()

    previous_handler = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        with tempfile.TemporaryDirectory(prefix="voxe_gpu_bench_") as tmp:
            tmp = Path(tmp)
            from voxe_core.tiny_sd import build_tiny_stable_diffusion

            tiny = build_tiny_stable_diffusion(tmp / "tiny", seed=0)
            if args.smoke:
                sd2 = sd14 = tiny
            else:  # built in subprocesses so their memory is returned before the models load
                sd2, sd14 = tmp / "sd2", tmp / "sd14"
                build_start = time.perf_counter()
                for path, family in ((sd2, "sd2-base"), (sd14, "sd1.4")):
                    subprocess.run([sys.executable, str(HERE / "edit_step.py"), "--build-full", str(path),
                                    "--tokenizer-from", str(tiny / "tokenizer"), "--family", family,
                                    "--build-device", profile.device], check=True)
                header["model_build_seconds"] = time.perf_counter() - build_start
            section("a", "edit_step", lambda: edit_step_runs(sd2, profile))
            section("b", "edit", lambda: edit_loop_run(sd2, profile))
            if args.data.is_dir():
                section("c", "reconstruction", lambda: reconstruction_runs(profile, args.data))
            else:
                runs.append({"name": "reconstruction skipped", "kind": "reconstruction",
                             "error": f"no data at {args.data}"})
            section("d", "refinement", lambda: refinement_run(sd14, profile))
            section("h", "render_passes", lambda: render_pass_runs(profile))
            if profile.device == "cuda":  # CUDA graphs exist only there
                section("g", "cuda_graphs", lambda: cuda_graph_runs(sd2, profile, _same_call_baseline(runs)))
            section("i", "edit_step", lambda: step_pass_runs(sd2, profile))
            section("l", "fused_render", lambda: fused_marcher_runs(sd2, profile))
            section("k", "step_profile", lambda: step_profile_run(sd2, profile))
            if profile.device == "cuda":  # after the other step sections: a compile's warm-up is the least predictable
                section("j", "edit_step", lambda: compiled_encoder_runs(sd2, profile))
            loops = [r for r in runs if r.get("section") == "b" and "ms_step" in r  # section b's, the latest call's,
                     and bool(r.get("fused_marcher")) == profile.fused_marcher]  # rendered as the job renders
            loop = max(loops, key=lambda r: r.get("call") or 0) if loops else None
            if args.data.is_dir():
                job_progress = {}
                section("f", "job", lambda: job_run(sd2, sd14, profile, args.data, tmp / "service",
                                                    loop["ms_step"] if loop else None, job_progress), job_progress)
    finally:
        signal.signal(signal.SIGTERM, previous_handler)
    save()
    plot(runs, out.with_suffix(".png"))
    for run in runs:
        figures = {k: round(v, 3) if isinstance(v, float) else v for k, v in run.items()
                   if k in ("ms_step", "edit_8000_minutes", "speedup_over_baseline", "seconds", "psnr", "ssim",
                            "peak_memory_gb", "error")}
        print(f"{run['name']:<60} {figures}")
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 1 if any("error" in r for r in runs if r.get("kind") != "reconstruction" or args.data.is_dir()) else 0


if __name__ == "__main__":
    sys.exit(main())
