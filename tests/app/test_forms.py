"""The app's pipeline form (app/forms.py): flat names to dotted config paths and back, and which of its
fields a config ignores, in the form's names."""

from __future__ import annotations

import pytest

from app.forms import (
    FORM_FIELDS,
    PATH_LABELS,
    form_values,
    ignored_settings,
    overrides_from_form,
    stage_switches,
)
from leap_core.config import PipelineConfig, config_from_dict
from leap_core.errors import LeapError
from leap_core.labelers import LABELERS


def test_form_fields() -> None:
    form = {"k": 5, "threshold": 0.3, "consistency": True, "cluster_gap": 2.0}
    cfg = config_from_dict(overrides_from_form(form))
    vals = form_values(cfg)
    assert vals["k"] == 5 and vals["threshold"] == 0.3 and vals["consistency"] is True
    assert vals["cluster_gap"] == 2.0 and vals["voxel_size"] == 0.2
    # A labeler's section is a path like any other: the threshold is read from grounded-sam's section.
    assert overrides_from_form({"threshold": 0.3}) == {"grounded_sam": {"box_threshold": 0.3}}
    with pytest.raises(LeapError, match="unknown field 'kk'"):
        overrides_from_form({"kk": 1})


def test_the_labeler_choices_are_the_registry() -> None:
    assert [value for value, _ in FORM_FIELDS["labeler"].choices] == list(LABELERS)
    assert PATH_LABELS["grounded_sam.box_threshold"] == "Box threshold"


def test_ignored_settings_in_the_forms_names() -> None:
    assert stage_switches() == {"3dcn": "consistency"}
    default = ignored_settings(PipelineConfig())
    assert set(default) == {"threshold", "sam3_threshold", "share", "temperature", "iterations"}
    assert "simulated" in default["threshold"]
    assert default["share"] == "the 3D-CN stage is off (3D Consistency Network is unticked)"
    gsam = config_from_dict({"labeler": "grounded-sam", "consistency": {"enabled": True}})
    assert ignored_settings(gsam) == {
        "sam3_threshold": "only the SAM 3 labeler uses it; the Grounding DINO + SAM labeler ignores it"
    }
    sam3 = config_from_dict({"labeler": "sam3"})
    assert "threshold" in ignored_settings(sam3) and "sam3_threshold" not in ignored_settings(sam3)
    assert set(FORM_FIELDS) >= set(default)
