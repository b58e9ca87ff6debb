"""npz files without whole-array copies: streamed writing, memory-mapped reading (docs/METHOD.md,
"Memory").

``np.savez`` needs every array in memory and ``np.load`` of an npz reads each member into a fresh array.
A whole-sequence grid is the largest thing a run holds, so the grid stages write their output rows as
they are computed (:class:`Streamed` members of :func:`save_npz`) and readers may map an uncompressed
member straight from the file (:func:`load_npz` with ``mmap=True``). The files are ordinary npz files
(uncompressed zip, zip64, one ``.npy`` member per array) that ``np.load`` reads as before, and
:func:`load_npz` reads compressed ones (``np.savez_compressed``) too, member by member.

A mapped member's pages count towards the process's resident memory once touched, like an array read
into memory, but the kernel may drop them at any time and :func:`release` drops them at once (after a
pass over a large mapped array), so a chunked pass over a mapped grid holds about one chunk.
"""

from __future__ import annotations

import mmap
import struct
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError
from leap_core.io_utils import atomic_write

_LOCAL_HEADER = struct.Struct("<4sHHHHHIIIHH")
"""A zip local file header (30 bytes): signature ... file name length, extra field length."""
_LOCAL_SIGNATURE = b"PK\x03\x04"


@dataclass(frozen=True)
class Streamed:
    """An npz member written from row blocks as they come.

    Attributes:
        shape: the whole array's shape (rows first).
        dtype: its dtype (every block is cast to it).
        blocks: C-ordered blocks of consecutive rows, in order; together exactly ``shape[0]`` rows.
    """

    shape: tuple[int, ...]
    dtype: np.dtype[Any]
    blocks: Iterable[npt.NDArray[Any]]


def _write_member(zf: zipfile.ZipFile, name: str, value: npt.ArrayLike | Streamed) -> None:
    with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
        if not isinstance(value, Streamed):
            arr = np.asanyarray(value)
            np.lib.format.write_array(fh, arr, allow_pickle=False)
            release(arr)  # a memory-mapped source: written, so its pages can go
            return
        dtype = np.dtype(value.dtype)
        header = {
            "descr": np.lib.format.dtype_to_descr(dtype),
            "fortran_order": False,
            "shape": tuple(int(s) for s in value.shape),
        }
        np.lib.format.write_array_header_1_0(fh, header)
        row_shape = tuple(value.shape[1:])
        rows = 0
        for block in value.blocks:
            b = np.ascontiguousarray(block, dtype=dtype)
            if b.shape[1:] != row_shape:
                raise ValueError(f"npz member {name!r}: block shape {b.shape}, rows {row_shape} expected")
            rows += b.shape[0]
            if rows > value.shape[0]:
                raise ValueError(f"npz member {name!r}: more than {value.shape[0]} rows streamed")
            fh.write(b.data)
        if rows != value.shape[0]:
            raise ValueError(f"npz member {name!r}: {rows} rows streamed, {value.shape[0]} announced")


def save_npz(path: str | Path, **arrays: npt.ArrayLike | Streamed) -> None:
    """Write an uncompressed npz atomically (:func:`leap_core.io_utils.atomic_write`), members in the order
    given; :class:`Streamed` members are written block by block, never whole in memory. ``np.load`` reads
    the file as one written by ``np.savez``."""
    with atomic_write(path, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in arrays.items():
            _write_member(zf, name, value)


def _mapped(path: Path, fh: Any, info: zipfile.ZipInfo) -> npt.NDArray[Any] | None:
    """The member as a read-only array mapped from the file, or None when it cannot be mapped
    (compressed, object dtype, empty or 0-d)."""
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    fh.seek(info.header_offset)
    head = fh.read(_LOCAL_HEADER.size)
    if len(head) != _LOCAL_HEADER.size:
        return None
    fields = _LOCAL_HEADER.unpack(head)
    if fields[0] != _LOCAL_SIGNATURE:
        return None
    fh.seek(info.header_offset + _LOCAL_HEADER.size + fields[9] + fields[10])
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        return None
    if dtype.hasobject or len(shape) == 0 or int(np.prod(shape)) == 0:
        return None
    arr = np.memmap(path, dtype=dtype, mode="r", offset=fh.tell(), shape=shape, order="F" if fortran else "C")
    return np.asarray(arr)


def load_npz(path: str | Path, names: Sequence[str], *, mmap: bool = False) -> dict[str, npt.NDArray[Any]]:
    """Read the members ``names`` of an npz file (KeyError naming the file when one is missing).

    Args:
        path: the npz file.
        names: member names without ``.npy``.
        mmap: map uncompressed non-empty members read-only from the file instead of reading them (compressed
            members, such as those of ``np.savez_compressed``, and 0-d ones are read as usual).

    Raises:
        DatasetError: unreadable file or member, naming the file.
    """
    path = Path(path)
    out: dict[str, npt.NDArray[Any]] = {}
    try:
        with open(path, "rb") as raw, zipfile.ZipFile(raw) as zf:
            for name in names:
                try:
                    info = zf.getinfo(f"{name}.npy")
                except KeyError:
                    raise KeyError(f"{path}: no array {name!r}") from None
                arr = _mapped(path, raw, info) if mmap else None
                if arr is None:
                    with zf.open(info) as member:
                        arr = np.lib.format.read_array(member, allow_pickle=False)
                out[name] = arr
    except (OSError, zipfile.BadZipFile, ValueError, EOFError, struct.error) as exc:
        raise DatasetError(path, f"unreadable npz file ({exc})") from exc
    return out


def has_member(path: str | Path, name: str) -> bool:
    """Whether the npz file holds an array ``name`` (False when unreadable)."""
    try:
        with zipfile.ZipFile(path) as zf:
            return f"{name}.npy" in zf.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def release(arr: npt.NDArray[Any]) -> None:
    """Drop the resident pages of a memory-mapped array (one :func:`load_npz` gave with ``mmap=True``);
    nothing for an ordinary array. The data stays readable: later reads fault the pages in again from the
    file (usually still in the page cache)."""
    base: Any = arr
    while base is not None:
        if isinstance(base, np.memmap):
            m = getattr(base, "_mmap", None)
            if m is not None and hasattr(m, "madvise"):
                m.madvise(mmap.MADV_DONTNEED)
            return
        base = getattr(base, "base", None)


def is_mapped(arr: npt.NDArray[Any]) -> bool:
    """Whether ``arr`` is (a view of) a memory-mapped file."""
    base: Any = arr
    while base is not None:
        if isinstance(base, np.memmap):
            return True
        base = getattr(base, "base", None)
    return False


__all__ = ["Streamed", "has_member", "is_mapped", "load_npz", "release", "save_npz"]
