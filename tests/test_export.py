"""Export: PNG, batched renders, turntable cameras, MP4/GIF, marching-cubes meshes and mesh files."""

from __future__ import annotations

import errno
import inspect
import math
import os
import stat
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from conftest import RED_LOGITS
from voxe_core.cli import main
from voxe_core.export import (
    default_mesh_level,
    extract_mesh,
    render_views,
    save_mesh,
    save_png,
    _surface_colours,
    to_uint8,
    VideoEncoderError,
    VideoWriter,
    turntable_cameras,
    write_video,
)
from voxe_core.files import replacing
from voxe_core.grid import VoxelGrid
from voxe_core.presets import VIDEO_MIN_FPS
from voxe_core.progress import Callbacks, StageCancelled
from voxe_core.render import RenderConfig, render_image
from voxe_core.scene_grid import SceneGrid

R = 0.8


def gradient_frames(n: int, h: int, w: int) -> torch.Tensor:
    """Frames that fade from blue to red, so each frame differs and colours are checkable."""
    t = torch.linspace(0, 1, n)[:, None, None]
    frames = torch.zeros(n, h, w, 3)
    frames[..., 0] = t
    frames[..., 2] = 1 - t
    return frames


# ------------------------------------------------------------------------ PNG
def test_png_round_trip_rounds_and_clamps(tmp_path):
    image = torch.tensor([[[0.0, 0.5, 1.0], [-0.2, 1.3, 0.502]], [[0.1, 0.2, 0.3], [1.0, 1.0, 1.0]]])
    save_png(tmp_path / "sub" / "a.png", image)
    back = np.asarray(Image.open(tmp_path / "sub" / "a.png"))
    assert back.dtype == np.uint8 and back.shape == (2, 2, 3)
    expected = np.array([[[0, 128, 255], [0, 255, 128]], [[26, 51, 76], [255, 255, 255]]], dtype=np.uint8)
    assert np.array_equal(back, expected)


def test_uint8_images_are_written_as_the_pixels_they_are(tmp_path):
    """Regression: uint8 was read as floats in [0, 1], so every pixel above 1 was written white (an image from
    imageio or PIL became a white PNG or video, silently). Integers of other types give no scale: refused."""
    pixels = np.array([[[0, 1, 2], [100, 200, 255]]], dtype=np.uint8)
    save_png(tmp_path / "pixels.png", pixels)
    assert np.array_equal(np.asarray(Image.open(tmp_path / "pixels.png")), pixels)
    frames = np.repeat(np.full((1, 16, 16, 3), (40, 120, 200), dtype=np.uint8), 2, axis=0)
    write_video(tmp_path / "pixels.gif", frames, fps=10)
    decoded = np.asarray(Image.open(tmp_path / "pixels.gif").convert("RGB"))
    assert np.abs(decoded.astype(int) - (40, 120, 200)).max() <= 2
    with pytest.raises(ValueError, match="floats in \\[0, 1\\] or uint8 pixels, got torch.int64"):
        save_png(tmp_path / "ints.png", np.full((2, 2, 3), 7))


def test_a_png_save_that_fails_keeps_the_earlier_file_and_leaves_no_partial_one(tmp_path):
    """A full disk (a file-size limit stands in for it): the PNG had been written into its final name, leaving the
    first 20,000 bytes of it there in place of the earlier view."""
    import resource

    path = tmp_path / "view.png"
    path.write_bytes(b"the earlier view")
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, hard))  # (Python ignores SIGXFSZ: writes fail EFBIG)
    try:
        with pytest.raises(OSError):
            save_png(path, torch.rand(200, 200, 3, generator=torch.Generator().manual_seed(0)))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert path.read_bytes() == b"the earlier view"
    assert [p.name for p in tmp_path.iterdir()] == ["view.png"]


@pytest.mark.parametrize("letter", ["v", "é"])  # é: two bytes in a name, never cut in half
@pytest.mark.parametrize("suffix", [".png", ".mp4", ".safetensors"])
def test_a_file_whose_name_fits_but_whose_partial_name_would_not_is_written(sphere_grid, tmp_path, letter, suffix):
    """Regression: a name within the 255 bytes a file name may hold, but not 9 bytes within, was refused "File name
    too long" (naming the file asked for, which fits): its partial file's name, ``.<stem>.partial<suffix>``, did not.
    Two such names that differ at their end keep their partial files apart."""
    stem = letter * ((254 - len(suffix)) // len(letter.encode()))
    names = [stem + end + suffix for end in "12"]
    for name in names:
        if suffix == ".png":
            save_png(tmp_path / name, torch.rand(4, 4, 3))
        elif suffix == ".mp4":
            write_video(tmp_path / name, gradient_frames(2, 8, 8), fps=10)
        else:
            sphere_grid.save(tmp_path / name)
    assert sorted(p.name for p in tmp_path.iterdir()) == names and all(len(n.encode()) <= 255 for n in names)
    with replacing(tmp_path / names[0]) as first, replacing(tmp_path / names[1]) as second:
        first.write_text("first")
        second.write_text("second")
        assert first != second and all(p.name.endswith(suffix) for p in (first, second))
    assert [(tmp_path / name).read_text() for name in names] == ["first", "second"]
    too_long = tmp_path / (stem + "123" + suffix)  # refused as it is opened, not once written whole, naming it
    with pytest.raises(OSError, match="File name too long") as error, replacing(too_long) as partial:
        partial.write_text("never")
    assert error.value.filename == str(too_long) and len(list(tmp_path.iterdir())) == 2


def test_a_replaced_file_keeps_its_permissions_and_a_symlink_stays_one(tmp_path):
    """Writing over a 0600 file had left it readable by all (the umask's mode of the new file), and writing through a
    symlink (latest.png -> runs/1/view.png) had put a file of its own in place of the link, the run's left as it was."""
    run = tmp_path / "runs" / "1"
    run.mkdir(parents=True)
    view, latest = run / "view.png", tmp_path / "latest.png"
    view.write_bytes(b"old")
    view.chmod(0o600)
    latest.symlink_to(Path("runs") / "1" / "view.png")
    save_png(latest, torch.rand(4, 4, 3))
    assert latest.is_symlink() and os.readlink(latest) == str(Path("runs") / "1" / "view.png")
    assert Image.open(view).size == (4, 4) and stat.S_IMODE(view.stat().st_mode) == 0o600
    assert sorted(p.name for p in run.iterdir()) == ["view.png"]


def test_a_file_is_on_the_disk_before_it_replaces_the_earlier_one(sphere_grid, tmp_path, monkeypatch, flushed_renames):
    """The rename that puts a written file in place was not preceded by an fsync: a power loss or kernel crash soon
    after could leave the final name holding an empty or torn file (XFS, Btrfs, ext4 writing a new file), the earlier
    one gone, though files.py promises a crash never does. Each writer's file (a PNG, a grid safetensors renames in
    itself, an OBJ and its MTL, a GIF) is flushed before its rename; a flush that finds the write failed (EIO) fails
    the write, the earlier file kept; a file system that cannot flush (EINVAL) writes as before."""
    from voxe_core.export import write_video

    save_png(tmp_path / "view.png", torch.rand(4, 4, 3))
    sphere_grid.save(tmp_path / "grid.safetensors")
    save_mesh(extract_mesh(sphere_grid), tmp_path / "mesh.obj")
    write_video(tmp_path / "turn.gif", np.zeros((2, 8, 8, 3), np.uint8), fps=10)
    assert sorted(flushed_renames) == [(name, True) for name in
                                       ("grid.safetensors", "mesh.mtl", "mesh.obj", "turn.gif", "view.png")]

    def failing(code):
        def fsync(fd):
            raise OSError(code, os.strerror(code))
        return fsync

    earlier = (tmp_path / "view.png").read_bytes()
    monkeypatch.setattr(os, "fsync", failing(errno.EIO))
    with pytest.raises(OSError) as error:
        save_png(tmp_path / "view.png", torch.rand(6, 6, 3))
    assert error.value.errno == errno.EIO and (tmp_path / "view.png").read_bytes() == earlier
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "grid.safetensors", "mesh.mtl", "mesh.obj", "turn.gif", "view.png"]
    monkeypatch.setattr(os, "fsync", failing(errno.EINVAL))
    save_png(tmp_path / "view.png", torch.rand(6, 6, 3))
    assert Image.open(tmp_path / "view.png").size == (6, 6)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="only root gives a file to another user")
def test_a_users_file_replaced_by_root_stays_the_users(tmp_path):
    """Root (a container, sudo) writing over a user's 0600 file had made it root's, 0600: the user could no longer
    read their own output. It keeps its owner, as it keeps its mode."""
    view = tmp_path / "view.png"
    view.write_bytes(b"old")
    os.chown(view, 65534, 65534)
    view.chmod(0o600)
    save_png(view, torch.rand(4, 4, 3))
    assert Image.open(view).size == (4, 4)
    assert (view.stat().st_uid, view.stat().st_gid, stat.S_IMODE(view.stat().st_mode)) == (65534, 65534, 0o600)


def test_an_obj_written_through_a_symlink_names_the_material_library_beside_it(tmp_path):
    """latest.obj -> runs/1/mesh.obj: the OBJ is written through the link, and its library with it, runs/1/mesh.mtl,
    which its mtllib names (the OBJ had named latest.mtl, written beside the link, not beside the OBJ)."""
    import trimesh

    run = tmp_path / "runs" / "1"
    run.mkdir(parents=True)
    (run / "mesh.obj").write_text("old")
    (tmp_path / "latest.obj").symlink_to(run / "mesh.obj")
    tri = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], vertex_colors=[[255, 0, 0, 255]] * 3,
                          process=False)
    save_mesh(tri, tmp_path / "latest.obj")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest.obj", "runs"]
    assert sorted(p.name for p in run.iterdir()) == ["mesh.mtl", "mesh.obj"]
    assert "mtllib mesh.mtl" in (run / "mesh.obj").read_text().splitlines()
    assert (run / "mesh.mtl").read_text().splitlines()[1] == "Kd 1.000000 0.000000 0.000000"


def test_two_writers_of_one_file_at_once_each_write_a_partial_file_of_their_own(tmp_path):
    """Two writes of one file at once (two runs given one --out) had shared its partial file: the second's bytes
    went over the first's, the first to finish renamed that into place, and the other failed "No such file or
    directory" naming the file asked for. Each now writes its own; the last to finish leaves its file, whole."""
    target = tmp_path / "notes.txt"
    with replacing(target) as first:
        first.write_text("the first, longer text")
        with replacing(target) as second:
            second.write_text("second")
        assert first != second and target.read_text() == "second"
    assert target.read_text() == "the first, longer text" and [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def test_a_write_removes_the_partial_files_of_writers_killed_mid_write_but_not_a_live_writers(tmp_path):
    """A run killed mid-write (SIGKILL, out of memory) left its partial file .<stem>.<token>.partial<suffix> for
    good, one more hidden file each run. The next write of the file removes those of dead writers; a live writer's
    (its process holding its partial file locked) stays, however long it has been writing, and so does one written
    just now (it may be a writer's that has made it but not yet locked it)."""
    import signal
    import subprocess
    import time

    target = tmp_path / "grid.safetensors"
    writer = ("import sys, time\nfrom voxe_core.files import replacing\nwith replacing(sys.argv[1]) as partial:\n"
              "    partial.write_bytes(b'half a grid')\n    print(partial, flush=True)\n    time.sleep(600)\n")
    repo = Path(__file__).resolve().parents[1]
    processes = [subprocess.Popen([sys.executable, "-c", writer, str(target)], cwd=repo, stdout=subprocess.PIPE,
                                  text=True) for _ in range(4)]
    try:
        partials = [Path(process.stdout.readline().strip()) for process in processes]
        assert all(partial.is_file() for partial in partials)
        for process in processes[:3]:
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=30)
        long_ago = time.time() - 3600
        for partial in partials[:2] + partials[3:]:  # written an hour ago: the live writer's too
            os.utime(partial, (long_ago, long_ago))
        other = tmp_path / ".grid.0123abcd.partial.png"  # another file's (grid.png) partial file
        other.write_bytes(b"")
        os.utime(other, (long_ago, long_ago))
        with replacing(target) as partial:
            partial.write_bytes(b"a whole grid")
        assert target.read_bytes() == b"a whole grid"
        kept = [target.name, other.name] + [p.name for p in partials[2:]]
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept)
    finally:
        for process in processes:
            process.kill()
            process.wait(timeout=30)


def test_a_write_removes_the_partial_file_a_writer_killed_before_partial_files_had_tokens_left(tmp_path):
    """Before each writer had a partial file of its own, a file's one was .<stem>.partial<suffix>; one a killed writer
    had left then was never removed, the new writers sweeping only names with a token. The aged one goes now; one
    written just now stays, and so does another file's."""
    import time

    target = tmp_path / "grid.safetensors"
    old, other = tmp_path / ".grid.partial.safetensors", tmp_path / ".grid.partial.png"
    long_ago = time.time() - 3600
    for partial in (old, other):
        partial.write_bytes(b"half a grid")
        os.utime(partial, (long_ago, long_ago))
    with replacing(target) as partial:
        partial.write_bytes(b"a whole grid")
    assert sorted(p.name for p in tmp_path.iterdir()) == [other.name, target.name]
    old.write_bytes(b"half a grid")  # (just written: maybe a live writer's)
    with replacing(target) as partial:
        partial.write_bytes(b"a whole grid")
    assert old.exists()


def test_png_rgba_and_bad_shape(tmp_path):
    rgba = torch.rand(5, 6, 4, generator=torch.Generator().manual_seed(0))
    save_png(tmp_path / "rgba.png", rgba)
    back = np.asarray(Image.open(tmp_path / "rgba.png"))
    assert back.shape == (5, 6, 4)
    assert np.abs(back / 255.0 - rgba.numpy()).max() <= 0.5 / 255 + 1e-6
    with pytest.raises(ValueError, match="H, W, 3"):
        save_png(tmp_path / "bad.png", torch.zeros(5, 6, 2))


# -------------------------------------------------------------------- renders
def test_turntable_cameras_ring_geometry():
    cams = turntable_cameras(n_frames=8, elevation_deg=30.0, size=40)
    assert len(cams) == 8 and (cams.width, cams.height) == (40, 40)
    eye = cams.c2w[:, :3, 3]
    assert torch.allclose(eye.norm(dim=-1), torch.full((8,), 4.0311), atol=1e-4)
    assert torch.allclose(eye[:, 2], torch.full((8,), 4.0311 * math.sin(math.radians(30))), atol=1e-4)
    azimuth = torch.rad2deg(torch.atan2(eye[:, 1], eye[:, 0])) % 360
    assert torch.allclose(azimuth, torch.arange(8) * 45.0, atol=1e-3)
    # Every camera looks at the origin (-z axis towards it) with the NeRF-synthetic focal length.
    forward = -cams.c2w[:, :3, 2]
    assert torch.allclose(forward, -eye / eye.norm(dim=-1, keepdim=True), atol=1e-5)
    assert torch.allclose(cams.fx, torch.full((8,), 0.5 * 40 / math.tan(0.5 * 0.6911)), rtol=1e-4)


@pytest.mark.parametrize("elevation", [90.5, 120.0, -91.0, float("nan"), float("inf")])
def test_a_turntable_elevation_past_the_poles_is_refused_naming_the_range(sphere_grid, tmp_path, capsys, elevation):
    """Regression: 120 had been taken: a ring seen from 60° up on the far side of each azimuth, its cameras upside
    down; the CLI rendered it. The poles themselves (a view straight down or up) stay."""
    with pytest.raises(ValueError, match=rf"a turntable's elevation must lie between -90 and 90 degrees, got "
                                         rf"{elevation:g}"):
        turntable_cameras(4, elevation, 8)
    grid, out = tmp_path / "g.safetensors", tmp_path / "t.gif"
    sphere_grid.save(grid)
    if math.isfinite(elevation):  # (nan and inf: refused as voxe's options are read, test_cli.py)
        assert main(["turntable", str(grid), "--out", str(out), "--elevation", str(elevation), "--quiet"]) == 2
        assert "between -90 and 90 degrees" in capsys.readouterr().err and not out.exists()
    for pole in (90.0, -90.0):
        assert torch.allclose(turntable_cameras(2, pole, 8).c2w[:, :3, 2], torch.tensor([0.0, 0.0, pole / 90]),
                              atol=1e-6)


@pytest.mark.parametrize("pole", [90.0, -90.0])
def test_a_turntable_at_a_pole_turns_as_the_rings_beside_it_do(make_sphere_grid, pole):
    """A ring at elevation ±90° (voxe turntable / render --ring --elevation 90) had been one pose repeated: look_at
    gives a camera on the up axis no azimuth, so every frame was the same picture (an off-centre object did not turn
    at all). Each pose at the pole now has its azimuth's roll, that of the ring 0.001° off the pole."""
    at_pole, beside = turntable_cameras(4, pole, 16), turntable_cameras(4, pole - math.copysign(1e-3, pole), 16)
    assert torch.allclose(at_pole.c2w[:, :3, :3], beside.c2w[:, :3, :3], atol=1e-4)
    assert torch.allclose(at_pole.c2w[:, :3, :3].det(), torch.ones(4), atol=1e-6)
    grid = make_sphere_grid(radius=0.3, center=(0.6, 0.0, 0.0))
    frames = render_views(grid, at_pole)
    assert not torch.equal(frames[0], frames[1]) and torch.allclose(frames[0], frames[2].flip(0, 1), atol=1e-4)


def test_render_views_matches_render_image_and_shows_the_sphere(sphere_grid):
    cams = turntable_cameras(n_frames=3, elevation_deg=20.0, size=20)
    seen = []
    frames = render_views(sphere_grid, cams, RenderConfig(), Callbacks(on_progress=lambda p: seen.append(p.iteration)))
    assert frames.shape == (3, 20, 20, 3)
    assert seen == [1, 2, 3]
    for i in range(3):
        assert torch.allclose(frames[i], render_image(sphere_grid, cams, i).rgb, atol=1e-6)
    centre, corner = frames[:, 10, 10], frames[:, 0, 0]
    assert (centre[:, 0] > 0.9).all() and (centre[:, 1:] < 0.1).all()  # the red sphere
    assert torch.allclose(corner, torch.ones(3, 3), atol=1e-4)  # white background


def test_render_views_can_be_cancelled(sphere_grid):
    cams = turntable_cameras(n_frames=4, size=8)
    with pytest.raises(StageCancelled):
        render_views(sphere_grid, cams, callbacks=Callbacks(should_cancel=lambda: True))


# --------------------------------------------------------------------- videos
def read_mp4(path):
    reader = imageio.get_reader(path, format="FFMPEG")
    try:
        return [frame for frame in reader], reader.get_meta_data()
    finally:
        reader.close()


def test_mp4_is_playable_with_even_size_and_right_colours(tmp_path):
    frames = gradient_frames(7, 31, 33)  # odd sizes must be padded for yuv420p
    path = write_video(tmp_path / "v.mp4", frames, fps=12)
    decoded, meta = read_mp4(path)
    assert len(decoded) == 7
    assert decoded[0].shape == (32, 34, 3)
    assert meta["fps"] == pytest.approx(12.0)
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    first, last = decoded[0].astype(int), decoded[-1].astype(int)
    assert first[16, 17, 2] > 240 and first[16, 17, 0] < 15  # blue
    assert last[16, 17, 0] > 240 and last[16, 17, 2] < 15  # red
    # The padding replicates the edge rather than adding black bars.
    assert abs(first[31, 33, 2] - 255) < 20


def test_mp4_states_the_colour_matrix_its_pixels_were_converted_by(tmp_path):
    """Regression: the stream had no colour tags, so each player picked a matrix; one guessing BT.709 for an untagged
    stream (as browsers may, for the web UI's video) showed the BT.601 pixels' red (250, 5, 5) as (255, 27, 1) and the
    green (128, 225, 30) as (124, 202, 23). Here ffmpeg plays that player: the stated matrix, else BT.709."""
    import re
    import subprocess

    import imageio_ffmpeg

    frames = torch.zeros(2, 16, 16, 3)
    frames[:, :, :8] = torch.tensor([250, 5, 5]) / 255
    frames[:, :, 8:] = torch.tensor([128, 225, 30]) / 255
    path = write_video(tmp_path / "v.mp4", frames, fps=30)
    ffmpeg = imageio_ffmpeg.get_ffmpeg_exe()
    info = subprocess.run([ffmpeg, "-hide_banner", "-i", str(path)], capture_output=True, text=True).stderr
    stated = re.search(r"yuv420p\((tv|pc), (\w+)", info)
    matrix = {"smpte170m": "bt601", "bt470bg": "bt601", "bt709": "bt709"}[stated[2]] if stated else "bt709"
    command = [ffmpeg, "-v", "error", "-i", str(path), "-vf", f"scale=in_color_matrix={matrix},format=rgb24",
               "-frames:v", "1", "-f", "rawvideo", "-"]
    pixels = np.frombuffer(subprocess.run(command, capture_output=True, check=True).stdout, np.uint8)
    pixels = pixels.reshape(16, 16, 3).astype(int)
    assert np.abs(pixels[8, 3] - [250, 5, 5]).max() <= 4 and np.abs(pixels[8, 12] - [128, 225, 30]).max() <= 4
    decoded, _ = read_mp4(path)  # imageio (ffmpeg's own default) reads it as before
    assert np.abs(decoded[0][8, 3].astype(int) - [250, 5, 5]).max() <= 4


@pytest.mark.parametrize("n, fps, shown", [(30, 30.0, 30), (30, 60.0, 15), (30, 120.0, 10), (30, 7.0, 30),
                                           (1, 30.0, 1), (2, 120.0, 1)])
def test_gif_delays_follow_the_true_timeline_and_none_is_too_short_to_play(tmp_path, n, fps, shown):
    """GIF delays are whole centiseconds: 1000/fps had been cut (30 fps played 10 % fast), and 60 fps and above
    wrote delays of 1 or 0 cs, which browsers play at about 10 fps. One frame kept (a 1-frame turntable, or 2 at
    120 fps) had crashed in Pillow, which takes a list of delays only for several frames."""
    frames = gradient_frames(n, 8, 8)
    write_video(tmp_path / "v.gif", frames, fps=fps)
    with Image.open(tmp_path / "v.gif") as gif:
        delays = []
        for index in range(gif.n_frames):
            gif.seek(index)
            delays.append(gif.info["duration"])
    assert len(delays) == shown and min(delays) >= 20
    assert sum(delays) == pytest.approx(max(n / fps * 1000, 20), abs=10)


def test_gif_frames_loop_and_duration(tmp_path):
    write_video(tmp_path / "v.gif", gradient_frames(5, 12, 10), fps=10)
    with Image.open(tmp_path / "v.gif") as gif:
        assert gif.n_frames == 5
        assert gif.size == (10, 12)
        assert gif.info["loop"] == 0
        assert gif.info["duration"] == 100
        gif.seek(4)
        r, g, b = gif.convert("RGB").getpixel((5, 5))
        assert r > 240 and b < 15


def test_video_rejects_unknown_suffix_and_bad_frames(tmp_path):
    with pytest.raises(ValueError, match=r"'\.avi'"):
        write_video(tmp_path / "v.avi", gradient_frames(2, 4, 4))
    with pytest.raises(ValueError, match="N, H, W, 3"):
        write_video(tmp_path / "v.mp4", torch.zeros(0, 4, 4, 3))
    assert not (tmp_path / "v.avi").exists()
    # Pillow had overflowed its 16-bit GIF delay, and ffmpeg had failed after the encode with no file
    for name, fps in (("slow.gif", 0.0015), ("slow.mp4", 1e-9), ("nan.mp4", float("nan")), ("inf.gif", float("inf"))):
        with pytest.raises(ValueError, match=rf"fps must be a finite number of at least 0.001526 .* got {fps:g}$"):
            write_video(tmp_path / name, gradient_frames(2, 4, 4), fps=fps)
    for name in ("slowest.gif", "slowest.mp4"):  # a 655.35 s frame, the floor of both formats
        write_video(tmp_path / name, gradient_frames(2, 4, 4), fps=VIDEO_MIN_FPS)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slowest.gif", "slowest.mp4"]


@pytest.mark.parametrize("name, shape, message", [
    ("wide.mp4", (2, 16385), r"^an MP4 holds frames of at most 16384 pixels a side .*, got 16385x2: make them smaller"),
    ("tall.mp4", (16386, 2), r", got 2x16386: "),
    ("wide.gif", (1, 65536), r"^a GIF holds frames of at most 65535 pixels a side, got 65536x1$"),
])
def test_frames_too_large_for_their_video_are_refused_before_the_encoder_is_started(tmp_path, name, shape, message):
    """ffmpeg had refused them in its words ("the video encoder failed (ffmpeg exited with status 187: invalid width x
    height (16386x2))") and Pillow had overflowed ("int too big to convert"). The widest it takes is written."""
    with pytest.raises(ValueError, match=message):
        write_video(tmp_path / name, np.zeros((1, *shape, 3), np.uint8))
    assert not list(tmp_path.iterdir())
    assert write_video(tmp_path / "widest.mp4", np.zeros((1, 2, 16384, 3), np.uint8)).stat().st_size > 0


def test_a_video_is_whole_or_absent(tmp_path):
    """It is written under a temporary name and renamed when whole: an interrupted encode had left a playable
    video of the frames so far, and an encoder that failed (ffmpeg logs and exits) a 'wrote' with no file."""
    frames = gradient_frames(6, 16, 16)

    def interrupted():
        yield from frames[:3]
        raise KeyboardInterrupt  # what Ctrl-C raises while the frames are rendered and encoded

    for name in ("t.mp4", "t.gif"):
        with pytest.raises(KeyboardInterrupt):
            write_video(tmp_path / name, interrupted(), fps=10, n_frames=6)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "taken.mp4").mkdir()  # the destination is a folder: the encode succeeds, the rename cannot
    with pytest.raises(IsADirectoryError):
        write_video(tmp_path / "taken.mp4", frames, fps=10)
    assert [p.name for p in tmp_path.iterdir()] == ["taken.mp4"]
    assert write_video(tmp_path / "t.mp4", frames, fps=10).stat().st_size > 0


@pytest.mark.parametrize("reads, says, code", [
    ("cat > /dev/null", "Error writing trailer: No space left on device", errno.ENOSPC),  # the disk filled at the end
    ("", "Error writing trailer: No space left on device", errno.ENOSPC),  # it stopped reading: the pipe broke
    ("cat > /dev/null", "Conversion failed!", None),  # a failure that names no system error
    ("cat > /dev/null", "Error writing trailer: Broken pipe", errno.EPIPE),  # not a BrokenPipeError (the CLI's own)
])
def test_an_mp4_whose_encoder_failed_is_an_error_and_leaves_the_earlier_file(tmp_path, monkeypatch, reads, says, code):
    """Regression: imageio-ffmpeg never read ffmpeg's exit status, so on a full disk write_video returned and left the
    64 KiB ffmpeg had written (no video) under the final name. Now the encoder's failure is an OSError naming what
    ffmpeg said, with the errno it names (ENOSPC: a worker can tell a full disk), the earlier file kept, no other left.
    Here an ffmpeg that does what the real one did on a full 64 KiB tmpfs."""
    ffmpeg = tmp_path / "bin" / "ffmpeg"
    ffmpeg.parent.mkdir()
    ffmpeg.write_text(f'#!/bin/sh\nfor out; do :; done\n{reads}\nhead -c 65536 /dev/zero > "$out"\n'
                      f'echo "[out#0/mp4 @ 0x5603c2d1a2c0] {says}" >&2\nexit 1\n')
    ffmpeg.chmod(0o755)
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", str(ffmpeg))
    videos = tmp_path / "videos"
    videos.mkdir()
    (videos / "v.mp4").write_bytes(b"the earlier video")
    with pytest.raises(OSError, match=rf"the video encoder failed \(ffmpeg exited with status 1: {says}\)") as error:
        write_video(videos / "v.mp4", gradient_frames(12, 96, 96), fps=10)  # 320 KiB: more than a pipe holds
    assert type(error.value) is VideoEncoderError and error.value.errno == code
    assert error.value.filename == str(videos / "v.mp4") and str(videos / "v.mp4") in str(error.value)
    assert str(videos) not in error.value.strerror  # (a worker's failure text gives the words, not its files)
    assert [p.name for p in videos.iterdir()] == ["v.mp4"] and (videos / "v.mp4").read_bytes() == b"the earlier video"


@pytest.mark.parametrize("name", ["a:b.mp4", "http:b.mp4", "a:b.gif"])
def test_a_video_named_with_a_colon_in_the_working_folder_is_written(tmp_path, monkeypatch, name):
    """Regression: ffmpeg was given the relative partial name ('.a:b.<token>.partial.mp4') and read it as a URL of
    protocol '.a': the encode failed ("Protocol not found") after the whole render."""
    monkeypatch.chdir(tmp_path)
    path = write_video(name, gradient_frames(3, 16, 16), fps=10)
    assert str(path) == name and sorted(p.name for p in tmp_path.iterdir()) == [name]
    if name.endswith(".mp4"):
        assert len(read_mp4(tmp_path / name)[0]) == 3


def test_an_mp4_is_written_by_a_process_without_a_stderr(tmp_path, monkeypatch):
    """A process started with its stderr closed (a daemon) has sys.stderr None: the encoder's log, empty, had been
    written to it all the same, and every finished encode failed (AttributeError) and was removed."""
    monkeypatch.setattr(sys, "stderr", None)
    assert write_video(tmp_path / "v.mp4", gradient_frames(3, 16, 16), fps=10).stat().st_size > 0


@pytest.mark.parametrize("name", ["v.mp4", "v.gif"])
def test_a_streamed_video_given_the_wrong_frames_leaves_nothing(tmp_path, name):
    """A VideoWriter is opened for N frames of one size: fewer, more, or one of another size is a ValueError
    naming it, and nothing is left (not a shorter clip, not the partial file)."""
    frames = gradient_frames(4, 8, 10)
    with pytest.raises(ValueError, match=r"opened for 4 frames; 3 were given"):
        write_video(tmp_path / name, iter(frames[:3]), fps=10, n_frames=4)
    with pytest.raises(ValueError, match=r"opened for 3 frames; one more was given"):
        write_video(tmp_path / name, iter(frames), fps=10, n_frames=3)
    with pytest.raises(ValueError, match=r"frame 2 is \(8, 9, 3\), frame 0 \(8, 10, 3\)"):
        write_video(tmp_path / name, [frames[0], frames[1], frames[2, :, :9]], fps=10)
    with pytest.raises(TypeError, match="needs n_frames for frames of no length"):
        write_video(tmp_path / name, iter(frames), fps=10)
    renders = (frame for frame in frames)  # a generator of renders, holding its grid: let go on the error
    with pytest.raises(ValueError, match=r"opened for 2 frames; one more was given"):
        write_video(tmp_path / name, renders, fps=10, n_frames=2)
    assert inspect.getgeneratorstate(renders) == inspect.GEN_CLOSED
    with pytest.raises(RuntimeError, match=rf"VideoWriter\({name}\): append within its with block"):
        VideoWriter(tmp_path / name, 1, fps=10).append(frames[0])  # a GIF's frame had gone nowhere, silently
    assert list(tmp_path.iterdir()) == []


def decoded_video(path) -> tuple[list[np.ndarray], list[int]]:
    """(the frames a player shows, each one's delay in ms; an MP4's from its frame rate)."""
    if path.suffix == ".mp4":
        frames, meta = read_mp4(path)
        return frames, [round(1000 / meta["fps"])] * len(frames)
    frames, delays = [], []
    with Image.open(path) as gif:
        for index in range(gif.n_frames):
            gif.seek(index)
            frames.append(np.asarray(gif.convert("RGB")))
            delays.append(gif.info["duration"])
    return frames, delays


@pytest.mark.parametrize("name, n, fps", [("v.mp4", 7, 12.0), ("v.gif", 7, 30.0), ("v.gif", 9, 120.0),
                                          ("v.gif", 2, 120.0)])
def test_a_video_streamed_frame_by_frame_is_the_video_of_the_whole_array(tmp_path, name, n, fps):
    """Frames appended one by one as they are rendered give the file the whole array gave (odd sizes padded the
    same way, the GIF's shown frames and delays the same), and the GIF shows what Pillow's from the whole array
    shows, though each frame is quantised and written as it comes."""
    import imageio.v3 as iio

    from voxe_core.export import gif_timeline, to_uint8

    frames = gradient_frames(n, 31, 33)
    frames[:, 5:9, 3:20, 1] = torch.rand(n, 4, 17, generator=torch.Generator().manual_seed(1))  # some texture
    whole = write_video(tmp_path / "whole" / name, frames, fps=fps)
    streamed = write_video(tmp_path / "streamed" / name, (frame.clone() for frame in frames), fps=fps, n_frames=n)
    assert streamed.read_bytes() == whole.read_bytes()
    (whole_frames, whole_delays), (streamed_frames, streamed_delays) = decoded_video(whole), decoded_video(streamed)
    assert streamed_delays == whole_delays and len(streamed_frames) == len(whole_frames)
    assert all(np.array_equal(a, b) for a, b in zip(streamed_frames, whole_frames))
    if name.endswith(".gif"):
        shown, delays = gif_timeline(n, fps)
        assert streamed_delays == delays
        reference = tmp_path / "pillow.gif"  # how write_video wrote a GIF before it streamed
        iio.imwrite(reference, to_uint8(frames)[shown], plugin="pillow", extension=".gif",
                    duration=delays if len(shown) > 1 else delays[0], loop=0)
        reference_frames, reference_delays = decoded_video(reference)  # (written as it comes, not byte for byte)
        assert streamed_delays == reference_delays and len(streamed_frames) == len(reference_frames)
        assert all(np.array_equal(a, b) for a, b in zip(streamed_frames, reference_frames))
    else:
        assert streamed_frames[0].shape == (32, 34, 3)
        reference = tmp_path / "ffmpeg.mp4"  # how write_video wrote an MP4 before it streamed
        padded = np.pad(to_uint8(frames), ((0, 0), (0, 1), (0, 1), (0, 0)), mode="edge")
        with imageio.get_writer(reference, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
                                quality=None, output_params=["-colorspace", "smpte170m", "-color_range", "tv", "-crf",
                                                             "18", "-preset", "medium", "-movflags", "+faststart"],
                                macro_block_size=1, ffmpeg_log_level="error") as writer:
            for frame in padded:
                writer.append_data(frame)
        assert streamed.read_bytes() == reference.read_bytes()


class FramesAlive:
    """A frame source that counts how many of the frames it made are still referenced when it makes the next."""

    def __init__(self, frames: torch.Tensor):
        self.frames, self.alive, self.most_alive = frames, 0, 0

    def _released(self) -> None:
        self.alive -= 1

    def __iter__(self):
        import weakref

        for frame in self.frames:
            frame = frame.clone()
            self.alive += 1
            self.most_alive = max(self.most_alive, self.alive)
            weakref.finalize(frame, self._released)
            yield frame


def views_alive(height: int, width: int) -> float:
    """How many (height, width, 3) float views' worth of memory the tensors of that image size alive now hold, for
    renders made inside a command (where :class:`FramesAlive` cannot stand in for the renderer): a stack of N views
    counts N, a one-channel coverage a third, a storage several tensors share once."""
    import gc

    storages = {}
    # type(obj), not isinstance: that reads __class__, which some objects warn on. Plain tensors only: renders are,
    # and a FakeTensor an earlier test's torch.compile left has no storage to read
    for obj in gc.get_objects():
        if type(obj) is torch.Tensor and obj.dim() >= 3 and tuple(obj.shape[-3:-1]) == (height, width):
            storage = obj.untyped_storage()
            storages[storage.data_ptr()] = storage.nbytes()
    return sum(storages.values()) / (height * width * 3 * 4)


@pytest.mark.parametrize("name", ["v.mp4", "v.gif"])
def test_a_streamed_video_holds_no_more_than_two_of_its_frames(tmp_path, name):
    """Regression: write_video took the whole clip (render_views' (N, H, W, 3) floats, 50 GB for 1,000 frames of
    2,048²) and converted it whole. Streamed, a frame is let go once it is encoded (the GIF quantises each shown
    frame to palette indices, written once the next differs): at most the one being appended and the next are alive."""
    source = FramesAlive(gradient_frames(30, 12, 14))
    write_video(tmp_path / name, iter(source), fps=30, n_frames=30)
    assert source.most_alive <= 2 and source.alive == 0
    assert len(decoded_video(tmp_path / name)[0]) == 30


def test_a_gif_is_written_as_its_frames_come_not_held_to_the_end(tmp_path):
    """Regression: each shown frame was kept (as a palette image) until the block ended, for Pillow's encoder to take
    the clip at once: 4 GB for 1,000 frames of 2,048². Now a frame is in the file once the next one differs."""
    frames = gradient_frames(6, 20, 24)
    written = []
    with VideoWriter(tmp_path / "v.gif", 6, fps=10) as video:
        for frame in frames:
            video.append(frame)
            written.append(sum(path.stat().st_size for path in tmp_path.iterdir()))  # (the partial file's)
    assert all(later > earlier for earlier, later in zip(written[1:], written[2:]))
    shown, delays = decoded_video(tmp_path / "v.gif")
    assert delays == [100] * 6
    assert all(np.abs(a.astype(int) - b).max() <= 8 for a, b in zip(shown, (to_uint8(f).astype(int) for f in frames)))


def test_a_gif_of_a_still_scene_longer_than_a_gif_delay_plays_its_whole_length(tmp_path):
    """Regression: the repeated frames of a still scene (an empty grid's turntable, a sphere's) were folded into one
    frame, whose 700 s overflowed the GIF's 16-bit delay (655.35 s): OverflowError, after the whole render."""
    still = torch.full((700, 8, 8, 3), 0.5)
    write_video(tmp_path / "v.gif", still, fps=1.0)
    shown, delays = decoded_video(tmp_path / "v.gif")
    assert sum(delays) == 700_000 and max(delays) <= 655_350
    assert all((frame == 128).all() for frame in shown)


def test_iter_views_yields_render_views_frames_one_at_a_time(sphere_grid):
    """render_views is iter_views' frames stacked; each comes after its progress report (a cancel between)."""
    from voxe_core.export import iter_views

    cams = turntable_cameras(n_frames=3, elevation_deg=20.0, size=12)
    seen = []
    views = iter_views(sphere_grid, cams, callbacks=Callbacks(on_progress=lambda p: seen.append(p.iteration)))
    first = next(views)
    assert seen == [1] and first.shape == (12, 12, 3)
    assert torch.equal(torch.stack([first, *views]), render_views(sphere_grid, cams))


# ---------------------------------------------------------------------- meshes
def test_default_level_is_half_opacity_over_one_voxel(sphere_grid):
    level = default_mesh_level(sphere_grid)
    voxel = float(sphere_grid.voxel_size.min())
    assert 1 - math.exp(-level * voxel) == pytest.approx(0.5)
    # over the smallest edge of a grid whose voxels are 0.25 x 0.5 x 1
    assert default_mesh_level(VoxelGrid((9, 5, 3), (-1.0,) * 3, (1.0,) * 3)) == pytest.approx(math.log(2) / 0.25)


def test_sphere_mesh_radius_colour_and_closure(sphere_grid):
    mesh = extract_mesh(sphere_grid)
    voxel = float(sphere_grid.voxel_size.min())
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert len(mesh.vertices) > 500
    assert np.abs(radius - R).mean() < voxel
    assert np.abs(radius - R).max() < 1.5 * voxel
    colors = mesh.visual.vertex_colors
    assert colors.dtype == np.uint8 and colors.shape == (len(mesh.vertices), 4)
    assert (colors[:, 0] > 240).all() and (colors[:, 1:3] < 15).all() and (colors[:, 3] == 255).all()
    assert mesh.is_watertight
    # Outward normals: positive volume close to the ball's.
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * R**3, rel=0.12)


@pytest.mark.parametrize("resolution", [None, 45])
def test_mesh_colours_are_the_renders_not_those_of_the_empty_vertices_outside(make_sphere_grid, resolution):
    """A red ball whose empty vertices outside are grey (raw colour 0, where a fit starts them): on the level set the
    colour had been interpolated with theirs, so the mesh came out a pinkish grey (about 146, 109, 109 to 175, 80, 80)
    where its renders show red (a median of about 239, 16, 16 over the ball's opaque pixels)."""
    grid = make_sphere_grid()
    with torch.no_grad():
        outside = grid.features[..., 0] <= 0
        grid.features[..., 1:][outside] = 0.0  # sigmoid: 0.5, grey
    cameras = turntable_cameras(2, 30.0, 64)
    renders = [render_image(grid, cameras, i, RenderConfig()) for i in range(len(cameras))]
    shown = np.concatenate([to_uint8(render.rgb[render.opacity > 0.999]) for render in renders]).astype(int)
    colours = extract_mesh(grid, resolution=resolution).visual.vertex_colors[:, :3].astype(int)
    assert np.abs(np.median(colours, 0) - np.median(shown, 0)).max() <= 6
    assert colours[:, 0].min() >= shown[:, 0].min() - 5 and colours[:, 1:].max() <= shown[:, 1:].max() + 5


@pytest.mark.parametrize("colour_samples", [1, 2])
def test_colour_samples_set_how_many_samples_colour_each_vertex(make_sphere_grid, colour_samples):
    """bench/mesh_colours.py weighs fewer samples against the default: the count must reach the compositing."""
    grid = make_sphere_grid()
    with torch.no_grad():
        grid.features[..., 1:][grid.features[..., 0] <= 0] = 0.0  # grey outside, so the samples' depths matter
    fewer = extract_mesh(grid, colour_samples=colour_samples)
    colours = fewer.visual.vertex_colors[:, :3]
    assert np.array_equal(colours, _surface_colours(grid, fewer.vertices, fewer.vertex_normals, colour_samples))
    assert not np.array_equal(colours, extract_mesh(grid).visual.vertex_colors[:, :3])


@pytest.mark.parametrize("resolution", [None, 24])
def test_a_mesh_extracted_under_a_callers_bf16_autocast_is_the_float32_one(make_sphere_grid, resolution):
    """The resampled lattice's density and the vertices' colours are looked up by VoxelGrid.interpolate's bmm, which a
    caller's bf16 autocast had run in bf16: vertices up to 2e-4 off and colours 1 off (the renderer's float32 under
    autocast is the rule)."""
    grid = make_sphere_grid(16, slope=0.3)
    with torch.no_grad():
        ramp = torch.linspace(-3.0, 3.0, 16)
        grid.features[..., 1:] = torch.stack(torch.meshgrid(ramp, ramp, ramp, indexing="ij"), -1)
    expected = extract_mesh(grid, resolution=resolution)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mesh = extract_mesh(grid, resolution=resolution)
    assert np.array_equal(mesh.vertices, expected.vertices) and np.array_equal(mesh.faces, expected.faces)
    assert np.array_equal(mesh.visual.vertex_colors, expected.visual.vertex_colors)


@pytest.mark.parametrize("colour_samples", [0, -1])
def test_a_vertex_colour_needs_a_sample(sphere_grid, colour_samples):
    with pytest.raises(ValueError, match="at least 1 sample"):
        extract_mesh(sphere_grid, colour_samples=colour_samples)


def test_off_centre_sphere_lands_in_the_right_world_place(make_sphere_grid):
    centre = np.array([0.45, -0.3, 0.2])
    grid = make_sphere_grid(resolution=40, radius=0.5, center=tuple(centre))
    voxel = float(grid.voxel_size.min())
    for mesh in (extract_mesh(grid), extract_mesh(grid, resolution=61)):
        radius = np.linalg.norm(mesh.vertices - centre, axis=1)
        assert np.abs(radius - 0.5).mean() < voxel
        assert np.allclose(mesh.vertices.mean(0), centre, atol=0.1 * voxel)


def test_resolution_resamples_finer(sphere_grid):
    coarse = extract_mesh(sphere_grid)
    fine = extract_mesh(sphere_grid, resolution=64)
    assert len(fine.vertices) > 3 * len(coarse.vertices)
    err_fine = np.abs(np.linalg.norm(fine.vertices, axis=1) - R).mean()
    assert err_fine < 0.5 * float(sphere_grid.voxel_size.min())
    assert fine.is_watertight


def test_higher_level_gives_a_smaller_surface(sphere_grid):
    # Raw density grows 5 per voxel of depth: level at raw 2.5 lies half a voxel inside.
    voxel = float(sphere_grid.voxel_size.min())
    level = float(sphere_grid.activate_density(torch.tensor(2.5)))
    mesh = extract_mesh(sphere_grid, level=level)
    assert np.linalg.norm(mesh.vertices, axis=1).mean() == pytest.approx(R - 0.5 * voxel, abs=0.15 * voxel)


def test_matter_touching_the_box_is_capped_on_the_box():
    grid = VoxelGrid(6, init_density=1.0)  # dense everywhere
    mesh = extract_mesh(grid)
    assert np.allclose(mesh.bounds, [[-1.5] * 3, [1.5] * 3])
    assert mesh.is_watertight and mesh.volume == pytest.approx(27.0, rel=1e-6)


@pytest.mark.parametrize("dense", ["all", "corner voxel", "edge voxel"])
@pytest.mark.parametrize("resolution", [None, 13])
# ±1.2 and the skewed box: voxel sizes not exact in binary put the lattice's last plane 3e-8 short of the box
@pytest.mark.parametrize("box", [((-1.5,) * 3, (1.5,) * 3), ((-1.2,) * 3, (1.2,) * 3),
                                 ((-0.7, -1.3, 0.1), (1.1, 0.9, 2.3))])
def test_a_mesh_capped_on_the_box_stays_closed_when_a_reader_welds_its_vertices(dense, resolution, box, tmp_path):
    from scipy.spatial import cKDTree

    grid = VoxelGrid(8, *box, init_density=-10.0)
    with torch.no_grad():
        target = {"all": (...,), "corner voxel": (0, 0, 0), "edge voxel": (0, 0, 3)}[dense]
        grid.features[target + (0,)] = 100.0
    mesh = extract_mesh(grid, resolution=resolution)
    assert (mesh.area_faces > 0).all()
    # No vertices a merge by distance would weld (Blender's default is 1e-4): slivers between them open the surface.
    assert not cKDTree(mesh.vertices).query_pairs(1e-3 * float(grid.voxel_size.min()))
    save_mesh(mesh, tmp_path / "m.ply")
    loaded = trimesh.load(tmp_path / "m.ply")  # welds equal vertices, as MeshLab's and Blender's imports may
    assert loaded.is_watertight and loaded.is_winding_consistent
    assert loaded.volume == pytest.approx(mesh.volume) and loaded.volume > 0


def test_empty_grid_raises_clear_error():
    grid = VoxelGrid(8, init_density=-1.0)
    with pytest.raises(ValueError, match="grid has no surface at level"):
        extract_mesh(grid)
    faint = VoxelGrid(8, init_density=0.01)  # density 0.33 everywhere, far below ln2/voxel
    with pytest.raises(ValueError, match="grid has no surface at level"):
        extract_mesh(faint)
    assert len(extract_mesh(faint, level=0.1).vertices) > 0


def test_ply_round_trip_keeps_vertices_and_colours(sphere_grid, tmp_path):
    mesh = extract_mesh(sphere_grid)
    path = save_mesh(mesh, tmp_path / "m.ply")
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian")
    back = trimesh.load(path, process=False)
    assert len(back.vertices) == len(mesh.vertices) and len(back.faces) == len(mesh.faces)
    assert np.allclose(back.vertices, mesh.vertices, atol=1e-5)
    assert np.array_equal(back.visual.vertex_colors, mesh.visual.vertex_colors)


def test_glb_round_trip_keeps_geometry_and_colours(sphere_grid, tmp_path):
    mesh = extract_mesh(sphere_grid)
    path = save_mesh(mesh, tmp_path / "m.glb")
    assert path.read_bytes()[:4] == b"glTF"
    back = trimesh.load(path, force="mesh", skip_materials=True)  # (with its material, trimesh drops COLOR_0)
    # glTF readers may weld duplicate vertices; marching cubes emits none, so counts agree.
    assert len(back.faces) == len(mesh.faces)
    assert len(back.vertices) == len(np.unique(mesh.vertices.round(6), axis=0))
    assert np.allclose(back.bounds, mesh.bounds, atol=1e-5)
    colors = back.visual.vertex_colors  # linear light: (250, 5, 5) sRGB is (244, 0, 0)
    assert (colors[:, 0] > 240).all() and (colors[:, 1:3] < 15).all()


def glb_document(path) -> tuple[dict, bytes]:
    """A GLB's JSON chunk and binary chunk, read by the format's layout."""
    import json

    data = path.read_bytes()
    assert data[:4] == b"glTF" and int.from_bytes(data[4:8], "little") == 2
    assert int.from_bytes(data[8:12], "little") == len(data)
    json_length = int.from_bytes(data[12:16], "little")
    assert data[16:20] == b"JSON" and data[20 + json_length + 4 : 20 + json_length + 8] == b"BIN\0"
    return json.loads(data[20 : 20 + json_length]), data[20 + json_length + 8 :]


def test_glb_is_y_up_with_linear_colours_on_a_matte_material(tmp_path):
    """Regression: the GLB was written as trimesh exports it, against three glTF rules the web UI's model-viewer
    (three.js) follows: +y is up (an upright object lay on its back, its top facing the viewer), COLOR_0 is
    linear light (the sRGB colours showed washed out: mid grey 128 as 188) and a primitive without a material is
    fully metallic (the colours showed as dull metal)."""
    grid = VoxelGrid(32)
    axes = [torch.linspace(-1.5, 1.5, 32)] * 3
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    rod = torch.maximum((x**2 + y**2).sqrt() - 0.4, (z - 0.2).abs() - 1.0)  # upright: 2 tall on +z, 0.2 up
    with torch.no_grad():
        grid.features[..., 0] = -5 * rod / float(grid.voxel_size.min())
        grid.features[..., 1:] = torch.tensor([0.0, 2.0, -2.0])  # sigmoid: sRGB (0.5, 0.881, 0.119)
    mesh = extract_mesh(grid)
    path = save_mesh(mesh, tmp_path / "m.glb")

    viewed = trimesh.load(path, force="mesh", skip_materials=True)  # node transforms applied, as viewers do
    size = viewed.extents
    assert size[1] == pytest.approx(2.0, abs=0.2) and size[0] < 1 and size[2] < 1  # tall along glTF's up, +y
    assert viewed.bounds[:, 1].mean() == pytest.approx(0.2, abs=0.05)  # the grid's +z is +y
    assert np.allclose(viewed.vertices, mesh.vertices[:, [0, 2, 1]] * [1, 1, -1], atol=1e-5)

    document, binary = glb_document(path)
    primitive = document["meshes"][0]["primitives"][0]
    material = document["materials"][primitive["material"]]["pbrMetallicRoughness"]
    assert material["metallicFactor"] == 0 and material.get("baseColorFactor", [1] * 4) == [1] * 4
    accessor = document["accessors"][primitive["attributes"]["COLOR_0"]]
    view = document["bufferViews"][accessor["bufferView"]]
    assert accessor["componentType"] == 5126 and accessor["type"] == "VEC3"  # float32: no 8-bit banding
    linear = np.frombuffer(binary, np.float32, accessor["count"] * 3, view.get("byteOffset", 0)).reshape(-1, 3)
    srgb = np.asarray(mesh.visual.vertex_colors[:, :3]) / 255
    assert np.allclose(linear, np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4), atol=1e-6)
    assert linear[0] == pytest.approx([0.2158, 0.7529, 0.0130], abs=2e-3)  # sRGB (128, 225, 30)


def test_obj_round_trip_keeps_vertices_faces_and_colours(sphere_grid, tmp_path):
    """Parsed by hand (the format, not one reader's leniency), then by trimesh as a user's tool would."""
    mesh = extract_mesh(sphere_grid)
    path = save_mesh(mesh, tmp_path / "m.obj")
    lines = path.read_text().splitlines()
    assert "mtllib m.mtl" in lines and (tmp_path / "m.mtl").is_file()
    rows = np.array([[float(x) for x in line.split()[1:]] for line in lines if line.startswith("v ")])
    faces = np.array([[int(x) for x in line.split()[1:]] for line in lines if line.startswith("f ")])
    assert rows.shape == (len(mesh.vertices), 6) and np.array_equal(faces - 1, mesh.faces)
    assert np.allclose(rows[:, :3], mesh.vertices, atol=1e-6)
    assert np.array_equal(np.round(rows[:, 3:] * 255).astype(np.uint8), mesh.visual.vertex_colors[:, :3])
    kd = next(line for line in (tmp_path / "m.mtl").read_text().splitlines() if line.startswith("Kd "))
    assert np.allclose([float(x) for x in kd.split()[1:]], rows[:, 3:].mean(0), atol=1e-6)
    back = trimesh.load(path, process=False, maintain_order=True, skip_materials=True)  # its reader prefers the MTL
    assert len(back.vertices) == len(mesh.vertices) and len(back.faces) == len(mesh.faces)
    assert (back.visual.vertex_colors[:, 0] > 240).all() and (back.visual.vertex_colors[:, 1:3] < 15).all()


def test_an_obj_whose_material_library_cannot_be_written_leaves_the_earlier_obj(sphere_grid, tmp_path):
    """The OBJ had been renamed into place before its MTL, so an MTL that failed (a folder of its name) left a new
    OBJ over the earlier one, naming a library that is not there."""
    (tmp_path / "m.obj").write_text("the earlier run's")
    (tmp_path / "m.mtl").mkdir()
    with pytest.raises(OSError):
        save_mesh(extract_mesh(sphere_grid), tmp_path / "m.obj")
    assert (tmp_path / "m.obj").read_text() == "the earlier run's"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["m.mtl", "m.obj"]


@pytest.mark.parametrize("size", [1e-5, 1e-3, 1e4])
def test_every_mesh_format_keeps_the_vertices_of_a_tiny_or_huge_box(tmp_path, size):
    """Regression: OBJ positions had 6 decimals whatever the scale, so in a 1e-5 box every vertex moved by up to 5 %
    of the box (1.5 voxels here) while PLY and GLB kept float32's precision."""
    grid = VoxelGrid(32, bbox_min=(0.0, 0.0, 0.0), bbox_max=(size,) * 3)
    with torch.no_grad():
        x = torch.linspace(-1, 1, 32) ** 2
        grid.features[..., 0] = (0.6 - (x[:, None, None] + x[None, :, None] + x[None, None, :]).sqrt()) * 10  # a ball
    mesh = extract_mesh(grid)
    for suffix in (".ply", ".glb", ".obj"):
        back = trimesh.load(save_mesh(mesh, tmp_path / f"m{suffix}"), force="mesh", process=False)
        assert len(back.vertices) == len(mesh.vertices), suffix
        # (a GLB is y up: the grid's (x, y, z) is its (x, z, -y))
        expected = mesh.vertices[:, [0, 2, 1]] * [1, 1, -1] if suffix == ".glb" else mesh.vertices
        assert np.abs(np.asarray(back.vertices) - expected).max() <= 1e-6 * size, suffix


@pytest.mark.parametrize("suffix", [".ply", ".glb", ".obj"])
def test_a_mesh_save_that_fails_keeps_the_earlier_file_and_leaves_no_partial_one(sphere_grid, tmp_path, suffix):
    """A full disk (a file-size limit stands in for it): the save had streamed into the final name, leaving a
    torn mesh there in place of the earlier one."""
    import resource

    mesh = extract_mesh(sphere_grid)
    path = tmp_path / f"m{suffix}"
    earlier = {path: b"the earlier mesh", path.with_suffix(".mtl"): b"the earlier material"}
    for file, content in earlier.items():
        file.write_bytes(content)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, hard))  # (Python ignores SIGXFSZ: writes fail EFBIG)
    try:
        with pytest.raises(OSError):
            save_mesh(mesh, path)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert {f: f.read_bytes() for f in earlier} == earlier
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f.name for f in earlier)


def test_save_mesh_rejects_unknown_suffix(sphere_grid, tmp_path):
    with pytest.raises(ValueError, match=r"'\.stl'"):
        save_mesh(extract_mesh(sphere_grid), tmp_path / "m.stl")


# -------------------------------------------------------------- turntable centre
BLOB_RADIUS = 0.45


def scene_blob(centre) -> SceneGrid:
    """A 33³ scene grid holding one ball of radius 0.45 (canonical units) at ``centre``; the background is empty.

    Its foreground lattice (17³ over [-1.5, 1.5]³, spacing 0.1875) has a vertex at each centre used below,
    so the ball's voxel weights are symmetric about it.
    """
    grid = SceneGrid(33)
    axis = torch.linspace(-2.0, 2.0, 33)  # contracted coordinates of the lattice
    contracted = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1)
    canonical = contracted * grid.foreground_extent  # exact inside the foreground, where the ball is
    distance = (canonical - torch.tensor(centre)).norm(dim=-1)
    inside = contracted.abs().amax(-1) <= 1.0
    with torch.no_grad():
        grid.features[..., 0] = torch.where(inside, 40.0 * (BLOB_RADIUS - distance), torch.tensor(-1.0))
        grid.features[..., 1:] = torch.tensor(RED_LOGITS)
    return grid



def image_centroids(grid, cameras) -> torch.Tensor:
    """(N, 2) opacity-weighted (x, y) pixel centroid of each view (pixel centres at i + 0.5)."""
    out = []
    for i in range(len(cameras)):
        opacity = render_image(grid, cameras, i).opacity
        h, w = opacity.shape
        ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
        out.append(torch.stack([(opacity * xs).sum(), (opacity * ys).sum()]) / opacity.sum())
    return torch.stack(out)


def test_a_turntable_keeps_an_off_centre_capture_object_in_the_middle_of_every_frame():
    """The capture frame's origin is where the cameras looked; the ball sits 0.69 units away from it."""
    blob = (0.5625, -0.375, 0.1875)
    grid = scene_blob(blob)
    centre = grid.orbit_centre()
    assert torch.allclose(centre, torch.tensor(blob), atol=1e-5)
    size = 32
    cameras = turntable_cameras(6, 30.0, size, centre=centre)
    eye = cameras.c2w[:, :3, 3] - centre
    assert torch.allclose(eye.norm(dim=-1), torch.full((6,), 4.0311), atol=1e-4)  # the ring's radius, about the ball
    around_ball = image_centroids(grid, cameras)
    assert (around_ball - size / 2).abs().max() < 0.25, around_ball  # the middle of every frame, to a quarter pixel
    around_origin = image_centroids(grid, turntable_cameras(3, 30.0, size))
    assert (around_origin - size / 2).abs().max() > 4.0, around_origin  # what an orbit of the frame's origin does


def test_a_centred_capture_object_and_an_object_grid_keep_the_origin_ring(make_sphere_grid):
    centred = scene_blob((0.0, 0.0, 0.0))
    assert centred.orbit_centre().abs().max() < 1e-6
    ring = turntable_cameras(8, 30.0, 32)
    assert torch.allclose(turntable_cameras(8, 30.0, 32, centre=centred.orbit_centre()).c2w, ring.c2w, atol=1e-5)
    # An object grid is centred by convention (SPEC §0): its ring stays the paper's even with the object off it.
    off_centre = make_sphere_grid(center=(0.5, 0.0, 0.0))
    assert torch.equal(off_centre.orbit_centre(), torch.zeros(3))
    assert torch.equal(turntable_cameras(8, 30.0, 32, centre=off_centre.orbit_centre()).c2w, ring.c2w)
    assert torch.allclose(off_centre.matter_centre(), torch.tensor([0.5, 0.0, 0.0]), atol=0.02)  # yet it knows where it is


def test_matter_centre_weighs_by_opacity_and_is_the_box_centre_when_empty():
    grid = VoxelGrid(5, (0.0, 0.0, 0.0), (4.0, 4.0, 4.0))  # vertices at 0, 1, 2, 3, 4
    with torch.no_grad():
        grid.features[..., 0] = -1.0
    assert torch.equal(grid.matter_centre(), torch.tensor([2.0, 2.0, 2.0]))
    with torch.no_grad():
        grid.features[0, 0, 0, 0] = 1e4  # opaque: weight 1
        grid.features[4, 0, 0, 0] = 1e4
        grid.features[4, 4, 4, 0] = 1e-3 / grid.density_scale  # haze: weight 1 − e^(−0.001) ≈ 0.001
    haze = -math.expm1(-1e-3)
    expected = torch.tensor([(4.0 + 4.0 * haze), 4.0 * haze, 4.0 * haze]) / (2.0 + haze)
    assert torch.allclose(grid.matter_centre(), expected, atol=1e-6)


@pytest.mark.parametrize("vertices", [0, 3])
def test_a_glb_of_a_mesh_without_faces_is_refused_and_nothing_written(vertices, tmp_path):
    """glTF allows no empty accessor: the writer had raised numpy's "zero-size array" for an empty mesh and written
    a file the glTF validator refuses (accessor and buffer view of length 0) for vertices without faces."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=np.zeros((vertices, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)
    with pytest.raises(ValueError, match=f"a mesh without faces \\({vertices} vertices\\) cannot be written as glTF"):
        save_mesh(mesh, tmp_path / "empty.glb")
    assert list(tmp_path.iterdir()) == []
