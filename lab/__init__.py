"""The research lab beside the product: what fits the simulated labeler to the paper and reproduces its
Table 1, and the tuning sweeps behind the product's defaults.

The product (``leap_core``, ``app``) labels point clouds; its simulated labeler and the demo generator are
what the demo and the app use. The lab is research code on top of it and imports it one way: nothing in
``leap_core`` or ``app`` imports the lab (``tests/app/test_import_graph.py``). What it holds:

- ``lab.paper_labeler``: the ``simulated-paper`` labeler, the product's simulated labeler plus the noise
  terms fitted to the paper's Grounding DINO + SAM errors (docs/METHOD.md A.7-A.8), with its config section
  ``simulated_paper`` and presets ``default`` and ``paper`` (``lab/paper_preset.py``);
- ``python -m lab ...``: the ``leap`` command line with the lab's labelers registered
  (``python -m lab run SEQ --labeler simulated-paper --labeler-preset paper --out RUN``);
- ``python -m lab.fit_labeler``: fits the ``paper`` preset (and ``--write`` rewrites it);
- ``python -m lab.table1``: the paper's Table 1 on the synthetic domains;
- ``python -m lab.tune_defaults``: the sweep of the 3D-CN defaults on tuning seeds;
- ``python -m lab.selection_purity``: what the 3D-CN is taught, against the ground truth.

Importing ``lab`` registers its labeler into ``leap_core.labelers.LABELERS`` (:func:`register`), so a
config dict may name it (``pipeline: {labeler: simulated-paper, simulated_paper: {preset: paper}}``).
"""

from __future__ import annotations

from lab.paper_labeler import LABELER, SimulatedPaperConfig, SimulatedPaperLabeler
from leap_core.labelers import register_labeler, unregister_labeler


def register() -> None:
    """Register the lab's labeler into ``leap_core.labelers.LABELERS`` (again after :func:`unregister`;
    a second call changes nothing)."""
    register_labeler(LABELER)


def unregister() -> None:
    """Remove the lab's labeler from the registry (tests that must see the product's labelers only)."""
    unregister_labeler(LABELER.name)


register()

__all__ = ["LABELER", "SimulatedPaperConfig", "SimulatedPaperLabeler", "register", "unregister"]
