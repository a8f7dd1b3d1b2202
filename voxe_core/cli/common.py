"""What every ``voxe`` command shares: exit codes, Ctrl-C as cancellation, progress bars, option types, dataset views.

Nothing here imports torch, so ``voxe --help`` stays instant; the commands import the library where they run.
"""

from __future__ import annotations

import argparse
import contextlib
import contextvars
import fcntl
import importlib
import json
import math
import os
import re
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

from voxe_core.constants import INTEGER_AS_WRITTEN
from voxe_core.presets import DOWNSAMPLE, MAX_SEED, RESAMPLE

EXIT_FAILED = 1
"""The work did not succeed: the job (or sweep) waited for ended otherwise, or the machine failed it (a full disk)."""
EXIT_USAGE = 2
EXIT_SERVICE_FAILED = 3
"""The job service failed (an error status of 500 or more) or was not reached, where ``EXIT_USAGE`` says it refused
the request (4xx): a script can try the one again later, not the other."""
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 128 + signal.SIGTERM
"""SIGTERM (``docker stop``, ``timeout``, systemd) stopped the command, cancelled and cleaned up as Ctrl-C does: the
status a shell gives 128 + the signal's number (143), where Ctrl-C's is 130."""
EXIT_OUTPUT_CLOSED = 141
"""The output's reader stopped reading (``voxe status J | head -c 10``): the status a shell reports for ``cat`` or
``seq`` ended there by SIGPIPE (128 + 13), said nothing about."""


def write_json(path: Path, record: dict) -> None:
    """``record`` as indented JSON in UTF-8, its text as written ("a café"), as ``voxe status`` prints it: the
    files had escaped it ("a caf\\u00e9", ``json.dumps``' default) where stdout did not."""
    path.write_text(json.dumps(record, indent=2, ensure_ascii=False), encoding="utf-8")


INTERRUPT_CHECK_S = 0.1
"""How often a pause looks whether Ctrl-C was pressed."""


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""Ctrl-C, and what ``docker stop``, ``timeout`` and systemd send: either cancels a command cleanly (a SIGTERM had
killed it at once, its hidden partial files such as ``.spot.<token>.partial.mp4`` left in the output folder)."""

_stop_signals_received: list[int] = []
"""The stop signals the running command received (``sigterm_as_ctrl_c`` starts each command with none)."""


def interrupted_status() -> int:
    """The exit status of a command cancelled by a stop signal: 143 where a SIGTERM came, 130 (Ctrl-C) otherwise."""
    return EXIT_TERMINATED if signal.SIGTERM in _stop_signals_received else EXIT_INTERRUPTED


class Interrupt:
    """A stop signal (Ctrl-C, SIGTERM) sets a flag that a stage polls through ``Callbacks.should_cancel``; a second
    one aborts at once."""

    def __init__(self):
        self.requested = False

    def __call__(self) -> bool:
        return self.requested

    def _handle(self, signum, frame):
        _stop_signals_received.append(signum)
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        said, again = ("interrupt", "Ctrl-C") if signum == signal.SIGINT else (signal.Signals(signum).name,) * 2
        print(f"\nvoxe: {said} received, stopping after this step ({again} again to abort)", file=sys.stderr)

    def sleep(self, seconds: float) -> None:
        """Pause ``seconds``, or until a stop signal: a signal handler that returns resumes ``time.sleep``, and ``voxe
        sweep --wait --poll 600`` had answered a Ctrl-C only at the end of its 10-minute pause."""
        end = time.monotonic() + seconds
        while not self.requested and (left := end - time.monotonic()) > 0:
            time.sleep(min(left, INTERRUPT_CHECK_S))

    @contextlib.contextmanager
    def installed(self) -> Iterator["Interrupt"]:
        with _handling(STOP_SIGNALS, self._handle):
            yield self


def _sigterm_as_ctrl_c(signum, frame):
    _stop_signals_received.append(signum)
    raise KeyboardInterrupt


@contextlib.contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """A command's run: outside a stage, SIGTERM raises KeyboardInterrupt as Ctrl-C does (Python's default), so
    cleanup runs (its own default had killed the process at once); ``interrupted_status`` then says which came."""
    _stop_signals_received.clear()
    with _handling((signal.SIGTERM,), _sigterm_as_ctrl_c):
        yield


@contextlib.contextmanager
def _handling(signums: tuple[int, ...], handler) -> Iterator[None]:
    """``signums`` handled by ``handler`` inside the block, the previous handlers back after it (signal handlers can
    only be set from the main thread: elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, handler) for signum in signums}
    try:
        yield
    finally:
        for signum, earlier in previous.items():
            signal.signal(signum, earlier)


PROGRESS_INTERVAL_S = 0.1  # tqdm's own, on a terminal
LOG_PROGRESS_INTERVAL_S = 30.0
"""Off a terminal (a log file, CI) a bar is redrawn at most this often: 10 redraws a second had written 3.8 MB an hour
of carriage-returned lines."""


@contextlib.contextmanager
def progress_callbacks(
    desc: str, unit: str = "it", should_cancel=None, quiet: bool = False, total: int | None = None
):
    """Callbacks whose ``on_progress`` drives one tqdm bar (total and losses taken from each report) and whose
    ``on_warning`` prints ``voxe DESC: warning: ...`` on stderr. The bar's
    rate, and so its time left, counts the steps done since its first report: a resumed stage's first report stands
    where its checkpoint did, and counted as done in the moment it took had shown several times the real rate."""
    from tqdm import tqdm

    from voxe_core.progress import Callbacks, Progress

    terminal = sys.stderr.isatty()  # (off one, tqdm's monitor would still force a redraw every 10 s: maxinterval)
    bar = tqdm(desc=desc, unit=unit, total=total, disable=quiet, dynamic_ncols=True, file=sys.stderr,
               mininterval=PROGRESS_INTERVAL_S if terminal else LOG_PROGRESS_INTERVAL_S,
               **({} if terminal else {"maxinterval": LOG_PROGRESS_INTERVAL_S}))

    reported = False

    def on_progress(report: Progress) -> None:
        nonlocal reported
        if bar.total != report.total:
            bar.total = report.total
        if not reported and not bar.disable:  # the first report: where the stage starts from
            bar.initial = bar.n = bar.last_print_n = report.iteration
        reported = True
        postfix = {k: f"{v:.4f}" for k, v in report.losses.items()}
        for key in ("stage", "resolution"):
            if key in report.info:
                postfix[key] = report.info[key]
        if postfix:
            bar.set_postfix(postfix, refresh=False)
        bar.update(report.iteration - bar.n)

    def on_warning(stage: str, text: str) -> None:  # (even with --quiet; above the bar, which tqdm draws again)
        bar.write(f"voxe {desc}: warning: {text if stage == desc else f'{stage}: {text}'}", file=sys.stderr)

    try:
        yield Callbacks(on_progress=on_progress, should_cancel=should_cancel, on_warning=on_warning)
    finally:
        bar.close()


LIBRARY_BAR_SWITCHES = ("transformers.utils.logging", "diffusers.utils.logging")
"""Modules whose ``is_progress_bar_enabled`` / ``enable_progress_bar`` / ``disable_progress_bar`` switch the bars
their library draws on its own (transformers' "Loading weights", diffusers' "Loading checkpoint shards")."""
_LIBRARY_BARS_OFF: contextvars.ContextVar[bool] = contextvars.ContextVar("library_bars_off", default=False)


@contextlib.contextmanager
def library_progress_bars_off(quiet: bool) -> Iterator[None]:
    """With ``quiet`` (``--quiet``), no progress bar of Hugging Face's libraries in the block, then all as before.

    huggingface_hub's switch (its downloads) is read by transformers as it is imported, so transformers is quiet
    whenever the block imports it; a :data:`LIBRARY_BAR_SWITCHES` module already imported is switched off here, and
    diffusers, which reads no switch as it is imported, by :func:`quiet_library` where it is imported (importing it
    takes seconds: ``voxe status`` must not). After the block, a library it imported is as the hub's switch says.
    """
    if not quiet:
        yield
        return
    from huggingface_hub.utils import are_progress_bars_disabled, disable_progress_bars, enable_progress_bars

    hub_was_on = not are_progress_bars_disabled()
    disable_progress_bars()
    was_on = {name: sys.modules[name].is_progress_bar_enabled() for name in LIBRARY_BAR_SWITCHES
              if name in sys.modules}
    for name in was_on:
        sys.modules[name].disable_progress_bar()
    token = _LIBRARY_BARS_OFF.set(True)
    try:
        yield
    finally:
        _LIBRARY_BARS_OFF.reset(token)
        if hub_was_on:
            enable_progress_bars()
        for name in LIBRARY_BAR_SWITCHES:
            if name in sys.modules:
                switch = sys.modules[name]
                switch.enable_progress_bar() if was_on.get(name, hub_was_on) else switch.disable_progress_bar()


def quiet_library(name: str) -> None:
    """Inside :func:`library_progress_bars_off` (a ``--quiet`` command), the :data:`LIBRARY_BAR_SWITCHES` module
    ``name`` imported and switched off too, before the command loads a model through it; elsewhere nothing."""
    if _LIBRARY_BARS_OFF.get():
        importlib.import_module(name).disable_progress_bar()


def run_stage(fn, desc: str, unit: str, total: int | None, quiet: bool = False):
    """Run ``fn(callbacks)`` under a progress bar with Ctrl-C wired to cancellation.

    Returns what ``fn`` returns, or None when the user interrupted it (the
    stage raised ``StageCancelled`` at its next cancellation check).
    """
    from voxe_core.progress import StageCancelled

    interrupt = Interrupt()
    with interrupt.installed(), progress_callbacks(desc, unit, interrupt, quiet, total) as callbacks:
        try:
            return fn(callbacks)
        except StageCancelled:
            return None


MAX_COUNT = 2**31 - 1
"""The largest count an integer option takes (sizes, views, frames, iterations, rays...): past 64 bits torch had
said only "int too big to convert" (``voxe turntable --frames 99999999999999999999``: no option named), and near
them failed in its own words ("cannot be represented as a SymInt", a traceback). Up to it, a count too large for
the machine is said as out of memory, naming what to ask less of (or takes as long as it asks: Ctrl-C stops it)."""


def _at_most_max_count(value: int) -> int:
    if value > MAX_COUNT:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_COUNT}, got {value}")
    return value


def _integer(text: str) -> int:
    """An integer option as written (``constants.INTEGER_AS_WRITTEN``: the digits 0-9, an optional minus), as the
    service reads a query's integers. ``int`` had taken ``1_0`` as 10, ``+5`` and `` 5`` as 5 and ``５`` (full width)
    as 5: a typo run as though it were meant."""
    if not INTEGER_AS_WRITTEN.fullmatch(text):
        raise argparse.ArgumentTypeError(f"expected a whole number written in the digits 0-9, got {text!r}")
    try:
        return int(text)
    except ValueError:  # past Python's int-string limit
        raise argparse.ArgumentTypeError(f"has more than {sys.get_int_max_str_digits()} digits") from None


def int_list(text: str) -> list[int]:
    """One integer or a comma-separated list of them (spaces around the commas allowed), each as ``_integer``."""
    items = [v.strip() for v in text.split(",") if v.strip()]
    if not all(INTEGER_AS_WRITTEN.fullmatch(v) for v in items):
        raise argparse.ArgumentTypeError(f"expected an integer or a comma-separated list of integers written in the "
                                         f"digits 0-9, got {text!r}")
    values = [_integer(v) for v in items]
    if not values or any(v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected non-negative integers, got {text!r}")
    for value in values:
        _at_most_max_count(value)
    return values


def one_or_list(values: list[int] | None) -> int | list[int] | None:
    """An ``int_list`` option as the job parameters write it: one value as an int (so both share a cache key)."""
    return values[0] if values is not None and len(values) == 1 else values


def whole_number(text: str) -> int:
    """A count whose range a config checks (``said_by_option``): its option type had said a second, narrower rule
    (``voxe evaluate --views 0``: "must be at least 1", then ``--views 1``: "needs at least 2")."""
    return _at_most_max_count(_integer(text))


def positive_int(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return _at_most_max_count(value)


def positive_int_at_most(limit: int) -> Callable[[str], int]:
    """The option type of a positive whole number up to ``limit``, the service's bound for the same parameter: beyond
    it the CLI had run what a job's parameters refuse (``voxe refine --views 100000`` rendered every view)."""
    def whole_number(text: str) -> int:
        value = positive_int(text)
        if value > limit:
            raise argparse.ArgumentTypeError(f"must be at most {limit} (the service's limit), got {value}")
        return value
    return whole_number


def int_list_at_most(limit: int, last_at_least: int = 0) -> Callable[[str], list[int]]:
    """The option type of an ``int_list`` whose values are each at most ``limit``, and whose last (a final stage's) is
    at least ``last_at_least``, the service's bounds for the same parameter (as :func:`positive_int_at_most`):
    ``voxe reconstruct --resolution 5000`` had been taken, and ``--resolution 2``, which a job refuses."""
    def integers(text: str) -> list[int]:
        values = int_list(text)
        if max(values) > limit:
            raise argparse.ArgumentTypeError(f"must be at most {limit} (the service's limit), got {max(values)}")
        if values[-1] < last_at_least:
            said = "must be" if len(values) == 1 else "its last value (the final stage's) must be"
            raise argparse.ArgumentTypeError(f"{said} at least {last_at_least} (the service's limit), got "
                                             f"{values[-1]}")
        return values
    return integers


_DECIMAL = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?")


def _decimal(text: str) -> float:
    """A real-valued option as written: a decimal number of the digits 0-9 (``0.5``, ``.5``, ``5e-3``), or NaN where
    it is none. ``float`` had taken ``1_0`` as 10, `` 5`` as 5 and ``５`` (full width) as 5, as ``int`` had for the
    integer options (:func:`_integer`)."""
    return float(text) if _DECIMAL.fullmatch(text) else math.nan


def positive_seconds(text: str) -> float:
    value = _decimal(text)
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text!r}")
    return value


def non_negative_seconds(text: str) -> float:
    """Seconds where 0 means "not at all" (``--reconnect-for 0``: give up at the first loss, as
    ``Client.wait(reconnect_for=0)`` does; positive_seconds had refused it)."""
    value = _decimal(text)
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be 0 or a positive number of seconds, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A real-valued option, refused naming the option where it is no finite number (``inf``, ``nan``, ``1e400``): the
    setting it fills had refused it naming its own field, which no option is called (``--reg-weight inf``:
    "regulariser_weight must be >= 0 and finite in float32")."""
    value = _decimal(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


@contextlib.contextmanager
def said_by_option(options: dict[str, str]) -> Iterator[None]:
    """The config's range checks (their one source) refusing a setting of ``options`` (setting: option), said naming
    the option typed: ``voxe edit --reg-weight -1`` had been refused as "regulariser_weight must be >= 0 ...", a
    setting no option is called (finite_float names it only for a value that is no finite number). A setting may be
    said in words ("grid resolutions must be at least 2")."""
    try:
        yield
    except ValueError as exc:
        said = str(exc)
        setting = next((setting for setting in options if said.startswith(f"{setting} must ")), None)
        if setting is None:
            raise
        raise ValueError(f"{options[setting]} {said[len(setting) + 1:]}") from None


def non_negative_int(text: str) -> int:
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return _at_most_max_count(value)


def seed(text: str) -> int:
    """A ``--seed``: the service's range, refused here rather than by torch after the data is loaded."""
    value = _integer(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be between 0 and {MAX_SEED}, got {value}")
    return value


TENSOR_FILE_SUFFIX = ".safetensors"


def tensor_file(text: str) -> Path:
    """A grid or checkpoint to write: ``voxe_core.tensorio`` writes safetensors, and a file named otherwise (``--out
    grid.txt``) had been written all the same."""
    path = Path(text)
    if path.suffix.lower() != TENSOR_FILE_SUFFIX:
        raise argparse.ArgumentTypeError(f"unsupported suffix {path.suffix!r} for {path}: grids and checkpoints are "
                                         f"safetensors files; use {TENSOR_FILE_SUFFIX}")
    return path


_MADE_FOLDERS: contextvars.ContextVar[list[Path] | None] = contextvars.ContextVar("made_folders", default=None)


@contextlib.contextmanager
def removing_made_folders_unless(succeeded) -> Iterator[None]:
    """Folders ``writable_file`` and ``writable_folder`` make in the block are removed again, the deepest first,
    when ``succeeded()`` is false after it (or it raised) and they are still empty: a command that fails on a bad
    input must not leave the --out it made behind. One that existed before, or holds anything (an edit's
    checkpoint to resume from), stays."""
    made: list[Path] = []
    token = _MADE_FOLDERS.set(made)
    ok = False
    try:
        yield
        ok = succeeded()
    finally:
        _MADE_FOLDERS.reset(token)
        if not ok:
            for folder in sorted(set(made), key=lambda p: len(p.absolute().parts), reverse=True):
                with contextlib.suppress(OSError):  # not empty (or gone): it stays
                    folder.rmdir()


def _make_folder(path: Path) -> None:
    """``path`` made with its parents, those made noted for ``removing_made_folders_unless``; an OSError naming the
    file in the way, or the reason (``--out notes.txt/grid.safetensors`` had said "[Errno 17] File exists:
    'notes.txt'"), with the system's errno kept: a full disk or quota is the machine's failure, exit 1 (the words
    alone, no errno, had exited 2, "bad input")."""
    missing = [folder for folder in (path, *path.parents) if not folder.exists()]
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        in_the_way = next((folder for folder in (path, *path.parents) if folder.exists() and not folder.is_dir()), None)
        error = OSError(f"cannot make the folder {path}: " + (f"{in_the_way} is a file, not a folder" if in_the_way
                                                              else (exc.strerror or str(exc)).lower()))
        error.errno = exc.errno  # (set, not passed: the message stays without "[Errno N]")
        raise error from None
    made = _MADE_FOLDERS.get()
    if made is not None:
        made.extend(missing)


def writable_file(path: Path) -> Path:
    """``path`` with its folder made, or OSError now when it cannot be written (before a long stage, not after). A
    symlink's target is what is written (:func:`voxe_core.files.replacing`): its folder is the one checked."""
    _make_folder(path.parent)
    target = Path(os.path.realpath(path))
    if path.is_dir():
        raise OSError(f"cannot write {path}: it is a folder")
    if not os.access(target.parent, os.W_OK):
        if target.parent == path.parent.resolve():
            raise OSError(f"cannot write {path}: its folder is not writable")
        raise OSError(f"cannot write {path}: it links to {target}, whose folder is "
                      + ("not writable" if target.parent.is_dir() else "missing"))
    return path


def writable_folder(path: Path) -> Path:
    """``path`` made as a folder, or OSError now when it cannot be one (before a long stage, not after)."""
    if path.exists() and not path.is_dir():
        raise OSError(f"cannot write into {path}: it is a file, not a folder")
    _make_folder(path)
    if not os.access(path, os.W_OK):
        raise OSError(f"cannot write into {path}: the folder is not writable")
    return path


STAGING_MARKER = ".voxe-staging"
"""The file a command writes into the staging folder it makes: a folder of that name without it is not ours."""


@contextlib.contextmanager
def staging_folder(out: Path, command: str) -> Iterator[Path]:
    """``out/.<command>-staging``, emptied, where a command saves its views as it makes them until all are made, then
    moves them over the earlier run's: a cancelled or failed run leaves those as they were, not a mix of two runs'.
    One name a command, so a killed run's (a whole ring of views) goes at the next run's start; held locked while in
    use, so a second run into the same --out is refused rather than emptying the first's; gone on leaving. Marked
    (:data:`STAGING_MARKER`) when made: a folder of that name holding files but no mark is the user's, and is
    refused rather than emptied (a user's own ``.render-staging`` had been). An OSError naming a file in it names
    the file of ``out`` it stands for: a full disk had been said of ``views/.render-staging/000.png``, a path the user
    never asked for, not ``views/000.png``."""
    staging = out / f".{command}-staging"
    staging.mkdir(exist_ok=True)
    held = os.open(staging, os.O_RDONLY)
    try:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(held)
        raise OSError(f"another voxe {command} is writing into {out}: let it end, or choose another --out") from None
    marker = staging / STAGING_MARKER
    if not marker.is_file() and any(staging.iterdir()):  # (one left empty, by a run killed as it made it, is ours)
        os.close(held)
        raise OSError(f"{staging} is not a staging folder voxe {command} made (it has no {STAGING_MARKER} file), "
                      "and voxe would empty it: move it away, or choose another --out")
    try:
        marker.write_text(f"voxe {command}'s staging folder: emptied by its next run\n", encoding="utf-8")
        for leftover in staging.iterdir():  # a killed run's
            if leftover != marker:
                shutil.rmtree(leftover) if leftover.is_dir() and not leftover.is_symlink() else leftover.unlink()
        yield staging
    except OSError as exc:
        if isinstance(exc.filename, str) and exc.filename2 is None and Path(exc.filename).is_relative_to(staging):
            exc.filename = str(out / Path(exc.filename).relative_to(staging))  # (a move's names both: left as is)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        os.close(held)


def move_staged(staging: Path, out: Path, summaries: tuple[str, ...], clear_earlier: Callable[[], None]) -> None:
    """Move the whole set of outputs ``staging`` holds (every file but its mark) to the same paths under ``out``, over
    an earlier run's. The earlier ``summaries`` go first, then what ``clear_earlier`` removes (the earlier run's files
    this run may not replace), so a move failing part way leaves no summary beside a mix of two runs' files;
    ``summaries`` come last, the last of them last: where it is, the set is whole."""
    for name in summaries:
        (out / name).unlink(missing_ok=True)
    clear_earlier()
    last = [staging / name for name in summaries]
    for path in sorted(staging.rglob("*")):
        if path.is_file() and path.name != STAGING_MARKER and path not in last:
            target = out / path.relative_to(staging)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, target)
    for path in last:
        os.replace(path, out / path.name)


def remove_earlier_outputs(folder: Path, names: re.Pattern) -> None:
    """Delete the files in ``folder`` whose names ``names`` matches in full: those an earlier run of the command
    wrote, which a re-run into the same --out writing fewer would otherwise leave beside its own. Other files stay."""
    if folder.is_dir():
        for path in folder.iterdir():
            if path.is_file() and names.fullmatch(path.name):
                path.unlink()


def add_grid_output_arguments(parser: argparse.ArgumentParser) -> None:
    """How a command writes its grid files: sparse (occupied cells + margin, ``voxe_core.gridfile``) or dense."""
    parser.add_argument("--dense", action="store_true",
                        help="write grids with every vertex (default: sparse; voxe convert-grid converts)")


def add_view_arguments(parser: argparse.ArgumentParser, split: str) -> None:
    """Which dataset images a command reads, and how they are downsampled on load (the job parameters' defaults)."""
    options = [
        parser.add_argument("--split", default=split),
        parser.add_argument("--downsample", type=positive_int, default=DOWNSAMPLE,
                            help=f"integer image downsampling on load (default {DOWNSAMPLE}: the paper's 800 px at "
                                 "266)"),
        # voxe_core.data.RESAMPLE_FILTERS, spelt out: importing it here would load torch for --help.
        parser.add_argument("--resample", choices=("bilinear", "box"), default=RESAMPLE,
                            help="the downsampling's antialiasing filter (bilinear: as the authors' loader)"),
        parser.add_argument("--max-images", type=positive_int, default=None, help="use only the first N images"),
    ]
    parser.set_defaults(view_options={option.option_strings[0]: (option.dest, option.default) for option in options})


def view_options_given(args: argparse.Namespace) -> list[str]:
    """The options of ``add_view_arguments`` that ``args`` sets away from their defaults: a command that reads no
    dataset refuses them rather than ignore them."""
    return [flag for flag, (dest, default) in args.view_options.items() if getattr(args, dest) != default]


def add_model_arguments(parser: argparse.ArgumentParser, flag: str, what: str, default: str) -> None:
    """Which weights a command loads (``flag``, e.g. ``--model``; ``what`` they are) and where it runs them."""
    parser.add_argument(flag, default=None, metavar="MODEL_ID_OR_PATH",
                        help=f"{what}: hub id (from the local cache) or folder (default {default})")
    parser.add_argument("--offline", action="store_true", help="never contact the hub (as HF_HUB_OFFLINE=1)")
    add_device_argument(parser)


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """``--device``: where a stage command computes."""
    parser.add_argument("--device", default=None, metavar="DEVICE",
                        help="cpu, cuda or cuda:N (default: cuda when available, else cpu)")


def check_device(args: argparse.Namespace):
    """``args.device`` resolved (``voxe_core.devices.resolve_device``) and written back; a ValueError
    naming the device when this machine lacks it, raised before the command reads any data."""
    from voxe_core.devices import resolve_device

    device = resolve_device(args.device)
    if device.type not in ("cpu", "cuda"):  # meta, xpu, ...: torch names them, the stages do not run there (the
        raise ValueError(f"device {str(device)!r} is not supported here: use 'cpu' or a CUDA device")  # library's
    args.device = str(device)  # tests use "meta" to see where tensors land); they had been a traceback
    return device


def load_guidance(args: argparse.Namespace, model: str, cuda_graphs: bool | None = None,
                  compile_encoder: bool | None = None):
    """The Stable Diffusion guidance ``model`` on ``args.device`` (``cuda_graphs``, ``compile_encoder``: see
    ``from_pretrained``); None, said on stderr, when its weights are missing."""
    from voxe_core.guidance.loading import ModelNotAvailableError
    from voxe_core.guidance.sds import StableDiffusionGuidance

    quiet_library("diffusers.utils.logging")
    try:
        return StableDiffusionGuidance.from_pretrained(
            model, device=args.device, local_files_only=True if args.offline else None,
            cuda_graphs=cuda_graphs, compile_encoder=compile_encoder,
        )
    except ModelNotAvailableError as exc:
        print(f"voxe {args.command}: model not available: {exc}", file=sys.stderr)
        return None


def say_smoke_test(args: argparse.Namespace, model: str) -> str | None:
    """For a ``model`` folder ``voxe build-tiny-model`` wrote (random weights), the note the run records in what it
    writes, said once on stderr as it starts; None for any other model."""
    from voxe_core.guidance.loading import smoke_test_note

    if (note := smoke_test_note(model)) is None:
        return None
    print(f"voxe {args.command}: SMOKE TEST: {note}", file=sys.stderr)
    return note


def say_grid_notes(args: argparse.Namespace, path: Path) -> dict:
    """The notes of the grid file at ``path`` (``voxe_core.backbones.grid_notes``: a smoke-test edit's), for what the
    command writes from it to carry; a smoke test's said once on stderr as it starts."""
    from voxe_core.backbones import grid_notes

    notes = grid_notes(path)
    if "smoke_test" in notes:
        print(f"voxe {args.command}: SMOKE TEST: {path} was edited with a smoke-test model: {notes['smoke_test']}",
              file=sys.stderr)
    return notes


def view_params(args: argparse.Namespace) -> dict:
    """The job parameters of the dataset options of ``add_view_arguments``."""
    return {"downsample": args.downsample, "resample": args.resample, "max_images": args.max_images}


def load_views(args: argparse.Namespace):
    from voxe_core.data import load_scene

    return load_scene(args.data, args.split, args.downsample, args.max_images, resample=args.resample)
