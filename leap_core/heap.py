"""Keeping freed memory from staying with the process (glibc malloc; a no-op elsewhere).

glibc's malloc serves a request below its *mmap threshold* from a heap and one above it with its own
``mmap``. The threshold starts at 128 KiB and, each time a block above it is freed, rises to that block's
size (up to 32 MiB). torch and numpy free such blocks all the time (a training step's activations, a
scan's arrays), so after the first few the threshold sits at tens of MiB and every later tensor of
1-32 MiB comes from a heap, where freed memory is only returned to the system when it lies at the top. The
3D-CN's resident size then grows step after step with memory nobody uses: 4.1 GB at the end of a demo
run whose live working set is a few hundred MB (README, "Memory").

:func:`cap_heap_growth` fixes the threshold (which also ends its rising), so blocks of at least that size
get their own mapping and go back to the system when freed; :func:`release_free_memory` hands back the free
pages of every heap (``malloc_trim(0)``), called where a step or a scan has ended. Neither changes any
value a computation sees.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
from collections.abc import Iterator

MMAP_THRESHOLD = 1 << 20
"""Bytes from which :func:`cap_heap_growth` makes glibc map blocks of their own (1 MiB: a 64-channel
float32 row block of 4 096 points; smaller ones stay on the heap, where reusing them costs no page
faults)."""
_M_MMAP_THRESHOLD = -3
"""``mallopt`` parameter number of ``M_MMAP_THRESHOLD`` (glibc ``malloc.h``)."""


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (it has ``gnu_get_libc_version``, ``mallopt`` and ``malloc_trim``),
    else None (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        lib = ctypes.CDLL(name)
    except OSError:
        return None
    if not all(hasattr(lib, f) for f in ("gnu_get_libc_version", "mallopt", "malloc_trim")):
        return None
    lib.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    lib.mallopt.restype = ctypes.c_int
    lib.malloc_trim.argtypes = [ctypes.c_size_t]
    lib.malloc_trim.restype = ctypes.c_int
    return lib


def cap_heap_growth(threshold: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``threshold`` bytes for the rest of the process: blocks at least
    that large are mapped on their own and unmapped when freed, whatever was freed before.

    Process-wide and not undone (glibc has no call that restores the rising threshold); the 3D-CN stage
    sets it when it starts. Returns whether it was applied (False off glibc).
    """
    lib = _glibc()
    return lib is not None and lib.mallopt(_M_MMAP_THRESHOLD, int(threshold)) == 1


REUSE_THRESHOLD = 32 << 20
"""Bytes below which :func:`reusing_heap` serves blocks from a heap (32 MiB, glibc's own ceiling for its
rising threshold): a 3D-CN training step's activations, freed at its end and allocated again by the next."""


@contextlib.contextmanager
def reusing_heap(threshold: int = REUSE_THRESHOLD) -> Iterator[None]:
    """For the block, blocks below ``threshold`` bytes come from a heap, where memory freed by one
    iteration serves the next without the page faults of a fresh mapping (with the 1 MiB cap a default
    3D-CN training step faulted in some 600 MB, a third of its CPU time). The caller hands freed pages
    back now and then (:func:`release_free_memory`) so fragments cannot add up; afterwards the threshold is
    :func:`cap_heap_growth`'s again and the free pages are handed back. Nothing happens off glibc."""
    lib = _glibc()
    if lib is None:
        yield
        return
    lib.mallopt(_M_MMAP_THRESHOLD, int(threshold))
    try:
        yield
    finally:
        cap_heap_growth()
        release_free_memory()


def release_free_memory() -> bool:
    """Return the free pages of every malloc heap (all threads' arenas) to the system:
    ``malloc_trim(0)``. Returns whether memory was released (False off glibc)."""
    lib = _glibc()
    return lib is not None and lib.malloc_trim(0) == 1


__all__ = ["MMAP_THRESHOLD", "REUSE_THRESHOLD", "cap_heap_growth", "release_free_memory", "reusing_heap"]
