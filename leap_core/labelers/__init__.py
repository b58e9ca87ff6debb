"""2D labelers: the :class:`~leap_core.labelers.base.Labeler` protocol, the implementations, their registry.

:data:`LABELERS` holds one :class:`LabelerSpec` per labeler. Everything that names or builds labelers
derives from it: ``PipelineConfig.labeler`` validation, :func:`make_labeler`, the ``--labeler`` help of
the CLI and the labeler choices of the app's form. Adding a labeler is one record here, its config
dataclass (a field of :class:`~leap_core.config.PipelineConfig`) and its class.

Importing this module loads the labelers' configs and classes but not their model stacks: torch and
transformers are imported by the grounded-sam labeler only when it first needs its models.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from leap_core.labelers.base import Labeler, SoftMasks
from leap_core.labelers.grounded_sam import GroundedSamConfig, GroundedSamLabeler
from leap_core.labelers.simulated import SimulatedLabeler, SimulatedLabelerConfig
from leap_core.runtime import Runtime

if TYPE_CHECKING:
    from leap_core.config import PipelineConfig

LabelerInput = Literal["gt2d", "images"]
"""What a labeler reads per frame: ``gt2d`` = the dataset's 2D ground truth (``gt2d/semantic``,
``gt2d/instance``), ``images`` = the camera images (``image_2/``)."""


@dataclass(frozen=True)
class LabelerSpec:
    """One 2D labeler: its name, its config section, how to build it and what it needs."""

    name: str
    """Value of ``PipelineConfig.labeler`` (and ``leap run --labeler``)."""
    label: str
    """Short human name (the app form's choice)."""
    description: str
    """One line on what it does (CLI help)."""
    config_field: str
    """Attribute of :class:`~leap_core.config.PipelineConfig` holding its settings."""
    config_type: type
    """Type of that attribute, the labeler's config dataclass."""
    factory: Callable[[Any, Runtime], Labeler]
    """``factory(section_config, runtime)``: the labeler for its config section and the run's deployment
    values (models folder, 2D cache folder, device)."""
    needs: LabelerInput
    """The input it reads from a dataset."""
    missing: str
    """One line for a dataset that lacks ``needs``, e.g. to follow the folder's name in an error."""


def _simulated(config: SimulatedLabelerConfig, runtime: Runtime) -> Labeler:  # noqa: ARG001 - no deployment values
    return SimulatedLabeler(config)


def _grounded_sam(config: GroundedSamConfig, runtime: Runtime) -> Labeler:
    return GroundedSamLabeler(config, runtime)


LABELERS: dict[str, LabelerSpec] = {
    spec.name: spec
    for spec in (
        LabelerSpec(
            name="simulated",
            label="simulated (from 2D ground truth)",
            description="noisy 2D labels made from the dataset's 2D ground truth (demo data, no models)",
            config_field="simulated",
            config_type=SimulatedLabelerConfig,
            factory=_simulated,
            needs="gt2d",
            missing="the simulated labeler needs 2D ground truth (gt2d/semantic, gt2d/instance); "
            "for real camera images choose the grounded-sam labeler",
        ),
        LabelerSpec(
            name="grounded-sam",
            label="Grounding DINO + SAM",
            description="Grounding DINO boxes for the class prompts, SAM masks inside them (camera images)",
            config_field="grounded_sam",
            config_type=GroundedSamConfig,
            factory=_grounded_sam,
            needs="images",
            missing="the grounded-sam labeler needs camera images (image_2/)",
        ),
    )
}
"""Every 2D labeler by name, in the order forms and help texts list them."""


def make_labeler(config: PipelineConfig, runtime: Runtime | None = None) -> Labeler:
    """The labeler selected by ``config.labeler``, configured by its section of ``config`` and run where
    ``runtime`` says (models folder, shared 2D cache, device). ``PipelineConfig`` accepts only names in
    :data:`LABELERS`, so the lookup cannot miss."""
    spec = LABELERS[config.labeler]
    return spec.factory(getattr(config, spec.config_field), runtime or Runtime())


__all__ = ["LABELERS", "Labeler", "LabelerInput", "LabelerSpec", "SoftMasks", "make_labeler"]
