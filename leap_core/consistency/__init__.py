"""3D Consistency Network (docs/METHOD.md stage C): a WaffleIron-style point backbone self-trained on the most
confident voxel labels, whose predictions on every point are fused back into the voxel grid.

Modules: :mod:`.config` (typed configs), :mod:`.backbone` (pure ``nn.Module``\\ s), :mod:`.data` (scan →
tensors), :mod:`.selection` (reliable labels), :mod:`.train` (training, checkpoint, inference),
:mod:`.stage` (:func:`~leap_core.consistency.stage.run_3dcn_iteration`, what the pipeline calls).
Only the configs are imported here, so reading a config does not import torch.
"""

from __future__ import annotations

from leap_core.consistency.config import BackboneConfig, ConsistencyConfig

__all__ = ["BackboneConfig", "ConsistencyConfig"]
