"""The ``voxe`` command line: a thin layer of argument parsing over voxe_core, one module per command group.

    voxe reconstruct DATA_DIR --out grid.safetensors [--preset fast|paper] ...                    (reconstruct)
    voxe render GRID --data DATA_DIR --split test --out DIR   |   --ring N --size S                (render)
    voxe turntable GRID --out turntable.mp4|.gif [--frames 100] [--size 256] [--elevation 30]    (render)
    voxe export-mesh GRID --out mesh.ply|.glb [--level L] [--resolution N]                        (mesh)
    voxe mesh-to-grid MESH --out grid.safetensors [--texture PNG] [--route voxelize|render]       (mesh)
    voxe convert-grid GRID --out grid.safetensors [--dense] [--margin N]   (sparse <-> dense)    (grids)
    voxe edit GRID --prompt TEXT --out DIR [--model ID_OR_DIR] [--iterations N] [--render-size N] ...  (edit)
    voxe build-tiny-model DIR      (random-weight SMOKE-TEST Stable Diffusion, plumbing only)     (edit)
    voxe refine EDITED_GRID --initial GRID --prompt TEXT --edit-words WORDS --out DIR ...         (refine)
    voxe evaluate GRID --edit EDITED_GRID PROMPT [MASK] ... --object NAME --out DIR ...          (evaluate)
    voxe export-mesh GRID --out mesh.obj (+ mesh.mtl beside it)                                    (mesh)
    voxe submit PROMPT --scene SCENE_ID | --upload PATH [--mode local --edit-word W] [--idempotency-key K] [--wait]
    voxe status | wait | cancel JOB_ID;  voxe download JOB_ID [--name N] --out DIR (sha256 checked) (service)
    voxe sweep --api URL --scene SCENE_ID=OBJECT ... [--params JSON] [--idempotency-key K] [--wait]     (service)
    voxe cancel-sweep SWEEP_ID    (its unfinished jobs canceled; the sweep's record as JSON)         (service)
    voxe webhook-secret [--rotate]      (the key's webhook signing secret, printed; --rotate: a new one)  (service)

Options that are job parameters of the service take their defaults from ``voxe_core.presets`` and
resolve to stage configs there, as the worker's do. Bad input (dataset, grid file, option values)
prints one line on stderr and exits 2 (a job service that failed, 5xx, or was not reached: 3);
grids are written sparse unless ``--dense``; Ctrl-C during a long stage cancels it cleanly and exits 130 (SIGTERM, as
``docker stop`` and ``timeout`` send: the same, exit 143);
output whose reader stopped reading (``voxe status J | head``) ends the command quietly with 141, as SIGPIPE ends ``cat``.
"""

from __future__ import annotations

import argparse
import codecs
import contextlib
import errno
import os
import sys
from typing import Iterator, Sequence

from voxe_core.cli import edit, evaluate, grids, mesh, reconstruct, refine, render, service
from voxe_core.cli.common import (
    EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OUTPUT_CLOSED, EXIT_USAGE, interrupted_status, library_progress_bars_off,
    removing_made_folders_unless, sigterm_as_ctrl_c,
)

COMMAND_GROUPS = (reconstruct, render, mesh, grids, edit, refine, evaluate, service)
MACHINE_FAILURES = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO)
"""The errnos of an OSError that is the machine's failure (a full disk or quota, a file size limit: RLIMIT_FSIZE,
FAT32's 4 GiB; a failing disk), not the input's: such a run exits ``EXIT_FAILED``, not 2 ("bad input"), which had
told a script to fix what it passed after a long stage ended on a full disk."""
OUT_OF_MEMORY_SAYINGS = ("can't allocate memory", "Tried to allocate", "out of memory",
                         "Storage size calculation overflowed")
"""How torch's RuntimeErrors say a tensor asked for is past the machine's memory; the last, past what a byte count
holds (``export-mesh --resolution 3000000``: it had been a traceback, exit 1)."""
STDOUT_ERRORS = "voxe.escape_unless_undecoded"
"""The name of the error handler stdout writes what its encoding lacks with (:func:`_escaped_unless_undecoded`)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="voxe", description="Vox-E voxel grids: reconstruct, render, export.")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", "-q", action="store_true",
                        help="no progress bars (nor those of the model libraries: hub downloads, weight loading)")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in COMMAND_GROUPS:
        group.add_parsers(commands, common)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``voxe``; returns the exit status (0 ok, 1 the work did not succeed: the job waited for, or
    the machine's disk full, at a file size limit or failing, 2 bad input, 3 the job service failed or was
    not reached, 130 interrupted, 143 stopped by SIGTERM, 141 its output's reader gone). A command that does not
    succeed leaves no folder it made and wrote nothing into."""
    status = None
    with _stdout_escaping_what_it_cannot_encode():  # (the help too: `voxe refine --help` had raised on a Latin-1 one)
        args = build_parser().parse_args(argv)
        with (removing_made_folders_unless(lambda: status == 0), library_progress_bars_off(args.quiet),
              sigterm_as_ctrl_c()):
            status = _run(args)
    return interrupted_status() if status == EXIT_INTERRUPTED else status


@contextlib.contextmanager
def _stdout_escaping_what_it_cannot_encode() -> Iterator[None]:
    """stdout writing a character its encoding lacks as a backslash escape, as Python's stderr does: a table naming
    "a café ☕" on a Latin-1 or ASCII stdout had raised UnicodeEncodeError once the work was done (``voxe sweep
    --wait``'s table: "error: 'latin-1' codec can't encode character", exit 2 for a sweep that succeeded), and a
    help naming λ or → (``voxe refine --help``) with a traceback, exit 1. A C locale's stdout (its handler
    surrogateescape, not strict: Python's UTF-8 mode off) had been left as it was, and raised the same."""
    stdout = sys.stdout
    errors = getattr(stdout, "errors", None)
    if errors not in ("strict", "surrogateescape") or not hasattr(stdout, "reconfigure"):
        yield
        return
    stdout.reconfigure(errors=STDOUT_ERRORS)
    try:
        yield
    finally:
        stdout.reconfigure(errors=errors)


def _escaped_unless_undecoded(error: UnicodeError) -> tuple[str | bytes, int]:
    """A character stdout's encoding lacks as its backslash escape ("\\xe9"), one that stands for a byte the locale
    could not decode (surrogateescape's, in a file name from argv) as that byte, as a C locale's stdout writes it."""
    if not isinstance(error, UnicodeEncodeError):
        raise error
    char = error.object[error.start]
    if "\udc80" <= char <= "\udcff":
        return bytes([ord(char) - 0xDC00]), error.start + 1
    return char.encode("ascii", "backslashreplace").decode("ascii"), error.start + 1


codecs.register_error(STDOUT_ERRORS, _escaped_unless_undecoded)


def _run(args: argparse.Namespace) -> int:
    """The command's exit status, its errors said in one line on stderr."""
    try:
        status = args.run(args)
        sys.stdout.flush()  # here, not as Python exits: a reader gone is then a BrokenPipeError caught below
        return status
    except BrokenPipeError:  # (an OSError: it had printed "error: [Errno 32] Broken pipe" and exited 2)
        _stdout_to_null()
        return EXIT_OUTPUT_CLOSED
    # (DatasetError and FormatError are ValueErrors, EditDiverged an ArithmeticError)
    except (ValueError, ArithmeticError, OSError) as exc:
        kind = "dataset error" if _is_dataset_error(exc) else "error"
        print(f"voxe {args.command}: {kind}: {exc}", file=sys.stderr)
        return EXIT_FAILED if isinstance(exc, OSError) and exc.errno in MACHINE_FAILURES else EXIT_USAGE
    except (MemoryError, RuntimeError) as exc:  # torch's allocators raise RuntimeErrors ("can't allocate memory")
        if not isinstance(exc, MemoryError) and not any(words in str(exc) for words in OUT_OF_MEMORY_SAYINGS):
            raise  # any other RuntimeError is a bug to see whole
        first_line = (str(exc).splitlines() or [type(exc).__name__])[0]  # Python's own MemoryError has no message
        print(f"voxe {args.command}: error: out of memory ({first_line}): ask for less (a smaller --resolution, "
              "--size, --rays or --ring)", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("\nvoxe: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _is_dataset_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a ``voxe_core.data.DatasetError``, without importing that module: it loads torch, which had
    taken seconds of every ``voxe status`` that never reads a dataset (one that raised it had imported it)."""
    data = sys.modules.get("voxe_core.data")
    return data is not None and isinstance(exc, data.DatasetError)


def _stdout_to_null() -> None:
    """Points stdout, whose reader has gone, at the null device: Python flushes what is left in its buffer as it
    exits, and into the closed pipe that had printed "Exception ignored ... BrokenPipeError"."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, ValueError, OSError):  # no file behind it (a test's capture): nothing flushed at exit
        return
    os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
