"""A model's card (``model.card.json`` beside ``model.pt``), read without torch: the server lists models and
answers their routes without importing torch, which costs a second at every start."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from leap_core.errors import ModelLoadError


def card_path(model: str | Path) -> Path:
    """The model card beside a checkpoint: ``model.pt`` → ``model.card.json``."""
    return Path(model).with_suffix(".card.json")


def read_card(path: str | Path) -> dict[str, Any]:
    """A model's card from its ``.card.json`` (no torch).

    Raises:
        ModelLoadError: naming the file, when it is missing or not JSON.
    """
    cp = card_path(path)
    try:
        data = json.loads(cp.read_text())
    except (OSError, ValueError) as exc:
        raise ModelLoadError(f"{cp}: unreadable model card ({exc})") from exc
    if not isinstance(data, dict):
        raise ModelLoadError(f"{cp}: a model card is a JSON object")
    return data


__all__ = ["card_path", "read_card"]
