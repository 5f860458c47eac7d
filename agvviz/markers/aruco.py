"""ArUco marker detection with sub-pixel corner refinement (OpenCV). No file I/O, no printing.

Any OpenCV predefined dictionary works, the AprilTag families included
(``DICT_APRILTAG_16h5``, ``DICT_APRILTAG_25h9``, ``DICT_APRILTAG_36h10``,
``DICT_APRILTAG_36h11``: OpenCV's ArUco detector reads them, and their bit patterns with the
one-module black border are the ECC templates); a tag's side is that of its black border, as
for ArUco markers (AprilTag's "tag size").

Input frames come from an ideal pinhole camera (the pipeline undistorts first). Corners are in
OpenCV pixel coordinates and ArUco order TL, TR, BR, BL as printed (:mod:`agvviz.conventions`);
they are the outer corners of the marker's black border, so a marker of side ``s`` in a map has
corners ``(∓s/2, ±s/2)``.

Refinement (``refine=``, the names the QR pipeline uses):

``"ecc"``     the marker's own bit pattern (black border included) from the dictionary, aligned
              to the image by :func:`agvviz.markers.qr.align_symbol_ecc`; falls back to
              ``"subpix"`` when ECC fails (``refine_note`` says why);
``"subpix"``  OpenCV's ``CORNER_REFINE_SUBPIX``;
``"none"``    the detector's contour corners.
"""

from __future__ import annotations

from agvviz.errors import InputError

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from agvviz.markers.qr import REFINE_METHODS, align_symbol_ecc


class ArucoError(InputError):
    """An unknown ArUco dictionary name or a marker id outside the dictionary."""


@dataclass
class ArucoDetection:
    """One detected marker: its id, refined corners (4, 2) and how they were refined."""

    marker_id: int
    corners_px: np.ndarray
    raw_corners_px: np.ndarray
    refine_method: str
    refine_ok: bool = True
    refine_note: str = ""


def is_aruco_dictionary(name: str) -> bool:
    """True when ``name`` is an OpenCV predefined ArUco dictionary (e.g. ``DICT_5X5_50``)."""
    return isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)


@functools.lru_cache(maxsize=8)
def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The predefined dictionary called ``name``; :class:`ArucoError` names the valid ones."""
    if not is_aruco_dictionary(name):
        valid = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and not n.endswith("_CUSTOM"))
        raise ArucoError(f"unknown ArUco dictionary {name!r}; valid: {', '.join(valid)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@functools.lru_cache(maxsize=64)
def aruco_modules(name: str, marker_id: int) -> np.ndarray:
    """Dark modules ((n + 2)², bool, row 0 the printed top) of marker ``marker_id`` including
    its one-module black border."""
    dictionary = aruco_dictionary(name)
    count = dictionary.bytesList.shape[0]
    if not 0 <= int(marker_id) < count:
        raise ArucoError(f"marker id {marker_id} is outside {name} (ids 0..{count - 1})")
    n = dictionary.markerSize + 2
    image = cv2.aruco.generateImageMarker(dictionary, int(marker_id), n, borderBits=1)
    return image == 0


@functools.lru_cache(maxsize=8)
def _detector(name: str, subpix: bool) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX if subpix else cv2.aruco.CORNER_REFINE_NONE
    return cv2.aruco.ArucoDetector(aruco_dictionary(name), params)


def detect_aruco(gray: np.ndarray, dictionary_name: str, refine: str = "ecc") -> list[ArucoDetection]:
    """Every marker of ``dictionary_name`` found in the uint8 gray image, corners refined."""
    if refine not in REFINE_METHODS:
        raise ValueError(f"unknown refine method {refine!r}; valid: {', '.join(REFINE_METHODS)}")
    corners, ids, _ = _detector(dictionary_name, refine != "none").detectMarkers(gray)
    if ids is None:
        return []
    detections = []
    for marker_corners, marker_id in zip(corners, ids.ravel()):
        raw = marker_corners.reshape(4, 2).astype(float)
        detection = ArucoDetection(int(marker_id), raw.copy(), raw, "subpix" if refine != "none" else "none")
        if refine == "ecc":
            refined, note = align_symbol_ecc(gray, aruco_modules(dictionary_name, int(marker_id)), raw)
            if refined is None:
                detection.refine_ok = False
                detection.refine_note = f"ecc: {note}; kept subpix"
            else:
                detection.corners_px = refined
                detection.refine_method = "ecc"
        detections.append(detection)
    return detections


@dataclass(frozen=True)
class MapMarker:
    """One ArUco marker of a marker map.

    frame : "world" (fixed) or "agv" (mounted on the vehicle).
    corners_m : (4, 3) corners TL, TR, BR, BL in ``frame``.
    T_frame_marker : (4, 4) the marker frame in ``frame`` (:mod:`agvviz.conventions`).
    points_marker_m : (4, 3) the corners in the marker frame (z = 0).
    """

    frame: str
    corners_m: np.ndarray
    T_frame_marker: np.ndarray
    points_marker_m: np.ndarray


@dataclass(frozen=True)
class ArucoMap:
    """An ``agvviz.MarkerMap`` of ArUco markers: the dictionary and the markers by id."""

    dictionary: str
    markers: dict[int, MapMarker]


def parse_aruco_map(marker_map: dict) -> ArucoMap | None:
    """The :class:`ArucoMap` of an ``agvviz.MarkerMap`` message, or None when the map is of
    QR codes (``dictionary`` "qr", whose codes carry their own coordinates).

    Raises :class:`ArucoError` for an unknown dictionary, a non-integer or out-of-range id, an
    unknown frame or corners that do not form a square's plane.
    """
    from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners

    dictionary = marker_map.get("dictionary")
    if dictionary == "qr":
        return None
    aruco_dictionary(dictionary)  # raises for an unknown name
    count = aruco_dictionary(dictionary).bytesList.shape[0]
    markers: dict[int, MapMarker] = {}
    for entry in marker_map.get("markers", []):
        text = str(entry.get("id"))
        if not text.isdigit() or not 0 <= int(text) < count:
            raise ArucoError(f"marker map: id {text!r} is not an id of {dictionary} (0..{count - 1})")
        frame = entry.get("frame", "world")
        if frame not in ("world", "agv"):
            raise ArucoError(f"marker map: marker {text} has frame {frame!r}; expected 'world' or 'agv'")
        corners = np.asarray(entry.get("corners_world_m"), dtype=float)
        try:
            T_frame_marker, points_marker_m = marker_frame_from_corners(corners)
        except DegenerateGeometryError as exc:
            raise ArucoError(f"marker map: marker {text}: {exc}") from None
        markers[int(text)] = MapMarker(frame, corners[:4], T_frame_marker, points_marker_m[:4])
    return ArucoMap(dictionary, markers)
