"""Access token check, the same-origin rule for state-changing requests, and confinement of user-given
paths to the configured data roots."""

from __future__ import annotations

import hmac
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from urllib.parse import urlsplit

from app.core.errors import Forbidden, InvalidField, printable
from leap_core.paths import UnusablePath, real_path, real_path_or_none


def token_matches(expected: str | None, given: str | None) -> bool:
    """Constant-time comparison; with no configured token everything matches."""
    if expected is None:
        return True
    if not given:
        return False
    # surrogatepass: a query parameter may carry any code point; it must not turn a 403 into a 500.
    return hmac.compare_digest(expected.encode(), given.encode("utf-8", "surrogatepass"))


CHANGE_ROOTS = (
    "the data roots are the server's data_roots setting: start it with `leap serve --data-root DIR` "
    "(repeatable) or set LEAP_DATA_ROOTS to a JSON list of folders, then restart it"
)
"""How a user whose path lies outside the data roots gets them changed (every such refusal says it)."""


def outside_roots(roots: Iterable[Path]) -> str:
    """The end of a refusal for a path outside the data roots: the current roots and how to change them."""
    return f"the allowed data roots ({', '.join(str(r) for r in roots) or 'none'}); {CHANGE_ROOTS}"


def resolve_in_roots(
    raw: str | Path,
    roots: Iterable[Path],
    *,
    what: str = "path",
    loc: Sequence[str | int] = ("body", "path"),
) -> Path:
    """Resolve ``raw`` (relative paths are taken inside the first root) and check it lies in a root.

    Symlinks are resolved first, so a link inside a root that points outside it is refused too; the
    refusal then names the link and where it leads.

    Raises:
        Forbidden: naming the path and the allowed roots.
        InvalidField: at ``loc``, a path the system cannot even look up (a symlink loop, a NUL byte, a
            name too long).
    """
    given = list(roots)
    # A root that cannot be looked up (a stored folder turned into a loop) holds nothing.
    roots = [r for r in map(real_path_or_none, given) if r is not None]
    candidate = Path(str(raw))
    if not candidate.is_absolute() and not str(raw).startswith("~"):
        candidate = Path(given[0]) / candidate
    try:
        resolved = real_path(candidate)
    except UnusablePath as exc:
        raise InvalidField(loc, f"{what} {printable(str(raw), 120)!r} {exc}; name a real folder") from None
    if _inside(resolved, roots):
        return resolved
    link = _escaping_link(candidate, roots)
    if link is not None:
        where, target = link
        via = "is" if where == candidate.expanduser() else f"goes through {str(where)!r},"
        raise Forbidden(
            f"{what} {str(raw)!r} {via} a symlink to {str(target)!r}, which is outside "
            + outside_roots(roots)
        )
    raise Forbidden(f"{what} {str(raw)!r} is outside {outside_roots(roots)}")


def _inside(path: Path, roots: Sequence[Path]) -> bool:
    return any(path == root or path.is_relative_to(root) for root in roots)


def _escaping_link(path: Path, roots: Sequence[Path]) -> tuple[Path, Path] | None:
    """(link, its real target) of the first symbolic link along ``path`` (itself included) that leads
    outside every root, or None: what a refusal names instead of the typed path."""
    path = path.expanduser()
    prefix = Path(path.anchor)
    for part in path.parts[1:]:
        prefix = prefix / part
        if not prefix.is_symlink():  # lstat: the link itself, never followed
            continue
        try:
            target = real_path(prefix)
        except UnusablePath:
            return None
        if not _inside(target, roots):
            return prefix, target
    return None


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
