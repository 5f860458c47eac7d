"""Run statistics from per-frame results: counts, rejections, errors against truth, timing.

Pure numpy; the pipeline's :class:`~agvviz.results.FrameResult` s are reduced to small
:class:`FrameScore` records as they stream past, so memory does not grow with images.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from agvviz.results import FrameResult


@dataclass(frozen=True)
class FrameScore:
    """What a summary needs of one frame."""

    index: int
    rejected: str | None
    position_error_m: float | None
    heading_error_deg: float | None
    reproj_rms_px: float | None
    total_s: float
    detect_s: float
    solve_s: float

    @classmethod
    def of(cls, frame: FrameResult) -> "FrameScore":
        return cls(
            index=frame.index,
            rejected=frame.rejected,
            position_error_m=frame.position_error_m,
            heading_error_deg=frame.heading_error_deg,
            reproj_rms_px=frame.reproj_rms_px,
            total_s=frame.total_s,
            detect_s=frame.detect_s,
            solve_s=frame.solve_s,
        )


def _stats(values: np.ndarray, scale: float) -> dict:
    if values.size == 0:
        return {"rmse": None, "median": None, "p95": None, "max": None, "n": 0}
    v = np.abs(values) * scale
    return {
        "rmse": float(np.sqrt(np.mean(v**2))),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(np.max(v)),
        "n": int(v.size),
    }


def summarize(scores: list[FrameScore], wall_time_s: float | None = None) -> dict:
    """Summary of a run: frames, solved, rejected by reason, position errors (mm), heading
    errors (deg), pipeline time per frame (ms) and throughput (frames/s)."""
    solved = [s for s in scores if s.rejected is None]
    pos = np.array([s.position_error_m for s in solved if s.position_error_m is not None])
    hdg = np.array([s.heading_error_deg for s in solved if s.heading_error_deg is not None])
    reproj = np.array([s.reproj_rms_px for s in solved if s.reproj_rms_px is not None])
    total_s = np.array([s.total_s for s in scores])
    summary = {
        "frames": len(scores),
        "solved": len(solved),
        "rejected": dict(sorted(Counter(s.rejected for s in scores if s.rejected).items())),
        "position_error_mm": _stats(pos, 1000.0),
        "heading_error_deg": _stats(hdg, 1.0),
        "reproj_rms_px": _stats(reproj, 1.0),
        "time_per_frame_ms": float(np.mean(total_s) * 1000.0) if scores else None,
        "detect_ms": float(np.mean([s.detect_s for s in scores]) * 1000.0) if scores else None,
        "solve_ms": float(np.mean([s.solve_s for s in scores]) * 1000.0) if scores else None,
    }
    if wall_time_s is not None and wall_time_s > 0:
        summary["wall_time_s"] = float(wall_time_s)
        summary["frames_per_s"] = len(scores) / wall_time_s
    return summary
