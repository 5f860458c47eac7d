"""Per-frame results of a replay: what the pipeline saw and decided.

Plain dataclasses shared by :mod:`agvviz.pipeline` (which produces them),
:mod:`agvviz.viz` (which logs them) and :mod:`agvviz.evaluation` (which scores them).
Frames and units follow :mod:`agvviz.conventions`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Reasons a frame is rejected. Every rejected frame carries exactly one.
REJECT_NO_MARKER = "no_marker"  # no QR code found in the frame
REJECT_DECODE = "decode_failed"  # code found but its payload could not be decoded
REJECT_PAYLOAD = "payload_invalid"  # payload decoded but refused by the strict parser
REJECT_GEOMETRY = "degenerate_geometry"  # payload points do not define a marker plane
REJECT_SOLVER = "solver_failed"  # the solver returned no pose
REJECT_REPROJECTION = "reprojection"  # reprojection error above the threshold
REJECT_NO_CALIBRATION = "no_calibration"  # image before any calibration/extrinsics

REJECT_REASONS = (
    REJECT_NO_MARKER,
    REJECT_DECODE,
    REJECT_PAYLOAD,
    REJECT_GEOMETRY,
    REJECT_SOLVER,
    REJECT_REPROJECTION,
    REJECT_NO_CALIBRATION,
)


@dataclass
class LmIteration:
    """One Levenberg–Marquardt iteration: cost ½‖f‖² of the chosen objective after the
    step, the RMS reprojection error in pixels, the damping λ and the step norm."""

    cost: float
    reproj_rms_px: float
    damping: float
    step_norm: float
    accepted: bool


@dataclass
class MarkerObservation:
    """One decoded QR code in one frame.

    ``corners_px`` are in the *recorded image's* pixels (distortion included), feature
    points in the order TL, TR, BR, BL (+ edge midpoints top, right, bottom, left).
    ``reprojected_px`` is the solved pose's projection of ``points_world_m`` through the
    full camera model, or ``None`` when the frame was not solved.
    """

    marker_id: str
    payload: str
    corners_px: np.ndarray  # (N, 2)
    points_world_m: np.ndarray  # (N, 3)
    reprojected_px: np.ndarray | None = None


@dataclass
class FrameResult:
    """Everything one camera frame produced."""

    index: int
    log_time_ns: int
    cam_name: str
    image_format: str  # "jpeg" | "png" (media of the recorded bytes)
    image_bytes: bytes  # the recorded frame, never re-encoded
    observations: list[MarkerObservation] = field(default_factory=list)
    rejected: str | None = None  # one of REJECT_REASONS, None when solved
    reject_detail: str = ""
    used_marker_id: str | None = None
    T_world_cam: np.ndarray | None = None
    T_world_agv: np.ndarray | None = None
    hpr_rad: np.ndarray | None = None  # heading, pitch, roll of T_world_agv (eq 57)
    reproj_rms_px: float | None = None
    lm_iterations: list[LmIteration] = field(default_factory=list)
    T_world_agv_truth: np.ndarray | None = None
    hpr_truth_rad: np.ndarray | None = None
    position_error_m: float | None = None
    heading_error_deg: float | None = None
    detect_s: float = 0.0
    solve_s: float = 0.0
    total_s: float = 0.0

    @property
    def solved(self) -> bool:
        return self.rejected is None
