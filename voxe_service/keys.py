"""The rule a storage key obeys, apart from the storage so the settings can check ``VOXE_S3_PREFIX`` by it (the
storage reads the settings)."""

from __future__ import annotations

import re

_KEY_PART = re.compile(r"[A-Za-z0-9._-]+")


def is_key(key: str) -> bool:
    """Folder and file names of letters, digits, dots, hyphens and underscores joined by '/': none empty, none
    '.' or '..', so a key never climbs out of its root nor reads two ways.

    Examples:
        >>> is_key("jobs/1/grid.safetensors"), is_key("../x"), is_key("a//b"), is_key("/x")
        (True, False, False, False)
    """
    return all(part not in (".", "..") and _KEY_PART.fullmatch(part) for part in key.split("/"))
