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
    from leap_core.runtime import Runtime

LABELERS: tuple[str, ...] = ("simulated", "grounded-sam")
"""Names accepted by ``PipelineConfig.labeler`` and ``leap run --labeler``."""


def make_labeler(config: PipelineConfig, runtime: Runtime | None = None) -> Labeler:
    """The labeler selected by ``config.labeler``, configured by its section of ``config`` and run where
    ``runtime`` says (models folder, shared 2D cache, device).

    Raises:
        LeapError: for an unknown labeler name.
    """
    if config.labeler == "simulated":
        from leap_core.labelers.simulated import SimulatedLabeler

        return SimulatedLabeler(config.simulated)
    if config.labeler == "grounded-sam":
        import dataclasses

        from leap_core.labelers.cache import pass_cache_dir
        from leap_core.labelers.grounded_sam import GroundedSamLabeler

        # Transitional: runtime values still travel as config fields until GroundedSamConfig drops them.
        gs = config.grounded_sam
        if runtime is not None:
            if runtime.models_dir is not None and gs.models_dir is None:
                gs = dataclasses.replace(gs, models_dir=str(runtime.models_dir))
            if runtime.cache_dir is not None and gs.cache_dir is None:
                # Per-pass detector cache beside the per-frame one: a prompt edit of one class then only
                # recomputes that class's pass (per-class mode).
                gs = dataclasses.replace(gs, cache_dir=str(pass_cache_dir(runtime.cache_dir)))
        return GroundedSamLabeler(gs)
    raise LeapError(
        f"pipeline.labeler: unknown labeler {config.labeler!r} (choose from {', '.join(LABELERS)})"
    )


__all__ = ["LABELERS", "Labeler", "SoftMasks", "make_labeler"]
