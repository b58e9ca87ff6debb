"""Small shared types and constants."""

from __future__ import annotations

from typing import Final

UNLABELED: Final[int] = -1
"""Class index used for points / voxels / pixels that carry no label (int16 arrays)."""

LABEL_DTYPE: Final = "int16"
"""dtype of per-point and per-voxel class-index arrays."""
