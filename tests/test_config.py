"""Pipeline config: field paths on errors, retired deployment fields, the labeler registry, presets, and
that reading a config stays free of torch."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from conftest import build_tiny_sequence

from leap_core.bounds import Bound
from leap_core.config import (
    RETIRED_FIELDS,
    PipelineConfig,
    config_from_dict,
    config_to_dict,
    setting_bounds,
    without_retired,
)
from leap_core.errors import ConfigError, LeapError, SchemaError
from leap_core.labelers import (
    LABELERS,
    PRODUCT_LABELERS,
    LabelerSpec,
    make_labeler,
    register_labeler,
    unregister_labeler,
)
from leap_core.labelers.cache import pass_cache_dir
from leap_core.labelers.grounded_sam import GroundedSamConfig, GroundedSamLabeler
from leap_core.labelers.simulated import MOVED_TERMS, SimulatedLabeler, SimulatedLabelerConfig
from leap_core.presets import builtin_preset, list_presets, load_preset
from leap_core.runtime import Runtime
from leap_core.schema import projects_dir

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------- field paths
@pytest.mark.parametrize(
    ("overrides", "field", "problem"),
    [
        # PipelineConfig's own fields
        (
            {"labeler": "sam"},
            ("pipeline", "labeler"),
            "must be one of 'simulated', 'grounded-sam', 'sam3', got 'sam'",
        ),
        ({"correction_strength": 0}, ("pipeline", "correction_strength"), "must be in (0, 1000] nats, got 0"),
        ({"bogus": 1}, ("pipeline", "bogus"), "unknown setting"),
        # one level down: every section's own check
        (
            {"fusion": {"voxel_size": 0}},
            ("pipeline", "fusion", "voxel_size"),
            "must be in [0.01, 10] m, got 0",
        ),
        (
            {"projection": {"cluster_gap": -1}},
            ("pipeline", "projection", "cluster_gap"),
            "must be in [0.01, 1000] m, got -1",
        ),
        ({"smoothing": {"workers": 0}}, ("pipeline", "smoothing", "workers"), "must be in [1, 256] or -1"),
        ({"grounded_sam": {"match_iou": 0}}, ("pipeline", "grounded_sam", "match_iou"), "must be in (0, 1]"),
        ({"simulated": {"jitter_px": -1}}, ("pipeline", "simulated", "jitter_px"), "must be in [0, 100] px"),
        ({"consistency": {"share": 1.5}}, ("pipeline", "consistency", "share"), "must be in (0, 1]"),
        ({"smoothing": {"k": "9"}}, ("pipeline", "smoothing", "k"), "must be an integer"),
        ({"projection": 3}, ("pipeline", "projection"), "must be a mapping of settings"),
        # two levels down
        (
            {"simulated": {"class_recall": {"car": 2}}},
            ("pipeline", "simulated", "class_recall", "car"),
            "must be in [0, 1]",
        ),
        (
            {"consistency": {"backbone": {"channels": 2}}},
            ("pipeline", "consistency", "backbone", "channels"),
            "must be in [4, 1024], got 2",
        ),
        (
            {"consistency": {"backbone": {"kernel_size": 4}}},
            ("pipeline", "consistency", "backbone", "kernel_size"),
            "must be odd",
        ),
        (
            {"consistency": {"backbone": {"chanels": 8}}},
            ("pipeline", "consistency", "backbone", "chanels"),
            "unknown setting (did you mean 'channels'?)",
        ),
        ({"consistency": {"backbone": 8}}, ("pipeline", "consistency", "backbone"), "must be a mapping"),
    ],
)
def test_every_error_carries_its_absolute_field_path(
    overrides: dict, field: tuple[str, ...], problem: str
) -> None:
    with pytest.raises(ConfigError) as err:
        config_from_dict(overrides)
    assert err.value.field == field
    assert str(err.value).startswith(".".join(field) + ": " + problem)
    assert "\n" not in str(err.value)


def test_configs_raise_relative_paths_that_config_from_dict_makes_absolute() -> None:
    from leap_core.consistency.config import BackboneConfig

    with pytest.raises(ConfigError) as err:
        BackboneConfig(channels=2)
    assert err.value.field == ("channels",) and str(err.value) == "channels: must be in [4, 1024], got 2"
    assert err.value.within("pipeline", "consistency", "backbone").field == (
        "pipeline",
        "consistency",
        "backbone",
        "channels",
    )
    # A bad override of a valid base keeps the base untouched and names the field.
    base = config_from_dict({"fusion": {"voxel_size": 0.3}})
    with pytest.raises(ConfigError):
        config_from_dict({"fusion": {"voxel_size": -0.1}}, base)
    assert base.fusion.voxel_size == 0.3


def test_float_settings_must_be_finite_and_messages_stay_short() -> None:
    # YAML's .inf / .nan and JSON's 1e400 arrive as non-finite floats, 10**400 as an int no float holds.
    for value in (float("inf"), float("-inf"), float("nan"), 10**400):
        with pytest.raises(ConfigError, match="must be a finite number") as info:
            config_from_dict({"fusion": {"voxel_size": value}})
        assert info.value.field == ("pipeline", "fusion", "voxel_size")
        assert len(str(info.value)) < 200
    with pytest.raises(ConfigError) as info:
        config_from_dict({"labeler": "x" * 100_000})
    assert len(str(info.value)) < 300
    assert config_from_dict({"fusion": {"voxel_size": 1}}).fusion.voxel_size == 1.0


def test_config_errors_survive_pickling() -> None:
    import pickle

    err = ConfigError("must be > 0", field=("pipeline", "fusion", "logp_clip"))
    back = pickle.loads(pickle.dumps(err))
    assert back.field == err.field and str(back) == str(err) and back.problem == err.problem


# ------------------------------------------------------------------------------------------ bounds
PRODUCT_SECTIONS: dict[str, type] = {spec.section: spec.config_type for spec in PRODUCT_LABELERS}
"""The config sections of leap_core's own labelers."""


@pytest.mark.parametrize(
    ("overrides", "field", "problem"),
    [
        # k neighbours are queried and mixed per voxel of a chunk: 10⁹ took a worker to 4.8 GiB.
        ({"smoothing": {"k": 10**9}}, ("pipeline", "smoothing", "k"), "must be in [1, 64], got 1000000000"),
        # A denormal voxel edge: every point its own voxel, and coordinates past the key's range.
        (
            {"fusion": {"voxel_size": 1e-320}},
            ("pipeline", "fusion", "voxel_size"),
            "must be in [0.01, 10] m, got 1e-320",
        ),
        (
            {"fusion": {"chunk_points": 10**12}},
            ("pipeline", "fusion", "chunk_points"),
            "must be in [1, 20000000], got 1000000000000",
        ),
        (
            {"consistency": {"backbone": {"grid_cells": [0.8, 0.001, 0.8]}}},
            ("pipeline", "consistency", "backbone", "grid_cells"),
            "must be in [0.1, 10] m, got 0.001",
        ),
        (
            {"simulated": {"bleed_px": 10**6}},
            ("pipeline", "simulated", "bleed_px"),
            "must be in [0, 100] px, got 1000000",
        ),
        (
            {"simulated": {"seed": -1}},
            ("pipeline", "simulated", "seed"),
            "must be in [0, 4294967295], got -1",
        ),
        (
            {"grounded_sam": {"batch_size": 4096}},
            ("pipeline", "grounded_sam", "batch_size"),
            "must be in [1, 64], got 4096",
        ),
        (
            {"consistency": {"epochs": 10**6}},
            ("pipeline", "consistency", "epochs"),
            "must be in [1, 1000], got 1000000",
        ),
        (
            {
                "simulated": {
                    "match_detection": {"exact": 1.0, "synonym": 2.0, "descriptive": 1, "hypernym": 1}
                }
            },
            ("pipeline", "simulated", "match_detection", "synonym"),
            "must be in [0, 1], got 2.0",
        ),
    ],
)
def test_sizes_counts_and_rates_are_refused_past_their_bounds_naming_field_value_and_range(
    overrides: dict, field: tuple[str, ...], problem: str
) -> None:
    with pytest.raises(ConfigError) as err:
        config_from_dict(overrides)
    assert err.value.field == field
    assert str(err.value) == ".".join(field) + ": " + problem


def _filled(default: object, value: float) -> object:
    """A setting's value with every number of ``default`` replaced by ``value`` (an empty table gets one
    entry)."""
    if isinstance(default, dict):
        return {k: _filled(v, value) for k, v in default.items()} or {"car": value}
    if isinstance(default, tuple):
        return [value] * len(default)
    return value


def _setting(cfg: object, path: str) -> object:
    for part in path.split("."):
        cfg = (
            cfg.labelers[part]
            if isinstance(cfg, PipelineConfig) and part in cfg.labelers
            else getattr(cfg, part)
        )
    return cfg


def _nested(path: str, value: object) -> dict:
    out: dict = value  # type: ignore[assignment]
    for part in reversed(path.split(".")):
        out = {part: out}
    return out


def _ends(bound: Bound, integer: bool) -> tuple[list[float], list[float]]:
    """Values a bound takes (its closed ends, a point just inside an open one) and values just beyond."""
    step = 1 if integer else 1e-6 * max(1.0, abs(bound.high - bound.low))
    inside = [
        bound.low + step if bound.low_open else bound.low,
        bound.high - step if bound.high_open else bound.high,
    ]
    beyond = [
        bound.high if bound.high_open else bound.high + step,
        bound.low if bound.low_open else bound.low - step,
    ]
    if integer:
        return [int(v) for v in inside], [int(v) for v in beyond]
    return inside, beyond


def test_every_bounded_setting_takes_its_ends_and_refuses_values_beyond() -> None:
    default = PipelineConfig()
    rows = setting_bounds(PRODUCT_SECTIONS)  # a labeler registered by another test module is not checked
    assert len(rows) > 50
    assert {"smoothing.k", "fusion.voxel_size", "consistency.backbone.channels"} <= {p for p, _ in rows}
    for path, bound in rows:
        parts = tuple(path.split("."))
        current = _setting(default, path)
        sample = next(iter(current.values())) if isinstance(current, dict) and current else current
        sample = sample[0] if isinstance(sample, tuple) else sample
        inside, beyond = _ends(bound, isinstance(sample, int) and not isinstance(sample, bool))
        for value in inside:
            cfg = config_from_dict(_nested(path, _filled(current, value)))
            assert _setting(cfg, path) == _setting(config_from_dict(config_to_dict(cfg)), path), path
        for value in beyond:
            with pytest.raises(ConfigError) as err:
                config_from_dict(_nested(path, _filled(current, value)))
            assert err.value.field[1 : len(parts) + 1] == parts, (path, err.value.field)
            assert f"must be in {bound.text()}, got " in str(err.value), (path, str(err.value))


def test_the_default_config_and_stored_configs_inside_the_bounds_read_unchanged() -> None:
    stored = json.loads(STORED.read_text())
    assert config_to_dict(config_from_dict(stored)) == with_settings_added_since(without_retired(stored))
    for name in list_presets():
        preset = builtin_preset(name)
        assert config_from_dict(config_to_dict(preset.pipeline)) == preset.pipeline, name


BOUNDS_TABLE = ("<!-- table:bounds -->", "<!-- /table:bounds -->")
"""The markers of the allowed ranges' table in docs/METHOD.md (section F)."""


def bounds_markdown() -> str:
    """docs/METHOD.md's table of every bounded setting of leap_core's own config sections."""
    lines = ["| setting | allowed |", "|---|---|"]
    lines += [f"| `{path}` | {bound.text()} |" for path, bound in setting_bounds(PRODUCT_SECTIONS)]
    return "\n".join(lines)


def test_method_md_lists_every_settings_allowed_range() -> None:
    text = (REPO / "docs" / "METHOD.md").read_text()
    start, end = (text.index(m) for m in BOUNDS_TABLE)
    body = text[start + len(BOUNDS_TABLE[0]) : end].strip()
    assert body == bounds_markdown(), "docs/METHOD.md's table:bounds should read:\n" + bounds_markdown()


# ------------------------------------------------------------------------- retired deployment fields
@pytest.mark.parametrize(
    ("key", "value", "replacement"),
    [
        ("models_dir", "models", "--models DIR"),
        ("cache_dir", "/tmp/c", "--cache DIR"),
        ("device", "cuda", "--device"),
        ("allow_download", True, "--allow-download"),
    ],
)
def test_deployment_fields_in_a_config_say_what_replaces_them(
    key: str, value: object, replacement: str
) -> None:
    with pytest.raises(ConfigError) as err:
        config_from_dict({"grounded_sam": {key: value}})
    message = str(err.value)
    assert err.value.field == ("pipeline", "grounded_sam", key)
    assert message.startswith(f"pipeline.grounded_sam.{key}: no longer a pipeline setting; ")
    assert replacement in message and "\n" not in message
    if key == "models_dir":
        assert "LEAP_MODELS_DIR" in message


def test_dicts_stored_by_older_versions_still_read() -> None:
    """Old SQLite rows and run specs hold every former field at its default: those say nothing."""
    old = config_to_dict(PipelineConfig())
    old["grounded_sam"].update({k[1]: r.default for k, r in RETIRED_FIELDS.items() if k[0] == "grounded_sam"})
    assert config_from_dict(old) == PipelineConfig()
    with pytest.raises(ConfigError):  # but a value that would have meant something is refused
        config_from_dict({"grounded_sam": {"device": "cpu"}})


def test_a_project_file_with_models_dir_is_refused_with_file_and_field(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import cli

    text = (projects_dir() / "agri_uav.yaml").read_text()
    bad = tmp_path / "old.yaml"
    bad.write_text(text.replace("    mode: joint\n", "    mode: joint\n    models_dir: models\n"))
    with pytest.raises(LeapError) as err:
        load_preset(bad)
    assert err.value.field == ("pipeline", "grounded_sam", "models_dir")
    assert str(err.value).startswith(f"{bad}: pipeline.grounded_sam.models_dir: no longer a pipeline setting")
    seq = build_tiny_sequence(tmp_path, n_frames=1).root  # a sequence: the project file is what is wrong
    args = ["run", str(seq), "--out", str(tmp_path / "r"), "--project-file", str(bad)]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 2 and not (tmp_path / "r").exists()
    last = res.output.strip().splitlines()[-1]
    assert last.startswith(f"error: --project-file {bad}: pipeline.grounded_sam.models_dir: no longer")
    assert "--models DIR" in last


ADDED_SECTIONS = ("sam3", "tracking")
"""Config sections added after the stored file was written (read as their defaults)."""
ADDED_FIELDS = (
    ("consistency", "precision"),
    ("grounded_sam", "flip_votes"),
    ("grounded_sam", "half_precision"),
    ("simulated", "instance_miss"),
    ("simulated", "instance_merge"),
    ("simulated", "instance_split"),
)
"""Fields added to existing sections since (read as their defaults)."""


def with_settings_added_since(stored: dict[str, Any]) -> dict[str, Any]:
    """``stored`` with the sections and fields added since at their defaults: what reading it gives."""
    default = config_to_dict(PipelineConfig())
    out = {**stored, **{name: default[name] for name in ADDED_SECTIONS}}
    for section, name in ADDED_FIELDS:
        out[section] = {**out[section], name: default[section][name]}
    return out


STORED = Path(__file__).resolve().parent / "data" / "pipeline_config_with_simulated_terms.json"
"""``config_to_dict(PipelineConfig())`` as SQLite rows, run specs and project files stored it while the
simulated labeler's config still held the paper preset's noise terms (each at its off value)."""


def test_a_stored_dict_with_the_moved_noise_terms_at_their_defaults_still_reads() -> None:
    stored = json.loads(STORED.read_text())
    assert set(MOVED_TERMS) <= set(stored["simulated"])  # the file is of that shape
    cfg = config_from_dict(stored)
    assert cfg == PipelineConfig()
    # Read back, it is today's dict form: the same sections, the simulated one without the moved terms.
    now = config_to_dict(cfg)
    assert sorted(now) == sorted([*stored, *ADDED_SECTIONS])  # labeler sections follow the registry
    added = {k: now["simulated"][k] for s, k in ADDED_FIELDS if s == "simulated"}
    assert now["simulated"] == {k: v for k, v in stored["simulated"].items() if k not in MOVED_TERMS} | added
    # Written by hand, a number term may be an integer (YAML "0"), a switch must be a switch.
    assert config_from_dict({"simulated": {"box_leak_prob": 0, "stratified_draws": False}}) == cfg
    with pytest.raises(ConfigError):
        config_from_dict({"simulated": {"stratified_draws": 0}})


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("box_leak_prob", 0.1),
        ("class_confusion", {"car": 0.2}),
        ("stratified_draws", True),
        ("stuff_tile_px", 32),
    ],
)
def test_a_moved_noise_term_that_is_on_is_refused_naming_the_field_and_the_labs_labeler(
    name: str, value: object
) -> None:
    stored = json.loads(STORED.read_text())
    stored["simulated"][name] = value
    with pytest.raises(ConfigError) as err:
        config_from_dict(stored)
    assert err.value.field == ("pipeline", "simulated", name)
    message = str(err.value)
    assert message.startswith(f"pipeline.simulated.{name}: no longer a setting of the simulated labeler; ")
    assert "simulated-paper" in message and "simulated_paper" in message and "python -m lab" in message


def test_the_stored_dicts_labeler_keeps_its_fingerprint() -> None:
    # The 2D stage's fingerprint hashes the labeler's name and its fingerprint (never the section's dict):
    # with this one pinned before the terms moved, a run folder made from a stored dict stays current.
    cfg = config_from_dict(json.loads(STORED.read_text()))
    schema = builtin_preset("semantickitti").schema
    assert make_labeler(cfg).fingerprint(schema) == "0a4824aaa8fea028"


def test_runtime_values_reach_the_labeler_and_not_the_config(tmp_path: Path) -> None:
    assert not {"models_dir", "cache_dir", "device", "allow_download"} & {
        f.name for f in dataclasses.fields(GroundedSamConfig)
    }
    rt = Runtime(models_dir=tmp_path / "m", cache_dir=tmp_path / "c", device="cpu", allow_download=True)
    lab = make_labeler(PipelineConfig(labeler="grounded-sam"), rt)
    assert isinstance(lab, GroundedSamLabeler) and lab.runtime == rt
    assert lab.cache is not None and lab.cache.root == pass_cache_dir(tmp_path / "c")
    assert make_labeler(PipelineConfig(labeler="grounded-sam")).cache is None
    with pytest.raises(ConfigError) as err:
        Runtime(device="tpu")  # type: ignore[arg-type]  # invalid on purpose: the check under test
    assert err.value.field == ("device",)


# ------------------------------------------------------------------------------------ labeler registry
def test_every_registered_labeler_has_its_config_section_and_builds() -> None:
    assert list(LABELERS) == [
        "simulated",
        "grounded-sam",
        "sam3",
    ]  # the product's; the lab's registers on import
    own = {f.name for f in dataclasses.fields(PipelineConfig)}
    default = PipelineConfig()
    assert list(default.labelers) == [spec.section for spec in LABELERS.values()]
    for name, spec in LABELERS.items():
        assert spec.name == name and spec.needs in ("gt2d", "images") and spec.missing and spec.description
        assert spec.section not in own
        assert type(default.labelers[spec.section]) is spec.config_type, name
        assert spec.config_of(default) == spec.config_type() == default.labeler_config(spec.config_type)
        labeler = make_labeler(PipelineConfig(labeler=name))
        assert labeler.name == name
    # The dict form keeps the shape of the time the sections were fields.
    assert list(config_to_dict(default))[:3] == ["labeler", "simulated", "grounded_sam"]


@dataclasses.dataclass(frozen=True)
class ExactConfig:
    """A test labeler's section: the simulated labeler with every knob off, at a seed."""

    seed: int = 0

    def __post_init__(self) -> None:
        if self.seed < 0:
            raise ConfigError(f"must be >= 0, got {self.seed}", field=("seed",))


def _exact_spec(built: list[ExactConfig], section: str = "exact") -> LabelerSpec[ExactConfig]:
    def factory(config: ExactConfig, runtime: Runtime) -> SimulatedLabeler:
        built.append(config)
        return SimulatedLabeler(SimulatedLabelerConfig.exact(config.seed))

    return LabelerSpec(
        "exact", "exact", "2D ground truth without noise", section, ExactConfig, factory, "gt2d", "-"
    )


def test_a_registered_labeler_brings_its_config_section() -> None:
    with pytest.raises(ConfigError):
        PipelineConfig(labeler="exact")
    with pytest.raises(ConfigError, match=r"pipeline\.exact: unknown setting"):
        config_from_dict({"exact": {"seed": 3}})
    built: list[ExactConfig] = []
    spec = _exact_spec(built)
    register_labeler(spec)
    try:
        register_labeler(spec)  # again: nothing changes
        assert list(LABELERS) == ["simulated", "grounded-sam", "sam3", "exact"]
        with pytest.raises(ValueError, match="named 'exact'"):
            register_labeler(_exact_spec([]))
        with pytest.raises(ValueError, match="section 'simulated' belongs to the 'simulated' labeler"):
            register_labeler(dataclasses.replace(_exact_spec([], "simulated"), name="other"))
        cfg = config_from_dict({"labeler": "exact", "exact": {"seed": 3}})
        assert cfg.labeler_config(ExactConfig) == ExactConfig(3) == spec.config_of(cfg)
        labeler = make_labeler(cfg)
        assert isinstance(labeler, SimulatedLabeler) and labeler.cfg.seed == 3 and built == [ExactConfig(3)]
        d = config_to_dict(cfg)
        assert list(d)[:5] == ["labeler", "simulated", "grounded_sam", "sam3", "exact"]
        assert d["exact"] == {"seed": 3}
        assert config_from_dict(d) == cfg
        # Its fields are checked like any section's, with the absolute path.
        with pytest.raises(ConfigError) as err:
            config_from_dict({"exact": {"seed": -1}})
        assert err.value.field == ("pipeline", "exact", "seed")
        with pytest.raises(
            ConfigError, match=r"pipeline\.exact\.sed: unknown setting \(did you mean 'seed'\?\)"
        ):
            config_from_dict({"exact": {"sed": 1}})
        # A section holds its own type only; a config made before the registration reads its defaults.
        with pytest.raises(ConfigError) as err:
            PipelineConfig(labelers={"exact": SimulatedLabelerConfig()})
        assert err.value.field == ("exact",)
        with pytest.raises(
            ConfigError, match="must be one of 'simulated', 'grounded-sam', 'sam3', 'exact', got 'x'"
        ):
            config_from_dict({"labeler": "x"})
        with_section = dataclasses.replace(PipelineConfig(), labelers={"simulated": SimulatedLabelerConfig()})
        assert with_section.labeler_config(ExactConfig) == ExactConfig()
        assert with_section.with_labeler_config(ExactConfig(5)).labeler_config(ExactConfig).seed == 5
    finally:
        unregister_labeler("exact")
    assert "exact" not in LABELERS and "exact" not in PipelineConfig().labelers
    with pytest.raises(ValueError, match="part of leap_core"):
        unregister_labeler("simulated")


def test_cli_labeler_help_lists_the_registry() -> None:
    from typer.testing import CliRunner

    from app.cli import cli

    res = CliRunner().invoke(cli, ["run", "--help"], env={"COLUMNS": "400"})
    assert res.exit_code == 0
    for name, spec in LABELERS.items():
        assert f"{name} ({spec.description})" in " ".join(res.output.split())


# ---------------------------------------------------------------------------------------------- presets
def test_presets_read_classes_and_pipeline_section() -> None:
    assert {"agri_uav", "demo", "semantickitti", "semantickitti_expanded"} <= set(list_presets())
    agri = load_preset("agri_uav")
    assert agri.source == projects_dir() / "agri_uav.yaml" and agri.schema.num_classes == 7
    agri_gs = agri.pipeline.labeler_config(GroundedSamConfig)
    assert agri.pipeline.labeler == "grounded-sam" and agri_gs.box_threshold == 0.2
    assert agri.pipeline.consistency.class_balance_power == 0.0  # the farm's choice on its tuning sequences
    assert load_preset(projects_dir() / "agri_uav.yaml") == agri == builtin_preset("agri_uav")
    assert load_preset("semantickitti").pipeline == PipelineConfig()
    # The section applies onto a base: fields it does not name keep the base's values.
    base = config_from_dict({"smoothing": {"k": 3}, "grounded_sam": {"box_threshold": 0.4}})
    on_base = load_preset("agri_uav", base).pipeline
    assert on_base.smoothing.k == 3 and on_base.labeler_config(GroundedSamConfig).box_threshold == 0.2


def test_unknown_presets_and_paths_for_names_are_refused() -> None:
    with pytest.raises(SchemaError, match=r"nope: no such file, and no built-in preset .*agri_uav"):
        load_preset("nope")
    # An API payload's name is never read as a path, even one that exists.
    with pytest.raises(SchemaError, match="unknown built-in schema"):
        builtin_preset(str(projects_dir() / "agri_uav.yaml"))
    with pytest.raises(SchemaError, match="unknown built-in schema"):
        builtin_preset("../projects/agri_uav")


def test_cli_errors_name_the_option(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import cli

    seq = build_tiny_sequence(tmp_path, n_frames=1).root  # a sequence: the option is what is wrong
    for args, message in [
        (["--schema", "nope"], "error: --schema nope: no such file"),
        (["--device", "gpu"], "error: --device must be 'auto', 'cpu' or 'cuda', got 'gpu'"),
    ]:
        res = CliRunner().invoke(cli, ["run", str(seq), "--out", str(tmp_path / "r"), *args])
        assert res.exit_code == 2 and res.output.strip().splitlines()[-1].startswith(message), res.output
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------------------------------------ no torch
_READ_CONFIG = "import leap_core.config, leap_core.presets, leap_core.labelers"


def _modules_after(statement: str) -> set[str]:
    heavy = "('torch', 'transformers')"
    code = f"import sys; {statement}; print(' '.join(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_reading_a_config_or_preset_never_imports_transformers() -> None:
    assert "transformers" not in _modules_after(_READ_CONFIG)


def test_reading_a_config_or_preset_never_imports_torch() -> None:
    assert "torch" not in _modules_after(_READ_CONFIG)


def test_the_server_app_imports_without_torch() -> None:
    """``leap serve`` starts without importing torch (a second on every start); workers import it."""
    assert "torch" not in _modules_after("import app.main")
