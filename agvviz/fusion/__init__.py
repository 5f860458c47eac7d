"""Camera–UWB fusion (paper 003 §2.3) as pure components fed in time order. Numpy only.

- :class:`CameraOnly` — the camera fixes, nothing else (the baseline).
- :class:`MeanCompensation` — paper 003: camera-primary switching; while the camera is
  blocked, UWB fixes shifted by the offset of eqs 13–16.
- :class:`KalmanFusion` — constant-velocity Kalman filter with per-anchor range biases,
  camera position updates and UWB range updates, both Mahalanobis-gated.

All three take the same calls — :meth:`camera` (a fix, or ``None`` when no camera saw the
marker), :meth:`uwb_fix` and :meth:`uwb_range` — and return a :class:`FusionStep`.
"""

from agvviz.fusion.common import FUSION_NAMES, FusedFix, FusionStep, SwitchEvent, make_fusion
from agvviz.fusion.kalman import KalmanFusion, KalmanSettings
from agvviz.fusion.switching import CameraOnly, MeanCompensation

__all__ = [
    "FUSION_NAMES",
    "CameraOnly",
    "FusedFix",
    "FusionStep",
    "KalmanFusion",
    "KalmanSettings",
    "MeanCompensation",
    "SwitchEvent",
    "make_fusion",
]
