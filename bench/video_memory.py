"""Turntable memory: the export before it streamed (every frame rendered into one (N, H, W, 3) float tensor, then the
MP4 and the GIF written from it) against today's (each frame encoded into both as it is rendered), in one run.

Each variant runs in its own process on the same textured sphere grid and turntable (the worker's export flow, an
MP4 and a GIF), one torch thread; its peak is the rise of the kernel's resident-set high-water mark over the work
alone (freed heap trimmed and the mark reset through /proc/self/clear_refs just before it, blocks of 128 KiB and
more mapped alone so that freeing one returns it; ffmpeg's own process is not counted, alike for all). The
rise of rendering one view alone, measured the same way just before, is the floor every variant pays (the
renderer's per-view buffers); the seconds are wall time on a shared machine, not compared.

* ``before``: ``voxe_core/export.py`` as it was at ``--before`` (read with ``git show``): ``render_views`` then
  ``write_video`` of the whole array, once per format;
* ``array``: today's ``write_video`` given ``render_views``' whole array (what a library caller holding the frames
  pays: the stack, not the copies the former conversion made of it);
* ``stream``: today's worker: ``iter_views`` into two ``VideoWriter`` s.

The three variants' files are compared byte for byte and decoded (frames; the GIF's delays). Writes
bench/results/video_memory.json and .png.

    nice python bench/video_memory.py     # the export's default turntable, 100 frames of 256²: ~6 min on 2 cores
    nice python bench/video_memory.py --frames 200 --size 512
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import os
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
BEFORE = "dcfa9ff"  # the last commit whose export held every frame
VARIANTS = ("before", "array", "stream")
FPS = 30.0
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": "131072"}  # every block of 128 KiB or more mapped alone and unmapped when
# freed, so the resident set follows what is alive (glibc's default keeps freed blocks of up to 32 MiB for reuse)


def _reset_peak() -> int:
    """Return freed heap to the system and restart the kernel's high-water mark from here; the resident KiB now."""
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    Path("/proc/self/clear_refs").write_text("5")
    return _kib("VmRSS")


def _kib(field: str) -> int:
    """A /proc/self/status memory field (VmRSS, VmHWM) in KiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


def textured_sphere(resolution: int = 32):
    """A solid sphere whose colour varies around it, so consecutive turntable frames differ (a plain one would fold
    into a single GIF frame)."""
    import torch

    from voxe_core.grid import VoxelGrid

    grid = VoxelGrid(resolution)
    axis = torch.linspace(float(grid.bbox_min[0]), float(grid.bbox_max[0]), resolution)
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")
    with torch.no_grad():
        grid.features[..., 0] = 5.0 * (0.8 - (x * x + y * y + z * z).sqrt()) / float(grid.voxel_size.min())
        grid.features[..., 1:] = 3.0 * torch.stack([torch.sin(6 * x), torch.cos(5 * y), torch.sin(4 * z + 3 * x)], -1)
    return grid


def former_export(rev: str) -> types.ModuleType:
    """``voxe_core/export.py`` as it was at ``rev``, as a module (its imports are today's voxe_core)."""
    source = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:voxe_core/export.py"], capture_output=True,
                            text=True, check=True).stdout
    module = types.ModuleType("export_before")
    exec(compile(source, f"{rev}:voxe_core/export.py", "exec"), module.__dict__)
    return module


def run_variant(variant: str, frames: int, size: int, out: Path, before: str) -> dict:
    """The export's turntable (MP4 + GIF) the variant's way; its peak memory over the work and its seconds."""
    import torch

    from voxe_core import export

    torch.set_num_threads(1)
    grid = textured_sphere()
    cameras = export.turntable_cameras(frames, 30.0, size)
    former = former_export(before) if variant == "before" else None
    paths = [out / f"{variant}.mp4", out / f"{variant}.gif"]
    warm_up = export.turntable_cameras(1, 30.0, size)  # imports, encoders and the renderer's first allocations: not
    for path in paths:  # what the clip costs
        (former or export).write_video(path, (former or export).render_views(grid, warm_up), fps=FPS)
    start_kib = _reset_peak()
    export.render_views(grid, warm_up)  # the floor any variant pays: one view's render
    one_view_mb = (_kib("VmHWM") - start_kib) / 1024
    start_kib, start = _reset_peak(), time.perf_counter()
    if variant == "stream":
        with contextlib.ExitStack() as opened:
            writers = [opened.enter_context(export.VideoWriter(path, frames, FPS)) for path in paths]
            for frame in export.iter_views(grid, cameras):
                for writer in writers:
                    writer.append(frame)
    else:
        module = former or export
        stack = module.render_views(grid, cameras)
        for path in paths:
            module.write_video(path, stack, fps=FPS)
    seconds = time.perf_counter() - start
    return {"variant": variant, "peak_mb": (_kib("VmHWM") - start_kib) / 1024, "one_view_mb": one_view_mb,
            "seconds": seconds}


def decoded(path: Path) -> tuple[list[np.ndarray], list[int]]:
    """(frames, delays in ms; an MP4's are its frame rate's)."""
    if path.suffix == ".mp4":
        import imageio.v2 as imageio

        reader = imageio.get_reader(path, format="FFMPEG")
        try:
            return [frame for frame in reader], [round(1000 / reader.get_meta_data()["fps"])] * reader.count_frames()
        finally:
            reader.close()
    from PIL import Image

    frames, delays = [], []
    with Image.open(path) as gif:
        for index in range(gif.n_frames):
            gif.seek(index)
            frames.append(np.asarray(gif.convert("RGB")))
            delays.append(gif.info["duration"])
    return frames, delays


def compare(out: Path) -> dict:
    """Per format, whether each variant's file equals ``before``'s: bytes, decoded frames, delays."""
    result = {}
    for suffix in ("mp4", "gif"):
        reference_frames, reference_delays = decoded(out / f"before.{suffix}")
        reference_bytes = (out / f"before.{suffix}").read_bytes()
        for variant in VARIANTS[1:]:
            frames, delays = decoded(out / f"{variant}.{suffix}")
            result[f"{variant}.{suffix}"] = {
                "bytes_equal": (out / f"{variant}.{suffix}").read_bytes() == reference_bytes,
                "frames_equal": len(frames) == len(reference_frames)
                and all(np.array_equal(a, b) for a, b in zip(frames, reference_frames)),
                "delays_equal": delays == reference_delays,
                "decoded_frames": len(frames),
            }
    return result


def plot(record: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, summary = record["runs"], record["summary"]
    names, floors = [r["variant"] for r in rows], [r["one_view_mb"] for r in rows]
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.bar(names, floors, color="#ccc", label="one view's render")
    bars = ax.bar(names, [r["peak_mb"] - floor for r, floor in zip(rows, floors)], bottom=floors,
                  color=["#c44", "#888", "#4a4"], label="the clip's frames")
    ax.bar_label(bars, labels=[f"{r['peak_mb']:.0f} MB" for r in rows])
    ax.set_ylabel("peak RSS rise (MB)")
    ax.set_title(f"turntable MP4 + GIF, {summary['frames']} frames of {summary['size']}² "
                 f"(float stack {summary['float_stack_mb']:.0f} MB)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--before", default=BEFORE, help="the commit whose export.py is 'before'")
    parser.add_argument("--variant", choices=VARIANTS, help=argparse.SUPPRESS)  # one variant, in a subprocess
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.variant:
        print(json.dumps(run_variant(args.variant, args.frames, args.size, args.out, args.before)))
        return
    with tempfile.TemporaryDirectory(prefix="video_memory_") as tmp:
        rows = []
        for variant in VARIANTS:
            command = [sys.executable, __file__, "--variant", variant, "--out", tmp, "--frames", str(args.frames),
                       "--size", str(args.size), "--before", args.before]
            rows.append(json.loads(subprocess.run(command, capture_output=True, text=True, check=True,
                                                  env={**os.environ, **MALLOC_ENV}).stdout))
        equality = compare(Path(tmp))
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    stack_mb = args.frames * args.size * args.size * 3 * 4 / 2**20
    peaks = {r["variant"]: r["peak_mb"] for r in rows}
    summary = {"frames": args.frames, "size": args.size, "fps": FPS, "before": args.before, "code": commit,
               "float_stack_mb": stack_mb, "peak_ratio_before_to_stream": peaks["before"] / peaks["stream"],
               "peak_ratio_array_to_stream": peaks["array"] / peaks["stream"],
               "all_files_equal_to_before": all(all(v for k, v in same.items() if k.endswith("_equal"))
                                                for same in equality.values())}
    record = {"runs": rows, "summary": summary, "equal_to_before": equality}
    print(f"turntable MP4 + GIF, {args.frames} frames of {args.size}² (float stack {stack_mb:.0f} MB):")
    print("| variant | peak RSS rise MB | of which one view's render MB | seconds |\n| --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['variant']} | {r['peak_mb']:.1f} | {r['one_view_mb']:.1f} | {r['seconds']:.1f} |")
    print(f"peak before / stream: {summary['peak_ratio_before_to_stream']:.1f}x; "
          f"array / stream: {summary['peak_ratio_array_to_stream']:.1f}x")
    for name, same in equality.items():
        print(f"{name} vs before.{name.split('.')[1]}: {same}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "video_memory.json").write_text(json.dumps(record, indent=2) + "\n")
    plot(record, RESULTS / "video_memory.png")


if __name__ == "__main__":
    main()
