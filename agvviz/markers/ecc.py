"""Corner refinement by template alignment (ECC), for every square module-grid symbol: QR
codes, ArUco markers and AprilTags (the ``"ecc"`` refinement of :mod:`.qr`, :mod:`.aruco` and
:mod:`.apriltag`). No file I/O, no printing.

A template of the symbol's dark modules (plus a light border) is aligned to a crop of the image
around the detector's corners with ``cv2.findTransformECC(MOTION_HOMOGRAPHY)``; the refined
corners are the template's symbol corners mapped through the homography found. A refinement
whose correlation is low or that moves a corner too far is refused (``(None, reason)``).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

#: A refinement that moves any corner further than this many pixels — or, on large codes,
#: further than :data:`MAX_REFINE_SHIFT_MODULES` module widths — is rejected. OpenCV's raw
#: bottom-right corner is often 4–5 px off on a 300 px code, which ECC corrects.
MAX_REFINE_SHIFT_PX = 4.0
MAX_REFINE_SHIFT_MODULES = 1.0
#: Smallest ECC correlation coefficient accepted after alignment.
ECC_MIN_CORRELATION = 0.7
#: ECC samples the image at the template's pixels; when a template pixel spans more than this
#: many image pixels (modules larger than the template's, e.g. 32 px modules on an 8 px/module
#: template) the sharp edges alias and ECC lands up to 2 px off (measured on rendered markers with
#: 0.7–1.5 px blur), so the crop is first blurred with σ = ratio/2 px (edges stay in place).
ECC_ANTIALIAS_RATIO = 2.0
#: Light border (modules) drawn around the template symbol so its outer edges constrain ECC.
TEMPLATE_BORDER_MODULES = 1
#: Template pixels per module are the image's pixels per module, clamped to this range.
TEMPLATE_PX_PER_MODULE_RANGE = (3, 12)

_ECC_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-5)
_ECC_GAUSS_FILTER_SIZE = 3


#: Templates up to this many pixels a side are cached (at most 256 of them, 64 KiB each: an
#: ArUco marker's is 80 px at 8 px per module); larger ones (QR codes: 35 modules at 8 px are
#: 280 px, 306 KiB) in a cache of their own of :data:`LARGE_TEMPLATES_CACHED` (a tracked code
#: is aligned with the same template frame after frame; building it costs ≈1 ms).
CACHED_TEMPLATE_MAX_SIDE_PX = 128
LARGE_TEMPLATES_CACHED = 16


def _ecc_template(symbol: np.ndarray, scale: int) -> np.ndarray:
    """The ECC template of an (n, n) symbol (True dark): the symbol and a
    :data:`TEMPLATE_BORDER_MODULES` light border, ``scale`` px per module, float32 0/255."""
    n = len(symbol)
    key = np.ascontiguousarray(symbol, dtype=bool).tobytes()
    if (n + 2 * TEMPLATE_BORDER_MODULES) * scale <= CACHED_TEMPLATE_MAX_SIDE_PX:
        return _cached_template(key, n, scale)
    return _cached_large_template(key, n, scale)


@functools.lru_cache(maxsize=256)
def _cached_template(symbol_bytes: bytes, n: int, scale: int) -> np.ndarray:
    """:func:`_ecc_template` of a small symbol, cached (read-only): a replay sees the same
    markers frame after frame."""
    template = _build_template(np.frombuffer(symbol_bytes, dtype=bool).reshape(n, n), scale)
    template.setflags(write=False)
    return template


@functools.lru_cache(maxsize=LARGE_TEMPLATES_CACHED)
def _cached_large_template(symbol_bytes: bytes, n: int, scale: int) -> np.ndarray:
    """:func:`_cached_template` for the large templates, in a smaller cache."""
    return _cached_template.__wrapped__(symbol_bytes, n, scale)


def _build_template(symbol: np.ndarray, scale: int) -> np.ndarray:
    padded = np.pad(symbol, TEMPLATE_BORDER_MODULES, constant_values=False)
    return np.where(np.kron(padded, np.ones((scale, scale), dtype=bool)), np.float32(0.0), np.float32(255.0))


def _refine_ecc(
    gray: np.ndarray, symbol: np.ndarray, raw_corners_px: np.ndarray,
    px_per_module_range: tuple[int, int] = TEMPLATE_PX_PER_MODULE_RANGE,
) -> tuple[np.ndarray | None, str]:
    """ECC-aligned symbol corners, or (None, reason)."""
    n = len(symbol)
    side_px = mean_side_px(raw_corners_px)
    low, high = px_per_module_range
    scale = int(np.clip(round(side_px / n), low, high))
    border = TEMPLATE_BORDER_MODULES
    template = _ecc_template(symbol, scale)
    # Template pixel centres are integers, so module coordinate m sits at (m + border)·scale − 0.5.
    symbol_corners_template = (
        np.array([[0, 0], [n, 0], [n, n], [0, n]], dtype=float) + border
    ) * scale - 0.5

    x0, y0, x1, y1 = ecc_crop_box(raw_corners_px, n, gray.shape)
    crop = gray[y0:y1, x0:x1].astype(np.float32)
    ratio = side_px / n / scale  # image pixels per template pixel
    if ratio > ECC_ANTIALIAS_RATIO:
        crop = cv2.GaussianBlur(crop, (0, 0), 0.5 * ratio)
    offset = np.array([x0, y0], dtype=float)

    H_crop_template = cv2.getPerspectiveTransform(
        symbol_corners_template.astype(np.float32), (raw_corners_px - offset).astype(np.float32)
    ).astype(np.float32)
    try:
        correlation, H_crop_template = cv2.findTransformECC(
            template, crop, H_crop_template, cv2.MOTION_HOMOGRAPHY, _ECC_CRITERIA, None,
            _ECC_GAUSS_FILTER_SIZE,
        )
    except cv2.error as exc:
        return None, f"did not converge ({error_line(exc)})"
    if not np.isfinite(correlation) or correlation < ECC_MIN_CORRELATION:
        return None, f"correlation {correlation:.2f} < {ECC_MIN_CORRELATION}"
    corners_px = cv2.perspectiveTransform(
        symbol_corners_template.reshape(1, 4, 2), H_crop_template.astype(float)
    ).reshape(4, 2) + offset
    return accept_shift(corners_px, raw_corners_px, side_px / n)


def ecc_crop_box(raw_corners_px: np.ndarray, n: int, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the part of an image of ``shape`` (H, W) that ECC reads to align an
    ``n``-module symbol from ``raw_corners_px`` — the corners' bounding box with a margin of
    the template's border plus one module plus 4 px (a refinement that moves a corner further
    than one module is refused), clipped to the image; ``gray[y0:y1, x0:x1]``."""
    side_px = mean_side_px(raw_corners_px)
    margin_px = (TEMPLATE_BORDER_MODULES + 1) * side_px / n + 4
    x0 = int(max(np.floor(raw_corners_px[:, 0].min() - margin_px), 0))
    y0 = int(max(np.floor(raw_corners_px[:, 1].min() - margin_px), 0))
    x1 = int(min(np.ceil(raw_corners_px[:, 0].max() + margin_px) + 1, shape[1]))
    y1 = int(min(np.ceil(raw_corners_px[:, 1].max() + margin_px) + 1, shape[0]))
    return x0, y0, x1, y1


def mean_side_px(corners_px: np.ndarray) -> float:
    """Mean side length (px) of the quadrilateral ``corners_px`` (4, 2)."""
    return float(np.mean(np.linalg.norm(np.roll(corners_px, -1, axis=0) - corners_px, axis=1)))


def error_line(exc: Exception) -> str:
    """The last line of an exception's message (OpenCV's errors are several lines), ≤ 100 chars."""
    lines = str(exc).strip().splitlines()
    return lines[-1][:100] if lines else type(exc).__name__


def accept_shift(
    corners_px: np.ndarray, raw_corners_px: np.ndarray, module_px: float
) -> tuple[np.ndarray | None, str]:
    """``(corners_px, "")`` when refinement moved no corner further than
    :data:`MAX_REFINE_SHIFT_PX` or :data:`MAX_REFINE_SHIFT_MODULES` modules of ``module_px``
    (whichever is larger) from ``raw_corners_px``, else ``(None, reason)``."""
    if not np.all(np.isfinite(corners_px)):
        return None, "non-finite corners"
    shift_px = float(np.max(np.linalg.norm(corners_px - raw_corners_px, axis=1)))
    limit_px = max(MAX_REFINE_SHIFT_PX, MAX_REFINE_SHIFT_MODULES * module_px)
    if shift_px > limit_px:
        return None, f"moved a corner {shift_px:.1f} px > {limit_px:.1f} px"
    return corners_px, ""


def align_symbol_ecc(
    gray: np.ndarray, dark_modules: np.ndarray, raw_corners_px: np.ndarray, *,
    max_px_per_module: int = TEMPLATE_PX_PER_MODULE_RANGE[1],
) -> tuple[np.ndarray | None, str]:
    """Refine the outer corners (TL, TR, BR, BL) of any square module-grid symbol printed on a
    light background — a QR symbol or an ArUco marker with its black border — by aligning a
    template of ``dark_modules`` ((n, n) bool, row 0 the printed top) to ``gray`` with
    ``cv2.findTransformECC`` (the module docstring).
    ``max_px_per_module`` caps the template's pixels per module (ECC's cost grows with the
    template's pixel count).

    Returns the refined corners (4, 2), or ``(None, reason)`` when ECC fails, its correlation
    is low or a corner would move more than one module.
    """
    low = min(TEMPLATE_PX_PER_MODULE_RANGE[0], int(max_px_per_module))
    return _refine_ecc(
        gray, np.asarray(dark_modules, dtype=bool), np.asarray(raw_corners_px, dtype=float), (low, int(max_px_per_module))
    )
