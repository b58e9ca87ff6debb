"""Atomic file writes and folder removal: results are never left half-written or half-deleted."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import secrets
import shutil
import struct
import uuid
import zipfile
import zlib
from collections.abc import Iterable, Iterator
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


def atomic_copy(src: str | Path, dst: str | Path) -> None:
    """Copy the file ``src`` to ``dst`` through :func:`atomic_write`: ``dst`` gets the mode ``open()`` gives
    under the umask, whatever ``src`` has. For files another library wrote (``save_pretrained`` writes
    its weights through a 0600 temp file of its own) into a staging folder, published here."""
    with open(src, "rb") as fin, atomic_write(dst, "wb") as fout:
        shutil.copyfileobj(fin, fout, 1 << 20)


def atomic_save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """``np.savez`` (uncompressed: these are read back often) through :func:`atomic_write`."""
    with atomic_write(path, "wb") as fh:
        # allow_pickle=True is numpy's default, spelled out so the type checker does not match **arrays to it.
        np.savez(fh, allow_pickle=True, **arrays)


_LOCAL_HEADER = struct.Struct("<4s22xHH")
"""A zip member's local header (30 bytes): signature, then the name and extra-field lengths at 26 and 28."""


def _npy_array(data: bytes, name: str) -> np.ndarray:
    """The array of one ``.npy`` file's bytes, as a read-only view of them."""
    fp = io.BytesIO(data)
    version = np.lib.format.read_magic(fp)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fp)
    elif version in ((2, 0), (3, 0)):
        # 3.0 differs from 2.0 only in the header's text encoding (utf-8), which this reader accepts too.
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fp)
    else:
        raise ValueError(f"member {name}: unsupported .npy version {version}")
    if dtype.hasobject:
        raise ValueError(f"member {name}: object arrays are not read (they would need pickle)")
    count = math.prod(shape)
    if len(data) - fp.tell() != count * dtype.itemsize:
        raise ValueError(f"member {name}: {len(data) - fp.tell()} data bytes for shape {shape} {dtype}")
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=fp.tell())
    return arr.reshape(shape, order="F" if fortran else "C")


def read_npz(path: str | Path, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file (``np.savez`` or ``np.savez_compressed``), by name: all of them, or
    those in ``names`` (a missing one raises KeyError).

    Each member costs one read and, when deflated, one ``zlib`` call, with zipfile's CRC check. ``np.load``
    reads a deflated member in 256 KiB pieces (a decompress and a CRC call each: about 20 for one 2D label
    file of 5.6 MB unpacked) and opens the archive again for every member asked for, which together with
    its file handling was ≈ 10 ms per frame of the 3D stages (docs/METHOD.md "Performance facts").

    Returns:
        name (without ``.npy``) → array. Arrays are READ-ONLY views of the file's bytes (copy before
        writing into one).

    Raises:
        OSError: the file cannot be read.
        KeyError: a name in ``names`` is not in the file.
        ValueError: not an npz archive, a damaged member (CRC, sizes), an object array or another member.
    """
    out: dict[str, np.ndarray] = {}
    with open(path, "rb") as fh:
        try:
            members = zipfile.ZipFile(fh).infolist()
        except zipfile.BadZipFile as exc:
            raise ValueError(f"not an npz archive ({exc})") from exc
        wanted = None if names is None else set(names)
        if wanted is not None:
            missing = wanted - {m.filename[:-4] for m in members if m.filename.endswith(".npy")}
            if missing:
                raise KeyError(f"{sorted(missing)[0]} is not a member of {path}")
        for info in members:
            name = info.filename
            if not name.endswith(".npy"):
                raise ValueError(f"member {name} is not a .npy array")
            if wanted is None or name[:-4] in wanted:
                out[name[:-4]] = _npy_array(_member_bytes(fh, info), name)
    return out


def _member_bytes(fh: IO[bytes], info: zipfile.ZipInfo) -> bytes:
    """One zip member's content: one read, one ``zlib`` call when deflated, zipfile's CRC check."""
    name = info.filename
    fh.seek(info.header_offset)
    sig, name_len, extra_len = _LOCAL_HEADER.unpack(fh.read(_LOCAL_HEADER.size))
    if sig != b"PK\x03\x04":
        raise ValueError(f"member {name}: bad local header")
    fh.seek(info.header_offset + _LOCAL_HEADER.size + name_len + extra_len)
    raw = fh.read(info.compress_size)
    if len(raw) != info.compress_size:
        raise ValueError(f"member {name}: truncated")
    if info.compress_type == zipfile.ZIP_STORED:
        data = raw
    elif info.compress_type == zipfile.ZIP_DEFLATED:
        try:
            data = zlib.decompress(raw, -zlib.MAX_WBITS, max(info.file_size, 1))
        except zlib.error as exc:
            raise ValueError(f"member {name}: {exc}") from exc
    else:
        raise ValueError(f"member {name}: compression method {info.compress_type} not supported")
    if len(data) != info.file_size or zlib.crc32(data) != info.CRC:
        raise ValueError(f"member {name}: damaged (size or CRC mismatch)")
    return data


def file_digest(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


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
