"""Tensor files without pickle: safetensors plus a JSON header with a format version.

The authors' checkpoints pickled Python objects (unsafe, and unloadable on
torch >= 2.6). Every file here is plain tensors and a versioned JSON header.
"""

from __future__ import annotations

import json
import numbers
import os
import re
import stat
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from voxe_core.files import replacing, unreadable_file

HEADER_KEY = "voxe"
OS_ERROR_NUMBER = re.compile(r"\(os error (\d+)\)")
"""How safetensors (Rust's ``std::io::Error``) ends the text of a failed write: its only trace of the errno."""


class FormatError(ValueError):
    """A tensor file that is not ours, is damaged, or is from a newer format version."""


@contextmanager
def safetensors_name(path: str | os.PathLike) -> Iterator[str]:
    """The name safetensors reads ``path`` by while the block runs: its own, unless that is no valid UTF-8 (a file
    named in another encoding, "\xe9.safetensors" for Latin-1's é), which safetensors refuses to open ("Path ... is
    not valid UTF-8") though it writes it: then the file is opened here and read through its descriptor's name.
    Such a grid had been written by ``voxe mesh-to-grid`` and then refused by every command as "not a readable
    safetensors file" (``voxe convert-grid`` exiting 2 with its output written)."""
    name = os.fspath(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        descriptor = os.open(name, os.O_RDONLY)
        try:
            yield f"/dev/fd/{descriptor}"
        finally:
            os.close(descriptor)
        return
    yield name


def config_recipe(config, left_out: Iterable[str]) -> dict:
    """A stage config's recipe as JSON values: every field but ``left_out``, its ``render`` by the render's own
    ``recipe()`` (what a checkpoint records, and :func:`recipe_changes` compares)."""
    fields = {**asdict(config), "render": config.render.recipe()}
    for name in left_out:
        del fields[name]
    return json.loads(json.dumps(fields, default=_plain_number))


def _plain_number(value):
    """A numpy number as the Python one JSON writes (the configs take them: np.float32(0.01) as an lr had passed
    EditConfig's checks and failed the edit as it began, "Object of type float32 is not JSON serializable")."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


def is_number(value) -> bool:
    """Whether ``value`` is a real number (numpy floats are; True and False, JSON's true and false, are not)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_numbers(config, names: Iterable[str]) -> None:
    """ValueError naming the first of ``config``'s real-valued settings ``names`` that is no number
    (:func:`is_number`): a string or None had failed a range test naming no setting ("'<' not supported between
    instances of 'int' and 'str'"), and True had run as 1."""
    for name in names:
        if not is_number(value := getattr(config, name)):
            raise ValueError(f"{name} must be a number, got {value!r}")


def check_flags(config, names: Iterable[str]) -> None:
    """ValueError naming the first of ``config``'s switches ``names`` that is not True or False: a string had run as
    the opposite of what was asked (view_words="false", a true string)."""
    for name in names:
        if not isinstance(value := getattr(config, name), bool):
            raise ValueError(f"{name} takes True or False, got {value!r}")


def recipe_changes(path: str | os.PathLike, meta: dict, config) -> list[str]:
    """What of ``config.recipe()`` (the fields a resumed run must share with its checkpoint's) differs from the
    recipe the checkpoint at ``path``, of ``meta``, was made with ("name old (now new)"); none for a checkpoint older
    than recipes. FormatError for a recipe that is no JSON object (an AttributeError had failed the worker's stage,
    which starts over from a damaged checkpoint)."""
    now = config.recipe()
    made_with = meta.get("recipe", now)
    if not isinstance(made_with, dict):
        raise FormatError(f"{path}: damaged checkpoint: its recipe is a {type(made_with).__name__}, not an object")
    return [f"{name} {made_with.get(name)!r} (now {now[name]!r})" for name in now if made_with.get(name) != now[name]]


def save_tensors(path: str | os.PathLike, tensors: dict[str, torch.Tensor], kind: str, version: int, meta: dict) -> None:
    """Write atomically (:func:`voxe_core.files.replacing`) so a crash never leaves a torn file. OSError naming the
    path when it cannot be written (safetensors' own error type had reached the CLI as a traceback), with the
    system's errno where there is one (:func:`_write_error`)."""
    path = Path(path)
    header = json.dumps({"kind": kind, "format_version": version, "meta": meta}, sort_keys=True)
    with replacing(path) as partial:
        partial.touch()  # the mode a new file gets here (the umask's): safetensors renames its own 0600 file into place
        mode = stat.S_IMODE(partial.stat().st_mode)
        try:
            save_file({k: v.detach().contiguous().cpu() for k, v in tensors.items()}, str(partial),
                      metadata={HEADER_KEY: header})
        except SafetensorError as exc:
            raise _write_error(path, exc) from exc
        os.chmod(partial, mode)


def _write_error(path: Path, exc: SafetensorError) -> OSError:
    """safetensors' failed write of ``path`` as the OSError the system gave it: its errno, read back from the text,
    and ``path`` as its filename (a full disk had been an OSError of words alone, ``path`` among them: a caller's
    ENOSPC check missed it, and could not say it without the path). Without an errno in the text, the words alone."""
    number = OS_ERROR_NUMBER.search(str(exc))
    if number is None:
        return OSError(f"cannot write {path}: {exc}")
    return OSError(int(number[1]), os.strerror(int(number[1])), str(path))


def load_tensors(path: str | os.PathLike, kind: str, max_version: int) -> tuple[dict[str, torch.Tensor], dict]:
    """Read a file written by :func:`save_tensors`; returns (tensors, meta)."""
    meta = load_header(path, kind, max_version)
    try:
        with safetensors_name(path) as name:
            tensors = load_file(name)
    except (SafetensorError, OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable safetensors file ({exc})") from exc
    return tensors, meta


def load_header(path: str | os.PathLike, kind: str, max_version: int) -> dict:
    """The meta of a file written by :func:`save_tensors`, read from its header alone, no tensor: safetensors checks
    there that the tensors' declared offsets cover the file exactly, so a truncated or padded file fails here as in
    :func:`load_tensors`."""
    path = Path(path)
    if problem := unreadable_file(path):  # (safetensors had said "No such file or directory" of an unreadable one)
        raise FormatError(f"{path}: {problem}")
    try:
        from safetensors import safe_open

        with safetensors_name(path) as name, safe_open(name, framework="pt") as handle:
            raw_header = (handle.metadata() or {}).get(HEADER_KEY)
    except (SafetensorError, OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable safetensors file ({exc})") from exc
    if raw_header is None:
        raise FormatError(f"{path}: missing the '{HEADER_KEY}' header; not a Vox-E file")
    try:  # a damaged header is the file's error, named (it had been an AttributeError or json's bare message)
        header = json.loads(raw_header)
        if not isinstance(header, dict):  # a list had been named by Python's "'list' object has no attribute 'get'"
            raise TypeError(f"it is a {type(header).__name__}, not an object")
        version = header.get("format_version")
        meta = header.get("meta", {})
        if isinstance(version, bool) or not isinstance(version, int):  # JSON's true had read as version 1, "2" as 2
            raise TypeError(f"its format_version {version!r} is not a whole number")
        if not isinstance(meta, dict):
            raise TypeError(f"its meta is a {type(meta).__name__}")
    except (ValueError, TypeError) as exc:
        raise FormatError(f"{path}: damaged '{HEADER_KEY}' header ({exc})") from None
    except RecursionError:  # (it had escaped as itself, a traceback)
        raise FormatError(f"{path}: damaged '{HEADER_KEY}' header (its JSON nests too deeply)") from None
    if header.get("kind") != kind:
        raise FormatError(f"{path}: holds a '{header.get('kind')}', expected a '{kind}'")
    if version < 1:
        raise FormatError(f"{path}: format version {version} is none a voxe_core wrote "
                          "(they start at 1): a damaged header")
    if version > max_version:
        raise FormatError(
            f"{path}: format version {version} is newer than this voxe_core supports ({max_version}); upgrade voxe_core"
        )
    return meta
