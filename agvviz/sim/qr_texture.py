"""Printed QR codes for the simulated floor: module matrices and :class:`FloorCode` objects.

The symbols come from ``cv2.QRCodeEncoder.create().encode(text)`` with the default encoder
parameters — the corner refiner re-encodes decoded text the same way, so do not change them.
"""

from __future__ import annotations

import cv2
import numpy as np

from agvviz.geometry import euler, se3
from agvviz.geometry.plane import square_points_marker
from agvviz.markers.payload import QrPayload, encode_payload
from agvviz.sim.render import FloorCode

#: White margin printed around every symbol, in modules (the QR standard's quiet zone).
QUIET_ZONE_MODULES = 4
#: Payload coordinates are stored at 0.1 mm; floor-code vertices must sit on that grid.
PAYLOAD_RESOLUTION_M = 1e-4


def qr_symbol_modules(text: str) -> np.ndarray:
    """Dark modules (n, n) bool of the QR symbol of ``text``, quiet zone removed.

    Row 0 is the printed top row (the two upper finder patterns), column 0 the printed left
    column. Raises ``ValueError`` when OpenCV cannot encode the text.
    """
    image = cv2.QRCodeEncoder.create().encode(text)
    if image is None or image.size == 0:
        raise ValueError(f"OpenCV could not encode {text!r} as a QR code (too long?)")
    dark = image < 128
    rows = np.flatnonzero(dark.any(axis=1))
    cols = np.flatnonzero(dark.any(axis=0))
    # Finder patterns occupy the first and last rows/columns of the symbol, so the extent of
    # the dark pixels is the symbol (the encoder adds its own light border of 1 px per module).
    symbol = dark[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    if symbol.shape[0] != symbol.shape[1] or (symbol.shape[0] - 17) % 4 != 0:
        raise ValueError(f"unexpected QR symbol size {symbol.shape} from OpenCV's encoder")
    return symbol


def make_floor_code(
    marker_id: str,
    center_world_m: tuple[float, float],
    quarter_turns: int,
    side_m: float,
    with_midpoints: bool = False,
) -> FloorCode:
    """A QR code printed flat on the floor whose payload carries its own world coordinates.

    Parameters
    ----------
    marker_id : str
        Id written into the payload (``[A-Za-z0-9_-]{1,32}``).
    center_world_m : (x, y)
        Symbol centre on the floor (z = 0).
    quarter_turns : int
        In-plane rotation of the printed code: the marker x axis (printed top edge, left to
        right) points along world ``Rz(quarter_turns · 90°) · x``.
    side_m : float
        Symbol side between the outer vertices (quiet zone excluded).
    with_midpoints : bool
        Payload carries 8 points (vertices + edge midpoints) instead of 4.

    Raises
    ------
    ValueError
        When the feature points do not lie on the payload's 0.1 mm grid (the printed code
        would disagree with its own payload) or the payload cannot be encoded.
    """
    T_world_marker = se3.make(
        euler.Rz(quarter_turns * np.pi / 2.0), [center_world_m[0], center_world_m[1], 0.0]
    )
    points_marker_m = square_points_marker(side_m, with_midpoints)
    points_world_m = se3.transform_points(T_world_marker, points_marker_m)
    off_grid_m = np.max(np.abs(points_world_m - np.round(points_world_m / PAYLOAD_RESOLUTION_M) * PAYLOAD_RESOLUTION_M))
    if off_grid_m > 1e-9:
        raise ValueError(
            f"code {marker_id}: feature points are {off_grid_m * 1000:.3f} mm off the payload's "
            "0.1 mm grid; choose the code centre and side_m / 2 as multiples of 0.1 mm"
        )
    payload = encode_payload(QrPayload(marker_id=marker_id, points_world_m=points_world_m))
    return FloorCode(
        marker_id=marker_id,
        payload=payload,
        T_world_marker=T_world_marker,
        side_m=float(side_m),
        modules=qr_symbol_modules(payload),
        points_marker_m=points_marker_m,
        quiet_zone_modules=QUIET_ZONE_MODULES,
    )
