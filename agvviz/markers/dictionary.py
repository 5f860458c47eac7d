"""OpenCV's predefined ArUco dictionaries by name (``DICT_5X5_50``, ``DICT_APRILTAG_36h11``…),
with agvviz's refusals (:data:`agvviz.markers.apriltag.UNSUPPORTED_APRILTAG`). No file I/O,
no printing.
"""

from __future__ import annotations

import functools

import cv2

from agvviz.markers.apriltag import UNSUPPORTED_APRILTAG
from agvviz.markers.types import ArucoError


def is_aruco_dictionary(name: str) -> bool:
    """True when ``name`` is an OpenCV predefined ArUco dictionary (e.g. ``DICT_5X5_50``)."""
    return isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)


@functools.lru_cache(maxsize=8)
def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The predefined dictionary called ``name``; :class:`ArucoError` names the valid ones."""
    if name in UNSUPPORTED_APRILTAG:
        raise ArucoError(UNSUPPORTED_APRILTAG[name])
    if not is_aruco_dictionary(name):
        valid = sorted(
            n for n in dir(cv2.aruco)
            if n.startswith("DICT_") and not n.endswith("_CUSTOM") and n not in UNSUPPORTED_APRILTAG
        )
        raise ArucoError(f"unknown ArUco dictionary {name!r}; valid: {', '.join(valid)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
