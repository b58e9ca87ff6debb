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

MAX_FRAME_THREADS = 64
"""Upper bound of :attr:`Runtime.frame_threads` (each thread holds one frame's arrays)."""


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
    frame_threads: int = 4
    """Frames that the per-frame 3D stages (project, label_points, export) compute at a time, on threads of
    the run's process (:meth:`leap_core.pipeline.context.Ctx.each_frame`). NumPy releases the interpreter
    lock in its array loops and an atomic write's fsync waits for the disk, so a few frames in flight
    overlap one frame's file round trips with another's arithmetic. The files and the progress reports are
    the same for every value (progress counts frames in frame order); 1 computes one frame after another.
    The 2D labeler always labels one frame at a time (its models are not shared between threads)."""

    init_3dcn: Path | None = None
    """A 3D-CN checkpoint (one a run wrote, ``RUN/3dcn/3dcn_iter1.pt``) whose weights every 3D-CN round
    starts from instead of random ones: the round fine-tunes it on its own reliable labels, at
    ``consistency.finetune_lr`` for ``consistency.finetune_min_steps`` (default one epoch), as the paper
    fine-tunes a pre-trained network. Its backbone and class count must match the run's. A path, so it is a
    runtime value and never a project setting; its content is part of the 3D-CN's fingerprints (another file
    trains again). None = random weights."""

    # --- the distributed engine (leap_core.pipeline.executor)
    ray_address: str | None = None
    """Run per-frame stages, fusion and the 3D-CN's inference as Ray tasks, and a run's several
    sequences at once: ``"auto"`` joins the Ray cluster this machine belongs
    to (``ray start --head`` / ``--address``) or, when there is none, starts a private local instance of
    :attr:`ray_cpus` CPUs; any other value is a cluster address (``"10.0.0.5:6379"``,
    ``"ray://host:10001"``). None = the local single-process engine, which never imports ray. The run
    folder (and dataset) must lie on storage every node sees at the same path."""
    ray_cpus: int | None = None
    """CPUs of the local Ray instance that ``"auto"`` starts when no cluster runs; None = the cores this
    process may use. Ignored when joining a cluster (its nodes declare their own)."""

    def __post_init__(self) -> None:
        if self.device not in get_args(Device):
            raise ConfigError(f"must be 'auto', 'cpu' or 'cuda', got {self.device!r}", field=("device",))
        if self.ray_address is not None and not self.ray_address.strip():
            raise ConfigError("must be 'auto' or a Ray cluster address, got ''", field=("ray_address",))
        if self.ray_cpus is not None and self.ray_cpus < 1:
            raise ConfigError(f"must be >= 1, got {self.ray_cpus}", field=("ray_cpus",))
        if (
            isinstance(self.frame_threads, bool)
            or not isinstance(self.frame_threads, int)
            or not 1 <= self.frame_threads <= MAX_FRAME_THREADS
        ):
            raise ConfigError(
                f"must be an integer in 1..{MAX_FRAME_THREADS}, got {self.frame_threads!r}",
                field=("frame_threads",),
            )


__all__ = ["MAX_FRAME_THREADS", "Device", "Runtime"]
