"""The zoom panel's images: the crop around a small code (:func:`crop_around`) and the
placeholder while it is not seen (issue 26: nothing stale).

A zoom panel (:meth:`agvviz.viz.log_frames.FrameLogger.log_zoom`) shows a crop around a camera's
smallest code. When that code is gone — hidden, or only large codes in view — the panel must not
keep the last crop as if it were current: it shows this placeholder (also at a frame where the
camera's image is missing altogether, a dropped frame), an image of the crops' size
and channels (the viewer refuses an image stream that changes either) with the words of
:func:`zoom_unseen_lines`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from agvviz.errors import RunError
from agvviz.viz.style import COLOR_STALE

#: Every crop is resized to this side (nearest neighbour: pixels stay visible as blocks), so
#: the zoomed image keeps one size (the viewer refuses a stream of images changing size).
ZOOM_SIDE_PX = 256
ZOOM_CROP_CODE_SIDES = 3.0
ZOOM_MIN_CROP_PX = 32


def zoom_unseen_lines(last_seen_frame: int, codes_in_view: bool, dropped: bool = False) -> list[str]:
    """The words on a zoom panel whose small code is gone: since when, and why (no code in view,
    or only large codes, which the full image shows; ``dropped``: the camera's image is missing
    at this frame, so nothing was seen)."""
    if dropped:
        return ["no image at this frame", "(camera frame dropped)", f"code last seen: frame {last_seen_frame}"]
    why = "only large codes in view (full image tab)" if codes_in_view else "no code in view"
    return ["small code not seen", f"since frame {last_seen_frame}", why]


def zoom_unseen_png(last_seen_frame: int, codes_in_view: bool, gray: bool, side_px: int, dropped: bool = False) -> bytes:
    """PNG placeholder, ``side_px`` square, one channel when ``gray`` (else BGR), carrying
    :func:`zoom_unseen_lines` in the stale colour on black."""
    image = np.zeros((side_px, side_px) if gray else (side_px, side_px, 3), np.uint8)
    color = (int(np.mean(COLOR_STALE)),) if gray else tuple(int(c) for c in COLOR_STALE[::-1])
    for k, line in enumerate(zoom_unseen_lines(last_seen_frame, codes_in_view, dropped)):
        scale = (0.55 if k < 2 else 0.4) * side_px / 256
        (width, _), _ = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        y = side_px // 2 + int((30 * k - 30) * side_px / 256)
        cv2.putText(image, line, ((side_px - width) // 2, y), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise RunError("cannot encode the zoom placeholder")
    return png.tobytes()


def longest_edge_px(corners_px: np.ndarray) -> float:
    """Longest edge of a code's outline (TL, TR, BR, BL) in pixels."""
    previous = np.concatenate((corners_px[-1:], corners_px[:-1]))  # np.roll(corners_px, 1, axis=0)
    return float(np.max(np.linalg.norm(corners_px - previous, axis=1)))


def crop_around(image_bytes: bytes, corners_px: np.ndarray) -> tuple[bytes, np.ndarray, float, bool] | None:
    """PNG of a square crop of the image centred on the code, resized to ZOOM_SIDE_PX; the
    crop's top-left pixel, the zoom's pixels per image pixel and whether it is one-channel. None
    when the image does not decode."""
    image = cv2.imdecode(np.frombuffer(image_bytes, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    height, width = image.shape[:2]
    side = int(max(ZOOM_MIN_CROP_PX, math.ceil(ZOOM_CROP_CODE_SIDES * longest_edge_px(corners_px))))
    centre = corners_px.mean(axis=0)
    x0 = int(np.clip(round(centre[0] - side / 2), 0, max(width - side, 0)))
    y0 = int(np.clip(round(centre[1] - side / 2), 0, max(height - side, 0)))
    crop = image[y0 : y0 + side, x0 : x0 + side]
    if crop.shape[0] != crop.shape[1]:  # an image smaller than the crop: pad it square
        side = max(crop.shape[:2])
        crop = cv2.copyMakeBorder(crop, 0, side - crop.shape[0], 0, side - crop.shape[1], cv2.BORDER_CONSTANT)
    zoomed = cv2.resize(crop, (ZOOM_SIDE_PX, ZOOM_SIDE_PX), interpolation=cv2.INTER_NEAREST)
    ok, png = cv2.imencode(".png", zoomed)
    if not ok:
        return None
    return png.tobytes(), np.array([x0, y0], dtype=float), ZOOM_SIDE_PX / side, zoomed.ndim == 2
