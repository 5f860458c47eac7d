"""Replay: recording messages → per-frame results (a generator). No I/O of its own.

For every camera frame: decode → undistort (when the camera has distortion) → detect and
decode QR codes → refine corners → parse each payload strictly → solve the pose of the
largest decoded code → T_world_cam → T_world_agv through the extrinsics (paper 000 eqs 31–33)
→ heading/pitch/roll (eq 57) → reprojection check → score against ground truth.
A frame that fails any step is *rejected* with one reason from :mod:`agvviz.results`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import cv2
import numpy as np

from agvviz.conventions import camera_frame
from agvviz.geometry import PinholeCamera, euler, se3
from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners
from agvviz.markers.payload import PayloadError, parse_payload
from agvviz.markers.qr import detect_qr_codes
from agvviz.recording.reader import (
    CalibrationMsg,
    CompressedFrame,
    FrameTransformMsg,
    PoseMsg,
    RecordedMessage,
)
from agvviz.results import (
    REJECT_DECODE,
    REJECT_GEOMETRY,
    REJECT_NO_CALIBRATION,
    REJECT_NO_MARKER,
    REJECT_PAYLOAD,
    REJECT_REPROJECTION,
    REJECT_SOLVER,
    FrameResult,
    MarkerObservation,
)
from agvviz.settings import RunSettings
from agvviz.solvers import SolverOptions, solve

GROUND_TRUTH_TOPIC = "/agv/ground_truth"


@dataclass
class _Camera:
    """What the replay knows about one camera: calibration, extrinsics, undistortion maps."""

    camera: PinholeCamera | None = None
    T_agv_cam: np.ndarray | None = None
    undistort_maps: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class ReplayContext:
    """State gathered from non-image messages while streaming (static and latest values)."""

    cameras: dict[str, _Camera] = field(default_factory=dict)
    truth: list[tuple[int, np.ndarray]] = field(default_factory=list)  # last two (t_ns, T)

    def camera(self, cam_name: str) -> _Camera:
        return self.cameras.setdefault(cam_name, _Camera())


def _polygon_area_px2(corners_px: np.ndarray) -> float:
    x, y = corners_px[:4, 0], corners_px[:4, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _ideal_to_image_px(camera: PinholeCamera, ideal_px: np.ndarray) -> np.ndarray:
    """Pixels of the undistorted (ideal) image → pixels of the recorded (distorted) image."""
    if not camera.has_distortion:
        return ideal_px.copy()
    xy = camera.without_distortion().pixels_to_normalized_distorted(ideal_px)
    return camera.normalized_to_pixels(camera.distort_normalized(xy))


def _truth_at(ctx: ReplayContext, t_ns: int, max_dt_ns: int) -> np.ndarray | None:
    """Ground truth at ``t_ns``: the nearest of the last truths within ``max_dt_ns``."""
    best = None
    for t_truth, T in ctx.truth:
        dt = abs(t_truth - t_ns)
        if dt <= max_dt_ns and (best is None or dt < best[0]):
            best = (dt, T)
    return None if best is None else best[1]


class Replay:
    """Streams :class:`FrameResult` s from recording messages under fixed settings."""

    def __init__(self, settings: RunSettings):
        self.settings = settings
        self.ctx = ReplayContext()
        self._frame_index = 0
        self._solver_options = SolverOptions(
            objective=settings.objective, max_iterations=settings.lm_max_iterations
        )

    # -- message handling ---------------------------------------------------------------
    def feed(self, message: RecordedMessage) -> FrameResult | None:
        """Consume one message; returns a FrameResult for camera frames, else None."""
        value = message.value
        if isinstance(value, CalibrationMsg):
            self._set_calibration(value)
        elif isinstance(value, list) and value and isinstance(value[0], FrameTransformMsg):
            self._set_transforms(value)
        elif isinstance(value, PoseMsg) and message.topic == GROUND_TRUTH_TOPIC:
            self.ctx.truth = (self.ctx.truth + [(message.log_time_ns, value.T)])[-2:]
        elif isinstance(value, CompressedFrame):
            result = self.process_frame(value, message.log_time_ns)
            self._frame_index += 1
            return result
        return None

    def _set_calibration(self, calib: CalibrationMsg) -> None:
        cam = self.ctx.camera(calib.cam_name)
        cam.camera = calib.camera
        cam.undistort_maps = None
        c = calib.camera
        if c.has_distortion:
            cam.undistort_maps = cv2.initUndistortRectifyMap(
                c.K, c.dist, None, c.K, (c.width_px, c.height_px), cv2.CV_32FC2
            )

    def _set_transforms(self, transforms: list[FrameTransformMsg]) -> None:
        for tf in transforms:
            if tf.parent_frame == "agv" and tf.child_frame.startswith("cam_"):
                self.ctx.camera(tf.child_frame[len("cam_") :]).T_agv_cam = tf.T_parent_child

    # -- one frame ------------------------------------------------------------------------
    def process_frame(self, frame: CompressedFrame, log_time_ns: int) -> FrameResult:
        t_start = time.perf_counter()
        result = FrameResult(
            index=self._frame_index,
            log_time_ns=log_time_ns,
            cam_name=frame.cam_name,
            image_format=frame.image_format,
            image_bytes=frame.data,
        )
        truth = _truth_at(self.ctx, log_time_ns, int(self.settings.truth_max_dt_s * 1e9))
        if truth is not None:
            result.T_world_agv_truth = truth
            result.hpr_truth_rad = np.array(
                euler.hpr_from_matrix(truth[:3, :3], self.settings.gimbal_threshold)
            )
        try:
            self._solve_frame(frame, result)
        finally:
            result.total_s = time.perf_counter() - t_start
        return result

    def _reject(self, result: FrameResult, reason: str, detail: str) -> FrameResult:
        result.rejected = reason
        result.reject_detail = detail
        return result

    def _solve_frame(self, frame: CompressedFrame, result: FrameResult) -> FrameResult:
        cam = self.ctx.cameras.get(frame.cam_name)
        if cam is None or cam.camera is None or cam.T_agv_cam is None:
            missing = "calibration" if cam is None or cam.camera is None else "agv→camera extrinsic"
            return self._reject(
                result, REJECT_NO_CALIBRATION,
                f"no {missing} for camera {frame.cam_name!r} ({camera_frame(frame.cam_name)}) "
                "before this frame",
            )
        camera = cam.camera
        t0 = time.perf_counter()
        gray = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            result.detect_s = time.perf_counter() - t0
            return self._reject(result, REJECT_DECODE, f"{frame.image_format} frame does not decode")
        if cam.undistort_maps is not None:
            gray = cv2.remap(gray, *cam.undistort_maps, interpolation=cv2.INTER_LINEAR)
        detections = detect_qr_codes(gray, refine=self.settings.refine)
        result.detect_s = time.perf_counter() - t0

        if not detections:
            return self._reject(result, REJECT_NO_MARKER, "no QR code found")
        candidates = []  # (observation, ideal corners px, marker-frame points, T_world_marker)
        problems = []
        for det in detections:
            if det.text is None:
                problems.append((REJECT_DECODE, "a QR code was found but not decoded"))
                continue
            try:
                payload = parse_payload(det.text)
                T_world_marker, points_marker_m = marker_frame_from_corners(payload.points_world_m)
            except PayloadError as exc:
                problems.append((REJECT_PAYLOAD, f"payload refused: {exc}"))
                continue
            except DegenerateGeometryError as exc:
                problems.append((REJECT_GEOMETRY, f"payload geometry: {exc}"))
                continue
            # Only the 4 vertices are measured in the image; edge midpoints (if the payload
            # carries them) have no independent image measurement here.
            observation = MarkerObservation(
                marker_id=payload.marker_id,
                payload=det.text,
                corners_px=_ideal_to_image_px(camera, det.corners_px),
                points_world_m=payload.points_world_m[:4],
            )
            result.observations.append(observation)
            candidates.append((observation, det.corners_px, points_marker_m[:4], T_world_marker))
        if not candidates:
            reason, detail = problems[0]
            return self._reject(result, reason, "; ".join(d for _, d in problems))

        t1 = time.perf_counter()
        observation, ideal_px, points_marker_m, T_world_marker = max(
            candidates, key=lambda c: _polygon_area_px2(c[1])
        )
        result.used_marker_id = observation.marker_id
        solved = solve(
            self.settings.solver, points_marker_m, ideal_px, camera.K, self._solver_options
        )
        result.lm_iterations = list(solved.iterations)
        result.solve_s = time.perf_counter() - t1
        if not solved.success:
            return self._reject(
                result, REJECT_SOLVER, f"{self.settings.solver} on code {observation.marker_id}: {solved.reason}"
            )
        result.reproj_rms_px = solved.reproj_rms_px
        if solved.reproj_rms_px is None or solved.reproj_rms_px > self.settings.max_reproj_px:
            # The pose is not kept: a rejected frame never shows or scores a pose.
            return self._reject(
                result,
                REJECT_REPROJECTION,
                f"RMS reprojection error {solved.reproj_rms_px:.2f} px > "
                f"max_reproj_px {self.settings.max_reproj_px:g} px (code {observation.marker_id})",
            )
        T_world_cam = T_world_marker @ se3.inverse(solved.T_cam_marker)
        T_world_agv = T_world_cam @ se3.inverse(cam.T_agv_cam)
        result.T_world_cam = T_world_cam
        result.T_world_agv = T_world_agv
        result.hpr_rad = np.array(
            euler.hpr_from_matrix(T_world_agv[:3, :3], self.settings.gimbal_threshold)
        )
        T_cam_world = se3.inverse(T_world_cam)
        for obs in result.observations:
            points_cam = se3.transform_points(T_cam_world, obs.points_world_m)
            if np.all(points_cam[:, 2] > 0):
                obs.reprojected_px = camera.project(points_cam)
        if result.T_world_agv_truth is not None:
            truth = result.T_world_agv_truth
            result.position_error_m = float(np.linalg.norm(T_world_agv[:3, 3] - truth[:3, 3]))
            result.heading_error_deg = float(
                np.degrees(euler.wrap_angle_rad(result.hpr_rad[0] - result.hpr_truth_rad[0]))
            )
        return result


def replay(messages: Iterable[RecordedMessage], settings: RunSettings) -> Iterator[FrameResult]:
    """Per-frame results of replaying ``messages`` (in recording order) under ``settings``."""
    engine = Replay(settings)
    for message in messages:
        result = engine.feed(message)
        if result is not None:
            yield result
