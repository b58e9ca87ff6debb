"""The ``demo_synth`` setting: overrides of the demo sequence generator's :class:`SynthConfig`.

Read by :class:`app.core.config.Settings` (to refuse a bad value at start-up) and by :mod:`app.demo`
(to generate the sequence). It lives here, below both, so that the settings never import the demo module
(which imports the settings).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from leap_core.errors import LeapError
from leap_core.synth import SynthConfig


def synth_config(overrides: dict[str, Any]) -> SynthConfig:
    """``SynthConfig()`` with nested overrides, e.g. ``{"frames": 8, "lidar": {"beams": 32}}``.

    Raises:
        LeapError: naming the field (``demo_synth.lidar.beams: ...``) for an unknown key or a bad value.
    """

    def apply(obj: Any, changes: dict[str, Any], where: str) -> Any:
        if not isinstance(changes, dict):
            raise LeapError(f"{where}: must be a mapping of settings, got {changes!r}")
        names = {f.name for f in dataclasses.fields(obj)}
        updates: dict[str, Any] = {}
        for key, value in changes.items():
            if key not in names:
                raise LeapError(f"{where}.{key}: unknown setting (known: {', '.join(sorted(names))})")
            current = getattr(obj, key)
            if dataclasses.is_dataclass(current):
                updates[key] = apply(current, value, f"{where}.{key}")
            else:
                updates[key] = (
                    tuple(value) if isinstance(current, tuple) and isinstance(value, list) else value
                )
        try:
            return dataclasses.replace(obj, **updates)
        except (TypeError, ValueError) as exc:
            raise LeapError(f"{where}: {exc}") from None

    config: SynthConfig = apply(SynthConfig(), overrides, "demo_synth")
    return config


__all__ = ["synth_config"]
