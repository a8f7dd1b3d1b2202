"""Scratch folders a process holds while it lives, and the sweep that removes those no live process holds.

A folder's ``.owner`` file is locked (flock) by the process using it; the kernel releases the lock when the process
dies, however it dies (OOM, SIGKILL, a deploy). The sweep takes the lock of each folder it judges: one it gets
belonged to a dead process. Users: the API's upload staging (``api.uploads``) and an ingest's unpacked upload
(``worker.ingest``). On a filesystem without locks (some NFS / CIFS mounts) folders are used all the same and the
sweep removes nothing.

Examples:
    >>> import tempfile
    >>> work = Path(tempfile.mkdtemp())
    >>> with locked_folder(work, "run-") as folder:
    ...     sweep_unlocked(work, "run-*"), folder.is_dir()  # held: left alone
    (0, True)
    >>> folder.exists()
    False
"""

from __future__ import annotations

import fcntl
import logging
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger("voxe.scratch")

OWNER = ".owner"


@contextmanager
def locked_folder(parent: Path, prefix: str) -> Iterator[Path]:
    """A new folder ``parent/<prefix>*``, its ``.owner`` locked while the block runs, removed on leaving. One that a
    sweep removed between its making and its locking is replaced by another."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    while True:
        folder = Path(tempfile.mkdtemp(dir=parent, prefix=prefix))
        try:
            owner = open(folder / OWNER, "ab")
        except FileNotFoundError:  # swept before it was locked: another
            continue
        try:
            fcntl.flock(owner, fcntl.LOCK_EX)
        except OSError:  # a filesystem without locks: the sweep cannot lock it either
            log.warning("scratch folders in %s cannot be locked; a killed process's stay there", parent)
        if folder.is_dir():  # (else swept before it was locked)
            break
        owner.close()
    try:
        with owner:
            yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def sweep_unlocked(parent: Path, pattern: str) -> int:
    """Remove the folders ``parent/<pattern>`` whose lock no process holds (their processes died); the count removed.
    Safe beside the live processes sharing ``parent``: their folders are locked (one swept before its process locked
    it is replaced, :func:`locked_folder`)."""
    removed = 0
    for folder in Path(parent).glob(pattern):
        try:
            with open(folder / OWNER, "ab") as owner:  # (made for a folder whose process died before making it)
                fcntl.flock(owner, fcntl.LOCK_EX | fcntl.LOCK_NB)
                shutil.rmtree(folder, ignore_errors=True)
        except OSError:  # in use, removed meanwhile, not a folder, or a filesystem without locks: left alone
            continue
        if folder.exists():  # (a file rmtree could not delete: it had been counted removed all the same)
            log.warning("scratch folder %s could not be removed whole; the next sweep tries again", folder)
            continue
        removed += 1
    return removed
