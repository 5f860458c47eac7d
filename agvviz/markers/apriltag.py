"""AprilTag detection and module grids from the AprilTag library itself (``pupil-apriltags``,
the AprilRobotics C library). No file I/O, no printing.

Why not OpenCV's ArUco detector with its ``DICT_APRILTAG_*`` dictionaries: OpenCV 5.0 reports
a printed tag's bottom-right corner first and ``generateImageMarker`` draws the tags turned 180°
(both from the same bit tables, so they agree with each other and not with a printed tag), and a
later OpenCV 5 changes the order (opencv/opencv PR 28823). The AprilTag library is the one that
generated the official tag images; its code tables and its corner order are the reference,
whatever OpenCV is installed (docs/markers.md).

The library's conventions, and what this module turns them into (checked against the official
``apriltag_imgs`` images in tests/test_marker_orientation.py):

- corners: the library returns them in the order printed bottom-left, bottom-right, top-right,
  top-left (its tag frame has y up; "counter-clockwise" in a y-down image) → reversed here to
  agvviz's TL, TR, BR, BL as printed (:mod:`agvviz.conventions`);
- pixels: the library puts a pixel's centre at +0.5 (an edge between pixel columns 99 and 100
  is at x = 100) → 0.5 px is subtracted, OpenCV's convention (centres at integers);
- the corners are the outer corners of the black border (the library's ``tag_size``), as for
  ArUco markers;
- families: OpenCV's names map to the library's (``DICT_APRILTAG_36h11`` → ``tag36h11``);
  ``DICT_APRILTAG_36h10`` is refused: AprilTag 3 dropped tag36h10, so there is neither a code
  table nor an official image to check its printed orientation against.

Refinement (``refine=``): ``"none"`` — the library's quad fitted to the tag's contour pixels
(``refine_edges`` off); ``"subpix"`` — those corners through ``cv2.cornerSubPix`` with the
window, iterations and accuracy OpenCV's ``CORNER_REFINE_SUBPIX`` uses for ArUco markers;
``"apriltag"`` — the library's own edge refinement (``refine_edges`` on); ``"ecc"`` — the tag's
module grid (:func:`apriltag_modules`) aligned to the image from the subpix corners by
:func:`agvviz.markers.ecc.align_symbol_ecc`, falling back to subpix when ECC fails.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from agvviz.errors import InputError
from agvviz.markers.ecc import align_symbol_ecc
from agvviz.markers.types import ArucoDetection

#: OpenCV dictionary name → the AprilTag library's family name.
APRILTAG_FAMILIES = {
    "DICT_APRILTAG_16h5": "tag16h5",
    "DICT_APRILTAG_25h9": "tag25h9",
    "DICT_APRILTAG_36h11": "tag36h11",
}
#: OpenCV AprilTag dictionaries agvviz refuses, with the reason.
UNSUPPORTED_APRILTAG = {
    "DICT_APRILTAG_36h10": (
        "DICT_APRILTAG_36h10 is not supported: AprilTag 3 dropped tag36h10, so its printed "
        "orientation cannot be checked (use DICT_APRILTAG_36h11)"
    ),
}
#: Most bit errors a decoded tag may carry, per family: OpenCV's ArUco budget
#: (``errorCorrectionRate`` 0.6 × the family's correctable bits, (min. Hamming distance − 1) / 2),
#: capped at the 2 bits the library is built to correct. 16h5 (distance 5) gets 1 bit: its
#: 30 codes are few enough that 2 corrected bits make false detections in texture common.
MAX_HAMMING = {"tag16h5": 1, "tag25h9": 2, "tag36h11": 2}
#: Added to the library's pixel coordinates to get OpenCV's (pixel centres at integers).
LIBRARY_TO_OPENCV_PX = -0.5
#: The library's corner order (printed BL, BR, TR, TL) → agvviz's TL, TR, BR, BL.
LIBRARY_TO_AGVVIZ_ORDER = [3, 2, 1, 0]
#: Refinements :func:`detect_apriltags` accepts.
APRILTAG_REFINE_METHODS = ("ecc", "subpix", "none", "apriltag")


class AprilTagError(InputError):
    """An AprilTag family agvviz cannot detect, or the AprilTag library missing."""


def is_apriltag_dictionary(name: object) -> bool:
    """True for an OpenCV AprilTag dictionary name (``DICT_APRILTAG_*``), supported or not."""
    return isinstance(name, str) and name.startswith("DICT_APRILTAG_")


def apriltag_family(name: str) -> str:
    """The library's family name of OpenCV dictionary ``name``; :class:`AprilTagError` for an
    unsupported one."""
    if name in UNSUPPORTED_APRILTAG:
        raise AprilTagError(UNSUPPORTED_APRILTAG[name])
    if name not in APRILTAG_FAMILIES:
        raise AprilTagError(f"unknown AprilTag dictionary {name!r}; valid: {', '.join(APRILTAG_FAMILIES)}")
    return APRILTAG_FAMILIES[name]


@functools.lru_cache(maxsize=8)
def _library_detector(family: str, refine_edges: bool):
    try:
        import pupil_apriltags
    except ImportError:  # pragma: no cover - a declared dependency
        raise AprilTagError("AprilTag detection needs the pupil-apriltags package (pip install pupil-apriltags)") from None

    class Detector(pupil_apriltags.Detector):
        """pupil-apriltags 1.0.4's ``__del__`` frees the families before the detector, whose
        destructor then touches them (apriltag_detector_clear_families → quick_decode_uninit):
        a use-after-free that aborted the interpreter at exit ("corrupted size vs. prev_size").
        Free them in the right order."""

        def __del__(self):
            if getattr(self, "tag_detector_ptr", None) is None:
                return
            self.libc.apriltag_detector_destroy.restype = None
            self.libc.apriltag_detector_destroy(self.tag_detector_ptr)
            self.tag_detector_ptr = None
            for name, family_ptr in self.tag_families.items():
                destroy = getattr(self.libc, f"{name}_destroy")
                destroy.restype = None
                destroy(family_ptr)
            self.tag_families = {}

    # Full resolution (quad_decimate 1): decimating halves the corner precision of small tags.
    # One thread: detection workers are processes already.
    return Detector(
        families=family, nthreads=1, quad_decimate=1.0, quad_sigma=0.0, refine_edges=int(refine_edges)
    )


@functools.lru_cache(maxsize=8)
def _module_table(name: str) -> np.ndarray:
    """Dark modules of every code of the family, (ncodes, n + 2, n + 2) bool, row 0 the printed
    top, the one-module black border included — drawn as the library's ``apriltag_to_image``
    draws the official images (bit i of the code, most significant first, is white at
    (bit_x[i], bit_y[i]) counted from the black border's outer corner)."""
    family_name = apriltag_family(name)
    family = _library_detector(family_name, True).tag_families[family_name].contents
    if family.reversed_border:  # pragma: no cover - only the classic families are mapped
        raise AprilTagError(f"{name}: families with a reversed border are not supported")
    width = int(family.width_at_border)
    nbits = int(family.nbits)
    bit_x = np.array([family.bit_x[i] for i in range(nbits)])
    bit_y = np.array([family.bit_y[i] for i in range(nbits)])
    table = np.ones((int(family.ncodes), width, width), dtype=bool)
    for index in range(int(family.ncodes)):
        code = int(family.codes[index])
        white = np.array([(code >> (nbits - 1 - i)) & 1 for i in range(nbits)], dtype=bool)
        table[index, bit_y[white], bit_x[white]] = False
    table.setflags(write=False)
    return table


def apriltag_code_count(name: str) -> int:
    """Number of ids of AprilTag dictionary ``name``."""
    return len(_module_table(name))


def apriltag_modules(name: str, marker_id: int) -> np.ndarray:
    """Dark modules ((n + 2)², bool, row 0 the printed top, black border included) of tag
    ``marker_id``, from the AprilTag library's code table."""
    table = _module_table(name)
    if not 0 <= int(marker_id) < len(table):
        raise AprilTagError(f"marker id {marker_id} is outside {name} (ids 0..{len(table) - 1})")
    return table[int(marker_id)].copy()


@functools.lru_cache(maxsize=8)
def opencv_quarter_turns(name: str) -> int:
    """Quarter turns k (counter-clockwise, ``np.rot90``) that take the tags OpenCV's
    ``generateImageMarker`` draws for dictionary ``name`` to the printed tags (2 on OpenCV 5.0;
    0 for an OpenCV that draws them upright). Measured on this OpenCV, not assumed: OpenCV's
    corner 0 of a tag is the top-left of its own drawing, so its corners rolled by this many
    places are the printed TL, TR, BR, BL (used for ChArUco boards drawn by OpenCV)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
    n = dictionary.markerSize + 2
    ids = range(min(8, apriltag_code_count(name)))
    drawn = [cv2.aruco.generateImageMarker(dictionary, i, n, borderBits=1) == 0 for i in ids]
    for k in range(4):
        if all(np.array_equal(np.rot90(d, k), apriltag_modules(name, i)) for i, d in zip(ids, drawn)):
            return k
    raise AprilTagError(f"OpenCV's {name} bits match the AprilTag library's code table in no orientation")


def _subpix(gray: np.ndarray, corners_px: np.ndarray, n_modules: int) -> np.ndarray | None:
    """OpenCV's ArUco ``CORNER_REFINE_SUBPIX`` on ``corners_px``: window half-size
    ``relativeCornerRefinmentWinSize`` × the module size, at most ``cornerRefinementWinSize``."""
    params = cv2.aruco.DetectorParameters()
    side_px = float(np.mean(np.linalg.norm(np.roll(corners_px, -1, axis=0) - corners_px, axis=1)))
    window = max(1, round(params.relativeCornerRefinmentWinSize * side_px / n_modules))
    window = min(window, params.cornerRefinementWinSize)
    criteria = (
        cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS,
        params.cornerRefinementMaxIterations, params.cornerRefinementMinAccuracy,
    )
    try:
        refined = cv2.cornerSubPix(gray, corners_px.astype(np.float32).reshape(-1, 1, 2), (window, window), (-1, -1), criteria)
    except cv2.error:
        return None
    refined = refined.reshape(4, 2).astype(float)
    return refined if np.all(np.isfinite(refined)) else None


def detect_apriltags(gray: np.ndarray, dictionary_name: str, refine: str = "ecc") -> list:
    """Every tag of AprilTag dictionary ``dictionary_name`` in the uint8 gray image, as
    :class:`agvviz.markers.types.ArucoDetection` (corners TL, TR, BR, BL as printed, OpenCV
    pixels, outer corners of the black border), refined by ``refine`` (module docstring)."""
    if refine not in APRILTAG_REFINE_METHODS:
        raise ValueError(f"unknown refine method {refine!r}; valid: {', '.join(APRILTAG_REFINE_METHODS)}")
    family = apriltag_family(dictionary_name)
    image = np.ascontiguousarray(gray, dtype=np.uint8)
    found = _library_detector(family, refine == "apriltag").detect(image)
    n_modules = _module_table(dictionary_name).shape[1]
    detections = []
    for tag in sorted(found, key=lambda t: t.tag_id):
        if tag.hamming > MAX_HAMMING[family]:
            continue
        raw = np.asarray(tag.corners, dtype=float)[LIBRARY_TO_AGVVIZ_ORDER] + LIBRARY_TO_OPENCV_PX
        detection = ArucoDetection(int(tag.tag_id), raw.copy(), raw, refine)
        if refine in ("subpix", "ecc"):
            subpix = _subpix(image, raw, n_modules)
            if subpix is None:
                detection.refine_method, detection.refine_ok = "none", False
                detection.refine_note = "cornerSubPix failed; kept the library's corners"
            else:
                detection.corners_px, detection.refine_method = subpix, "subpix"
        if refine == "ecc":
            refined, note = align_symbol_ecc(image, apriltag_modules(dictionary_name, tag.tag_id), detection.corners_px)
            if refined is None:
                detection.refine_ok = False
                detection.refine_note = f"ecc: {note}; kept {detection.refine_method}"
            else:
                detection.corners_px, detection.refine_method = refined, "ecc"
                detection.refine_ok, detection.refine_note = True, ""
        detections.append(detection)
    return detections
