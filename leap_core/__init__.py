"""LeAP Studio core: the open-vocabulary 3D labeling pipeline (no web, database or viewer code)."""

from __future__ import annotations

__version__ = "0.1.0"
