"""QR code detection and decoding (zxing-cpp, OpenCV as the fallback) and sub-pixel corner
refinement (OpenCV). No file I/O, no printing.

Detection: ``zxingcpp.read_barcodes`` (QR Code format only) finds and decodes the codes first;
it decodes far more real photographs than OpenCV (DESIGN §9: 20 of 20 on zxing's ``qrcode-1``
against OpenCV's 12) and takes a few milliseconds on a 1280×1024 frame. Its corner positions
are integers in the pixel-corner convention (the image's outer edge at 0), so 0.5 px is
subtracted to get OpenCV's pixel-centre convention. Only when zxing-cpp decodes nothing do
OpenCV's detectors run (``QRCodeDetector.detectAndDecodeBytesMulti``, then
``detectAndDecodeBytes`` and ``QRCodeDetectorAruco``); they also report codes found but not
decoded. Payloads are taken as bytes in every path; bytes that are not UTF-8 text are kept in
``QrDetection.payload_bytes`` (``text`` None) for the strict payload parser to refuse — never an
exception.

Input frames come from an ideal pinhole camera (the pipeline undistorts first). Corners are in
OpenCV pixel coordinates (integer coordinates at pixel centres, the image's outer edge at -0.5)
and in the order of the code as printed: TL, TR, BR, BL, where TL, TR and BL carry the finder
patterns. They are the symbol's outer corners (the quiet zone is not part of the symbol).

Refinement methods (``refine=``):

``"ecc"``
    Needs the decoded text. Template modules: the text re-encoded with ``cv2.QRCodeEncoder``
    (OpenCV's default parameters first, then the other error-correction levels), checked
    against the image by sampling it at the module centres the raw corners predict; when no
    re-encoding matches (a code printed by another encoder, with another mask or mode), the
    module grid the detector read while decoding (OpenCV's binarised code; for zxing-cpp, the
    image sampled at the module centres of the version zxing-cpp reports, thresholded with
    Otsu's method), checked the same way (``refine_note`` says so). The template is the symbol plus a one-module light border, at about the image's
    pixels per module; a homography initialised from the detector's corners is aligned to a
    local crop with ``cv2.findTransformECC(MOTION_HOMOGRAPHY)``, and the refined corners are the
    template's symbol corners mapped through it (:func:`agvviz.markers.ecc.align_symbol_ecc`).
``"subpix"``
    ``cv2.cornerSubPix`` on the three finder-pattern corners (TL, TR, BL: each is the outer
    corner of a dark 7×7 finder square against the light quiet zone), with a window of about
    0.6 modules so the finder's inner edges stay outside it. The BR corner has no finder
    pattern (its module may be light, and when it is dark the neighbouring modules pull
    cornerSubPix off by up to 4 px on rendered codes), so BR is left as the detector gave it.
    Use ``"ecc"`` when all four corners matter.
``"none"``
    The detector's corners.

When the requested method fails (ECC does not converge, its correlation is low, a corner moves
more than :data:`~agvviz.markers.ecc.MAX_REFINE_SHIFT_PX` / :data:`~agvviz.markers.ecc.MAX_REFINE_SHIFT_MODULES`, or the code was not decoded), the next method down the
list ecc → subpix → none is applied; ``refine_method`` says what was applied, ``refine_ok`` is
False and ``refine_note`` says why.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import zxingcpp

from agvviz.markers.ecc import accept_shift, align_symbol_ecc, error_line, mean_side_px

#: Accepted values of ``refine``, from most to least accurate.
REFINE_METHODS = ("ecc", "subpix", "none")
#: Smallest correlation between a re-encoded symbol and the image sampled at module centres.
TEMPLATE_MIN_CORRELATION = 0.6
#: Correlation at which a re-encoded symbol is taken without trying further levels.
TEMPLATE_GOOD_CORRELATION = 0.8
#: Module count assumed for sizing the cornerSubPix window when the code has no template
#: (version 6; a larger guess only makes the window smaller).
ASSUMED_MODULES_UNDECODED = 41

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-3)
_CORRECTION_LEVELS = (
    cv2.QRCODE_ENCODER_CORRECT_LEVEL_L,  # OpenCV's default
    cv2.QRCODE_ENCODER_CORRECT_LEVEL_M,
    cv2.QRCODE_ENCODER_CORRECT_LEVEL_Q,
    cv2.QRCODE_ENCODER_CORRECT_LEVEL_H,
)


@dataclass
class QrDetection:
    """One QR code found in a frame.

    Attributes
    ----------
    text : str or None
        Decoded text, None when the code was found but not decoded — or when its payload is
        not UTF-8 text (then ``payload_bytes`` holds it).
    corners_px : np.ndarray, shape (4, 2)
        Refined symbol corners TL, TR, BR, BL (as printed), OpenCV pixel convention.
    raw_corners_px : np.ndarray, shape (4, 2)
        The corners as OpenCV's detector returned them.
    refine_method : str
        What was applied to get ``corners_px``: ``"ecc"``, ``"subpix"`` or ``"none"``.
    refine_ok : bool
        True when the requested refinement was applied; False after a fallback.
    refine_note : str
        Why a fallback happened, or that the ECC template came from the detector's module grid
        rather than the re-encoded text; empty otherwise.
    n_modules : int or None
        Modules per side of the symbol (21 + 4·(version − 1)) when its template is known.
    payload_bytes : bytes or None
        The decoded payload bytes when they are not UTF-8 text (``text`` is None then): a
        code on a floor is untrusted input, and binary or Shift-JIS payloads exist in the wild
        (OpenCV's text API raises ``UnicodeDecodeError`` on them); None otherwise.
    symbol : np.ndarray, shape (n, n), bool, or None
        The module grid the corners were refined against (True for dark modules, row 0 the
        printed top; read-only when it is the cached re-encoding): what
        :mod:`agvviz.markers.tracking` aligns in later frames. None when no template was
        found or ``refine="none"``.
    """

    text: str | None
    corners_px: np.ndarray
    raw_corners_px: np.ndarray
    refine_method: str
    refine_ok: bool
    refine_note: str = ""
    n_modules: int | None = None
    payload_bytes: bytes | None = None
    symbol: np.ndarray | None = None


def detect_qr_codes(
    gray: np.ndarray, refine: str = "ecc", *, fallback_detectors: bool = True
) -> list[QrDetection]:
    """Detect, decode and refine every QR code in a grayscale frame.

    Parameters
    ----------
    gray : np.ndarray, shape (H, W), uint8
        Undistorted grayscale frame.
    refine : {"ecc", "subpix", "none"}
        Corner refinement (module docstring).
    fallback_detectors : bool
        When zxing-cpp decodes nothing, run OpenCV's ``QRCodeDetector.detectAndDecodeBytesMulti``
        and, when that finds nothing or leaves a code undecoded, ``detectAndDecodeBytes`` and
        ``QRCodeDetectorAruco``, keeping what they find. Costs extra time on such frames (and
        on frames without codes: OpenCV takes ≈45 ms where zxing-cpp takes a few).

    Returns
    -------
    list of QrDetection
        Empty when nothing was found. Never raises on image content (nor on payload bytes that
        are not UTF-8: see ``QrDetection.payload_bytes``).

    Raises
    ------
    ValueError
        ``gray`` is not a non-empty 2-D uint8 array, or ``refine`` is unknown.
    """
    check_gray(gray)
    if refine not in REFINE_METHODS:
        raise ValueError(f"refine must be one of {REFINE_METHODS}, got {refine!r}")
    gray = np.ascontiguousarray(gray)
    return [_refine(gray, code, refine) for code in _find_codes(gray, fallback_detectors)]


def check_gray(gray: np.ndarray) -> None:
    """Raise ``ValueError`` unless ``gray`` is a 2-D uint8 image large enough for a QR code."""
    if not isinstance(gray, np.ndarray) or gray.dtype != np.uint8 or gray.ndim != 2:
        description = (
            f"{gray.dtype} array of shape {gray.shape}"
            if isinstance(gray, np.ndarray)
            else type(gray).__name__
        )
        raise ValueError(
            f"gray must be a 2-D uint8 grayscale image, got {description}; "
            "convert with cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) first"
        )
    if gray.shape[0] < 21 or gray.shape[1] < 21:
        raise ValueError(f"gray is too small to hold a QR code: shape {gray.shape}")


def qr_modules(text: str, correction_level: int = cv2.QRCODE_ENCODER_CORRECT_LEVEL_L) -> np.ndarray:
    """The symbol ``cv2.QRCodeEncoder`` makes for ``text``, without its quiet zone.

    Parameters
    ----------
    text : str
        Payload to encode (OpenCV's default mode selection).
    correction_level : int
        ``cv2.QRCODE_ENCODER_CORRECT_LEVEL_*``; L is OpenCV's default.

    Returns
    -------
    np.ndarray, shape (n, n), bool
        True for dark modules; n = 17 + 4·version.

    Raises
    ------
    cv2.error
        When OpenCV cannot encode ``text``.
    """
    return _encoded_symbol(text, correction_level).copy()


@functools.lru_cache(maxsize=256)
def _encoded_symbol(text: str, correction_level: int) -> np.ndarray:
    """Cached :func:`qr_modules` (one encode costs ~15 ms; a replay sees the same codes often)."""
    params = cv2.QRCodeEncoder.Params()
    params.correction_level = correction_level
    image = cv2.QRCodeEncoder.create(params).encode(text)
    dark = image < 128
    rows = np.flatnonzero(dark.any(axis=1))
    cols = np.flatnonzero(dark.any(axis=0))
    symbol = dark[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    symbol.setflags(write=False)
    return symbol


@dataclass
class _RawCode:
    """What a detector reported for one code."""

    data: bytes | str | None  # the decoded payload (bytes; text is taken as is), None when not decoded
    corners_px: np.ndarray  # (4, 2) TL, TR, BR, BL
    modules_seen: np.ndarray | None  # (n, n) bool, dark modules as the detector read them

    @property
    def text(self) -> str | None:
        """The payload as UTF-8 text; None when not decoded or not UTF-8."""
        if self.data is None or isinstance(self.data, str):
            return self.data
        try:
            return self.data.decode("utf-8")
        except UnicodeDecodeError:
            return None


def _find_codes(gray: np.ndarray, fallback_detectors: bool) -> list[_RawCode]:
    """Every code in the frame: zxing-cpp's decoded codes; OpenCV's detectors only when
    zxing-cpp decoded nothing (primary detector first, fallbacks merged in)."""
    found = _run_zxing(gray)
    if found or not fallback_detectors:
        return found
    # The *Bytes* variants: the text variants raise UnicodeDecodeError on non-UTF-8 payloads.
    found = _run_detector(cv2.QRCodeDetector().detectAndDecodeBytesMulti, gray)
    if found and all(code.data is not None for code in found):
        return found
    single = cv2.QRCodeDetector()
    for detector in (
        lambda image: _single_as_multi(single, image),
        cv2.QRCodeDetectorAruco().detectAndDecodeBytesMulti,
    ):
        for code in _run_detector(detector, gray):
            if code.data is None:
                continue
            centre = tuple(float(c) for c in code.corners_px.mean(axis=0))
            same = [
                i
                for i, known in enumerate(found)
                if cv2.pointPolygonTest(known.corners_px.astype(np.float32), centre, False) >= 0
            ]
            if not same:
                found.append(code)
            elif found[same[0]].data is None:
                found[same[0]] = code
    return found


#: zxing-cpp reports corners in the pixel-corner convention (the image's outer edge at 0);
#: OpenCV's puts integer coordinates at pixel centres (outer edge at -0.5) — DESIGN §9.
ZXING_TO_OPENCV_PX = -0.5


def _run_zxing(gray: np.ndarray) -> list[_RawCode]:
    """The QR codes zxing-cpp decodes (checksum-valid only), corners in OpenCV's convention.

    Codes are printed upright or in any rotation on a floor; QR detection in zxing-cpp does
    not need ``try_rotate`` for that (it is for 1-D codes). Inverted (light-on-dark) codes are
    not searched for. Never raises on image content.
    """
    try:
        barcodes = zxingcpp.read_barcodes(
            gray, formats=zxingcpp.BarcodeFormat.QRCode, try_rotate=False, try_invert=False
        )
    except (RuntimeError, ValueError, TypeError):
        return []
    found = []
    for barcode in barcodes:
        if not barcode.valid:
            continue
        position = barcode.position
        corners_px = np.array(
            [[p.x, p.y] for p in (position.top_left, position.top_right, position.bottom_right, position.bottom_left)],
            dtype=float,
        ) + ZXING_TO_OPENCV_PX
        if not (np.all(np.isfinite(corners_px)) and _is_convex(corners_px)):
            continue
        found.append(
            _RawCode(bytes(barcode.bytes), corners_px, _sampled_module_grid(gray, corners_px, _zxing_modules(barcode)))
        )
    return found


def _zxing_modules(barcode) -> int | None:
    """Modules per side (17 + 4·version) of a zxing-cpp QR result, None when not reported."""
    try:
        version = int(barcode.extra.get("Version", ""))
    except (AttributeError, TypeError, ValueError):
        return None
    return 17 + 4 * version if 1 <= version <= 40 else None


def _sampled_module_grid(gray: np.ndarray, corners_px: np.ndarray, n: int | None) -> np.ndarray | None:
    """The dark modules of an ``n``×``n`` symbol with corners ``corners_px``, read from the
    image at the module centres and thresholded with Otsu's method; None when ``n`` is unknown
    or the samples have no contrast. (zxing-cpp does not return the grid it decoded.)"""
    if n is None:
        return None
    samples = _module_samples(gray, corners_px, n).reshape(-1, 1)
    if int(samples.max()) - int(samples.min()) < 10:
        return None
    threshold, _ = cv2.threshold(samples, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return (samples.reshape(n, n) <= threshold).copy()


def _module_samples(gray: np.ndarray, corners_px: np.ndarray, n: int) -> np.ndarray:
    """The image (bilinear, uint8) at the centres of the ``n``×``n`` modules of a symbol with
    corners ``corners_px`` (TL, TR, BR, BL), row-major from the printed top-left: shape (n·n,)."""
    H_image_module = cv2.getPerspectiveTransform(
        np.array([[0, 0], [n, 0], [n, n], [0, n]], dtype=np.float32), corners_px.astype(np.float32)
    )
    centres = np.stack(np.meshgrid(np.arange(n), np.arange(n)), axis=-1).reshape(1, -1, 2) + 0.5
    centres_px = cv2.perspectiveTransform(centres.astype(np.float32), H_image_module)
    return cv2.remap(
        gray, centres_px[..., 0], centres_px[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    ).reshape(-1)


def _single_as_multi(detector: cv2.QRCodeDetector, gray: np.ndarray):
    """``detectAndDecodeBytes`` with ``detectAndDecodeBytesMulti``'s return layout."""
    text, points, straight_code = detector.detectAndDecodeBytes(gray)
    if points is None:
        return False, (), None, None
    return True, (text,), points.reshape(1, 4, 2), (straight_code,)


def _run_detector(detect_and_decode_multi, gray: np.ndarray) -> list[_RawCode]:
    try:
        ok, texts, points, straight_codes = detect_and_decode_multi(gray)
    except (cv2.error, UnicodeDecodeError):
        return []
    if not ok or points is None:
        return []
    corners_all = np.asarray(points, dtype=float).reshape(-1, 4, 2)
    if straight_codes is None or len(straight_codes) != len(corners_all):
        straight_codes = [None] * len(corners_all)
    found = []
    for text, corners_px, straight_code in zip(texts, corners_all, straight_codes):
        if np.all(np.isfinite(corners_px)) and _is_convex(corners_px):
            found.append(_RawCode(bytes(text) if text else None, corners_px, _module_grid(straight_code)))
    return found


def _module_grid(straight_code: np.ndarray | None) -> np.ndarray | None:
    """The detector's binarised code as a dark-module grid, if it has a QR symbol's size."""
    if straight_code is None or straight_code.ndim != 2:
        return None
    n = straight_code.shape[0]
    if straight_code.shape != (n, n) or n < 21 or (n - 17) % 4 != 0:
        return None
    return straight_code < 128


def _is_convex(corners_px: np.ndarray) -> bool:
    edges = np.roll(corners_px, -1, axis=0) - corners_px
    following = np.roll(edges, -1, axis=0)
    turns = edges[:, 0] * following[:, 1] - edges[:, 1] * following[:, 0]
    return bool(np.all(turns > 0) or np.all(turns < 0))


def _refine(gray: np.ndarray, code: _RawCode, refine: str) -> QrDetection:
    """Apply ``refine``, falling back ecc → subpix → none."""
    notes = []
    symbol, symbol_note = _symbol_for(gray, code) if refine != "none" else (None, "")
    corners_px = None
    method = refine
    if method == "ecc":
        if symbol is None:
            notes.append(f"ecc: {symbol_note}")
            method = "subpix"
        else:
            if symbol_note:
                notes.append(symbol_note)
            corners_px, note = align_symbol_ecc(gray, symbol, code.corners_px)
            if corners_px is None:
                notes.append(f"ecc: {note}")
                method = "subpix"
    if method == "subpix":
        corners_px, note = _refine_subpix(gray, code.corners_px, symbol)
        if corners_px is None:
            notes.append(f"subpix: {note}")
            method = "none"
    if method == "none":
        corners_px = code.corners_px.copy()
    return QrDetection(
        text=code.text,
        corners_px=corners_px,
        raw_corners_px=code.corners_px,
        refine_method=method,
        refine_ok=method == refine,
        refine_note="; ".join(notes),
        n_modules=len(symbol) if symbol is not None else None,
        payload_bytes=code.data if code.data is not None and code.text is None else None,
        symbol=symbol,
    )


def _symbol_for(gray: np.ndarray, code: _RawCode) -> tuple[np.ndarray | None, str]:
    """The module grid of a decoded code, checked against the image, and a note on its source.

    First choice: ``text`` re-encoded by OpenCV (exact; error-correction levels tried in order,
    OpenCV's default L first; the first correlating at ``TEMPLATE_GOOD_CORRELATION`` wins, else
    the best above ``TEMPLATE_MIN_CORRELATION``). Second: the grid the detector read while
    decoding (codes printed by other encoders use other masks or modes), if it correlates.
    A payload that is not UTF-8 text cannot be re-encoded: only the detector's grid is tried.
    """
    if code.data is None:
        return None, "code not decoded, no template"
    best_symbol, best_correlation = None, TEMPLATE_MIN_CORRELATION
    for level in _CORRECTION_LEVELS if code.text is not None else ():
        try:
            symbol = _encoded_symbol(code.text, level)
        except cv2.error:
            break
        correlation = module_correlation(gray, symbol, code.corners_px)
        if correlation >= TEMPLATE_GOOD_CORRELATION:
            return symbol, ""
        if correlation > best_correlation:
            best_symbol, best_correlation = symbol, correlation
    if best_symbol is not None:
        return best_symbol, ""
    if code.modules_seen is not None:
        if module_correlation(gray, code.modules_seen, code.corners_px) > TEMPLATE_MIN_CORRELATION:
            return code.modules_seen, "template from the detector's module grid (re-encoding differs)"
    return None, "no template: neither re-encoding nor the detector's grid matches the image"


def module_correlation(gray: np.ndarray, symbol: np.ndarray, raw_corners_px: np.ndarray) -> float:
    """Correlation of module darkness with the image sampled at the predicted module centres.

    ``symbol`` (n, n) bool, True dark; ``raw_corners_px`` (4, 2) the symbol's corners TL, TR,
    BR, BL. 1 for a perfect match; a wrong version or mask correlates only through the shared
    finder patterns (≈0.2); 0 when the samples or the symbol have no contrast.
    """
    return module_agreement(gray, symbol, raw_corners_px)[0]


def module_agreement(gray: np.ndarray, symbol: np.ndarray, corners_px: np.ndarray) -> tuple[float, float]:
    """How well the image at the module centres of a symbol with corners ``corners_px`` (TL,
    TR, BR, BL) matches ``symbol`` ((n, n) bool, True dark): (correlation, mismatch fraction).

    The correlation is :func:`module_correlation`'s. The mismatch fraction is the share of
    modules read the other way: each sample is called dark when it is below the midpoint of the
    mean sample of the symbol's dark modules and that of its light modules (1.0 when the dark
    modules are not darker). Two symbols of different payloads differ in at least one module
    per differing Reed–Solomon codeword and in at least (error-correction codewords per block
    + 1) codewords of a block (same version, level and mask; another mask changes far more) —
    in many more modules in practice: at least 6.8 % between any two codes of the default
    ``qr_floor`` scene, 9 % between neighbours Q014 and Q015; a symbol 9 % off still correlates
    at 0.81. The true symbol at ECC-refined corners mismatches in no module on qr_floor frames.
    """
    samples = _module_samples(gray, corners_px, len(symbol)).astype(float)
    darkness = symbol.reshape(-1)
    if samples.std() == 0 or darkness.all() or not darkness.any():
        return 0.0, 1.0
    correlation = -float(np.corrcoef(samples, darkness.astype(float))[0, 1])
    dark_mean, light_mean = samples[darkness].mean(), samples[~darkness].mean()
    if dark_mean >= light_mean:
        return correlation, 1.0
    read_dark = samples < 0.5 * (dark_mean + light_mean)
    return correlation, float(np.mean(read_dark != darkness))


def _refine_subpix(
    gray: np.ndarray, raw_corners_px: np.ndarray, symbol: np.ndarray | None
) -> tuple[np.ndarray | None, str]:
    """cornerSubPix on the finder corners TL, TR, BL; BR stays as detected. Or (None, reason).

    The window half-size is 0.6 modules so the finder's inner edges (one module in) stay out.
    """
    modules = len(symbol) if symbol is not None else ASSUMED_MODULES_UNDECODED
    half_window = int(np.clip(round(0.6 * mean_side_px(raw_corners_px) / modules), 2, 10))
    finder_index = [0, 1, 3]
    initial = raw_corners_px[finder_index].astype(np.float32).reshape(-1, 1, 2)
    try:
        refined = cv2.cornerSubPix(
            gray, initial, (half_window, half_window), (-1, -1), _SUBPIX_CRITERIA
        )
    except cv2.error as exc:
        return None, f"cornerSubPix failed ({error_line(exc)})"
    corners_px = raw_corners_px.copy()
    corners_px[finder_index] = refined.reshape(-1, 2)
    return accept_shift(corners_px, raw_corners_px, mean_side_px(raw_corners_px) / modules)


#: Corners of one finder pattern in module units from its own top-left corner (x right, y
#: down): the dark 7×7 square's outer corners, the inner edge of its dark ring (5×5), and the
#: dark 3×3 core — 12 L-shaped corners, each at least one module from any other edge.
FINDER_CORNER_MODULES = np.array(
    [[0, 0], [7, 0], [7, 7], [0, 7], [1, 1], [6, 1], [6, 6], [1, 6], [2, 2], [5, 2], [5, 5], [2, 5]], dtype=float
)
#: Smallest module size (px) at which finder corners are measured: the cornerSubPix window must
#: stay within half a module of its corner.
FINDER_MIN_MODULE_PX = 5.0
#: A finder corner that moves further than this (modules) from where the symbol's corners
#: predict it is dropped.
FINDER_MAX_SHIFT_MODULES = 0.35


def finder_corners(
    gray: np.ndarray, corners_px: np.ndarray, n_modules: int
) -> tuple[np.ndarray, np.ndarray]:
    """The corners of the three finder patterns, each measured on its own with cornerSubPix.

    Every corner is predicted from the symbol's corners (``corners_px``, TL, TR, BR, BL; a
    homography of the module grid) and refined with ``cv2.cornerSubPix`` in a window of
    0.4 module half-width, so each uses only the pixels around itself: the measurements of
    different corners share no pixels (independent sensor noise). The three corners that are
    the symbol's own vertices (TL, TR, BL) are left out — they are measured already.

    Parameters
    ----------
    gray : (H, W) uint8 undistorted frame.
    corners_px : (4, 2) refined symbol corners.
    n_modules : modules per side (:attr:`QrDetection.n_modules`).

    Returns
    -------
    (points_px (M, 2), points_module (M, 2)): pixels and module coordinates (x right, y down
    from the symbol's TL corner, the symbol spans 0..n_modules), M ≤ 33; empty (0, 2) arrays
    when modules are smaller than :data:`FINDER_MIN_MODULE_PX`.
    """
    n = float(n_modules)
    module_px = mean_side_px(corners_px) / n
    empty = np.zeros((0, 2))
    if module_px < FINDER_MIN_MODULE_PX:
        return empty, empty
    origins = ((0.0, 0.0), (n - 7.0, 0.0), (0.0, n - 7.0))  # TL, TR, BL finder patterns
    vertices = {(0.0, 0.0), (n, 0.0), (0.0, n)}
    modules = np.array(
        [c + o for o in origins for c in FINDER_CORNER_MODULES if tuple(c + o) not in vertices]
    )
    H_image_module = cv2.getPerspectiveTransform(
        np.array([[0, 0], [n, 0], [n, n], [0, n]], dtype=np.float32), corners_px.astype(np.float32)
    )
    predicted = cv2.perspectiveTransform(modules.reshape(1, -1, 2).astype(np.float64), H_image_module).reshape(-1, 2)
    half_window = int(np.clip(np.floor(0.4 * module_px), 2, 10))
    try:
        refined = cv2.cornerSubPix(
            gray, predicted.astype(np.float32).reshape(-1, 1, 2), (half_window, half_window), (-1, -1),
            _SUBPIX_CRITERIA,
        ).reshape(-1, 2).astype(float)
    except cv2.error:
        return empty, empty
    keep = np.all(np.isfinite(refined), axis=1) & (
        np.linalg.norm(refined - predicted, axis=1) <= FINDER_MAX_SHIFT_MODULES * module_px
    )
    return refined[keep], modules[keep]
