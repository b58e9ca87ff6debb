"""Access token check and confinement of user-given paths to the configured data roots."""

from __future__ import annotations

import hmac
from collections.abc import Iterable
from pathlib import Path

from app.core.errors import Forbidden


def token_matches(expected: str | None, given: str | None) -> bool:
    """Constant-time comparison; with no configured token everything matches."""
    if expected is None:
        return True
    if not given:
        return False
    return hmac.compare_digest(expected.encode(), given.encode())


def resolve_in_roots(raw: str | Path, roots: Iterable[Path], *, what: str = "path") -> Path:
    """Resolve ``raw`` (relative paths are taken inside the first root) and check it lies in a root.

    Symlinks are resolved first, so a link inside a root that points outside it is refused too.

    Raises:
        Forbidden: naming the path and the allowed roots.
    """
    roots = [Path(r).resolve() for r in roots]
    candidate = Path(str(raw)).expanduser()
    if not candidate.is_absolute():
        candidate = roots[0] / candidate
    resolved = candidate.resolve()
    for root in roots:
        if resolved == root or resolved.is_relative_to(root):
            return resolved
    allowed = ", ".join(str(r) for r in roots)
    raise Forbidden(f"{what} {str(raw)!r} is outside the allowed data roots ({allowed})")
