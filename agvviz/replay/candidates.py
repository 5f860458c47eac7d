"""The solve stage's candidates: which detected codes of a frame can give a pose.

A QR code's payload is parsed strictly and checked against the marker map; an ArUco marker is
looked up in the map, a ChArUco board's saddle corners are one more candidate (for the joint
solve). Each candidate is (observation, ideal corners px, marker-frame points, frame of the
marker, ``T_frame_marker``); each code that cannot be used is a problem (reject reason, detail),
ranked by :data:`REASON_RANK` when no code of the frame is usable. Used by
:class:`agvviz.replay.solve.Replay`, which keeps one :class:`PayloadMemo` per run (a code's
payload is parsed once, not in every frame that sees it).
"""

from __future__ import annotations

import cv2
import numpy as np

from agvviz.conventions import WORLD_FRAME
from agvviz.geometry import PinholeCamera, se3
from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners
from agvviz.markers.aruco import ArucoMap
from agvviz.markers.charuco import chessboard_id
from agvviz.markers.payload import PayloadError, parse_payload
from agvviz.model.frames import (
    REJECT_DECODE,
    REJECT_GEOMETRY,
    REJECT_NO_MARKER,
    REJECT_PAYLOAD,
    FrameDraft,
    MarkerObservation,
)
from agvviz.model.frames import REJECT_MAP_MISMATCH
from agvviz.recording.contract import payload_map_problem
from agvviz.model.detections import CodeDetection

#: When no code of a frame is usable, the frame's reason is the first of these its codes had.
REASON_RANK = {
    r: i for i, r in enumerate((REJECT_MAP_MISMATCH, REJECT_PAYLOAD, REJECT_GEOMETRY, REJECT_DECODE, REJECT_NO_MARKER))
}



class PayloadMemo:
    """A QR payload's parse and marker frame, computed once per payload of a run (issue 27).

    The same code is seen in many frames with the same payload; :func:`parse_payload` and
    :func:`marker_frame_from_corners` depend on the payload alone, so their result (or the problem
    they raise) is kept by payload. The arrays handed out are read-only: a caller that changed
    one would change every later frame's."""

    def __init__(self):
        self._by_payload: dict = {}

    def frame_of(self, payload_value):
        """``(payload, T_world_marker, points_marker_m)`` of the payload ``payload_value`` (text or
        bytes), or raise the :class:`PayloadError` / :class:`DegenerateGeometryError` its parse
        raised."""
        entry = self._by_payload.get(payload_value)
        if entry is None:
            try:
                payload = parse_payload(payload_value)
                T_world_marker, points_marker_m = marker_frame_from_corners(payload.points_world_m)
                T_world_marker.setflags(write=False)
                points_marker_m.setflags(write=False)
                entry = (payload, T_world_marker, points_marker_m)
            except (PayloadError, DegenerateGeometryError) as exc:
                entry = exc
            self._by_payload[payload_value] = entry
        if isinstance(entry, Exception):
            raise entry.with_traceback(None)  # a fresh traceback each time, not a growing one
        return entry


def module_to_marker(points_module: np.ndarray, n_modules: int, vertices_marker_m: np.ndarray) -> np.ndarray:
    """Marker-frame points (M, 3) of QR module coordinates (M, 2) (x right, y down from the
    symbol's TL corner), through the projective map of the module square onto the marker's
    vertices TL, TR, BR, BL (exact for any planar quadrilateral the payload describes)."""
    n = float(n_modules)
    H = cv2.getPerspectiveTransform(
        np.array([[0, 0], [n, 0], [n, n], [0, n]], dtype=np.float32),
        vertices_marker_m[:4, :2].astype(np.float32),
    ).astype(float)
    xy = cv2.perspectiveTransform(points_module.reshape(1, -1, 2).astype(float), H).reshape(-1, 2)
    return np.c_[xy, np.zeros(len(xy))]


def ideal_to_image_px(camera: PinholeCamera, ideal_px: np.ndarray) -> np.ndarray:
    """Pixels of the undistorted (ideal) image → pixels of the recorded (distorted) image."""
    if not camera.has_distortion:
        return ideal_px.copy()
    # Ideal pixels → normalised coordinates through K alone (the undistorted camera's K is the same).
    xy = camera.pixels_to_normalized_distorted(ideal_px)
    return camera.normalized_to_pixels(camera.distort_normalized(xy))


def aruco_candidates(
    aruco_map: ArucoMap, codes: tuple[CodeDetection, ...], camera: PinholeCamera, result: FrameDraft,
    chessboards: tuple, chessboards_not_used: dict[str, tuple[int, str]],
):
    """ArUco markers of the map among the detected codes: (candidates, problems) as in
    :func:`qr_candidates`; a marker id the map does not list is a problem, not a pose.
    The saddle corners of each ChArUco board in view are one more candidate, named
    :func:`chessboard_id` (for the joint solve only: never the largest marker); a board
    whose saddles were not used says why in the frame's ``marker_note`` and is counted in
    ``chessboards_not_used`` (board name → (frames, first note))."""
    candidates, problems = [], []
    for det in codes:
        if det.kind != "aruco":
            continue
        marker = aruco_map.markers.get(det.aruco_id)
        if marker is None:
            problems.append((REJECT_PAYLOAD, f"ArUco id {det.aruco_id} is not in the marker map"))
            continue
        observation = MarkerObservation(
            marker_id=str(det.aruco_id),
            payload="",
            corners_px=ideal_to_image_px(camera, det.corners_px),
            points_world_m=marker.corners_m,
            points_frame=marker.frame,
        )
        result.observations.append(observation)
        candidates.append((observation, det.corners_px, marker.points_marker_m, marker.frame, marker.T_frame_marker))
    notes = []
    for found in chessboards:
        if found.note:
            notes.append(found.note)
        if len(found.corner_ids) == 0 and "not used" in found.note:  # not: too few markers in view
            name = chessboard_id(found.board_index)
            count, first = chessboards_not_used.get(name, (0, found.note))
            chessboards_not_used[name] = (count + 1, first)
        if not 0 <= found.board_index < len(aruco_map.boards) or len(found.corner_ids) == 0:
            continue
        board = aruco_map.boards[found.board_index]
        ids = np.asarray(found.corner_ids, dtype=int)
        ideal = np.asarray(found.corners_px, dtype=float)
        observation = MarkerObservation(
            marker_id=chessboard_id(found.board_index),
            payload="",
            corners_px=ideal_to_image_px(camera, ideal),
            points_world_m=board.corners_m[ids],
            points_frame=board.frame,
        )
        result.observations.append(observation)
        candidates.append((observation, ideal, board.points_board_m[ids], board.frame, board.T_frame_board))
    result.marker_note = "; ".join(notes)
    misplaced = [found for found in chessboards if found.misplaced_ids]
    if misplaced:
        # A board seen unlike its description (a wrong legacy_pattern, ids or squares): its
        # markers would give a pose off by whole squares. The frame is refused.
        return [], [(REJECT_MAP_MISMATCH, found.note) for found in misplaced]
    if not candidates and not problems:
        problems.append((REJECT_NO_MARKER, f"no {aruco_map.dictionary} marker found"))
    return candidates, problems


def qr_candidates(
    qr_map: dict[str, np.ndarray], unmapped_tolerance_m: float, codes: tuple[CodeDetection, ...],
    camera: PinholeCamera, result: FrameDraft, memo: PayloadMemo | None = None,
):
    """The detected QR codes whose payload parses and agrees with the marker map (each payload
    parsed once per ``memo``: a run passes its own; without one, every call parses afresh).

    Returns ``(candidates, problems)``: candidates are (observation, ideal corners px,
    marker-frame points, frame of the marker, ``T_frame_marker``); problems are
    (reject reason, detail) of every code that could not be used.
    """
    codes = [c for c in codes if c.kind == "qr"]
    if not codes:
        return [], [(REJECT_NO_MARKER, "no QR code found")]
    candidates = []
    problems = []
    memo = memo if memo is not None else PayloadMemo()
    for det in codes:
        if not det.decoded:
            problems.append((REJECT_DECODE, "a QR code was found but not decoded"))
            continue
        try:
            # Bytes that are not UTF-8 text go to the strict parser too, which refuses them.
            payload, T_world_marker, points_marker_m = memo.frame_of(
                det.text if det.text is not None else det.payload_bytes
            )
        except PayloadError as exc:
            problems.append((REJECT_PAYLOAD, f"payload refused: {exc}"))
            continue
        except DegenerateGeometryError as exc:
            problems.append((REJECT_GEOMETRY, f"payload geometry: {exc}"))
            continue
        map_problem = payload_map_problem(
            payload.marker_id, payload.points_world_m, qr_map, unmapped_tolerance_m
        )
        if map_problem is not None:
            problems.append((REJECT_MAP_MISMATCH, f"payload refused: {map_problem}"))
            continue
        # The 4 vertices are measured in the image; edge midpoints (if the payload carries
        # them) have no image measurement of their own (a point of the fitted homography
        # adds no information). feature_points=finder adds the finder-pattern corners,
        # each measured on its own by the detect stage (agvviz.markers.qr.finder_corners).
        ideal_px, points_m = det.corners_px, points_marker_m[:4]
        if det.finder_px is not None:
            ideal_px = np.vstack([ideal_px, det.finder_px])
            points_m = np.vstack([points_m, module_to_marker(det.finder_modules, det.n_modules, points_m)])
        observation = MarkerObservation(
            marker_id=payload.marker_id,
            payload=det.text,
            corners_px=ideal_to_image_px(camera, ideal_px),
            points_world_m=se3.transform_points(T_world_marker, points_m)
            if len(points_m) > 4 else payload.points_world_m[:4],
        )
        result.observations.append(observation)
        candidates.append((observation, ideal_px, points_m, WORLD_FRAME, T_world_marker))
    return candidates, problems
