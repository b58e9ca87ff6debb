"""Deployment values of a run: where models and caches live and which device computes.

These are facts about the machine that runs the pipeline, not settings of a labeling project, so they
never live in :class:`~leap_core.config.PipelineConfig` (a project file or the app's database cannot
point a run at another folder). The CLI builds a :class:`Runtime` from its flags and the app from its
server settings; both pass it to :func:`leap_core.pipeline.run_pipeline` and the labeler factory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

from leap_core.errors import ConfigError

Device = Literal["auto", "cpu", "cuda"]


@dataclass(frozen=True)
class Runtime:
    """Where and how one pipeline run executes."""

    models_dir: Path | None = None
    """Local folder with one subfolder per model (``<models_dir>/grounding-dino-tiny``); None = the user's
    Hugging Face cache."""
    cache_dir: Path | None = None
    """Shared 2D cache folder reused across runs of a project; None = no sharing."""
    device: Device = "auto"
    """Where models run: "auto" picks CUDA when torch sees a GPU, else the CPU."""
    allow_download: bool = False
    """Without ``models_dir``: may a model missing from the Hugging Face cache be downloaded?"""

    def __post_init__(self) -> None:
        if self.device not in get_args(Device):
            raise ConfigError(f"must be 'auto', 'cpu' or 'cuda', got {self.device!r}", field=("device",))


__all__ = ["Device", "Runtime"]
