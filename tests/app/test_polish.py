"""Small things a user meets: the CLI's stage lines, viser's silent start and the dataset picker."""

from __future__ import annotations

import io
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import appfixtures
import pytest
from apphelpers import API
from fastapi.testclient import TestClient

from app.cli import SequenceBars
from app.core.config import Settings
from leap_core.config import PipelineConfig
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.presets import load_preset

client, data_root, settings, tiny_dataset = (
    appfixtures.client,
    appfixtures.data_root,
    appfixtures.settings,
    appfixtures.tiny_dataset,
)


def test_dataset_picker_lists_the_demo_street_but_no_run_folder(
    client: TestClient, settings: Settings, tiny_dataset: Path, make_tiny_sequence: Callable[..., Any]
) -> None:
    """The work folder lies inside the data root: its demo street and farm drone demo are offered, its runs
    and caches not."""
    demo = make_tiny_sequence(settings.work_dir / "demo", n_frames=2, n_points=50)
    assert demo.root == settings.demo_dataset
    farm = make_tiny_sequence(settings.work_dir / "demo-agri", n_frames=2, n_points=50)
    assert farm.root == settings.demo_agri_dataset
    make_tiny_sequence(settings.work_dir / "runs" / "p1" / "r1", n_frames=1, n_points=50)
    paths = [d["path"] for d in client.get(f"{API}/datasets").json()["data"]]
    assert sorted(paths) == sorted(
        [str(tiny_dataset), str(settings.demo_dataset), str(settings.demo_agri_dataset)]
    )


def test_cli_shows_skipped_stages_as_lines_and_logs_above_the_bars(
    tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A second run on the same folder computes nothing: every stage prints ``skipped`` instead of a full
    bar; a warning logged while a bar is open starts on its own line."""
    preset = load_preset("semantickitti")
    cfg: PipelineConfig = preset.pipeline
    out = tmp_path / "run"
    err = io.StringIO()
    monkeypatch.setattr("sys.stderr", err)  # tqdm and the logging handler write to sys.stderr
    specs = [SequenceSpec.of(tiny_dataset)]
    with SequenceBars(out, ["00"]) as bars:
        run_pipeline(specs, preset.schema, cfg, out, progress=bars)
    first = err.getvalue()
    assert "3dcn         skipped (3D-CN disabled)" in first, first
    assert "labels2d" in first and "skipped (unchanged" not in first

    err.truncate(0)
    err.seek(0)
    with SequenceBars(out, ["00"]) as bars:
        bars("00", "labels2d", 0, 4)
        logging.getLogger("leap_core.test").warning("a warning during a bar")
        bars("00", "labels2d", 4, 4)
        run_pipeline(specs, preset.schema, cfg, out, progress=bars)
    second = err.getvalue()
    for stage in ("project", "fuse", "smooth", "label_points", "tracks", "evaluate", "export"):
        assert f"{stage:<12} skipped (unchanged since the last run in this folder)" in second, second
    lines = second.replace("\r", "\n").splitlines()
    assert "a warning during a bar" in lines, second


def test_the_viewer_prints_no_viser_banner(capfd: pytest.CaptureFixture[str]) -> None:
    """viser prints a panel naming its internal port on start (users must use the app's relay instead)."""
    from app.viewer.scene import ReviewScene

    scene = ReviewScene()
    port = scene.port
    scene.stop()
    out, err = capfd.readouterr()
    assert "viser" not in out + err and str(port) not in out + err, out + err


@pytest.mark.slow
def test_the_server_prints_its_url_on_a_line_of_its_own(tmp_path: Path) -> None:
    from serverproc import Server

    data = tmp_path / "data"
    data.mkdir()
    server = Server(data).start()
    server.stop()
    lines = (data / "server.log").read_text().splitlines()
    assert f"LeAP Studio: http://127.0.0.1:{server.port}/" in lines, lines
