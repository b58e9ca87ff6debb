"""A LiDAR-only segmentation model trained on a project's final labels (docs/METHOD.md "A LiDAR-only model").

- :mod:`~leap_core.lidar_model.config`: :class:`LidarModelConfig`, the training settings;
- :mod:`~leap_core.lidar_model.data`: the labeled scans (a run's final labels, corrections included, or a
  dataset's ground truth) and the validation split (whole sequences or frame blocks);
- :mod:`~leap_core.lidar_model.train`: resumable training, validation, the model card;
- :mod:`~leap_core.lidar_model.model`: the checkpoint and card files;
- :mod:`~leap_core.lidar_model.predict`: labeling sequences without a camera into a run folder;
- :mod:`~leap_core.lidar_model.export`: TorchScript export.

Only the config is imported here (no torch).
"""

from leap_core.lidar_model.config import LidarModelConfig

__all__ = ["LidarModelConfig"]
