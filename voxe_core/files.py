"""Files written whole or not at all: a crash, a full disk or an encoder error never leaves a torn file under
the final name, nor destroys the one already there."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

SPECIAL_FILES = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
                 (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))
"""What a path that is neither a regular file nor a folder is, by its mode."""


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


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write into; when the block ends without an error it replaces ``path``
    in one rename, otherwise it is removed and ``path`` is left as it was. It keeps ``path``'s suffix (writers
    pick their format by it) and is hidden (``.<stem>.partial<suffix>``) from listings of the folder. An OSError
    about that temporary file (a missing folder, no permission) names ``path``, the file the caller asked for.

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
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield partial
        os.replace(partial, path)
    except OSError as exc:
        if exc.errno is None or exc.filename != str(partial):
            raise
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    finally:
        partial.unlink(missing_ok=True)
