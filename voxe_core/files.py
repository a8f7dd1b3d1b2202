"""Files written whole or not at all: a crash, a full disk or an encoder error never leaves a torn file under
the final name, nor destroys the one already there."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


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
