"""The detect stage's output, frozen: the markers found in one frame (corners, ids, payloads), no
pose. Made by :mod:`agvviz.replay.detect.stage`, solved by :mod:`agvviz.replay.solve`, cached by
:mod:`agvviz.replay.detect.cache` and handed to sinks such as the audit's collector."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CodeDetection:
    """One marker found in one frame, in the *undistorted* (ideal) image's pixels.

    ``kind`` is ``"qr"`` (``text`` or ``payload_bytes`` carry the payload) or ``"aruco"``
    (``aruco_id``). ``corners_px`` (4, 2) are the refined symbol corners TL, TR, BR, BL;
    ``finder_px`` / ``finder_modules`` (M, 2) the finder patterns' corners measured on their own
    (setting ``feature_points=finder``) and their module coordinates.
    """

    kind: str
    corners_px: np.ndarray
    raw_corners_px: np.ndarray
    text: str | None = None
    payload_bytes: bytes | None = None
    aruco_id: int | None = None
    n_modules: int | None = None
    finder_px: np.ndarray | None = None
    finder_modules: np.ndarray | None = None
    refine_method: str = ""
    refine_note: str = ""

    @property
    def decoded(self) -> bool:
        return self.kind == "aruco" or self.text is not None or self.payload_bytes is not None


@dataclass(frozen=True)
class FrameDetections:
    """The detect stage's output for one frame.

    ``reject`` is ``(reason, detail)`` when the frame itself could not be searched (an invalid
    or undecodable image, a size that is not the calibration's); ``drop_image`` then says the
    bytes are nothing a viewer should try to show. ``keyframe`` is False for a frame whose codes
    were tracked (``tracked`` of them); ``note`` says why tracking fell back, if it did.
    ``chessboards`` are the saddle corners of the map's ChArUco boards in view
    (:class:`agvviz.markers.charuco.ChessboardCorners`, undistorted image px; one with no
    corners carries the note saying why they were not used).
    """

    codes: tuple[CodeDetection, ...] = ()
    reject: tuple[str, str] | None = None
    drop_image: bool = False
    detect_s: float = 0.0
    keyframe: bool = True
    tracked: int = 0
    note: str = ""
    chessboards: tuple = ()
