"""Types shared by the fusion components, and :func:`make_fusion`. Numpy only."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FUSION_NAMES = ("camera_only", "mean_compensation", "kalman")


@dataclass(frozen=True)
class FusedFix:
    """The fused AGV position (x, y in world metres) at ``log_time_ns``; ``source`` is what
    produced it: "camera", "uwb" (compensated UWB) or "kalman"."""

    log_time_ns: int
    position_xy_m: np.ndarray
    source: str


@dataclass(frozen=True)
class SwitchEvent:
    """A change of the sensor the fused estimate relies on.

    from_source, to_source : "camera" | "uwb".
    offset_m : (2,) compensation offset (δx, δy) of paper 003 eq 15 applied from now on
        (mean compensation, camera→UWB), else None.
    jump_m : size of the fused position's jump at the switch: the distance between the last
        fused position before and the first after it.
    detail : one human-readable line (what the offset was computed from, gate resets…).
    """

    log_time_ns: int
    from_source: str
    to_source: str
    offset_m: np.ndarray | None
    jump_m: float
    detail: str = ""

    def text(self) -> str:
        offset = (
            f" offset (δx, δy) = ({self.offset_m[0] * 1000:+.1f}, {self.offset_m[1] * 1000:+.1f}) mm;"
            if self.offset_m is not None
            else ""
        )
        return (
            f"{self.from_source} → {self.to_source}:{offset} jump {self.jump_m * 1000:.1f} mm"
            + (f" ({self.detail})" if self.detail else "")
        )


@dataclass
class FusionStep:
    """What one input produced: a fused fix (or None) and any switch events."""

    fused: FusedFix | None = None
    events: list[SwitchEvent] = field(default_factory=list)
    #: Kalman only: anchor id → True when this range passed the gate.
    range_gate: dict[str, bool] = field(default_factory=dict)


def make_fusion(name: str, anchors_m: dict[str, np.ndarray], tag_z_m: float, kalman_settings=None):
    """The fusion component called ``name`` (one of :data:`FUSION_NAMES`)."""
    from agvviz.fusion.kalman import KalmanFusion, KalmanSettings
    from agvviz.fusion.switching import CameraOnly, MeanCompensation

    if name == "camera_only":
        return CameraOnly()
    if name == "mean_compensation":
        return MeanCompensation()
    if name == "kalman":
        return KalmanFusion(anchors_m, tag_z_m, kalman_settings or KalmanSettings())
    raise ValueError(f"unknown fusion {name!r}; valid: {', '.join(FUSION_NAMES)}")
