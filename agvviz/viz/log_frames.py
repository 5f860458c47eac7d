"""The frames of a run in its ``.rrd``: the marker map and cameras (static), each frame's image,
detected and reprojected corners, code ids, the zoom on a small code, the codes seen in 3D, the
truth and estimated poses and trajectories, and the error series with the rejections.

:class:`FrameLogger` is one of the modality loggers a :class:`agvviz.viz.run_logger.RunLogger`
holds (beside :mod:`agvviz.viz.log_lm` and :mod:`agvviz.viz.log_uncertainty`); per-frame values go
through the run's :class:`agvviz.viz.columns.Columns`. The image is logged per frame (it is large)
from its bytes without an archetype.
"""

from __future__ import annotations

import cv2
import numpy as np
import rerun as rr

from agvviz.errors import RunError
from agvviz.geometry.camera import PinholeCamera
from agvviz.markers.charuco import is_chessboard_id
from agvviz.evaluation.suspect_report import cause_words
from agvviz.model.frames import FrameResult
from agvviz.viz import log_rejections, paths
from agvviz.viz.columns import Columns, Stamp
from agvviz.viz.encoded_image import MEDIA_TYPES, log_encoded_image
from agvviz.viz.log_findings import error_values, rejection_row, suspect_row
from agvviz.viz.zoom_placeholder import ZOOM_SIDE_PX, crop_around, longest_edge_px, zoom_unseen_png
from agvviz.viz.style import (
    COLOR_CAMERA,
    COLOR_DETECTED,
    COLOR_HEADING,
    COLOR_MARKER,
    COLOR_MARKER_FILL,
    COLOR_OBSERVED,
    COLOR_PITCH,
    COLOR_REPROJECTED,
    COLOR_ROLL,
    COLOR_STALE,
    COLOR_SUSPECT,
    COLOR_THRESHOLD,
    COLOR_TRUTH,
)

#: Media type of each ``FrameResult.image_format``.
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
LM_ITERATION_RADIUS = rr.Radius.ui_points(2.0)
#: A trajectory is redrawn every frame from at most this many of its points (evenly spread,
#: first and newest always kept), so logging cost per frame stays bounded on long runs.
MAX_TRAJECTORY_POINTS = 400
#: A code whose longest detected edge is shorter than this fraction of the image width (a code a
#: few UI points wide in an image panel) also gets a zoomed view: a crop of the recorded image
#: around it, ZOOM_CROP_CODE_SIDES code sides wide (:func:`~agvviz.viz.zoom_placeholder.crop_around`), so a ≈15 px
#: code fills its own panel.
ZOOM_CODE_BELOW_FRACTION = 0.05

#: Per-frame error series: (entity, legend name, colour).
FRAME_SERIES = (
    (paths.ERROR_POSITION_MM, "position error [mm] (camera estimate)", COLOR_CAMERA),
    (paths.ERROR_HEADING_DEG, "heading error [deg]", COLOR_HEADING),
    (paths.ERROR_PITCH_DEG, "pitch error [deg]", COLOR_PITCH),
    (paths.ERROR_ROLL_DEG, "roll error [deg]", COLOR_ROLL),
    (paths.ERROR_REPROJ_RMS_PX, "reprojection RMS [px]", COLOR_REPROJECTED),
)


#: Legend name of the suspect-frame markers on every error plot (issue 25).
SUSPECT_LEGEND = "suspect frame (why: suspects log)"


class RunLogError(RunError):
    """Input the run logger cannot log (wrong shape, unknown image format, used after save)."""


class Track:
    """Positions (m) appended one per frame into a growing array (no list → array per frame)."""

    def __init__(self):
        self._xyz = np.zeros((256, 3))
        self._n = 0

    def append(self, position_m: np.ndarray) -> None:
        if self._n == len(self._xyz):
            self._xyz = np.concatenate([self._xyz, np.zeros_like(self._xyz)])
        self._xyz[self._n] = position_m
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def array(self) -> np.ndarray:
        return self._xyz[: self._n]


class FrameLogger:
    """Logs the static world and cameras and, per frame, images, corners, poses, trajectories and
    errors into ``rec``; per-frame values into ``columns``. ``max_reproj_px``: the run's setting,
    drawn as a threshold line on the reprojection plot (None: no line)."""

    def __init__(self, rec: rr.RecordingStream, columns: Columns, max_reproj_px: float | None = None):
        self._rec = rec
        self._columns = columns
        self.max_reproj_px = max_reproj_px
        #: False: the camera images are not logged (``run --images none``, a sweep's layers);
        #: everything drawn over them still is.
        self.images = True
        self._cam_names: list[str] = []
        self._image_width_px: dict[str, int] = {}
        #: Cameras fixed in the world (paper 003's wall cameras).
        self.fixed_cams: set[str] = set()
        self._trajectory_truth_m = Track()
        self._trajectory_camera_m = Track()
        # What the previous frame left drawn, so a state is logged only when it changes.
        self._camera_body_label: str | None = None  # None: not drawn yet; "": solved; else its label
        self._zoomed: set[str] = set()  # cameras whose zoom shows a crop now
        self._zoom_last_seen: dict[str, int] = {}  # camera -> last frame its zoom showed a crop
        self._zoom_gray: dict[str, bool] = {}  # camera -> its crops are one-channel (the placeholder too)
        self._zoom_dropped: set[str] = set()  # cameras whose zoom says "no image at this frame" now
        # What the run held, for the layout.
        self._zoom_cams: set[str] = set()
        #: Frames rejected so far.
        self.rejected_frames = 0
        #: (stamp, reason) of every rejected frame: their markers are logged at the end
        #: (:meth:`log_rejection_markers`), where the plots' axes are known.
        self.rejections: list[tuple[Stamp, str]] = []
        #: Suspect frames so far (solved, but failed a check against what else the log knows).
        self.suspect_frames = 0
        #: Frames that carried ground truth (0: a run without truth, e.g. ``truth=ignore``).
        self.truth_frames = 0
        #: Points the vehicle draws, in its body frame: the body's corners, each camera on it,
        #: the axes and the 3σ ellipsoid above the body (:meth:`scene_extent_m`).
        self._vehicle_points_agv_m = [np.array(AGV_BODY_CENTER_M) + np.array(AGV_BODY_HALF_SIZES_M) * np.array(c)
                                      for c in ((-1, -1, -1), (1, 1, 1))]
        self._vehicle_points_agv_m.append(np.array([0.0, 0.0, AGV_AXIS_LENGTH_M]))
        self._seen_low_m: np.ndarray | None = None  # corners of the codes seen in 3D, lowest / highest
        self._seen_high_m: np.ndarray | None = None

    @property
    def cam_names(self) -> list[str]:
        return list(self._cam_names)

    @property
    def zoom_cams(self) -> list[str]:
        """Cameras that had a small code at least once (they have a zoomed view)."""
        return sorted(self._zoom_cams)

    def scene_extent_m(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(low, high) world corners (m) of what the run drew around the vehicle: both vehicles
        (truth and estimate) at every pose, each with its body, cameras, axes and ellipsoid (as
        a box of their reach, whatever the heading), and every code seen. None: no pose."""
        positions = [t.array() for t in (self._trajectory_truth_m, self._trajectory_camera_m) if len(t)]
        if not positions:
            return None
        positions = np.concatenate(positions)
        positions = positions[np.all(np.isfinite(positions), axis=1)]
        if not len(positions):
            return None
        vehicle = np.array(self._vehicle_points_agv_m, dtype=float)
        reach_xy_m = float(np.max(np.linalg.norm(vehicle[:, :2], axis=1)))
        low = positions.min(axis=0) + np.array([-reach_xy_m, -reach_xy_m, min(0.0, vehicle[:, 2].min())])
        high = positions.max(axis=0) + np.array([reach_xy_m, reach_xy_m, max(0.0, vehicle[:, 2].max())])
        if self._seen_low_m is not None:
            low, high = np.minimum(low, self._seen_low_m), np.maximum(high, self._seen_high_m)
        return low, high

    # -- static content --------------------------------------------------------------------
    def log_styles(self) -> None:
        """The world's axes and the static styles of the frame entities."""
        rec = self._rec
        rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for entity, name, color in FRAME_SERIES:
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        if self.max_reproj_px is not None:
            rec.log(
                paths.ERROR_REPROJ_THRESHOLD_PX,
                rr.SeriesLines(
                    names=f"max_reproj_px = {self.max_reproj_px:g} px (above: frame rejected)",
                    colors=COLOR_THRESHOLD,
                    widths=1.0,
                ),
                static=True,
            )
        for entity in paths.SUSPECT_MARKED:
            rec.log(
                paths.error_suspect(entity),
                rr.SeriesPoints(
                    names=SUSPECT_LEGEND,
                    colors=COLOR_SUSPECT,
                    markers=rr.components.MarkerShape.Diamond,
                    marker_sizes=5.0,
                ),
                static=True,
            )
        for entity in (paths.AGV_TRUTH, paths.AGV_CAMERA):
            rec.log(entity, rr.TransformAxes3D(AGV_AXIS_LENGTH_M), static=True)
        rec.log(paths.TRAJECTORY_TRUTH, rr.LineStrips3D.from_fields(colors=COLOR_TRUTH, radii=rr.Radius.ui_points(2.0)), static=True)
        rec.log(paths.TRAJECTORY_CAMERA, rr.LineStrips3D.from_fields(colors=COLOR_CAMERA, radii=rr.Radius.ui_points(2.0)), static=True)
        rec.log(
            paths.MARKERS_SEEN,
            rr.LineStrips3D.from_fields(colors=COLOR_DETECTED, radii=rr.Radius.ui_points(3.0), show_labels=True),
            static=True,
        )

    def _log_camera_styles(self, cam_name: str, fixed: bool) -> None:
        """Static colours, sizes and draw order of the per-frame 2D entities of ``cam_name``."""
        rec = self._rec
        for entity, color, radius, order, labels in (
            (paths.detected(cam_name, fixed), COLOR_DETECTED, DETECTED_RADIUS, 10.0, False),
            (paths.reprojected(cam_name, fixed), COLOR_REPROJECTED, REPROJECTED_RADIUS, 11.0, False),
            (paths.lm_iteration(cam_name, fixed), COLOR_OBSERVED, LM_ITERATION_RADIUS, 12.0, False),
            (paths.marker_ids(cam_name, fixed), COLOR_DETECTED, rr.Radius.ui_points(1.0), 13.0, True),
            (paths.zoom_detected(cam_name), COLOR_DETECTED, DETECTED_RADIUS, 10.0, False),
            (paths.zoom_reprojected(cam_name), COLOR_REPROJECTED, REPROJECTED_RADIUS, 11.0, False),
        ):
            rec.log(
                entity,
                rr.Points2D.from_fields(colors=color, radii=radius, draw_order=order, show_labels=labels),
                static=True,
            )
        rec.log(
            paths.lm_path(cam_name, fixed),
            rr.LineStrips2D.from_fields(colors=COLOR_OBSERVED, radii=rr.Radius.ui_points(1.0), draw_order=9.0),
            static=True,
        )

    def log_world_static(self, markers: list[tuple[str, np.ndarray]]) -> None:
        """Log the marker map: outlines with an id label and faint faces (static).

        Parameters
        ----------
        markers : list of (marker_id, corners_world_m)
            ``corners_world_m`` (4, 3) in world metres, order TL, TR, BR, BL.
        """
        if not markers:
            return
        ids = [str(marker_id) for marker_id, _ in markers]
        corners = [
            as_array(c, (4, 3), f"corners_world_m of marker {marker_id!r}") for marker_id, c in markers
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
        if camera.width_px <= 0 or camera.height_px <= 0:
            raise RunLogError(
                f"camera {cam_name!r} has no image size ({camera.width_px}×{camera.height_px} px): "
                "log the camera with the width/height from its calibration"
            )
        T_agv_cam = as_transform(T_agv_cam, f"T_agv_cam of camera {cam_name!r}")
        entity = paths.camera(cam_name)
        self._rec.log(entity, transform3d(T_agv_cam), static=True)
        self._rec.log(entity, _pinhole(camera), static=True)
        self._vehicle_points_agv_m.append(T_agv_cam[:3, 3])
        self._log_camera_styles(cam_name, fixed=False)
        self._image_width_px[cam_name] = int(camera.width_px)
        if cam_name not in self._cam_names:
            self._cam_names.append(cam_name)

    def log_fixed_camera_static(self, cam_name: str, camera: PinholeCamera, T_world_cam: np.ndarray) -> None:
        """Log camera ``cam_name`` fixed in the world (paper 003): ``T_world_cam`` and its
        Pinhole under ``world/cameras`` (static); its images and corners go there too."""
        T_world_cam = as_transform(T_world_cam, f"T_world_cam of camera {cam_name!r}")
        entity = paths.camera(cam_name, fixed=True)
        self._rec.log(entity, transform3d(T_world_cam), static=True)
        self._rec.log(entity, _pinhole(camera), static=True)
        self._log_camera_styles(cam_name, fixed=True)
        self._image_width_px[cam_name] = int(camera.width_px)
        self.fixed_cams.add(cam_name)
        if cam_name not in self._cam_names:
            self._cam_names.append(cam_name)

    # -- per frame -------------------------------------------------------------------------
    def log_image(self, frame: FrameResult) -> None:
        if not frame.image_bytes or not self.images:
            return  # corner-only recordings carry no image; a layers-only run logs none
        log_encoded_image(
            self._rec, paths.image(frame.cam_name, frame.cam_name in self.fixed_cams), frame.image_format,
            frame.image_bytes,
        )

    def log_corners(self, frame: FrameResult, stamp: Stamp) -> None:
        """Detected and reprojected corners, each code's id at its centre, and the zoomed view
        of a small code. Empty batches on frames without corners, so the previous frame's
        points vanish."""
        detected, detected_ids, reprojected, reprojected_ids, centres = [], [], [], [], []
        for obs in frame.observations:
            corners = np.asarray(obs.corners_px, dtype=float)
            detected.append(corners)
            # A ChArUco board's saddles carry their own label (board<k>:chessboard).
            detected_ids += [obs.marker_id] * len(corners)
            centres.append((corners if is_chessboard_id(obs.marker_id) else corners[:4]).mean(axis=0))
            if obs.reprojected_px is not None:
                reproj = np.asarray(obs.reprojected_px, dtype=float)
                reprojected.append(reproj)
                reprojected_ids += [obs.marker_id] * len(reproj)
        fixed = frame.cam_name in self.fixed_cams
        row = self._columns.row
        row(
            paths.detected(frame.cam_name, fixed), "points2d", stamp,
            np.concatenate(detected) if detected else np.zeros((0, 2)), detected_ids,
        )
        row(
            paths.reprojected(frame.cam_name, fixed), "points2d", stamp,
            np.concatenate(reprojected) if reprojected else np.zeros((0, 2)), reprojected_ids,
        )
        row(
            paths.marker_ids(frame.cam_name, fixed), "points2d", stamp,
            np.array(centres) if centres else np.zeros((0, 2)),
            [f"id {obs.marker_id}" for obs in frame.observations],
        )
        self.log_zoom(frame)

    def log_zoom(self, frame: FrameResult) -> None:
        """A crop of the image around the smallest code when it is under ZOOM_CODE_BELOW_FRACTION
        of the image width (a camera logged without its size is never zoomed)."""
        cam = frame.cam_name
        below_px = ZOOM_CODE_BELOW_FRACTION * self._image_width_px.get(cam, 0)
        small = []  # (longest edge, observation) of the codes under the threshold
        if below_px > 0 and frame.image_bytes:
            for obs in frame.observations:
                if is_chessboard_id(obs.marker_id):
                    continue  # saddles, not a code's outline
                edge_px = longest_edge_px(np.asarray(obs.corners_px, float)[:4])
                if edge_px < below_px:
                    small.append((edge_px, obs))
        crop = None
        if small:
            _, obs = min(small, key=lambda edge_obs: edge_obs[0])
            crop = crop_around(frame.image_bytes, np.asarray(obs.corners_px, float)[:4])
        if crop is None:
            if cam in self._zoomed or cam in self._zoom_dropped:
                self._log_zoom_unseen(cam, bool(frame.observations))
            return
        png, origin_px, px_per_image_px, gray = crop
        obs_points = [(np.asarray(o.corners_px, float), o.reprojected_px) for o in frame.observations]
        detected = (np.concatenate([c for c, _ in obs_points]) - origin_px) * px_per_image_px
        reprojected = [np.asarray(r, float) for _, r in obs_points if r is not None]
        rec = self._rec
        rec.log(paths.zoom_image(cam), rr.EncodedImage(contents=png, media_type="image/png"))
        rec.log(paths.zoom_detected(cam), rr.Points2D(detected))
        rec.log(
            paths.zoom_reprojected(cam),
            rr.Points2D(
                (np.concatenate(reprojected) - origin_px) * px_per_image_px if reprojected else np.zeros((0, 2))
            ),
        )
        self._zoomed.add(cam)
        self._zoom_dropped.discard(cam)
        self._zoom_cams.add(cam)
        self._zoom_last_seen[cam] = int(frame.index)
        self._zoom_gray[cam] = gray

    def log_zoom_dropped(self, cams: set[str]) -> None:
        """At a time stamp where cameras ``cams`` have no frame at all (a dropped image), the
        zoom of each that shows a crop says so instead (at the stamp the time stamp's frames were
        logged at): the crop left on screen would read as current. A zoom that says "not seen
        since frame N" already stays as it is."""
        for cam in sorted(cams & self._zoomed):
            self._log_zoom_unseen(cam, False, dropped=True)
            self._zoom_dropped.add(cam)

    def _log_zoom_unseen(self, cam: str, codes_in_view: bool, dropped: bool = False) -> None:
        """The camera's small code is gone (``dropped``: its whole image is): the zoom shows a
        placeholder saying since when (not the last crop, which would read as current), and its
        corners go."""
        rec = self._rec
        last = self._zoom_last_seen[cam]
        png = zoom_unseen_png(last, codes_in_view, self._zoom_gray[cam], ZOOM_SIDE_PX, dropped=dropped)
        rec.log(paths.zoom_image(cam), rr.EncodedImage(contents=png, media_type="image/png"))
        rec.log(paths.zoom_detected(cam), rr.Points2D(np.zeros((0, 2))))
        rec.log(paths.zoom_reprojected(cam), rr.Points2D(np.zeros((0, 2))))
        self._zoomed.discard(cam)
        self._zoom_dropped.discard(cam)

    def log_markers_seen(self, frame: FrameResult, stamp: Stamp) -> None:
        """The outline and id of every code of this frame in 3D (world-fixed codes only)."""
        outlines, labels = [], []
        for obs in frame.observations:
            if obs.points_frame != "world":
                continue
            corners = np.asarray(obs.points_world_m, dtype=float)
            corners = _outline_of_points(corners) if is_chessboard_id(obs.marker_id) else corners[:4]
            outlines.append(np.vstack([corners, corners[:1]]))
            finite = corners[np.all(np.isfinite(corners), axis=1)]
            if len(finite):
                low, high = finite.min(axis=0), finite.max(axis=0)
                self._seen_low_m = low if self._seen_low_m is None else np.minimum(self._seen_low_m, low)
                self._seen_high_m = high if self._seen_high_m is None else np.maximum(self._seen_high_m, high)
            used = (
                " (used)" if obs.marker_id in (frame.used_marker_ids or (frame.used_marker_id,))
                else " (left out)" if obs.marker_id in frame.excluded_marker_ids else ""
            )
            labels.append(f"id {obs.marker_id}{used}")
        self._columns.row(paths.MARKERS_SEEN, "strips3d", stamp, outlines, labels)

    def log_poses(self, frame: FrameResult, stamp: Stamp) -> None:
        rec = self._rec
        if frame.T_world_agv_truth is not None:
            T_truth = np.asarray(frame.T_world_agv_truth, dtype=float)
            if self.truth_frames == 0:  # the truth body only in a run with truth (not at the origin)
                # Unlabelled: the 3D view's title says "truth (green)"; a "truth" label covered the
                # ids of the codes beside the body in the whole-run framing.
                rec.log(paths.AGV_TRUTH_BODY, agv_body(COLOR_TRUTH), static=True)
            self.truth_frames += 1
            self._columns.transform(paths.AGV_TRUTH, stamp, T_truth)
            self._trajectory_truth_m.append(T_truth[:3, 3])
            self._columns.row(paths.TRAJECTORY_TRUTH, "strip3d", stamp, _thinned(self._trajectory_truth_m.array()))
        if frame.solved:
            T_est = np.asarray(frame.T_world_agv, dtype=float)
            self._columns.transform(paths.AGV_CAMERA, stamp, T_est)
            # A suspect pose is labelled with its likely cause (the suspects log says more).
            label = "" if frame.suspect is None else f"suspect: {cause_words(frame.suspect.cause)}"
            if self._camera_body_label != label:
                rec.log(paths.AGV_CAMERA_BODY, agv_body(COLOR_CAMERA, label))
                self._camera_body_label = label
            self._trajectory_camera_m.append(T_est[:3, 3])
            self._columns.row(paths.TRAJECTORY_CAMERA, "strip3d", stamp, _thinned(self._trajectory_camera_m.array()))
        else:
            # The estimate entity keeps its last pose; grey it so a stale pose is not mistaken
            # for this frame's answer.
            stale = "no estimate yet" if not self._trajectory_camera_m else "last estimate"
            label = f"rejected: {frame.rejected} ({stale})"
            if label != self._camera_body_label:
                rec.log(paths.AGV_CAMERA_BODY, agv_body(COLOR_STALE, label))
                self._camera_body_label = label

    def log_errors(self, frame: FrameResult, stamp: Stamp) -> None:
        columns = self._columns
        suspect = frame.suspect if frame.solved else None
        for entity, value in error_values(frame):
            if not frame.solved:
                # A rejected frame has no value (not even a reprojection RMS it was rejected
                # for): the line breaks and a marker stands in (log_rejection_markers).
                columns.gap(entity, stamp)
            elif value is not None:
                columns.scalar(entity, stamp, value)
                if suspect is not None:  # a marker on the line, at this frame's value
                    columns.scalar(paths.error_suspect(entity), stamp, value)
        if suspect is not None:
            self.suspect_frames += 1
            self._rec.log(paths.EVENTS_SUSPECTS, rr.TextLog(suspect_row(suspect), level=rr.TextLogLevel.WARN))
        if self.max_reproj_px is not None:
            columns.scalar(paths.ERROR_REPROJ_THRESHOLD_PX, stamp, self.max_reproj_px)
        if not frame.solved:
            self.rejected_frames += 1
            self.rejections.append((stamp, frame.rejected))
            self._rec.log(paths.EVENTS_REJECTIONS, rr.TextLog(rejection_row(frame), level=rr.TextLogLevel.WARN))

    def rejection_reasons(self) -> list[str]:
        """The reasons frames were rejected for, in order of first occurrence."""
        return list(dict.fromkeys(reason for _, reason in self.rejections))

    def log_rejection_markers(self, marker_y: dict[str, float]) -> None:
        """The crosses of the rejected frames on every plot (:func:`log_rejections.log_rejection_markers`)."""
        log_rejections.log_rejection_markers(self._rec, self._columns, self.rejections, marker_y, self.max_reproj_px)


def agv_body(color: tuple[int, int, int], label: str = "") -> rr.Boxes3D:
    """The nominal AGV body box; labelled only when it needs explaining (stale pose)."""
    return rr.Boxes3D(
        half_sizes=[AGV_BODY_HALF_SIZES_M],
        centers=[AGV_BODY_CENTER_M],
        colors=color,
        labels=[label] if label else [],  # empty clears a previous stale label
        radii=rr.Radius.ui_points(1.5),
    )


def _thinned(positions_m: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """At most MAX_TRAJECTORY_POINTS of ``positions_m``, evenly spread, first and last kept."""
    n = len(positions_m)
    if n <= MAX_TRAJECTORY_POINTS and isinstance(positions_m, np.ndarray):
        return positions_m.copy()
    keep = np.unique(np.linspace(0, n - 1, min(n, MAX_TRAJECTORY_POINTS)).round().astype(int))
    if isinstance(positions_m, np.ndarray):
        return positions_m[keep]
    return np.array([positions_m[i] for i in keep])


def _pinhole(camera: PinholeCamera) -> rr.Pinhole:
    """The frustum of ``camera`` (an ideal pinhole: Rerun does not draw lens distortion)."""
    return rr.Pinhole(
        image_from_camera=camera.K,
        resolution=[camera.width_px, camera.height_px],
        camera_xyz=rr.ViewCoordinates.RDF,
        image_plane_distance=FRUSTUM_IMAGE_PLANE_M,
        color=COLOR_CAMERA,
    )


def _outline_of_points(points_m: np.ndarray) -> np.ndarray:
    """The convex hull (in their plane) of coplanar 3-D points: a board's saddles seen."""
    centre = points_m.mean(axis=0)
    if len(points_m) < 3:
        return points_m
    _, _, Vt = np.linalg.svd(points_m - centre)
    uv = ((points_m - centre) @ Vt[:2].T).astype(np.float32)
    hull = cv2.convexHull(uv, returnPoints=False).ravel()
    return points_m[hull]


def check_frame(frame: FrameResult) -> None:
    """Raise RunLogError if ``frame`` cannot be logged as it is."""
    where = f"frame {frame.index}"
    if frame.image_format not in MEDIA_TYPES:
        raise RunLogError(
            f"{where}: image_format {frame.image_format!r} is not one of {sorted(MEDIA_TYPES)}"
        )
    for obs in frame.observations:
        as_array(obs.corners_px, (-1, 2), f"{where}: corners_px of marker {obs.marker_id!r}")
        if obs.reprojected_px is not None:
            as_array(obs.reprojected_px, (-1, 2), f"{where}: reprojected_px of marker {obs.marker_id!r}")
    if frame.T_world_agv_truth is not None:
        as_transform(frame.T_world_agv_truth, f"{where}: T_world_agv_truth")
    if frame.T_world_agv_ghost is not None:
        as_transform(frame.T_world_agv_ghost, f"{where}: T_world_agv_ghost")
    if frame.position_cov_world_m2 is not None:
        as_array(frame.position_cov_world_m2, (3, 3), f"{where}: position_cov_world_m2")
    if frame.solved:
        if frame.T_world_agv is None:
            raise RunLogError(f"{where} is solved (rejected is None) but has no T_world_agv")
        as_transform(frame.T_world_agv, f"{where}: T_world_agv")


def as_array(value, shape: tuple[int, int], what: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (-1 = any length), else RunLogError."""
    a = np.asarray(value, dtype=float)
    if a.ndim != 2 or any(want not in (-1, got) for want, got in zip(shape, a.shape)):
        raise RunLogError(f"{what} must have shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise RunLogError(f"{what} contains NaN or inf")
    return a


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def as_transform(T, what: str) -> np.ndarray:
    T = as_array(T, (4, 4), what)
    # np.allclose(T[3], [0, 0, 0, 1]) (rtol 1e-5, atol 1e-8) for finite T, without its overhead
    if not (np.abs(T[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all():
        raise RunLogError(f"{what} is not a homogeneous transform (last row {T[3].tolist()})")
    return T


def transform3d(T_parent_child: np.ndarray) -> rr.Transform3D:
    """Transform3D placing the child entity at ``T_parent_child`` in its parent."""
    return rr.Transform3D(translation=T_parent_child[:3, 3], mat3x3=T_parent_child[:3, :3])


def trajectory(positions_m: list[np.ndarray], color: tuple[int, int, int]) -> rr.LineStrips3D:
    """The trajectory so far, thinned to at most MAX_TRAJECTORY_POINTS (first and last kept)."""
    return rr.LineStrips3D([_thinned(positions_m)], colors=color, radii=rr.Radius.ui_points(2.0))


