"""Resolving a path a user gave: every symbolic link followed, a loop reported as an error naming it.

:meth:`Path.resolve` reports a symbolic link loop as ``RuntimeError`` on Python 3.11 (``OSError`` ELOOP on
later versions) and an unknown ``~user`` as ``RuntimeError`` too, which would escape a program as a
traceback. :func:`real_path` turns each into :class:`UnusablePath`, whose message completes "path X ...",
so the caller names the file, flag or field in its own words.
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path

from leap_core.errors import LeapError

LOOP = "a symlink loop (a link that leads back to itself, or too many links in a row)"

_SHOWN_CHARS = 200
"""A path quoted in a reason is cut to this many characters."""


class UnusablePath(LeapError):
    """A path the system cannot look up: a symbolic link loop, a name too long, a NUL byte; the message
    completes "path X ..." (e.g. ``is a symlink loop ...``)."""


def _shown(path: Path) -> str:
    """``path`` quoted for a message: cut to :data:`_SHOWN_CHARS`, lone surrogates escaped (a message
    must encode as UTF-8)."""
    text = str(path)
    if len(text) > _SHOWN_CHARS:
        text = text[:_SHOWN_CHARS] + "…"
    return repr(text.encode("utf-8", "backslashreplace").decode("utf-8"))


def loop_reason(path: Path) -> str:
    """How ``path`` (absolute or relative to the current folder) meets a loop: it is one, or a folder on
    the way is."""
    prefix = Path(path.anchor) if path.is_absolute() else Path()
    for part in path.parts[1:] if path.is_absolute() else path.parts:
        prefix = prefix / part
        try:
            os.stat(prefix)
        except OSError as exc:
            if exc.errno != errno.ELOOP:
                break
            return f"is {LOOP}" if prefix == path else f"goes through {_shown(prefix)}, {LOOP}"
    return f"leads into {LOOP}"


def real_path(path: str | Path) -> Path:
    """``path`` made absolute with ``~`` expanded and every symbolic link followed, as :meth:`Path.resolve`
    (parts that do not exist are allowed). The one way a path a user gave or stored is resolved.

    Raises:
        UnusablePath: a loop, an unknown ``~user``, a name too long, a NUL byte.
    """
    try:
        expanded = Path(str(path)).expanduser()
    except RuntimeError:  # "Could not determine home directory"
        raise UnusablePath("starts with '~' of a user this system does not know") from None
    try:
        resolved = expanded.resolve()
        # resolve() skips what does not exist; stat raises what later checks (is_dir) would hide.
        with contextlib.suppress(FileNotFoundError, NotADirectoryError):
            resolved.stat()
    except RuntimeError:  # Python 3.11's report of a loop
        raise UnusablePath(loop_reason(expanded)) from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UnusablePath(loop_reason(expanded)) from None
        raise UnusablePath(f"cannot be looked up ({exc.strerror or exc})") from None
    except ValueError as exc:  # "embedded null byte"
        raise UnusablePath(f"cannot be looked up ({exc})") from None
    return resolved


def real_path_or_none(path: str | Path) -> Path | None:
    """:func:`real_path`, or None for a path that cannot be looked up (a stored folder that has become a
    symlink loop holds nothing and equals no other folder)."""
    try:
        return real_path(path)
    except UnusablePath:
        return None
