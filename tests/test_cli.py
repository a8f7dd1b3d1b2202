"""The ``voxe`` CLI end to end, in-process (plus one real subprocess), on tiny settings."""

from __future__ import annotations

import errno
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from types import SimpleNamespace

import imageio.v2 as imageio
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

import voxe_core.reconstruct
from voxe_core.backbones import load_grid
from voxe_core.cli import main
from voxe_core.cli.common import STAGING_MARKER, load_guidance as load_guidance_of_common
from voxe_core.constants import MAX_REFINE_VIEWS, MAX_RENDER_SIZE
from voxe_core.data import load_scene
from voxe_core.export import render_views
from voxe_core.grid import VoxelGrid
from voxe_core.metrics import psnr, ssim

from needs import MIC, needs_data

REPO = Path(__file__).resolve().parents[1]

needs_mic = needs_data(MIC)

# 4 training views of 50x50, 8³ -> 15³ -> 24³ with 3/3/4 iterations of 512 rays: about two seconds.
TINY = ["--downsample", "16", "--max-images", "4", "--resolution", "24", "--iterations", "3,3,4",
        "--rays", "512", "--quiet"]


@pytest.fixture(scope="module")
def fitted(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fit") / "grid.safetensors"
    assert main(["reconstruct", str(MIC), "--out", str(out), *TINY]) == 0
    return out


@pytest.fixture
def sphere_file(sphere_grid, tmp_path) -> Path:
    path = tmp_path / "sphere.safetensors"
    sphere_grid.save(path)
    return path


# ---------------------------------------------------------------- reconstruct
@needs_mic
def test_reconstruct_writes_a_loadable_grid_with_the_asked_schedule(fitted, capsys):
    grid = load_grid(fitted)
    assert grid.resolution == (24, 24, 24)
    assert torch.isfinite(grid.features).all()
    # It trained: the initial uniform raw density 0.01 is gone.
    assert not torch.allclose(grid.features[..., 0], torch.full((24, 24, 24), 0.01))


@needs_mic
def test_reconstruct_reports_stats(tmp_path, capsys):
    out = tmp_path / "g.safetensors"
    args = ["--downsample", "16", "--max-images", "2", "--resolution", "24", "--iterations", "1,1,1", "--rays", "64"]
    assert main(["reconstruct", str(MIC), "--out", str(out), *args]) == 0
    captured = capsys.readouterr()
    fraction = float(captured.out.split("occupied fraction")[1].split()[0])
    assert fraction == pytest.approx(load_grid(out).occupancy().fraction, abs=1e-4)
    assert "fitting 2 train images of 50x50" in captured.err
    assert "resolutions [8, 15, 24]" in captured.err and "iterations [1, 1, 1]" in captured.err
    assert "reconstruct: 100%" in captured.err  # the progress bar ran to the end


@needs_mic
def test_ctrl_c_cancels_cleanly_and_resume_finishes_the_same_fit(fitted, tmp_path, monkeypatch, capsys):
    real = voxe_core.reconstruct.reconstruct
    seen = []

    def interrupted(images, cameras, config, callbacks, checkpoint_path, resume_from, initial_grid=None, device="cpu"):
        report = callbacks.on_progress

        def on_progress(p):
            seen.append(p.iteration)
            report(p)
            if p.iteration == 5:
                os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C does

        callbacks.on_progress = on_progress
        return real(images, cameras, config, callbacks, checkpoint_path, resume_from, initial_grid, device)

    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", interrupted)
    out, ck = tmp_path / "g.safetensors", tmp_path / "ck.safetensors"
    previous_handler = signal.getsignal(signal.SIGINT)
    code = main(["reconstruct", str(MIC), "--out", str(out), "--checkpoint", str(ck), "--checkpoint-every", "2", *TINY])
    assert code == 130
    assert seen == [1, 2, 3, 4, 5]  # stopped at the next cancellation check
    assert not out.exists() and ck.is_file()
    err = capsys.readouterr().err
    assert "cancelled" in err and f"--resume {ck}" in err and "Traceback" not in err
    assert signal.getsignal(signal.SIGINT) is previous_handler  # handler restored

    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", real)
    assert main(["reconstruct", str(MIC), "--out", str(out), "--resume", str(ck), *TINY]) == 0
    resumed, uninterrupted = load_grid(out), load_grid(fitted)
    assert torch.allclose(resumed.features, uninterrupted.features, atol=1e-5)


@needs_mic
def test_reconstruct_refuses_to_resume_from_the_file_it_would_write_before_any_work(tmp_path, monkeypatch, capsys):
    """--resume X --out X had been taken: the finished grid replaced the checkpoint it resumed from, so the fit could
    not be resumed or rerun from it again."""
    real = voxe_core.reconstruct.reconstruct

    def cancelled_at_4(images, cameras, config, callbacks, *args):  # leaves its checkpoint, as Ctrl-C does
        done, report = [], callbacks.on_progress
        callbacks.on_progress = lambda progress: (done.append(progress.iteration), report(progress))
        callbacks.should_cancel = lambda: len(done) >= 4
        return real(images, cameras, config, callbacks, *args)

    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", cancelled_at_4)
    ck = tmp_path / "ck.safetensors"
    assert main(["reconstruct", str(MIC), "--out", str(tmp_path / "g.safetensors"), "--checkpoint", str(ck),
                 "--checkpoint-every", "2", *TINY]) == 130
    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", real)
    checkpoint = ck.read_bytes()
    capsys.readouterr()
    assert main(["reconstruct", str(MIC), "--resume", str(ck), "--out", str(tmp_path / "." / "ck.safetensors"),
                 *TINY]) == 2
    err = capsys.readouterr().err
    assert "--resume and --out both name" in err and "fitting" not in err  # refused before the data is read
    assert ck.read_bytes() == checkpoint


@pytest.mark.skipif(torch.cuda.is_available(), reason="shows the refusal of a device this machine lacks")
@pytest.mark.parametrize("command", [
    ["reconstruct", "no_such_scene", "--out", "g.safetensors"],
    ["render", "no_such_grid.safetensors", "--ring", "2", "--out", "renders"],
    ["turntable", "no_such_grid.safetensors", "--out", "t.mp4"],
    ["export-mesh", "no_such_grid.safetensors", "--out", "m.ply"],
    ["mesh-to-grid", "no_such_mesh.obj", "--route", "render", "--out", "g.safetensors"],
    ["evaluate", "no_such_grid.safetensors", "--edit", "e.safetensors", "a dog", "--object", "dog", "--out", "eval"],
    ["edit", "no_such_grid.safetensors", "--prompt", "a dog", "--out", "edit"],
    ["refine", "no_such_edit.safetensors", "--initial", "no_such_grid.safetensors", "--prompt", "a dog",
     "--edit-words", "dog", "--out", "refine"],
])
def test_stage_commands_refuse_a_missing_device_before_reading_anything(command, tmp_path, capsys, monkeypatch):
    """--device cuda on a CPU machine: exit 2 naming the device, not the missing input read after it."""
    monkeypatch.chdir(tmp_path)
    assert main([*command, "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert "'cuda' asked for" in err and "no usable CUDA device" in err and "no_such" not in err
    assert main([*command, "--device", "meta"]) == 2  # a kind torch names and no stage runs on: had been a traceback
    err = capsys.readouterr().err
    assert "device 'meta' is not supported here: use 'cpu' or a CUDA device" in err and "no_such" not in err


REFINE_MISSING = ["refine", "no_such_edit.safetensors", "--initial", "no_such_grid.safetensors", "--out", "refine"]


@pytest.mark.parametrize("command, said", [
    ([*REFINE_MISSING, "--prompt", "a dog wearing a hat", "--edit-words", "zebra"],
     "edit word 'zebra' does not occur in the prompt"),
    ([*REFINE_MISSING, "--prompt", "a dog wearing a hat!", "--edit-words", "hat!"],
     "does not occur in the prompt as the model reads it"),
    ([*REFINE_MISSING, "--prompt", "sunglasses", "--edit-words", "sunglasses"], "nothing names the object"),
    ([*REFINE_MISSING, "--prompt", "a dog! a hat", "--edit-words", "!"], "edit word '!' names nothing"),
    ([*REFINE_MISSING, "--prompt", "a mic " + "very " * 80, "--edit-words", "mic"], "tokens as the model sees it"),
    (["edit", "no_such_grid.safetensors", "--prompt", "a mic " + "very " * 80, "--out", "edit"],
     "tokens as the model sees it"),
])
def test_a_prompt_or_edit_word_the_model_cannot_read_is_refused_before_anything_is_read(command, said, tmp_path,
                                                                                         capsys, monkeypatch):
    """They had been found after the grids were read and the model loaded (a download of gigabytes, maybe)."""
    monkeypatch.chdir(tmp_path)
    assert main([*command, "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert said in err and "no_such" not in err, err


@pytest.mark.parametrize("prompt, edit_word", [("a \U0001f3a9 on a mic", "\U0001f3a9"),
                                               ("a \u2665 necklace on a dog", "\u2665")])
def test_a_symbol_the_model_reads_is_an_edit_word(prompt, edit_word, tmp_path, capsys, monkeypatch):
    """An emoji or symbol edit word, which the tokenizer finds, had been refused up front as having no letters or
    numbers: the refinement now goes on to read its grids (missing here)."""
    monkeypatch.chdir(tmp_path)
    assert main([*REFINE_MISSING, "--prompt", prompt, "--edit-words", edit_word, "--device", "cpu"]) == 2
    assert "no_such_grid.safetensors: no such file" in capsys.readouterr().err


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO])
def test_a_machine_side_os_error_exits_1_not_as_bad_input(tmp_path, monkeypatch, capsys, code):
    """A full disk (or quota), a file size limit (EFBIG: RLIMIT_FSIZE, FAT32's 4 GiB) or an I/O error at a stage's
    end had exited 2, "bad input", as a missing file does: a script told to fix its arguments. It is the machine's
    failure: 1, as README's exit statuses say."""
    import voxe_core.cli.grids

    def failing(args):
        raise OSError(code, os.strerror(code), str(tmp_path / "g.safetensors"))

    monkeypatch.setattr(voxe_core.cli.grids, "cmd_convert_grid", failing)
    assert main(["convert-grid", str(tmp_path / "in.safetensors"), "--out", str(tmp_path / "g2.safetensors")]) == 1
    assert f"voxe convert-grid: error: [Errno {code}] {os.strerror(code)}" in capsys.readouterr().err


def test_bad_data_dir_exits_2_with_a_message(tmp_path, capsys):
    missing = tmp_path / "no_such_scene"
    assert main(["reconstruct", str(missing), "--out", str(tmp_path / "g.safetensors")]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "not a folder" in err and "Traceback" not in err

    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "transforms_train.json").write_text("{not json")
    assert main(["reconstruct", str(tmp_path / "scene"), "--out", str(tmp_path / "g.safetensors")]) == 2
    assert "transforms_train.json" in capsys.readouterr().err


class FakeSweeps:
    """A service client for ``voxe sweep``: the sweep it makes is in each of ``states`` at the polls in turn, with
    job ``counts``; ``polls`` counts them."""

    base_url = "http://service"

    def __init__(self, states: Iterable[str], counts: dict[str, int]):
        self.states, self.counts, self.polls = iter(states), counts, 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def create_sweep(self, scenes, params=None, evaluation=None, idempotency_key=None):
        return {"id": "s1", "entries": [{}] * 6, "state": "queued", "counts": {"queued": 12}, "table": "T\n"}

    def get_sweep(self, sweep_id):
        self.polls += 1
        return {"id": sweep_id, "entries": [], "state": next(self.states), "counts": self.counts, "table": "T\n"}


def test_a_waited_sweeps_table_on_a_stdout_that_cannot_encode_it_is_printed_escaped(monkeypatch, capsys):
    """Regression: a table naming "a café ☕" on a Latin-1 stdout raised UnicodeEncodeError after the sweep ended:
    "voxe sweep: error: 'latin-1' codec can't encode character '\\u2615'", exit 2 for a sweep that succeeded."""
    import io

    import voxe_core.cli.service as service

    sweeps = FakeSweeps(["succeeded"], {"succeeded": 12})
    monkeypatch.setattr(sweeps, "get_sweep", lambda sweep_id: {"id": sweep_id, "entries": [], "state": "succeeded",
                                                                 "counts": {"succeeded": 12}, "table": "a café ☕\n"})
    monkeypatch.setattr(service, "_client", lambda args: sweeps)
    latin1 = io.TextIOWrapper(io.BytesIO(), encoding="latin-1")
    monkeypatch.setattr(sys, "stdout", latin1)
    assert main(["sweep", "--scene", "s1=mic", "--wait", "--poll", "0.01", "-q"]) == 0
    latin1.flush()
    assert latin1.buffer.getvalue().decode("latin-1") == "a café \\u2615\n" and latin1.errors == "strict"
    assert "error" not in capsys.readouterr().err


@pytest.mark.parametrize("command", [[], ["edit"], ["refine"], ["reconstruct"], ["render"]])
def test_a_help_on_a_stdout_that_cannot_encode_it_is_printed_escaped(monkeypatch, command):
    """Regression: a help naming §, λ, → or ° (voxe --help, voxe refine --help) on an ASCII stdout
    (PYTHONIOENCODING=ascii) raised UnicodeEncodeError, a traceback and exit 1: only a command's run escaped them."""
    import io

    ascii_out = io.TextIOWrapper(io.BytesIO(), encoding="ascii")
    monkeypatch.setattr(sys, "stdout", ascii_out)
    with pytest.raises(SystemExit) as done:
        main([*command, "--help"])
    assert done.value.code == 0
    ascii_out.flush()
    shown = ascii_out.buffer.getvalue().decode("ascii")
    assert shown.startswith("usage: voxe") and re.search(r"\\(x[0-9a-f]{2}|u[0-9a-f]{4})", shown)
    assert ascii_out.errors == "strict"


def test_a_c_locales_stdout_escapes_what_it_cannot_encode_and_keeps_undecoded_bytes(monkeypatch, capsys):
    """A C locale's stdout (ASCII, its handler surrogateescape: Python's UTF-8 mode off) had been left as it was: a
    sweep's table naming "a café ☕" raised "'ascii' codec can't encode character" (exit 2, the sweep done), a help
    naming λ a traceback. Now escaped, while a byte the locale could not decode (a file name's) is written back."""
    import io

    import voxe_core.cli.service as service

    sweeps = FakeSweeps(["succeeded"], {"succeeded": 12})
    table = "a café ☕ " + b"\xc3\xa9\n".decode("ascii", "surrogateescape")
    monkeypatch.setattr(sweeps, "get_sweep", lambda sweep_id: {"id": sweep_id, "entries": [], "state": "succeeded",
                                                                 "counts": {"succeeded": 12}, "table": table})
    monkeypatch.setattr(service, "_client", lambda args: sweeps)
    c_locales = io.TextIOWrapper(io.BytesIO(), encoding="ascii", errors="surrogateescape")
    monkeypatch.setattr(sys, "stdout", c_locales)
    assert main(["sweep", "--scene", "s1=mic", "--wait", "--poll", "0.01", "-q"]) == 0
    with pytest.raises(SystemExit) as done:
        main(["refine", "--help"])
    assert done.value.code == 0
    c_locales.flush()
    written = c_locales.buffer.getvalue()
    assert written.startswith(b"a caf\\xe9 \\u2615 \xc3\xa9\nusage: voxe refine") and b"\\u03bb" in written
    assert c_locales.errors == "surrogateescape" and "error" not in capsys.readouterr().err


@pytest.mark.parametrize("end, code", [("succeeded", 0), ("failed", 1), ("canceled", 1)])
def test_a_waited_sweep_exits_1_unless_it_succeeded(monkeypatch, capsys, tmp_path, end, code):
    """As voxe wait does for a job: a failed sweep had exited 0, saying nothing of its failed jobs."""
    import voxe_core.cli.service as service

    counts = {"succeeded": 12} if end == "succeeded" else {end: 6, "succeeded": 6}
    sweeps = FakeSweeps(["running", end], counts)
    monkeypatch.setattr(service, "_client", lambda args: sweeps)
    assert main(["sweep", "--scene", "s1=mic", "--wait", "--poll", "0.01", "--out", str(tmp_path / "s.json")]) == code
    err = capsys.readouterr().err
    assert (f"ended {end}: jobs {{'{end}': 6, 'succeeded': 6}}" in err) == (code == 1)


def test_a_sweeps_out_file_keeps_its_text_as_written(monkeypatch, tmp_path):
    """``voxe sweep --out`` wrote "a caf\\u00e9" where ``voxe status`` prints "a café": the CLI's JSON files are
    UTF-8, their text as written, whatever the locale's encoding."""
    import voxe_core.cli.service as service

    sweeps = FakeSweeps(["succeeded"], {"succeeded": 12})
    real_get = sweeps.get_sweep
    monkeypatch.setattr(sweeps, "get_sweep", lambda sweep_id: {**real_get(sweep_id), "table": "a café ☕\n"})
    monkeypatch.setattr(service, "_client", lambda args: sweeps)
    out = tmp_path / "s.json"
    assert main(["sweep", "--scene", "s1=mic", "--wait", "--poll", "0.01", "--out", str(out)]) == 0
    assert '"table": "a café ☕\\n"' in out.read_bytes().decode("utf-8")
    assert json.loads(out.read_bytes())["table"] == "a café ☕\n"


@pytest.fixture
def sigterm_fails_the_test():
    """A SIGTERM that the command under test leaves unhandled fails the test, rather than killing pytest."""
    def unhandled(signum, frame):
        pytest.fail("the command left SIGTERM to its default: the process would have been killed")

    previous = signal.signal(signal.SIGTERM, unhandled)
    yield
    signal.signal(signal.SIGTERM, previous)


@pytest.mark.parametrize("signum,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_during_a_waited_sweeps_pause_stops_waiting_at_once(monkeypatch, capsys, sigterm_fails_the_test,
                                                                  signum, code):
    """Ctrl-C between a waited sweep's polls had been answered only once the pause was over (``--poll 600``: ten
    minutes), the handler's return resuming the sleep; and no poll follows the Ctrl-C (a hung service's had held it up
    to a minute more). SIGTERM (docker stop) does the same, exiting 143: it had killed the command, no table said."""
    import itertools
    import threading

    import voxe_core.cli.service as service

    def ctrl_c_while_waiting():
        while signal.getsignal(signal.SIGINT) is default:  # once the command's handler is in place
            time.sleep(0.01)
        time.sleep(0.2)
        os.kill(os.getpid(), signum)

    sweeps = FakeSweeps(itertools.repeat("running"), {"running": 12})
    monkeypatch.setattr(service, "_client", lambda args: sweeps)
    default = signal.getsignal(signal.SIGINT)
    threading.Thread(target=ctrl_c_while_waiting, daemon=True).start()
    started = time.monotonic()
    assert main(["sweep", "--scene", "s1=mic", "--wait", "--poll", "20"]) == code
    assert time.monotonic() - started < 10 and sweeps.polls == 0
    assert capsys.readouterr().err.endswith("voxe sweep: stopped waiting; the sweep s1 goes on in the service (`voxe "
                                            "cancel-sweep s1` stops it)\n")


def test_ctrl_c_during_a_waited_sweep_writes_no_summary_as_if_final(monkeypatch, capsys, tmp_path):
    """``--out FILE`` is "the final summary JSON", but a Ctrl-C had written the last poll there, a sweep still
    running, as if it were: nothing is written now (an earlier FILE stays as it was), and the command says so."""
    import threading

    import voxe_core.cli.service as service

    def ctrl_c_while_waiting():
        while signal.getsignal(signal.SIGINT) is default:
            time.sleep(0.01)
        time.sleep(0.2)
        os.kill(os.getpid(), signal.SIGINT)

    out = tmp_path / "s.json"
    out.write_text("earlier")
    monkeypatch.setattr(service, "_client", lambda args: FakeSweeps(["running"] * 1000, {"running": 12}))
    default = signal.getsignal(signal.SIGINT)
    threading.Thread(target=ctrl_c_while_waiting, daemon=True).start()
    assert main(["sweep", "--scene", "s1=mic", "--wait", "--poll", "0.01", "--out", str(out)]) == 130
    assert out.read_text() == "earlier"
    assert capsys.readouterr().err.endswith(
        f"voxe sweep: {out} not written: the sweep had not ended (GET /v1/sweeps/s1 gives its summary)\n"
        "voxe sweep: stopped waiting; the sweep s1 goes on in the service (`voxe cancel-sweep s1` stops "
        "it)\n")


def test_a_waited_sweep_polls_on_through_an_outage_for_as_long_as_wait_reconnects(monkeypatch, capsys, tmp_path):
    """One poll refused (an API restarting) had ended ``voxe sweep --wait`` with exit 3 and no --out, and no command
    takes the wait up again: polls the service fails or does not answer go on for ``RECONNECT_FOR_S``, said once;
    after that, or at a refusal (4xx), the error ends it as before."""
    import httpx

    import voxe_client.client as client_module
    import voxe_core.cli.service as service
    from voxe_client import Client

    polls = []

    def answer(request: httpx.Request) -> httpx.Response:
        if request.method == "POST":
            return httpx.Response(201, json={"id": "s1", "entries": [{}] * 6, "state": "queued",
                                             "counts": {"queued": 12}, "table": "T\n"})
        polls.append(outage.pop(0) if outage else "succeeded")
        if polls[-1] == "refused":
            raise httpx.ConnectError("connection refused")
        if isinstance(polls[-1], int):
            return httpx.Response(polls[-1], json={"detail": "no such sweep"})
        return httpx.Response(200, json={"id": "s1", "entries": [], "state": polls[-1], "counts": {polls[-1]: 12},
                                         "table": "T\n"})

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    wait = ["sweep", "--scene", "s1=mic", "--wait", "--poll", "0.01", "--out", str(tmp_path / "s.json")]
    outage = ["running", "refused", 502, "refused"]
    assert main(wait) == 0 and polls == ["running", "refused", 502, "refused", "succeeded"]
    assert json.loads((tmp_path / "s.json").read_text())["state"] == "succeeded"
    err = capsys.readouterr().err
    assert err.count("voxe sweep: cannot reach the service at http://127.0.0.1:8000: connection refused; polling on "
                     "for up to 300 s (the sweep goes on in the service)") == 1 and err.count("running, jobs") == 1
    monkeypatch.setattr(client_module, "RECONNECT_FOR_S", 0.05)
    polls.clear()
    outage = ["refused"] * 1000
    assert main(wait) == 3 and 1 < len(polls) < 1000
    assert capsys.readouterr().err.endswith("voxe sweep: error: cannot reach the service at http://127.0.0.1:8000: "
                                            "connection refused\n")
    polls.clear()
    outage = [404]
    assert main(wait) == 2 and polls == [404]
    assert capsys.readouterr().err.endswith("voxe sweep: error: GET /v1/sweeps/s1: HTTP 404: no such sweep\n")


def test_a_sweep_not_waited_for_prints_its_id_and_where_its_table_fills_in(monkeypatch, capsys, tmp_path):
    """Without --wait it had printed its summary table's header with no row (the sweep had just been queued), its
    id nowhere on stdout."""
    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client
    from voxe_core.evaluate import format_table

    created = {"id": "sw1", "state": "queued", "counts": {"queued": 12}, "entries": [{}] * 6, "rows": [],
               "table": format_table([], extra_columns=("object",))}
    monkeypatch.setattr(service, "_client", lambda args: Client(
        "http://svc.test", transport=httpx.MockTransport(lambda request: httpx.Response(201, json=created))))
    assert main(["sweep", "--scene", "s1=mic", "--out", str(tmp_path / "s.json")]) == 0
    printed = capsys.readouterr()
    assert printed.out == "sw1\n"
    assert printed.err.splitlines()[-1] == ("voxe sweep: not waited for (--wait polls until it ends): GET "
                                            "/v1/sweeps/sw1 shows its summary table as its evaluations finish")
    assert json.loads((tmp_path / "s.json").read_text()) == created


def test_a_sweep_summary_that_cannot_be_written_is_refused_before_the_sweep_is_created(tmp_path, capsys):
    """--out had been written only after the sweep was created (and, with --wait, after it ended): a folder there
    failed the command with its 12 jobs queued, and running it again queued 12 more."""
    (tmp_path / "taken.json").mkdir()
    assert main(["sweep", "--scene", "s1=mic", "--out", str(tmp_path / "taken.json"),
                 "--api", "http://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert f"cannot write {tmp_path / 'taken.json'}: it is a folder" in err and "cannot reach" not in err
    assert main(["sweep", "--scene", "s1=mic", "--out", str(tmp_path / "new" / "s.json"),
                 "--api", "http://127.0.0.1:9"]) == 3
    assert "cannot reach the service at http://127.0.0.1:9" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken.json"]  # the folder made for --out went again


def test_a_sweep_polled_without_wait_is_refused_before_the_sweep_is_created(capsys):
    """--poll without --wait had been taken and ignored: the sweep was created and the command returned at once."""
    assert main(["sweep", "--scene", "s1=mic", "--poll", "5", "--api", "http://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "--poll sets the seconds between the polls of --wait: pass --wait too" in err and "cannot reach" not in err
    # and submit's --reconnect-for, which only --wait uses: refused before anything is uploaded or submitted
    assert main(["submit", "a mic", "--scene", "s1", "--reconnect-for", "600",
                 "--api", "http://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "--reconnect-for sets how long --wait rides out a lost event stream: pass --wait too" in err
    assert "cannot reach" not in err


def test_wait_rides_out_the_outage_its_reconnect_for_allows_then_says_how_to_follow_again(monkeypatch, capsys):
    """``voxe wait`` had given up after about 15 s of an unreachable service (an API restart during a long job);
    --reconnect-for sets how long it keeps reconnecting, and giving up says the job goes on and how to follow it."""
    import httpx

    import voxe_client.client as client_module
    import voxe_core.cli.service as service
    from voxe_client import Client

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    job = {"id": "j1", "state": "succeeded"}

    def answer(request: httpx.Request) -> httpx.Response:
        stream = {"content-type": "text/event-stream"}
        if not request.url.path.endswith("/events"):
            return httpx.Response(200, json=job)
        if "last-event-id" not in request.headers:  # the API stops, ending the stream
            return httpx.Response(200, headers=stream, content=b'id: 8\nevent: checkpoint\ndata: {}\n\n')
        if clock[0] < 60:  # and restarts
            raise httpx.ConnectError("connection refused")
        return httpx.Response(200, headers=stream, content=b'id: 9\nevent: succeeded\ndata: {}\n\n')

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1", "--quiet"]) == 0  # a minute's outage: the default rides it out
    assert json.loads(capsys.readouterr().out) == job
    clock[0] = 0.0
    assert main(["wait", "j1", "--reconnect-for", "30"]) == 3
    assert capsys.readouterr().err == (
        "voxe wait: event stream of job j1 lost (the server ended the stream before the job ended); reconnecting for "
        "up to 30 s (the job goes on in the service)\n"
        "voxe wait: error: event stream of job j1 at http://127.0.0.1:8000 lost: connection refused (10 attempts over "
        "30 s, reconnecting for up to 30 s); the job goes on in the service: `voxe wait j1` follows it again "
        "(--reconnect-for SECONDS rides out a longer outage)\n")
    clock[0] = 0.0

    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused")

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(refuse)))
    assert main(["wait", "j1"]) == 3  # a service never reached (a wrong --api) is not waited for
    assert capsys.readouterr().err == ("voxe wait: error: cannot reach the service at http://127.0.0.1:8000: "
                                       "connection refused\n") and clock[0] == 0


def test_wait_reconnect_for_0_gives_up_at_the_first_loss_as_the_client_does(monkeypatch, capsys):
    """``Client.wait(reconnect_for=0)`` gives up at the first loss, but ``voxe wait --reconnect-for 0`` had been
    refused ("must be a positive number of seconds"); negative and infinite values still are."""
    import httpx

    import voxe_client.client as client_module
    import voxe_core.cli.service as service
    from voxe_client import Client

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))

    def answer(request: httpx.Request) -> httpx.Response:
        if "last-event-id" not in request.headers:  # the API stops, ending the stream
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 8\nevent: checkpoint\ndata: {}\n\n')
        raise httpx.ConnectError("connection refused")

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1", "--reconnect-for", "0"]) == 3
    assert capsys.readouterr().err == (
        "voxe wait: error: event stream of job j1 at http://127.0.0.1:8000 lost: the server ended the stream before "
        "the job ended (1 attempt over 0 s, reconnecting for up to 0 s); the job goes on in the service: `voxe wait "
        "j1` follows it again (--reconnect-for SECONDS rides out a longer outage)\n") and clock[0] == 0
    for bad in ("-1", "inf"):
        with pytest.raises(SystemExit):
            main(["wait", "j1", "--reconnect-for", bad])
        assert "must be 0 or a positive number of seconds, got" in capsys.readouterr().err


def test_wait_on_a_job_deleted_meanwhile_says_it_was_deleted(monkeypatch, capsys):
    """The service ends the stream of a job deleted meanwhile (or of a key revoked) with an ``error`` event saying so;
    ``voxe wait`` then read the job and ended on that answer, "GET /v1/jobs/j1: HTTP 404: job 'j1' not found", as if
    the id were wrong. It says what the stream said, still a refusal's exit status."""
    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client, ServiceError

    said = {"deleted": (b"job 'j1' was deleted", 404), "revoked": (b"the API key of this stream was revoked", 401)}

    for why, (detail, status) in said.items():
        def answer(request: httpx.Request, detail=detail, status=status) -> httpx.Response:
            if request.url.path.endswith("/events"):
                return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                      content=b'id: 3\nevent: stage_started\ndata: {}\n\n'
                                              b'event: error\ndata: {"detail": "' + detail + b'"}\n\n')
            return httpx.Response(status, json={"detail": "job 'j1' not found" if status == 404 else "invalid key"})

        monkeypatch.setattr(service, "_client",
                            lambda args, answer=answer: Client(transport=httpx.MockTransport(answer)))
        assert main(["wait", "j1", "--quiet"]) == 2, why
        assert capsys.readouterr().err == f"voxe wait: error: event stream of job j1 ended: {detail.decode()}\n"
        with pytest.raises(ServiceError) as raised:
            Client(transport=httpx.MockTransport(answer)).wait("j1")
        assert raised.value.status == status


def test_wait_on_a_job_deleted_while_its_stream_was_lost_says_it_was_deleted(monkeypatch, capsys):
    """A job deleted while ``voxe wait`` reconnected to a stopping API's stream was answered 404 at the reconnect, and
    the wait ended "GET /v1/jobs/j1/events: HTTP 404: job 'j1' not found", as if the id were wrong: it says the job
    is gone, deleted while it was followed."""
    import httpx

    import voxe_client.client as client_module
    import voxe_core.cli.service as service
    from voxe_client import Client

    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: None)

    def answer(request: httpx.Request) -> httpx.Response:
        if "last-event-id" not in request.headers:  # the API stops, ending the stream
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 8\nevent: checkpoint\ndata: {}\n\n')
        return httpx.Response(404, json={"detail": "job 'j1' not found"})

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1", "--quiet"]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        "voxe wait: error: event stream of job j1 ended: the job is gone, deleted while it was followed "
        "(GET /v1/jobs/j1/events: HTTP 404: job 'j1' not found)")


def test_wait_on_a_terminal_ends_the_bars_row_before_its_error(monkeypatch, capsys):
    """On a terminal, ``voxe wait``'s error was written on the progress bar's row, after it: "[#####...] 50.0%
    running editvoxe wait: error: ...". The row is ended first; an error before any bar is drawn (a wrong id) has
    no empty line before it."""
    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    monkeypatch.setattr(shutil, "get_terminal_size", lambda *args: os.terminal_size((100, 24)))
    running = b'event: progress\ndata: {"state": "running", "stage": "edit", "overall_progress": 0.5}\n\n'

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/nope/events":
            return httpx.Response(404, json={"detail": "job 'nope' not found"})
        if request.url.path.endswith("/events"):
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=running + b'event: error\ndata: {"detail": "job \'j1\' was deleted"}\n\n')
        return httpx.Response(404, json={"detail": "job 'j1' not found"})

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1"]) == 2
    assert capsys.readouterr().err == (
        "\r[###############               ]  50.0% running edit\n"
        "voxe wait: error: event stream of job j1 ended: job 'j1' was deleted\n")
    assert main(["wait", "nope"]) == 2
    assert capsys.readouterr().err == "voxe wait: error: GET /v1/jobs/nope/events: HTTP 404: job 'nope' not found\n"


def test_wait_says_when_it_reconnects_and_when_the_stream_is_back(monkeypatch, capsys):
    """While ``voxe wait`` rode out an outage its progress line froze with nothing said, as if the job had hung."""
    import httpx

    import voxe_client.client as client_module
    import voxe_core.cli.service as service
    from voxe_client import Client

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    running = b'event: progress\ndata: {"state": "running", "stage": "edit", "overall_progress": 0.5}\n\n'
    done = b'event: progress\ndata: {"state": "succeeded", "stage": "export", "overall_progress": 1.0}\n\n'

    def answer(request: httpx.Request) -> httpx.Response:
        stream = {"content-type": "text/event-stream"}
        if not request.url.path.endswith("/events"):
            return httpx.Response(200, json={"id": "j1", "state": "succeeded"})
        if "last-event-id" not in request.headers:  # the API stops, ending the stream
            return httpx.Response(200, headers=stream, content=b'id: 8\nevent: checkpoint\ndata: {}\n\n' + running)
        if clock[0] < 10:  # and restarts
            raise httpx.ConnectError("connection refused")
        return httpx.Response(200, headers=stream, content=b'id: 9\nevent: succeeded\ndata: {}\n\n' + done)

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1"]) == 0  # capsys: stderr is no terminal
    assert capsys.readouterr().err.splitlines() == [
        "[###############               ]  50.0% running edit",
        "voxe wait: event stream of job j1 lost (the server ended the stream before the job ended); reconnecting "
        "for up to 300 s (the job goes on in the service)",
        "voxe wait: event stream of job j1 back after 12 s",
        "[##############################] 100.0% succeeded export",
    ]
    clock[0] = 0.0
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: over the bar's row, the bar drawn below
    monkeypatch.setattr(shutil, "get_terminal_size", lambda *args: os.terminal_size((100, 24)))
    assert main(["wait", "j1"]) == 0
    rows = capsys.readouterr().err.split("\r")
    assert rows[1].startswith("[###############               ]  50.0% running edit")
    assert rows[2].startswith("voxe wait: event stream of job j1 lost (") and rows[2].endswith("service)\n")
    assert rows[3] == "voxe wait: event stream of job j1 back after 12 s".ljust(99) + "\n"
    assert rows[4].startswith("[##############################] 100.0% succeeded export")


def test_wait_says_a_stages_warning(monkeypatch, capsys):
    """A refinement whose cut kept none of the voxels says so as a warning event and as the job's message only until
    the export starts: ``voxe wait`` (and ``submit --wait``) had shown the progress alone, never the warning."""
    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    said = "the graph cut kept none of the 216 occupied voxels: the refined grid is the initial one"
    stream = (b'id: 3\nevent: warning\ndata: {"kind": "warning", "stage": "refine", "detail": "' + said.encode()
              + b'"}\n\nid: 4\nevent: succeeded\ndata: {}\n\nevent: progress\ndata: {"state": "succeeded", '
              b'"stage": "export", "overall_progress": 1.0}\n\n')

    def answer(request: httpx.Request) -> httpx.Response:
        if not request.url.path.endswith("/events"):
            return httpx.Response(200, json={"id": "j1", "state": "succeeded"})
        return httpx.Response(200, headers={"content-type": "text/event-stream"}, content=stream)

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1", "--quiet"]) == 0
    assert capsys.readouterr().err.splitlines() == [f"voxe wait: refine: {said}"]


@pytest.mark.parametrize("signum,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_while_waiting_stops_following_and_says_the_job_goes_on(monkeypatch, capsys, sigterm_fails_the_test,
                                                                      signum, code):
    """Ctrl-C during ``voxe wait`` had said "voxe: interrupted", as if the job had stopped with the command; SIGTERM
    (docker stop) had killed it saying nothing. Both stop following and say so, SIGTERM exiting 143."""
    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    def answer(request: httpx.Request) -> httpx.Response:
        os.kill(os.getpid(), signum)  # its handler raises here, in the main thread
        time.sleep(10)

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1"]) == code
    assert capsys.readouterr().err == ("\nvoxe wait: stopped following; the job j1 goes on in the service (`voxe "
                                       "cancel j1` stops it)\n")


def test_status_cancel_and_cancel_sweep_print_the_records_text_as_it_is(monkeypatch, capsys):
    """Regression: the record was printed with JSON's ASCII escapes, a prompt "a café" as "a caf\\u00e9". A stdout
    that cannot encode it (LANG=C) gets those escapes, the same JSON, rather than an error after the service's answer."""
    import io

    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    record = {"id": "j1", "state": "canceled", "prompt": "a café in Zürich ☕", "scene_name": "mic ✓",
              "entries": [], "counts": {"canceled": 1}, "table": "| a café |\n"}  # (a sweep's members too)
    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(
        lambda request: httpx.Response(200, json=record))))
    for argv in (["status", "j1"], ["cancel", "j1"], ["cancel-sweep", "s1"]):
        assert main(argv) == 0
        out = capsys.readouterr().out
        assert '"prompt": "a café in Zürich ☕"' in out and "\\u" not in out and json.loads(out) == record
    ascii_stdout = io.TextIOWrapper(io.BytesIO(), encoding="ascii", errors="strict")
    monkeypatch.setattr(sys, "stdout", ascii_stdout)
    assert main(["status", "j1"]) == 0
    ascii_stdout.flush()
    out = ascii_stdout.buffer.getvalue().decode("ascii")
    assert '"prompt": "a caf\\u00e9 in Z\\u00fcrich \\u2615"' in out and json.loads(out) == record
    assert capsys.readouterr().err == ""


def test_a_service_that_failed_or_was_not_reached_exits_3_and_a_refusal_2(monkeypatch, capsys):
    """Both had exited 2, which says bad input: a script could not tell an outage to try again later from a request
    the service refused (a job not found, a bad id)."""
    import httpx

    import voxe_client.client as client_module
    import voxe_core.cli.service as service
    from voxe_client import Client

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    answers = {"/v1/jobs/broken": (500, {}), "/v1/jobs/busy": (503, {"retry-after": "1"}),
               "/v1/jobs/gone": (404, {})}

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/down":
            raise httpx.ConnectError("connection refused")
        status, headers = answers[request.url.path.removesuffix("/cancel")]
        return httpx.Response(status, headers=headers, json={"detail": "no"})

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    for job_id, status in (("broken", 3), ("busy", 3), ("down", 3), ("gone", 2), ("..", 2)):
        assert main(["status", job_id]) == status, job_id
        assert capsys.readouterr().err.startswith("voxe status: error: "), job_id
    assert main(["cancel", "broken"]) == 3 and main(["download", "down", "--out", "."]) == 3
    assert main(["download", "gone", "--out", "."]) == 2


def test_a_download_refuses_an_unlisted_name_before_any_and_a_failed_one_leaves_no_folder_it_made(
        monkeypatch, tmp_path, capsys):
    """--name a --name nope had written a, then failed on nope; a failed download left the --out folder it made,
    empty; --out naming a file failed on mkdir's "[Errno 17] File exists"."""
    import hashlib

    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    body = b"frame"
    listing = [{"name": name, "size": len(body), "sha256": hashlib.sha256(body).hexdigest()}
               for name in ("a.png", "gone.png")]

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/j1":
            return httpx.Response(200, json={"id": "j1", "state": "succeeded"})
        if request.url.path == "/v1/jobs/j1/artifacts":
            return httpx.Response(200, json=listing)
        if request.url.path == "/v1/jobs/j1/artifacts/a.png":
            return httpx.Response(200, content=body)
        return httpx.Response(404, json={"detail": "artifact 'gone.png' is missing from storage"})

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["download", "j1", "--name", "a.png", "--name", "nope", "--out", str(tmp_path / "new")]) == 2
    assert "job j1 has no artifact 'nope'; it has a.png, gone.png; nothing downloaded" in capsys.readouterr().err
    assert main(["download", "j1", "--name", "gone.png", "--out", str(tmp_path / "made" / "out")]) == 2
    assert "HTTP 404: artifact 'gone.png' is missing from storage" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "afile").write_text("x")
    assert main(["download", "j1", "--out", str(tmp_path / "afile")]) == 2
    assert f"cannot write into {tmp_path / 'afile'}: it is a file, not a folder" in capsys.readouterr().err
    assert main(["download", "j1", "--out", str(tmp_path / "all"), "--quiet"]) == 2  # what downloaded whole stays
    assert [p.name for p in (tmp_path / "all").iterdir()] == ["a.png"]
    assert (tmp_path / "all" / "a.png").read_bytes() == body


def test_a_download_naming_an_artifact_twice_downloads_it_once(monkeypatch, tmp_path, capsys):
    """``voxe download j1 --name a.png --name a.png`` had downloaded (and checked, and said) a.png twice, and a name
    not listed given twice was named twice in the refusal."""
    import hashlib

    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    asked = []

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request.url.path)
        if request.url.path == "/v1/jobs/j1":
            return httpx.Response(200, json={"id": "j1", "state": "succeeded"})
        if request.url.path == "/v1/jobs/j1/artifacts":
            return httpx.Response(200, json=[{"name": name, "size": 5, "sha256": hashlib.sha256(b"frame").hexdigest()}
                                             for name in ("a.png", "b.png")])
        return httpx.Response(200, content=b"frame")

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["download", "j1", "--name", "a.png", "--name", "a.png", "--out", str(tmp_path)]) == 0
    assert [path for path in asked if "/artifacts/" in path] == ["/v1/jobs/j1/artifacts/a.png"]
    assert capsys.readouterr().err == f"{tmp_path / 'a.png'} (sha256 checked)\n"
    assert main(["download", "j1", "--name", "nope", "--name", "nope", "--out", str(tmp_path)]) == 2
    assert "job j1 has no artifact 'nope'; it has a.png, b.png; nothing downloaded" in capsys.readouterr().err


def test_a_download_of_n_artifacts_reads_the_listing_once(monkeypatch, tmp_path):
    """``voxe download j1`` of three artifacts had read the job's listing four times (Client.download read it again for
    each); it reads it once and hands each download its entry. A download whose answer names another version (one
    replaced since the listing) still reads the listing again for it."""
    import hashlib

    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    asked, served = [], {name: b"frame" for name in ("a.png", "b.png", "c.png")}

    def entry(name: str) -> dict:
        return {"name": name, "size": len(served[name]), "sha256": hashlib.sha256(served[name]).hexdigest()}

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request.url.path)
        if request.url.path == "/v1/jobs/j1":
            return httpx.Response(200, json={"id": "j1", "state": "succeeded"})
        if request.url.path == "/v1/jobs/j1/artifacts":
            return httpx.Response(200, json=[entry(name) for name in served])
        data = served[request.url.path.rpartition("/")[2]]
        return httpx.Response(200, content=data, headers={"etag": f'"{hashlib.sha256(data).hexdigest()}"'})

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["download", "j1", "--out", str(tmp_path / "all"), "--quiet"]) == 0
    assert asked == ["/v1/jobs/j1", "/v1/jobs/j1/artifacts", "/v1/jobs/j1/artifacts/a.png",
                     "/v1/jobs/j1/artifacts/b.png", "/v1/jobs/j1/artifacts/c.png"]
    assert all((tmp_path / "all" / name).read_bytes() == b"frame" for name in served)
    asked.clear()
    with Client(transport=httpx.MockTransport(answer)) as client:
        (b_listed,) = [a for a in client.artifacts("j1") if a["name"] == "b.png"]
        served["b.png"] = b"frame, republished"  # replaced after its listing was read
        client.download("j1", "b.png", tmp_path / "one" / "b.png", listed=b_listed)
        assert client.download("j1", "c.png", tmp_path / "one" / "c.png").read_bytes() == b"frame"  # as before
        with pytest.raises(ValueError, match="download of 'c.png': listed is the entry of 'b.png'"):
            client.download("j1", "c.png", tmp_path / "one" / "c.png", listed=b_listed)
    assert (tmp_path / "one" / "b.png").read_bytes() == b"frame, republished"
    assert asked == ["/v1/jobs/j1/artifacts", "/v1/jobs/j1/artifacts/b.png", "/v1/jobs/j1/artifacts",
                     "/v1/jobs/j1/artifacts/b.png", "/v1/jobs/j1/artifacts", "/v1/jobs/j1/artifacts/c.png"]


@pytest.mark.parametrize("state, artifacts, said", [
    ("running", ["a.png"], "job j1 is running: these are the artifacts it has so far; `voxe wait j1`, then download "
                           "again for all of them"),
    ("queued", [], "job j1 is queued: it has no artifacts yet; `voxe wait j1`, then download again for all of them"),
    ("failed", [], "job j1 failed with no artifacts: nothing downloaded"),
    ("succeeded", ["a.png"], None),
])
def test_a_download_of_an_unfinished_job_says_it_has_only_what_it_has_so_far(state, artifacts, said, monkeypatch,
                                                                           tmp_path, capsys):
    """A download right after ``voxe submit`` had exited 0 with the job's first files (or none), saying nothing."""
    import hashlib

    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    listing = [{"name": name, "size": 5, "sha256": hashlib.sha256(b"frame").hexdigest()} for name in artifacts]

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/j1":
            return httpx.Response(200, json={"id": "j1", "state": state})
        if request.url.path == "/v1/jobs/j1/artifacts":
            return httpx.Response(200, json=listing)
        return httpx.Response(200, content=b"frame")

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["download", "j1", "--out", str(tmp_path), "--quiet"]) == 0
    assert capsys.readouterr().err == (f"voxe download: note: {said}\n" if said else "")
    assert sorted(p.name for p in tmp_path.iterdir()) == artifacts


def test_an_output_that_cannot_be_written_is_refused_before_the_inputs_are_read(tmp_path, capsys):
    """render, refine, evaluate, mesh-to-grid, export-mesh and turntable had run their whole stage, then failed on
    --out (a file where a folder goes, a folder where a file goes): each input here is missing, so a check made after
    reading them would name the input, not the output."""
    a_file, a_folder, a_grid_folder = tmp_path / "afile", tmp_path / "afolder.ply", tmp_path / "afolder.safetensors"
    a_video_folder = tmp_path / "afolder.gif"
    a_file.write_text("x")
    for folder in (a_folder, a_grid_folder, a_video_folder):
        folder.mkdir()
    missing = str(tmp_path / "missing.safetensors")
    for command, out, said in (
        (["render", missing, "--ring", "2"], a_file, f"cannot write into {a_file}: it is a file, not a folder"),
        (["refine", missing, "--initial", missing, "--prompt", "a dog", "--edit-words", "dog"], a_file,
         f"cannot write into {a_file}: it is a file, not a folder"),
        (["evaluate", missing, "--object", "mic", "--edit", missing, "a mic"], a_file,
         f"cannot write into {a_file}: it is a file, not a folder"),
        (["mesh-to-grid", str(tmp_path / "missing.obj")], a_grid_folder, f"cannot write {a_grid_folder}: it is a folder"),
        (["export-mesh", missing], a_folder, f"cannot write {a_folder}: it is a folder"),
        (["turntable", missing], a_video_folder, f"cannot write {a_video_folder}: it is a folder"),
    ):
        assert main([*command, "--out", str(out), "--device", "cpu"]) == 2, command
        err = capsys.readouterr().err
        assert said in err and "missing" not in err.replace(said, ""), (command, err)


def test_an_output_under_a_file_or_in_a_folder_not_writable_is_refused_naming_why(sphere_file, tmp_path, capsys,
                                                                                   monkeypatch):
    """``--out notes.txt/grid.safetensors`` had said "[Errno 17] File exists: 'notes.txt'", a folder deeper under it
    "[Errno 20] Not a directory", and build-tiny-model onto a file the first; a folder the command may not make
    "[Errno 13] Permission denied: 'ro/views'" (as root here: mkdir refused by hand)."""
    notes = tmp_path / "notes.txt"
    notes.write_text("x")
    for command, said in (
        (["convert-grid", str(sphere_file), "--out", str(notes / "g.safetensors")],
         f"cannot make the folder {notes}: {notes} is a file, not a folder"),
        (["render", str(sphere_file), "--ring", "2", "--size", "8", "--out", str(notes / "views" / "ring")],
         f"cannot make the folder {notes / 'views' / 'ring'}: {notes} is a file, not a folder"),
        (["build-tiny-model", str(notes)], f"cannot write into {notes}: it is a file, not a folder"),
    ):
        assert main([*command, "--quiet"]) == 2
        assert capsys.readouterr().err == f"voxe {command[0]}: error: {said}\n"
    assert notes.read_text() == "x" and sorted(tmp_path.iterdir()) == sorted([notes, sphere_file])

    def refused(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(Path, "mkdir", refused)
    assert main(["render", str(sphere_file), "--ring", "2", "--size", "8", "--out", str(tmp_path / "views")]) == 2
    assert capsys.readouterr().err == \
        f"voxe render: error: cannot make the folder {tmp_path / 'views'}: permission denied\n"


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT])
def test_an_output_folder_a_full_disk_cannot_make_exits_1_as_the_machines_failure(sphere_file, tmp_path, monkeypatch,
                                                                                capsys, code):
    """A full disk (or inode table, or quota) refusing the --out folder's mkdir had exited 2, "bad input": the
    folder's error said the reason in words but dropped its errno, which the exit status is read from (README: a full
    disk or quota exits 1). The words stay; the errno goes with them."""
    def full(path, *args, **kwargs):
        raise OSError(code, os.strerror(code), str(path))

    monkeypatch.setattr(Path, "mkdir", full)
    for command in (["render", str(sphere_file), "--ring", "2", "--size", "8"],
                    ["convert-grid", str(sphere_file)], ["download", "j1", "--api", "http://127.0.0.1:9"]):
        out = tmp_path / "new" / ("g.safetensors" if command[0] == "convert-grid" else "views")
        assert main([*command, "--out", str(out), "--quiet"]) == 1, command
        made = out.parent if command[0] == "convert-grid" else out
        assert capsys.readouterr().err == (f"voxe {command[0]}: error: cannot make the folder {made}: "
                                           f"{os.strerror(code).lower()}\n")


def test_progress_off_a_terminal_is_a_line_now_and_then_not_ten_redraws_a_second(capsys, monkeypatch):
    """A 13 s reconstruct into a log had written 125 carriage-returned redraws (3.8 MB an hour); voxe wait's bar
    redrew unchanged snapshots too."""
    from voxe_core.cli.common import progress_callbacks
    from voxe_core.cli.service import _progress_bar
    from voxe_core.progress import Progress

    with progress_callbacks("fit", total=400) as callbacks:  # capsys: stderr is no terminal
        for i in range(1, 401):
            callbacks.progress(Progress("fit", i, 400))
            time.sleep(0.001)
    assert capsys.readouterr().err.count("\r") <= 3  # opened, closed: no redraw in between

    draw = _progress_bar(quiet=False)
    for done in (0.1, 0.1, 0.2, 0.3):
        draw({"state": "running", "stage": "edit", "overall_progress": done})
    draw({"state": "succeeded", "stage": "export", "overall_progress": 1.0})  # the end, however soon
    assert capsys.readouterr().err.splitlines() == ["[###                           ]  10.0% running edit",
                                                    "[##############################] 100.0% succeeded export"]
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: each change redrawn in place
    draw = _progress_bar(quiet=False)
    for done in (0.1, 0.1, 0.2):
        draw({"state": "running", "stage": "edit", "overall_progress": done})
    assert capsys.readouterr().err.count("\r") == 2


def test_the_bar_draws_what_it_can_of_a_snapshot_the_service_sent_wrong(capsys):
    """A snapshot without its state, or its progress or time left not a number ("50%", a bool, NaN, an integer too
    large for a float), had been a KeyError, TypeError, ValueError or OverflowError traceback ending ``voxe wait`` (a
    progress of 1e9, a bar of a billion #'s; True one of 100%; a time left of 1e400, "~inf s left")."""
    from voxe_core.cli.service import _progress_bar

    draw = _progress_bar(quiet=False)
    for snapshot in ({"stage": "edit", "overall_progress": 0.5}, {"state": "running", "overall_progress": "50%"},
                     {"state": "queued", "overall_progress": True},
                     {"state": "failed", "overall_progress": float("nan")},
                     {"state": "running", "overall_progress": 1e9, "overall_eta_seconds": "soon"},
                     json.loads('{"state": "queued", "overall_progress": 1%s, "overall_eta_seconds": 1%s}'
                                % ("0" * 400, "0" * 400)),
                     json.loads('{"state": "running", "overall_progress": 0.5, "overall_eta_seconds": 1e400}')):
        draw(snapshot)
    assert capsys.readouterr().err.splitlines() == ["[###############               ]  50.0% edit",
                                                    "[                              ]   ?  % running",
                                                    "[                              ]   ?  % queued",
                                                    "[                              ]   ?  % failed",
                                                    "[                              ]   ?  % running",
                                                    "[                              ]   ?  % queued",
                                                    "[###############               ]  50.0% running"]


@pytest.mark.parametrize("terminal", [False, True])
def test_a_resumed_stages_bar_rates_only_the_steps_it_saw(terminal, capsys, monkeypatch):
    """A fit resumed at 300 of 400 had its first report counted as 301 steps done at once: 67 it/s shown for a real
    30 (and the time left with it) in a log, and on a terminal too until the average forgot the jump."""
    import re

    from voxe_core.cli.common import progress_callbacks
    from voxe_core.progress import Progress

    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    with progress_callbacks("fit", total=400) as callbacks:
        for i in range(301, 306):  # 4 steps in 0.2 s after the first report: 20 it/s
            callbacks.progress(Progress("fit", i, 400))
            time.sleep(0.05)
        quiet_counts = progress_callbacks("fit", quiet=True)  # a disabled bar takes reports too
        with quiet_counts as quiet:
            quiet.progress(Progress("fit", 301, 400))
    last = capsys.readouterr().err.split("\r")[-1]
    assert "305/400" in last
    rate = float(re.search(r"([0-9.]+)it/s", last).group(1))
    assert 5 < rate < 30, last


def test_the_bar_on_a_terminal_stays_on_one_row_and_leaves_nothing_of_a_longer_line(monkeypatch, capsys):
    """Redrawn in place (a carriage return), a shorter line had left the end of the one before on screen (a phase
    long done), and one wider than the terminal wrapped, so the next redraw began on the wrapped row."""
    import os
    import shutil

    from voxe_core.cli.service import _progress_bar

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    monkeypatch.setattr(shutil, "get_terminal_size", lambda *args: os.terminal_size((80, 24)))
    draw = _progress_bar(quiet=False)
    draw({"state": "running", "stage": "refine", "overall_progress": 0.5, "message": "refine: attention_grids"})
    draw({"state": "succeeded", "stage": "export", "overall_progress": 1.0})
    rows = capsys.readouterr().err.split("\r")[1:]
    assert [len(row) for row in rows] == [79, 79]  # cut to the width less one (no wrap), the second padded over
    assert rows[0].startswith("[###############               ]  50.0% running refine - refine: att")
    assert rows[1].rstrip() == "[##############################] 100.0% succeeded export"
    draw({"state": "running", "stage": "refine", "overall_progress": 0.5, "message": "refine: attention_grids"})
    monkeypatch.setattr(shutil, "get_terminal_size", lambda *args: os.terminal_size((60, 24)))  # narrowed
    draw({"state": "running", "stage": "refine", "overall_progress": 0.6, "message": "refine: graph_cut"})
    assert [len(row) for row in capsys.readouterr().err.split("\r")[1:]] == [79, 59]


def test_wait_in_a_log_says_each_state_stage_and_phase_at_once(monkeypatch, capsys):
    """``voxe wait`` into a log (CI): a job through its stages in a few seconds had shown only its first and last
    snapshot (a line at most every 30 s); each change of state, stage or phase is a line of its own at once, and
    progress within one is still throttled."""
    import httpx

    import voxe_core.cli.service as service
    from voxe_client import Client

    snapshots = [
        {"state": "queued", "stage": None, "overall_progress": 0.0},
        {"state": "running", "stage": "reconstruct", "overall_progress": 0.1},
        {"state": "running", "stage": "reconstruct", "overall_progress": 0.2},  # within the stage: throttled
        {"state": "running", "stage": "edit", "overall_progress": 0.3},
        {"state": "running", "stage": "refine", "overall_progress": 0.6, "message": "refine: attention_maps"},
        {"state": "running", "stage": "refine", "overall_progress": 0.7, "message": "refine: attention_maps"},
        {"state": "running", "stage": "refine", "overall_progress": 0.8, "message": "refine: graph_cut"},
        {"state": "succeeded", "stage": "export", "overall_progress": 1.0},
    ]
    stream = "".join(f"event: progress\ndata: {json.dumps(s)}\n\n" for s in snapshots)

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/j1/events":
            return httpx.Response(200, headers={"content-type": "text/event-stream"}, text=stream)
        return httpx.Response(200, json={"id": "j1", **snapshots[-1]})

    monkeypatch.setattr(service, "_client", lambda args: Client(args.api, transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1", "--api", "http://svc.test"]) == 0  # capsys: stderr is no terminal
    out = capsys.readouterr()
    assert json.loads(out.out)["state"] == "succeeded"
    assert out.err.endswith("export\n")  # no blank line: that ends a terminal's bar, redrawn in place
    assert out.err.splitlines() == [
        "[                              ]   0.0% queued",
        "[###                           ]  10.0% running reconstruct",
        "[#########                     ]  30.0% running edit",
        "[##################            ]  60.0% running refine - refine: attention_maps",
        "[########################      ]  80.0% running refine - refine: graph_cut",
        "[##############################] 100.0% succeeded export",
    ]


def test_the_readmes_voxe_command_lines_name_commands_and_options_they_take():
    """Every ``voxe <command> ... --option`` the README writes (its CLI block, the fresh-machine submit, options named
    in its prose) is a command of ``voxe`` and an option of that command, as a user would copy it."""
    from voxe_core.cli import build_parser

    commands = next(action.choices for action in build_parser()._actions if action.dest == "command")
    readme = re.sub(r"\\\n\s*", " ", (REPO / "README.md").read_text())  # a line continued by \ joined to the next
    written = re.findall(r"(?:^\s*|[`;]\s*)(?:\.venv/bin/)?voxe ([a-z][a-z-]*)([^`\n#;]*)", readme, re.M)
    assert len(written) > 20
    for command, rest in written:
        assert command in commands, f"README: `voxe {command}` is no command"
        options = {option for action in commands[command]._actions for option in action.option_strings}
        unknown = [option for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", rest) if option not in options]
        assert not unknown, f"README: `voxe {command}` takes no {unknown}"


def test_the_readmes_voxe_commands_parse_as_written(capsys):
    """The README's CLI block and its fresh-machine submit, each command as a user copies it (placeholders filled in,
    ``[optional]`` brackets dropped), parse: required options, argument counts and choices included."""
    from voxe_core.cli import build_parser

    readme = re.sub(r"\\\n\s*", " ", (REPO / "README.md").read_text())
    block = readme.split("\n## CLI\n", 1)[1].split("\n\n", 1)[0]
    lines = [part.split("  #", 1)[0].strip() for line in block.splitlines() for part in line.split(";")]
    lines += [line.replace("\n", " ") for line in re.findall(r"\.venv/bin/(voxe submit .*?\}\}')", readme, re.S)]
    commands = [line for line in lines if line.startswith("voxe ")]
    assert len(commands) > 15
    for command in commands:
        filled = command.replace("<job id>", "J1").replace("<scene id>", "S1").replace("<sweep id>", "W1")
        filled = filled.replace("[", "").replace("]", "")
        try:
            build_parser().parse_args(shlex.split(filled)[1:])
        except SystemExit:
            pytest.fail(f"README: `{command}` does not parse: {capsys.readouterr().err}")

def test_an_elevation_past_a_pole_is_refused_naming_the_option_before_the_grid_is_read(tmp_path, capsys):
    """``voxe render --ring 4 --elevation 120`` had been refused as "a turntable's elevation must lie ...", a
    turntable it makes none of, once its grid was read; render and turntable now name --elevation, a grid that is
    not there unread."""
    grid = str(tmp_path / "missing.safetensors")
    for command in (["render", grid, "--ring", "4", "--out", str(tmp_path / "r")],
                    ["turntable", grid, "--out", str(tmp_path / "t.gif")]):
        assert main([*command, "--elevation", "120"]) == 2
        err = capsys.readouterr().err
        assert "--elevation must lie between -90 and 90 degrees, got 120" in err and "turntable's" not in err
        assert not (tmp_path / "r").exists() and not (tmp_path / "t.gif").exists()


def test_options_a_command_would_ignore_are_refused(sphere_file, tmp_path, capsys):
    """render --data had taken --size / --elevation / --centre-of and rendered the dataset's cameras anyway;
    convert-grid --dense had taken --margin and written every vertex."""
    grid = str(tmp_path / "g.safetensors")
    assert main(["render", grid, "--data", str(tmp_path), "--size", "64", "--elevation", "10",
                 "--out", str(tmp_path / "r")]) == 2
    assert "--size, --elevation set the --ring views; --data renders the dataset's own cameras" in \
        capsys.readouterr().err
    assert main(["convert-grid", grid, "--dense", "--margin", "3", "--out", str(tmp_path / "d.safetensors")]) == 2
    assert "--margin sets the sparse layout's kept cells; --dense writes every vertex" in capsys.readouterr().err
    # a ring reads no dataset: --split / --downsample / --resample / --max-images had been taken and ignored
    assert main(["render", grid, "--ring", "4", "--split", "train", "--downsample", "2", "--max-images", "3",
                 "--out", str(tmp_path / "r")]) == 2
    assert "--split, --downsample, --max-images set how --data's images are read; --ring reads no dataset" in \
        capsys.readouterr().err
    assert main(["evaluate", grid, "--edit", grid, "a hat", "--object", "dog", "--resample", "box",
                 "--out", str(tmp_path / "e")]) == 2
    assert "--resample set how --data's images are read (for FID_input); without --data none are" in \
        capsys.readouterr().err
    # --data is read for FID_input alone: without --inception its images had been loaded and compared with nothing
    assert main(["evaluate", grid, "--edit", grid, "a hat", "--object", "dog", "--data", str(tmp_path),
                 "--out", str(tmp_path / "e")]) == 2
    assert "--data gives the input images FID_input compares with; without --inception no FID is computed" in \
        capsys.readouterr().err
    # the voxelize route renders no views and fits nothing: these had been taken and ignored
    assert main(["mesh-to-grid", str(tmp_path / "m.obj"), "--views", "7", "--size", "999", "--iterations", "5000",
                 "--rays", "3", "--out", str(tmp_path / "m" / "g.safetensors")]) == 2
    assert ("--views, --size, --iterations, --rays set the render route's views and fit; --route voxelize writes the "
            "mesh into the grid") in capsys.readouterr().err
    assert main(["reconstruct", str(tmp_path), "--checkpoint-every", "50",
                 "--out", str(tmp_path / "g" / "g.safetensors")]) == 2
    assert "--checkpoint-every sets how often --checkpoint is written; without --checkpoint none is" in \
        capsys.readouterr().err
    # the grid written at the end had replaced the checkpoint, which a --resume then refused as a grid
    assert main(["reconstruct", str(tmp_path), "--checkpoint", str(tmp_path / "g" / "g.safetensors"),
                 "--out", str(tmp_path / "g" / ".." / "g" / "g.safetensors")]) == 2
    assert "--checkpoint and --out both name" in capsys.readouterr().err
    # a --resume that is no checkpoint had been said only once the dataset was read (here: no dataset at all)
    for resume, message in ((tmp_path / "missing.safetensors", "no such file"),
                            (sphere_file, "holds a 'voxel_grid', expected a 'reconstruction_checkpoint'")):
        assert main(["reconstruct", str(tmp_path), "--resume", str(resume),
                     "--out", str(tmp_path / "g" / "g.safetensors")]) == 2
        assert f"{resume}: {message}" in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in ("r", "e", "m", "g"))


def test_bad_option_values_exit_2(tmp_path, capsys):
    args = ["reconstruct", str(tmp_path), "--out", str(tmp_path / "g.safetensors")]
    # a named preset fixes the stage count before any data is read (auto's depends on the backbone)
    assert main([*args, "--preset", "fast", "--iterations", "1,2"]) == 2  # the fast preset has 3 stages
    assert "one per stage (3 stages)" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # argparse's own usage errors are exit 2 as well
        main([*args, "--preset", "slow"])
    assert exc.value.code == 2
    for poll in ("nan", "-1", "inf"):  # refused before the sweep is created on the service (then run twice)
        with pytest.raises(SystemExit) as exc:
            main(["sweep", "--scene", "s1=mic", "--wait", "--poll", poll, "--api", "http://127.0.0.1:9"])
        assert exc.value.code == 2 and "must be a positive number of seconds" in capsys.readouterr().err
    for command in (args, ["edit", "g", "--prompt", "p", "--out", "o"], ["mesh-to-grid", "m.obj", "--out", "o.safetensors"],
                    ["refine", "e", "--initial", "g", "--prompt", "p", "--edit-words", "p", "--out", "o"], ["build-tiny-model", "o"]):
        for seed in ("-1", str(2**32)):  # the service's range; torch took -1 and failed on 2**64 after the data
            with pytest.raises(SystemExit) as exc:
                main([*command, "--seed", seed])
            assert exc.value.code == 2 and f"--seed: must be between 0 and 4294967295, got {seed}" in \
                capsys.readouterr().err


def test_a_real_valued_option_that_is_no_finite_number_is_refused_naming_the_option(capsys):
    """``voxe edit --reg-weight inf`` had been refused only after the grid was read, naming the setting it fills,
    "regulariser_weight must be >= 0 and finite in float32", and ``voxe refine --tv-weight inf`` "the fit's lr must
    be positive, tv_weight non-negative ...": no option the user typed. Each is refused as the options are read, by
    the option's name."""
    edit = ["edit", "g", "--prompt", "p", "--out", "o"]
    refine = ["refine", "e", "--initial", "g", "--prompt", "p", "--edit-words", "p", "--out", "o"]
    options = [(edit, name) for name in ("--lr", "--reg-weight", "--guidance-scale")] + [
        (refine, name) for name in ("--smoothing-sigma", "--lr", "--tv-weight", "--sigma", "--smoothness")]
    for command, option in options:
        for value in ("inf", "-inf", "nan", "1e400", "ten"):
            with pytest.raises(SystemExit) as exc:
                main([*command, f"{option}={value}"])
            assert exc.value.code == 2
            assert f"error: argument {option}: must be a finite number, got {value!r}" in capsys.readouterr().err


def test_the_other_commands_real_valued_options_refuse_a_value_that_is_no_finite_number_naming_the_option(
        tmp_path, capsys):
    """``voxe export-mesh --level inf`` had been refused after the grid was read as "mesh level must be a positive
    density, got inf" (inf is positive), ``voxe render --ring 8 --elevation nan`` as "a turntable's elevation must lie
    between -90 and 90 degrees", ``--elevation 1e400`` as "got inf": options of plain float, unlike edit's and
    refine's. Each is refused as the options are read, by the option's name, as those are."""
    grid = str(tmp_path / "missing.safetensors")
    for command, option in ((["export-mesh", grid, "--out", "m.ply"], "--level"),
                            (["render", grid, "--ring", "8", "--out", "r"], "--elevation"),
                            (["turntable", grid, "--out", "t.gif"], "--elevation"),
                            (["turntable", grid, "--out", "t.gif"], "--fps"),
                            (["evaluate", grid, "--edit", grid, "a dog", "--object", "dog", "--out", "e"],
                             "--elevation")):
        for value in ("inf", "nan", "1e400"):
            with pytest.raises(SystemExit) as exc:
                main([*command, f"{option}={value}"])
            assert exc.value.code == 2
            assert f"error: argument {option}: must be a finite number, got {value!r}" in capsys.readouterr().err


def test_an_output_suffix_no_mesh_or_video_takes_is_refused_naming_the_option(tmp_path, capsys):
    """``voxe export-mesh --out m.xyz`` had said "unsupported mesh suffix '.xyz'" and ``voxe turntable --out t.xyz``
    "unsupported video suffix ...": neither named --out (``convert-grid`` does), nor export-mesh the path."""
    grid = str(tmp_path / "missing.safetensors")
    for command, what, choices in ((["export-mesh", grid], "mesh", ".ply, .glb, .obj"),
                                   (["turntable", grid], "video", ".mp4, .gif")):
        out = tmp_path / "out.xyz"
        assert main([*command, "--out", str(out)]) == 2
        assert (f"--out: unsupported {what} suffix '.xyz' for {out}; use one of {choices}"
                in capsys.readouterr().err)
        assert not out.exists()


def test_an_output_suffix_no_mesh_or_video_takes_is_refused_before_torch_is_loaded(tmp_path):
    """The --out suffix of export-mesh and turntable was checked after their torch imports: seconds to be told a
    typo. The suffix lists are torch-free (voxe_core.constants); the refusal comes without torch loaded."""
    for command in ("export-mesh", "turntable"):
        result = subprocess.run([sys.executable, "-X", "importtime", "-m", "voxe_core.cli", command,
                                 str(tmp_path / "missing.safetensors"), "--out", str(tmp_path / "out.xyz")],
                                capture_output=True, text=True, timeout=120, cwd=REPO)
        lines = result.stderr.splitlines()
        imported = {line.rsplit("|", 1)[1].strip() for line in lines if line.startswith("import time:")}
        said = [line for line in lines if not line.startswith("import time:")]
        assert result.returncode == 2 and "--out: unsupported" in said[0], result.stderr
        assert "torch" not in imported and "voxe_core.export" not in imported


@pytest.mark.parametrize("text, message", [
    ('{"a": ' * 5000 + "1" + "}" * 5000, "its arrays or objects nest too deeply"),  # had been a RecursionError
    # had been argparse's "invalid _json_object value: '{...}'", quoting the whole text
    ('{"a": ' + "9" * 5000 + "}", f"a number has more than {sys.get_int_max_str_digits()} digits"),
    ('{"a": 1', "not JSON: Expecting ',' delimiter"),
    # had been taken, then refused as sent: "Out of range float values are not JSON compliant", no option named
    ('{"iterations": 1e400}', "not JSON this command reads: the number 1e400 is past a float's range"),
    ('{"a": [-Infinity]}', "not JSON this command reads: -Infinity is no JSON number"),
    ('{"a": NaN}', "not JSON this command reads: NaN is no JSON number"),
])
def test_json_options_json_loads_refuses_are_usage_errors_saying_why(text, message, capsys):
    """``--params`` and ``--evaluation``, refused before any request: one usage line, exit 2, no traceback."""
    for command in (["submit", "p", "--scene", "s1"], ["sweep", "--scene", "s1=mic"]):
        flag = "--params" if command[0] == "submit" else "--evaluation"
        with pytest.raises(SystemExit) as exc:
            main([*command, "--api", "http://127.0.0.1:9", flag, text])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and f"argument {flag}: " in err and message in err and len(err) < 1000


@pytest.mark.parametrize("command,flag", [
    (["edit", "g", "--prompt", "p", "--out", "o"], flag) for flag in ("--iterations", "--checkpoint-every",
                                                                      "--preview-every")] + [
    (["refine", "e", "--initial", "g", "--prompt", "p", "--edit-words", "p", "--out", "o"], flag)
    for flag in ("--iterations", "--edit-seeds", "--preview-views")])
def test_a_negative_count_is_refused_naming_its_option(command, flag, capsys):
    """They had been refused after the grids were read, as "preview_every and checkpoint_every must be >= 0",
    "iterations and seed counts must be non-negative" or "--iterations and --preview-views ...": not which one."""
    with pytest.raises(SystemExit) as exc:
        main([*command, flag, "-1"])
    assert exc.value.code == 2 and f"argument {flag}: must be at least 0, got -1" in capsys.readouterr().err


def test_refine_without_object_seeds_is_refused_naming_the_option(capsys):
    """As a job's ``refine.object_seeds``: the cut has no unary term, so 0 object seeds had run the whole refinement
    to keep every voxel joined to an edit seed (an edit not localised)."""
    with pytest.raises(SystemExit) as exc:
        main(["refine", "e", "--initial", "g", "--prompt", "p", "--edit-words", "p", "--out", "o", "--object-seeds",
              "0"])
    assert exc.value.code == 2 and "argument --object-seeds: must be at least 1, got 0" in capsys.readouterr().err


def _count_options() -> list[tuple[str, str]]:
    """Every (command, option) of ``voxe`` whose value is a count: the option types of voxe_core.cli.common."""
    import argparse

    from voxe_core.cli import build_parser
    from voxe_core.cli.common import int_list, non_negative_int, positive_int, whole_number

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return [(name, action.option_strings[0]) for name, parser in commands.choices.items()
            for action in parser._actions
            if action.option_strings and action.type in (positive_int, non_negative_int, int_list, whole_number)]


@pytest.mark.parametrize("command, flag", _count_options())
def test_a_count_too_large_is_refused_naming_its_option_and_its_limit(command, flag, capsys):
    """A count past 64 bits had been taken, and torch then said only "int too big to convert" (``voxe turntable
    --frames 99999999999999999999``, ``render --ring``, ``export-mesh --resolution``: no option named) or failed
    with a traceback (``reconstruct --resolution`` or ``--rays``: "Overflow when unpacking long long")."""
    for value in ("99999999999999999999", str(2**31)):
        with pytest.raises(SystemExit) as exc:
            main([command, flag, value])
        assert exc.value.code == 2 and f"argument {flag}: must be at most 2147483647, got {value}" in \
            capsys.readouterr().err


@pytest.mark.parametrize("command", ["reconstruct", "mesh-to-grid", "refine"])
def test_rays_per_step_past_the_services_bound_are_refused_before_the_system_kills_the_fit(command, capsys):
    """``voxe reconstruct --rays 2000000000`` (4 images of 50 px) had been taken, where a job's rays_per_step stops at
    2**20: its first step allocated past the machine's memory and the system's out-of-memory killer ended it (exit
    137, nothing said). Every --rays takes the service's bound, refused by the option's name; the bound passes."""
    from api.schemas import RefineParams, ReconstructionParams
    from pydantic import ValidationError

    too_many = 2**20 + 1
    with pytest.raises(SystemExit) as exc:
        main([command, "--rays", str(too_many)])
    assert exc.value.code == 2 and (f"argument --rays: must be at most {2**20} (the service's limit), got {too_many}"
                                    in capsys.readouterr().err)
    assert _option_type(command, "--rays")(str(2**20)) == 2**20
    for params in (ReconstructionParams, RefineParams):  # the service's own bound, the same
        assert params(rays_per_step=2**20).rays_per_step == 2**20
        with pytest.raises(ValidationError):
            params(rays_per_step=too_many)


@pytest.mark.parametrize("command, limit", [(["reconstruct", "no_such_data"], 512), (["mesh-to-grid", "m.obj"], 512),
                                            (["export-mesh", "g.safetensors", "--out", "m.ply"], 1024)])
def test_a_resolution_past_the_services_bound_is_refused_before_it_runs_out_of_memory(command, limit, capsys):
    """``voxe reconstruct --resolution 5000`` (or ``mesh-to-grid``'s, ``export-mesh``'s 100000) had been taken where
    a job's reconstruction.resolution stops at 512 and its export.mesh_resolution at 1024: the grid or lattice asked
    for was past the machine's memory. Each --resolution takes the service's bound (one constant), refused by the
    option's name, a list's every value too; the bound passes."""
    from api.schemas import ExportParams, ReconstructionParams
    from pydantic import ValidationError

    for value in [str(limit + 1)] + ([] if command[0] == "export-mesh" else [f"64,{limit + 1},8"]):  # (one value)
        with pytest.raises(SystemExit) as exc:
            main([*command, "--resolution", value])
        assert exc.value.code == 2 and (f"argument --resolution: must be at most {limit} (the service's limit), got "
                                        f"{limit + 1}" in capsys.readouterr().err)
    assert _option_type(command[0], "--resolution")(str(limit)) in (limit, [limit])
    params, setting = (ExportParams, "mesh_resolution") if command[0] == "export-mesh" else \
        (ReconstructionParams, "resolution")  # the service's own bound, the same
    assert getattr(params(**{setting: limit}), setting) == limit
    with pytest.raises(ValidationError):
        params(**{setting: limit + 1})


@pytest.mark.parametrize("command", [["reconstruct", "no_such_data"], ["mesh-to-grid", "m.obj"],
                                     ["mesh-to-grid", "m.obj", "--route", "render"]])
def test_a_final_resolution_below_the_services_bound_is_refused_naming_the_option(command, capsys):
    """``voxe reconstruct --resolution 2`` (or 3; mesh-to-grid's on either route) had been taken where a job's
    reconstruction.resolution is refused below 4: one bound (constants.MIN_GRID_RESOLUTION) for both, the CLI's
    said by the option's name; a per-stage list's earlier stages may start coarser, as the service's scaled ones do."""
    from api.schemas import ReconstructionParams
    from pydantic import ValidationError

    for value, said in (("3", "must be at least 4"), ("2", "must be at least 4"),
                        ("2,2,3", "its last value (the final stage's) must be at least 4")):
        with pytest.raises(SystemExit) as exc:
            main([*command, "--resolution", value])
        assert exc.value.code == 2
        assert f"argument --resolution: {said} (the service's limit), got {value[-1]}" in capsys.readouterr().err
    assert _option_type(command[0], "--resolution")("4") == [4]
    assert _option_type(command[0], "--resolution")("2,2,4") == [2, 2, 4]
    assert ReconstructionParams(resolution=4).resolution == 4
    with pytest.raises(ValidationError, match="greater than or equal to 4"):
        ReconstructionParams(resolution=3)


def test_a_resolution_below_two_is_refused_naming_the_option_typed(sphere_file, tmp_path, capsys):
    """It had been refused as the setting it fills: "grid resolutions must be at least 2, got [2, 2, 0]" (reconstruct,
    mesh-to-grid --route render), "grid resolution must be >= 2 per axis" (the voxelize route), "mesh resolution must
    be at least 2, got 1" (export-mesh): no option typed is called that."""
    trimesh.creation.icosphere(subdivisions=1, radius=0.5).export(tmp_path / "m.obj")
    grid = tmp_path / "g.safetensors"
    for command, said in ((["reconstruct", str(tmp_path / "no_such_data"), "--out", str(grid), "--resolution", "0,2,4"],
                           "--resolution must be at least 2, got [0, 2, 4]"),
                          (["mesh-to-grid", str(tmp_path / "m.obj"), "--route", "render", "--out", str(grid),
                            "--resolution", "2,0,4"], "--resolution must be at least 2, got [2, 0, 4]"),
                          (["export-mesh", str(sphere_file), "--out", str(tmp_path / "m.ply"), "--resolution", "1"],
                           "--resolution must be at least 2, got 1")):
        assert main(command) == 2
        assert capsys.readouterr().err == f"voxe {command[0]}: error: {said}\n"
    assert not grid.exists() and not (tmp_path / "m.ply").exists()


def _integer_options() -> list[tuple[str, str]]:
    """Every (command, option) of ``voxe`` whose value is an integer: the counts, ``--seed`` and the counts the
    service bounds (``positive_int_at_most``, ``int_list_at_most``)."""
    import argparse

    from voxe_core.cli import build_parser
    from voxe_core.cli.common import seed

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return _count_options() + [
        (name, action.option_strings[0]) for name, parser in commands.choices.items() for action in parser._actions
        if action.option_strings and (action.type is seed or getattr(action.type, "__qualname__", "").startswith(
            ("positive_int_at_most.", "int_list_at_most.")))]


def _option_type(command: str, flag: str):
    import argparse

    from voxe_core.cli import build_parser

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return next(a.type for a in commands.choices[command]._actions if flag in a.option_strings)


@pytest.mark.parametrize("command, flag", _integer_options())
def test_an_integer_option_takes_only_digits_as_the_service_does(command, flag, capsys):
    """Python's int() had taken ``1_0`` as 10, ``+5``, `` 5`` and ``5 `` as 5 and a full-width ``５`` as 5, where the
    service answers a query's ``limit=1_0`` with a 422 (api.paging.DIGITS_ONLY): a typo run as though it were meant.
    Each is refused naming the option (a list's spaces around its commas aside); plain digits are still read."""
    from voxe_core.cli.common import int_list

    a_list = _option_type(command, flag) is int_list or _option_type(command, flag).__qualname__.startswith(
        "int_list_at_most.")
    for value in ("1_0", "+5", "\uff15", "5.0", *(() if a_list else (" 5", "5 "))):
        with pytest.raises(SystemExit) as exc:
            main([command, f"{flag}={value}"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and f"error: argument {flag}: expected " in err and f"{value!r}" in err, err
    with pytest.raises(SystemExit) as exc:  # a plain value passes the option (the command is refused elsewhere)
        main([command, f"{flag}=5", "--no-such-option"])
    assert f"argument {flag}" not in capsys.readouterr().err


def _real_options() -> list[tuple[str, str]]:
    """Every (command, option) of ``voxe`` whose value is a real number."""
    import argparse

    from voxe_core.cli import build_parser
    from voxe_core.cli.common import finite_float, non_negative_seconds, positive_seconds

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return [(name, action.option_strings[0]) for name, parser in commands.choices.items()
            for action in parser._actions
            if action.option_strings and action.type in (finite_float, positive_seconds, non_negative_seconds)]


@pytest.mark.parametrize("command, flag", _real_options())
def test_a_real_valued_option_takes_only_a_decimal_number_in_ascii_digits(command, flag, capsys):
    """Python's float() had taken ``--lr 1_0`` as 10, ``--poll ' 5'`` as 5 and a full-width ``５`` as 5: each is
    refused naming the option, as the integer options refuse them; ``.5``, ``+2`` and ``5e-3`` are still read."""
    assert ("turntable", "--fps") in _real_options() and ("sweep", "--poll") in _real_options()
    for value in ("1_0", " 5", "5 ", "\uff15"):
        with pytest.raises(SystemExit) as exc:
            main([command, f"{flag}={value}"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and f"error: argument {flag}: must be " in err and f"got {value!r}" in err, err
    for value in (".5", "+2", "5e-3"):
        with pytest.raises(SystemExit):
            main([command, f"{flag}={value}", "--no-such-option"])
        assert f"argument {flag}" not in capsys.readouterr().err


def test_an_integer_list_option_takes_digits_with_spaces_around_its_commas():
    import argparse

    from voxe_core.cli.common import int_list

    assert int_list("64, 128,256") == [64, 128, 256]
    for text in ("64,1_28", "+64", "64,\uff15"):
        with pytest.raises(argparse.ArgumentTypeError, match="written in the digits 0-9"):
            int_list(text)


def test_the_count_options_found_are_those_a_huge_value_had_failed(sphere_file, tmp_path, capsys):
    """The options listed above include those that had failed unnamed; a count at the limit is taken."""
    options = _count_options()
    for option in (("turntable", "--frames"), ("turntable", "--size"), ("render", "--ring"), ("render", "--size"),
                   ("reconstruct", "--iterations"),
                   ("evaluate", "--views"), ("mesh-to-grid", "--size"), ("convert-grid", "--margin")):
        assert option in options
    for option in (("reconstruct", "--rays"), ("refine", "--rays"), ("mesh-to-grid", "--rays"),  # (the service's
                   ("export-mesh", "--resolution"), ("reconstruct", "--resolution"), ("mesh-to-grid", "--resolution")):
        assert option in _integer_options()  # bound, tighter: test_rays_per_step_past_..., test_a_resolution_past_...
    assert main(["convert-grid", str(sphere_file), "--out", str(tmp_path / "c.safetensors"),
                 "--margin", "2147483647"]) == 0


REFINE_MISSING_GRIDS = ["refine", "no_such_edit.safetensors", "--initial", "no_such_grid.safetensors", "--prompt",
                        "a dog", "--edit-words", "dog", "--out", "refine"]


@pytest.mark.parametrize("command, flag, limit", [(REFINE_MISSING_GRIDS, "--views", MAX_REFINE_VIEWS),
                                                  (REFINE_MISSING_GRIDS, "--render-size", MAX_RENDER_SIZE),
                                                  (["edit", "no_such_grid.safetensors", "--prompt", "a dog", "--out",
                                                    "edit"], "--render-size", MAX_RENDER_SIZE)])
def test_refine_views_or_render_size_beyond_the_services_limit_are_refused_naming_it(command, flag, limit, capsys):
    """Regression: they had no upper limit (the API's refine and edit parameters stop at 1000 views and 1024 px):
    voxe refine --views 100000 went on to render and attend every view, voxe edit --render-size 50000 to render it."""
    with pytest.raises(SystemExit) as exc:
        main([*command, flag, str(limit + 1)])
    assert exc.value.code == 2
    assert f"argument {flag}: must be at most {limit} (the service's limit), got {limit + 1}" in capsys.readouterr().err
    assert main([*command, flag, str(limit)]) == 2  # the limit itself passes: refused only for the missing grids
    assert "argument" not in capsys.readouterr().err


def test_an_output_that_cannot_be_written_is_refused_before_the_fit_and_a_failed_save_leaves_nothing(
        sphere_file, tmp_path, capsys):
    """reconstruct had fitted first and then failed on its --out (or at its first checkpoint, whose folder it never
    made); a save that failed left its .tmp file, and safetensors' error came out as a traceback."""
    (tmp_path / "taken.safetensors").mkdir()
    args = ["reconstruct", str(tmp_path / "no_such_scene"), "--out"]
    assert main([*args, str(tmp_path / "taken.safetensors")]) == 2  # checked before the data is read
    assert f"cannot write {tmp_path / 'taken.safetensors'}: it is a folder" in capsys.readouterr().err
    assert main([*args, str(tmp_path / "g.safetensors"), "--checkpoint", str(tmp_path / "ck" / "c.safetensors")]) == 2
    assert "no_such_scene" in capsys.readouterr().err  # the data folder is what is refused now
    assert not (tmp_path / "ck").exists()  # made for the checkpoint, and removed with the failure
    assert main(["convert-grid", str(sphere_file), "--out", str(tmp_path / "taken.safetensors")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "taken.safetensors" in err
    assert not [p.name for p in tmp_path.rglob(".*.partial*")] and (tmp_path / "taken.safetensors").is_dir()


def test_a_failed_command_leaves_no_folder_it_made(sphere_file, tmp_path, capsys):
    """--out (and a grid file's folder) had been made before the inputs were read: a bad input left it behind,
    empty. A folder that was there before stays, and so does what a command that succeeds made."""
    missing = str(tmp_path / "missing.safetensors")
    assert main(["render", missing, "--ring", "2", "--out", str(tmp_path / "new" / "views")]) == 2
    assert "missing.safetensors: no such file" in capsys.readouterr().err
    assert main(["mesh-to-grid", str(tmp_path / "bad.obj"), "--out", str(tmp_path / "made" / "g.safetensors")]) == 2
    assert "bad.obj: no such file" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sphere.safetensors"]
    (tmp_path / "kept").mkdir()
    for out in (tmp_path / "kept", tmp_path / "kept" / "views"):
        assert main(["render", missing, "--ring", "2", "--out", str(out)]) == 2
    assert (tmp_path / "kept").is_dir() and not any((tmp_path / "kept").iterdir())
    assert main(["render", str(sphere_file), "--ring", "1", "--size", "8", "--out", str(tmp_path / "ok" / "views"),
                 "--quiet"]) == 0
    assert sorted(p.name for p in (tmp_path / "ok" / "views").iterdir()) == ["000.png", "render.json"]


def test_a_grid_or_checkpoint_named_other_than_safetensors_is_refused(sphere_file, tmp_path, capsys):
    """--out grid.txt had written a grid file under that name; the refusal comes before anything is read."""
    refusal = "grids and checkpoints are safetensors files; use .safetensors"
    for command in (["convert-grid", str(sphere_file), "--out", str(tmp_path / "grid.txt")],
                    ["mesh-to-grid", "m.obj", "--out", str(tmp_path / "grid.txt")],
                    ["reconstruct", str(tmp_path), "--out", str(tmp_path / "grid.txt")],
                    ["reconstruct", str(tmp_path), "--out", str(tmp_path / "g.safetensors"),
                     "--checkpoint", str(tmp_path / "ck.pt")]):
        with pytest.raises(SystemExit) as exc:
            main(command)
        bad = command[-1]
        assert exc.value.code == 2 and f"unsupported suffix {Path(bad).suffix!r} for {bad}: {refusal}" in \
            capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sphere.safetensors"]
    assert main(["convert-grid", str(sphere_file), "--out", str(tmp_path / "GRID.SafeTensors"), "--quiet"]) == 0


def test_an_output_linked_into_a_folder_that_is_not_there_is_refused_before_the_work(tmp_path):
    """An output is written through its symlink: one linking into a missing folder had passed the check made before
    the long stage (its own folder is writable), and failed once the work was done, "No such file or directory"."""
    from voxe_core.cli.common import writable_file

    link, target = tmp_path / "latest.mp4", tmp_path / "gone" / "spot.mp4"
    link.symlink_to(target)
    with pytest.raises(OSError) as error:
        writable_file(link)
    assert str(error.value) == f"cannot write {link}: it links to {target}, whose folder is missing"
    (tmp_path / "gone").mkdir()
    assert writable_file(link) == link


@pytest.mark.parametrize("umask", [0o022, 0o007])
def test_safetensors_outputs_follow_the_umask_as_other_outputs(sphere_file, tmp_path, umask):
    """safetensors renames its own 0600 temporary file into place: grids and the tiny model's weights had been 0600
    where the PNGs, JSON and configs beside them follow the umask."""
    previous = os.umask(umask)
    try:
        assert main(["convert-grid", str(sphere_file), "--out", str(tmp_path / "grid.safetensors"), "--quiet"]) == 0
        assert main(["build-tiny-model", str(tmp_path / "tiny")]) == 0
    finally:
        os.umask(previous)
    weights = [tmp_path / "grid.safetensors", *(tmp_path / "tiny").rglob("*.safetensors")]
    assert len(weights) == 4
    assert {str(path): oct(path.stat().st_mode & 0o777) for path in weights} == \
        {str(path): oct(0o666 & ~umask) for path in weights}
    assert (tmp_path / "tiny" / "model_index.json").stat().st_mode & 0o777 == 0o666 & ~umask


def test_build_tiny_model_refuses_a_folder_holding_another_model_and_rebuilds_its_own(tmp_path, capsys):
    """Built into a folder holding another model, its files had been mixed with those: a sharded UNet's index stayed
    beside the new weights, and loading read the other model's shards."""
    other = tmp_path / "other"
    (other / "unet").mkdir(parents=True)
    index = other / "unet" / "diffusion_pytorch_model.safetensors.index.json"
    index.write_text('{"weight_map": {"conv_in.weight": "diffusion_pytorch_model-00001-of-00002.safetensors"}}')
    assert main(["build-tiny-model", str(other)]) == 2
    assert f"{other} already holds unet, not a tiny model: the tiny model's files would be mixed with those; give " \
           "an empty or new folder" in capsys.readouterr().err
    assert sorted(path.name for path in other.rglob("*")) == ["diffusion_pytorch_model.safetensors.index.json", "unet"]
    tiny = tmp_path / "tiny"
    assert main(["build-tiny-model", str(tiny), "--seed", "1"]) == 0
    first = (tiny / "unet" / "diffusion_pytorch_model.safetensors").read_bytes()
    assert main(["build-tiny-model", str(tiny)]) == 0  # its own, rebuilt in place
    assert (tiny / "unet" / "diffusion_pytorch_model.safetensors").read_bytes() != first


def test_a_tiny_model_rebuild_failing_part_way_leaves_the_earlier_model_whole(tmp_path, monkeypatch):
    """The rebuild had written in place: one failing (here a full disk) or killed as it saved the text encoder left
    the new UNet and VAE beside the earlier text encoder and model_index.json, a mix that loaded as a whole model."""
    from transformers import CLIPTextModel

    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    tiny = tmp_path / "tiny"
    build_tiny_stable_diffusion(tiny, seed=1)
    before = {str(p.relative_to(tiny)): p.read_bytes() for p in tiny.rglob("*") if p.is_file()}

    def disk_full(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(CLIPTextModel, "save_pretrained", disk_full)
    with pytest.raises(OSError, match="No space left"):
        build_tiny_stable_diffusion(tiny, seed=2)
    assert {str(p.relative_to(tiny)): p.read_bytes() for p in tiny.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny"]  # no staging folder left beside it
    monkeypatch.undo()
    assert build_tiny_stable_diffusion(tiny, seed=2) == tiny
    after = (tiny / "unet" / "diffusion_pytorch_model.safetensors").read_bytes()
    assert after != before["unet/diffusion_pytorch_model.safetensors"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny"]


def test_a_tiny_model_build_removes_the_staging_folders_of_builds_killed_mid_way(tmp_path):
    """A build killed mid-way (SIGKILL) leaves its hidden staging folder beside the model, a model's size each time;
    the next build removes those no live build holds."""
    import fcntl

    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    dead, live = tmp_path / ".tiny.0badc0de.partial", tmp_path / ".tiny.1ec0ffee.partial"
    other = tmp_path / ".other.0badc0de.partial"  # another folder's build
    for folder in (dead, live, other):
        (folder / "unet").mkdir(parents=True)
        (folder / "unet" / "config.json").write_text("{}")
    held = os.open(live, os.O_RDONLY)
    try:
        fcntl.flock(held, fcntl.LOCK_EX)
        build_tiny_stable_diffusion(tmp_path / "tiny")
        assert sorted(p.name for p in tmp_path.iterdir()) == [".other.0badc0de.partial", ".tiny.1ec0ffee.partial",
                                                              "tiny"]
    finally:
        os.close(held)


def test_a_tiny_model_is_built_into_a_mount_point_in_place(tmp_path, monkeypatch):
    """A mount point (a container's volume at DIR) cannot be renamed over (EBUSY): built beside and renamed into place,
    its build had failed where writing in place had worked."""

    from voxe_core import tiny_sd

    volume = tmp_path / "volume"
    volume.mkdir()
    rename, replace = os.rename, os.replace

    def busy(fn):
        def renamed(src, dst, *args, **kwargs):
            if volume in (Path(src), Path(dst)):
                raise OSError(errno.EBUSY, "Device or resource busy", str(src))
            return fn(src, dst, *args, **kwargs)
        return renamed

    monkeypatch.setattr(tiny_sd.os, "rename", busy(rename))
    monkeypatch.setattr(tiny_sd.os, "replace", busy(replace))
    monkeypatch.setattr(tiny_sd.os.path, "ismount", lambda path: Path(path) == volume)
    assert tiny_sd.build_tiny_stable_diffusion(volume) == volume
    assert (volume / "model_index.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["volume"]


def test_a_tiny_model_build_failing_in_a_mount_point_leaves_it_as_it_was(tmp_path, monkeypatch):
    """Into a mount point the model was written in place: a rebuild failing as it saved the text encoder (a full disk,
    Ctrl-C) left the new UNet and VAE beside the earlier text encoder, a mix that loaded as a whole model, and a first
    build failing so left a half model the next build refused ("already holds tokenizer, unet, vae, not a tiny
    model"). It is built in a hidden folder inside the mount point, whose parts take the earlier ones' places."""
    from transformers import CLIPTextModel

    from voxe_core import tiny_sd

    volume, fresh = tmp_path / "volume", tmp_path / "fresh"
    monkeypatch.setattr(tiny_sd.os.path, "ismount", lambda path: Path(path) in (volume, fresh))
    tiny_sd.build_tiny_stable_diffusion(volume, seed=1)

    def files(folder: Path) -> dict:
        return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}

    before = files(volume)
    fresh.mkdir()
    dead = fresh / ".build.0badc0de.partial"  # a build killed in it
    (dead / "unet").mkdir(parents=True)

    def disk_full(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as failing:
        failing.setattr(CLIPTextModel, "save_pretrained", disk_full)
        for folder in (volume, fresh):
            with pytest.raises(OSError, match="No space left"):
                tiny_sd.build_tiny_stable_diffusion(folder, seed=2)
    assert files(volume) == before
    assert sorted(p.name for p in volume.iterdir()) == sorted({name.split("/")[0] for name in before})
    assert list(fresh.iterdir()) == []  # (the killed build's folder removed, the failed one's own too)
    assert tiny_sd.build_tiny_stable_diffusion(fresh, seed=2) == fresh
    assert tiny_sd.build_tiny_stable_diffusion(volume, seed=2) == volume
    assert files(volume) == files(fresh) != before
    assert not [p for folder in (volume, fresh) for p in folder.iterdir() if p.name.endswith(".partial")]


def test_build_tiny_model_takes_a_folder_holding_only_a_file_managers_files(tmp_path, capsys):
    """A folder made in Finder (holding only .DS_Store) had been refused as holding another model's files; a folder
    holding another hidden file (a .git) is still refused: building would replace it."""
    finder = tmp_path / "finder"
    finder.mkdir(mode=0o750)
    (finder / ".DS_Store").write_bytes(b"Bud1")
    assert main(["build-tiny-model", str(finder)]) == 0
    assert (finder / "model_index.json").is_file() and not (finder / ".DS_Store").exists()
    assert finder.stat().st_mode & 0o777 == 0o750  # the folder's own permissions kept
    repo = tmp_path / "repo"
    (repo / ".git").mkdir(parents=True)
    assert main(["build-tiny-model", str(repo)]) == 2
    assert f"{repo} already holds .git, not a tiny model" in capsys.readouterr().err
    assert [p.name for p in repo.iterdir()] == [".git"]


def test_bad_data_is_said_as_a_dataset_error_and_a_bad_grid_as_an_error(tmp_path, capsys):
    """The one-line message names which input was bad: found without importing the dataset module where no command
    had (``voxe status`` must not load torch to say its error)."""
    assert main(["reconstruct", str(tmp_path), "--out", str(tmp_path / "grid.safetensors")]) == 2
    assert capsys.readouterr().err.startswith(f"voxe reconstruct: dataset error: {tmp_path}: no dataset found")
    assert main(["convert-grid", str(tmp_path / "none.safetensors"), "--out", str(tmp_path / "g.safetensors")]) == 2
    assert capsys.readouterr().err == f"voxe convert-grid: error: {tmp_path / 'none.safetensors'}: no such file\n"


def test_a_grid_that_cannot_be_read_is_said_so_not_missing(sphere_file, tmp_path, capsys):
    """A grid without read permission had been "not a readable safetensors file (No such file or directory: ...)",
    safetensors' words, of a file that is there. (Root reads it all the same: skipped where this process does.)"""
    sphere_file.chmod(0)
    if os.access(sphere_file, os.R_OK):
        pytest.skip("this process reads files without read permission (root)")
    assert main(["convert-grid", str(sphere_file), "--out", str(tmp_path / "g.safetensors")]) == 2
    assert capsys.readouterr().err == f"voxe convert-grid: error: {sphere_file}: cannot be read: permission denied\n"


def test_cli_as_a_real_process_has_no_traceback(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "voxe_core.cli", "export-mesh", str(tmp_path / "missing.safetensors"),
         "--out", str(tmp_path / "m.ply")],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2
    assert "missing.safetensors: no such file" in result.stderr and "Traceback" not in result.stderr


def test_sigterm_cancels_a_long_command_as_ctrl_c_does_leaving_no_partial_file_and_exits_143(sphere_file, tmp_path):
    """SIGTERM (docker stop, timeout, systemd) had killed the command at once: the turntable's hidden
    .spot.<token>.partial.mp4 stayed in the output folder. It now cancels the stage at its next step, as Ctrl-C does."""
    out = tmp_path / "videos" / "spot.mp4"
    process = subprocess.Popen([sys.executable, "-m", "voxe_core.cli", "turntable", str(sphere_file), "--frames",
                                "100000", "--size", "16", "--device", "cpu", "--quiet", "--out", str(out)],
                               cwd=REPO, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not any(out.parent.glob(".spot.*.partial.mp4")) and process.poll() is None and \
                time.monotonic() < deadline:
            time.sleep(0.05)
        assert any(out.parent.glob(".spot.*.partial.mp4")), "the turntable never started"
        process.send_signal(signal.SIGTERM)
        err = process.communicate(timeout=30)[1]
    finally:
        process.kill()
    assert process.returncode == 143, err
    assert "SIGTERM received" in err and "turntable cancelled, nothing written" in err and "Traceback" not in err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["sphere.safetensors"]  # no partial file, no folder


@pytest.mark.parametrize("log_lines", [1, 5000])  # its output buffered to the end, and written as printed
def test_output_whose_reader_stopped_reading_ends_the_command_quietly(log_lines):
    """``voxe status J | head -c 10`` had printed "voxe status: error: [Errno 32] Broken pipe" and exited 2, as bad
    input does; it now ends quietly with 141, as SIGPIPE ends ``cat``."""
    from service_helpers import answering

    job = json.dumps({"id": "j1", "state": "running", "log": ["a line of the job's log"] * log_lines}).encode()
    with answering(job) as url:
        process = subprocess.Popen([sys.executable, "-m", "voxe_core.cli", "status", "j1", "--api", url],
                                   cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        process.stdout.close()  # the reader gone before the command prints
        err = process.communicate(timeout=120)[1]
    assert (process.returncode, err) == (141, "")


def test_quiet_silences_the_model_libraries_bars_for_the_command_only(tiny_sd_path, make_sphere_grid, tmp_path,
                                                                      capsys):
    """--quiet had silenced voxe's own bars only: loading a model drew transformers' "Loading weights" and (a
    sharded UNet) diffusers' "Loading checkpoint shards" all the same. A quiet command leaves them as they were.
    Here the libraries are imported before the command; a real process imports them during it."""
    import shutil

    from diffusers import UNet2DConditionModel

    model = shutil.copytree(tiny_sd_path, tmp_path / "sharded")
    unet = UNet2DConditionModel.from_pretrained(model / "unet")
    shutil.rmtree(model / "unet")
    unet.save_pretrained(model / "unet", max_shard_size="100KB")
    make_sphere_grid(16).save(tmp_path / "g.safetensors")
    edit = ["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--model", str(model), "--offline",
            "--iterations", "1", "--render-size", "16", "--device", "cpu", "--out", str(tmp_path / "out")]
    bars = ("Loading weights", "Loading checkpoint shards")

    def said(*flags: str) -> str:
        capsys.readouterr()
        assert main([*edit, *flags]) == 0
        return capsys.readouterr().err

    assert all(bar in said() for bar in bars)
    quiet = said("--quiet")
    assert not [bar for bar in bars if bar in quiet] and "it/s" not in quiet
    assert all(bar in said() for bar in bars)  # the next command without --quiet draws them again
    result = subprocess.run([sys.executable, "-m", "voxe_core.cli", *edit, "--quiet"], cwd=REPO, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert not [bar for bar in bars if bar in result.stderr] and "it/s" not in result.stderr


# --------------------------------------------------------------------- render
@needs_mic
@pytest.mark.parametrize("resample", [None, "box"])
def test_render_dataset_views_writes_pngs_and_metrics(sphere_grid, sphere_file, tmp_path, capsys, resample):
    out = tmp_path / "views"
    flag = [] if resample is None else ["--resample", resample]
    assert main(["render", str(sphere_file), "--data", str(MIC), "--split", "test", "--downsample", "16", *flag,
                 "--max-images", "2", "--out", str(out), "--quiet"]) == 0
    # Scored against the filter asked for (bilinear by default); the two ground truths differ by ~0.4 dB here.
    scene = load_scene(MIC, "test", 16, 2, resample=resample or "bilinear")
    expected = render_views(sphere_grid, scene.cameras)
    pngs = sorted(out.glob("*.png"))
    assert [p.name for p in pngs] == ["000_r_0.png", "001_r_10.png"]  # named after the split's frames
    for png, frame in zip(pngs, expected):
        written = np.asarray(Image.open(png)) / 255.0
        assert np.abs(written - frame.numpy()).max() <= 0.5 / 255 + 1e-6  # the right cameras, size and grid
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["psnr"] == pytest.approx(float(psnr(expected, scene.images).mean()), abs=1e-4)
    assert metrics["ssim"] == pytest.approx(float(ssim(expected, scene.images).mean()), abs=1e-4)
    assert f"PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}" in capsys.readouterr().out


def test_render_names_views_of_the_longest_image_names_within_the_file_system_s_limit(sphere_file, tmp_path, capsys):
    """A view is named '000_<image stem>.png': an image named with 255 bytes (the most a name holds) had failed
    "File name too long". The stem is cut to fit with a hash of the image's name (files.head_that_fits), and
    views of two such images alike at their start keep names of their own."""
    from test_data import make_synthetic, pose, write_png

    stems = ["é" * 125 + "a", "é" * 125 + "b", "r_2"]  # 251 bytes, 255 with '.png'
    for stem in stems:
        write_png(tmp_path / "data" / "train" / f"{stem}.png")
    make_synthetic(tmp_path / "data", [{"file_path": f"./train/{stem}", "transform_matrix": pose(translation=(0, 0, 4))}
                                       for stem in stems])
    out = tmp_path / "views"
    assert main(["render", str(sphere_file), "--data", str(tmp_path / "data"), "--split", "train", "--out", str(out),
                 "--device", "cpu", "--quiet"]) == 0, capsys.readouterr().err
    names = json.loads((out / "render.json").read_text())["files"]
    assert sorted(p.name for p in out.iterdir()) == sorted([*names, "render.json"])
    assert len(names) == 4 and names[2:] == ["002_r_2.png", "metrics.json"]
    for i, name in enumerate(names[:2]):
        assert name.startswith(f"{i:03d}_éé") and name.endswith(".png") and len(name.encode()) <= 255
    assert names[0][4:-21] == names[1][4:-21] and names[0][-21:] != names[1][-21:]  # cut alike, hashes differ
    assert [v["file"] for v in json.loads((out / "metrics.json").read_text())["per_view"]] == names[:3]


def test_a_png_gif_ply_or_obj_that_the_disk_cannot_hold_is_named_in_the_error(sphere_file, tmp_path):
    """A full disk under the PNG, GIF, PLY and OBJ writers (a write or a flush, which name no file) had been said as
    "[Errno 28] No space left on device" alone, no file named; an OBJ's as its .mtl's, had it been named. Here the
    kernel cuts each write at a file size limit (RLIMIT_FSIZE: EFBIG, raised as ENOSPC is, naming no file), in a
    process of its own: each error names the file asked for (render's view, not its staging copy), and nothing of it
    is left."""
    script = (
        "import json, resource, signal, sys\n"
        "from voxe_core.cli import main\n"
        "import voxe_core.export, PIL.PngImagePlugin, PIL.GifImagePlugin, trimesh\n"  # (before the limit)
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (2048, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))\n"
        "for argv in json.loads(sys.argv[1]):\n"
        "    print(main(argv), flush=True)\n"
    )
    grid = str(sphere_file)
    commands = [["render", grid, "--ring", "1", "--size", "256", "--out", str(tmp_path / "views"), "-q"],
                ["turntable", grid, "--frames", "16", "--size", "256", "--out", str(tmp_path / "t.gif"), "-q"],
                ["export-mesh", grid, "--out", str(tmp_path / "m.ply")],
                ["export-mesh", grid, "--out", str(tmp_path / "m.obj")]]
    result = subprocess.run([sys.executable, "-c", script, json.dumps(commands)], cwd=REPO, capture_output=True,
                            text=True, timeout=300)
    assert result.stdout.split() == ["1"] * 4, result.stderr  # the machine's limit, not bad input
    err = result.stderr.splitlines()
    assert err == [f"voxe {name}: error: [Errno 27] File too large: '{tmp_path / file}'" for name, file in
                   (("render", "views/000.png"), ("turntable", "t.gif"), ("export-mesh", "m.ply"),
                    ("export-mesh", "m.obj"))]  # (render's: the view asked for, not its .render-staging copy)
    assert sorted(p.name for p in tmp_path.iterdir()) == [sphere_file.name]


def test_a_full_disk_under_a_writer_names_its_file(tmp_path, monkeypatch):
    """ENOSPC as a write raises it, naming no file: the file written is named; the earlier one stays whole."""
    from voxe_core.export import save_png

    target = tmp_path / "view.png"
    save_png(target, np.zeros((4, 4, 3), np.uint8))
    earlier = target.read_bytes()

    def disk_full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(OSError) as error:
        save_png(target, np.ones((4, 4, 3), np.uint8))
    assert (error.value.errno, error.value.filename) == (errno.ENOSPC, str(target))
    assert str(error.value) == f"[Errno 28] No space left on device: '{target}'"
    assert target.read_bytes() == earlier and [p.name for p in tmp_path.iterdir()] == ["view.png"]


@pytest.mark.parametrize("command, name", [("evaluate", "ring/initial/000.png"), ("refine", "renders/000.png")])
def test_a_full_disk_in_a_staging_folder_names_the_file_asked_for(tmp_path, monkeypatch, command, name):
    """A view that the disk could not hold in a command's staging folder had been named as its hidden copy
    (``out/.evaluate-staging/ring/initial/000.png``): it is named as the file of --out it stands for."""
    from voxe_core.cli.common import staging_folder
    from voxe_core.export import save_png

    def disk_full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(OSError) as error, staging_folder(tmp_path, command) as staging:
        save_png(staging / name, np.zeros((4, 4, 3), np.uint8))
    assert str(error.value) == f"[Errno 28] No space left on device: '{tmp_path / name}'"
    assert list(tmp_path.iterdir()) == []


def test_render_metrics_that_cannot_be_written_keep_the_earlier_file(tmp_path, fill_disk, capsys):
    """A full disk while metrics.json was written had left it torn, the earlier render's destroyed: it is written
    whole or not at all."""
    from voxe_core.cli.render import _report_metrics

    images = torch.rand(2, 12, 12, 3, generator=torch.Generator().manual_seed(0))
    scene = SimpleNamespace(images=images, split="test")
    _report_metrics(psnr(images.flip(1), images), ssim(images.flip(1), images), scene, ["a.png", "b.png"], tmp_path)
    earlier = (tmp_path / "metrics.json").read_text()
    fill_disk()
    with pytest.raises(OSError, match="No space left on device"):
        _report_metrics(psnr(images.flip(2), images), None, scene, ["a.png", "b.png"], tmp_path)
    assert (tmp_path / "metrics.json").read_text() == earlier and json.loads(earlier)["views"] == 2
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


def test_render_metrics_of_a_view_identical_to_its_image_stay_finite(tmp_path, capsys):
    """A view rendered pixel for pixel as its image (its PSNR infinite) had made the mean PSNR inf, hiding every
    other view, and metrics.json invalid JSON (``Infinity``): it counts as PSNR_CAP_DB, as in ``voxe evaluate``."""
    from voxe_core.cli.render import _report_metrics
    from voxe_core.metrics import PSNR_CAP_DB

    images = torch.rand(2, 12, 12, 3, generator=torch.Generator().manual_seed(0))
    frames = torch.stack([images[0], 1 - images[1]])
    _report_metrics(psnr(frames, images), ssim(frames, images), SimpleNamespace(images=images, split="test"),
                    ["a.png", "b.png"], tmp_path)
    other = float(psnr(frames[1], images[1]))

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    metrics = json.loads((tmp_path / "metrics.json").read_text(), parse_constant=refuse)
    assert [view["psnr"] for view in metrics["per_view"]] == [PSNR_CAP_DB, pytest.approx(other)]
    assert metrics["psnr"] == pytest.approx((PSNR_CAP_DB + other) / 2)
    assert f"test: PSNR {(PSNR_CAP_DB + other) / 2:.2f} dB" in capsys.readouterr().out


def test_render_ring(sphere_file, tmp_path):
    out = tmp_path / "ring"
    assert main(["render", str(sphere_file), "--ring", "3", "--size", "16", "--out", str(out), "--quiet"]) == 0
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) == 3 and not (out / "metrics.json").exists()
    image = np.asarray(Image.open(pngs[0]))
    assert image.shape == (16, 16, 3)
    assert image[8, 8, 0] > 230 and image[8, 8, 1] < 25 and (image[0, 0] == 255).all()


def test_a_grid_with_nan_features_is_refused_by_render_and_turntable_before_any_view(make_sphere_grid, tmp_path,
                                                                                      capsys):
    """A damaged grid file with NaN features had been rendered: its views written black where the NaN lies (the
    sphere's front here), with exit 0, and --data's scores "PSNR nan dB" in a metrics.json holding NaN. As voxe
    edit and reconstruct refuse such an initial grid, render and turntable now do, naming it, and write nothing."""
    from test_data import make_synthetic, pose, write_png

    grid = make_sphere_grid()
    grid.features.data[12:20, 12:20, 24:32] = float("nan")  # facing the camera at z = 4
    path = tmp_path / "damaged.safetensors"
    grid.save(path)
    write_png(tmp_path / "data" / "train" / "r_0.png")
    make_synthetic(tmp_path / "data", [{"file_path": "./train/r_0", "transform_matrix": pose(translation=(0, 0, 4))}])
    for command, output in ((["render", "--ring", "2", "--size", "16"], tmp_path / "ring"),
                            (["render", "--data", str(tmp_path / "data"), "--split", "train"], tmp_path / "scored"),
                            (["turntable", "--frames", "2", "--size", "16"], tmp_path / "spin.gif")):
        assert main([command[0], str(path), *command[1:], "--out", str(output), "--device", "cpu", "--quiet"]) == 2
        assert (f"the grid {path} has non-finite (NaN or infinite) features at 512 of its 32768 vertices, which the "
                "renderer would carry into every view that sees them (a damaged grid file?)") in capsys.readouterr().err
        assert not output.exists() or not any(output.iterdir())


def test_a_grid_with_nan_colours_is_refused_by_export_mesh_not_meshed_black(make_sphere_grid, tmp_path, capsys):
    """A damaged grid file whose density is whole but whose colour features are NaN had been meshed with exit 0, its
    vertex colours black there (extract_mesh read only the density). It is now refused as render refuses it, naming
    the damage, and no mesh is written."""
    grid = make_sphere_grid()
    grid.features.data[12:20, 12:20, 24:32, 1:] = float("nan")  # the colours only: the surface is defined
    # (the sparse file keeps 192 of these 512 vertices: those of the cells that can hold density)
    path = tmp_path / "damaged.safetensors"
    grid.save(path)
    out = tmp_path / "mesh.ply"
    assert main(["export-mesh", str(path), "--out", str(out), "--device", "cpu"]) == 2
    assert ("the grid has non-finite (NaN or infinite) features at 192 of its 32768 vertices, which the vertex "
            "colouring would carry into the mesh's colours (a damaged grid file?)") in capsys.readouterr().err
    assert not out.exists()


def test_ring_of_a_capture_grid_orbits_its_object_or_the_grid_named_by_centre_of(tmp_path, capsys):
    """A scene grid's ball 0.69 units off its frame's origin is in the middle of every ring view; with
    ``--centre-of`` a grid whose ball is at the origin, the ring looks at the origin and the ball moves off."""
    from test_export import scene_blob

    off, centred = tmp_path / "off.safetensors", tmp_path / "centred.safetensors"
    scene_blob((0.5625, -0.375, 0.1875)).save(off)
    scene_blob((0.0, 0.0, 0.0)).save(centred)

    def ball_centroids(out: Path) -> np.ndarray:
        images = [np.asarray(Image.open(p), dtype=np.float64) / 255.0 for p in sorted(out.glob("*.png"))]
        ys, xs = np.mgrid[0:32, 0:32] + 0.5
        return np.array([[(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()] for w in (1.0 - i[..., 1] for i in images)])

    common = ["--ring", "3", "--size", "32", "--quiet"]
    assert main(["render", str(off), *common, "--out", str(tmp_path / "own")]) == 0
    assert np.abs(ball_centroids(tmp_path / "own") - 16).max() < 0.3
    assert main(["render", str(off), *common, "--centre-of", str(centred), "--out", str(tmp_path / "other")]) == 0
    assert np.abs(ball_centroids(tmp_path / "other") - 16).max() > 4.0
    missing = tmp_path / "missing.safetensors"
    assert main(["turntable", str(off), "--out", str(tmp_path / "t.gif"), "--centre-of", str(missing), "--quiet"]) == 2
    assert f"{missing}: no such file" in capsys.readouterr().err and not (tmp_path / "t.gif").exists()


def test_grids_named_in_another_encoding_than_utf8_are_read(sphere_file, tmp_path):
    """A grid whose file name is no valid UTF-8 (é as Latin-1's byte 0xe9, a folder copied from an older system) was
    written by voxe, but every command refused it: "not a readable safetensors file (Path ... is not valid UTF-8)",
    safetensors' own refusal to open it, and ``voxe convert-grid --out`` such a name exited 2 with its output
    written. Such a file reads as any other (under LC_ALL=C too: the commands are run as a shell runs them)."""
    import torch

    from voxe_core.backbones import load_grid

    latin1 = tmp_path / os.fsdecode(b"caf\xe9")
    try:
        latin1.mkdir()
    except (OSError, UnicodeEncodeError):
        pytest.skip("the file system takes no name that is not UTF-8")
    grid = latin1 / os.fsdecode(b"sph\xe8re.safetensors")
    grid.write_bytes(sphere_file.read_bytes())
    copy = latin1 / os.fsdecode(b"copie \xe9.safetensors")

    def voxe(*args: str) -> None:
        result = subprocess.run([sys.executable, "-m", "voxe_core.cli", *args], cwd=REPO, capture_output=True,
                                timeout=300, env={**os.environ, "LC_ALL": "C", "LANG": "C"})
        assert result.returncode == 0, result.stderr.decode(errors="replace")

    voxe("convert-grid", str(grid), "--out", str(copy), "--dense")
    assert main(["convert-grid", str(sphere_file), "--out", str(tmp_path / "utf8.safetensors"), "--dense"]) == 0
    assert torch.equal(load_grid(copy).features, load_grid(tmp_path / "utf8.safetensors").features)
    voxe("render", str(copy), "--ring", "1", "--size", "16", "--out", str(latin1 / "views"), "--quiet")
    assert sorted(os.listdir(latin1 / "views")) == ["000.png", "render.json"]


def test_render_into_an_earlier_output_leaves_only_this_runs_views(sphere_file, tmp_path):
    """A re-run into the same --out had left the earlier run's extra views beside its own: the files an earlier run
    listed in its manifest go; others stay, whatever their names (the user's own 1080.png or 123_scan.png too, which
    a name pattern had deleted)."""
    out = tmp_path / "views"
    ring = ["render", str(sphere_file), "--size", "16", "--out", str(out), "--quiet", "--ring"]
    assert main(ring + ["3"]) == 0
    assert json.loads((out / "render.json").read_text()) == {"written_by": "voxe render",
                                                             "files": ["000.png", "001.png", "002.png"]}
    for name in ("notes.txt", "cover.png", "0001.jpg", "1080.png", "123_scan.png", "metrics.json"):
        (out / name).write_text("mine")
    assert main(ring + ["2"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["000.png", "0001.jpg", "001.png", "1080.png", "123_scan.png",
                                                     "cover.png", "metrics.json", "notes.txt", "render.json"]
    assert np.asarray(Image.open(out / "001.png")).shape == (16, 16, 3)
    (out / "render.json").write_text(json.dumps({"written_by": "voxe render",  # other folders' files
                                                 "files": ["000.png", "../views/notes.txt", "/etc/hostname", 3]}))
    assert main(ring + ["1"]) == 0  # removes nothing of theirs
    assert (out / "notes.txt").exists() and (out / "cover.png").exists() and (out / "001.png").exists()


def test_render_removes_the_files_of_the_manifest_it_checked_not_of_one_written_during_its_render(
        sphere_file, tmp_path, monkeypatch):
    """voxe render read --out's manifest twice: to check --out before the render, and again after it to remove the
    earlier run's files. A manifest written meanwhile (another run into the same --out) had its files removed,
    unchecked: the listing checked is the one whose files go."""
    import voxe_core.cli.render as render

    out = tmp_path / "views"
    ring = ["render", str(sphere_file), "--size", "16", "--out", str(out), "--quiet", "--ring"]
    assert main(ring + ["2"]) == 0
    rendering = render._render_into

    def another_run_meanwhile(*args, **kwargs):
        (out / "other.png").write_text("another run's")
        (out / "render.json").write_text(json.dumps({"written_by": "voxe render", "files": ["other.png"]}))
        return rendering(*args, **kwargs)

    monkeypatch.setattr(render, "_render_into", another_run_meanwhile)
    assert main(ring + ["1"]) == 0
    assert sorted(os.listdir(out)) == ["000.png", "other.png", "render.json"]  # 001.png, checked, gone
    assert json.loads((out / "render.json").read_text()) == {"written_by": "voxe render", "files": ["000.png"]}


def test_render_refuses_to_write_over_files_no_earlier_run_wrote(sphere_file, tmp_path, capsys):
    """A user's own render.json, metrics.json or view-named file in --out had been overwritten by the run (the
    help says files no run listed stay): the run is refused before rendering, naming the file, which stays."""
    out = tmp_path / "views"
    ring = ["render", str(sphere_file), "--size", "16", "--out", str(out), "--quiet", "--ring", "2"]
    out.mkdir()
    for manifest in ({"files": ["notes.txt"]}, ["001.png"], "my render settings"):  # the user's own render.json
        (out / "render.json").write_text(json.dumps(manifest))
        assert main(ring) == 2
        assert (f"--out: {out / 'render.json'} is not a manifest voxe render wrote" in capsys.readouterr().err)
        assert json.loads((out / "render.json").read_text()) == manifest and sorted(os.listdir(out)) == ["render.json"]
    (out / "render.json").unlink()
    (out / "001.png").write_text("mine")
    assert main(ring) == 2
    assert f"--out: {out / '001.png'} was not written by an earlier voxe render" in capsys.readouterr().err
    assert (out / "001.png").read_text() == "mine" and sorted(os.listdir(out)) == ["001.png"]
    (out / "001.png").unlink()
    assert main(ring) == 0  # its own files it writes over at the next run
    assert main(ring) == 0 and sorted(os.listdir(out)) == ["000.png", "001.png", "render.json"]


@needs_mic
def test_render_refuses_to_write_over_a_users_metrics_json(sphere_file, tmp_path, capsys):
    """--data's metrics.json over a user's own one (a ring run's folder, which lists none) is refused."""
    out = tmp_path / "views"
    assert main(["render", str(sphere_file), "--ring", "1", "--size", "16", "--out", str(out), "--quiet"]) == 0
    (out / "metrics.json").write_text("mine")
    data = ["render", str(sphere_file), "--data", str(MIC), "--split", "test", "--downsample", "16",
            "--max-images", "1", "--out", str(out), "--quiet"]
    assert main(data) == 2
    assert f"--out: {out / 'metrics.json'} was not written by an earlier voxe render" in capsys.readouterr().err
    assert (out / "metrics.json").read_text() == "mine"
    (out / "metrics.json").unlink()
    assert main(data) == 0 and main(data) == 0  # its own metrics.json, replaced


@pytest.mark.parametrize("source", ["ring", pytest.param("data", marks=needs_mic)])
def test_render_saves_each_view_before_rendering_the_next(sphere_grid, sphere_file, tmp_path, monkeypatch, source):
    """Regression: voxe render rendered every view before it saved the first (a ring of 1,000 views of 2,048²: 50 GB
    of floats). Each is saved as it is rendered: at every save at most one view is alive (beside the dataset's
    images, read whole). The PNGs, and the dataset views' metrics, are bit for bit those of the views rendered and
    scored all at once."""
    import voxe_core.export
    from test_export import views_alive
    from voxe_core.cli.render import METRICS_FILE
    from voxe_core.export import turntable_cameras

    views = 6 if source == "ring" else 4
    options = (["--ring", "6", "--size", "20"] if source == "ring" else
               ["--data", str(MIC), "--split", "test", "--downsample", "16", "--max-images", "4"])
    size, images_read = ((20, 20), 0) if source == "ring" else ((50, 50), views)  # (MIC's 800² / 16)
    real_save_png, alive = voxe_core.export.save_png, []

    def counting_save_png(path, image):
        alive.append(views_alive(*size) - images_read)
        real_save_png(path, image)

    monkeypatch.setattr(voxe_core.export, "save_png", counting_save_png)
    out = tmp_path / "views"
    assert main(["render", str(sphere_file), *options, "--out", str(out), "--quiet"]) == 0
    assert len(alive) == views and max(alive) <= 1.5, alive
    if source == "ring":
        cameras, images = turntable_cameras(6, 30.0, 20, centre=sphere_grid.orbit_centre()), None
    else:
        scene = load_scene(MIC, "test", 16, 4)
        cameras, images = sphere_grid.dataset_cameras(scene.cameras), scene.images
    whole = render_views(sphere_grid, cameras)
    names = json.loads((out / "render.json").read_text())["files"]
    for name, frame in zip(names, whole):
        real_save_png(tmp_path / "whole" / name, frame)
        assert (out / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()
    if images is not None:
        metrics = json.loads((out / METRICS_FILE).read_text())
        assert [view["psnr"] for view in metrics["per_view"]] == psnr(whole, images).tolist()
        assert [view["ssim"] for view in metrics["per_view"]] == ssim(whole, images).tolist()


@pytest.mark.parametrize("failure", ["disk full", "cancelled"])
def test_a_render_failing_part_way_leaves_the_earlier_runs_views_as_they_were(sphere_file, tmp_path, monkeypatch,
                                                                              capsys, failure):
    """Saving each view as it is rendered, a run that fails or is cancelled at its third view must not leave a mix
    of its own views and the earlier run's: they are staged beside --out and moved in once all are written. A killed
    run's staging folder goes at the next run; one a running run holds is not emptied, the second run refused."""
    import fcntl

    import voxe_core.export
    from voxe_core.progress import StageCancelled

    out = tmp_path / "views"
    (out / ".render-staging").mkdir(parents=True)
    (out / ".render-staging" / STAGING_MARKER).write_text("voxe render's")
    (out / ".render-staging" / "000.png").write_bytes(b"a killed run's")
    staging = os.open(out / ".render-staging", os.O_RDONLY)  # a run writing into the same --out holds it
    fcntl.flock(staging, fcntl.LOCK_EX)
    assert main(["render", str(sphere_file), "--ring", "3", "--size", "16", "--out", str(out), "--quiet"]) == 2
    assert f"another voxe render is writing into {out}" in capsys.readouterr().err
    assert (out / ".render-staging" / "000.png").read_bytes() == b"a killed run's"  # that run's left as it was
    os.close(staging)
    assert main(["render", str(sphere_file), "--ring", "3", "--size", "16", "--out", str(out), "--quiet"]) == 0
    assert sorted(path.name for path in out.iterdir()) == ["000.png", "001.png", "002.png", "render.json"]
    earlier = {path.name: path.read_bytes() for path in out.iterdir()}
    real_save_png, saved = voxe_core.export.save_png, []

    def failing_at_the_third(path, image):
        if len(saved) == 2:
            raise (OSError(errno.ENOSPC, "No space left on device") if failure == "disk full"
                   else StageCancelled("render"))
        saved.append(path)
        real_save_png(path, image)

    monkeypatch.setattr(voxe_core.export, "save_png", failing_at_the_third)
    assert main(["render", str(sphere_file), "--ring", "4", "--size", "20", "--out", str(out), "--quiet"]) == (
        1 if failure == "disk full" else 130)  # a full disk is the machine's failure, not bad input (2)
    if failure == "disk full":
        assert "voxe render: error: [Errno 28] No space left on device" in capsys.readouterr().err
    assert len(saved) == 2 and {path.name: path.read_bytes() for path in out.iterdir()} == earlier


def staging_command(command: str, sphere_file, tmp_path) -> list[str]:
    """A small ``voxe render`` or ``voxe evaluate`` of ``sphere_file`` (--out not given): the commands that stage."""
    if command == "render":
        return ["render", str(sphere_file), "--ring", "2", "--size", "16"]
    from voxe_core.tiny_eval import build_tiny_clip

    return ["evaluate", str(sphere_file), "--object", "ball", "--size", "16", "--views", "2",
            "--edit", str(sphere_file), "a claymation ball",
            "--clip-model", str(build_tiny_clip(tmp_path / "clip"))]  # SMOKE-TEST MODEL: plumbing only


@pytest.mark.parametrize("command", ["render", "evaluate"])
def test_an_output_path_in_the_way_fails_the_run_before_it_renders(sphere_file, tmp_path, capsys, command):
    """A folder named as one of its outputs in --out had failed the move after the whole run: the earlier run's
    files replaced in part (evaluate's, beside the earlier evaluation.json). Every output path is checked first."""
    import voxe_core.export

    out = tmp_path / "out"
    argv = staging_command(command, sphere_file, tmp_path)
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    in_the_way = out / {"render": "001.png", "evaluate": "evaluation.md"}[command]
    in_the_way.unlink()
    in_the_way.mkdir()
    earlier = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    real_save_png, saved = voxe_core.export.save_png, []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(voxe_core.export, "save_png", lambda path, image: saved.append(path) or real_save_png(path, image))
        capsys.readouterr()
        assert main([*argv, "--out", str(out), "--quiet"]) == 2
    assert f"cannot write {in_the_way}: it is a folder" in capsys.readouterr().err and saved == []
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == earlier


def test_an_evaluation_whose_move_fails_part_way_leaves_no_summary(sphere_file, tmp_path, monkeypatch):
    """The earlier evaluation.json had stayed beside this run's ring renders moved in before the failure: it goes
    before the first move, so evaluation.json in --out means the set is whole."""

    from voxe_core.tiny_eval import build_tiny_clip

    out = tmp_path / "eval"
    command = ["evaluate", str(sphere_file), "--object", "ball", "--out", str(out), "--size", "16", "-q",
               "--clip-model", str(build_tiny_clip(tmp_path / "clip")), "--edit", str(sphere_file), "a claymation ball"]
    assert main(command + ["--views", "2"]) == 0
    real_replace, moved = os.replace, []

    def failing_at_the_second_frame(source, target):
        if Path(target).parent.parent == out / "ring":  # (other renames, a frame saved in the staging, go on)
            if moved:
                raise OSError(errno.EIO, "Input/output error", str(target))
            moved.append(target)
        real_replace(source, target)

    monkeypatch.setattr(os, "replace", failing_at_the_second_frame)
    assert main(command + ["--views", "3"]) == 1  # an I/O error: the machine's failure
    assert len(moved) == 1 and not (out / "evaluation.json").exists() and not (out / "evaluation.md").exists()


@pytest.mark.parametrize("command", ["render", "evaluate"])
def test_a_users_own_folder_named_like_the_staging_is_refused_not_emptied(sphere_file, tmp_path, capsys, command):
    """A folder of the staging's name that no run made (the user's, holding their files) had been emptied by the
    next run: it is refused, naming it, and left as it was; one a run made and was killed in (marked) is cleared."""
    out = tmp_path / "out"
    staging = out / f".{command}-staging"
    (staging / "mine").mkdir(parents=True)
    (staging / "mine" / "notes.txt").write_text("mine")
    argv = staging_command(command, sphere_file, tmp_path)
    assert main([*argv, "--out", str(out), "--quiet"]) == 2
    assert f"{staging} is not a staging folder voxe {command} made" in capsys.readouterr().err
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        f".{command}-staging", f".{command}-staging/mine", f".{command}-staging/mine/notes.txt"]
    (staging / STAGING_MARKER).write_text("a killed run's")  # as a run that made it leaves it
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    assert not staging.exists()


def test_render_needs_exactly_one_camera_source(sphere_file, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["render", str(sphere_file), "--out", str(tmp_path)])
    assert exc.value.code == 2


# ------------------------------------------------------------- turntable, mesh
def test_turntable_mp4_is_playable_with_the_right_frame_count(sphere_file, tmp_path):
    out = tmp_path / "tt.mp4"
    assert main(["turntable", str(sphere_file), "--out", str(out), "--frames", "6", "--size", "24", "--quiet"]) == 0
    reader = imageio.get_reader(out, format="FFMPEG")
    frames = [f for f in reader]
    reader.close()
    assert len(frames) == 6 and frames[0].shape == (24, 24, 3)
    centre = frames[0][12, 12].astype(int)
    assert centre[0] > 200 and centre[1] < 60  # the red sphere in the middle


def test_turntable_gif_and_bad_suffix(make_sphere_grid, sphere_file, tmp_path, capsys):
    # Off-centre, so the frames differ (Pillow folds identical consecutive GIF frames together).
    moving = tmp_path / "moving.safetensors"
    make_sphere_grid(resolution=24, radius=0.4, center=(0.6, 0.0, 0.0)).save(moving)
    gif = tmp_path / "tt.gif"
    assert main(["turntable", str(moving), "--out", str(gif), "--frames", "3", "--size", "16", "--fps", "5",
                 "--quiet"]) == 0
    with Image.open(gif) as im:
        assert im.size == (16, 16) and im.n_frames == 3
        assert im.info["loop"] == 0 and im.info["duration"] == 200
    assert capsys.readouterr().out == f"wrote {gif}: 3 frames of 16x16\n"
    assert main(["turntable", str(moving), "--out", str(gif), "--frames", "6", "--size", "16", "--fps", "120",
                 "--quiet"]) == 0  # every 3rd frame kept (it had said "6 frames")
    with Image.open(gif) as im:
        assert im.n_frames == 2
    assert capsys.readouterr().out == f"wrote {gif}: 6 frames of 16x16 (2 of them shown: a GIF plays at most 50 fps)\n"
    assert main(["turntable", str(sphere_file), "--out", str(tmp_path / "tt.webm"), "--quiet"]) == 2
    assert "'.webm'" in capsys.readouterr().err


@pytest.mark.parametrize("name, size, message", [
    ("tt.mp4", 16385, "an MP4 holds frames of at most 16384 pixels a side whose (width + 128) x (height + 128) is "
                      "under 268,435,456 (16254x16254 at most, square), got 16385x16385: make them smaller, or write "
                      "a GIF"),
    ("tt.mp4", 16255, "got 16255x16255"),  # (ffmpeg's "Picture size 16256x16256 is invalid", padded even)
    ("tt.gif", 65536, "a GIF holds frames of at most 65535 pixels a side, got 65536x65536"),
])
def test_a_turntable_of_frames_too_large_for_its_video_is_refused_before_rendering(sphere_file, tmp_path, capsys,
                                                                                    monkeypatch, name, size, message):
    """The encoder had refused them after the first frame's render (268 million rays at 16385²): "the video encoder
    failed (ffmpeg exited with status 187: invalid width x height (16386x16386))"."""
    import voxe_core.export

    def rendering(*args, **kwargs):
        raise AssertionError("rendered")
        yield

    monkeypatch.setattr(voxe_core.export, "iter_views", rendering)
    out = tmp_path / name
    assert main(["turntable", str(sphere_file), "--out", str(out), "--frames", "2", "--size", str(size),
                 "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_turntable_faster_than_a_video_holds_is_refused_before_rendering(sphere_file, tmp_path, capsys):
    """--fps had no ceiling: 1e10 failed in ffmpeg ("Unable to parse "framerate" option value") after the whole
    render, and 2e6 wrote an MP4 at 1,001,000 fps (a longer clip than asked)."""
    out = tmp_path / "tt.mp4"
    for fps in ("1e10", "2e6"):  # (inf: refused as the options are read, by finite_float)
        assert main(["turntable", str(sphere_file), "--out", str(out), "--frames", "2", "--size", "8", "--fps", fps,
                     "--quiet"]) == 2
        err = capsys.readouterr().err
        assert f"fps must be a finite number of at least 0.001526 (a frame's delay is at most 655.35 s in a GIF) " \
               f"and at most 1,000,000 (the fastest rate ffmpeg writes in an MP4), got {float(fps):g}" in err
        assert not out.exists()
    assert main(["turntable", str(sphere_file), "--out", str(out), "--frames", "2", "--size", "8", "--fps", "1e6",
                 "--quiet"]) == 0  # the ceiling itself, at its rate
    import imageio_ffmpeg

    probe = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-i", str(out)], capture_output=True, text=True)
    assert " 1000k fps," in probe.stderr  # (imageio's reader reads "1000k" as 0)


def test_export_mesh_ply_glb_and_obj(sphere_grid, sphere_file, tmp_path, capsys):
    ply = tmp_path / "m.ply"
    assert main(["export-mesh", str(sphere_file), "--out", str(ply)]) == 0
    mesh = trimesh.load(ply, process=False)
    voxel = float(sphere_grid.voxel_size.min())
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.8).mean() < voxel
    assert f"{len(mesh.vertices)} vertices" in capsys.readouterr().out
    glb = tmp_path / "m.glb"
    assert main(["export-mesh", str(sphere_file), "--out", str(glb), "--resolution", "48"]) == 0
    assert len(trimesh.load(glb, force="mesh").vertices) > len(mesh.vertices)
    obj = tmp_path / "m.obj"
    assert main(["export-mesh", str(sphere_file), "--out", str(obj)]) == 0
    assert len(trimesh.load(obj, force="mesh", process=False).vertices) == len(mesh.vertices)
    assert (tmp_path / "m.mtl").is_file()


def under_an_ascii_locale(command: list, timeout: float = 300) -> subprocess.CompletedProcess:
    """``command`` run where the locale's encoding is ASCII: LC_ALL=C with Python's UTF-8 mode and locale coercion
    off (C's own turn them on), as a non-UTF-8 locale (Latin-1's lacks "–" and "☕" too) writes text files."""
    env = {key: value for key, value in os.environ.items() if key != "PYTHONIOENCODING"}
    env.update(LC_ALL="C", LANG="C", PYTHONUTF8="0", PYTHONCOERCECLOCALE="0")
    return subprocess.run(command, cwd=REPO, env=env, capture_output=True, timeout=timeout)


def test_an_obj_names_its_material_library_by_its_files_name_under_an_ascii_locale(sphere_file, tmp_path):
    """``voxe export-mesh --out café.obj`` under an ASCII locale had failed (exit 2, "'ascii' codec can't encode
    characters"): the OBJ names its .mtl in the bytes the file system names it by."""
    out = os.fsencode(tmp_path) + "/café.obj".encode()
    result = under_an_ascii_locale([sys.executable, "-m", "voxe_core.cli", "export-mesh", str(sphere_file),
                                    "--out", out])
    assert result.returncode == 0, result.stderr
    assert b"mtllib caf\xc3\xa9.mtl\n" in Path(os.fsdecode(out)).read_bytes()
    assert (tmp_path / "café.mtl").is_file()


def test_export_mesh_obj_refuses_a_material_library_it_cannot_write_before_making_the_mesh(sphere_file, tmp_path,
                                                                                          capsys, monkeypatch):
    """A folder in the way of the .mtl beside --out m.obj had been found only as the mesh was saved, after the marching
    cubes, and the OBJ written all the same (exit 2, '[Errno 21] Is a directory: ...m.mtl')."""
    import voxe_core.export

    (tmp_path / "m.mtl").mkdir()
    monkeypatch.setattr(voxe_core.export, "extract_mesh", lambda *args, **kwargs: pytest.fail("the mesh was made"))
    assert main(["export-mesh", str(sphere_file), "--out", str(tmp_path / "m.obj")]) == 2
    assert capsys.readouterr().err == f"voxe export-mesh: error: cannot write {tmp_path / 'm.mtl'}: it is a folder\n"
    assert not (tmp_path / "m.obj").exists()


@pytest.mark.parametrize("resolution", ["100000", "3000000"])
def test_a_size_past_the_machines_memory_exits_2_naming_it(resolution, sphere_file, tmp_path, monkeypatch, capsys):
    """It had been torch's RuntimeError traceback (exit 1): "can't allocate memory", and at 3000000 "Storage size
    calculation overflowed" (a byte count past 64 bits). (--resolution now stops at the service's 1024 first: lifted
    here, as a library caller's is not bounded.)"""
    import voxe_core.cli.mesh as mesh_commands

    monkeypatch.setattr(mesh_commands, "MAX_MESH_RESOLUTION", 2**31 - 1)
    assert main(["export-mesh", str(sphere_file), "--out", str(tmp_path / "m.ply"), "--resolution", resolution]) == 2
    err = capsys.readouterr().err
    assert "voxe export-mesh: error: out of memory (" in err and "ask for less" in err and "Traceback" not in err
    assert not (tmp_path / "m.ply").exists()

    def bare_memory_error(args):
        raise MemoryError()  # Python's own allocation failures carry no message

    with pytest.MonkeyPatch.context() as patched:
        patched.setattr(mesh_commands, "cmd_export_mesh", bare_memory_error)
        assert main(["export-mesh", str(sphere_file), "--out", str(tmp_path / "m.ply")]) == 2
    assert "error: out of memory (MemoryError)" in capsys.readouterr().err


def test_export_mesh_errors_exit_2(sphere_file, tmp_path, capsys):
    empty = tmp_path / "empty.safetensors"
    VoxelGrid(8, init_density=-1.0).save(empty)
    assert main(["export-mesh", str(empty), "--out", str(tmp_path / "m.ply")]) == 2
    assert "grid has no surface at level" in capsys.readouterr().err
    not_a_grid = tmp_path / "junk.safetensors"
    not_a_grid.write_bytes(b"definitely not safetensors")
    assert main(["export-mesh", str(not_a_grid), "--out", str(tmp_path / "m.ply")]) == 2
    assert "not a readable safetensors file" in capsys.readouterr().err
    assert main(["export-mesh", str(sphere_file), "--out", str(tmp_path / "m.stl")]) == 2
    assert "'.stl'" in capsys.readouterr().err
    assert not (tmp_path / "m.ply").exists()


@pytest.mark.parametrize("name, content, message", [
    ("gone.obj", None, "gone.obj: no such file"),  # trimesh: "string is not a file: `<the full path>`"
    ("folder.ply", "folder", "folder.ply: is a folder, not a mesh file"),
    ("pipe.obj", "fifo", "pipe.obj: is a FIFO (named pipe), not a regular file"),  # "no such file"; trimesh waits
    ("cut.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n",  # "list index out of range"
     "cut.ply: its header has no end_header line: it is truncated, or not a PLY file"),
    ("faces.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",  # "index 3 is out of bounds for axis 0 with size 3"
     "faces.obj: line 4, 'f 1 2 4': a face names vertex 4, of the 3 the file holds"),
    ("scene.glb", "glTF garbage", "scene.glb: unsupported mesh type '.glb'; use one of .obj, .ply"),
])
def test_mesh_to_grid_says_what_is_wrong_with_its_mesh_in_one_line(tmp_path, capsys, name, content, message):
    if content == "folder":
        (tmp_path / name).mkdir()
    elif content == "fifo":
        os.mkfifo(tmp_path / name)
    elif content is not None:
        (tmp_path / name).write_text(content)
    assert main(["mesh-to-grid", str(tmp_path / name), "--out", str(tmp_path / "g.safetensors")]) == 2
    assert capsys.readouterr().err == f"voxe mesh-to-grid: error: {message}\n"


def test_the_services_smoke_test_model_name_is_told_as_such_with_how_to_build_one(sphere_grid, tmp_path, capsys,
                                                                                  monkeypatch):
    """Regression: ``--clip-model tiny`` (``--model tiny``), the service's name for its random-weight smoke-test
    models, was advised "`hf download tiny`", no hub id; the CLI takes such a model as the folder it is built in."""
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.chdir(tmp_path)
    sphere_grid.save(tmp_path / "g.safetensors")
    note = ("'tiny' is the service's name for its random-weight smoke-test model, which it builds in code; it is no "
            "hub id, and there is no folder 'tiny' here: write one with {build} and pass that folder (it proves the "
            "plumbing only, never quality)")
    assert main(["edit", "g.safetensors", "--prompt", "a dog", "--out", "out", "--offline", "--device", "cpu",
                 "--model", "tiny"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("voxe edit: model not available: Stable Diffusion weights 'tiny' are not available: "
                          + note.format(build="`voxe build-tiny-model DIR`") + ". Underlying error: ")
    assert "download" not in err
    assert main(["evaluate", "g.safetensors", "--edit", "g.safetensors", "a dog", "--object", "dog", "--out", "ev",
                 "--offline", "--device", "cpu", "--clip-model", "tiny"]) == 2
    build = "python -c \"from voxe_core.tiny_eval import build_tiny_clip; build_tiny_clip('DIR')\""
    assert capsys.readouterr().err == ("voxe evaluate: model not available: CLIP weights 'tiny' are not available: "
                                       + note.format(build=build) + ".\n")



def test_evaluate_inception_tiny_is_told_as_the_services_smoke_test_model(sphere_grid, tmp_path, capsys,
                                                                           monkeypatch):
    """Regression: ``--inception tiny`` (the service's VOXE_FID_MODEL=tiny) was told to download NVIDIA's Inception
    file "and pass its path"; the advice given now builds the smoke-test file, which --inception then takes."""
    from voxe_core.tiny_eval import build_tiny_clip

    monkeypatch.chdir(tmp_path)
    sphere_grid.save(tmp_path / "g.safetensors")
    clip = build_tiny_clip(tmp_path / "clip")  # SMOKE-TEST MODEL: plumbing only
    capsys.readouterr()  # (its writing's progress)
    command = ["evaluate", "g.safetensors", "--edit", "g.safetensors", "a dog", "--object", "dog", "--out", "ev",
               "--device", "cpu", "--clip-model", str(clip), "--views", "2", "--size", "16", "-q", "--inception"]
    assert main([*command, "tiny"]) == 2
    err = capsys.readouterr().err
    build = "python -c \"from voxe_core.tiny_eval import build_tiny_inception; build_tiny_inception('DIR/inception-2015-12-05.pt')\""
    assert err == ("voxe evaluate: model not available: FID Inception weights not found at tiny: 'tiny' is the "
                   "service's name for its random-weight smoke-test model, which it builds in code; it is no hub id, "
                   f"and there is no folder 'tiny' here: write one with {build} and pass that folder (it proves the "
                   "plumbing only, never quality).\n")
    _, flag, code = shlex.split(build)  # run as advised, DIR a folder of ours
    subprocess.run([sys.executable, flag, code.replace("DIR", str(tmp_path / "fid"))], check=True,
                   env={**os.environ, "PYTHONPATH": str(Path(__file__).parent.parent)})
    assert main([*command, str(tmp_path / "fid")]) == 0  # the folder it wrote, as the note says


def test_edit_with_missing_weights_names_the_model_and_how_to_provide_it(sphere_grid, tmp_path, capsys, monkeypatch):
    """A hub id is told how to fill the cache; a folder had been told to download itself from the hub
    (`huggingface-cli download ./models/sd`, and `models/sd/v15`, which no hub id can be), and a hub id that reads
    like a missing folder ("models/gone" beside a models/) was not told that no such folder is there."""
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.chdir(tmp_path)
    sphere_grid.save(tmp_path / "g.safetensors")
    edit = ["edit", "g.safetensors", "--prompt", "a dog", "--out", "out", "--offline", "--device", "cpu", "--model"]
    assert main([*edit, "voxe-test/no-such-sd"]) == 2
    err = capsys.readouterr().err
    assert ("voxe edit: model not available: Stable Diffusion weights 'voxe-test/no-such-sd' are not available "
            "offline: download them once with `hf download voxe-test/no-such-sd --include model_index.json ") in err
    assert "point HF_HOME at that cache, or pass a local folder in the diffusers layout" in err
    (tmp_path / "models" / "sd").mkdir(parents=True)
    for folder in ("./models/gone", "./models/sd"):
        assert main([*edit, folder]) == 2
        err = capsys.readouterr().err
        assert (f"voxe edit: model not available: Stable Diffusion weights '{folder}' are not available: that local "
                "folder must hold the whole model in the diffusers layout (model_index.json, unet/") in err
        assert f"download {folder}" not in err
    assert main([*edit, "models/sd/v15"]) == 2  # no hub id (owner/name): a folder, though not written ./
    err = capsys.readouterr().err
    assert ("Stable Diffusion weights 'models/sd/v15' are not available: that local folder must hold the whole model"
            in err and "no folder models/sd/v15" in err and "download models/sd/v15" not in err)
    assert main([*edit, "models/gone"]) == 2  # a hub id's form (as diffusers reads it), its owner a folder here
    assert (f"'models/gone' are not available offline (nor is there a folder models/gone: {tmp_path / 'models'} "
            "holds no 'gone'): download them once") in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("flag, expected", [([], {"cuda_graphs": None, "compile_encoder": None}),
                                            (["--no-cuda-graphs"], {"cuda_graphs": False, "compile_encoder": None}),
                                            (["--no-compile-encoder"], {"cuda_graphs": None, "compile_encoder": False})])
def test_edit_asks_for_cuda_graphs_and_a_compiled_encoder_unless_told_not_to(flag, expected, sphere_grid, tmp_path,
                                                                            monkeypatch):
    """``voxe edit`` leaves the graphs and the compile to ``from_pretrained``'s defaults (on CUDA) or turns them off."""
    from voxe_core.guidance.loading import ModelNotAvailableError
    from voxe_core.guidance.sds import StableDiffusionGuidance

    asked = {}

    def from_pretrained(model, **kwargs):
        asked.update(kwargs)
        raise ModelNotAvailableError(f"{model} is a stand-in")

    monkeypatch.setattr(StableDiffusionGuidance, "from_pretrained", from_pretrained)
    sphere_grid.save(tmp_path / "g.safetensors")
    code = main(["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--out", str(tmp_path / "out"),
                 "--model", "stand-in", "--device", "cpu", *flag])
    assert code == 2 and {key: asked[key] for key in expected} == expected


def previewing_edit(grid, prompt, guidance, config, callbacks, checkpoint, resume, views, on_preview, **kwargs):
    """``voxe_core.edit.edit``'s stand-in: previews at every ``preview_every``, and a checkpoint whose header is the
    one the edit writes (no tensors but G_e's features and the views' summary), at the iterations asked for."""
    import voxe_core.edit
    from voxe_core.tensorio import save_tensors

    for iteration in range(0, config.iterations + 1, config.preview_every or config.iterations + 1):
        on_preview(iteration, torch.zeros(4, 4, 3))
    meta = {**grid.header(), "prompt": prompt, "initial_sha256": voxe_core.edit.initial_fingerprint(grid),
            "model": guidance.model_id, "recipe": config.recipe(), "iteration": config.iterations}
    views_record = {} if views is None else {"views": voxe_core.reconstruct.views_summary(*views)}
    save_tensors(checkpoint, {"features": grid.features, **views_record}, voxe_core.edit.EDIT_CHECKPOINT_KIND,
                 voxe_core.edit.EDIT_CHECKPOINT_VERSION, meta)
    return grid


def stand_in_guidance(loaded: list | None = None):
    """``voxe_core.cli.edit.load_guidance``'s stand-in: a guidance named as the model asked for, appended to
    ``loaded``."""
    def load_guidance(args, model, **kwargs):
        guidance = SimpleNamespace(device="cpu", model_id=model)
        if loaded is not None:
            loaded.append(guidance)
        return guidance

    return load_guidance


def test_a_fresh_edit_leaves_no_earlier_runs_previews_and_a_resumed_one_keeps_its_own(sphere_grid, tmp_path,
                                                                                      monkeypatch):
    """A re-run into the same --out writing fewer previews (fewer iterations, another --preview-every, another
    prompt) had left the earlier run's beside its own, previews of an edit that edited.safetensors is not. A run
    with --resume continues the edit whose previews they are; files of other names stay."""
    import voxe_core.cli.edit as edit_command
    import voxe_core.edit

    monkeypatch.setattr(voxe_core.edit, "edit", previewing_edit)
    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance())
    sphere_grid.save(tmp_path / "g.safetensors")
    out = tmp_path / "out"
    edit = ["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--out", str(out), "--device", "cpu", "-q"]

    def previews() -> list[str]:
        return sorted(path.name for path in (out / "previews").iterdir())

    assert main([*edit, "--iterations", "4", "--preview-every", "1"]) == 0
    (out / "previews" / "notes.txt").write_text("the user's")
    assert main([*edit, "--iterations", "2", "--preview-every", "2"]) == 0
    assert previews() == ["notes.txt", "preview_00000.png", "preview_00002.png"]
    assert main([*edit, "--iterations", "3", "--preview-every", "3", "--resume", str(out / "checkpoint.safetensors")]) == 0
    assert previews() == ["notes.txt", "preview_00000.png", "preview_00002.png", "preview_00003.png"]


def test_a_fresh_edit_that_fails_or_is_cancelled_leaves_no_earlier_runs_result(sphere_grid, tmp_path, monkeypatch,
                                                                                capsys):
    """A fresh edit into an --out holding an earlier run's edited.safetensors had left it there when the new run
    failed or was cancelled: beside the new run's checkpoint and previews, as if it were this run's result. A fresh
    run removes it first (a resumed one continues that edit); a GRID that is that file, the input, stays."""
    import voxe_core.cli.edit as edit_command
    import voxe_core.edit
    from voxe_core.progress import StageCancelled

    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance())
    sphere_grid.save(tmp_path / "g.safetensors")
    out = tmp_path / "out"
    edit = ["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--out", str(out), "--device", "cpu", "-q",
            "--iterations", "2", "--preview-every", "1"]
    monkeypatch.setattr(voxe_core.edit, "edit", previewing_edit)

    def cancelled(*args, **kwargs):
        previewing_edit(*args, **kwargs)  # a checkpoint and previews of this run
        raise StageCancelled("edit")

    def failing(*args, **kwargs):
        raise RuntimeError("CUDA out of memory")

    for stand_in, code in ((cancelled, 130), (failing, 2)):
        assert main(edit) == 0 and (out / "edited.safetensors").is_file()  # the earlier run, whole
        monkeypatch.setattr(voxe_core.edit, "edit", stand_in)
        assert main(edit) == code
        assert not (out / "edited.safetensors").exists()
        monkeypatch.setattr(voxe_core.edit, "edit", previewing_edit)
    capsys.readouterr()
    assert main(edit) == 0
    monkeypatch.setattr(voxe_core.edit, "edit", failing)  # editing that result further, into the same --out
    assert main(["edit", str(out / "edited.safetensors"), *edit[2:]]) == 2
    assert (out / "edited.safetensors").is_file()


def test_a_fresh_edit_failing_before_its_first_checkpoint_leaves_no_earlier_runs_checkpoint(
        sphere_grid, tmp_path, monkeypatch, capsys):
    """A fresh edit (no --resume) failing or cancelled before its first checkpoint had left an earlier run's
    checkpoint.safetensors in --out, and the cancel hint named it to resume ("resume with --resume
    D/checkpoint.safetensors"), another run's edit. A fresh run removes it first, as it does the earlier result."""
    import voxe_core.cli.edit as edit_command
    import voxe_core.edit
    from voxe_core.progress import StageCancelled

    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance())
    sphere_grid.save(tmp_path / "g.safetensors")
    out = tmp_path / "out"
    edit = ["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--out", str(out), "--device", "cpu", "-q",
            "--iterations", "2", "--preview-every", "1"]

    def cancelled(*args, **kwargs):
        raise StageCancelled("edit")

    def failing(*args, **kwargs):
        raise RuntimeError("CUDA out of memory")

    for stand_in, code, said in ((cancelled, 130, "voxe: edit cancelled before its first step"),
                                 (failing, 2, "CUDA out of memory")):
        monkeypatch.setattr(voxe_core.edit, "edit", previewing_edit)
        assert main(edit) == 0 and (out / "checkpoint.safetensors").is_file()  # the earlier run, whole
        capsys.readouterr()
        monkeypatch.setattr(voxe_core.edit, "edit", stand_in)
        assert main(edit) == code
        assert said in capsys.readouterr().err
        assert not (out / "checkpoint.safetensors").exists()


@pytest.mark.parametrize("change, message", [
    ({"--prompt": "a cat"}, "checkpoint was made for the prompt 'a dog', not 'a cat'"),
    ({"grid": 20}, "checkpoint grid is (32, 32, 32), the initial grid (20, 20, 20)"),
    ({"grid": 0.6}, "checkpoint was made from a different initial grid"),
    ({"--guidance-scale": "50"}, "checkpoint was made with another recipe: guidance_scale 100.0 (now 50.0); resume"),
    ({"--model": "org/other"}, "checkpoint was made with the model 'org/model', not 'org/other'; resume with that"),
    ({"--iterations": "1"}, "checkpoint is at iteration 2, past the 1 iterations asked for; ask for at least 2"),
])
def test_edit_refuses_a_resume_from_another_jobs_checkpoint_before_it_loads_the_model(
        change, message, make_sphere_grid, tmp_path, monkeypatch, capsys):
    """A checkpoint of another grid, scene, prompt, recipe or model, or past the iterations asked for, had been
    refused only by the edit, after the diffusion model had loaded (minutes, a download maybe); with that model
    missing, the error had been the model's, not the checkpoint's. Refused now before the model is loaded."""
    import voxe_core.cli.edit as edit_command
    import voxe_core.edit

    loaded = []
    monkeypatch.setattr(voxe_core.edit, "edit", previewing_edit)
    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance(loaded))
    make_sphere_grid().save(tmp_path / "g.safetensors")
    out = tmp_path / "out"
    options = {"--prompt": "a dog", "--model": "org/model", "--iterations": "2"}
    run = ["--out", str(out), "--device", "cpu", "--preview-every", "0", "-q"]
    assert main(["edit", str(tmp_path / "g.safetensors"), *sum(options.items(), ()), *run]) == 0
    assert len(loaded) == 1
    grid = tmp_path / "g.safetensors"
    if "grid" in change:
        grid = tmp_path / "other.safetensors"
        value = change.pop("grid")
        (make_sphere_grid(value) if isinstance(value, int) else make_sphere_grid(radius=value)).save(grid)
    resume = ["edit", str(grid), *sum({**options, **change}.items(), ()), *run,
              "--resume", str(out / "checkpoint.safetensors")]
    assert main(resume) == 2
    assert f"voxe edit: error: {out / 'checkpoint.safetensors'}: {message}" in capsys.readouterr().err
    assert len(loaded) == 1  # no model loaded for it
    # the model missing too: the checkpoint's error, not the model's
    monkeypatch.setattr(edit_command, "load_guidance", load_guidance_of_common)
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    assert main([*resume, "--offline"]) == 2
    err = capsys.readouterr().err
    assert message in err and "model not available" not in err
    # the same job resumes (its model loaded once it is)
    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance(loaded))
    assert main(["edit", str(tmp_path / "g.safetensors"), *sum({**options, "--iterations": "3"}.items(), ()), *run,
                 "--resume", str(out / "checkpoint.safetensors")]) == 0
    assert len(loaded) == 2


def test_edit_refuses_a_resume_against_other_input_views_before_it_loads_the_model(sphere_grid, tmp_path,
                                                                                    monkeypatch, capsys):
    """An image-regularised edit resumed with another --data had been refused only by the edit, after the model's
    load (with that model missing: the model's error, not the checkpoint's)."""
    import voxe_core.cli.edit as edit_command
    import voxe_core.edit
    from test_data import make_synthetic

    loaded = []
    monkeypatch.setattr(voxe_core.edit, "edit", previewing_edit)
    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance(loaded))
    sphere_grid.save(tmp_path / "g.safetensors")
    views, other = make_synthetic(tmp_path / "views"), make_synthetic(tmp_path / "other", n=2)
    out = tmp_path / "out"
    edit = ["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--out", str(out), "--device", "cpu", "-q",
            "--regulariser", "image_l1", "--preview-every", "0", "--iterations"]
    assert main([*edit, "2", "--data", str(views)]) == 0
    resume = [*edit, "3", "--resume", str(out / "checkpoint.safetensors"), "--data"]
    assert main([*resume, str(other)]) == 2
    assert "checkpoint was made against other input views (images or cameras) for its image_l1 regulariser" in (
        capsys.readouterr().err)
    assert len(loaded) == 1  # none for the refused resume
    assert main([*resume, str(views)]) == 0 and len(loaded) == 2


@pytest.mark.parametrize("prompt", ["---", "?!", "'s ^^"])
def test_edit_refuses_a_prompt_that_names_nothing_before_it_loads_the_model(prompt, sphere_grid, tmp_path, monkeypatch,
                                                                            capsys):
    """The service refuses a prompt of punctuation alone (api.schemas.clean_text); voxe edit had loaded the model and
    run the whole edit towards "a render of ---"."""
    import voxe_core.cli.edit as edit_command
    import voxe_core.edit

    loaded = []
    monkeypatch.setattr(voxe_core.edit, "edit", previewing_edit)
    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance(loaded))
    sphere_grid.save(tmp_path / "g.safetensors")
    edit = ["edit", str(tmp_path / "g.safetensors"), "--out", str(tmp_path / "out"), "--device", "cpu", "-q",
            "--iterations", "1"]
    assert main([*edit, f"--prompt={prompt}"]) == 2  # (argparse reads a bare "---" as an option)
    assert f"voxe edit: error: the edit prompt {prompt!r} has no words: nothing in it names anything" in (
        capsys.readouterr().err)
    assert not loaded and not (tmp_path / "out").exists()
    assert main([*edit, "--prompt", "🐶"]) == 0 and len(loaded) == 1  # a symbol names something


def test_a_prompt_the_locale_could_not_decode_is_refused_naming_it_before_the_model_loads(sphere_file, tmp_path,
                                                                                        monkeypatch, capsys):
    """Under a locale that is not UTF-8 (LC_ALL=C, PYTHONUTF8=0) --prompt "a café ball" arrives with "é"'s bytes as
    surrogates ('\\udcc3\\udca9'): voxe edit loaded the model, then the tokenizer raised "TypeError: TextEncodeInput
    must be Union[...]", a traceback (exit 1); voxe evaluate so of its prompts and --object."""
    import voxe_core.cli.edit as edit_command

    loaded = []
    monkeypatch.setattr(edit_command, "load_guidance", stand_in_guidance(loaded))
    text = b"a caf\xc3\xa9 ball".decode("ascii", "surrogateescape")
    told = ("holds '\\udcc3', a byte that was no text in the encoding it was read in (a command line read under a "
            "locale that is not UTF-8: LC_ALL=C.UTF-8 or PYTHONUTF8=1 reads it whole)")
    assert main(["edit", str(sphere_file), "--out", str(tmp_path / "out"), "--device", "cpu", "-q", "--prompt",
                 text]) == 2
    assert capsys.readouterr().err == f"voxe edit: error: the prompt {told}\n" and not loaded
    evaluate = ["evaluate", str(sphere_file), "--out", str(tmp_path / "eval"), "--clip-model", str(tmp_path / "none")]
    assert main([*evaluate, "--object", "ball", "--edit", str(sphere_file), text]) == 2
    assert capsys.readouterr().err == f"voxe evaluate: error: the prompt {told}\n"
    assert main([*evaluate, "--object", text, "--edit", str(sphere_file), "a ball"]) == 2
    assert capsys.readouterr().err == f"voxe evaluate: error: the source text {told}\n"
    assert not (tmp_path / "out").exists() and not (tmp_path / "eval").exists()


@pytest.mark.parametrize("flag", [[], ["--fused-marcher"]])
def test_edit_marches_its_renders_fused_only_when_asked(flag, sphere_grid, tmp_path, monkeypatch):
    import voxe_core.cli.edit as edit_command
    import voxe_core.edit

    seen = []

    def recorded_edit(grid, prompt, guidance, config, *args, **kwargs):
        seen.append(config.render.fused)
        return grid

    monkeypatch.setattr(voxe_core.edit, "edit", recorded_edit)
    monkeypatch.setattr(edit_command, "load_guidance", lambda *args, **kwargs: SimpleNamespace(device="cpu"))
    sphere_grid.save(tmp_path / "g.safetensors")
    assert main(["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--out", str(tmp_path / "out"),
                 "--device", "cpu", "-q", *flag]) == 0
    assert seen == [bool(flag)]


# ---------------------------------------------------------------- evaluate
def test_the_evaluation_ring_defaults_are_the_same_for_the_cli_the_library_and_the_service():
    """Written once (voxe_core.constants), where the CLI, EvaluateConfig and the API's schema had each spelt them."""
    from api.schemas import EvaluationParams
    from voxe_core import constants
    from voxe_core.cli import build_parser
    from voxe_core.evaluate import EvaluateConfig

    args = build_parser().parse_args(["evaluate", "g", "--edit", "e", "p", "--object", "o", "--out", "d"])
    ring = (constants.EVALUATION_RING_VIEWS, constants.EVALUATION_RING_ELEVATION, constants.EVALUATION_RING_SIZE)
    assert ring == (100, 30.0, constants.RENDER_SIZE)  # the paper's ring (SPEC §4)
    for source in (args, EvaluateConfig(), EvaluationParams()):
        assert (source.views, source.elevation, source.size) == ring


@pytest.mark.parametrize("flag, value, rule", [
    ("--views", 0, "must be between 2 (FID needs two samples) and 360 (the service's limit), got 0"),
    ("--views", 1, "must be between 2 (FID needs two samples) and 360 (the service's limit), got 1"),
    ("--views", 361, "must be between 2 (FID needs two samples) and 360 (the service's limit), got 361"),
    ("--size", 0, "must be between 11 px (SSIM's window) and 1024 px (the service's limit), got 0"),
    ("--size", 10, "must be between 11 px (SSIM's window) and 1024 px (the service's limit), got 10"),
    ("--size", 1025, "must be between 11 px (SSIM's window) and 1024 px (the service's limit), got 1025"),
    ("--elevation", 90, "must lie strictly between -90 and 90 degrees, got 90.0"),
])
def test_evaluate_ring_options_are_refused_by_one_rule_the_services(flag, value, rule, capsys):
    """Regression: --views and --size had no upper bound (the API's evaluation stops at 360 views of 1024 px), and
    their option type said a rule of its own: --views 0 "must be at least 1", then --views 1 "needs at least 2"."""
    from api.schemas import EvaluationParams
    from pydantic import ValidationError

    command = ["evaluate", "no_such_grid.safetensors", "--edit", "e.safetensors", "a dog", "--object", "dog",
               "--out", "eval"]
    assert main([*command, flag, str(value)]) == 2
    assert capsys.readouterr().err == f"voxe evaluate: error: {flag} {rule}\n"
    with pytest.raises(ValidationError):  # the service refuses the same values
        EvaluationParams(**{flag[2:]: value})
    for views, size in ((2, 11), (360, 1024)):  # the bounds themselves pass: refused only for the missing grid
        assert main([*command, "--views", str(views), "--size", str(size)]) == 2
        assert "no_such_grid" in capsys.readouterr().err
        EvaluationParams(views=views, size=size)


def test_evaluate_refuses_a_mask_of_another_grid_before_reading_its_voxels(sphere_file, tmp_path, capsys):
    """Regression: the mask file's own shape was allocated first (a 252-byte file claiming 1290³ voxels: 2 GB), and
    a mask of another grid found out only after the CLIP model had loaded."""
    from voxe_core.refine.storage import save_mask

    mask = tmp_path / "mask.safetensors"
    save_mask(mask, torch.ones(7, 7, 7, dtype=torch.bool))
    resolution = load_grid(sphere_file).resolution
    assert main(["evaluate", str(sphere_file), "--edit", str(sphere_file), "a hat", str(mask), "--object", "ball",
                 "--out", str(tmp_path / "e"), "--clip-model", str(tmp_path / "no_model")]) == 2
    assert (f"{mask}: a mask of a grid of (7, 7, 7) voxels, where {resolution} was expected (a mask is of its "
            "initial grid" in capsys.readouterr().err)


def test_evaluate_refuses_a_text_clip_cannot_read_before_loading_anything(sphere_file, tmp_path, capsys):
    """An object name or prompt too long for CLIP's 77 tokens had been refused by the scorer's tokenizer only after
    the grids, the images and the CLIP model had been loaded (here: a missing model was said first)."""
    long_object = "-".join("a" * 50)  # "a render of a a-a-...-a": 105 tokens at least
    for edit_prompt, object_name, what in (("a hat", long_object, "the source text"),
                                           ("a " + "very " * 80 + "hat", "dog", "the prompt")):
        assert main(["evaluate", str(sphere_file), "--edit", str(sphere_file), edit_prompt, "--object", object_name,
                     "--out", str(tmp_path / "e"), "--clip-model", str(tmp_path / "no_model")]) == 2
        err = capsys.readouterr().err
        assert f"{what} is at least" in err and "model not available" not in err
    assert not (tmp_path / "e").exists()


@pytest.mark.parametrize("command,what", [
    (["edit", "no_grid.safetensors", "--out", "e", "--prompt", "a dog<|endoftext|> in a hat"], "the edit prompt"),
    (["refine", "no_edit.safetensors", "--initial", "no_grid.safetensors", "--out", "r", "--edit-words", "hat",
      "--prompt", "<|startoftext|>a dog in a hat"], "the edit prompt"),
    (["evaluate", "no_grid.safetensors", "--edit", "no_edit.safetensors", "a dog in a hat<|endoftext|>", "--object",
      "dog", "--out", "v"], "the prompt of no_edit.safetensors"),
    (["evaluate", "no_grid.safetensors", "--edit", "no_edit.safetensors", "a dog in a hat", "--object",
      "dog<|endoftext|>", "--out", "v"], "--object"),
])
def test_a_text_writing_out_clips_special_tokens_is_refused_before_anything_is_read(command, what, tmp_path,
                                                                                      monkeypatch, capsys):
    """As the service refuses it (api.schemas.clean_text): the CLI had taken a prompt CLIP reads as ending (or
    starting) at the token written out, and run a whole edit, refinement or evaluation towards it."""
    monkeypatch.chdir(tmp_path)
    assert main(command) == 2
    err = capsys.readouterr().err
    assert f"{what} contains '<|" in err and "which the model reads as the start or end of its text" in err
    assert "no_grid" not in err.replace(what, "") and list(tmp_path.iterdir()) == []


def test_an_evaluation_md_is_utf8_under_an_ascii_locale(sphere_file, tmp_path):
    """evaluation.md had been written in the locale's encoding: under an ASCII (or Latin-1) one the evaluation failed
    once done ("'ascii' codec can't encode character '\\u2013'", the table's "–", exit 2), whatever the prompts."""
    from voxe_core.tiny_eval import build_tiny_clip

    out = tmp_path / "eval"
    argv = ["evaluate", str(sphere_file), "--object", "ball", "--out", str(out), "--size", "16", "--views", "2", "-q",
            "--clip-model", str(build_tiny_clip(tmp_path / "clip")), "--edit", str(sphere_file), "a café ☕"]
    result = under_an_ascii_locale([sys.executable, "-c", f"import sys; from voxe_core.cli import main; "
                                                          f"sys.exit(main({ascii(argv)}))"])
    assert result.returncode == 0, result.stderr
    table = (out / "evaluation.md").read_bytes().decode("utf-8")
    assert "a café ☕" in table and "–" in table
    assert json.loads((out / "evaluation.json").read_bytes())["object"] == "ball"


def test_evaluate_into_an_earlier_output_leaves_no_stale_ring_renders(sphere_file, tmp_path):
    from voxe_core.tiny_eval import build_tiny_clip

    clip = build_tiny_clip(tmp_path / "clip")  # SMOKE-TEST MODEL: plumbing only
    out = tmp_path / "eval"

    def evaluate(views: int, edits: int) -> None:
        command = ["evaluate", str(sphere_file), "--object", "ball", "--out", str(out), "--clip-model", str(clip),
                   "--views", str(views), "--size", "16", "-q"]
        assert main(command + ["--edit", str(sphere_file), "a claymation ball"] * edits) == 0

    evaluate(views=3, edits=2)
    ring = out / "ring"
    (ring / "initial" / "notes.txt").write_text("mine")
    (ring / "mine").mkdir()
    (ring / "mine" / "000.png").write_bytes(b"mine")
    evaluate(views=2, edits=1)
    assert sorted(p.name for p in ring.iterdir()) == ["edit00", "initial", "mine"]  # edit01 of the first run gone
    assert sorted(p.name for p in (ring / "initial").iterdir()) == ["000.png", "001.png", "notes.txt"]
    assert sorted(p.name for p in (ring / "edit00").iterdir()) == ["000.png", "001.png"]
    assert (ring / "mine" / "000.png").read_bytes() == b"mine"  # not a name this command writes
    assert json.loads((out / "evaluation.json").read_text())["ring"]["views"] == 2



def test_an_evaluation_that_fails_leaves_the_earlier_ring_renders_and_nothing_of_its_own(sphere_file, tmp_path,
                                                                                      monkeypatch):
    """Each ring is saved as it is scored (not all held to the end), into a staging folder beside --out's: a run that
    fails after ring views were saved (G_i's and the edit's first) leaves the earlier run's renders as they were,
    and no staging folder; a killed run's staging folder (a full ring a grid) goes at the next run."""
    import voxe_core.evaluate
    from voxe_core.tiny_eval import build_tiny_clip

    clip = build_tiny_clip(tmp_path / "clip")  # SMOKE-TEST MODEL: plumbing only
    out = tmp_path / "eval"
    command = ["evaluate", str(sphere_file), "--object", "ball", "--out", str(out), "--clip-model", str(clip),
               "--size", "16", "-q", "--edit", str(sphere_file), "a claymation ball"]
    (out / ".evaluate-staging" / "initial").mkdir(parents=True)
    (out / ".evaluate-staging" / STAGING_MARKER).write_text("voxe evaluate's")
    (out / ".evaluate-staging" / "initial" / "000.png").write_bytes(b"a killed run's")
    assert main(command + ["--views", "2"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["evaluation.json", "evaluation.md", "ring"]
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def failing(*args, **kwargs):
        raise RuntimeError("the disk is gone")

    monkeypatch.setattr(voxe_core.evaluate, "ssim", failing)  # scoring the first pair, once both are saved
    with pytest.raises(RuntimeError, match="the disk is gone"):
        main(command + ["--views", "3"])
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in out.iterdir()) == ["evaluation.json", "evaluation.md", "ring"]


@pytest.mark.parametrize("smoke_test", [True, False])
def test_commands_writing_from_a_smoke_test_edit_carry_its_note(sphere_grid, tmp_path, capsys, smoke_test):
    """A grid `voxe edit` made with the random-weight tiny model carries a `smoke_test` note, which loading passes
    over: convert-grid's rewritten grid and render's manifest had dropped it, and render, turntable and export-mesh
    said nothing. Each now says so once on stderr and carries the note where it writes a grid or a manifest; a grid
    without the note, neither."""
    from voxe_core.backbones import grid_notes

    note = "sd is a random-weight smoke-test Stable Diffusion (voxe build-tiny-model): plumbing only"
    grid = tmp_path / "edited.safetensors"
    sphere_grid.save(grid, notes={"smoke_test": note} if smoke_test else None)
    for command in (["convert-grid", str(grid), "--out", str(tmp_path / "dense.safetensors"), "--dense"],
                    ["render", str(grid), "--ring", "2", "--size", "8", "--out", str(tmp_path / "views")],
                    ["turntable", str(grid), "--frames", "2", "--size", "16", "--out", str(tmp_path / "t.gif")],
                    ["export-mesh", str(grid), "--resolution", "16", "--out", str(tmp_path / "m.ply")]):
        assert main([*command, "--quiet", "--device", "cpu"] if command[0] != "convert-grid"
                    else [*command, "--quiet"]) == 0, command
        said = [line for line in capsys.readouterr().err.splitlines() if "SMOKE TEST" in line]
        assert said == ([f"voxe {command[0]}: SMOKE TEST: {grid} was edited with a smoke-test model: {note}"]
                        if smoke_test else []), command
    assert grid_notes(tmp_path / "dense.safetensors") == ({"smoke_test": note} if smoke_test else {})
    manifest = json.loads((tmp_path / "views" / "render.json").read_text())
    assert manifest.get("smoke_test") == (note if smoke_test else None)
