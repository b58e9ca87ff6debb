"""lab/table1.py: Table 1's rows, gains, means and acceptance from hand-made metrics dicts, and the
seed project files and base-run links that let every seed share one base run."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import ModuleType
from typing import Any

import labfixtures
import numpy as np
import pytest
import yaml

from lab import table1
from leap_core.metrics import metrics_from_confusion
from leap_core.run_layout import RunLayout, write_run_spec

lab_labeler = labfixtures.lab_labeler  # registers the lab's labeler for each test here

ROOT = Path(__file__).resolve().parents[2]


def _module() -> ModuleType:
    return table1


def _metrics(
    point: float, voxel: float, x1: float | None, x2: float | None = None, protocol: str = "paper"
) -> dict[str, Any]:
    table: dict[str, Any] = {"point": {"miou": point}, "voxel": {"miou": voxel}}
    if x1 is not None:
        table["+3D-CN x1"] = {"miou": x1}
    if x2 is not None:
        table["+3D-CN x2"] = {"miou": x2}
    # A decoy protocol with other figures: the row must come from the protocol asked for.
    return {protocol: table, "decoy": {r: {"miou": 0.01} for r in ("point", "voxel", "+3D-CN x1")}}


def test_seed_row_reads_the_protocol_in_percent_and_computes_gains() -> None:
    t1 = _module()
    r = t1.seed_row(3, _metrics(0.434, 0.622, 0.70, 0.715), "paper")
    assert (r.seed, r.point, r.voxel, r.x1, r.x2) == pytest.approx((3, 43.4, 62.2, 70.0, 71.5))
    assert r.gain1 == pytest.approx(7.8)
    assert r.gain2 == pytest.approx(9.3)
    # A run with one round has no x2 column: no x2 gain, no error.
    r1 = t1.seed_row(0, _metrics(0.4, 0.5, 0.45), "paper")
    assert r1.x2 is None and r1.gain2 is None and r1.gain1 == pytest.approx(-5.0)
    with pytest.raises(KeyError, match="camera"):
        t1.seed_row(0, _metrics(0.4, 0.5, 0.6), "camera")
    with pytest.raises(KeyError, match="voxel"):
        t1.seed_row(0, {"paper": {"point": {"miou": 0.4}}}, "paper")


def _conf(rows: list[list[int]]) -> list[list[int]]:
    return [[*r, 0] for r in rows]  # no unlabeled column entries: every row labels the common points


def test_same_points_gain_from_the_common_table_by_hand() -> None:
    t1 = _module()
    names, cats = ["a", "b"], ["x", "x"]
    # voxel: a 8/10 right, b 5/6 right; x1: a all right, b 3/6 right.
    voxel = _conf([[8, 2], [1, 5]])  # IoU a 8/11, b 5/8
    x1 = _conf([[10, 0], [3, 3]])  # IoU a 10/13, b 3/6
    m = _metrics(0.5, 0.6, 0.7, protocol="camera")
    m.update(
        class_names=names,
        categories=cats,
        common={"voxel": {"confusion": voxel}, "+3D-CN x1": {"confusion": x1}},
    )
    same = t1.same_points(m, "camera")
    assert same["voxel"] == pytest.approx(100 * (8 / 11 + 5 / 8) / 2)
    assert same["+3D-CN x1"] == pytest.approx(100 * (10 / 13 + 3 / 6) / 2)
    r = t1.seed_row(0, m, "camera")
    assert r.same1 == pytest.approx(same["+3D-CN x1"] - same["voxel"]) and r.gain1 == pytest.approx(10.0)
    # Without a common table (a file older than it): no same-points gain.
    assert (
        t1.same_points(_metrics(0.5, 0.6, 0.7), "paper") == {}
        and t1.seed_row(0, _metrics(0.5, 0.6, 0.7), "paper").same1 is None
    )


def test_same_points_on_the_paper_protocol_merges_first() -> None:
    t1 = _module()
    from leap_core.schema import builtin_schema

    schema = builtin_schema("semantickitti")
    c, ix = schema.num_classes, schema.index
    conf = [[0] * (c + 1) for _ in range(c)]
    conf[ix("truck")][ix("other-vehicle")] = 4  # other-vehicle after the merge: right
    conf[ix("car")][ix("car")] = 2
    m = _metrics(0.5, 0.6, 0.7)
    m.update(
        class_names=schema.names,
        categories=schema.categories(),
        common={"voxel": {"confusion": conf}, "+3D-CN x1": {"confusion": conf}},
    )
    # Merged: car 1.0 and other-vehicle 1.0 (19 classes: truck 0 and other-vehicle 0 would pull it down).
    assert t1.same_points(m, "paper")["voxel"] == pytest.approx(100.0)
    assert t1.same_points(m, "camera")["voxel"] == pytest.approx(100 / 3)


def test_check_shared_refuses_seeds_that_did_not_share_the_base_run() -> None:
    t1 = _module()
    a = t1.seed_row(0, _metrics(0.4, 0.5, 0.6), "paper")
    b = t1.seed_row(1, _metrics(0.4, 0.5, 0.55), "paper")
    t1.check_shared([a, b])
    c = t1.seed_row(2, _metrics(0.4, 0.51, 0.55), "paper")
    with pytest.raises(ValueError, match="voxel mIoU differs between seed 0"):
        t1.check_shared([a, b, c])


def test_verdict_needs_every_seed_above_voxel_and_a_mean_gain_of_five() -> None:
    t1 = _module()

    def rows(*x1: float | None) -> list[Any]:
        return [t1.seed_row(s, _metrics(0.40, 0.50, x), "paper") for s, x in enumerate(x1)]

    v = t1.verdict(rows(0.56, 0.57, 0.55))  # gains 6, 7, 5
    assert v.every_seed and v.passed and v.mean_gain == pytest.approx(6.0)
    v = t1.verdict(rows(0.53, 0.54, 0.52))  # every seed gains, mean 3 < 5
    assert v.every_seed and not v.passed and v.mean_gain == pytest.approx(3.0)
    v = t1.verdict(rows(0.70, 0.70, 0.49))  # mean 13 but seed 2 loses a point
    assert not v.every_seed and not v.passed
    v = t1.verdict(rows(0.70, 0.50))  # a tie is no gain
    assert not v.every_seed
    v = t1.verdict(rows(0.70, None))  # a seed without its x1 column cannot pass
    assert not v.every_seed and not v.passed and v.mean_gain is None
    assert not t1.verdict([]).passed


def test_table_markdown_rows_mean_std_and_paper_figures() -> None:
    t1 = _module()
    street = t1.DOMAINS["street"]
    agri = t1.DOMAINS["agri"]
    s_rows = [
        t1.seed_row(s, _metrics(0.434, 0.622, x1, x2), "paper")
        for s, x1, x2 in ((0, 0.70, 0.72), (1, 0.66, 0.69), (2, 0.68, 0.70))
    ]
    a_rows = [
        dataclasses.replace(
            t1.seed_row(0, _metrics(0.795, 0.888, 0.808, protocol="camera"), "camera"), same1=1.5
        )
    ]
    text = t1.table_markdown([(t1.as_run(street), s_rows), (agri, a_rows)])
    lines = text.splitlines()
    assert lines[0].startswith("| domain (protocol) | 3D-CN seed | point | voxel | +3D-CN ×1 | +3D-CN ×2 |")
    assert lines[0].endswith("| gain ×1, same points |") and lines[1].count("---") == 9
    assert lines[2] == (
        "| street demo, `paper` labeler preset, 3D-CN fine-tuned from a network trained on "
        "street-32's ground truth (3 × 60 scans), `consistency.temperature=0.25` "
        "(the paper's 11 merged classes, camera view) "
        "| 0 | 43.4 | 62.2 | 70.0 | 72.0 | +7.8 | +9.8 | n/a |"
    )
    assert lines[3] == "|  | 1 | 43.4 | 62.2 | 66.0 | 69.0 | +3.8 | +6.8 | n/a |"
    assert lines[4] == "|  | 2 | 43.4 | 62.2 | 68.0 | 70.0 | +5.8 | +7.8 | n/a |"
    # mean ± sample std over seeds: x1 68.0 ± 2.0, x2 70.33 ± 1.53, gains 5.8 ± 2.0 and 8.13 ± 1.53
    assert lines[5] == "| | mean | 43.4 | 62.2 | 68.0 ± 2.0 | 70.3 ± 1.5 | +5.8 ± 2.0 | +8.1 ± 1.5 | n/a |"
    assert lines[6] == "| | *paper, SemanticKITTI* | *46.8* | *48.9* | *57.6* | — | *+8.7* | — | — |"
    # One agri seed, one round: no mean line, n/a for x2; its same-points gain from the common table.
    assert lines[7] == (
        "| farm drone (agri-uav), `default` labeler preset (7 classes, camera view) "
        "| 0 | 79.5 | 88.8 | 80.8 | n/a | -8.0 | n/a | +1.5 |"
    )
    assert lines[8] == "| | *paper, AgriUAV* | *38.0* | *49.7* | *61.5* | — | *+11.8* | — | — |"
    assert len(lines) == 9
    # A domain with no seed measured is left out.
    assert "AgriUAV" not in t1.table_markdown([(street, s_rows), (agri, [])])
    line = t1.verdict_line(street, s_rows)
    assert "every seed (0, 1, 2): yes" in line and "+5.8" in line and "PASS" in line


def test_parse_sets_and_seed_project_keep_the_domain_file_and_add_the_seed(tmp_path: Path) -> None:
    t1 = _module()
    sets = t1.parse_sets(["consistency.class_balance=false", "consistency.temperature=1.5"])
    assert sets == {"consistency": {"class_balance": False, "temperature": 1.5}}
    path = t1.seed_project(t1.DOMAINS["agri"], 2, sets, tmp_path, "_nb")
    assert path.name == "agri_seed2_nb.yaml"
    doc = yaml.safe_load(path.read_text())
    orig = yaml.safe_load((ROOT / "projects" / "agri_uav.yaml").read_text())
    assert doc["classes"] == orig["classes"]
    assert doc["pipeline"]["grounded_sam"] == orig["pipeline"]["grounded_sam"]
    assert doc["pipeline"]["consistency"] == {
        **orig["pipeline"]["consistency"],
        "class_balance": False,
        "temperature": 1.5,
        "seed": 2,
    }
    # The file is a valid project for the CLI's loader, and the seed reaches the 3D-CN's config.
    from leap_core.presets import load_preset

    cfg = load_preset(path).pipeline.consistency
    assert (cfg.seed, cfg.class_balance, cfg.temperature) == (2, False, 1.5)


def test_link_base_shares_stage_outputs_but_not_the_runs_own_files(tmp_path: Path) -> None:
    t1 = _module()
    base = tmp_path / "base"
    seq = base / "sequences" / "00"
    (seq / "points").mkdir(parents=True)
    (seq / "stages.json").write_text("{}")
    (seq / "grid.npz").write_bytes(b"grid")
    (seq / "points" / "000000.npz").write_bytes(b"p")
    (seq / "corrections.npz").write_bytes(b"c")
    (seq / "export-coverage.json").write_text("{}")
    (seq / ".fuse_spill").mkdir()
    write_run_spec(RunLayout(base), [("00", tmp_path / "data" / "00", None)])
    for name in ("metrics.json", "run.log", "params.json", ".lock"):
        (base / name).write_text("{}")
    run = tmp_path / "seed1"
    t1.link_base(base, run)
    assert sorted(p.relative_to(run).as_posix() for p in run.rglob("*")) == [
        "sequences",
        "sequences/00",
        "sequences/00/grid.npz",
        "sequences/00/points",
        "sequences/00/points/000000.npz",
        "sequences/00/stages.json",
    ]
    assert (run / "sequences" / "00" / "grid.npz").stat().st_ino == (seq / "grid.npz").stat().st_ino
    # An existing seed run is left as it is (it resumes).
    (run / "sequences" / "00" / "grid.npz").unlink()
    t1.link_base(base, run)
    assert not (run / "sequences" / "00" / "grid.npz").exists()
    # A base run that did not finish a sequence stops the benchmark, naming the base run.
    (seq / "stages.json").unlink()
    with pytest.raises(SystemExit, match=f"{base} has no sequence"):
        t1.link_base(base, tmp_path / "seed2")


def test_a_seed_rows_metrics_are_those_of_the_runs_sequence(tmp_path: Path) -> None:
    t1 = _module()
    run = tmp_path / "seed0"
    assert t1.sequence_metrics(run) is None
    (run / "sequences" / "00").mkdir(parents=True)
    assert t1.sequence_metrics(run) is None
    cell = metrics_from_confusion(
        np.array([[3, 1, 0], [0, 4, 1]]), ["a", "b"], ["x", "y"], ignore_unlabeled_pred=True
    ).to_dict()
    data = {
        "class_names": ["a", "b"],
        "categories": ["x", "y"],
        "rows": ["point", "voxel"],
        "protocols": {"camera": "camera view"},
        "n_points": 9,
        "n_points_in_view": 9,
        "labeled_points": {"point": 8, "voxel": 8},
        "coverage_ratio": {"point": 1.0, "voxel": 1.0},
        "camera": {"point": cell, "voxel": cell},
    }
    (run / "sequences" / "00" / "metrics.json").write_text(json.dumps(data))
    assert t1.sequence_metrics(run) == data
    assert t1.seed_row(0, data, "camera").voxel == pytest.approx(100.0 * cell["miou"])


def test_results_page_has_the_table1_markers_that_readme_writes_into() -> None:
    text = (ROOT / "docs" / "RESULTS.md").read_text()
    assert text.count("<!-- table:table1 -->") == 1
    assert text.count("<!-- /table:table1 -->") == 1
    assert text.index("<!-- table:table1 -->") < text.index("<!-- /table:table1 -->")


def test_retarget_moves_a_domain_to_its_own_sequence_and_folders() -> None:
    t1 = _module()
    agri = t1.DOMAINS["agri"]
    assert t1.retarget(agri) is agri
    tuned = t1.retarget(agri, 101, 30)
    assert tuned.synth == ("--domain", "agri-uav", "--frames", "30", "--seed", "101")
    assert tuned.key == tuned.data == "agri_seq101_f30"
    assert (tuned.project, tuned.protocol, tuned.run_flags) == (agri.project, agri.protocol, agri.run_flags)
    street = t1.retarget(t1.DOMAINS["street"], sequence_seed=7)  # the length stays the report's
    assert street.synth == ("--frames", "60", "--seed", "7") and street.data == "street_seq7_f60"


def test_a_domains_own_settings_reach_its_seed_runs_and_its_title(tmp_path: Path) -> None:
    """The street's seed runs get its temperature (chosen on its tuning sequences); ``--set`` overrides
    it; the table names it; the farm has none."""
    from leap_core.presets import load_preset

    t1 = _module()
    street, agri = t1.DOMAINS["street"], t1.DOMAINS["agri"]
    assert street.settings == ("consistency.temperature=1",) and agri.settings == ()

    def consistency(dom: Any, extra: list[str]) -> Any:
        path = t1.seed_project(dom, 1, t1.parse_sets(t1.with_settings(dom, extra).settings), tmp_path, "")
        return load_preset(path).pipeline.consistency

    assert (consistency(street, []).temperature, consistency(street, []).seed) == (1.0, 1)
    assert consistency(street, ["consistency.temperature=2"]).temperature == 2.0
    assert consistency(agri, []).temperature == 2.0  # the default
    # A --set variant names its own value, not the domain's.
    variant = t1.with_settings(street, ["consistency.temperature=1", "consistency.seed=3"])
    assert variant.settings == ("consistency.temperature=1", "consistency.seed=3")
    assert t1.parse_sets(variant.settings)["consistency"] == {"temperature": 1, "seed": 3}
    assert t1.with_settings(agri, []) == agri
    row = t1.SeedRow(seed=0, point=40.0, voxel=50.0, x1=55.0, x2=None, same1=4.0)
    assert t1.domain_lines(t1.as_run(street), [row])[0].startswith(
        "| street demo, `paper` labeler preset, 3D-CN fine-tuned from a network trained on street-32's "
        "ground truth (3 × 60 scans), `consistency.temperature=0.25` ("
    )
    scratch = t1.as_run(street, from_scratch=True)
    assert scratch.source is None and scratch.settings == ("consistency.temperature=1",)
    assert t1.domain_lines(scratch, [row])[0].startswith(
        "| street demo, `paper` labeler preset, `consistency.temperature=1` ("
    )
    # The source's temperature replaces the domain's; --set replaces both; the farm has no source.
    assert t1.as_run(street).settings == ("consistency.temperature=0.25",)
    assert t1.as_run(street, ["consistency.temperature=0.5"]).settings == ("consistency.temperature=0.5",)
    assert t1.as_run(agri) == agri
    assert t1.domain_lines(agri, [row])[0].startswith("| farm drone (agri-uav), `default` labeler preset (")


def test_merged_table_rewrites_the_measured_domains_and_keeps_the_others() -> None:
    t1 = _module()
    street, agri = t1.DOMAINS["street"], t1.DOMAINS["agri"]

    def rows(x1: float) -> list[Any]:
        return [t1.seed_row(s, _metrics(0.4, 0.5, x1), "paper") for s in (0, 1)]

    old = t1.table_markdown([(street, rows(0.55)), (agri, rows(0.60))])
    blocks = t1.table_blocks(old)
    # Per domain: its seeds, the mean and the paper's row.
    assert [len(b) for b in blocks] == [4, 4]
    assert [t1.block_domain(b) for b in blocks] == ["street", "agri"]
    new_street = t1.table_markdown([(street, rows(0.57))])
    merged = t1.merged_table(old, new_street)
    assert merged.splitlines()[:2] == old.splitlines()[:2]
    assert t1.table_blocks(merged) == [t1.table_blocks(new_street)[0], blocks[1]]
    # The farm measured alone: the street's old rows stay first.
    new_agri = t1.table_markdown([(agri, rows(0.65))])
    assert t1.table_blocks(t1.merged_table(old, new_agri)) == [blocks[0], t1.table_blocks(new_agri)[0]]
    # Everything measured: nothing of the old table stays.
    both = t1.table_markdown([(street, rows(0.57)), (agri, rows(0.65))])
    assert t1.merged_table(old, both) == both
    # Rows of a domain this script no longer knows are kept, every block of them, after the known ones.
    strays = ["| an old variant | 0 | 1.0 |", "|  | 1 | 2.0 |", "| another one | 0 | 3.0 |"]
    merged = t1.merged_table("\n".join([old, *strays]), new_street)
    assert merged.splitlines()[-3:] == strays
    assert t1.table_blocks(merged)[:2] == [t1.table_blocks(new_street)[0], blocks[1]]


@pytest.mark.slow
def test_the_street_starts_from_a_network_of_another_domain(tmp_path: Path) -> None:
    """The street's source: street-32 sequences of their own seeds (never the report's), trained once
    into RUNS/sources by `leap train-3dcn` and reused; a checkpoint the street's runs accept."""
    from argparse import Namespace

    from leap_core.consistency.train import load_checkpoint, load_source
    from leap_core.presets import load_preset

    t1 = _module()
    street = t1.DOMAINS["street"]
    src = street.source
    assert src.domain == "street-32" and "0" not in map(str, src.seeds)
    assert t1.DOMAINS["agri"].source is None
    assert src.data(201) == "street-32_seed201_f60"
    assert src.checkpoint == "source_street-32_201-202-203_f60_s600.pt"
    # A tiny source, run for real: one 1-frame sequence, 2 steps.
    tiny = dataclasses.replace(street, source=t1.Source(domain="street-32", seeds=(5,), frames=1, steps=2))
    args = Namespace(data=str(tmp_path / "data"), runs=str(tmp_path / "runs"))
    ckpt = t1.source_network(tiny, args)
    assert ckpt == tmp_path / "runs" / "sources" / "source_street-32_5_f1_s2.pt"
    assert (tmp_path / "data" / "street-32_seed5_f1" / "sequences" / "00" / "synth_version.txt").is_file()
    ck = load_checkpoint(ckpt)
    assert ck.meta["kind"] == "ground-truth" and ck.meta["steps"] == 2
    preset = load_preset(ROOT / street.project)
    load_source(ckpt, preset.pipeline.consistency.backbone, preset.schema.num_classes)
    stamp = ckpt.stat().st_mtime_ns
    assert t1.source_network(tiny, args) == ckpt and ckpt.stat().st_mtime_ns == stamp
    assert t1.source_network(t1.DOMAINS["agri"], args) is None
