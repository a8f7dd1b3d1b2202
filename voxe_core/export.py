"""Getting results out of a grid: PNG views, turntable videos and meshes.

* ``iter_views`` renders cameras one view at a time (``render_views``: all at once), computing the occupancy once.
* ``turntable_cameras`` is the 360° ring of the evaluation protocol (SPEC §0, §4).
* ``VideoWriter`` writes H.264 MP4 (yuv420p, sizes padded to even) or a looping GIF frame by frame
  (``write_video``: frames at hand).
* ``extract_mesh`` runs marching cubes on the activated density (SPEC §6: users
  asked for mesh export) and ``save_mesh`` writes binary PLY or GLB with vertex colours.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, suppress
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from voxe_core.cameras import Cameras, ring_poses
from voxe_core.constants import MESH_SUFFIXES, NERF_SYNTHETIC_FOV_X, NERF_SYNTHETIC_RADIUS, VIDEO_SUFFIXES
from voxe_core.devices import PeakMemory, full_precision, resolve_device
from voxe_core.files import naming_write_failures, replacing
from voxe_core.grid import VoxelGrid
from voxe_core.presets import check_video_fps
from voxe_core.progress import Callbacks, Progress
from voxe_core.render import RenderConfig, composite, render_image
from voxe_core.volrend import RaySamples

_QUERY_CHUNK = 1 << 18  # points per grid query when sampling a mesh or a resampled lattice


# ---------------------------------------------------------------------- images
def to_uint8(image) -> np.ndarray:
    """Float image(s) in [0, 1] -> uint8 with rounding; values outside [0, 1] are clamped.

    uint8 images are 8-bit pixels already and are returned as they are (read as floats, any pixel above 1 had
    become white). Other integer types say neither scale: ValueError."""
    array = torch.as_tensor(image).detach().cpu()
    if array.dtype == torch.uint8:
        return array.numpy()
    if not (array.dtype.is_floating_point or array.dtype == torch.bool):
        raise ValueError(f"images are floats in [0, 1] or uint8 pixels, got {array.dtype}")
    array = torch.nan_to_num(array.float(), nan=0.0).clamp(0.0, 1.0)
    return (array * 255.0).round().to(torch.uint8).numpy()


def save_png(path: str | os.PathLike, image) -> None:
    """Write an (H, W, 3) or (H, W, 4) image (floats in [0, 1] or uint8) as an 8-bit PNG (parent folders created),
    whole or not at all (:func:`voxe_core.files.replacing`: a full disk had left a torn PNG in place of the earlier
    one)."""
    from PIL import Image

    array = to_uint8(image)
    if array.ndim != 3 or array.shape[-1] not in (3, 4):
        raise ValueError(f"save_png expects an (H, W, 3) or (H, W, 4) image, got shape {tuple(array.shape)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with replacing(path) as partial:
        Image.fromarray(array, "RGB" if array.shape[-1] == 3 else "RGBA").save(partial, format="PNG")


# --------------------------------------------------------------------- renders
@torch.no_grad()
def iter_views(
    grid: VoxelGrid,
    cameras: Cameras,
    config: RenderConfig = RenderConfig(),
    callbacks: Callbacks = Callbacks(),
    device: torch.device | str | None = None,
) -> Iterator[torch.Tensor]:
    """Render every camera, one view at a time: yields each (H, W, 3) on ``config.background``, on the CPU.

    A caller that writes each view as it comes (a :class:`VideoWriter`, PNGs) holds one frame, not all of them
    (1,000 turntable frames of 2,048² had been 50 GB of floats at once).
    Renders run on ``device`` (None: where the grid is); grid (in place, as
    ``nn.Module.to``) and cameras move there once, at the first view. The occupancy structure is
    built once for all views. ``callbacks`` gets a ``Progress("render", i, N)``
    after each view (info: peak memory, :class:`voxe_core.devices.PeakMemory`)
    and may cancel between views.
    """
    device = resolve_device(device if device is not None else grid.bbox_min.device)
    memory = PeakMemory(device).start()
    grid, cameras = grid.to(device), cameras.to(device)
    occupancy = grid.occupancy(config.sigma_threshold) if config.skip_empty else None
    for i in range(len(cameras)):
        callbacks.check_cancel("render")
        frame = render_image(grid, cameras, i, config, occupancy).rgb[..., :3].cpu()
        callbacks.progress(Progress("render", i + 1, len(cameras), info=memory.info()))
        yield frame


def render_views(
    grid: VoxelGrid,
    cameras: Cameras,
    config: RenderConfig = RenderConfig(),
    callbacks: Callbacks = Callbacks(),
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """:func:`iter_views`' views all at once: (N, H, W, 3), on the CPU, for callers that need them together."""
    frames = torch.empty(len(cameras), cameras.height, cameras.width, 3)
    for i, frame in enumerate(iter_views(grid, cameras, config, callbacks, device)):
        frames[i] = frame
    return frames


def turntable_cameras(
    n_frames: int = 180,
    elevation_deg: float = 30.0,
    size: int = 256,
    fov_x: float = NERF_SYNTHETIC_FOV_X,
    radius: float = NERF_SYNTHETIC_RADIUS,
    centre: torch.Tensor | None = None,
) -> Cameras:
    """``n_frames`` square cameras evenly on a 360° ring ``elevation_deg`` above the horizon, looking at ``centre``.

    ``centre``: the grid's ``orbit_centre()`` (None: the origin, where an object grid's object sits), so a
    capture whose object is off its frame's origin stays in the middle of every frame. ``elevation_deg`` lies in
    [-90, 90] (ValueError otherwise): past the pole, 120 had turned the ring over, each camera upside down on the far
    side of the azimuth asked for.
    """
    if n_frames < 1 or size < 1:
        raise ValueError(f"a turntable needs at least one frame of at least 1 pixel, got {n_frames} frames of {size}")
    if not -90.0 <= elevation_deg <= 90.0:  # (NaN too)
        raise ValueError(f"a turntable's elevation must lie between -90 and 90 degrees, got {elevation_deg:g}")
    return Cameras.from_fov(ring_poses(n_frames, elevation_deg, radius, centre), fov_x, size, size)


# ---------------------------------------------------------------------- videos
def _pad_even(frame: np.ndarray) -> np.ndarray:
    """Replicate the last row / column so height and width are even (yuv420p subsamples chroma 2x2)."""
    h, w, _ = frame.shape
    if h % 2 or w % 2:
        frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    return frame


GIF_MIN_DELAY_CS = 2
"""GIF delays are whole centiseconds, and browsers play 0 or 1 as 10 (about 10 fps): 2 is the shortest kept."""
GIF_MAX_DELAY_CS = 65535
"""A GIF frame's delay is 16 bits of centiseconds (655.35 s): a frame shown longer is written again."""


def gif_timeline(n_frames: int, fps: float) -> tuple[list[int], list[int]]:
    """(the frames a GIF shows, each one's delay in ms): the delays are whole centiseconds whose running sum
    follows the true timeline (30 fps: 30, 30, 40 ms, ...), and above 50 fps every k-th frame is kept so no delay
    is under ``GIF_MIN_DELAY_CS``. The total is n_frames / fps to the centisecond (a clip shorter than 2 cs per
    shown frame lasts that).

    Examples:
        >>> gif_timeline(4, 30.0)
        ([0, 1, 2, 3], [30, 40, 30, 30])
        >>> gif_timeline(6, 120.0)  # every 3rd frame: 40 fps
        ([0, 3], [20, 30])
    """
    step = max(1, math.ceil(fps * GIF_MIN_DELAY_CS / 100 - 1e-9))
    shown = list(range(0, n_frames, step))
    ends = [round(min(i + step, n_frames) * 100 / fps) for i in shown]  # each shown frame lasts to the next one
    starts = [round(i * 100 / fps) for i in shown]
    return shown, [10 * max(GIF_MIN_DELAY_CS, end - start) for start, end in zip(starts, ends)]


def check_video_output(path: str | os.PathLike, fps: float) -> Path:
    """``path`` as a Path, or ValueError for a suffix or frame rate no video takes (checked before any rendering)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"unsupported video suffix {path.suffix!r} for {path}; use one of {', '.join(VIDEO_SUFFIXES)}")
    check_video_fps(fps)
    return path


MP4_MAX_SIDE = 16384
"""The widest and tallest frame libx264 encodes ("invalid width x height")."""
MP4_MAX_PADDED_AREA = 2**28
"""ffmpeg refuses a frame whose (W + 128)·(H + 128) reaches this ("Picture size 16256x16256 is invalid"): a square
MP4 is at most 16254 pixels a side."""
GIF_MAX_SIDE = 65535  # a GIF's screen is 16 bits wide and high (Pillow had overflowed: "int too big to convert")


def check_video_size(path: str | os.PathLike, width: int, height: int) -> None:
    """ValueError for frames of a size the video at ``path`` cannot hold (its suffix picks the format): cheap, so
    checked before rendering; the encoder had refused them after the first frame's render."""
    if Path(path).suffix.lower() == ".mp4":
        padded_w, padded_h = width + width % 2, height + height % 2  # (as :func:`_pad_even` pads them)
        if max(padded_w, padded_h) > MP4_MAX_SIDE or (padded_w + 128) * (padded_h + 128) >= MP4_MAX_PADDED_AREA:
            raise ValueError(f"an MP4 holds frames of at most {MP4_MAX_SIDE} pixels a side whose (width + 128) x "
                             f"(height + 128) is under {MP4_MAX_PADDED_AREA:,} (16254x16254 at most, square), got "
                             f"{width}x{height}: make them smaller, or write a GIF")
    elif max(width, height) > GIF_MAX_SIDE:
        raise ValueError(f"a GIF holds frames of at most {GIF_MAX_SIDE} pixels a side, got {width}x{height}")


class VideoEncoderError(OSError):
    """An encode that failed, with the errno its log names (None: none) and its file as ``filename``, never in the
    words (a worker's failure text leaves the files of its disk out). Its own type whatever the errno: an OSError
    made with EPIPE becomes a BrokenPipeError, which the CLI reads as its output's reader gone (exit 141, said
    nothing)."""

    def __str__(self) -> str:
        return super().__str__() if self.errno is not None else f"{self.strerror}: {self.filename}"


class _Mp4Encoder:
    """ffmpeg encoding the RGB frames piped to it into an H.264 MP4 at ``path`` (started at the first frame, which
    gives the size), its exit status checked: imageio-ffmpeg's writer, used before, never read it, so an encode that
    failed (a full disk: "Error writing trailer: No space left on device") had left a torn MP4 as if written.
    ``shown_as``: the file ``path`` becomes, which its errors name. ffmpeg is given ``path`` absolute: a relative
    name with a ':' ('.a:b.<token>.partial.mp4', of 'a:b.mp4') is one it reads as a protocol's URL ("Protocol not
    found")."""

    OUTPUT_OPTIONS = ("-vcodec", "libx264", "-pix_fmt", "yuv420p", "-v", "error", "-colorspace", "smpte170m",
                      "-color_range", "tv", "-crf", "18", "-preset", "medium", "-movflags", "+faststart")

    def __init__(self, path: Path, fps: float, shown_as: Path):
        self.path, self.fps, self.shown_as = path.absolute(), fps, shown_as
        self._process: subprocess.Popen | None = None
        self._log: list[bytes] = []  # ffmpeg's stderr, read by a thread (a full pipe would stall it)
        self._log_reader: threading.Thread | None = None

    def write(self, pixels: np.ndarray) -> None:
        """Pipe one (H, W, 3) uint8 frame to ffmpeg; the OSError of :meth:`close` if ffmpeg has stopped."""
        if self._process is None:
            self._start(width=pixels.shape[1], height=pixels.shape[0])
        try:
            self._process.stdin.write(np.ascontiguousarray(pixels).data)
        except BrokenPipeError:  # ffmpeg exited: its log says why (the broken pipe's EPIPE would hide a full disk)
            self._process.wait()
            raise self._failure(self._process.returncode, self._read_log()) from None

    def close(self) -> None:
        """Let ffmpeg finish the file; an OSError if it failed, with the errno its log names (ENOSPC for a full
        disk)."""
        with suppress(BrokenPipeError):  # (flushing to an ffmpeg that has exited, which its status says)
            self._process.stdin.close()
        returncode = self._process.wait()
        log = self._read_log()
        if returncode != 0:
            raise self._failure(returncode, log)
        if log and sys.stderr is not None:  # (a process started without a stderr has None)
            sys.stderr.write(log)  # what it said of an encode that succeeded (imageio-ffmpeg left it on stderr too)

    def stop(self) -> None:
        """Kill ffmpeg if it is still running (a render that failed or was cancelled: its file is not wanted)."""
        if self._process is None or self._process.returncode is not None:
            return
        self._process.kill()
        with suppress(BrokenPipeError):
            self._process.stdin.close()
        self._process.wait()
        self._read_log()

    def _start(self, width: int, height: int) -> None:
        import imageio_ffmpeg

        rate = Fraction(self.fps).limit_denominator()  # (as imageio-ffmpeg gives it: 24000/1001 is not rounded)
        command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-f", "rawvideo", "-vcodec", "rawvideo", "-s",
                   f"{width}x{height}", "-pix_fmt", "rgb24", "-r", str(rate), "-i", "-", "-an", *self.OUTPUT_OPTIONS,
                   str(self.path)]
        # its own process group: a Ctrl-C at the terminal (a worker's warm shutdown, which lets the job finish) does
        # not stop the encoder of a video still wanted; one that reaches the render stops it (:meth:`stop`)
        # in the C locale: its log's system errors in English, the words the errno is read from
        self._process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                         stderr=subprocess.PIPE, process_group=0, env={**os.environ, "LC_ALL": "C"})
        self._log_reader = threading.Thread(target=lambda: self._log.append(self._process.stderr.read()), daemon=True)
        self._log_reader.start()

    def _read_log(self) -> str:
        """What ffmpeg, which has exited, wrote to stderr; the file it wrote named as the caller knows it."""
        self._log_reader.join()
        self._process.stderr.close()
        return b"".join(self._log).decode(errors="replace").replace(str(self.path), self.shown_as.name)

    def _failure(self, returncode: int, log: str) -> VideoEncoderError:
        """The error of an encode that failed: its first logged line (the cause; later ones are its consequences),
        and the errno of the first system error the log names, so a caller can tell a full disk."""
        lines = [re.sub(r"^\[[^]]* @ 0x[0-9a-f]+\] ", "", line) for line in log.splitlines() if line.strip()]
        status = f"exited with status {returncode}" if returncode > 0 else f"was killed by signal {-returncode}"
        words = f"the video encoder failed (ffmpeg {status}" + (f": {lines[0]})" if lines else ")")
        named = [(log.find(os.strerror(code)), -len(os.strerror(code)), code) for code in errno.errorcode
                 if os.strerror(code) in log]  # (of two alike, the longer: "No such device or address")
        return VideoEncoderError(min(named)[2] if named else None, words, str(self.shown_as))


class VideoWriter:
    """A video of ``n_frames`` frames written as they come (``append``), so a caller that renders as it writes
    holds one frame, not the clip; the suffix picks the format. Used as a context manager::

        with VideoWriter(path, len(cameras), fps) as video:
            for frame in iter_views(grid, cameras):
                video.append(frame)

    ``.mp4``: H.264 (libx264, CRF 18, yuv420p, +faststart) by ffmpeg (imageio-ffmpeg's), each frame piped to it
    as it is appended; odd sizes are padded by one replicated row / column, never rescaled. The stream is tagged
    with the matrix its pixels were converted by (BT.601, limited range): untagged, a player that guesses BT.709
    for it had shown the render's red (250, 5, 5) as (255, 27, 1) and its greens 20 levels dimmer.
    ``.gif``: palette GIF through Pillow, looping forever, on :func:`gif_timeline`'s whole-centisecond delays
    (above 50 fps some frames are left out). Each shown frame is quantised to its own 256-colour palette and
    written once the next shown frame differs from it (Pillow's GIF encoder, which takes the clip at once, had held
    every frame until the end: 4 GB for 1,000 frames of 2,048²); a frame identical to the one before lengthens it
    (so a static scene can decode to fewer frames; the total duration is kept), and a frame that differs is written
    as the rectangle that changed, drawn over the one before.
    The video is written beside ``path`` under a temporary name and renamed when whole, at the end of the block:
    an error in it (a cancelled render), a frame of another shape, too few or too many frames, or an encoder that
    failed leave nothing, and the file already at ``path`` as it was (an OSError for the encoder, with the errno its
    log names: ENOSPC for a full disk; or when it wrote no file).
    """

    def __init__(self, path: str | os.PathLike, n_frames: int, fps: float = 30):
        self.path = check_video_output(path, fps)
        if n_frames < 1:
            raise ValueError(f"a video needs frames shaped (N, H, W, 3) with N >= 1, got {n_frames} frames")
        self.n_frames, self.fps, self.appended = n_frames, fps, 0
        self._files: ExitStack | None = None  # set while open
        self._shape: tuple[int, ...] | None = None
        self._mp4 = None
        shown, delays = gif_timeline(n_frames, fps)
        self._gif_delays = dict(zip(shown, delays))  # ms, of each shown frame
        self._gif_file = None  # the GIF's partial file, while open
        self._gif_pending: list | None = None  # [palette image, delay in ms, changed box or None] not written yet

    def __enter__(self) -> "VideoWriter":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with ExitStack() as files:
            self._partial = files.enter_context(replacing(self.path))
            if self.path.suffix.lower() == ".mp4":
                self._mp4 = _Mp4Encoder(self._partial, self.fps, self.path)
                files.callback(self._mp4.stop)  # on an error in the block: before the partial file is removed
            else:
                self._gif_file = files.enter_context(open(self._partial, "wb", buffering=0))  # each frame on disk
            self._files = files.pop_all()
        return self

    def append(self, frame) -> None:
        """Add the next frame (H, W, 3), floats in [0, 1] or uint8, of the first frame's size."""
        if self._files is None:  # an MP4's encoder starts with the block: a GIF's frames would go nowhere
            raise RuntimeError(f"VideoWriter({self.path.name}): append within its with block")
        pixels = to_uint8(frame)
        if pixels.ndim != 3 or pixels.shape[-1] != 3 or pixels.shape != (self._shape or pixels.shape):
            raise ValueError(f"a video's frames are shaped (H, W, 3), all of one size: frame {self.appended} is "
                             f"{tuple(pixels.shape)}" + (f", frame 0 {self._shape}" if self._shape else ""))
        if self.appended == self.n_frames:
            raise ValueError(f"{self.path.name} was opened for {self.n_frames} frames; one more was given")
        if self._shape is None:  # (the encoder's own refusal had said it in ffmpeg's words)
            check_video_size(self.path, pixels.shape[1], pixels.shape[0])
        self._shape = pixels.shape
        if self._mp4 is not None:
            self._mp4.write(_pad_even(pixels))
        elif self.appended in self._gif_delays:
            self._add_gif_frame(pixels, self._gif_delays[self.appended])
        self.appended += 1

    def __exit__(self, kind, error, traceback) -> None:
        if kind is not None:  # the encoder closed, the partial file removed; the error goes on
            self._files.__exit__(kind, error, traceback)
            return
        with self._files:  # then renamed into place, or removed on an error here
            if self.appended != self.n_frames:
                raise ValueError(f"{self.path.name} was opened for {self.n_frames} frames; {self.appended} were given")
            if self._mp4 is not None:
                self._mp4.close()
            else:
                self._write_gif_frame(*self._gif_pending)
                self._gif_file.write(b";")  # the trailer
            if not self._partial.is_file() or self._partial.stat().st_size == 0:
                raise OSError(f"the video encoder wrote nothing for {self.path}")

    def _add_gif_frame(self, pixels: np.ndarray, delay_ms: int) -> None:
        """Quantise the next shown frame; write the one before once it is known to differ (its delay is final)."""
        from PIL import GifImagePlugin, Image, ImageChops

        image = Image.fromarray(pixels).convert("P", palette=Image.Palette.ADAPTIVE)
        if self._gif_pending is None:  # the first: its palette is the global one, and the screen its size
            header, _ = GifImagePlugin.getheader(image, info={"loop": 0})
            self._gif_file.write(b"".join(header))
            self._gif_pending = [image, delay_ms, None]
            return
        changed = ImageChops.difference(self._gif_pending[0].convert("RGB"), image.convert("RGB")).getbbox()
        if changed is None and self._gif_pending[1] + delay_ms <= 10 * GIF_MAX_DELAY_CS:
            self._gif_pending[1] += delay_ms  # as Pillow folds a repeated frame: the one before shows longer
            return
        # (a repeat past the longest delay, which Pillow's encoder had overflowed on after the whole render, is
        self._write_gif_frame(*self._gif_pending)  # written again as one unchanged pixel)
        self._gif_pending = [image, delay_ms, changed or (0, 0, 1, 1)]

    def _write_gif_frame(self, image, delay_ms: int, changed: tuple[int, int, int, int] | None) -> None:
        """One frame: the first whole on the global palette, a later one the box that changed, with its own."""
        from PIL import GifImagePlugin

        if changed is None:
            chunks = GifImagePlugin.getdata(image, duration=delay_ms)
        else:
            chunks = GifImagePlugin.getdata(image.crop(changed), offset=changed[:2], duration=delay_ms,
                                            include_color_table=True)
        self._gif_file.write(b"".join(chunks))


def write_video(path: str | os.PathLike, frames, fps: float = 30, n_frames: int | None = None) -> Path:
    """Write ``frames`` to ``path`` through a :class:`VideoWriter` (its doc: formats, a file whole or absent).

    ``frames``: an (N, H, W, 3) array or a sequence of (H, W, 3) frames, floats in [0, 1] or uint8; or any iterable
    of frames (a generator of renders, :func:`iter_views`) with ``n_frames`` its length, each frame encoded as it
    comes.
    """
    if n_frames is None:
        if not hasattr(frames, "__len__"):
            raise TypeError(f"write_video needs n_frames for frames of no length (a {type(frames).__name__})")
        n_frames = len(frames)
    try:
        with VideoWriter(path, n_frames, fps) as video:
            for frame in frames:
                video.append(frame)
    finally:  # a generator of renders left by an error lets go of its grid now, not with the traceback
        if hasattr(frames, "close"):
            frames.close()
    return video.path


# ---------------------------------------------------------------------- meshes
def default_mesh_level(grid: VoxelGrid) -> float:
    """The density at which one voxel length of matter is half opaque: sigma = ln 2 / voxel.

    A path of one (smallest) voxel edge through density sigma has alpha
    1 - exp(-sigma·voxel); it reaches 0.5 at sigma = ln 2 / voxel. Denser than
    that, a voxel-thick shell already hides half of what lies behind it, so
    the level set sits where renders show a surface, independent of the grid's
    resolution and scene unit.
    """
    return math.log(2.0) / float(grid.voxel_size.min())


def _lattice_density(grid: VoxelGrid, lo: torch.Tensor, hi: torch.Tensor, spacing: torch.Tensor) -> torch.Tensor:
    """Activated density at lattice points bbox_min + i·spacing, lo <= i <= hi (per axis), in float32 whatever autocast
    says (a caller's bf16 autocast had run the interpolation's bmm in bf16: vertices up to 2e-4 off)."""
    axes = [
        torch.arange(int(lo[d]), int(hi[d]) + 1, dtype=torch.float32) * spacing[d] + grid.bbox_min[d] for d in range(3)
    ]
    shape = tuple(len(a) for a in axes)
    out = torch.empty(shape)
    plane = shape[1] * shape[2]
    yz = torch.stack(torch.meshgrid(axes[1], axes[2], indexing="ij"), -1).reshape(-1, 2)
    slabs = max(1, _QUERY_CHUNK // plane)
    for start in range(0, shape[0], slabs):
        xs = axes[0][start : start + slabs]
        points = torch.cat([xs.repeat_interleave(plane)[:, None], yz.repeat(len(xs), 1)], dim=1)
        with full_precision(points):
            raw = grid.interpolate(points)[:, 0]
        out[start : start + len(xs)] = grid.activate_density(raw).reshape(len(xs), shape[1], shape[2])
    return out


SURFACE_COLOUR_SPAN = (-1.0, 3.0)
"""Where along its inward normal a mesh vertex's colour is composited from: voxels from the vertex, outside to in."""
SURFACE_COLOUR_SAMPLES = 8  # half a voxel apart, the renderer's default step


@torch.no_grad()
def extract_mesh(grid: VoxelGrid, level: float | None = None, resolution: int | None = None,
                 colour_samples: int = SURFACE_COLOUR_SAMPLES):
    """Marching cubes on the activated density -> ``trimesh.Trimesh`` in world coordinates.

    The mesh is of ``grid.foreground_grid()``: a scene grid's object in its canonical frame.

    ``level``: density of the surface, default :func:`default_mesh_level`
    (ln 2 / voxel size, computed on the grid's own voxels whatever ``resolution``).
    ``resolution``: sample the density on a lattice of this many points per axis
    across the grid's box (trilinear on the raw features, then activated, as the
    renderer does) instead of the grid's own vertices.

    Only the box around cells denser than ``level``, padded by one voxel, is
    processed. Outside the grid's box the density is 0 (as in the renderer), so
    matter touching the box is capped on the box faces and the mesh stays
    closed. Vertex colours (uint8 RGBA) are what a render shows there: :func:`_surface_colours`, from
    ``colour_samples`` samples per vertex (bench/mesh_colours.py weighs their cost against their error).
    Raises ``ValueError`` when no density crosses ``level``, or a feature is NaN or infinite (a damaged grid).
    """
    import trimesh
    from skimage.measure import marching_cubes

    if colour_samples < 1:
        raise ValueError(f"a vertex's colour needs at least 1 sample, got colour_samples={colour_samples}")
    grid = grid.foreground_grid()  # a scene grid's object, not its background
    if grid.bbox_min.device.type != "cpu":  # marching cubes runs on the CPU; leave the caller's grid where it is
        grid = VoxelGrid(
            grid.resolution, grid.bbox_min.cpu(), grid.bbox_max.cpu(), grid.activation, grid.density_scale,
            features=grid.features.detach().cpu(),
        )
    level = default_mesh_level(grid) if level is None else float(level)
    if not math.isfinite(level) or level <= 0:
        raise ValueError(f"mesh level must be a positive density, got {level}")
    unknown = int(grid.features[..., 0].detach().isnan().sum())
    if unknown:
        raise ValueError(f"grid density is NaN at {unknown} vertices, so its surface is undefined there "
                         "(a diverged fit or edit?)")
    from voxe_core.reconstruct import check_finite_grid  # (NaN colours had been exported as black, silently)

    check_finite_grid(grid, "the vertex colouring", what="the grid", where="the mesh's colours")
    occupancy = grid.occupancy_above(level)
    if occupancy.empty:
        peak = float(grid.activate_density(grid.features[..., 0].detach()).max())
        raise ValueError(
            f"grid has no surface at level {level:.4g}: its highest density is {peak:.4g}; "
            "pass a lower level (or fit the grid longer)"
        )
    cells = occupancy.cells.nonzero()
    native_res = torch.tensor(grid.resolution)
    voxel = grid.voxel_size.cpu()
    if resolution is None:
        # Vertices of the occupied cells are [lo, hi + 1]; pad one voxel each side, inside the grid.
        lo = (cells.min(0).values - 1).clamp_min(0)
        hi = torch.minimum(cells.max(0).values + 2, native_res - 1)
        spacing = voxel
        raw = grid.features[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1, 0].detach()
        density = grid.activate_density(raw)
    else:
        if resolution < 2:
            raise ValueError(f"mesh resolution must be at least 2, got {resolution}")
        spacing = (grid.bbox_max - grid.bbox_min).cpu() / (resolution - 1)
        box_lo = (cells.min(0).values - 1).clamp_min(0) * voxel  # relative to bbox_min
        box_hi = torch.minimum(cells.max(0).values + 2, native_res - 1) * voxel
        lo = (box_lo / spacing).floor().long().clamp(0, resolution - 1)
        hi = (box_hi / spacing).ceil().long().clamp(0, resolution - 1)
        density = _lattice_density(grid, lo, hi, spacing)
    # One layer of zero density all round: what lies beyond the crop is empty
    # (or outside the box, where the renderer sees nothing), so surfaces close.
    volume = np.pad(density.double().numpy(), 1, mode="constant", constant_values=0.0)
    if not (volume.max() > level):
        raise ValueError(f"grid has no surface at level {level:.4g} (resampled density never exceeds it)")
    # 'ascent': density grows inwards, so faces wind counter-clockwise seen from outside (outward normals).
    verts, faces, _normals, _values = marching_cubes(
        volume, level=level, spacing=tuple(spacing.double().tolist()), gradient_direction="ascent"
    )
    origin = (grid.bbox_min.cpu().double() + (lo.double() - 1) * spacing.double()).numpy()  # -1: the zero pad
    verts = verts + origin
    box = grid.bbox_min.cpu().double().numpy(), grid.bbox_max.cpu().double().numpy()
    verts, faces = _weld_on_box(np.clip(verts, *box), faces, box, tolerance=1e-4 * spacing.double().numpy())
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False)
    colors = np.full((len(verts), 4), 255, dtype=np.uint8)
    colors[:, :3] = _surface_colours(grid, mesh.vertices, mesh.vertex_normals, colour_samples)
    mesh.visual.vertex_colors = colors
    return mesh


def _surface_colours(grid: VoxelGrid, verts: np.ndarray, normals: np.ndarray,
                     samples: int = SURFACE_COLOUR_SAMPLES) -> np.ndarray:
    """(V, 3) uint8: at each vertex, the colour a ray meeting the surface there head-on composites
    (:func:`voxe_core.render.composite`, the renderer's own arithmetic), from ``samples`` evenly spaced over
    :data:`SURFACE_COLOUR_SPAN` along the inward normal, as an opaque surface's (divided by the ray's opacity).

    The colour at the vertex itself had been the mesh's: on the level set the raw colour is interpolated with the
    empty vertices just outside, whose colour no render shows (a fit leaves them near their grey start), so a red
    object (230, 25, 25 in its renders) had come out a pinkish grey (146, 109, 109). A vertex whose span holds no
    density keeps its own colour. In float32 whatever autocast says, as the renderer (a caller's bf16 autocast had run
    the lookups' bmm in bf16)."""
    voxel = float(grid.voxel_size.min())
    first, last = SURFACE_COLOUR_SPAN
    step = (last - first) / samples
    depths = torch.tensor([(first + (k + 0.5) * step) * voxel for k in range(samples)])
    points = torch.tensor(np.asarray(verts), dtype=torch.float32)
    inward = -torch.tensor(np.asarray(normals), dtype=torch.float32)
    colours = np.empty((len(verts), 3), dtype=np.uint8)
    per_chunk = max(1, _QUERY_CHUNK // samples)
    for start in range(0, len(points), per_chunk):
        at, towards = points[start : start + per_chunk], inward[start : start + per_chunk]
        along_normal = RaySamples(
            ray=torch.arange(len(at)).repeat_interleave(samples),
            t=depths.repeat(len(at)),
            delta=torch.full((len(at) * samples,), step * voxel),
            points=(at[:, None, :] + depths[None, :, None] * towards[:, None, :]).reshape(-1, 3),
        )
        with full_precision(at):
            ray = composite([along_normal], grid.query, len(at), torch.zeros(3))
            colour = ray.rgb / ray.opacity.clamp_min(1e-12)[:, None]
            empty = (ray.opacity <= 1e-6).nonzero().squeeze(1)
            if len(empty):
                colour[empty] = grid.query(at[empty])[1].float()
        colours[start : start + per_chunk] = to_uint8(colour)
    return colours


def _weld_on_box(verts: np.ndarray, faces: np.ndarray, box: tuple[np.ndarray, np.ndarray], tolerance: np.ndarray):
    """(verts, faces) with one vertex per position on the box's surface, and the triangles that leaves without
    area dropped. Coordinates within ``tolerance`` (per axis) of a box plane are first put on it.

    Clipping moves the crossings beyond the box onto its faces, where those at its edges and corners coincide: a
    grid full to its box had a quarter of its triangles of zero area, and every reader that welds equal vertices
    (trimesh's load, MeshLab, Blender's merge by distance) found the capped surface open along the box's edges.
    Only the vertices on the box are compared (sorting all of a mesh of millions took most of a minute).
    The lattice's last plane is not exactly on the box when its voxel size is not exact in binary (a box of
    ±1.2 puts it at 1.2000000179, the box at 1.2000000477), so without the snap its vertices stayed 3e-8 from
    the clipped ones, in slivers that readers welding within 1e-8 left open."""
    near_min, near_max = verts - box[0] <= tolerance, box[1] - verts <= tolerance  # verts lie in the box
    on_box = np.flatnonzero((near_min | near_max).any(1))
    if len(on_box) == 0:
        return verts, faces
    verts = verts.copy()
    verts[on_box] = np.where(near_min[on_box], box[0], np.where(near_max[on_box], box[1], verts[on_box]))
    _, first, same = np.unique(verts[on_box], axis=0, return_index=True, return_inverse=True)
    index = np.arange(len(verts))
    index[on_box] = on_box[first][same.reshape(-1)]
    faces = index[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    used = np.zeros(len(verts), dtype=bool)
    used[faces] = True  # the welded-away vertices, and any whose every triangle collapsed, go
    return verts[used], (np.cumsum(used) - 1)[faces]


def save_mesh(mesh, path: str | os.PathLike) -> Path:
    """Write ``mesh`` by suffix: ``.ply`` (binary, with vertex colours), ``.glb`` (:func:`glb_bytes`) or
    ``.obj`` (Wavefront, with its ``.mtl`` beside it: :func:`save_obj`). PLY and OBJ keep the grid's frame (z up)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"unsupported mesh suffix {path.suffix!r} for {path}; use one of {', '.join(MESH_SUFFIXES)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".obj":
        return save_obj(mesh, path)
    data = mesh.export(file_type="ply", encoding="binary") if suffix == ".ply" else glb_bytes(mesh)
    with replacing(path) as partial:
        partial.write_bytes(data)
    return path


GLTF_FROM_GRID = (-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))
"""The glb root node's rotation (quaternion x, y, z, w): -90° about x turns the grid's +z up onto glTF's +y up,
(x, y, z) -> (x, z, -y), as Blender's glTF exporter turns its z-up scenes."""


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (the IEC 61966-2-1 curve)."""
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)


def glb_bytes(mesh) -> bytes:
    """``mesh`` as a glTF 2.0 binary that glTF viewers (the web UI's model-viewer, three.js, Blender) show as the
    renders do. trimesh's own export had broken three of the format's rules: glTF is +y up (the grid is +z up, so
    an upright object lay on its back), COLOR_0 is linear light (the renders' sRGB colours showed washed out) and
    a primitive without a material gets the default one, fully metallic (the colours showed as dull metal).

    So: the vertices in the grid's frame under a root node turned by :data:`GLTF_FROM_GRID`, COLOR_0 the vertex
    colours made linear as float32 (8 bits of linear light would band the dark tones) and a matte, non-metallic
    white material that shows them as they are. A mesh without faces is refused (glTF allows no empty accessor).
    """
    if len(mesh.faces) == 0:
        raise ValueError(f"a mesh without faces ({len(mesh.vertices)} vertices) cannot be written as glTF")
    positions = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    colors = srgb_to_linear(np.asarray(mesh.visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0).astype(np.float32)
    indices = np.ascontiguousarray(mesh.faces, dtype=np.uint32).reshape(-1)
    blobs = [indices.tobytes(), positions.tobytes(), colors.tobytes()]  # each a multiple of 4 bytes
    offsets = np.cumsum([0] + [len(blob) for blob in blobs]).tolist()
    views = [{"buffer": 0, "byteOffset": offsets[i], "byteLength": len(blob), "target": target}
             for i, (blob, target) in enumerate(zip(blobs, (34963, 34962, 34962)))]  # element array, array buffers
    accessors = [
        {"bufferView": 0, "componentType": 5125, "count": len(indices), "type": "SCALAR"},  # uint32
        {"bufferView": 1, "componentType": 5126, "count": len(positions), "type": "VEC3",  # float32
         "min": positions.min(0).tolist(), "max": positions.max(0).tolist()},
        {"bufferView": 2, "componentType": 5126, "count": len(colors), "type": "VEC3"},
    ]
    document = {
        "asset": {"version": "2.0", "generator": "voxe_core.export"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "voxe", "mesh": 0, "rotation": list(GLTF_FROM_GRID)}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 1, "COLOR_0": 2}, "indices": 0, "material": 0,
                                    "mode": 4}]}],
        "materials": [{"name": "voxe", "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                                                "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": offsets[-1]}],
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned: JSON padded with spaces
    binary = b"".join(blobs)
    chunks = [(text, b"JSON"), (binary, b"BIN\0")]
    body = b"".join(len(data).to_bytes(4, "little") + kind + data for data, kind in chunks)
    return b"glTF" + (2).to_bytes(4, "little") + (12 + len(body)).to_bytes(4, "little") + body


def save_obj(mesh, path: str | os.PathLike) -> Path:
    """Wavefront OBJ with per-vertex colours (``v x y z r g b``, colours in [0, 1]: the extension MeshLab,
    Blender and trimesh read) and a material library ``<stem>.mtl`` beside it whose diffuse colour is the
    mean vertex colour, for importers that ignore vertex colours. Faces are 1-based, counter-clockwise
    seen from outside (as :func:`extract_mesh` winds them). Through a symlink the library is the OBJ's own, beside
    the file it writes (:func:`voxe_core.files.replacing`), named after it.

    Examples:
        >>> import tempfile, trimesh
        >>> tri = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]],
        ...                       vertex_colors=[[255, 0, 0, 255]] * 3, process=False)
        >>> path = save_obj(tri, Path(tempfile.mkdtemp()) / "tri.obj")
        >>> path.read_text().splitlines()[2:4]
        ['usemtl voxe', 'v 0 0 0 1.000000 0.000000 0.000000']
        >>> path.with_suffix(".mtl").read_text().splitlines()[1]
        'Kd 1.000000 0.000000 0.000000'
    """
    path = Path(path)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64) + 1
    rgb = np.asarray(mesh.visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
    mtl = Path(os.path.realpath(path)).with_suffix(".mtl")
    kd = rgb.mean(0) if len(rgb) else np.full(3, 0.8)
    # Both or neither: the MTL replaced first, the OBJ naming it only once that has been (the other way round, an
    # MTL that could not be written, a folder of its name, had left a new OBJ over the earlier one). The OBJ's one
    # text that may not be ASCII is the library's file name: written in the bytes the file system names it by (the
    # locale's encoding had refused `--out café.obj` under an ASCII locale)
    with replacing(path) as partial, replacing(mtl) as mtl_partial:
        mtl_partial.write_text(f"newmtl voxe\nKd {kd[0]:.6f} {kd[1]:.6f} {kd[2]:.6f}\nKa 0 0 0\nKs 0 0 0\nd 1\n"
                               "illum 1\n", encoding="utf-8")
        with (naming_write_failures(partial),  # (the OBJ's full disk, not the MTL's, whose replacing is innermost)
              open(partial, "w", encoding=sys.getfilesystemencoding(), errors=sys.getfilesystemencodeerrors()) as out):
            out.write(f"# Vox-E mesh: {len(vertices)} vertices, {len(faces)} faces\nmtllib {mtl.name}\nusemtl voxe\n")
            # Positions to 9 significant digits (float32's, as PLY and GLB hold them) at any scale: 6 decimals had
            # moved a mesh in a 1e-5 box by 5 % of its size. Colours in [0, 1]: 6 decimals are exact for 8 bits.
            np.savetxt(out, np.hstack([vertices, rgb]), fmt="v %.9g %.9g %.9g %.6f %.6f %.6f")
            np.savetxt(out, faces, fmt="f %d %d %d")
    return path
