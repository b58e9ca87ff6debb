"""Access token check and confinement of user-given paths to the configured data roots."""

from __future__ import annotations

import contextlib
import hmac
from collections.abc import Iterable, Sequence
from pathlib import Path

from app.core.errors import Forbidden, InvalidField, printable


def token_matches(expected: str | None, given: str | None) -> bool:
    """Constant-time comparison; with no configured token everything matches."""
    if expected is None:
        return True
    if not given:
        return False
    # surrogatepass: a query parameter may carry any code point; it must not turn a 403 into a 500.
    return hmac.compare_digest(expected.encode(), given.encode("utf-8", "surrogatepass"))


def resolve_in_roots(
    raw: str | Path,
    roots: Iterable[Path],
    *,
    what: str = "path",
    loc: Sequence[str | int] = ("body", "path"),
) -> Path:
    """Resolve ``raw`` (relative paths are taken inside the first root) and check it lies in a root.

    Symlinks are resolved first, so a link inside a root that points outside it is refused too.

    Raises:
        Forbidden: naming the path and the allowed roots.
        InvalidField: at ``loc``, a path the system cannot even look up (a NUL byte, a name too long).
    """
    roots = [Path(r).resolve() for r in roots]
    try:
        candidate = Path(str(raw)).expanduser()
        if not candidate.is_absolute():
            candidate = roots[0] / candidate
        resolved = candidate.resolve()
        # Raises what later checks (is_dir) would: a name too long, a loop. Absent is fine here.
        with contextlib.suppress(FileNotFoundError, NotADirectoryError):
            resolved.stat()
    except (OSError, ValueError) as exc:  # ENAMETOOLONG, ELOOP, "embedded null byte"
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise InvalidField(loc, f"{what} {printable(str(raw), 120)!r} cannot be used: {reason}") from None
    for root in roots:
        if resolved == root or resolved.is_relative_to(root):
            return resolved
    allowed = ", ".join(str(r) for r in roots)
    raise Forbidden(f"{what} {str(raw)!r} is outside the allowed data roots ({allowed})")
