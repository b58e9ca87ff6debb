"""On-disk cache of Grounding DINO + SAM results, one file per (image, detector pass).

The unit cached is one detector pass over one image (:class:`PassResult`): the kept boxes, their class
logits for the pass's classes and their SAM masks as packed bits. The per-image :class:`SoftMasks` is
assembled from the pass results in milliseconds, so:

* in per-class mode (one pass per class) editing one class's prompts invalidates only that class's file;
* in joint mode the single text holds every prompt, so any prompt edit recomputes the pass (the logits of
  every class depend on the whole text).

Keys are SHA-256 digests of the image content (pixels, not file bytes, so re-encoding a PNG losslessly
keeps its key), the model identities (id + a hash of each model folder's config and weight files), the
pass text and class roles, and every setting that changes the result (threshold, mode, mask settings).
Entries are compressed ``.npz`` files. Writes are atomic (temp file + rename), so an interrupted run leaves
no half-written entry and a rerun resumes where it stopped; two writers of the same key write identical
content, last one wins.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from leap_core.io_utils import atomic_write

CACHE_FORMAT = 1
"""Bumped whenever the stored layout or the meaning of a stored field changes."""


def image_digest(image: npt.NDArray[Any]) -> str:
    """SHA-256 hex digest of an image's pixels (shape and dtype included)."""
    arr = np.ascontiguousarray(image)
    h = hashlib.sha256(f"{arr.shape}|{arr.dtype.str}|".encode())
    h.update(arr.data.cast("B"))
    return h.hexdigest()


def cache_key(parts: dict[str, Any]) -> str:
    """SHA-256 hex digest of a JSON-serialisable mapping (key order does not matter)."""
    blob = json.dumps({"format": CACHE_FORMAT, **parts}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()


def default_cache_dir(dataset_root: str | Path) -> Path:
    """The shared cache root ``leap labels2d`` uses unless told otherwise: ``<sequence>/leap_cache``.

    It is the same kind of folder as ``leap run --cache``: pass results live in :func:`pass_cache_dir`.
    """
    return Path(dataset_root) / "leap_cache"


def pass_cache_dir(cache_root: str | Path) -> Path:
    """Folder of the per-pass results inside a shared cache root (``<root>/passes``)."""
    return Path(cache_root) / "passes"


@dataclass(frozen=True)
class PassResult:
    """What one detector pass (plus SAM) produced for one image.

    Attributes:
        height, width: image size in pixels.
        class_names: (K,) the pass's classes, in the column order of ``scores``.
        boxes: (R, 4) float32 xyxy boxes in pixels of the kept regions.
        scores: (R, K) float32 class logits s(q, k) after negative prompts (-inf = ruled out).
        bits: (R, ceil(H*W/8)) uint8 ``np.packbits`` of each region's row-major SAM mask.
    """

    height: int
    width: int
    class_names: tuple[str, ...]
    boxes: npt.NDArray[np.float32]
    scores: npt.NDArray[np.float32]
    bits: npt.NDArray[np.uint8]

    def __post_init__(self) -> None:
        r = self.boxes.shape[0]
        nbytes = (self.height * self.width + 7) // 8
        if self.boxes.shape != (r, 4) or self.scores.shape != (r, len(self.class_names)):
            raise ValueError(f"boxes {self.boxes.shape} / scores {self.scores.shape} do not match {r} rows")
        if self.bits.shape != (r, nbytes):
            raise ValueError(f"bits {self.bits.shape} do not match {r} masks of {self.height}×{self.width}")

    @property
    def num_regions(self) -> int:
        return int(self.boxes.shape[0])

    def save(self, path: str | Path) -> None:
        """Write atomically as a compressed ``.npz`` (mask bits are mostly runs of zeros: deflate shrinks
        them many times over, and a cache entry is read about once per run)."""
        with atomic_write(path, "wb") as fh:
            np.savez_compressed(
                fh,
                size=np.array([self.height, self.width], dtype=np.int64),
                class_names=np.array(self.class_names, dtype=np.str_).reshape(-1),
                boxes=self.boxes.astype(np.float32),
                scores=self.scores.astype(np.float32),
                bits=self.bits.astype(np.uint8),
            )

    @classmethod
    def load(cls, path: str | Path) -> PassResult:
        with np.load(path, allow_pickle=False) as z:
            h, w = (int(x) for x in z["size"])
            names = tuple(str(x) for x in z["class_names"].reshape(-1))
            return cls(h, w, names, z["boxes"], z["scores"], z["bits"])


class LabelCache:
    """A folder of :class:`PassResult` files addressed by :func:`cache_key` digests.

    Layout: ``<root>/<key[:2]>/<key>.npz``. An unreadable entry counts as a miss and is overwritten by
    the next :meth:`put`.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.hits = 0
        """Number of :meth:`get` calls answered from disk."""
        self.misses = 0
        """Number of :meth:`get` calls that found nothing usable."""

    def path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}.npz"

    def get(self, key: str) -> PassResult | None:
        p = self.path(key)
        if p.is_file():
            try:
                result = PassResult.load(p)
            except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
                pass  # A damaged entry is recomputed; it is overwritten atomically by put().
            else:
                self.hits += 1
                return result
        self.misses += 1
        return None

    def put(self, key: str, result: PassResult) -> None:
        result.save(self.path(key))

    def __contains__(self, key: str) -> bool:
        return self.path(key).is_file()


__all__ = [
    "CACHE_FORMAT",
    "LabelCache",
    "PassResult",
    "cache_key",
    "default_cache_dir",
    "image_digest",
    "pass_cache_dir",
]
