"""Types shared by the fusion components: what they read (:class:`UwbPosition`) and what they
return (:class:`FusionStep`, :class:`FusedFix`, :class:`SwitchEvent`). Numpy only."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

FUSION_NAMES = ("camera_only", "mean_compensation", "kalman")


class UwbPosition(Protocol):
    """A UWB position fix as the fusion components read it: :class:`agvviz.uwb.localize.UwbFix`
    is one. agvviz.fusion sits beside agvviz.uwb, not above it, so it names the two fields it
    reads instead of importing the class."""

    #: When the fix was taken (the recording's log time, ns).
    log_time_ns: int
    #: (3,) world position of the UWB tag (metres); fusion uses x and y.
    position_m: np.ndarray


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
