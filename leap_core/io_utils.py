"""Atomic file writes and folder removal: results are never left half-written or half-deleted."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

_TEMP_TRIES = 100


def create_temp_file(folder: Path, name: str) -> tuple[int, Path]:
    """Create a new empty file ``folder/.<name>.<random>.tmp`` for writing: ``(fd, path)``.

    Created with mode 0o666 less the process umask, as ``open()`` creates files (0644 under umask 022,
    0664 under 002), so a colleague or a job running as another user can read what the project writes.
    ``tempfile.mkstemp`` would give 0600 whatever the umask, and the rename would keep it. ``O_EXCL``
    makes the name ours alone.
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for _ in range(_TEMP_TRIES):
        tmp = folder / f".{name}.{secrets.token_hex(6)}.tmp"
        try:
            return os.open(tmp, flags, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{folder}: no free temporary name for {name} after {_TEMP_TRIES} tries")


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temp file beside ``path``; on success fsync and rename it over ``path``.

    The file gets the mode ``open()`` would give it under the current umask (:func:`create_temp_file`).
    On any exception the temp file is removed and ``path`` keeps its previous content.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = create_temp_file(path.parent, path.name)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def atomic_write_json(path: str | Path, obj: Any) -> None:
    with atomic_write(path, "w") as fh:
        json.dump(obj, fh, indent=2, sort_keys=True)


def atomic_save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """``np.savez`` (uncompressed: these are read back often) through :func:`atomic_write`."""
    with atomic_write(path, "wb") as fh:
        # allow_pickle=True is numpy's default, spelled out so the type checker does not match **arrays to it.
        np.savez(fh, allow_pickle=True, **arrays)


def link_or_copy(src: str | Path, dst: str | Path) -> None:
    """Make ``dst`` the same file as ``src``: a hard link (no copy of a large file), else a copy (another
    file system); atomic, so a reader never sees a half-copied ``dst``."""
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.link")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def remove_tree(path: str | Path) -> bool:
    """Delete the folder ``path`` (False when it does not exist).

    The folder is first renamed to a hidden sibling, so an interrupted delete leaves nothing at ``path``
    that a later reader could take for a complete (or partial) result.
    """
    path = Path(path)
    if not path.exists():
        return False
    doomed = path.with_name(f".deleting-{path.name}-{uuid.uuid4().hex[:8]}")
    os.rename(path, doomed)
    shutil.rmtree(doomed, ignore_errors=True)
    return True
