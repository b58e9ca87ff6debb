"""The 2D labeler interface and its compact result type.

A labeler turns one camera image into M masks, each with a class distribution and a confidence
(docs/METHOD.md stage A). Masks are kept as packed bits; a dense float H×W×C array is never stored.
"""

from __future__ import annotations

import dataclasses
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from leap_core.errors import DatasetError, LeapError
from leap_core.io_utils import atomic_save_npz
from leap_core.labelers.cache import LabelCache, image_digest

if TYPE_CHECKING:
    from leap_core.datasets.kitti import Frame
    from leap_core.schema import Schema


@dataclass(frozen=True)
class Instances:
    """The object instances of one image: which instance each pixel shows, and each instance's class.

    Attributes:
        ids: (H, W) int32 instance id per pixel; 0 = no instance, k = instance k (1..N).
        label: (N,) int16 class index of instance k at row k-1 (a thing class of the schema).
        score: (N,) float32 in (0, 1], instance k's score at row k-1 (a detector box's or a mask's).

    One pixel shows at most one instance. Where the masks of several instances overlap, the
    higher-scoring instance takes the pixel (ties: the one given first); an instance left with no pixel is
    dropped. Ids are numbered by descending score: instance 1 scores highest
    (:meth:`from_masks`, :meth:`from_id_image`).
    """

    ids: npt.NDArray[np.int32]
    label: npt.NDArray[np.int16]
    score: npt.NDArray[np.float32]

    def __post_init__(self) -> None:
        n = self.label.shape[0]
        if self.ids.ndim != 2 or self.label.shape != (n,) or self.score.shape != (n,):
            raise ValueError(
                f"instance ids {self.ids.shape} must be (H, W) and label {self.label.shape} / score "
                f"{self.score.shape} (N,)"
            )

    @property
    def num_instances(self) -> int:
        return int(self.label.shape[0])

    @classmethod
    def empty(cls, height: int, width: int) -> Instances:
        return cls(np.zeros((height, width), np.int32), np.zeros(0, np.int16), np.zeros(0, np.float32))

    @classmethod
    def from_masks(cls, masks: npt.ArrayLike, label: npt.ArrayLike, score: npt.ArrayLike) -> Instances:
        """Instances of (M, H, W) boolean masks with their (M,) class indices and scores, by the overlap
        rule of the class docstring."""
        m = np.asarray(masks, dtype=bool)
        if m.ndim != 3:
            raise ValueError(f"instance masks must be (M, H, W), got shape {m.shape}")
        _, h, w = m.shape
        return cls.from_bits(np.packbits(m.reshape(m.shape[0], h * w), axis=1), h, w, label, score)

    @classmethod
    def from_bits(
        cls, bits: npt.NDArray[np.uint8], height: int, width: int, label: npt.ArrayLike, score: npt.ArrayLike
    ) -> Instances:
        """:meth:`from_masks` of (M, ceil(H*W/8)) packed masks (``np.packbits`` of each row-major mask),
        unpacked one at a time."""
        lab = np.asarray(label, dtype=np.int16).reshape(-1)
        sc = np.asarray(score, dtype=np.float32).reshape(-1)
        if bits.shape[0] != lab.shape[0] or sc.shape != lab.shape:
            raise ValueError(f"{bits.shape[0]} masks but label {lab.shape} / score {sc.shape}")
        order = np.argsort(-sc, kind="stable")
        n = height * width
        flat = np.zeros(n, np.int32)
        # Painted from the lowest priority up, so the higher-scoring (then earlier) mask overwrites.
        for rank in range(order.size - 1, -1, -1):
            covered = np.unpackbits(bits[order[rank]], count=n).astype(bool)
            flat[covered] = rank + 1
        return cls._compact(flat.reshape(height, width), lab[order], sc[order])

    @classmethod
    def from_id_image(cls, ids: npt.ArrayLike, label: npt.ArrayLike, score: npt.ArrayLike) -> Instances:
        """Instances of an (H, W) id image whose id k (1..N) has class ``label[k-1]`` and score
        ``score[k-1]``, renumbered by descending score (ties: lower id first); ids without a pixel are
        dropped."""
        img = np.asarray(ids)
        lab = np.asarray(label, dtype=np.int16).reshape(-1)
        sc = np.asarray(score, dtype=np.float32).reshape(-1)
        if img.ndim != 2 or sc.shape != lab.shape or (img.size and (img.min() < 0 or img.max() > lab.size)):
            raise ValueError(f"id image {img.shape} must be (H, W) with ids 0..{lab.size}")
        order = np.argsort(-sc, kind="stable")
        rank = np.zeros(lab.size + 1, np.int32)
        rank[order + 1] = np.arange(1, lab.size + 1, dtype=np.int32)
        return cls._compact(rank[img], lab[order], sc[order])

    @classmethod
    def _compact(
        cls, ids: npt.NDArray[np.int32], label: npt.NDArray[np.int16], score: npt.NDArray[np.float32]
    ) -> Instances:
        """Drop the instances without a pixel and number the others 1..N, keeping their order."""
        present = np.bincount(ids.ravel(), minlength=label.size + 1)[1:] > 0
        if present.all():
            return cls(ids, label, score)
        new = np.zeros(label.size + 1, np.int32)
        new[1:][present] = np.arange(1, int(present.sum()) + 1, dtype=np.int32)
        return cls(new[ids], label[present], score[present])

    def masks(self) -> npt.NDArray[np.bool_]:
        """(N, H, W) boolean mask of each instance (for tests and display)."""
        out: npt.NDArray[np.bool_] = self.ids[None] == np.arange(1, self.num_instances + 1)[:, None, None]
        return out

    def mirrored(self) -> Instances:
        """The same instances for the image mirrored left to right."""
        return Instances(np.ascontiguousarray(self.ids[:, ::-1]), self.label, self.score)

    def joined(self, other: Instances) -> Instances:
        """Both images' instances as one set, by the overlap rule (``self``'s first where scores tie)."""
        if other.ids.shape != self.ids.shape:
            raise ValueError(f"cannot join instances of {other.ids.shape} with {self.ids.shape} images")
        h, w = self.ids.shape
        return Instances.from_masks(
            np.concatenate([self.masks(), other.masks()]).reshape(-1, h, w),
            np.concatenate([self.label, other.label]),
            np.concatenate([self.score, other.score]),
        )


@dataclass(frozen=True)
class SoftMasks:
    """Soft 2D labels of one image.

    Attributes:
        height, width: image size in pixels.
        bits: (M, ceil(H*W/8)) uint8, ``np.packbits`` of each row-major flattened boolean mask.
        probs: (M, C) float32, per-mask class distribution p(q, ·); rows sum to 1.
        confidence: (M,) float32 in (0, 1], the mask's weight where masks overlap (its max similarity).
        instances: the image's object instances (:class:`Instances`: thing classes only), or None where
            the labels carry none (a file written before instances existed).

    The per-pixel distribution is p(u,v) = Σ_m w_m·1[m covers (u,v)]·p_m / Σ_m w_m·1[m covers (u,v)];
    pixels covered by no mask carry no observation.
    """

    height: int
    width: int
    bits: npt.NDArray[np.uint8]
    probs: npt.NDArray[np.float32]
    confidence: npt.NDArray[np.float32]
    instances: Instances | None = None

    @property
    def num_masks(self) -> int:
        return int(self.probs.shape[0])

    @property
    def num_classes(self) -> int:
        return int(self.probs.shape[1])

    @classmethod
    def from_dense(
        cls,
        masks: npt.NDArray[np.bool_],
        probs: npt.ArrayLike,
        confidence: npt.ArrayLike,
        num_classes: int | None = None,
        instances: Instances | None = None,
    ) -> SoftMasks:
        """Pack (M, H, W) boolean masks. ``num_classes`` is needed only when M = 0."""
        masks = np.asarray(masks, dtype=bool)
        if masks.ndim != 3:
            raise ValueError(f"masks must be (M, H, W), got shape {masks.shape}")
        m, h, w = masks.shape
        probs_arr = np.asarray(probs, dtype=np.float32)
        if m == 0 and probs_arr.size == 0:
            probs_arr = np.zeros((0, num_classes or 0), dtype=np.float32)
        conf = np.asarray(confidence, dtype=np.float32).reshape(-1)
        if probs_arr.ndim != 2 or probs_arr.shape[0] != m or conf.shape[0] != m:
            raise ValueError(f"probs {probs_arr.shape} / confidence {conf.shape} do not match {m} masks")
        bits = (
            np.packbits(masks.reshape(m, h * w), axis=1) if m else np.zeros((0, (h * w + 7) // 8), np.uint8)
        )
        return cls(height=h, width=w, bits=bits, probs=probs_arr, confidence=conf, instances=instances)

    @classmethod
    def empty(cls, height: int, width: int, num_classes: int) -> SoftMasks:
        """No mask and no instance."""
        return cls.from_dense(
            np.zeros((0, height, width), bool),
            np.zeros((0, num_classes)),
            [],
            num_classes,
            Instances.empty(height, width),
        )

    def dense(self) -> npt.NDArray[np.bool_]:
        """(M, H, W) boolean masks."""
        n = self.height * self.width
        flat = np.unpackbits(self.bits, axis=1, count=n).astype(bool)
        return flat.reshape(self.num_masks, self.height, self.width)

    def mask(self, i: int) -> npt.NDArray[np.bool_]:
        n = self.height * self.width
        return np.unpackbits(self.bits[i], count=n).astype(bool).reshape(self.height, self.width)

    def membership(self, u: npt.NDArray[np.integer], v: npt.NDArray[np.integer]) -> npt.NDArray[np.bool_]:
        """(M, P) bool: does mask m cover pixel (u_p, v_p)? u = column, v = row, both in range."""
        flat = v.astype(np.int64) * self.width + u.astype(np.int64)
        byte, bit = flat >> 3, (7 - (flat & 7)).astype(np.uint8)
        return ((self.bits[:, byte] >> bit) & 1).astype(bool)

    def pixel_probs(self) -> npt.NDArray[np.float32]:
        """(H, W, C) dense per-pixel distribution (zeros where no mask). For display and tests only."""
        dense = self.dense().astype(np.float32)  # (M, H, W)
        w = dense * self.confidence[:, None, None]
        num = np.einsum("mhw,mc->hwc", w, self.probs)
        den = w.sum(axis=0)[..., None]
        out: npt.NDArray[np.float32] = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
        return out

    def mirrored(self) -> SoftMasks:
        """The same labels for the image mirrored left to right (column u becomes W-1-u)."""
        dense = self.dense()[:, :, ::-1]
        inst = None if self.instances is None else self.instances.mirrored()
        return SoftMasks.from_dense(dense, self.probs, self.confidence, self.num_classes, inst)

    def joined(self, other: SoftMasks) -> SoftMasks:
        """Both sets of masks as one: where masks of both overlap, the per-pixel rule above averages
        their distributions weighted by confidence. The instances are both sets joined by the overlap rule
        (:meth:`Instances.joined`); None when either has none.

        Raises:
            ValueError: ``other`` has another image size or class count.
        """
        if (other.height, other.width, other.num_classes) != (self.height, self.width, self.num_classes):
            raise ValueError(
                f"cannot join soft masks of {other.height}×{other.width}, {other.num_classes} classes with "
                f"{self.height}×{self.width}, {self.num_classes} classes"
            )
        return SoftMasks(
            self.height,
            self.width,
            np.concatenate([self.bits, other.bits], axis=0),
            np.concatenate([self.probs, other.probs], axis=0),
            np.concatenate([self.confidence, other.confidence], axis=0),
            None
            if self.instances is None or other.instances is None
            else self.instances.joined(other.instances),
        )

    def arrays(self) -> dict[str, npt.NDArray[Any]]:
        """The members of a 2D label file: ``size``, ``bits``, ``probs``, ``confidence`` and, with
        instances, ``instance_ids`` (H, W) int32, ``instance_label`` (N,) int16 and ``instance_score`` (N,)
        float32."""
        out: dict[str, npt.NDArray[Any]] = {
            "size": np.array([self.height, self.width], dtype=np.int64),
            "bits": self.bits,
            "probs": self.probs,
            "confidence": self.confidence,
        }
        if self.instances is not None:
            out["instance_ids"] = self.instances.ids
            out["instance_label"] = self.instances.label
            out["instance_score"] = self.instances.score
        return out

    @classmethod
    def from_arrays(cls, z: Mapping[str, npt.NDArray[Any]]) -> SoftMasks:
        """The labels of a 2D label file's members (:meth:`arrays`); a file without the instance members
        (written before instances existed) gives ``instances=None``.

        Raises:
            KeyError, ValueError: a member is missing or does not fit the others.
        """
        h, w = (int(x) for x in z["size"])
        inst = None
        if "instance_ids" in z:
            inst = Instances(
                np.asarray(z["instance_ids"], np.int32),
                np.asarray(z["instance_label"], np.int16),
                np.asarray(z["instance_score"], np.float32),
            )
            if inst.ids.shape != (h, w):
                raise ValueError(f"instance ids {inst.ids.shape} do not match the image size {(h, w)}")
        return cls(h, w, z["bits"], z["probs"].astype(np.float32), z["confidence"].astype(np.float32), inst)

    def save(self, path: str | Path) -> None:
        atomic_save_npz(path, **self.arrays())

    @classmethod
    def load(cls, path: str | Path) -> SoftMasks:
        try:
            with np.load(path) as z:
                return cls.from_arrays({k: z[k] for k in z.files})
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            raise DatasetError(path, f"unreadable 2D label file ({exc})") from exc


def with_flip_votes(
    images: Sequence[npt.NDArray[np.uint8]],
    label: Callable[[list[npt.NDArray[np.uint8]]], list[SoftMasks]],
) -> list[SoftMasks]:
    """Flip votes: ``label`` each image and its left-right mirror in one call, and join each image's
    labels with its mirror's mirrored back (:meth:`SoftMasks.joined`), keeping the image's own instances
    (the mirror's are the same objects found again: joined, each would show up twice).

    A pixel that masks of both views cover gets the confidence-weighted mean of their distributions; one
    that only one view covers keeps that view's (a view that found nothing there casts no vote). The
    labeler runs on twice the images: twice the 2D stage's time.
    """
    mirrors = [np.ascontiguousarray(im[:, ::-1]) for im in images]
    out = label([*images, *mirrors])
    n = len(images)
    joined = []
    for i in range(n):
        mirror = dataclasses.replace(out[n + i], instances=None).mirrored()
        joined.append(dataclasses.replace(out[i].joined(mirror), instances=out[i].instances))
    return joined


class Labeler(Protocol):
    """Produces :class:`SoftMasks` for one frame's camera image."""

    name: str
    """Short id shown to users ("simulated", "grounded-sam")."""

    def fingerprint(self, schema: Schema) -> str:
        """A string that changes whenever this labeler's output for the same image would change."""
        ...

    def label(self, frame: Frame, schema: Schema) -> SoftMasks:
        """Label ``frame.image`` for the classes of ``schema`` (probs has ``len(schema.classes)`` columns)."""
        ...


class ImageModelLabeler:
    """A :class:`Labeler` that runs models on camera images, with a 2D cache (``leap labels2d`` fills it).
    The base gives what they share: the input check, flip votes and the cache test. A subclass sets
    ``name``, ``cache`` and ``flip_votes`` and gives :meth:`_label` (the labels of images, reading and
    filling its cache), :meth:`cache_keys` (the cache entries one image needs) and the methods below that
    raise ``NotImplementedError``."""

    name: str
    cache: LabelCache | None
    flip_votes: bool

    def cache_keys(self, digest: str, schema: Schema) -> list[str]:
        """The cache keys labeling the image with content digest ``digest`` reads."""
        raise NotImplementedError

    @property
    def uses_random_weights(self) -> bool:
        """True when a model folder holds tiny random test weights (meaningless labels)."""
        raise NotImplementedError

    def fingerprint(self, schema: Schema) -> str:
        """A string that changes whenever this labeler's output for the same image would change."""
        raise NotImplementedError

    def work_per_image(self, schema: Schema) -> str:
        """What labeling one image costs, for a summary line (``2 detector pass(es) per image``)."""
        raise NotImplementedError

    def forward_passes(self) -> dict[str, int]:
        """Forward passes run so far by model part (``{"detector": 3, "SAM encoder": 3}``)."""
        raise NotImplementedError

    def _label(self, images: Sequence[npt.NDArray[np.uint8]], schema: Schema) -> list[SoftMasks]:
        raise NotImplementedError

    def label(self, frame: Frame, schema: Schema) -> SoftMasks:
        """Soft masks of ``frame.image`` (probs has ``len(schema.classes)`` columns)."""
        return self.label_images([frame.image], schema)[0]

    def label_frames(self, frames: Sequence[Frame], schema: Schema) -> list[SoftMasks]:
        """:meth:`label` for several frames, batched through the models."""
        return self.label_images([f.image for f in frames], schema)

    def label_images(self, images: Sequence[npt.NDArray[np.uint8]], schema: Schema) -> list[SoftMasks]:
        """Soft masks of (H, W, 3) uint8 RGB images; cached results are read, the others computed and
        written to the cache (with flip votes, of the images and their mirrors).

        Raises:
            LeapError: an image is not (H, W, 3) uint8.
        """
        for im in images:
            if im.ndim != 3 or im.shape[2] != 3 or im.dtype != np.uint8:
                raise LeapError(f"{self.name} labels (H, W, 3) uint8 RGB images, got {im.shape} {im.dtype}")
        if self.flip_votes:
            return with_flip_votes(images, lambda ims: self._label(ims, schema))
        return self._label(images, schema)

    def is_cached(self, image: npt.NDArray[np.uint8], schema: Schema) -> bool:
        """Whether labeling ``image`` reads only the cache (its mirror's entries too with flip votes)."""
        if self.cache is None:
            return False
        images = [image, np.ascontiguousarray(image[:, ::-1])] if self.flip_votes else [image]
        return all(k in self.cache for im in images for k in self.cache_keys(image_digest(im), schema))


def model_dtype(device: str, half_precision: bool) -> Any:
    """The torch dtype a model labeler runs its models in on ``device`` ("cpu" or "cuda"):
    ``torch.float16`` when its ``half_precision`` setting is on and the device is a CUDA GPU, else
    ``torch.float32``. The CPU ignores the setting: float16 is no reliable speed-up there, and the CPU's
    float32 labels stay the reference that tests compare with transformers."""
    import torch  # noqa: PLC0415  every labeler imports this module; only a model labeler's models need torch

    return torch.float16 if half_precision and device == "cuda" else torch.float32


def passes_text(passes: dict[str, int]) -> str:
    """``3 detector and 3 SAM encoder forward passes``."""
    return " and ".join(f"{n} {part}" for part, n in passes.items()) + " forward passes"
