"""scripts/readme_tables.py: result tables are replaced between their markers only, every table the script
computes has its markers in docs/RESULTS.md, and the table text is built from metrics.json as documented."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest
from scripthelpers import load_script

ROOT = Path(__file__).resolve().parents[1]


def _module() -> ModuleType:
    return load_script("scripts/readme_tables.py")


def test_replace_tables_rewrites_only_between_each_pair_of_markers() -> None:
    rt = _module()
    text = (
        "intro\n<!-- table:a -->\nold a\n<!-- /table:a -->\nmiddle\n"
        "<!-- table:b -->\nold b\nmore b\n<!-- /table:b -->\nend\n"
    )
    out = rt.replace_tables(text, {"a": "new a", "b": "new b"})
    assert out == (
        "intro\n<!-- table:a -->\nnew a\n<!-- /table:a -->\nmiddle\n"
        "<!-- table:b -->\nnew b\n<!-- /table:b -->\nend\n"
    )
    # Replacing with what is there changes nothing (what --check relies on).
    assert rt.replace_tables(out, {"a": "new a", "b": "new b"}) == out
    # What lies between a table's markers, read back.
    assert rt.table_body(text, "b") == "old b\nmore b"
    assert rt.table_body(out, "a") == "new a"
    assert rt.table_body(text, "c") is None


def test_replace_tables_refuses_a_table_without_markers() -> None:
    rt = _module()
    with pytest.raises(SystemExit, match=r"table:b"):
        rt.replace_tables("<!-- table:a -->\nx\n<!-- /table:a -->\n", {"a": "y", "b": "z"})


def test_results_page_has_the_markers_of_every_table_the_script_writes() -> None:
    rt = _module()
    assert rt.RESULTS == ROOT / "docs" / "RESULTS.md"
    text = rt.RESULTS.read_text()
    for name in rt.TABLES:
        assert text.count(f"<!-- table:{name} -->") == 1, name
        assert text.count(f"<!-- /table:{name} -->") == 1, name
        assert text.index(f"<!-- table:{name} -->") < text.index(f"<!-- /table:{name} -->"), name


def _metrics(camera: list[float], all_: list[float], share: list[float]) -> dict[str, object]:
    rows = ["point", "voxel", "+3D-CN x1", "+3D-CN x2"]
    return {
        "camera": {r: {"miou": v, "labeled_share": 0.9} for r, v in zip(rows, camera, strict=True)},
        "all": {r: {"miou": v, "labeled_share": sh} for r, v, sh in zip(rows, all_, share, strict=True)},
        # Every point, not only those with ground truth: not what the row shows.
        "labeled_share_all_points": dict.fromkeys(rows, 0.5),
    }


def test_demo_table_rows_are_the_camera_and_all_points_miou_and_the_ground_truth_labeled_share() -> None:
    rt = _module()
    table = rt.demo_miou(
        _metrics([0.779, 0.8534, 0.79, None], [0.128, 0.441, 0.6194, 0.62], [0.1224, 0.584, 1.0, 1.0])
    )
    lines = table.splitlines()
    assert "Report seed 0" in lines[0] and "--3dcn-iterations 2" in lines[0]
    assert lines[-3] == "| camera view | 77.9 | 85.3 | 79.0 | n/a |"
    assert lines[-2] == "| all points | 12.8 | 44.1 | 61.9 | 62.0 |"
    assert lines[-1] == "| points labeled | 12.2 % | 58.4 % | 100 % | 100 % |"
    # A run with the paper's protocol (a SemanticKITTI schema) gets its row after the camera view's.
    m = _metrics([0.779, 0.8534, 0.79, None], [0.128, 0.441, 0.6194, 0.62], [0.1224, 0.584, 1.0, 1.0])
    m["paper"] = {
        r: {"miou": v}
        for r, v in zip(["point", "voxel", "+3D-CN x1", "+3D-CN x2"], [0.5, 0.61, 0.7, 0.71], strict=True)
    }
    lines = rt.demo_miou(m).splitlines()
    assert lines[-4] == "| camera view | 77.9 | 85.3 | 79.0 | n/a |"
    assert lines[-3] == "| paper's 11 classes (camera view) | 50.0 | 61.0 | 70.0 | 71.0 |"
    assert lines[-2] == "| all points | 12.8 | 44.1 | 61.9 | 62.0 |"
