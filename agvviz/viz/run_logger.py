"""Log one replay run into a Rerun recording and save it as one ``.rrd``.

The entity tree is in :mod:`agvviz.viz.paths`; the default layout in
:mod:`agvviz.viz.blueprint`. The logger owns an explicit ``rr.RecordingStream`` (never the
global one) that buffers everything in memory until :meth:`RunLogger.save`, which streams
the buffer plus the default blueprint into a temporary file next to the target and then
renames it into place. Wall-clock ``log_time``/``log_tick`` timelines and the wall-clock
start-time property are disabled and chunks are cut by size only (no wall-clock batcher
tick), so the file depends only on the data: two identical runs compare equal with
``rerun rrd compare --unordered`` (row ids and file bytes still differ).
"""

from __future__ import annotations

from agvviz.errors import RunError

import json
import math
import os
from pathlib import Path

import numpy as np
import rerun as rr

from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.results import FrameResult, LmIteration
from agvviz.viz import paths
from agvviz.viz.blueprint import default_blueprint
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.style import (
    COLOR_CAMERA,
    COLOR_DETECTED,
    COLOR_GHOST,
    COLOR_HEADING,
    COLOR_MARKER,
    COLOR_MARKER_FILL,
    COLOR_PITCH,
    COLOR_REJECTED,
    COLOR_REPROJECTED,
    COLOR_ROLL,
    COLOR_STALE,
    COLOR_TRUTH,
)


#: Media type of each ``FrameResult.image_format``.
MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}

#: The covariance ellipsoid is magnified by this factor (positions are sub-millimetre).
POSITION_COV_SCALE = 100.0
#: Ambiguity ratios above this are plotted at this value (exact fits give inf).
AMBIGUITY_RATIO_CAP = 100.0

#: Nominal AGV body drawn around the body frame (half sizes x, y, z in m; centre on the
#: floor-origin's vertical). A visual marker only: the recording does not carry a body size.
AGV_BODY_HALF_SIZES_M = (0.30, 0.40, 0.10)
AGV_BODY_CENTER_M = (0.0, 0.0, 0.10)
AGV_AXIS_LENGTH_M = 0.5
#: Distance of the image plane drawn in the camera frustum (m).
FRUSTUM_IMAGE_PLANE_M = 0.4
#: Point radii in the image view (UI points, so they keep their size when zooming).
DETECTED_RADIUS = rr.Radius.ui_points(5.0)
REPROJECTED_RADIUS = rr.Radius.ui_points(2.5)
#: A trajectory is redrawn every frame from at most this many of its points (evenly spread,
#: first and newest always kept), so logging cost per frame stays bounded on long runs.
MAX_TRAJECTORY_POINTS = 400


class RunLogError(RunError):
    """Input the run logger cannot log (wrong shape, unknown image format, used after save)."""


class RunLogger:
    """Logs a run (static world, cameras, per-frame results, manifest, summary) to one ``.rrd``.

    Data streams to a temporary ``.rrd`` beside ``out_path`` as it is logged (memory does not
    grow with the run); :meth:`close` adds the default blueprint and renames the file into
    place, :meth:`discard` deletes it. Used as a context manager, an exception discards.

    Parameters
    ----------
    out_path : path
        The ``.rrd`` to write; its folder is created if needed. Replaced only by a complete
        file; a write failure (disk full, read-only) raises ``OutputError`` and leaves no
        temporary file.
    recording_name : str
        Shown in the viewer (scenario + setting).
    recording_id : str
        Rerun recording id; pin it so repeated runs produce comparable files.
    """

    def __init__(
        self,
        out_path: str | os.PathLike,
        *,
        recording_name: str,
        recording_id: str,
        inputs: tuple[str | os.PathLike, ...] = (),
    ):
        # OutputError (from agvviz.errors) when out_path is an input or cannot be written.
        self._file = AtomicRrd(out_path, recording_id=recording_id, recording_name=recording_name, inputs=inputs)
        self._rec = self._file.rec
        self._cam_names: list[str] = []
        self._fixed_cams: set[str] = set()
        #: Layout shipped at :meth:`close`; None: :func:`default_blueprint` of the cameras.
        self.blueprint = None
        self._start_time_sent = False
        self._saved = False
        self._trajectory_truth_m: list[np.ndarray] = []
        self._trajectory_camera_m: list[np.ndarray] = []
        try:
            self._log_static_styles()
        except BaseException:  # no `with` block owns the file yet: discard it here
            self._file.discard()
            raise

    # -- static content --------------------------------------------------------------------
    def _log_static_styles(self) -> None:
        rec = self._rec
        rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        series = (
            (paths.ERROR_POSITION_MM, "position error [mm]", COLOR_CAMERA),
            (paths.ERROR_HEADING_DEG, "heading error [deg]", COLOR_HEADING),
            (paths.ERROR_PITCH_DEG, "pitch error [deg]", COLOR_PITCH),
            (paths.ERROR_ROLL_DEG, "roll error [deg]", COLOR_ROLL),
            (paths.ERROR_REPROJ_RMS_PX, "reprojection RMS [px]", COLOR_REPROJECTED),
            (paths.LM_COST, "LM cost", COLOR_CAMERA),
            (paths.LM_REPROJ_RMS_PX, "LM reprojection RMS [px]", COLOR_REPROJECTED),
            (paths.LM_DAMPING, "LM damping", COLOR_HEADING),
            (paths.LM_STEP_NORM, "LM step norm", COLOR_TRUTH),
        )
        for entity, name, color in series:
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        rec.log(
            paths.ERROR_REJECTED,
            rr.SeriesPoints(
                names="rejected frame",
                colors=COLOR_REJECTED,
                markers=rr.components.MarkerShape.Cross,
                marker_sizes=4.0,
            ),
            static=True,
        )
        for entity in (paths.AGV_TRUTH, paths.AGV_CAMERA):
            rec.log(entity, rr.TransformAxes3D(AGV_AXIS_LENGTH_M), static=True)
        rec.log(paths.AGV_TRUTH_BODY, self._body(COLOR_TRUTH), static=True)
        self._log_uncertainty_styles()

    def log_world_static(self, markers: list[tuple[str, np.ndarray]]) -> None:
        """Log the marker map: outlines with an id label and faint faces (static).

        Parameters
        ----------
        markers : list of (marker_id, corners_world_m)
            ``corners_world_m`` (4, 3) in world metres, order TL, TR, BR, BL.
        """
        self._check_open()
        if not markers:
            return
        ids = [str(marker_id) for marker_id, _ in markers]
        corners = [
            _as_array(c, (4, 3), f"corners_world_m of marker {marker_id!r}") for marker_id, c in markers
        ]
        outlines = [np.vstack([c, c[:1]]) for c in corners]  # closed loop TL→TR→BR→BL→TL
        self._rec.log(
            paths.MARKERS,
            rr.LineStrips3D(outlines, colors=COLOR_MARKER, labels=ids, radii=rr.Radius.ui_points(1.5)),
            static=True,
        )
        vertices = np.concatenate(corners, axis=0)
        quads = np.arange(len(corners))[:, None] * 4
        triangles = np.concatenate([quads + [0, 1, 2], quads + [0, 2, 3]], axis=0)
        self._rec.log(
            paths.MARKERS_FILL,
            rr.Mesh3D(
                vertex_positions=vertices,
                triangle_indices=triangles,
                vertex_colors=np.tile(COLOR_MARKER_FILL, (len(vertices), 1)),
            ),
            static=True,
        )

    def log_camera_static(self, cam_name: str, camera: PinholeCamera, T_agv_cam: np.ndarray) -> None:
        """Log camera ``cam_name``: extrinsic ``T_agv_cam`` and its Pinhole (static).

        The camera hangs under the estimated AGV pose, so its frustum shows where the
        pipeline places the camera. The Pinhole ignores lens distortion (Rerun draws an
        ideal pinhole); the recorded image and corners stay in distorted pixels.

        Parameters
        ----------
        cam_name : str
            Camera name (entity ``cam_<name>``).
        camera : PinholeCamera
            Intrinsics ``K`` and image size; the size must be known (> 0).
        T_agv_cam : (4, 4) array
            Camera pose in the AGV body frame.
        """
        self._check_open()
        if camera.width_px <= 0 or camera.height_px <= 0:
            raise RunLogError(
                f"camera {cam_name!r} has no image size ({camera.width_px}×{camera.height_px} px): "
                "log the camera with the width/height from its calibration"
            )
        T_agv_cam = _as_transform(T_agv_cam, f"T_agv_cam of camera {cam_name!r}")
        entity = paths.camera(cam_name)
        self._rec.log(entity, _transform3d(T_agv_cam), static=True)
        self._rec.log(entity, _pinhole(camera), static=True)
        if cam_name not in self._cam_names:
            self._cam_names.append(cam_name)

    def log_fixed_camera_static(self, cam_name: str, camera: PinholeCamera, T_world_cam: np.ndarray) -> None:
        """Log camera ``cam_name`` fixed in the world (paper 003): ``T_world_cam`` and its
        Pinhole under ``world/cameras`` (static); its images and corners go there too."""
        self._check_open()
        T_world_cam = _as_transform(T_world_cam, f"T_world_cam of camera {cam_name!r}")
        entity = paths.camera(cam_name, fixed=True)
        self._rec.log(entity, _transform3d(T_world_cam), static=True)
        self._rec.log(entity, _pinhole(camera), static=True)
        self._fixed_cams.add(cam_name)
        if cam_name not in self._cam_names:
            self._cam_names.append(cam_name)

    @property
    def stream(self) -> rr.RecordingStream:
        """The recording stream, for loggers of other modalities (UWB, fusion)."""
        return self._rec

    @property
    def cam_names(self) -> list[str]:
        return list(self._cam_names)

    # -- per frame -------------------------------------------------------------------------
    def log_camera_view(self, frame: FrameResult) -> None:
        """Log only the image and corners of ``frame`` — another camera's view of a time
        stamp whose pose and errors :meth:`log_frame` logged from the chosen camera."""
        self._check_open()
        _check_frame(frame)
        self._rec.set_time(paths.TIMELINE_FRAME, sequence=int(frame.index))
        self._rec.set_time(paths.TIMELINE_TIME, timestamp=np.datetime64(int(frame.log_time_ns), "ns"))
        self._log_image(frame)
        self._log_corners(frame)

    def log_frame(self, frame: FrameResult) -> None:
        """Log everything one frame produced at ``time = log_time_ns`` and ``frame = index``.

        The estimated pose is shown for solved frames only; on a rejected frame the estimate
        keeps its last pose and its body turns grey with the reason as label. The frame is
        checked completely before anything is logged, so a bad frame logs nothing.
        """
        self._check_open()
        self._file.check()  # stop at once when the disk is full, not after the whole run
        _check_frame(frame)
        rec = self._rec
        if not self._start_time_sent:
            rec.send_recording_start_time_nanos(int(frame.log_time_ns))
            self._start_time_sent = True
        rec.set_time(paths.TIMELINE_FRAME, sequence=int(frame.index))
        rec.set_time(paths.TIMELINE_TIME, timestamp=np.datetime64(int(frame.log_time_ns), "ns"))
        self._log_image(frame)
        self._log_corners(frame)
        self._log_poses(frame)
        self._log_errors(frame)
        self._log_lm(frame)
        self._log_uncertainty(frame)

    def _log_image(self, frame: FrameResult) -> None:
        if not frame.image_bytes:
            return  # corner-only recordings carry no image
        self._rec.log(
            paths.image(frame.cam_name, frame.cam_name in self._fixed_cams),
            rr.EncodedImage(contents=frame.image_bytes, media_type=MEDIA_TYPES[frame.image_format]),
        )

    def _log_corners(self, frame: FrameResult) -> None:
        detected, detected_ids, reprojected, reprojected_ids = [], [], [], []
        for obs in frame.observations:
            corners = np.asarray(obs.corners_px, dtype=float)
            detected.append(corners)
            detected_ids += [obs.marker_id] * len(corners)
            if obs.reprojected_px is not None:
                reproj = np.asarray(obs.reprojected_px, dtype=float)
                reprojected.append(reproj)
                reprojected_ids += [obs.marker_id] * len(reproj)
        # Empty batches on frames without corners, so the previous frame's points vanish.
        fixed = frame.cam_name in self._fixed_cams
        self._rec.log(
            paths.detected(frame.cam_name, fixed),
            rr.Points2D(
                np.concatenate(detected) if detected else np.zeros((0, 2)),
                labels=detected_ids,
                colors=COLOR_DETECTED,
                radii=DETECTED_RADIUS,
                show_labels=False,
                draw_order=10.0,
            ),
        )
        self._rec.log(
            paths.reprojected(frame.cam_name, fixed),
            rr.Points2D(
                np.concatenate(reprojected) if reprojected else np.zeros((0, 2)),
                labels=reprojected_ids,
                colors=COLOR_REPROJECTED,
                radii=REPROJECTED_RADIUS,
                show_labels=False,
                draw_order=11.0,
            ),
        )

    def _log_poses(self, frame: FrameResult) -> None:
        rec = self._rec
        if frame.T_world_agv_truth is not None:
            T_truth = np.asarray(frame.T_world_agv_truth, dtype=float)
            rec.log(paths.AGV_TRUTH, _transform3d(T_truth))
            self._trajectory_truth_m.append(T_truth[:3, 3])
            rec.log(paths.TRAJECTORY_TRUTH, _trajectory(self._trajectory_truth_m, COLOR_TRUTH))
        if frame.solved:
            T_est = np.asarray(frame.T_world_agv, dtype=float)
            rec.log(paths.AGV_CAMERA, _transform3d(T_est))
            rec.log(paths.AGV_CAMERA_BODY, self._body(COLOR_CAMERA))
            self._trajectory_camera_m.append(T_est[:3, 3])
            rec.log(paths.TRAJECTORY_CAMERA, _trajectory(self._trajectory_camera_m, COLOR_CAMERA))
        else:
            # The estimate entity keeps its last pose; grey it so a stale pose is not mistaken
            # for this frame's answer.
            stale = "no estimate yet" if not self._trajectory_camera_m else "last estimate"
            label = f"rejected: {frame.rejected} ({stale})"
            rec.log(paths.AGV_CAMERA_BODY, self._body(COLOR_STALE, label))

    def _log_errors(self, frame: FrameResult) -> None:
        rec = self._rec
        for entity, value in (
            (paths.ERROR_POSITION_MM, None if frame.position_error_m is None else 1000.0 * frame.position_error_m),
            (paths.ERROR_HEADING_DEG, frame.heading_error_deg),
            (paths.ERROR_PITCH_DEG, frame.pitch_error_deg),
            (paths.ERROR_ROLL_DEG, frame.roll_error_deg),
            (paths.ERROR_REPROJ_RMS_PX, frame.reproj_rms_px),
        ):
            if value is not None:
                rec.log(entity, rr.Scalars(float(value)))
        if not frame.solved:
            rec.log(paths.ERROR_REJECTED, rr.Scalars(0.0))
            detail = f" — {frame.reject_detail}" if frame.reject_detail else ""
            rec.log(
                paths.EVENTS_REJECTIONS,
                rr.TextLog(
                    f"frame {frame.index} ({frame.cam_name}): {frame.rejected}{detail}",
                    level=rr.TextLogLevel.WARN,
                ),
            )

    def _log_uncertainty_styles(self) -> None:
        rec = self._rec
        for entity, name, color in (
            (paths.ERROR_NEES, "NEES (expected: dof)", COLOR_CAMERA),
            (paths.ERROR_POSITION_OVER_CRLB, "position error ÷ CRLB", COLOR_REPROJECTED),
            (paths.ERROR_CRLB_POSITION_M, "CRLB position [m]", COLOR_TRUTH),
            (paths.ERROR_POSITION_SIGMA_M, "covariance position σ [m]", COLOR_CAMERA),
            (paths.SOLVER_AMBIGUITY_RATIO, f"IPPE ambiguity ratio (capped at {AMBIGUITY_RATIO_CAP:g})", COLOR_GHOST),
        ):
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        rec.log(paths.AGV_GHOST, rr.TransformAxes3D(0.5 * AGV_AXIS_LENGTH_M), static=True)

    def _log_uncertainty(self, frame: FrameResult) -> None:
        """NEES, error ÷ CRLB, ambiguity ratio, flips, the covariance ellipsoid and the ghost."""
        rec = self._rec
        for entity, value in (
            (paths.ERROR_NEES, frame.nees),
            (paths.ERROR_POSITION_OVER_CRLB, frame.position_over_crlb),
            (paths.ERROR_CRLB_POSITION_M, frame.crlb_position_m),
            (paths.ERROR_POSITION_SIGMA_M, frame.position_sigma_m),
        ):
            if value is not None and math.isfinite(value):
                rec.log(entity, rr.Scalars(float(value)))
        if frame.ambiguity_ratio is not None:
            rec.log(paths.SOLVER_AMBIGUITY_RATIO, rr.Scalars(min(float(frame.ambiguity_ratio), AMBIGUITY_RATIO_CAP)))
        if frame.flipped and frame.solved:
            rec.log(
                paths.EVENTS_FLIPS,
                rr.TextLog(
                    f"frame {frame.index}: pose flipped to the branch the previous frame rejected "
                    f"(ambiguity ratio {frame.ambiguity_ratio:.2f}, chosen by {frame.ambiguity_rule})",
                    level=rr.TextLogLevel.WARN,
                ),
            )
        if frame.solved and frame.position_cov_world_m2 is not None:
            R_world_agv = np.asarray(frame.T_world_agv, dtype=float)[:3, :3]
            cov_agv = R_world_agv.T @ np.asarray(frame.position_cov_world_m2, dtype=float) @ R_world_agv
            eigenvalues, axes = np.linalg.eigh(0.5 * (cov_agv + cov_agv.T))
            if np.linalg.det(axes) < 0:
                axes[:, 0] = -axes[:, 0]
            sigma_mm = 1000.0 * math.sqrt(max(float(np.sum(eigenvalues)), 0.0))
            rec.log(
                paths.AGV_CAMERA_POSITION_COV,
                rr.Ellipsoids3D(
                    half_sizes=[3.0 * POSITION_COV_SCALE * np.sqrt(np.clip(eigenvalues, 0.0, None))],
                    quaternions=[rr.Quaternion(xyzw=se3.to_quaternion_xyzw(axes))],
                    colors=COLOR_CAMERA,
                    fill_mode=rr.components.FillMode.MajorWireframe,
                    labels=[f"3σ position ×{POSITION_COV_SCALE:g} (σ = {sigma_mm:.2f} mm)"],
                    show_labels=False,
                ),
            )
        else:
            rec.log(paths.AGV_CAMERA_POSITION_COV, rr.Clear(recursive=False))
        if frame.solved and frame.T_world_agv_ghost is not None:
            rec.log(paths.AGV_GHOST, _transform3d(np.asarray(frame.T_world_agv_ghost, dtype=float)))
            rec.log(paths.AGV_GHOST_BODY, self._body(COLOR_GHOST))
        else:
            rec.log(paths.AGV_GHOST_BODY, rr.Clear(recursive=False))

    def _log_lm(self, frame: FrameResult) -> None:
        rec = self._rec
        iterations: list[LmIteration] = frame.lm_iterations
        if not iterations:
            rec.log(paths.LM_COST_PER_ITERATION, rr.Clear(recursive=False))
            return
        costs = np.array([it.cost for it in iterations], dtype=float)
        rec.log(paths.LM_COST_PER_ITERATION, rr.BarChart(costs, color=COLOR_CAMERA))
        n = len(iterations)
        # Columns, not set_time("lm_iter") + log: the iteration timeline must not leak onto
        # later log calls (DESIGN §8).
        indexes = [
            rr.TimeColumn(paths.TIMELINE_LM_ITER, sequence=np.arange(n)),
            rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.full(n, int(frame.index))),
            rr.TimeColumn(
                paths.TIMELINE_TIME,
                timestamp=np.full(n, int(frame.log_time_ns), dtype=np.int64).astype("datetime64[ns]"),
            ),
        ]
        for entity, values in (
            (paths.LM_COST, costs),
            (paths.LM_REPROJ_RMS_PX, [it.reproj_rms_px for it in iterations]),
            (paths.LM_DAMPING, [it.damping for it in iterations]),
            (paths.LM_STEP_NORM, [it.step_norm for it in iterations]),
        ):
            columns = rr.Scalars.columns(scalars=np.asarray(values, dtype=float))
            rec.send_columns(entity, indexes=indexes, columns=columns)

    # -- run documents ---------------------------------------------------------------------
    def log_manifest(self, manifest: dict) -> None:
        """Log the run manifest (settings, recording hash, version) as static markdown."""
        self._check_open()
        text = _markdown_document("Run manifest", manifest)
        self._rec.log(paths.RUN_MANIFEST, _markdown(text), static=True)

    def log_summary(self, summary: dict) -> None:
        """Log the run summary (RMSE, median, p95, frames solved/rejected) as static markdown."""
        self._check_open()
        text = _markdown_document("Run summary", summary)
        self._rec.log(paths.RUN_SUMMARY, _markdown(text), static=True)

    # -- output ----------------------------------------------------------------------------
    def close(self) -> None:
        """Finish the file: ship the default blueprint, write the footer, move it into place."""
        self._check_open()
        self._saved = True
        self._file.commit(self.blueprint if self.blueprint is not None else default_blueprint(self._cam_names))

    def discard(self) -> None:
        """Stop logging and delete the unfinished file; ``out_path`` is left untouched."""
        self._saved = True
        self._file.discard()

    def __enter__(self) -> "RunLogger":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()
        elif not self._saved:
            self.close()

    # -- helpers ---------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._saved:
            raise RunLogError("this RunLogger was already closed; create a new one for another run")

    @staticmethod
    def _body(color: tuple[int, int, int], label: str = "") -> rr.Boxes3D:
        """The nominal AGV body box; labelled only when it needs explaining (stale pose)."""
        return rr.Boxes3D(
            half_sizes=[AGV_BODY_HALF_SIZES_M],
            centers=[AGV_BODY_CENTER_M],
            colors=color,
            labels=[label] if label else [],  # empty clears a previous stale label
            radii=rr.Radius.ui_points(1.5),
        )


def _pinhole(camera: PinholeCamera) -> rr.Pinhole:
    """The frustum of ``camera`` (an ideal pinhole: Rerun does not draw lens distortion)."""
    return rr.Pinhole(
        image_from_camera=camera.K,
        resolution=[camera.width_px, camera.height_px],
        camera_xyz=rr.ViewCoordinates.RDF,
        image_plane_distance=FRUSTUM_IMAGE_PLANE_M,
        color=COLOR_CAMERA,
    )


def _check_frame(frame: FrameResult) -> None:
    """Raise RunLogError if ``frame`` cannot be logged as it is."""
    where = f"frame {frame.index}"
    if frame.image_format not in MEDIA_TYPES:
        raise RunLogError(
            f"{where}: image_format {frame.image_format!r} is not one of {sorted(MEDIA_TYPES)}"
        )
    for obs in frame.observations:
        _as_array(obs.corners_px, (-1, 2), f"{where}: corners_px of marker {obs.marker_id!r}")
        if obs.reprojected_px is not None:
            _as_array(obs.reprojected_px, (-1, 2), f"{where}: reprojected_px of marker {obs.marker_id!r}")
    if frame.T_world_agv_truth is not None:
        _as_transform(frame.T_world_agv_truth, f"{where}: T_world_agv_truth")
    if frame.T_world_agv_ghost is not None:
        _as_transform(frame.T_world_agv_ghost, f"{where}: T_world_agv_ghost")
    if frame.position_cov_world_m2 is not None:
        _as_array(frame.position_cov_world_m2, (3, 3), f"{where}: position_cov_world_m2")
    if frame.solved:
        if frame.T_world_agv is None:
            raise RunLogError(f"{where} is solved (rejected is None) but has no T_world_agv")
        _as_transform(frame.T_world_agv, f"{where}: T_world_agv")


def _as_array(value, shape: tuple[int, int], what: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (-1 = any length), else RunLogError."""
    a = np.asarray(value, dtype=float)
    if a.ndim != 2 or any(want not in (-1, got) for want, got in zip(shape, a.shape)):
        raise RunLogError(f"{what} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise RunLogError(f"{what} contains NaN or inf")
    return a


def _as_transform(T, what: str) -> np.ndarray:
    T = _as_array(T, (4, 4), what)
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise RunLogError(f"{what} is not a homogeneous transform (last row {T[3].tolist()})")
    return T


def _transform3d(T_parent_child: np.ndarray) -> rr.Transform3D:
    """Transform3D placing the child entity at ``T_parent_child`` in its parent."""
    return rr.Transform3D(translation=T_parent_child[:3, 3], mat3x3=T_parent_child[:3, :3])


def _trajectory(positions_m: list[np.ndarray], color: tuple[int, int, int]) -> rr.LineStrips3D:
    """The trajectory so far, thinned to at most MAX_TRAJECTORY_POINTS (first and last kept)."""
    n = len(positions_m)
    keep = np.unique(np.linspace(0, n - 1, min(n, MAX_TRAJECTORY_POINTS)).round().astype(int))
    strip = np.array([positions_m[i] for i in keep])
    return rr.LineStrips3D([strip], colors=color, radii=rr.Radius.ui_points(2.0))


def _markdown(text: str) -> rr.TextDocument:
    return rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN)


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _markdown_document(title: str, content: dict) -> str:
    """Markdown: a key/value table (nested dicts flattened with dots) and a JSON block."""
    try:
        block = json.dumps(content, indent=2, sort_keys=True, default=_json_default, allow_nan=True)
    except TypeError as exc:
        raise RunLogError(f"{title.lower()} is not JSON serialisable: {exc}") from exc
    rows = []
    for key, value in _flatten(json.loads(block)):
        if isinstance(value, float):
            text = f"{value:.6g}" if math.isfinite(value) else str(value)
        else:
            text = json.dumps(value) if isinstance(value, list) else str(value)
        escaped = text.replace("|", "\\|")
        rows.append(f"| {key} | {escaped} |")
    table = "\n".join(["| key | value |", "| --- | --- |", *rows])
    return f"# {title}\n\n{table}\n\n```json\n{block}\n```\n"


def _flatten(content: dict, prefix: str = ""):
    for key, value in content.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value
