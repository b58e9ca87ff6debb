"""Deployment settings of the LeAP Studio app, read once at start-up.

Only this module reads the environment (variables prefixed ``LEAP_``, e.g. ``LEAP_PORT=8001`` or
``LEAP_DATA_ROOTS='["/data/kitti"]'``). Everything else receives a :class:`Settings` object explicitly.
"""

from __future__ import annotations

import functools
import ipaddress
import math
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from app.core.demo_synth import synth_config
from leap_core.paths import UnusablePath, real_path

LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1", "ip6-localhost"})


def _real(path: str | Path, what: str) -> Path:
    """:func:`~app.core.security.real_path` of a configured folder; a ValueError naming it otherwise (pydantic
    reports it as the setting's error)."""
    try:
        return real_path(path)
    except UnusablePath as exc:
        raise ValueError(f"{what} {path} {exc}") from None


def is_loopback(host: str) -> bool:
    """True when ``host`` only accepts connections from this machine."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


MIN_TOKEN_LENGTH = 16
MIN_TOKEN_DISTINCT = 8
MIN_TOKEN_BITS = 64


def token_weakness(token: str) -> str | None:
    """Why ``token`` is too easy to guess, or None.

    A token must have at least 16 characters, 8 of them different, and an estimated 64 bits of entropy:
    length × log2(size of the character classes it uses: lower case 26, upper case 26, digits 10, other
    printable ASCII 33, anything else 100). ``secrets.token_urlsafe(32)`` (what ``--new-token`` makes)
    has about 256. The estimate is an upper bound for chosen words, so it only turns away the obviously
    weak (``aaaaaaaaaaaaaaaa``, ``1234567890123456``).
    """
    if len(token) < MIN_TOKEN_LENGTH:
        return f"must have at least {MIN_TOKEN_LENGTH} characters (it has {len(token)})"
    if any(not ch.isprintable() or ch.isspace() for ch in token):
        return "may only contain printable characters without spaces"
    if len(set(token)) < MIN_TOKEN_DISTINCT:
        return f"must use at least {MIN_TOKEN_DISTINCT} different characters (it uses {len(set(token))})"
    pool = 0
    for present, size in (
        (any(ch.islower() and ch.isascii() for ch in token), 26),
        (any(ch.isupper() and ch.isascii() for ch in token), 26),
        (any(ch.isdigit() and ch.isascii() for ch in token), 10),
        (any(ch.isascii() and not ch.isalnum() for ch in token), 33),
        (any(not ch.isascii() for ch in token), 100),
    ):
        pool += size if present else 0
    bits = len(token) * math.log2(pool)
    if bits < MIN_TOKEN_BITS:
        return (
            f"is too easy to guess (about {bits:.0f} bits; needs {MIN_TOKEN_BITS}): make it longer or mix "
            "letters, digits and symbols"
        )
    return None


class Settings(BaseSettings):
    """Where the app listens, where data may live, and where it keeps its state."""

    model_config = SettingsConfigDict(env_prefix="LEAP_", env_ignore_empty=True, extra="ignore", frozen=True)

    host: str = "127.0.0.1"
    """Address to bind. Anything but a loopback address requires ``access_token``."""
    port: int = Field(default=8000, ge=1, le=65535)
    """TCP port of the API and web UI."""
    data_roots: list[Path] = Field(default_factory=lambda: [Path("data")])
    """Folders datasets may be read from and exports written to; every user path must lie inside one."""
    work_dir: Path = Path("data/studio")
    """Where runs, stage caches, the demo sequence and the SQLite database live."""
    db_path: Path | None = None
    """SQLite file; defaults to ``work_dir/studio.db``."""
    access_token: SecretStr | None = None
    """Shared secret every API call (and the viewer) must present when set; required off loopback."""
    models_dir: Path | None = None
    """Local folder with Grounding DINO / SAM weights; None = the Hugging Face cache of the user running the
    server. Only the server's settings name it: a project names model ids, never folders."""
    allow_download: bool = False
    """Without ``models_dir``: may a run download a model missing from the Hugging Face cache? Off by
    default, and only the server's settings can turn it on (a project cannot)."""
    ray_address: str | None = None
    """Ray cluster the run workers send per-frame work and fusion to (``LEAP_RAY_ADDRESS``): ``auto`` (the
    cluster this machine belongs to, else a local instance) or ``host:6379``; the work folder and the data
    roots must be on storage every node sees at the same path. None = each worker computes its run itself."""
    max_parallel_runs: int = Field(default=1, ge=1, le=8)
    """Runs executed at the same time across all projects; further runs wait in a FIFO queue."""
    prewarm_workers: bool = True
    """Keep a worker process with the pipeline already imported, so a run starts without a delay."""
    seed_demo: bool = True
    """On first start, create the demo project and queue its first run."""
    demo_synth: dict[str, Any] = Field(default_factory=dict)
    """Overrides for ``leap_core.synth.SynthConfig`` when generating the demo sequence (e.g. fewer frames);
    its ``frames`` also sets the farm demo's frame count (``app.demo.demo_config``)."""
    seed_agri_demo: bool = True
    """With ``seed_demo``: on first start, also create the farm drone demo project (``leap synth --domain
    agri-uav``, generated by its first run) and queue that run after the street demo's."""
    viewer_enabled: bool = True
    """Start the 3D review viewer (viser) when a run is opened for review."""
    viewer_port: int = Field(default=0, ge=0, le=65535)
    """Port of the viser viewer; 0 picks a free port."""
    viewer_max_points: int = Field(default=2_000_000, ge=1000)
    """Most points the viewer sends for the voxel map: a bigger map is drawn with level of detail (full
    resolution near the focus, one point per block elsewhere; ``app.viewer.lod``)."""
    progress_interval_s: float = Field(default=0.1, gt=0, le=5)
    """Minimum seconds between two progress messages of one stage (the last one is always sent)."""
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    """Server log level."""
    min_free_disk_mb: float = Field(default=200.0, ge=0)
    """Free space (MiB) the work folder's file system must have for a run to start: below it, starting or
    resuming a run is refused with a message and a queued run fails before it starts. ``/health`` reports
    the free space. 0 turns the check off."""
    db_max_mb: float | None = Field(default=None, gt=0)
    """Largest size (MiB) the SQLite database may grow to; a write that needs more fails as on a full
    disk (the run that needed it fails, the server stays up). None: no cap beyond the disk's size."""
    max_body_bytes: int = Field(default=1024 * 1024, ge=1024, le=1024**3)
    """Largest request body accepted (bytes); a larger one is answered 413 before it is read."""
    request_head_timeout_s: float = Field(default=10.0, gt=0, le=300)
    """Seconds a connection has to send a request's line and headers, from its start or from the end of
    its previous response; a slower one is answered 408 and closed, so a client that trickles a head
    cannot hold connections open forever (``app.core.request_head``)."""

    @field_validator("host")
    @classmethod
    def _host_not_empty(cls, value: str) -> str:
        value = value.strip()
        if not value:
            raise ValueError("host must not be empty")
        return value

    @field_validator("data_roots")
    @classmethod
    def _roots(cls, value: list[Path]) -> list[Path]:
        if not value:
            raise ValueError("at least one data root is needed")
        roots = [_real(p, "data root") for p in value]
        for root in roots:
            if root.exists() and not root.is_dir():
                raise ValueError(f"data root {root} is a file, not a folder")
            if root == Path(root.anchor):
                raise ValueError(f"data root {root} is the file-system root; name a data folder")
        return roots

    @field_validator("work_dir", "models_dir")
    @classmethod
    def _abs_dir(cls, value: Path | None) -> Path | None:
        if value is None:
            return None
        path = _real(value, "folder")
        if path.exists() and not path.is_dir():
            raise ValueError(f"{path} is a file, not a folder")
        return path

    @field_validator("demo_synth")
    @classmethod
    def _synth(cls, value: dict[str, Any]) -> dict[str, Any]:
        try:
            synth_config(value)
        except ValueError as exc:  # LeapError is a ValueError; its message names the field
            raise ValueError(str(exc)) from None
        return value

    @field_validator("access_token")
    @classmethod
    def _token_strength(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None:
            problem = token_weakness(value.get_secret_value())
            if problem is not None:
                raise ValueError(f"access_token {problem}; `leap serve --new-token` generates a strong one")
        return value

    @model_validator(mode="after")
    def _check(self) -> Settings:
        if not is_loopback(self.host) and self.access_token is None:
            raise ValueError(
                f"host {self.host!r} is not a loopback address: set access_token (LEAP_ACCESS_TOKEN) "
                "so that only people with the token can use the app"
            )
        if self.db_path is None:
            object.__setattr__(self, "db_path", self.work_dir / "studio.db")
        else:
            object.__setattr__(self, "db_path", _real(self.db_path, "db_path"))
        return self

    # ----------------------------------------------------------------------------------- derived paths
    @property
    def database(self) -> Path:
        """The SQLite file (``db_path`` with its default filled in)."""
        assert self.db_path is not None
        return self.db_path

    @property
    def runs_dir(self) -> Path:
        return self.work_dir / "runs"

    @property
    def cache_dir(self) -> Path:
        return self.work_dir / "cache"

    @property
    def demo_dataset(self) -> Path:
        """Sequence folder of the built-in demo (generated on first use)."""
        return self.work_dir / "demo" / "sequences" / "00"

    @property
    def demo_agri_dataset(self) -> Path:
        """Sequence folder of the built-in farm drone demo (generated on first use)."""
        return self.work_dir / "demo-agri" / "sequences" / "00"

    @property
    def token(self) -> str | None:
        return None if self.access_token is None else self.access_token.get_secret_value()


@functools.lru_cache(maxsize=1)
def get_settings() -> Settings:
    """Settings from the environment, read once (tests build ``Settings(...)`` and pass them instead)."""
    return Settings()
