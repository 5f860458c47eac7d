"""Markers: the QR payload codec (:mod:`.payload`) and QR detection with corner refinement
(:mod:`.qr`)."""

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
