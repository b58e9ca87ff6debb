"""A real server on 127.0.0.1 facing untrusted settings and dataset files: a size, count or distance past
its bound is a 422 naming the field, the value and the range (never a worker running out of memory); a
per-frame file linked out of the data roots is named, never read; a label that is a directory and a
truncated camera image are named by the dataset check."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from appfixtures import add_gt2d
from conftest import build_tiny_sequence
from serverproc import Server

from leap_core.datasets.kitti import LINK_OUTSIDE


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``data/`` (the server's one data root) with ``tiny/sequences/00`` and a file outside it."""
    root = tmp_path_factory.mktemp("integrity")
    data = root / "data"
    seq = build_tiny_sequence(data / "tiny", n_frames=4, n_points=400)
    add_gt2d(seq.root, seq.frame_ids, (48, 64))
    (root / "outside.txt").write_bytes(b"root:x:0:0:root:/root:/bin/bash\n")
    return data


@pytest.fixture(scope="module")
def api(data: Path) -> Iterator[httpx.Client]:
    server = Server(data, extra_env={"LEAP_PREWARM_WORKERS": "false"}).start()
    try:
        with server.client() as client:
            yield client
    finally:
        server.stop()


def _copy(data: Path, name: str) -> Path:
    """A copy of the tiny sequence at ``data/<name>/sequences/00``."""
    return Path(shutil.copytree(data / "tiny" / "sequences" / "00", data / name / "sequences" / "00"))


def _create(api: httpx.Client, path: Path, **extra: Any) -> httpx.Response:
    return api.post(
        "/projects", json={"name": path.parts[-3], "dataset": {"kind": "folder", "path": str(path)}, **extra}
    )


def _findings(check: dict[str, Any], code: str) -> list[dict[str, Any]]:
    return [f for f in check["findings"] if f["code"] == code]


def test_settings_past_their_bounds_are_422_naming_field_value_and_range(
    api: httpx.Client, data: Path
) -> None:
    seq = data / "tiny" / "sequences" / "00"
    r = _create(api, seq, pipeline={"smoothing": {"k": 1_000_000_000}})
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "pipeline", "smoothing", "k"]
    assert err["msg"] == "pipeline.smoothing.k: must be in [1, 64], got 1000000000"

    r = _create(api, seq)
    assert r.status_code == 201, r.text
    project = r.json()
    for body, loc, msg in (
        (
            {"pipeline": {"fusion": {"voxel_size": 1e-320}}},
            ["body", "pipeline", "fusion", "voxel_size"],
            "pipeline.fusion.voxel_size: must be in [0.01, 10] m, got 1e-320",
        ),
        (
            {"pipeline": {"consistency": {"backbone": {"grid_cells": [0.8, 0.8, 0.001]}}}},
            ["body", "pipeline", "consistency", "backbone", "grid_cells"],
            "pipeline.consistency.backbone.grid_cells: must be in [0.1, 10] m, got 0.001",
        ),
        ({"form": {"k": 65}}, ["body", "form", "k"], "pipeline.smoothing.k: must be in [1, 64], got 65"),
        (
            {"form": {"voxel_size": 50.0}},
            ["body", "form", "voxel_size"],
            "pipeline.fusion.voxel_size: must be in [0.01, 10] m, got 50.0",
        ),
    ):
        r = api.patch(f"/projects/{project['id']}", json=body)
        assert r.status_code == 422, (body, r.text)
        assert r.json()["detail"][0]["loc"] == loc and r.json()["detail"][0]["msg"] == msg
    assert api.get(f"/projects/{project['id']}").json()["form"] == project["form"]  # nothing changed
    # The form offers the same ranges.
    form = {f["name"]: f for f in api.get("/pipeline").json()["form"]}
    assert (form["k"]["minimum"], form["k"]["maximum"]) == (1, 64)
    assert (form["voxel_size"]["minimum"], form["voxel_size"]["maximum"]) == (0.01, 10)


def test_a_label_linked_out_of_the_data_roots_is_named_and_never_read(api: httpx.Client, data: Path) -> None:
    seq = _copy(data, "linked")
    label = seq / "labels" / "000001.label"
    label.unlink()
    label.symlink_to(data.parent / "outside.txt")
    r = _create(api, seq)
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["loc"] == ["body", "dataset", "path"]
    assert f"{label.parent}: 000001.label is {LINK_OUTSIDE}" in err["msg"]
    assert "replace each link with a copy of the file it points to" in err["msg"]
    assert "bytes" not in err["msg"] and "outside.txt" not in err["msg"]  # its size, its name: nothing

    listed = {d["path"]: d["check"] for d in api.get("/datasets").json()["data"]}
    check = listed[str(seq)]
    assert check["verdict"] == "none"
    (finding,) = _findings(check, "linked_outside")
    assert finding["frames"] == ["000001"] and "000001.label" in finding["message"]


def test_a_label_that_is_a_directory_is_named(api: httpx.Client, data: Path) -> None:
    seq = _copy(data, "labeldir")
    label = seq / "labels" / "000003.label"
    label.unlink()
    label.mkdir()
    r = _create(api, seq)
    assert r.status_code == 201, r.text
    check = r.json()["dataset"]["check"]
    (finding,) = _findings(check, "not_a_file")
    assert finding["severity"] == "warning" and finding["path"] == str(label.parent)
    assert finding["message"].startswith(f"{label.parent}: 000003.label is a directory, not a file")
    assert "put the file itself in place" in finding["fix"]


def test_a_truncated_camera_image_is_named(api: httpx.Client, data: Path) -> None:
    seq = _copy(data, "truncated")
    image = seq / "image_2" / "000002.png"
    image.write_bytes(image.read_bytes()[:-40])
    r = _create(api, seq)
    assert r.status_code == 201, r.text  # the simulated labeler reads the 2D ground truth, not the images
    check = r.json()["dataset"]["check"]
    (finding,) = _findings(check, "images_damaged")
    assert finding["frames"] == ["000002"]
    assert "000002.png is a truncated PNG" in finding["message"] and "image_2" in finding["fix"]
    gsam = next(lab for lab in check["labelers"] if lab["name"] == "grounded-sam")
    assert not gsam["can_run"] and "damaged camera images" in gsam["reason"]
    assert check["images"]["present"] == 4
