"""The solve stage: recording messages (and their detections) → per-frame results. No I/O of its own.

For every camera frame: decode → undistort (when the camera has distortion) → detect and
decode QR codes → refine corners → parse each payload strictly → solve the pose of the
largest decoded code → with ``markers=all``, one LM over every usable marker's corners started
from it, markers that disagree left out (:mod:`agvviz.solvers.joint`) → T_world_cam →
T_world_agv through the extrinsics (paper 000 eqs 31–33) → heading/pitch/roll (eq 57) → reprojection check → score against ground truth.
A frame that fails any step is *rejected* with one reason from :mod:`agvviz.model.frames` or
:mod:`agvviz.recording.contract` (whose checks ``inspect`` shares): an image time stamp that
does not increase per camera (``time_not_increasing``), an empty, non-jpeg/png or oversized
frame (``image_invalid``), an image whose size is not its calibration's
(``calibration_size_mismatch``), a QR payload that disagrees with the recording's marker map
(``payload_map_mismatch``). Recording-level findings (:class:`TimeChecks`) are left for the
caller's summary (:meth:`Replay.warnings`).

Which detected codes can give a pose (payloads, map, boards) is :mod:`agvviz.replay.candidates`;
this module keeps the per-frame pipeline around it — camera state, the largest code's solve,
the joint solve and the scoring.
Longer than 600 lines because those steps share one frame's draft: split further, each would
pass the draft and the camera state back and forth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Iterable, Mapping

import numpy as np

from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.geometry import PinholeCamera, euler, se3
from agvviz.geometry.plane import quad_area_px2
from agvviz.markers.aruco import ArucoMap, parse_aruco_map
from agvviz.markers.types import ArucoError
from agvviz.markers.charuco import is_chessboard_id
from agvviz.model.frames import (
    REJECT_GEOMETRY,
    REJECT_NO_CALIBRATION,
    REJECT_NO_EXTRINSIC,
    REJECT_REPROJECTION,
    REJECT_SOLVER,
    FrameDraft,
    FrameResult,
    freeze,
)
from agvviz.recording.checks import IMAGE_FORMATS, unmapped_tolerance_m
from agvviz.model.frames import REJECT_TIME
from agvviz.recording.contract import TimeChecks, qr_map_of
from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg
from agvviz.recording.reader import RecordedMessage
from agvviz.model.topics import ROLE_MARKER_MAP, ROLE_TRUTH, camera_of_role
from agvviz.replay.candidates import REASON_RANK, PayloadMemo, aruco_candidates, qr_candidates
from agvviz.replay.detect.stage import DetectParams, FrameJob, SegmentDetector, camera_model
from agvviz.model.detections import FrameDetections
from agvviz.replay.diagnostics import PoseDiagnostics
from agvviz.settings import RunSettings
from agvviz.solvers import SolverOptions, SolveResult, solve
from agvviz.solvers.joint import MarkerView, solve_joint
from agvviz.solvers.planar import PlanarPrior
from agvviz.model.cameras import CameraState
from agvviz.replay.sync import SyncState

@dataclass
class ReplayContext:
    """State gathered from non-image messages while streaming (static and latest values)."""

    #: camera name -> its state; a state is frozen and replaced when it changes (then
    #: ``cameras_version`` counts up), so a copy of the dict is a snapshot
    cameras: dict[str, CameraState] = field(default_factory=dict)
    cameras_version: int = 0
    marker_map: dict | None = None  # the marker map in use (side file or recording)
    aruco_map: ArucoMap | None = None  # from /markers/map when it names an ArUco dictionary
    marker_map_problem: str = ""  # why /markers/map was refused, for the rejection detail
    qr_map: dict[str, np.ndarray] = field(default_factory=dict)  # QR id -> world corners (4, 3)
    unmapped_tolerance_m: float = 0.0  # see agvviz.recording.checks.payload_map_problem

    def cameras_snapshot(self) -> Mapping[str, CameraState]:
        """The cameras as they are now (a read-only copy: later changes do not show in it)."""
        return MappingProxyType(dict(self.cameras))


def _path_px(camera: PinholeCamera, path: list, points_marker_m: np.ndarray) -> tuple[np.ndarray, ...]:
    """The marker points (N, 3) reprojected (image pixels, distortion applied) at each pose
    (4, 4) ``T_cam_marker`` of an LM path; a pose with a point behind the camera gives NaNs."""
    projected = []
    for T_cam_marker in path:
        points_cam = se3.transform_points(T_cam_marker, points_marker_m)
        if (points_cam[:, 2] > 0).all():
            projected.append(camera.project(points_cam))
        else:
            projected.append(np.full((len(points_marker_m), 2), np.nan))
    return tuple(projected)



class Replay:
    """Streams :class:`FrameResult` s from recording messages under fixed settings.

    A run first calls :meth:`prime` with every non-image message of the recording (the sync
    stage, :class:`agvviz.replay.sync.SyncState`: calibrations, transforms, truth, odometry, marker
    map), then :meth:`feed` with the messages in file order; calibration and transforms then
    apply to every frame whatever order the file holds them in, and truth is interpolated at
    each image's stamp. Fed without :meth:`prime`, a frame knows what came before it.
    Messages are dispatched on their role (:mod:`agvviz.model.topics`).
    """

    def __init__(self, settings: RunSettings, body_frame: str = AGV_FRAME, world_frame: str = WORLD_FRAME):
        self.settings = settings
        self.ctx = ReplayContext()
        self.sync = SyncState(
            body_frame=body_frame,
            world_frame=world_frame,
            truth_max_dt_ns=int(settings.truth_max_dt_s * 1e9),
            truth_max_gap_ns=int(settings.truth_max_gap_s * 1e9),
            ignore_truth=settings.truth == "ignore",
        )
        self.primed = False
        #: camera name -> the frame id its images carry, when known before the first image
        self.camera_frames: dict[str, str] = {}
        self.frames_truth_gap = 0  # solved frames not scored: no truth within the gap limits
        self._frame_index = 0
        self._last_frame_time_ns: int | None = None
        self._cams_at_index: set[str] = set()
        self.time_checks = TimeChecks()
        self.truth_seen = False
        self.frames_solved = 0
        self.frames_scored = 0  # solved frames scored against ground truth
        self.markers_left_out: dict[str, int] = {}  # marker id -> frames the joint solve left it out of
        self.frames_markers_disagree = 0  # frames whose markers failed the χ² test as a group
        self.frames_joint_fallback = 0  # frames whose joint pose failed max_reproj_px: the largest code alone
        #: board chessboard name -> (frames its saddles were not used, the first such note)
        self.chessboards_not_used: dict[str, tuple[int, str]] = {}
        self._solver_options = SolverOptions(
            objective=settings.objective, max_iterations=settings.lm_max_iterations
        )
        self._diagnostics = PoseDiagnostics(
            settings.solver, settings.objective, settings.ambiguity, settings.sigma_px_value,
            self._solver_options, settings.systematic_sigmas,
        )
        #: per camera: the detect stage run in process, when :meth:`feed` is not given the
        #: frame's detections (computed ahead by :mod:`agvviz.replay.detect.pool`)
        self._detectors: dict[str, SegmentDetector] = {}
        #: each QR payload's parse and marker frame, once per run (candidates.PayloadMemo)
        self._payloads = PayloadMemo()

    @property
    def detect_params(self) -> DetectParams:
        """The detect stage's parameters: the detection settings and the marker family."""
        aruco = self.ctx.aruco_map
        if aruco is None:
            return DetectParams.of(self.settings, None)
        return DetectParams.of(self.settings, aruco.dictionary, tuple(b.spec for b in aruco.boards))

    def image_frame(self, message: RecordedMessage) -> CompressedFrame:
        """The message's frame under the camera name of its role (the role map names cameras)."""
        value = message.value
        cam_role = camera_of_role(message.role)
        if cam_role is not None and cam_role[0] != value.cam_name:
            value = CompressedFrame(cam_role[0], value.frame_id, value.image_format, value.data,
                                    value.stamp_ns, value.source_encoding)
        return value

    def detect_job(self, message: RecordedMessage) -> FrameJob | None:
        """The detect stage's input for an image message, or None when its camera has no
        calibration at its time (the frame is then rejected without a search). After
        :meth:`prime`, the same for every message whatever was fed before it, which is what
        lets :mod:`agvviz.replay.detect.pool` detect frames ahead of the replay. A camera on
        the vehicle (an extrinsic ``T_body_cam``) of a recording with odometry at the frame's
        stamp also gets both poses, for tracking's floor prediction."""
        frame = self.image_frame(message)
        calibration = self.sync.calibration_at(frame.cam_name, message.time_ns)
        if calibration is None:
            return None
        T_odom_agv = self.sync.odometry_at(message.time_ns)
        T_agv_cam = None
        if T_odom_agv is not None:
            T_agv_cam, _, _ = self.sync.extrinsic(frame.cam_name, frame.frame_id, message.time_ns)
        if T_agv_cam is None:
            T_odom_agv = None
        return FrameJob(frame.cam_name, frame.image_format, frame.data, calibration, T_odom_agv, T_agv_cam)

    # -- message handling ---------------------------------------------------------------
    def set_side_inputs(
        self,
        marker_map: dict | None = None,
        calibrations: dict[str, CalibrationMsg] | None = None,
        extrinsics: dict[str, np.ndarray] | None = None,
    ) -> None:
        """Side files (``--markers``, ``--calibration``, ``--extrinsic``): they override the
        recording's own value for their camera (or the marker map). Call before any message.
        ``extrinsics`` are ``T_body_cam`` per camera."""
        for cam_name, calib in (calibrations or {}).items():
            self.sync.side_calibrations[cam_name] = calib
        for cam_name, T in (extrinsics or {}).items():
            self.sync.side_extrinsics[cam_name] = np.asarray(T, dtype=float)
        if marker_map is not None:
            self.sync.side_marker_map = marker_map
            self._set_marker_map(marker_map)
        self._update_all_cameras(0)

    def prime(self, messages: Iterable[RecordedMessage]) -> None:
        """First pass: every non-image message of the recording into the sync stage."""
        for message in messages:
            if isinstance(message.value, CompressedFrame):
                continue
            self._take_context(message)
        self.primed = True
        self._update_all_cameras(None)

    def _take_context(self, message: RecordedMessage) -> None:
        value = message.value
        kept = self.sync.add(message)
        if message.role == ROLE_TRUTH and kept and not self.sync.ignore_truth:
            self.truth_seen = True
        if message.role == ROLE_MARKER_MAP and isinstance(value, dict) and self.sync.side_marker_map is None:
            self._set_marker_map(value)

    def _set_marker_map(self, value: dict) -> None:
        self.ctx.marker_map = value
        self.ctx.qr_map = qr_map_of(value)
        self.ctx.unmapped_tolerance_m = unmapped_tolerance_m(self.ctx.qr_map) if self.ctx.qr_map else 0.0
        try:
            self.ctx.aruco_map = parse_aruco_map(value)
            self.ctx.marker_map_problem = ""
        except ArucoError as exc:
            self.ctx.aruco_map, self.ctx.marker_map_problem = None, str(exc)

    def feed(self, message: RecordedMessage, detections: FrameDetections | None = None) -> FrameResult | None:
        """Consume one message; returns a FrameResult for camera frames, else None.

        ``detections`` are the frame's detect-stage output when computed elsewhere (a worker
        pool, the detection cache: :mod:`agvviz.replay.detect.pool`); without them the frame is
        detected here, by the same code and with the same segments."""
        value = message.value
        is_image = isinstance(value, CompressedFrame)
        t_ns = message.time_ns
        if is_image and detections is None:
            job = self.detect_job(message)
            if job is not None:
                detector = self._detectors.setdefault(job.cam_name, SegmentDetector(self.detect_params))
                detections = detector.detect(job)
        time_problem = self.time_checks.message(message.topic, t_ns, is_image, is_truth=message.role == ROLE_TRUTH)
        if not is_image:
            if not self.primed:
                self._take_context(message)
                if isinstance(value, CalibrationMsg) or (
                    isinstance(value, list) and value and isinstance(value[0], FrameTransformMsg)
                ):
                    self._update_all_cameras(t_ns)
            return None
        value = self.image_frame(message)
        # Frames of several cameras at one time stamp share one frame index; a second frame
        # of one camera (a repeated time stamp) gets its own.
        if self._last_frame_time_ns is not None and (
            t_ns != self._last_frame_time_ns or value.cam_name in self._cams_at_index
        ):
            self._frame_index += 1
            self._cams_at_index = set()
        self._cams_at_index.add(value.cam_name)
        self._last_frame_time_ns = t_ns
        if time_problem is not None:
            result = FrameDraft(
                index=self._frame_index, log_time_ns=t_ns, cam_name=value.cam_name,
                image_format=value.image_format, image_bytes=value.data,
            )
            return freeze(self._reject(result, REJECT_TIME, time_problem))
        self._update_camera(value.cam_name, value.frame_id, t_ns)
        odometry = self.sync.odometry_at(t_ns)
        if odometry is not None:
            self._diagnostics.odometry = odometry  # T_odom_agv at this frame, for ambiguity=odometry
        result = self.process_frame(value, t_ns, detections)
        for marker_id in result.excluded_marker_ids:
            self.markers_left_out[marker_id] = self.markers_left_out.get(marker_id, 0) + 1
        if result.rejected is None:
            self.frames_solved += 1
            self.frames_scored += result.position_error_m is not None
            if self.truth_seen and result.T_world_agv_truth is None:
                self.frames_truth_gap += 1
        return result

    def warnings(self) -> list[str]:
        """Recording-level problems seen so far, for the run summary: time stamps (shared with
        ``inspect``, :class:`agvviz.recording.contract.TimeChecks`) and ground truth that scored
        no frame."""
        max_dt_ns = int(self.settings.truth_max_dt_s * 1e9)
        lines = self.time_checks.problems(max_dt_ns) + list(self.sync.notes.values())
        left_out = {k: n for k, n in self.markers_left_out.items() if not is_chessboard_id(k)}
        for name, count in sorted((k, n) for k, n in self.markers_left_out.items() if is_chessboard_id(k)):
            lines.append(
                f"{name} (the board's saddle corners) left out of the joint solve by the χ² test on {count} frame(s): "
                "they disagree with the markers — check the board's square_length_m and marker_length_m, and its flatness"
            )
        if left_out:
            worst = sorted(left_out.items(), key=lambda item: (-item[1], item[0]))
            shown = ", ".join(f"{marker_id} ({count} frame{'s' if count > 1 else ''})" for marker_id, count in worst[:5])
            more = f" and {len(worst) - 5} more" if len(worst) > 5 else ""
            lines.append(
                f"markers left out of the joint solve by the χ² test: {shown}{more} — a marker left out "
                "often is likely misplaced in the map or misprinted; `agvviz audit` estimates where it is"
            )
        for name, (count, note) in sorted(self.chessboards_not_used.items()):
            lines.append(f"{name}: saddles not used on {count} frame(s) — first: {note}")
        if self.frames_joint_fallback:
            lines.append(
                f"{self.frames_joint_fallback} frame(s): the markers in view fit no common pose within max_reproj_px, "
                "the largest code alone was used — check the camera calibration and the map"
            )
        if self.frames_markers_disagree:
            lines.append(
                f"{self.frames_markers_disagree} frame(s): the markers in view disagree as a group (most fail the "
                "χ² test together) — check the map's marker size and the camera calibration"
            )
        no_score = self.truth_seen and self.frames_solved > 0 and self.frames_scored == 0
        if no_score and not any("ground truth" in line for line in lines):
            lines.append(
                f"ground truth is recorded but no frame could be scored against it (none within "
                f"truth_max_dt_s = {self.settings.truth_max_dt_s:g} s of a solved frame, nor between "
                f"two truth samples at most truth_max_gap_s = {self.settings.truth_max_gap_s:g} s "
                "apart): the error statistics are empty"
            )
        elif self.frames_truth_gap and self.frames_scored:
            lines.append(
                f"{self.frames_truth_gap} solved frame(s) not scored: no ground truth within "
                f"truth_max_dt_s = {self.settings.truth_max_dt_s:g} s nor between two truth samples "
                f"at most truth_max_gap_s = {self.settings.truth_max_gap_s:g} s apart"
            )
        return lines

    def truth_status(self) -> dict:
        """The run summary's ``truth`` section: whether ground truth was given, how many solved
        frames it scored, and — when it was given but scored none — ``note``, one line naming
        the offset between the truth's and the images' time spans (the usual cause: a truth
        log on another clock or time zone)."""
        status = {"given": self.truth_seen, "frames_solved": self.frames_solved, "frames_scored": self.frames_scored}
        if not (self.truth_seen and self.frames_solved > 0 and self.frames_scored == 0):
            return status
        spans = self.time_checks.truth_vs_images()
        note = "given but no frame scored"
        if spans is not None:
            (t0, t1), (i0, i1) = spans
            offset_s = (t0 - i0) / 1e9
            status["truth_offset_s"] = offset_s
            if t0 > i1:
                where = f"truth stamps start {offset_s:.6g} s after the images"
            elif t1 < i0:
                where = f"truth stamps start {-offset_s:.6g} s before the images (and end before them)"
            else:
                where = (f"truth overlaps the images in time (starting {offset_s:+.6g} s from them) but no "
                         f"sample lies within truth_max_dt_s = {self.settings.truth_max_dt_s:g} s of a solved frame")
            note += f" — {where}; check the time base"
        status["note"] = note
        return status

    def _known_cameras(self) -> set[str]:
        names = set(self.sync.calibrations) | set(self.sync.side_calibrations) | set(self.sync.side_extrinsics)
        names |= set(self.ctx.cameras) | set(self.camera_frames)
        names |= {f[len("cam_"):] for f in self.sync.tf.frames() if f.startswith("cam_")}
        return names

    def _update_all_cameras(self, t_ns: int | None) -> None:
        """Refresh every known camera from the sync stage (at ``t_ns``; ``None``: the first
        calibration and fixed transforms), so consumers of :attr:`ctx` (fusion, correction)
        see calibrations and extrinsics before any image of that camera."""
        for cam_name in sorted(self._known_cameras()):
            frame_id = self.camera_frames.get(cam_name) or camera_frame(cam_name)
            self._update_camera(cam_name, frame_id, t_ns, keep_extrinsic=True)

    def _update_camera(self, cam_name: str, frame_id: str, t_ns: int | None, keep_extrinsic: bool = False) -> None:
        """Calibration and extrinsic of one camera at ``t_ns`` for an image in ``frame_id``
        (its :class:`CameraState` replaced when either changed)."""
        old = self.ctx.cameras.get(cam_name)
        cam = old if old is not None else CameraState()
        calib = self.sync.calibration_at(cam_name, t_ns if t_ns is not None else -(2**62))
        if calib is not cam.calibration:
            if calib is None:
                cam = replace(cam, calibration=None, camera=None)
            else:
                model = camera_model(calib, maps=False)  # shared with the detect stage, which builds the maps
                cam = replace(cam, calibration=calib, camera=model.camera, calibration_problem=model.problem)
        T_body_cam, T_world_cam, why = self.sync.extrinsic(cam_name, frame_id, t_ns)
        if not (T_body_cam is None and T_world_cam is None and keep_extrinsic) and not (
            _same_pose(cam.T_agv_cam, T_body_cam) and _same_pose(cam.T_world_cam, T_world_cam)
            and cam.extrinsic_problem == why
        ):
            cam = replace(cam, T_agv_cam=T_body_cam, T_world_cam=T_world_cam, extrinsic_problem=why)
        if cam is not old:
            self.ctx.cameras[cam_name] = cam
            self.ctx.cameras_version += 1

    # -- one frame ------------------------------------------------------------------------
    def process_frame(
        self, frame: CompressedFrame, log_time_ns: int, detections: FrameDetections | None = None
    ) -> FrameResult:
        t_start = time.perf_counter()
        result = FrameDraft(
            index=self._frame_index,
            log_time_ns=log_time_ns,
            cam_name=frame.cam_name,
            image_format=frame.image_format,
            image_bytes=frame.data,
        )
        truth = self.sync.truth_at(log_time_ns)
        if truth is not None:
            result.T_world_agv_truth = truth
            result.hpr_truth_rad = np.array(
                euler.hpr_from_matrix(truth[:3, :3], self.settings.gimbal_threshold)
            )
        try:
            self._solve_frame(frame, result, detections)
        finally:
            result.total_s = time.perf_counter() - t_start + (detections.detect_s if detections else 0.0)
        return freeze(result)

    def _reject(self, result: FrameDraft, reason: str, detail: str) -> FrameDraft:
        result.rejected = reason
        result.reject_detail = detail
        return result

    def _solve_frame(self, frame: CompressedFrame, result: FrameDraft, detections: FrameDetections | None) -> FrameResult:
        cam = self.ctx.cameras.get(frame.cam_name)
        if (
            cam is None or cam.camera is None or (cam.T_agv_cam is None and cam.T_world_cam is None)
            or detections is None
        ):
            no_calibration = cam is None or cam.camera is None or detections is None
            missing = (
                "calibration" if no_calibration
                else f"extrinsic ({self.sync.body_frame}→camera or {self.sync.world_frame}→camera)"
            )
            detail = (
                f"no {missing} for camera {frame.cam_name!r} ({frame.frame_id or camera_frame(frame.cam_name)}) "
                + ("before this frame" if not self.primed else "at this frame's time" if not no_calibration
                   else "in the recording or side files")
            )
            if cam is not None and cam.calibration_problem:
                detail += f" ({cam.calibration_problem})"
            elif cam is not None and cam.camera is not None and cam.extrinsic_problem:
                detail += f": {cam.extrinsic_problem}"
            elif not no_calibration:
                detail += f" (give --extrinsic {frame.cam_name}=x,y,z,qx,qy,qz,qw)"
            return self._reject(result, REJECT_NO_CALIBRATION if no_calibration else REJECT_NO_EXTRINSIC, detail)
        result.detect_s = detections.detect_s
        if detections.reject is not None:
            if detections.drop_image:
                # Nothing a viewer should try to show (not jpeg/png, empty, or a header claiming
                # a huge image): the bytes are dropped; the detail names the recorded format.
                result.image_bytes = b""
                result.image_format = frame.image_format if frame.image_format in IMAGE_FORMATS else "jpeg"
            return self._reject(result, *detections.reject)
        camera = cam.camera
        if self.ctx.aruco_map is not None:
            candidates, problems = aruco_candidates(
                self.ctx.aruco_map, detections.codes, camera, result, detections.chessboards, self.chessboards_not_used
            )
        else:
            candidates, problems = qr_candidates(
                self.ctx.qr_map, self.ctx.unmapped_tolerance_m, detections.codes, camera, result, self._payloads
            )
        if not candidates:
            # The reason of a code that was read and refused outranks one that was not read.
            reason = min((r for r, _ in problems), key=lambda r: REASON_RANK.get(r, len(REASON_RANK)))
            return self._reject(result, reason, "; ".join(d for _, d in problems))
        return self._solve_candidates(cam, candidates, result)

    def _solve_candidates(self, cam: CameraState, candidates: list, result: FrameDraft) -> FrameResult:
        """Pose of the largest candidate (the run's solver and ambiguity rule); with
        ``markers=all`` and more markers fixed in the same frame, one LM over all their corners
        started from it (:func:`agvviz.solvers.joint.solve_joint`, which leaves out markers that
        disagree); then the AGV through whichever of the camera and the marker is fixed in the
        world and whichever rides on the AGV (:func:`agv_pose_from_marker`)."""
        camera = cam.camera
        t1 = time.perf_counter()
        # A board's saddles join the joint solve; they are never "the largest marker".
        markers = [c for c in candidates if not is_chessboard_id(c[0].marker_id)] or candidates
        observation, ideal_px, points_marker_m, marker_frame, T_frame_marker = max(
            markers, key=lambda c: quad_area_px2(c[1][:4])
        )
        board_note = result.marker_note
        result.used_marker_id = observation.marker_id
        camera_on_agv = marker_frame == WORLD_FRAME and cam.T_agv_cam is not None
        prior = None
        if self.settings.solver == "planar" and camera_on_agv:
            prior = PlanarPrior(cam.T_agv_cam, T_frame_marker, sigma_px=self.settings.sigma_px_value)
        solved = solve(
            self.settings.solver, points_marker_m, ideal_px, camera.K, self._solver_options, prior
        )
        result.solve_s = time.perf_counter() - t1
        if not solved.success:
            result.lm_iterations = list(solved.iterations)
            result.lm_iteration_px = _path_px(camera, solved.path, points_marker_m)
            return self._reject(
                result, REJECT_SOLVER, f"{self.settings.solver} on code {observation.marker_id}: {solved.reason}"
            )
        solved = self._diagnostics.resolve(
            solved, points_marker_m, ideal_px, camera.K,
            lambda T: agv_pose_from_marker(T, marker_frame, T_frame_marker, cam.T_agv_cam, cam.T_world_cam),
            result,
        )
        result.used_marker_ids = (observation.marker_id,)
        used_markers = [(T_frame_marker, points_marker_m)]  # each used marker's pose in its frame and points
        used_ids = [observation.marker_id]
        same_frame = [c for c in candidates if c[3] == marker_frame]
        if self.settings.solver != "planar":
            self._diagnostics.note_single_marker(solved.T_cam_marker, points_marker_m, ideal_px, camera.K)
        if self.settings.markers == "all" and len(same_frame) >= 2 and self.settings.solver != "planar":
            t2 = time.perf_counter()
            joint = solve_joint(
                [MarkerView(c[0].marker_id, c[2], c[4], c[1]) for c in same_frame],
                camera.K,
                solved.T_cam_marker @ se3.inverse(T_frame_marker),
                self._diagnostics.corner_sigma_px(self.settings.corner_bias_px),
                self._solver_options,
                self.settings.marker_outlier_p,
            )
            result.solve_s += time.perf_counter() - t2  # the solve's time includes the joint solve
            self.frames_markers_disagree += joint.disagree_as_group
            if joint.T_cam_F is None:
                result.marker_note = _notes(f"joint solve failed ({joint.reason}): the largest code alone", board_note)
            elif (
                joint.reproj_rms_px > self.settings.max_reproj_px
                and solved.reproj_rms_px is not None and solved.reproj_rms_px <= self.settings.max_reproj_px
            ):
                # The markers do not fit one pose within max_reproj_px (a calibration or map error
                # spread over the image) but the largest one fits on its own: keep paper 000's
                # one-code pose rather than no pose, and say so.
                result.marker_note = _notes(
                    f"{joint.note + '; ' if joint.note else ''}the joint pose's RMS {joint.reproj_rms_px:.2f} px > "
                    f"max_reproj_px {self.settings.max_reproj_px:g} px: the largest code {observation.marker_id} alone",
                    board_note,
                )
                self.frames_joint_fallback += 1
            else:
                # From here on the "marker" is the frame F the markers are fixed in.
                used = [c for c in same_frame if c[0].marker_id in joint.used]
                ideal_px = np.vstack([c[1] for c in used])
                points_marker_m = np.vstack([se3.transform_points(c[4], c[2]) for c in used])
                used_markers = [(c[4], c[2]) for c in used]
                used_ids = [c[0].marker_id for c in used]
                T_frame_marker = np.eye(4)
                solved = SolveResult(joint.T_cam_F, "", joint.iterations, joint.reproj_rms_px, joint.path)
                result.used_marker_ids = joint.used
                result.excluded_marker_ids = joint.excluded
                result.marker_checks = joint.checks
                result.marker_note = _notes(joint.note, board_note)
                if len(joint.used) >= 2:
                    self._diagnostics.joint_resolved(result, len(joint.used))
        result.lm_iterations = list(solved.iterations)
        result.lm_iteration_px = _path_px(camera, solved.path, points_marker_m)
        result.reproj_rms_px = solved.reproj_rms_px
        if solved.reproj_rms_px is None or solved.reproj_rms_px > self.settings.max_reproj_px:
            # The pose is not kept: a rejected frame never shows or scores a pose.
            return self._reject(
                result,
                REJECT_REPROJECTION,
                f"RMS reprojection error {solved.reproj_rms_px:.2f} px > "
                f"max_reproj_px {self.settings.max_reproj_px:g} px (code{'s' if len(result.used_marker_ids) > 1 else ''} "
                f"{', '.join(result.used_marker_ids)})",
            )
        try:
            T_world_cam, T_world_agv = agv_pose_from_marker(
                solved.T_cam_marker, marker_frame, T_frame_marker, cam.T_agv_cam, cam.T_world_cam
            )
        except ValueError as exc:
            return self._reject(result, REJECT_GEOMETRY, f"camera {result.cam_name}: {exc}")
        result.T_world_cam = T_world_cam
        result.T_world_agv = T_world_agv
        result.hpr_rad = np.array(
            euler.hpr_from_matrix(T_world_agv[:3, :3], self.settings.gimbal_threshold)
        )
        T_cam_world = se3.inverse(T_world_cam)
        T_cam_frame = {WORLD_FRAME: T_cam_world, AGV_FRAME: T_cam_world @ T_world_agv}
        observations = []
        for obs in result.observations:
            points_cam = se3.transform_points(T_cam_frame[obs.points_frame], obs.points_world_m)
            if (points_cam[:, 2] > 0).all():
                obs = replace(obs, reprojected_px=camera.project(points_cam))
            observations.append(obs)
        result.observations = observations
        if result.T_world_agv_truth is not None:
            truth = result.T_world_agv_truth
            result.position_error_m = float(np.linalg.norm(T_world_agv[:3, 3] - truth[:3, 3]))
            heading_err, pitch_err, roll_err = np.degrees(
                euler.wrap_angle_rad(result.hpr_rad - result.hpr_truth_rad)
            )
            result.heading_error_deg = float(heading_err)
            result.pitch_error_deg = float(pitch_err)
            result.roll_error_deg = float(roll_err)
        self._diagnostics.finish(
            result, solved.T_cam_marker, points_marker_m, ideal_px, camera.K, cam.T_agv_cam, camera_on_agv,
            used_markers, T_frame_marker, used_ids,
        )
        return result


def _same_pose(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return a is b or (a is not None and b is not None and np.array_equal(a, b))


def _notes(*notes: str) -> str:
    return "; ".join(n for n in notes if n)


def agv_pose_from_marker(
    T_cam_marker: np.ndarray,
    marker_frame: str,
    T_frame_marker: np.ndarray,
    T_agv_cam: np.ndarray | None,
    T_world_cam: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(T_world_cam, T_world_agv)`` from one marker pose seen by one camera.

    One of the two must be fixed in the world and the other ride on the AGV:

    * marker in the world, camera on the AGV (paper 000): ``T_world_cam = T_world_marker ·
      T_cam_marker⁻¹``, ``T_world_agv = T_world_cam · T_agv_cam⁻¹`` (eqs 31–33);
    * marker on the AGV, camera in the world (paper 003): ``T_world_agv = T_world_cam ·
      T_cam_marker · T_agv_marker⁻¹``.

    Raises ``ValueError`` when neither combination is available (both fixed or both moving).
    """
    if marker_frame == WORLD_FRAME and T_agv_cam is not None:
        T_world_cam = T_frame_marker @ se3.inverse(T_cam_marker)
        return T_world_cam, T_world_cam @ se3.inverse(T_agv_cam)
    if marker_frame == AGV_FRAME and T_world_cam is not None:
        return T_world_cam, T_world_cam @ T_cam_marker @ se3.inverse(T_frame_marker)
    raise ValueError(
        f"a marker in frame {marker_frame!r} seen by a camera "
        f"{'on the AGV' if T_agv_cam is not None else 'fixed in the world'} says nothing about the AGV"
    )

