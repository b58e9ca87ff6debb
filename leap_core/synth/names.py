"""Names in the demo world: the demo's own extension of the SemanticKITTI raw label ids.

SemanticKITTI's raw ids stop at 259 (``moving-other-vehicle``). The demo scene also holds objects that no
SemanticKITTI class names well; their points carry the raw ids below in the demo's ``labels/*.label`` files,
so a class added in the UI can be evaluated against them (docs/METHOD.md, "The demo world").
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

DEMO_EXTRA_RAW_IDS: Mapping[int, str] = MappingProxyType({300: "traffic-cone", 301: "bench", 302: "bollard"})
"""Raw id -> name of the demo-only objects (ids above SemanticKITTI's 0..259 range)."""
