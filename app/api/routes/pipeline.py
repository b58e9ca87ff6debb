"""What the pipeline looks like to the web UI: its stages, the project form's parameters, the 2D labelers
and which run states are active, ended or resumable.

The web UI builds its stage list and its parameter form from this answer, so a stage or a parameter is
declared once (``STAGE_TABLE`` in leap_core, ``FORM_FIELDS`` in ``app/forms.py``), and nowhere in the browser
code. Each form field says which labeler or switchable stage it belongs to
(``leap_core.pipeline.steering.setting_scope``) and each switchable stage which form field switches it, so
the form greys out what the chosen settings ignore without knowing any setting by name.
"""

from __future__ import annotations

import typing

from fastapi import APIRouter

from app import models
from app.forms import FORM_FIELDS, stage_switches
from app.jobs.progress import TERMINAL_STATUSES
from app.jobs.stages import POSES, SYNTH
from app.rows import RunStatus
from leap_core.labelers import LABELERS
from leap_core.pipeline import STAGE_TABLE
from leap_core.pipeline.steering import setting_scope
from leap_core.presets import builtin_preset, list_presets

router = APIRouter(prefix="/pipeline", tags=["pipeline"])

DEMO_STAGE = models.StageInfoPublic(
    name=SYNTH,
    label="Generate demo",
    description="generate the built-in demo sequence (before the first run of a demo project)",
    per_frame=True,
)
"""The stage the job manager puts first in a run of a demo project whose sequence does not exist yet."""

POSES_STAGE_INFO = models.StageInfoPublic(
    name=POSES,
    label="Estimate poses",
    description="KISS-ICP LiDAR odometry refined by a pose graph, into the work folder (projects that "
    "estimate poses, on a dataset without poses.txt; cached for later runs)",
    per_frame=True,
)
"""The stage before the pipeline's in a run that estimates poses."""


def pipeline_public() -> models.PipelinePublic:
    """The answer of ``GET /pipeline`` (the same for every request)."""
    switches = stage_switches()
    stages = [DEMO_STAGE, POSES_STAGE_INFO] + [
        models.StageInfoPublic(
            name=s.name,
            label=s.label,
            description=s.description,
            per_frame=s.per_frame,
            switch=switches.get(s.name),
        )
        for s in STAGE_TABLE
    ]
    scopes = {name: setting_scope(f.path) for name, f in FORM_FIELDS.items()}
    form = [
        models.FormFieldPublic(
            name=name,
            path=f.path,
            label=f.label,
            kind=f.kind,
            help=f.help,
            minimum=f.minimum,
            maximum=f.maximum,
            step=f.step,
            choices=[models.FormChoice(value=value, label=label) for value, label in f.choices],
            labeler=scopes[name].labeler,
            stage=scopes[name].stage,
        )
        for name, f in FORM_FIELDS.items()
    ]
    labels = {value: label for f in FORM_FIELDS.values() if f.path == "labeler" for value, label in f.choices}
    statuses = typing.get_args(RunStatus)
    return models.PipelinePublic(
        stages=stages,
        form=form,
        labelers=[models.LabelerPublic(name=name, label=labels.get(name, name)) for name in LABELERS],
        run_statuses=models.RunStatusesPublic(
            active=[s for s in statuses if s in models.ACTIVE_STATUSES],
            terminal=[s for s in statuses if s in TERMINAL_STATUSES],
            resumable=[s for s in statuses if s in models.RESUMABLE_STATUSES],
        ),
        presets=[models.PresetPublic(name=n, classes=builtin_preset(n).schema.names) for n in list_presets()],
    )


PIPELINE = pipeline_public()


@router.get("", response_model=models.PipelinePublic)
async def read_pipeline() -> models.PipelinePublic:
    return PIPELINE
