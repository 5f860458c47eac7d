"""Camera–UWB fusion (paper 003 §2.3) as pure components fed in time order. Numpy only.

- :class:`CameraOnly` — the camera fixes, nothing else (the baseline).
- :class:`MeanCompensation` — paper 003: camera-primary switching; while the camera is
  blocked, UWB fixes shifted by the offset of eqs 13–16.
- :class:`KalmanFusion` — constant-velocity Kalman filter with per-anchor range biases,
  camera position updates and UWB range updates, both Mahalanobis-gated.

All three take the same calls — :meth:`camera` (a fix, or ``None`` when no camera saw the
marker), :meth:`uwb_fix` and :meth:`uwb_range` — and return a :class:`FusionStep`.
:func:`make_fusion` (defined here, above the three) makes one by name.
"""

from __future__ import annotations

import numpy as np

from agvviz.fusion.common import FUSION_NAMES, FusedFix, FusionStep, SwitchEvent, UwbPosition
from agvviz.fusion.kalman import KalmanFusion, KalmanSettings
from agvviz.fusion.switching import CameraOnly, MeanCompensation


def make_fusion(name: str, anchors_m: dict[str, np.ndarray], tag_z_m: float, kalman_settings=None):
    """The fusion component called ``name`` (one of :data:`FUSION_NAMES`)."""
    if name == "camera_only":
        return CameraOnly()
    if name == "mean_compensation":
        return MeanCompensation()
    if name == "kalman":
        return KalmanFusion(anchors_m, tag_z_m, kalman_settings or KalmanSettings())
    raise ValueError(f"unknown fusion {name!r}; valid: {', '.join(FUSION_NAMES)}")


__all__ = [
    "FUSION_NAMES",
    "CameraOnly",
    "FusedFix",
    "FusionStep",
    "KalmanFusion",
    "KalmanSettings",
    "MeanCompensation",
    "SwitchEvent",
    "UwbPosition",
    "make_fusion",
]
