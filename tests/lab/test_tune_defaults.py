"""lab/tune_defaults.py: the rule that picks a default from the tuning seeds only."""

from __future__ import annotations

from types import ModuleType

import labfixtures

from lab import tune_defaults

lab_labeler = labfixtures.lab_labeler  # registers the lab's labeler for each test here


def _module() -> ModuleType:
    return tune_defaults


def _figs(cam: float) -> dict[str, float]:
    return {"camera_3dcn": cam, "camera_voxel": 80.0, "all_3dcn": 50.0, "all_voxel": 30.0}


def test_choose_takes_the_best_tuning_mean_and_ignores_report_seeds() -> None:
    td = _module()
    # "b" wins on the tuning seeds 1 and 2; seed 9 (report) would favour "a" by far and must not count.
    values = {
        "a": {1: _figs(70.0), 2: _figs(72.0), 9: _figs(99.0)},
        "b": {1: _figs(73.0), 2: _figs(74.0), 9: _figs(10.0)},
    }
    assert td.choose(values, "a", [1, 2], tie=0.5) == "b"


def test_choose_keeps_the_default_within_the_tie_margin() -> None:
    td = _module()
    values = {"a": {1: _figs(70.0), 2: _figs(72.0)}, "b": {1: _figs(70.5), 2: _figs(72.3)}}
    assert td.choose(values, "a", [1, 2], tie=0.5) == "a"  # b ahead by 0.4
    assert td.choose(values, "a", [1, 2], tie=0.3) == "b"


def test_choose_refuses_to_pick_without_every_tuning_figure() -> None:
    td = _module()
    values = {"a": {1: _figs(70.0), 2: _figs(72.0)}, "b": {1: _figs(90.0), 2: None}}
    assert td.choose(values, "a", [1, 2], tie=0.5) is None


def test_variants_change_one_setting_at_a_time_around_the_centre() -> None:
    td = _module()
    base = td.base_config("cpu", 0, {"consistency.temperature": 0.25})
    vs = td.variants(base, ["temperature", "selection_scope"])
    assert [(n, v) for n, v, _, _ in vs] == [
        ("temperature", "0.25"),
        ("temperature", "0.5"),
        ("temperature", "1.0"),
        ("temperature", "2.0"),
        ("selection_scope", '"sequence"'),
        ("selection_scope", '"scan"'),
    ]
    for name, _, cfg, _ in vs:
        cn = cfg.consistency
        assert cn.enabled and cn.iterations == 1
        if name != "temperature":
            assert cn.temperature == 0.25
        if name != "selection_scope":
            assert cn.selection_scope == base.consistency.selection_scope
    # Equal configurations share a cache key (the centre's value repeats the base run, not a new one).
    keys = {(n, v): k for n, v, _, k in vs}
    centre_scope = f'"{base.consistency.selection_scope}"'
    assert keys[("selection_scope", centre_scope)] == keys[("temperature", "0.25")]
    assert len(set(keys.values())) == len(vs) - 1
