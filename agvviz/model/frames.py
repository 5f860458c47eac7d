"""Per-frame results of a replay: what the pipeline saw and decided.

Plain dataclasses shared by :mod:`agvviz.replay.solve` (which produces them),
:mod:`agvviz.viz` (which logs them) and :mod:`agvviz.evaluation` (which scores them).
Frames and units follow :mod:`agvviz.conventions`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, make_dataclass

import numpy as np

from agvviz.model.suspects import Suspect
from agvviz.solvers.joint import MarkerCheck
from agvviz.solvers.types import LmIteration

#: Reasons a frame is rejected. Every rejected frame carries exactly one.
REJECT_NO_MARKER = "no_marker"  # no QR code found in the frame
REJECT_DECODE = "decode_failed"  # code found but its payload could not be decoded
REJECT_PAYLOAD = "payload_invalid"  # payload decoded but refused by the strict parser
REJECT_GEOMETRY = "degenerate_geometry"  # payload points do not define a marker plane
REJECT_SOLVER = "solver_failed"  # the solver returned no pose
REJECT_REPROJECTION = "reprojection"  # reprojection error above the threshold
REJECT_NO_CALIBRATION = "no_calibration"  # image before any calibration
REJECT_NO_EXTRINSIC = "no_extrinsic"  # calibrated, but no camera extrinsic (mount) at the image's time
REJECT_IMAGE = "image_invalid"  # empty, not jpeg/png, or larger than MAX_IMAGE_SIDE_PX
REJECT_CALIBRATION_SIZE = "calibration_size_mismatch"  # image size differs from the calibration's
REJECT_TIME = "time_not_increasing"  # log time not after the previous image of the same camera
REJECT_MAP_MISMATCH = "payload_map_mismatch"  # QR payload disagrees with /markers/map

REJECT_REASONS = (
    REJECT_NO_MARKER,
    REJECT_DECODE,
    REJECT_PAYLOAD,
    REJECT_GEOMETRY,
    REJECT_SOLVER,
    REJECT_REPROJECTION,
    REJECT_NO_CALIBRATION,
    REJECT_NO_EXTRINSIC,
    REJECT_IMAGE,
    REJECT_CALIBRATION_SIZE,
    REJECT_TIME,
    REJECT_MAP_MISMATCH,
)


@dataclass(frozen=True)
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
    #: Frame of ``points_world_m``: "world", or "agv" for a marker mounted on the vehicle
    #: (paper 003), whose points are then in the agv frame.
    points_frame: str = "world"


@dataclass(frozen=True)
class FrameResult:
    """Everything one camera frame produced: the solve stage's immutable output (it is built
    as a :data:`FrameDraft` and frozen once complete, :func:`freeze`)."""

    index: int
    log_time_ns: int
    cam_name: str
    image_format: str  # "jpeg" | "png" (media of the recorded bytes)
    image_bytes: bytes  # the recorded frame, never re-encoded
    observations: tuple[MarkerObservation, ...] = ()
    rejected: str | None = None  # one of REJECT_REASONS, None when solved
    reject_detail: str = ""
    used_marker_id: str | None = None  # the largest usable marker: the single-marker start
    #: Every marker whose corners made the pose (setting ``markers=all``: the joint solve,
    #: :mod:`agvviz.solvers.joint`); just ``used_marker_id`` with ``markers=largest``.
    used_marker_ids: tuple[str, ...] = ()
    #: Markers seen and mapped but left out: their corners failed the χ² test against the others.
    excluded_marker_ids: tuple[str, ...] = ()
    marker_note: str = ""  # the joint solve's finding in plain words (who was left out, why)
    #: The joint solve's test of each marker against the joint pose (χ², own-pose offset), one per
    #: marker given to it; empty without a joint solve. Read by the check stage (issue 25).
    marker_checks: tuple[MarkerCheck, ...] = ()
    T_world_cam: np.ndarray | None = None
    T_world_agv: np.ndarray | None = None
    hpr_rad: np.ndarray | None = None  # heading, pitch, roll of T_world_agv (eq 57)
    reproj_rms_px: float | None = None
    lm_iterations: tuple[LmIteration, ...] = ()
    #: Per LM record, the used code's feature points (N, 2) reprojected at the pose kept after
    #: it, in the recorded image's pixels: how the fit moved. Empty for closed-form solvers.
    lm_iteration_px: tuple[np.ndarray, ...] = ()
    T_world_agv_truth: np.ndarray | None = None
    hpr_truth_rad: np.ndarray | None = None
    position_error_m: float | None = None
    heading_error_deg: float | None = None
    pitch_error_deg: float | None = None  # wrapped estimate − truth, eq 57 angles
    roll_error_deg: float | None = None
    detect_s: float = 0.0
    solve_s: float = 0.0
    total_s: float = 0.0
    # -- uncertainty and ambiguity (agvviz.replay.diagnostics); solved frames only ------------
    n_points: int = 0  # feature points the solver used
    sigma_px: float | None = None  # pixel noise σ behind the covariance and the bound
    #: (6, 6) covariance of T_world_agv, left perturbation in the world frame, δ = (ρ, φ).
    cov_world_agv: np.ndarray | None = None
    position_cov_world_m2: np.ndarray | None = None  # (3, 3) of the AGV origin in the world
    #: The covariance's common-mode factors, signed (6, p) in the same tangent space: "camera" (its
    #: intrinsics, distortion, extrinsic) and "marker:<id>" per used marker (its corners and map entry),
    #: whose errors recur in other frames of the camera; cov_world_agv includes Σ S Sᵀ. None: all of
    #: cov_world_agv is independent between frames (agvviz.solvers.uncertainty.frame_covariance_split).
    cov_common_factors: dict | None = None
    position_sigma_m: float | None = None  # sqrt(trace(position_cov_world_m2))
    #: sqrt(trace) of the Cramér–Rao bound on the AGV position at the true pose (m).
    crlb_position_m: float | None = None
    position_over_crlb: float | None = None  # position_error_m / crlb_position_m
    nees: float | None = None  # normalised estimation error squared vs truth
    nees_dof: int = 0  # its expected value for a consistent estimator (6; 3 for planar)
    uncertainty_note: str = ""  # why no covariance, if none
    ambiguity_ratio: float | None = None  # IPPE rms(other) / rms(best), ≥ 1
    ambiguity_rule: str = ""  # which rule chose the pose (or why there was no choice)
    flipped: bool = False  # chosen pose on the branch the previous solved frame rejected
    T_world_agv_ghost: np.ndarray | None = None  # the rejected candidate pose
    #: The checks against what else the log knows (:mod:`agvviz.replay.checks`), when this solved
    #: frame failed one; ``None`` for a clean or rejected frame, or before the check stage ran.
    suspect: Suspect | None = None

    @property
    def solved(self) -> bool:
        return self.rejected is None


#: The mutable twin of :class:`FrameResult` (same fields), filled step by step while the solve
#: stage works on one frame — and by :class:`agvviz.replay.diagnostics.PoseDiagnostics` — then
#: frozen by :func:`freeze`. Nothing outside the solve stage sees a draft.
FrameDraft = make_dataclass(
    "FrameDraft",
    [
        (f.name, f.type, field(default_factory=list) if f.name in ("observations", "lm_iterations") else f)
        for f in fields(FrameResult)
    ],
    namespace={"solved": property(lambda self: self.rejected is None)},
)


_FIELD_NAMES = tuple(f.name for f in fields(FrameResult))


def freeze(draft) -> FrameResult:
    """The :class:`FrameResult` of a finished draft."""
    values = {name: getattr(draft, name) for name in _FIELD_NAMES}
    values["observations"] = tuple(values["observations"])
    values["lm_iterations"] = tuple(values["lm_iterations"])
    values["lm_iteration_px"] = tuple(values["lm_iteration_px"])
    return FrameResult(**values)
