"""Statistics of the camera fixes, UWB fixes and fused positions of a run (paper 003).

All errors are 2-D (x, y) — paper 003 eq 17 — in millimetres. :class:`FusionStats` keeps only
numbers while items stream past. "Blocked" outputs are fused positions produced while no
camera had a fix (the stretch paper 003 Table 4 scores).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agvviz.model.fusion import FrameSetResult, RangeResult, UwbFixResult


def error_stats_mm(errors_m) -> dict:
    """mean (paper 003's figure), RMSE, median, p95, max in mm, and the count."""
    v = np.asarray(errors_m, dtype=float) * 1000.0
    if v.size == 0:
        return {"mean": None, "rmse": None, "median": None, "p95": None, "max": None, "n": 0}
    return {
        "mean": float(np.mean(v)),
        "rmse": float(np.sqrt(np.mean(v**2))),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(np.max(v)),
        "n": int(v.size),
    }


@dataclass
class FusionStats:
    """Accumulates the fuse stage's items (:mod:`agvviz.model.fusion`); :meth:`summary` reduces them."""

    camera_xy_m: list[float] = field(default_factory=list)
    camera_used: dict[str, int] = field(default_factory=dict)
    time_stamps: int = 0
    uwb_xy_m: list[float] = field(default_factory=list)
    gdop: list[float] = field(default_factory=list)
    ranges: int = 0
    range_gated: int = 0
    kalman_range_gated: int = 0
    fused_m: list[float] = field(default_factory=list)
    fused_blocked_m: list[float] = field(default_factory=list)
    jumps_m: list[float] = field(default_factory=list)
    switches: int = 0

    def add(self, item) -> None:
        if isinstance(item, FrameSetResult):
            self.time_stamps += 1
            primary = item.selection.primary
            if primary is not None:
                name = "+".join(item.selection.used)
                self.camera_used[name] = self.camera_used.get(name, 0) + 1
                if primary.T_world_agv_truth is not None:
                    self.camera_xy_m.append(
                        float(np.linalg.norm(primary.T_world_agv[:2, 3] - primary.T_world_agv_truth[:2, 3]))
                    )
        elif isinstance(item, RangeResult):
            self.ranges += 1
            self.kalman_range_gated += sum(1 for ok in item.step.range_gate.values() if not ok)
        elif isinstance(item, UwbFixResult):
            if item.error_m is not None:
                self.uwb_xy_m.append(item.error_m)
            if np.isfinite(item.fix.gdop):
                self.gdop.append(item.fix.gdop)
            self.range_gated += int(np.sum(item.fix.gated))
        if item.fused_error_m is not None:
            self.fused_m.append(item.fused_error_m)
            if not item.camera_available:
                self.fused_blocked_m.append(item.fused_error_m)
        for event in item.step.events:
            self.switches += 1
            self.jumps_m.append(event.jump_m)

    def summary(self) -> dict:
        return {
            "camera_xy_error_mm": error_stats_mm(self.camera_xy_m),
            "camera_fix_rate": (len(self.camera_xy_m) / self.time_stamps) if self.time_stamps else None,
            "camera_used": dict(sorted(self.camera_used.items())),
            "uwb_xy_error_mm": error_stats_mm(self.uwb_xy_m),
            "uwb_gdop_mean": float(np.mean(self.gdop)) if self.gdop else None,
            "uwb_ranges": self.ranges,
            "uwb_ranges_gated": self.range_gated,
            "kalman_ranges_gated": self.kalman_range_gated,
            "fused_xy_error_mm": error_stats_mm(self.fused_m),
            "fused_blocked_xy_error_mm": error_stats_mm(self.fused_blocked_m),
            "switches": self.switches,
            "switch_jump_mm": error_stats_mm(self.jumps_m),
        }
