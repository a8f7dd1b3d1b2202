"""Text from outside (a client's names and paths, a receiver's redirect) cut for a message.

Such text may be of any length: a raw zip read as a form had named its whole body in a 422 (a 1.9 MB message). The
API's 4xx messages and the webhook sender's errors cut it by the same rule, here, so neither imports the other.
"""

from __future__ import annotations


def shorter(text: str, most: int = 200) -> str:
    """``text`` cut to its first ``most`` characters, "..." saying so.

    Examples:
        >>> shorter("abc", 3), shorter("abcd", 3)
        ('abc', 'abc...')
    """
    return text if len(text) <= most else text[:most] + "..."


def listed(names: list[str], most: int = 5, width: int = 40) -> str:
    """``names`` for a message, quoted: the first ``most``, each cut to ``width`` characters (:func:`shorter`),
    then how many more.

    Examples:
        >>> listed(["a", "b"]), listed([str(n) for n in range(7)], most=2), listed(["x" * 9], width=4)
        ("'a', 'b'", "'0', '1' and 5 more", "'xxxx...'")
    """
    shown = ", ".join(repr(shorter(name, width)) for name in names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")
