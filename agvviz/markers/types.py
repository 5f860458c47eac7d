"""What the ArUco and AprilTag detectors return (:class:`ArucoDetection`) and the error for an
unknown dictionary or a bad marker id (:class:`ArucoError`). No file I/O, no printing.

Below every marker module (:mod:`.apriltag`, :mod:`.dictionary`, :mod:`.charuco`,
:mod:`.aruco`), so that their imports point one way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.errors import InputError


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
