"""Prompt text, token↔prompt mapping, token-budget splitting and the stage-A region maths (docs/METHOD.md).

Everything here is a pure function on strings and arrays: no model, no I/O. The Grounding DINO labeler
(:mod:`leap_core.labelers.grounded_sam`) feeds it the tokenizer offsets and the detector outputs.

Vocabulary used throughout:

* **phrase**: one prompt string in the detector text. The text of a pass is ``"p1 . p2 . … pK ."``;
  Grounding DINO splits phrases at ``.`` (and ``?``), so every phrase gets its own token columns.
  A phrase may serve several roles (the positive prompt of one class and a negative prompt of another);
  it is written once and its columns are shared.
* **pass**: one detector forward pass with one text. A pass covers a set of classes; all their prompts
  (and, optionally, their negative prompts) are phrases of that pass.
* **Q, T, C, R, P**: detector queries (900 for the real model), text-token columns (256), schema classes,
  kept regions, phrases of a pass.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from leap_core.errors import SchemaError

PHRASE_SEPARATOR = " . "
"""Between two phrases of the detector text; the text also ends with ``" ."``."""

SPECIAL_TOKENS_PER_PASS = 2
"""[CLS] and [SEP]: text-token columns every pass spends besides its phrases."""

NEG_INF = np.float32(-np.inf)


# ------------------------------------------------------------------------------------------- text
def build_text(phrases: Sequence[str]) -> tuple[str, list[tuple[int, int]]]:
    """Join phrases into one detector text and return each phrase's character span.

    ``["car", "parking lot"]`` → ``("car . parking lot .", [(0, 3), (6, 17)])``.

    Raises:
        ValueError: if a phrase is empty or contains ``.`` or ``?`` (it would split into two phrases).
    """
    text = ""
    spans: list[tuple[int, int]] = []
    for phrase in phrases:
        p = " ".join(phrase.split())
        if not p or "." in p or "?" in p:
            raise ValueError(f"prompt {p!r} is empty or contains '.'/'?', which separate detector phrases")
        if text:
            text += PHRASE_SEPARATOR
        spans.append((len(text), len(text) + len(p)))
        text += p
    return text + " .", spans


def token_phrase_index(
    offsets: npt.ArrayLike, spans: Sequence[tuple[int, int]], num_columns: int | None = None
) -> npt.NDArray[np.int64]:
    """Which phrase each text-token column belongs to, from the tokenizer's character offsets.

    Args:
        offsets: (T', 2) ``(start, end)`` character offsets per token, as returned by the tokenizer with
            ``return_offsets_mapping=True``; special tokens have ``(0, 0)``.
        spans: (P,) character span ``(start, end)`` of each phrase in the text (from :func:`build_text`).
        num_columns: T, the width of the detector's logit matrix (≥ T'); extra columns map to -1.

    Returns:
        (T,) int64: phrase index of column t, or -1 for [CLS], [SEP], ``.`` separators and padding.
        A token belongs to phrase j iff ``start_j <= start_t`` and ``end_t <= end_j`` and the token is
        non-empty.
    """
    off = np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
    t = off.shape[0] if num_columns is None else int(num_columns)
    out = np.full(t, -1, dtype=np.int64)
    n = min(t, off.shape[0])
    start, end = off[:n, 0], off[:n, 1]
    nonempty = end > start
    for j, (s, e) in enumerate(spans):
        out[:n][nonempty & (start >= s) & (end <= e)] = j
    return out


# ------------------------------------------------------------------------------------------ passes
@dataclass(frozen=True)
class ClassPrompts:
    """The prompts of one schema class, as the planner sees them."""

    index: int
    """Schema class index."""
    name: str
    """Class name (part of cache keys, so a pass result can be mapped back to schema columns)."""
    prompts: tuple[str, ...]
    """Positive prompts (≥ 1)."""
    negatives: tuple[str, ...] = ()
    """Negative prompts ("not this"); empty when negatives are disabled."""


@dataclass(frozen=True)
class PassPlan:
    """One detector pass: its text and how its phrases map to classes.

    ``positive[j, k]`` / ``negative[j, k]`` say that phrase j is a positive / negative prompt of the
    pass's k-th class ``classes[k]``.
    """

    classes: tuple[ClassPrompts, ...]
    """Classes scored by this pass, in schema order."""
    phrases: tuple[str, ...]
    """Unique phrases in text order (case-insensitive dedup)."""
    text: str
    """``"p1 . p2 . … ."``"""
    spans: tuple[tuple[int, int], ...]
    """Character span of each phrase in ``text``."""
    positive: npt.NDArray[np.bool_]
    """(P, K) phrase j is a prompt of class k."""
    negative: npt.NDArray[np.bool_]
    """(P, K) phrase j is a negative prompt of class k."""
    num_tokens: int
    """Text-token columns this pass uses, [CLS] and [SEP] included."""

    @property
    def class_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.classes)

    def key_parts(self) -> dict[str, object]:
        """Everything about the pass that changes its output (for cache keys)."""
        return {
            "text": self.text,
            "classes": [[c.name, list(c.prompts), list(c.negatives)] for c in self.classes],
        }


def make_pass(classes: Sequence[ClassPrompts], token_count: Callable[[str], int]) -> PassPlan:
    """Build the pass covering ``classes``: dedup phrases, build the text, count its tokens.

    Args:
        classes: classes of the pass (in schema order).
        token_count: number of word-piece tokens of a phrase (no special tokens), from the tokenizer.
    """
    phrases: list[str] = []
    where: dict[str, int] = {}
    roles: list[tuple[int, int, bool]] = []  # (phrase, class-in-pass, negative)
    for k, c in enumerate(classes):
        for negative, plist in ((False, c.prompts), (True, c.negatives)):
            for p in plist:
                norm = " ".join(p.split())
                key = norm.lower()
                if key not in where:
                    where[key] = len(phrases)
                    phrases.append(norm)
                roles.append((where[key], k, negative))
    pos = np.zeros((len(phrases), len(classes)), dtype=bool)
    neg = np.zeros_like(pos)
    for j, k, negative in roles:
        (neg if negative else pos)[j, k] = True
    # A phrase that is one class's prompt and another's negative is written once: both read its columns.
    text, spans = build_text(phrases)
    n_tokens = SPECIAL_TOKENS_PER_PASS + sum(token_count(p) + 1 for p in phrases)  # +1: the "." after it
    return PassPlan(
        classes=tuple(classes),
        phrases=tuple(phrases),
        text=text,
        spans=tuple(spans),
        positive=pos,
        negative=neg,
        num_tokens=n_tokens,
    )


def plan_passes(
    classes: Sequence[ClassPrompts],
    token_count: Callable[[str], int],
    budget: int,
    mode: str = "joint",
) -> list[PassPlan]:
    """Split the classes into detector passes.

    ``mode="per-class"``: one pass per class. ``mode="joint"``: as few passes as the text-token budget
    allows; classes are packed in schema order (next-fit), and a class is never split across passes,
    so each class's score for a region always comes from one text (its own pass).

    Args:
        classes: all classes, in schema order.
        token_count: word-piece tokens of one phrase (no special tokens).
        budget: text-token columns of one pass ([CLS]/[SEP] included), e.g. 256.
        mode: ``"joint"`` or ``"per-class"``.

    Raises:
        SchemaError: when one class's prompts alone exceed the budget (naming the class and the counts).
    """
    passes: list[PassPlan] = []
    for c in classes:
        alone = make_pass([c], token_count)
        if alone.num_tokens > budget:
            raise SchemaError(
                f"class {c.name!r}: its prompts need {alone.num_tokens} text tokens, more than the "
                f"detector's {budget} per pass; shorten its prompt list"
            )
    if mode == "per-class":
        return [make_pass([c], token_count) for c in classes]
    if mode != "joint":
        raise ValueError(f"mode must be 'joint' or 'per-class', got {mode!r}")
    current: list[ClassPrompts] = []
    for c in classes:
        trial = make_pass([*current, c], token_count)
        if current and trial.num_tokens > budget:
            passes.append(make_pass(current, token_count))
            current = [c]
        else:
            current.append(c)
    if current:
        passes.append(make_pass(current, token_count))
    return passes


# ------------------------------------------------------------------------------ region mathematics
def phrase_max(
    logits: npt.ArrayLike, token_phrase: npt.ArrayLike, membership: npt.ArrayLike
) -> npt.NDArray[np.float32]:
    """Max logit over the token columns of each group of phrases.

    .. math:: s(q,k) = \\max_{t:\\ M[\\mathrm{phrase}(t),k]} L(q,t)\\quad (-\\infty \\text{ if no column})

    Args:
        logits: (Q, T) region↔token logits L.
        token_phrase: (T,) phrase index of each column, -1 for columns of no phrase.
        membership: (P, K) bool, phrase j belongs to group k (a class's prompts, or its negatives).

    Returns:
        (Q, K) float32.
    """
    lg = np.asarray(logits, dtype=np.float32)
    tp = np.asarray(token_phrase, dtype=np.int64)
    mem = np.asarray(membership, dtype=bool)
    q, k = lg.shape[0], mem.shape[1]
    out = np.full((q, k), NEG_INF, dtype=np.float32)
    for j in range(k):
        cols = np.flatnonzero((tp >= 0) & mem[np.clip(tp, 0, None), j])
        if cols.size:
            out[:, j] = lg[:, cols].max(axis=1)
    return out


def apply_negatives(positive: npt.ArrayLike, negative: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Rule out a class for a region that matches one of its negative prompts better than its prompts.

    .. math:: s'(q,k) = -\\infty \\text{ if } n(q,k) > s(q,k) \\text{ else } s(q,k)

    Args:
        positive: (R, K) class scores s from the positive prompts.
        negative: (R, K) scores n from each class's negative prompts (-inf where a class has none).
    """
    s = np.asarray(positive, dtype=np.float32)
    n = np.asarray(negative, dtype=np.float32)
    out: npt.NDArray[np.float32] = np.where(n > s, NEG_INF, s).astype(np.float32)
    return out


def sigmoid(x: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Numerically stable logistic function (sigmoid(-inf) = 0)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty_like(x)
    pos = x >= 0
    out[pos] = 1.0 / (1.0 + np.exp(-x[pos]))
    ex = np.exp(x[~pos])
    out[~pos] = ex / (1.0 + ex)
    return out.astype(np.float32)


def keep_regions(scores: npt.ArrayLike, threshold: float) -> npt.NDArray[np.bool_]:
    """Regions whose max similarity over the classes reaches the threshold.

    .. math:: \\mathrm{keep}(q) = \\max_k \\sigma(s(q,k)) \\ge \\tau

    Args:
        scores: (Q, K) class logits s (only prompt tokens count: [CLS], [SEP] and ``.`` never do).
        threshold: τ in (0, 1).

    Returns:
        (Q,) bool.
    """
    s = np.asarray(scores, dtype=np.float32)
    if s.shape[1] == 0:
        return np.zeros(s.shape[0], dtype=bool)
    keep: npt.NDArray[np.bool_] = sigmoid(s.max(axis=1)) >= np.float32(threshold)
    return keep


def softmax_classes(scores: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Softmax over classes of class logits; -inf columns get probability 0.

    .. math:: p(q,c) = \\frac{e^{s(q,c)}}{\\sum_{c'} e^{s(q,c')}}

    Args:
        scores: (R, C) with at least one finite value per row.
    """
    s = np.asarray(scores, dtype=np.float64)
    if s.shape[0] == 0:
        return np.zeros(s.shape, dtype=np.float32)
    m = s.max(axis=1, keepdims=True)
    if not np.isfinite(m).all():
        raise ValueError("every region needs at least one finite class score")
    e = np.exp(s - m)
    out: npt.NDArray[np.float32] = (e / e.sum(axis=1, keepdims=True)).astype(np.float32)
    return out


def box_iou(a: npt.ArrayLike, b: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """(A, B) intersection over union of xyxy boxes (A, 4) and (B, 4); 0 where the union is empty."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(rb - lt, 0, None).prod(axis=2)
    area_a = np.clip(a[:, 2:] - a[:, :2], 0, None).prod(axis=1)
    area_b = np.clip(b[:, 2:] - b[:, :2], 0, None).prod(axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
    out: npt.NDArray[np.float32] = iou.astype(np.float32)
    return out


def fill_across_passes(
    boxes: npt.ArrayLike,
    scores: npt.ArrayLike,
    pass_id: npt.ArrayLike,
    pass_classes: npt.ArrayLike,
    match_iou: float,
) -> npt.NDArray[np.float32]:
    """Give every region a logit for the classes outside its own pass.

    A region r of pass p has logits only for p's classes. For a class c of another pass, its logit
    becomes the max logit for c of the regions of c's pass whose box overlaps r's with IoU ≥
    ``match_iou`` (the same object seen with c's text), or -inf if there is none:

    .. math:: \\tilde s(r,c) = s(r,c) \\text{ if } c \\in \\mathrm{pass}(r) \\text{ else }
              \\max_{r' :\\ c\\in\\mathrm{pass}(r'),\\ \\mathrm{IoU}(r,r') \\ge \\theta} s(r',c)

    With one pass this is the identity. A class ruled out for r by a negative prompt of r's own pass
    (-inf) stays ruled out.

    Args:
        boxes: (R, 4) xyxy boxes of all regions of all passes.
        scores: (R, C) logits; entries of classes outside the region's pass are ignored.
        pass_id: (R,) pass index of each region.
        pass_classes: (num_passes, C) bool, class c is scored by pass p.
        match_iou: θ in (0, 1].

    Returns:
        (R, C) float32.
    """
    pid = np.asarray(pass_id, dtype=np.int64)
    member = np.asarray(pass_classes, dtype=bool)
    s = np.asarray(scores, dtype=np.float32)
    if s.shape[0] == 0:
        empty: npt.NDArray[np.float32] = s.copy()
        return empty
    in_pass = member[pid]  # (R, C)
    own: npt.NDArray[np.float32] = np.where(in_pass, s, NEG_INF).astype(np.float32)
    if np.unique(pid).size < 2:
        return own
    iou = box_iou(boxes, boxes)
    match = (iou >= np.float32(match_iou)) & (pid[:, None] != pid[None, :])
    out: npt.NDArray[np.float32] = own.copy()
    for c in range(s.shape[1]):
        col = np.where(match, own[None, :, c], NEG_INF)  # (R, R'): matched regions' logits for c
        out[:, c] = np.where(in_pass[:, c], own[:, c], col.max(axis=1))
    return out


__all__ = [
    "ClassPrompts",
    "PassPlan",
    "apply_negatives",
    "box_iou",
    "build_text",
    "fill_across_passes",
    "keep_regions",
    "make_pass",
    "phrase_max",
    "plan_passes",
    "sigmoid",
    "softmax_classes",
    "token_phrase_index",
]
