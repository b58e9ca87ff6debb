"""A trained LiDAR-only model on disk: its checkpoint (weights + model card) and the card beside it.

``<name>.pt`` (``torch.save``, read with ``weights_only``: no code is unpickled) holds the format tag, the
settings it was trained with, the class count, the weights and the **model card**; ``<name>.card.json``
repeats the card for readers that do not load torch (the app's list of models). The card says what the
model is (classes with their export ids, the schema), what it saw (data, runs, scans, the checkpoint it
started from), how (settings, steps, seconds, points) and how well (validation mIoU per class), and the
code that trained it (package version and git commit).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from leap_core.consistency.backbone import PointSegmenter
from leap_core.errors import ModelLoadError
from leap_core.io_utils import atomic_write, atomic_write_json
from leap_core.lidar_model.card import card_path, read_card
from leap_core.lidar_model.config import LidarModelConfig, model_config_from_dict, model_config_to_dict
from leap_core.schema import Schema

MODEL_FORMAT = "leap-lidar-model"
MODEL_VERSION = 1


def state_path(model: str | Path) -> Path:
    """The resumable training state beside a checkpoint: ``model.pt`` → ``model.state.pt``."""
    return Path(model).with_suffix(".state.pt")


@dataclass
class LidarModel:
    """A loaded model: its network (eval mode), settings, schema and card."""

    network: PointSegmenter
    config: LidarModelConfig
    schema: Schema
    """The classes it predicts (index order) with their export ids and ground-truth ids."""
    card: dict[str, Any]


def save_model(
    path: str | Path, network: PointSegmenter, cfg: LidarModelConfig, card: dict[str, Any]
) -> None:
    """Write the checkpoint, then its card (each atomically)."""
    payload = {
        "format": MODEL_FORMAT,
        "version": MODEL_VERSION,
        "config": model_config_to_dict(cfg),
        "num_classes": int(network.num_classes),
        "state_dict": {k: v.detach().cpu() for k, v in network.state_dict().items()},
        "card": card,
    }
    with atomic_write(path, "wb") as fh:
        torch.save(payload, fh)
    atomic_write_json(card_path(path), card)


def load_model(path: str | Path, device: str = "cpu") -> LidarModel:
    """Read a checkpoint written by :func:`save_model`.

    Raises:
        ModelLoadError: naming the file, when it is missing, unreadable, of another format, or its weights
            do not fit the network its settings describe.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelLoadError(f"{path}: model not found (train one with `leap train`)")
    try:
        with warnings.catch_warnings():  # torch warns before refusing a TorchScript archive
            warnings.simplefilter("ignore", UserWarning)
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several unrelated types for corrupt files
        raise ModelLoadError(f"{path}: unreadable model ({type(exc).__name__}: {exc})") from exc
    if not isinstance(payload, dict) or payload.get("format") != MODEL_FORMAT:
        raise ModelLoadError(f"{path}: not a LeAP LiDAR model (a `leap train` checkpoint)")
    if payload.get("version") != MODEL_VERSION:
        raise ModelLoadError(f"{path}: model version {payload.get('version')} != supported {MODEL_VERSION}")
    try:
        cfg = model_config_from_dict(payload["config"])
        card = dict(payload["card"])
        schema = Schema.from_dict(card["schema"], source=f"{path} (card)")
        network = PointSegmenter(cfg.backbone, int(payload["num_classes"]))
        network.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ModelLoadError(f"{path}: model does not match its settings ({exc})") from exc
    if schema.num_classes != network.num_classes:
        raise ModelLoadError(f"{path}: card has {schema.num_classes} classes, network {network.num_classes}")
    network.eval()
    return LidarModel(network.to(device), cfg, schema, card)


__all__ = [
    "MODEL_FORMAT",
    "LidarModel",
    "card_path",
    "load_model",
    "read_card",
    "save_model",
    "state_path",
]
