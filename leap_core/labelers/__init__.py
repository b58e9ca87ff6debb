"""2D labelers: the :class:`~leap_core.labelers.base.Labeler` protocol, the implementations, their registry.

:data:`LABELERS` holds one :class:`LabelerSpec` per labeler. Everything that names or builds labelers
derives from it: ``PipelineConfig.labeler`` validation, the config sections of
:class:`~leap_core.config.PipelineConfig` (one per labeler, named :attr:`LabelerSpec.section`, holding a
:attr:`LabelerSpec.config_type`), :func:`make_labeler`, the ``--labeler`` help of the CLI and the labeler
choices of the app's form. Adding a labeler is one record, its config dataclass and its class: here for
the product's labelers, or :func:`register_labeler` from a package beside leap_core (the research lab's
``simulated-paper`` registers itself when imported).

Importing this module loads the labelers' configs and classes but not their model stacks: torch and
transformers are imported by the model labelers (grounded-sam, sam3) only when they first need them.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar

from leap_core.errors import LeapError
from leap_core.labelers.base import ImageModelLabeler, Labeler, SoftMasks
from leap_core.labelers.grounded_sam import GroundedSamConfig, GroundedSamLabeler
from leap_core.labelers.sam3 import Sam3Labeler, Sam3LabelerConfig
from leap_core.labelers.simulated import SIMULATED_PRESETS, SimulatedLabeler, SimulatedLabelerConfig
from leap_core.runtime import Runtime

if TYPE_CHECKING:
    from leap_core.config import PipelineConfig

LabelerInput = Literal["gt2d", "images"]
"""What a labeler reads per frame: ``gt2d`` = the dataset's 2D ground truth (``gt2d/semantic``,
``gt2d/instance``), ``images`` = the camera images (``image_2/``)."""

C = TypeVar("C")
"""A labeler's config dataclass."""


@dataclass(frozen=True)
class LabelerSpec(Generic[C]):
    """One 2D labeler: its name, its config section, how to build it and what it needs."""

    name: str
    """Value of ``PipelineConfig.labeler`` (and ``leap run --labeler``)."""
    label: str
    """Short human name (the app form's choice)."""
    description: str
    """One line on what it does (CLI help)."""
    section: str
    """Its config section: the key of its settings in the config dict (``pipeline: {<section>: {...}}``)
    and in ``PipelineConfig.labelers``."""
    config_type: type[C]
    """The section's config dataclass (its defaults are the section's defaults)."""
    factory: Callable[[C, Runtime], Labeler]
    """``factory(section_config, runtime)``: the labeler for its config section and the run's deployment
    values (models folder, 2D cache folder, device)."""
    needs: LabelerInput
    """The input it reads from a dataset."""
    missing: str
    """One line for a dataset that lacks ``needs``, e.g. to follow the folder's name in an error (what to
    do instead depends on the folder: :func:`missing_input`)."""
    presets: tuple[str, ...] = ()
    """Names of whole settings of its section (``pipeline: {<section>: {preset: NAME}}``, ``leap run
    --labeler-preset NAME``): the names its config type's ``from_preset`` accepts."""
    models: Callable[[C], tuple[str, ...]] = field(default=lambda _config: ())
    """``models(section_config)``: the Hugging Face ids of the model folders it loads (none for a labeler
    without models), for the pre-flight check and the cache of dataset checks."""

    @property
    def title(self) -> str:
        """Its name with its human name, said once: ``grounded-sam (Grounding DINO + SAM)``, or the human
        name alone when it already starts with the name (``simulated (from 2D ground truth)``)."""
        return self.label if self.label.startswith(self.name) else f"{self.name} ({self.label})"

    def config_of(self, config: PipelineConfig) -> C:
        """This labeler's section of ``config`` (its defaults when ``config`` was made before this
        labeler was registered)."""
        return config.labeler_section(self.section, self.config_type)


def _simulated(config: SimulatedLabelerConfig, runtime: Runtime) -> Labeler:  # noqa: ARG001 - no deployment values
    return SimulatedLabeler(config)


def _grounded_sam(config: GroundedSamConfig, runtime: Runtime) -> Labeler:
    return GroundedSamLabeler(config, runtime)


def _sam3(config: Sam3LabelerConfig, runtime: Runtime) -> Labeler:
    return Sam3Labeler(config, runtime)


_SIMULATED: LabelerSpec[SimulatedLabelerConfig] = LabelerSpec(
    name="simulated",
    label="simulated (from 2D ground truth)",
    description="noisy 2D labels made from the dataset's 2D ground truth (demo data, no models)",
    section="simulated",
    config_type=SimulatedLabelerConfig,
    factory=_simulated,
    needs="gt2d",
    missing="the simulated labeler needs 2D ground truth (gt2d/semantic, gt2d/instance)",
    presets=tuple(SIMULATED_PRESETS),
)
_GROUNDED_SAM: LabelerSpec[GroundedSamConfig] = LabelerSpec(
    name="grounded-sam",
    label="Grounding DINO + SAM",
    description="Grounding DINO boxes for the class prompts, SAM masks inside them (camera images)",
    section="grounded_sam",
    config_type=GroundedSamConfig,
    factory=_grounded_sam,
    needs="images",
    missing="the grounded-sam labeler needs camera images (image_2/)",
    models=lambda c: (c.detector_id, c.segmenter_id),
)
_SAM3: LabelerSpec[Sam3LabelerConfig] = LabelerSpec(
    name="sam3",
    label="SAM 3",
    description="SAM 3 instance masks for every class prompt, one model (camera images)",
    section="sam3",
    config_type=Sam3LabelerConfig,
    factory=_sam3,
    needs="images",
    missing="the sam3 labeler needs camera images (image_2/)",
    models=lambda c: (c.model_id,),
)
PRODUCT_LABELERS = (_SIMULATED, _GROUNDED_SAM, _SAM3)
"""The labelers that are part of leap_core (they stay registered)."""


LABELERS: dict[str, LabelerSpec[Any]] = {spec.name: spec for spec in PRODUCT_LABELERS}
"""Every 2D labeler by name, in the order forms and help texts list them (the product's first, then those
registered by :func:`register_labeler`)."""


def register_labeler(spec: LabelerSpec[Any]) -> None:
    """Add ``spec`` to :data:`LABELERS`; registering the same record again changes nothing.

    Config objects made before the call get the new section's defaults when they are read
    (:meth:`LabelerSpec.config_of`); dicts read after it may hold the section.

    Raises:
        ValueError: another record has the same name, or another labeler's section has the same name.
    """
    if LABELERS.get(spec.name) is spec:
        return
    if spec.name in LABELERS:
        raise ValueError(f"a labeler named {spec.name!r} is registered already")
    taken = next((s.name for s in LABELERS.values() if s.section == spec.section), None)
    if taken is not None:
        raise ValueError(f"config section {spec.section!r} belongs to the {taken!r} labeler already")
    LABELERS[spec.name] = spec


def unregister_labeler(name: str) -> None:
    """Remove a labeler :func:`register_labeler` added (a test that registers one for its own span); the
    product's own labelers stay.

    Raises:
        ValueError: ``name`` is one of the product's labelers.
    """
    if name in (s.name for s in PRODUCT_LABELERS):
        raise ValueError(f"the {name!r} labeler is part of leap_core and stays registered")
    LABELERS.pop(name, None)


def labeler_by_section(section: str) -> LabelerSpec[Any] | None:
    """The registered labeler whose config section is ``section``, or None."""
    return next((s for s in LABELERS.values() if s.section == section), None)


INPUT_FOLDERS: dict[LabelerInput, str] = {
    "gt2d": "2D ground truth (gt2d/)",
    "images": "camera images (image_2/)",
}
"""Each labeler input as a folder's content, for messages."""


def missing_input(spec: LabelerSpec[Any], has: Collection[LabelerInput]) -> str:
    """Why ``spec``'s labeler cannot label a dataset that lacks its input, and what to do, fitted to what
    the dataset has (``has``): another labeler whose input it holds, else what to add. E.g. the simulated
    labeler on a folder of camera images: "...; for its camera images (image_2/) choose the grounded-sam
    labeler"; on a folder of scans alone: "..., and the dataset has no camera images (image_2/) for the
    grounded-sam labeler either: add them"."""
    usable = [s for s in LABELERS.values() if s.needs in has and s.name != spec.name]
    if usable:
        return f"{spec.missing}; for its {INPUT_FOLDERS[usable[0].needs]} choose the {usable[0].name} labeler"
    other = next((s for s in LABELERS.values() if s.needs != spec.needs), None)
    if other is None:
        return spec.missing
    return (
        f"{spec.missing}, and the dataset has no {INPUT_FOLDERS[other.needs]} for the {other.name} "
        "labeler either: add them"
    )


Weights = Literal["real", "random", "none"]
"""What a labeler's 2D labels rest on: ``real`` model weights, ``random`` ones (tiny test models of ``leap
make-tiny-models``: meaningless labels), or ``none`` (no model: the simulated labelers read 2D ground
truth)."""


def labeler_weights(labeler: Labeler) -> Weights:
    """:data:`Weights` of ``labeler`` (resolves a model labeler's folders; loads no model)."""
    if isinstance(labeler, ImageModelLabeler):
        return "random" if labeler.uses_random_weights else "real"
    return "none"


def model_labeler(config: PipelineConfig, runtime: Runtime | None = None) -> tuple[ImageModelLabeler, int]:
    """The model labeler ``config.labeler`` (as :func:`make_labeler`) and its ``batch_size``, for work that
    fills its 2D cache.

    Raises:
        LeapError: ``config.labeler`` runs no models (the simulated labelers read 2D ground truth).
    """
    labeler = make_labeler(config, runtime)
    if not isinstance(labeler, ImageModelLabeler):
        names = " or ".join(s.name for s in LABELERS.values() if s.models(s.config_type()))
        raise LeapError(
            f"the {config.labeler} labeler runs no models, so it has no 2D cache to fill: use {names}"
        )
    return labeler, int(LABELERS[config.labeler].config_of(config).batch_size)


def make_labeler(config: PipelineConfig, runtime: Runtime | None = None) -> Labeler:
    """The labeler selected by ``config.labeler``, configured by its section of ``config`` and run where
    ``runtime`` says (models folder, shared 2D cache, device). ``PipelineConfig`` accepts only names in
    :data:`LABELERS`, so the lookup cannot miss."""
    spec = LABELERS[config.labeler]
    return spec.factory(spec.config_of(config), runtime or Runtime())


__all__ = [
    "INPUT_FOLDERS",
    "LABELERS",
    "PRODUCT_LABELERS",
    "Labeler",
    "LabelerInput",
    "LabelerSpec",
    "SoftMasks",
    "Weights",
    "labeler_by_section",
    "labeler_weights",
    "make_labeler",
    "missing_input",
    "model_labeler",
    "register_labeler",
    "unregister_labeler",
]
