"""lab/table2.py: Table 2's gains, Markdown and target from hand-made rows; the source-domain class
mapping; the coarsened generator configs."""

from __future__ import annotations

import numpy as np

from lab import table2
from leap_core.presets import builtin_preset
from leap_core.synth.agri import AgriSynthConfig
from leap_core.synth.generator import SynthConfig


def _rows(voxel: list[float]) -> dict[str, list[float]]:
    return {"source-only": [30.0], "voxel labels": voxel, "+3D-CN labels": [50.0, 52.0], "oracle": [60.0]}


def test_gains_are_each_seed_minus_source_only() -> None:
    g = table2.gains(_rows([41.0, 39.0]))
    assert g == {"voxel labels": [11.0, 9.0], "+3D-CN labels": [20.0, 22.0], "oracle": [30.0]}


def test_target_needs_every_seed_above_source_only() -> None:
    assert table2.beats_source_only(_rows([31.0, 35.0]))
    assert not table2.beats_source_only(_rows([31.0, 29.0]))
    assert not table2.beats_source_only({"source-only": [30.0]})


def test_markdown_has_mean_std_gains_and_the_paper_s_gains() -> None:
    md = table2.table_markdown([(table2.DOMAINS["agri"], _rows([41.0, 39.0]))])
    lines = md.splitlines()
    assert lines[2] == "| street → farm (agri-uav) | mIoU | 30.0 | 40.0 ± 1.4 | 51.0 ± 1.4 | 60.0 |"
    assert lines[3] == "| | gain | — | +10.0 ± 1.4 | +21.0 ± 1.4 | +30.0 |"
    assert lines[4] == "| | *paper, SemanticKITTI → AgriUAV*, gain | — | *+20.5* | *+34.2* | — |"


def test_the_street_ground_truth_reads_as_farm_classes() -> None:
    farm = builtin_preset("agri_uav").schema
    mapped = table2.mapped_schema(farm, table2.DOMAINS["agri"].source_classes or {})
    assert mapped.names == farm.names
    assert np.array_equal(mapped.export_ids(), farm.export_ids())
    raw = np.array([70, 40, 50, 10, 7], np.uint32)  # vegetation, road, building, car, a farm id
    got = mapped.map_gt(raw).tolist()
    assert got == [farm.index("tree"), farm.index("ground"), farm.index("building"), -1, -1]


def test_coarser_lidar_for_both_domains() -> None:
    street = table2.synth_config("street", 4, 0, 3)
    assert isinstance(street, SynthConfig)
    assert street.lidar.azimuth_step_deg == SynthConfig().lidar.azimuth_step_deg * 3
    farm = table2.synth_config("agri-uav", 4, 0, 4)
    assert isinstance(farm, AgriSynthConfig)
    assert farm.lidar.columns == AgriSynthConfig().lidar.columns // 4
