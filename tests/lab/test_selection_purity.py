"""lab/selection_purity.py's pure parts: the taught-as counts and their table, by hand."""

from __future__ import annotations

import labfixtures
import numpy as np
import pytest

from lab import selection_purity as sp

lab_labeler = labfixtures.lab_labeler  # registers the lab's labeler for each test here


def test_taught_counts_by_hand() -> None:
    # gt:      0  0  1  1  1 -1  2
    # targets: 0  1  1 -1  1  0  0
    counts = sp.taught_counts([0, 0, 1, 1, 1, -1, 2], [0, 1, 1, -1, 1, 0, 0], 3)
    assert counts.tolist() == [[1, 1, 0], [0, 2, 0], [1, 0, 0]]
    with pytest.raises(ValueError, match="differ in shape"):
        sp.taught_counts([0, 1], [0], 2)


def test_purity_lines_by_hand() -> None:
    taught = np.array([[6, 3, 1], [0, 0, 0], [0, 4, 0]])
    gt_points = np.array([20, 5, 8])
    lines = sp.purity_lines(taught, gt_points, ["car", "truck", "person"], top=1)
    assert lines[2:] == [
        "| car | 20 | 50.0 % | 60.0 % | truck 30 % |",  # 10 of 20 selected, 6 of them right
        "| truck | 5 | 0 | - | - |",
        "| person | 8 | 50.0 % | 0.0 % | truck 100 % |",
    ]
    # a class without ground truth has no row
    assert len(sp.purity_lines(taught, np.array([20, 0, 8]), ["car", "truck", "person"])) == 4
