"""Load a benchmark or script of the repository (not a package) as a module, to test its pure parts."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_script(relpath: str) -> ModuleType:
    """``ROOT / relpath`` (e.g. ``benchmarks/bench_scale.py``) imported under its file stem and registered in
    ``sys.modules`` (dataclasses defined in it need their module there)."""
    path = ROOT / relpath
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    spec.loader.exec_module(module)
    return module
