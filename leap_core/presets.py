"""Presets: project files (``projects/*.yaml`` or any file of that format) read as a class schema plus the
pipeline configuration of their ``pipeline:`` section.

This is the one reader of a project file's two halves; the CLI (``--schema``, ``--project-file``) and the
app (a project created from a built-in preset, the demo project) all go through it, so a preset's
``pipeline:`` section is never dropped on one path and applied on another.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.errors import ConfigError, LeapError, SchemaError
from leap_core.schema import Schema, builtin_names, builtin_path, load_project_file


@dataclass(frozen=True)
class Preset:
    """A project file, read."""

    schema: Schema
    """Its classes."""
    pipeline: PipelineConfig
    """Its ``pipeline:`` section applied onto the base config (default ``PipelineConfig()``)."""
    source: Path
    """The file it was read from."""
    names_labeler: bool = False
    """Its ``pipeline:`` section sets ``labeler`` (otherwise the labeler is the base config's, and a run
    that nobody named one for picks the one that can run: ``leap_core.pipeline.preflight.pick_labeler``)."""


def load_preset(name_or_path: str | Path, base: PipelineConfig | None = None) -> Preset:
    """Read a project file: an existing file path, else the built-in ``projects/<name>.yaml``.

    Args:
        name_or_path: a file path, or the name of a built-in preset (:func:`list_presets`).
        base: the config the file's ``pipeline:`` section applies onto; default ``PipelineConfig()``.

    Raises:
        SchemaError: unknown name, unreadable file or bad class list (names the file and the entry).
        LeapError: a bad ``pipeline:`` entry: ``field`` = its path (``("pipeline", "fusion",
            "voxel_size")``), the message is the file, then the :class:`ConfigError`'s message.
    """
    path = Path(name_or_path)
    if path.is_file():
        return _read(path, base)
    if str(name_or_path) not in list_presets():
        raise SchemaError(
            f"{name_or_path}: no such file, and no built-in preset of that name "
            f"(built-in: {', '.join(list_presets()) or 'none'})"
        )
    return builtin_preset(str(name_or_path), base)


def builtin_preset(name: str, base: PipelineConfig | None = None) -> Preset:
    """The built-in preset ``projects/<name>.yaml``; ``name`` is only ever a name, never a path (for
    names that come from outside, such as an API payload). Raises as :func:`load_preset`."""
    return _read(builtin_path(name), base)


def list_presets() -> list[str]:
    """Names of the built-in presets, sorted."""
    return builtin_names()


def _read(path: Path, base: PipelineConfig | None) -> Preset:
    schema, section = load_project_file(path)
    try:
        pipeline = config_from_dict(section, base)
    except ConfigError as exc:
        raise LeapError(f"{path}: {exc}", field=exc.field) from None
    return Preset(schema, pipeline, path, "labeler" in section)


__all__ = ["Preset", "builtin_preset", "list_presets", "load_preset"]
