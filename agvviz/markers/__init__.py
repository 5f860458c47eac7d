"""Markers: finding fiducial markers in images and reading what they carry. No file I/O.

Imports point down this list: :mod:`.scan` (which family a recording holds) → :mod:`.aruco`
(ArUco detection, marker maps) → :mod:`.charuco` (ChArUco boards) → :mod:`.dictionary`
(OpenCV dictionaries by name) → :mod:`.apriltag` (AprilTag library) → :mod:`.types`
(detection record, ArucoError) and :mod:`.ecc` (corner refinement by template alignment, used
by every family). :mod:`.qr` (QR detection, above :mod:`.ecc`), :mod:`.payload` (the QR payload
codec) and :mod:`.tracking` (QR codes followed from frame to frame) sit beside them.
"""

from agvviz.markers.payload import (
    MAX_PAYLOAD_CHARS,
    PAYLOAD_PREFIX,
    PayloadError,
    QrPayload,
    encode_payload,
    parse_payload,
)
from agvviz.markers.qr import REFINE_METHODS, QrDetection, detect_qr_codes, qr_modules

__all__ = [
    "MAX_PAYLOAD_CHARS",
    "PAYLOAD_PREFIX",
    "REFINE_METHODS",
    "PayloadError",
    "QrDetection",
    "QrPayload",
    "detect_qr_codes",
    "encode_payload",
    "parse_payload",
    "qr_modules",
]
