"""Files written whole or not at all: a crash, a full disk or an encoder error never leaves a torn file under
the final name, nor destroys the one already there."""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import re
import secrets
import stat
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

SPECIAL_FILES = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
                 (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))
"""What a path that is neither a regular file nor a folder is, by its mode."""
NAME_MAX = 255
"""The longest file name, in bytes, of the filesystems written to (ext4, XFS, Btrfs, tmpfs)."""
WRITE_FAILURES = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO)
"""The errnos of a file's bytes that could not be written (a full disk or quota, a file past its size limit, a
failing disk), which a write or a flush raises naming no file."""
DEAD_PARTIAL_AGE_S = 60.0
"""How long ago an unlocked partial file must have been written last to be taken for a dead writer's: a writer
locks its own just after creating it, and safetensors renames its own file in place of it, unlocked, just before
the block ends (:func:`remove_dead_partials`)."""


def unreadable_file(path: str | os.PathLike, kind: str = "a file") -> str | None:
    """Why ``path`` is no regular file this process can read, in the words a refusal after the path gives ("no such
    file", "is a folder, not ``kind``", "is a FIFO (named pipe), not a regular file", "cannot be read: permission
    denied"); None when it is one. A FIFO, socket or device had been "no such file", of a path that is there (and
    a reader that opened a FIFO would wait for a writer that never comes)."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return "no such file"
    except OSError as exc:  # a folder on the way without search permission, a symlink loop, a name too long
        return f"cannot be read: {exc.strerror.lower() if exc.strerror else exc}"
    except ValueError:  # os.stat's "embedded null byte" had escaped the callers' FormatError
        return "cannot be read: its name holds a null byte, which no file's can"
    if stat.S_ISDIR(mode):
        return f"is a folder, not {kind}"
    if not stat.S_ISREG(mode):
        what = next((name for is_it, name in SPECIAL_FILES if is_it(mode)), "no regular file")
        return f"is {what}, not a regular file"
    if not os.access(path, os.R_OK):
        return "cannot be read: permission denied"
    return None


def head_that_fits(head: str, tail: str, name: str) -> str:
    """``head``, or where ``head`` + ``tail`` would pass :data:`NAME_MAX` bytes, its start that fits with ``~`` and 16
    hex digits of a hash of ``name`` (the file the name is made for) after it: cut by whole characters (one cut inside
    a UTF-8 character is not printable), and two long names alike at their start keep names of their own."""
    if len(os.fsencode(head + tail)) <= NAME_MAX:
        return head
    mark = "~" + hashlib.sha256(os.fsencode(name)).hexdigest()[:16]
    while head and len(os.fsencode(head + mark + tail)) > NAME_MAX:
        head = head[:-1]
    return head + mark


def partial_path(path: Path, token: str) -> Path:
    """``.<stem>.<token>.partial<suffix>`` beside ``path``, its stem cut where that would pass :data:`NAME_MAX` bytes
    (:func:`head_that_fits`): a name that fits had been refused "File name too long", for the bytes the partial
    name adds. A name too long itself keeps the whole partial name, which fails as it is opened (cut to fit, it
    would be written whole before the rename was refused).

    Examples:
        >>> partial_path(Path("out/view.png"), "1f2e3d4c")
        PosixPath('out/.view.1f2e3d4c.partial.png')
        >>> len(partial_path(Path("é" * 125 + ".png"), "1f2e3d4c").name.encode())
        255
    """
    tail = f".{token}.partial{path.suffix}"
    if len(os.fsencode(path.name)) > NAME_MAX:
        return path.with_name(f".{path.stem}{tail}")
    return path.with_name(head_that_fits(f".{path.stem}", tail, path.name) + tail)


def locked(fd: int) -> bool:
    """Whether this process now holds the file open at ``fd`` locked, exclusively (flock: a lock of the open file,
    kept while the writer opens and closes the path itself); False where another holds it or the filesystem has no
    locks (ENOLCK, EOPNOTSUPP)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True


def remove_dead_partials(target: Path) -> None:
    """Remove the partial files of ``target`` (:func:`partial_path`) that writers killed mid-write (SIGKILL, out of
    memory, power loss) left: each killed run had left one more for good. A partial file is a dead writer's when no
    process holds it locked (:func:`replacing` holds its own) and it was last written :data:`DEAD_PARTIAL_AGE_S`
    ago. Best effort: a folder that cannot be listed, or a file that cannot be opened or removed, is left.
    The one partial file of ``target`` of before each writer had its own, ``.<stem>.partial<suffix>``, goes by the
    same rule: a writer killed then had left it, which no writer since would ever have removed."""
    token = "0" * 8
    tail = f".partial{target.suffix}"
    head = partial_path(target, token).name[:-len(f".{token}{tail}")]
    pattern = re.compile(re.escape(head) + r"\.[0-9a-f]{8}" + re.escape(tail))
    shared_name = head_that_fits(f".{target.stem}", tail, target.name) + tail
    names = []
    with suppress(OSError), os.scandir(target.parent) as entries:
        names = [entry.name for entry in entries if pattern.fullmatch(entry.name) or entry.name == shared_name]
    for name in names:
        with suppress(OSError):
            fd = os.open(target.parent / name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)  # (a FIFO: not waited on)
            try:
                found = os.fstat(fd)
                if stat.S_ISREG(found.st_mode) and time.time() - found.st_mtime > DEAD_PARTIAL_AGE_S and locked(fd):
                    os.unlink(target.parent / name)
            finally:
                os.close(fd)


def take_the_mode_of(target: Path, partial: Path) -> None:
    """Give ``partial`` the permissions of ``target``, the file it is to replace, if there is one (a new file gets the
    umask's: a 0600 file replaced had become readable by all), and its owner where this process may give it (root: a
    container or sudo writing a user's folder, whose 0600 file had become root's, its user locked out of it)."""
    try:
        old = os.stat(target)
    except FileNotFoundError:
        return
    if os.geteuid() == 0 and (old.st_uid, old.st_gid) != (os.geteuid(), os.getegid()):
        with suppress(PermissionError):  # (root squashed on NFS: the mode is kept all the same)
            os.chown(partial, old.st_uid, old.st_gid)
    os.chmod(partial, stat.S_IMODE(old.st_mode))  # after chown, which clears set-user-ID and set-group-ID


def flush_to_disk(path: Path) -> None:
    """fsync the file at ``path``: its bytes on the disk before a rename puts it in place of the earlier file, which
    the rename alone does not (a power loss or kernel crash soon after had been able to leave the final name holding
    an empty or torn file on XFS, Btrfs or ext4 writing a new file, the earlier one gone). A file system that cannot
    flush (EINVAL, ENOTSUP, ENOSYS: some FUSE mounts) is passed over; a write the flush finds failed (ENOSPC, EIO:
    NFS reports them here) is the writer's error."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.ENOSYS):
            raise
    finally:
        os.close(fd)


@contextmanager
def naming_write_failures(path: Path) -> Iterator[None]:
    """A failure of the block to write bytes (:data:`WRITE_FAILURES`) that names no file, as a write or a flush
    raises it, named as ``path``'s, the file the block writes: a full disk had been said as "[Errno 28] No space left
    on device" alone. Another OSError goes on as it is."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None or exc.errno not in WRITE_FAILURES:
            raise
        raise OSError(exc.errno, exc.strerror, str(path)) from None


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write into; when the block ends without an error it replaces ``path``
    in one rename, its bytes flushed to the disk first (:func:`flush_to_disk`), otherwise it is removed and ``path``
    is left as it was. It keeps ``path``'s suffix (writers pick their format by it), is hidden (:func:`partial_path`)
    from listings of the folder, and is this writer's own (a random token in its name: two writers of one file at
    once had shared one partial file, each writing over the other's bytes, the first to finish renaming that mix
    into place and the other failing "No such file"). An OSError about that temporary file (a missing folder, no
    permission) names ``path``, the file the caller asked for, as does a failure to write bytes that names no file
    (:func:`naming_write_failures`: a full disk under a PNG, GIF or PLY writer); a block writing two files names the
    other's itself.
    A file replaced keeps its permissions, and a symlink stays one, its target replaced (the new file had taken the
    umask's mode, a 0600 file becoming readable by all, and the link had become a file of its own).
    The partial file is made here and held locked while the block runs, so that a writer killed mid-write is told
    from a live one: each write first removes the partial files of ``path`` dead writers left
    (:func:`remove_dead_partials`; none where the filesystem has no locks).

    Examples:
        >>> import tempfile
        >>> target = Path(tempfile.mkdtemp()) / "notes.txt"
        >>> with replacing(target) as partial:
        ...     _ = partial.write_text("whole")
        >>> target.read_text()
        'whole'
        >>> try:
        ...     with replacing(target) as partial:
        ...         _ = partial.write_text("torn")
        ...         raise OSError("disk full")
        ... except OSError:
        ...     pass
        >>> target.read_text(), sorted(p.name for p in target.parent.iterdir())
        ('whole', ['notes.txt'])
    """
    path = Path(path)
    target = Path(os.path.realpath(path))
    partial = partial_path(target, secrets.token_hex(4))
    fd = None
    try:
        fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the writer writes into it in place
        if locked(fd):
            remove_dead_partials(target)
        with naming_write_failures(partial):
            yield partial
            flush_to_disk(partial)
        take_the_mode_of(target, partial)
        os.replace(partial, target)
    except OSError as exc:
        if exc.errno is None or exc.filename != str(partial):
            raise
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    finally:
        try:
            partial.unlink(missing_ok=True)
        except OSError as exc:  # a name too long for any file: none to remove, and its own error had replaced the
            if exc.errno != errno.ENAMETOOLONG:  # one above, which names the file asked for
                raise
        finally:
            if fd is not None:
                os.close(fd)  # (its lock with it, once the partial file is renamed or removed)
