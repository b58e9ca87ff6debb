"""Access token check, the same-origin rule for state-changing requests, and confinement of user-given
paths to the configured data roots."""

from __future__ import annotations

import contextlib
import hmac
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from urllib.parse import urlsplit

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


UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
"""Methods that change state: a page of another origin must not be able to send them."""

_DEFAULT_PORTS = {"http": 80, "https": 443, "ws": 80, "wss": 443}


def _host_port(netloc: str, scheme: str) -> tuple[str, int | None] | None:
    """(lower-case host, port) of ``netloc``; the scheme's default port when it names none."""
    try:
        parts = urlsplit(f"//{netloc}")
        port = parts.port
    except ValueError:
        return None
    if parts.hostname is None:
        return None
    return parts.hostname.lower(), port if port is not None else _DEFAULT_PORTS.get(scheme)


def cross_origin_reason(headers: Mapping[str, str]) -> str | None:
    """Why a browser request comes from a page of another origin, or None when it does not.

    ``headers`` are the request's (lower-case names). ``Sec-Fetch-Site: cross-site`` or ``same-site``, an
    ``Origin`` of ``null`` (sandboxed pages, file: URLs) or an ``Origin`` whose host and port differ from the
    ``Host`` the request was sent to all count as another origin. Loopback aliases are distinct origins
    (``127.0.0.2`` is not ``127.0.0.1``, nor is ``localhost``): a browser keeps their pages apart too.
    Requests with neither header (curl, the CLI, scripts) are not from a web page and pass.
    """
    site = headers.get("sec-fetch-site", "").lower()
    if site in ("cross-site", "same-site"):
        return f"Sec-Fetch-Site is {site}"
    origin = headers.get("origin")
    if origin is None:
        return None
    scheme = urlsplit(origin).scheme.lower() if origin != "null" else ""
    if scheme not in _DEFAULT_PORTS:
        return f"Origin {origin!r} is not a web origin"
    theirs = _host_port(urlsplit(origin).netloc, scheme)
    # A Host without a port means the default port of the scheme the browser used, the Origin's.
    ours = _host_port(headers.get("host", ""), scheme)
    if theirs is None or ours is None or theirs != ours:
        return f"Origin {origin!r} is not this server ({headers.get('host', '')!r})"
    return None
