"""Detect stage: one camera frame → its markers' corners, ids and payloads (no pose).

A frame is detected from its recorded bytes and its camera's calibration (and, when tracking,
the odometry of its segment's frames, below): the header is checked
(:func:`agvviz.recording.contract.frame_problem`), the image decoded, checked against the
calibration's size and undistorted, then QR codes (zxing-cpp, ECC-refined corners,
:mod:`agvviz.markers.qr`) or the map's ArUco markers are found. What a code *means* (its
payload parsed, its place in the marker map) is the solve stage's business, so detections do
not depend on the marker map's contents — only on its ArUco dictionary, when it names one.

Tracking (setting ``tracking``): the frames of each camera are cut into *segments* of whole
keyframe intervals (:attr:`DetectParams.segment_frames`, by the camera's own frame count). The
first frame of a segment and every ``keyframe_every``-th after it get a full detection; the
others follow the codes found so far (:class:`agvviz.markers.tracking.CodeTracker`), falling
back to full detection when a check fails. When the frame and the one before it carry the
vehicle's odometry pose and the camera's extrinsic (:class:`FrameJob`), the tracker is given
the floor's motion between them as its ``motion_hint``: the homography the floor (z = 0 of the
body frame) induces in the undistorted image
(:func:`agvviz.geometry.homography.floor_homography`). It predicts every code, also on the frame
after a segment's first and through the AGV's turns, where a code's own image motion does not;
the tracker's checks refuse a wrong prediction (bad odometry) and fall back to full detection.
A code that comes into view between keyframes is found at the next one. A segment is the unit
of work of a detection worker, so detections are a function of the segment's jobs alone, the
same whatever the number of workers, the window of frames in flight or the cache
(:mod:`agvviz.replay.detect.cache`) — and runs of equal settings write equal ``.rrd`` files.

Everything here is pure (no I/O beyond the bytes given, no Rerun, no printing) and picklable,
so :mod:`agvviz.replay.detect.pool` can run it in worker processes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from agvviz.errors import InputError
from agvviz.geometry import PinholeCamera
from agvviz.geometry.homography import floor_homography
from agvviz.geometry.plane import DegenerateGeometryError
from agvviz.recording.checks import frame_problem
from agvviz.model.detections import CodeDetection, FrameDetections
from agvviz.model.messages import CalibrationMsg
from agvviz.recording.values import image_size_problem
from agvviz.model.frames import REJECT_DECODE, REJECT_IMAGE, REJECT_NO_CALIBRATION
from agvviz.settings import RunSettings

#: The run settings that change what the detect stage outputs; every other setting (solver,
#: fusion, correction, …) reuses a recording's stored detections.
DETECTION_SETTINGS = ("refine", "feature_points", "tracking", "keyframe_every")

#: Bumped whenever a change to detection or tracking changes what they output, so that cached
#: detections (:mod:`agvviz.replay.detect.cache`, keyed by it and agvviz's version) of an earlier
#: build are never reused.
DETECT_REVISION = 5

#: Shortest tracking segment (frames): the unit of work of a detection worker.
MIN_SEGMENT_FRAMES = 30


def detection_settings(settings: RunSettings) -> dict:
    """The detection-relevant part of ``settings`` (equal dicts ⇒ equal detections)."""
    return {name: getattr(settings, name) for name in DETECTION_SETTINGS}


@dataclass(frozen=True)
class DetectParams:
    """What detection depends on besides the frame: the detection settings, the marker
    family (``aruco_dictionary`` of the marker map, or None for QR codes) and the layouts of the
    map's ChArUco boards (``charuco_boards``, :class:`agvviz.markers.charuco.CharucoSpec`, in the
    map's order), whose chessboard corners are found from their detected markers."""

    refine: str = "ecc"
    feature_points: str = "vertices"
    tracking: bool = True
    keyframe_every: int = 10
    aruco_dictionary: str | None = None
    charuco_boards: tuple = ()

    def __post_init__(self) -> None:
        from agvviz.markers.apriltag import is_apriltag_dictionary
        from agvviz.markers.aruco import check_apriltag_refine
        from agvviz.markers.qr import REFINE_METHODS as QR_REFINE_METHODS

        if is_apriltag_dictionary(self.aruco_dictionary):
            check_apriltag_refine(self.refine)  # ArucoError, an InputError: before any work
        if self.aruco_dictionary is None and self.refine not in QR_REFINE_METHODS:
            raise InputError(
                f"refine={self.refine} is OpenCV's corner refinement of ArUco/AprilTag markers; the markers "
                f"here are QR codes: use refine={' or '.join(QR_REFINE_METHODS)}"
            )

    @classmethod
    def of(cls, settings: RunSettings, aruco_dictionary: str | None, charuco_boards: tuple = ()) -> "DetectParams":
        return cls(**detection_settings(settings), aruco_dictionary=aruco_dictionary, charuco_boards=tuple(charuco_boards))

    @property
    def tracks(self) -> bool:
        """Tracking applies: it is on, and the markers are QR codes (ArUco frames are always
        detected in full)."""
        return self.tracking and self.aruco_dictionary is None

    @property
    def segment_frames(self) -> int:
        """Frames per unit of work. Tracking: a segment of whole keyframe intervals, at least
        :data:`MIN_SEGMENT_FRAMES` long (without odometry a track needs two frames to know a
        code's motion, so the frame after a segment's first is a keyframe too: longer segments
        waste fewer).
        Without tracking a small batch (every frame is a keyframe: results do not depend on it)."""
        if not self.tracks:
            return 4
        return self.keyframe_every * -(-MIN_SEGMENT_FRAMES // self.keyframe_every)


@dataclass(frozen=True)
class FrameJob:
    """One frame to detect: its camera's calibration and its recorded bytes; for a camera on
    the vehicle of a recording with odometry, also the odometry pose ``T_odom_agv`` at the
    frame's stamp and the camera's extrinsic ``T_agv_cam`` (4×4; None when unknown, or for a
    camera fixed in the world), which let tracking predict the floor's motion."""

    cam_name: str
    image_format: str
    data: bytes
    calibration: CalibrationMsg
    T_odom_agv: np.ndarray | None = None
    T_agv_cam: np.ndarray | None = None


@dataclass
class CameraModel:
    """A calibration made usable: the camera, its undistortion maps (once built: ``maps_built``),
    or why it was refused."""

    camera: PinholeCamera | None
    undistort_maps: tuple[np.ndarray, np.ndarray] | None = None
    problem: str = ""
    #: False for a model asked for without its maps (:func:`camera_model`), until they are.
    maps_built: bool = True


def camera_model(calibration: CalibrationMsg, maps: bool = True) -> CameraModel:
    """The camera of ``calibration`` with its undistortion maps (when it has distortion), or a
    refusal (an absurd image size, maps that cannot be built). Without ``maps`` (the solve
    stage: it never undistorts an image) they are not built, and their failure is not known:
    the maps of a 1280×1024 camera are 10 MB and take ≈20-30 ms, in every process that solves
    (a warm run, each setting of a sweep) where only detection needs them. Cached per
    calibration value."""
    c = calibration.camera
    key = (c.width_px, c.height_px, np.asarray(c.K, float).tobytes(), np.asarray(c.dist, float).tobytes())
    model = _CAMERA_MODELS.get(key)
    if model is None or (maps and not model.maps_built):
        if model is None and len(_CAMERA_MODELS) >= 8:
            _CAMERA_MODELS.clear()
        model = _CAMERA_MODELS[key] = _build_camera_model(c, maps)
    return model


_CAMERA_MODELS: dict[tuple, CameraModel] = {}


def _build_camera_model(camera: PinholeCamera, maps: bool) -> CameraModel:
    problem = image_size_problem(camera.width_px, camera.height_px)
    undistort_maps = None
    if problem is None and not maps:
        return CameraModel(camera, None, maps_built=not camera.has_distortion)
    if problem is None and camera.has_distortion:
        try:
            undistort_maps = cv2.initUndistortRectifyMap(
                camera.K, camera.dist, None, camera.K, (camera.width_px, camera.height_px), cv2.CV_32FC2
            )
        except (cv2.error, MemoryError) as exc:
            problem = f"undistortion maps could not be built ({str(exc).strip().splitlines()[-1]})"
    if problem is not None:
        return CameraModel(None, None, f"calibration refused: {problem}")
    return CameraModel(camera, undistort_maps)


def _decode(
    job: FrameJob, model: CameraModel, undistort: bool = True
) -> tuple[np.ndarray | None, tuple[str, str] | None, bool]:
    """(gray image, undistorted unless ``undistort`` is False; rejection; drop the bytes)."""
    problem = frame_problem(job.image_format, job.data, model.camera)  # header only, no decode
    if problem is not None:
        return None, problem, problem[0] == REJECT_IMAGE
    try:
        gray = cv2.imdecode(np.frombuffer(job.data, np.uint8), cv2.IMREAD_GRAYSCALE)
    except cv2.error as exc:
        gray, error = None, str(exc).strip().splitlines()[-1]
    else:
        error = ""
    if gray is None:
        return None, (REJECT_DECODE, f"{job.image_format} frame does not decode" + (f" ({error})" if error else "")), False
    problem = frame_problem(job.image_format, job.data, model.camera, size=(gray.shape[1], gray.shape[0]))
    if problem is not None:
        return None, problem, problem[0] == REJECT_IMAGE
    if undistort:
        gray = _undistorted(gray, model)
    return gray, None, False


def _undistorted(gray: np.ndarray, model: CameraModel) -> np.ndarray:
    """The whole frame undistorted (itself when the camera has no distortion)."""
    if model.undistort_maps is None:
        return gray
    return cv2.remap(gray, *model.undistort_maps, interpolation=cv2.INTER_LINEAR)


def _undistorted_boxes(gray: np.ndarray, model: CameraModel, boxes) -> np.ndarray:
    """A frame whose ``boxes`` ``(x0, y0, x1, y1)`` hold the undistorted frame's pixels — the
    same values as :func:`_undistorted`'s, each output pixel being a function of its own map
    entry — and the rest 0: what a tracked frame reads, at a fraction of the cost."""
    map_xy, map_extra = model.undistort_maps
    out = np.zeros_like(gray)
    for x0, y0, x1, y1 in boxes:
        if x1 > x0 and y1 > y0:
            extra = map_extra[y0:y1, x0:x1] if map_extra is not None and map_extra.size else None
            out[y0:y1, x0:x1] = cv2.remap(gray, map_xy[y0:y1, x0:x1], extra, interpolation=cv2.INTER_LINEAR)
    return out


def _qr_code(gray: np.ndarray, det, params: DetectParams) -> CodeDetection:
    from agvviz.markers.qr import finder_corners

    finder_px = finder_modules = None
    if params.feature_points == "finder" and det.n_modules is not None and det.text is not None:
        finder_px, finder_modules = finder_corners(gray, det.corners_px, det.n_modules)
    return CodeDetection(
        kind="qr", corners_px=det.corners_px, raw_corners_px=det.raw_corners_px, text=det.text,
        payload_bytes=det.payload_bytes, n_modules=det.n_modules, finder_px=finder_px,
        finder_modules=finder_modules, refine_method=det.refine_method, refine_note=det.refine_note,
    )


@dataclass
class SegmentDetector:
    """Detects the consecutive frames of one camera in order; tracking state lives here and
    restarts every ``params.segment_frames`` frames (a new segment starts with a keyframe).
    Used whole by a worker for one segment, or fed frame by frame by an in-process replay."""

    params: DetectParams
    _tracker: object | None = field(default=None, repr=False)
    _frames: int = 0
    #: (K, T_odom_agv, T_agv_cam) of the last frame given to the tracker, None when unknown
    _last_motion: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    def detect(self, job: FrameJob) -> FrameDetections:
        t0 = time.perf_counter()
        if self._frames % self.params.segment_frames == 0:
            self._tracker = None  # a new segment: its first frame is a keyframe
            self._last_motion = None
        position = self._frames % self.params.segment_frames
        self._frames += 1
        model = camera_model(job.calibration)
        if model.camera is None:
            # The solve stage, which checks the calibration without building the maps, rejects
            # the frame on its own for an absurd image size; maps that cannot be built are
            # known here only.
            return FrameDetections(
                reject=(REJECT_NO_CALIBRATION, f"camera {job.cam_name!r}: {model.problem}"),
                detect_s=time.perf_counter() - t0, note=model.problem,
            )
        # A tracked frame reads only the parts of the image around its codes: when the camera
        # has distortion, only those are undistorted (the whole frame if it turns out a keyframe).
        partial = self.params.tracks and model.undistort_maps is not None
        gray, reject, drop = _decode(job, model, undistort=not partial)
        if gray is None:
            return FrameDetections(reject=reject, drop_image=drop, detect_s=time.perf_counter() - t0)
        params = self.params
        keyframe, tracked, note = True, 0, ""
        chessboards: tuple = ()
        if params.aruco_dictionary is not None:
            from agvviz.markers.aruco import detect_aruco

            codes = tuple(
                CodeDetection(
                    kind="aruco", corners_px=d.corners_px, raw_corners_px=d.raw_corners_px, aruco_id=d.marker_id,
                    refine_method=d.refine_method, refine_note=d.refine_note,
                )
                for d in detect_aruco(gray, params.aruco_dictionary, refine=params.refine)
            )
            if params.charuco_boards:
                from agvviz.markers.charuco import detect_chessboard

                seen = {c.aruco_id: c.corners_px for c in codes}
                found = (detect_chessboard(gray, spec, i, seen) for i, spec in enumerate(params.charuco_boards))
                chessboards = tuple(c for c in found if c is not None)
        elif params.tracks:
            if self._tracker is None:
                from agvviz.markers.tracking import CodeTracker

                self._tracker = CodeTracker(refine=params.refine, keyframe_every=params.keyframe_every)
            motion = _motion_of(job, model.camera)
            hint = _floor_hint(self._last_motion, motion)
            full_image = None
            if partial:
                distorted = gray
                boxes = self._tracker.regions(distorted.shape, position, motion_hint=hint)
                if boxes is None:
                    gray = _undistorted(distorted, model)
                else:
                    gray = _undistorted_boxes(distorted, model, boxes)
                    whole: list[np.ndarray] = []

                    def full_image() -> np.ndarray:  # a keyframe after all
                        whole.append(_undistorted(distorted, model))
                        return whole[0]

            outcome = self._tracker.detect(gray, position, motion_hint=hint, full_image=full_image)
            if outcome.keyframe and full_image is not None:
                gray = whole[0]  # what the keyframe's codes were found in
            self._last_motion = motion
            keyframe, tracked, note = outcome.keyframe, outcome.tracked, outcome.fallback_reason
            codes = tuple(_qr_code(gray, d, params) for d in outcome.detections)
        else:
            from agvviz.markers.qr import detect_qr_codes

            codes = tuple(_qr_code(gray, d, params) for d in detect_qr_codes(gray, refine=params.refine))
        return FrameDetections(
            codes=codes, detect_s=time.perf_counter() - t0, keyframe=keyframe, tracked=tracked, note=note,
            chessboards=chessboards,
        )


def _motion_of(job: FrameJob, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(K, T_odom_agv, T_agv_cam) of a frame whose job carries its odometry and extrinsic."""
    if job.T_odom_agv is None or job.T_agv_cam is None:
        return None
    return camera.K, np.asarray(job.T_odom_agv, dtype=float), np.asarray(job.T_agv_cam, dtype=float)


def _floor_hint(previous, current) -> np.ndarray | None:
    """The tracker's ``motion_hint``: the floor's homography from the previous frame's
    undistorted pixels to this frame's, from the odometry motion between them (None when
    either frame lacks odometry or extrinsic, the camera matrix changed, or the geometry is
    degenerate — a camera at floor height)."""
    if previous is None or current is None or not np.array_equal(previous[0], current[0]):
        return None
    K, T_odom_agv_previous, T_agv_cam_previous = previous
    _, T_odom_agv, T_agv_cam = current
    try:
        H = floor_homography(K, T_odom_agv_previous, T_odom_agv, T_agv_cam_previous, T_agv_cam)
    except DegenerateGeometryError:
        return None
    return H if np.all(np.isfinite(H)) else None


def detect_segment(params: DetectParams, jobs: list[FrameJob]) -> list[FrameDetections]:
    """Detections of one segment (consecutive frames of one camera, the first a keyframe)."""
    detector = SegmentDetector(params)
    return [detector.detect(job) for job in jobs]
