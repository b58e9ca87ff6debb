"""2D labelers: the :class:`~leap_core.labelers.base.Labeler` protocol and its implementations.

``make_labeler`` builds the labeler a :class:`~leap_core.config.PipelineConfig` names; implementations are
imported on demand so that choosing "simulated" never loads the model stack.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from leap_core.errors import LeapError
from leap_core.labelers.base import Labeler, SoftMasks

if TYPE_CHECKING:
    from leap_core.config import PipelineConfig

LABELERS: tuple[str, ...] = ("simulated", "grounded-sam")
"""Names accepted by ``PipelineConfig.labeler`` and ``leap run --labeler``."""


def make_labeler(config: PipelineConfig) -> Labeler:
    """The labeler selected by ``config.labeler``, configured by its section of ``config``.

    Raises:
        LeapError: for an unknown labeler name.
    """
    if config.labeler == "simulated":
        from leap_core.labelers.simulated import SimulatedLabeler

        return SimulatedLabeler(config.simulated)
    if config.labeler == "grounded-sam":
        from leap_core.labelers.grounded_sam import GroundedSamLabeler

        return GroundedSamLabeler(config.grounded_sam)
    raise LeapError(
        f"pipeline.labeler: unknown labeler {config.labeler!r} (choose from {', '.join(LABELERS)})"
    )


__all__ = ["LABELERS", "Labeler", "SoftMasks", "make_labeler"]
