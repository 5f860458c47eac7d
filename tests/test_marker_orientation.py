"""Marker corner order against third-party references (issue 23 item 1).

AprilTag: the official images (``../shared/data/apriltag_imgs``, AprilRobotics' own, upright as
printed; see its README) scaled without interpolation, given a white margin, turned 0/90/180/270°
and warped by known homographies. Corner 0 must be the printed top-left and every corner must
sit on the warped truth, for tag36h11, tag16h5 and tag25h9. ArUco: OpenCV is the reference
(its ``generateImageMarker``). ChArUco: boards drawn by OpenCV's own board generator (legacy
and new pattern); the detected corners must be those agvviz's map expansion
(:func:`agvviz.markers.charuco.charuco_marker_corners`) assigns, through the known image
transform. The module grids the renderer draws are compared bit for bit with the official
images.

Tolerances. A wrong corner order moves a corner by a whole tag side (≥ 50 px here); a pixel-
convention slip by 0.5 px. Warped corners (ECC refinement, the default) are checked to 0.4 px:
ECC's own error on these renders is ≈0.02 px median but ≈0.2 px on the magnified side of the
strongest perspective (warp 3, one side 1.5× the other; every refiner is off there by
0.15–0.33 px while the rendered edge sits within 0.005 px of the truth) — max 0.21 px over all
1200 images of bench/bench_marker_orientation.py. 0.4 px is twice that and below the slip; the
pixel convention itself is pinned on unwarped images to 0.02 px.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from agvviz.markers.apriltag import opencv_quarter_turns
from agvviz.markers.aruco import aruco_modules, detect_aruco
from agvviz.markers.dictionary import aruco_dictionary
from agvviz.markers.types import ArucoError
from agvviz.markers.charuco import charuco_marker_corners


def _shared_data() -> Path:
    """``shared/data`` next to the repository (main checkout) or next to the worktree folder."""
    here = Path(__file__).resolve()
    for parent in here.parents[1:4]:
        if (parent / "shared" / "data").is_dir():
            return parent / "shared" / "data"
    return here.parents[2] / "shared" / "data"


APRILTAG_IMGS = _shared_data() / "apriltag_imgs"
#: (OpenCV dictionary, official folder, file prefix)
FAMILIES = [
    ("DICT_APRILTAG_36h11", "tag36h11", "tag36_11_"),
    ("DICT_APRILTAG_16h5", "tag16h5", "tag16_05_"),
    ("DICT_APRILTAG_25h9", "tag25h9", "tag25_09_"),
]
CORNER_TOLERANCE_PX = 0.4
#: Five homographies applied after the turn (image px → image px): a plain scale-down, a shear,
#: two perspectives (one tilting the tag away by ≈45°) and a small tag (≈5 px modules).
WARPS = [
    np.array([[0.8, 0.0, 10.0], [0.0, 0.8, 12.0], [0.0, 0.0, 1.0]]),
    np.array([[0.9, 0.25, 5.0], [-0.1, 0.85, 40.0], [0.0, 0.0, 1.0]]),
    np.array([[1.0, 0.1, 10.0], [0.05, 1.0, 5.0], [4e-4, 2e-4, 1.0]]),
    np.array([[0.7, 0.0, 60.0], [0.0, 1.0, 10.0], [-1e-3, 0.0, 1.0]]),
    np.array([[0.42, 0.05, 30.0], [-0.04, 0.45, 25.0], [1e-4, 1e-4, 1.0]]),
]
SUPERSAMPLE = 8


def _need(path: Path) -> None:
    if not path.is_dir():
        pytest.skip(f"official AprilTag images not found at {path} (see ../shared/data/MANIFEST.md)")


def official(folder: str, prefix: str, tag_id: int) -> np.ndarray:
    """The official image (uint8, 1 px per module, white border included)."""
    path = APRILTAG_IMGS / folder / f"{prefix}{tag_id:05d}.png"
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    gray = image[..., 0] if image.ndim == 3 else image
    if image.ndim == 3 and image.shape[2] == 4:  # transparent pixels are white paper
        gray = np.where(image[..., 3] == 0, 255, gray)
    return np.ascontiguousarray(gray)


def printed(image_1px: np.ndarray, scale: int, margin: int, black_from: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``image_1px`` scaled ×scale (nearest) with a white margin, and the black border's outer
    corners TL, TR, BR, BL in OpenCV pixels (its first black module is ``black_from`` in)."""
    big = cv2.resize(image_1px, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    big = cv2.copyMakeBorder(big, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)
    lo = margin + black_from * scale - 0.5
    hi = margin + (len(image_1px) - black_from) * scale - 0.5
    return big, np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])


def turned(image: np.ndarray, points_px: np.ndarray, quarter_turns: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.rot90(image, k)`` (counter-clockwise) and the points moved with it (OpenCV pixels:
    one counter-clockwise turn maps (x, y) to (y, W − 1 − x))."""
    points = np.asarray(points_px, dtype=float).copy()
    for _ in range(quarter_turns % 4):
        width = image.shape[1]
        points = np.column_stack([points[:, 1], width - 1 - points[:, 0]])
        image = np.rot90(image)
    return np.ascontiguousarray(image), points


def warped(image: np.ndarray, points_px: np.ndarray, H: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``image`` warped by ``H`` as a camera would see it — supersampled ×8 and area-averaged
    (OpenCV's pixel-centre convention kept), blurred σ 0.6 px, noise σ 1 DN — and the points."""
    h, w = image.shape
    corners = cv2.perspectiveTransform(np.array([[[0, 0], [w, 0], [w, h], [0, h]]], dtype=float), H)[0]
    out_w, out_h = int(np.ceil(corners[:, 0].max())) + 20, int(np.ceil(corners[:, 1].max())) + 20
    s = SUPERSAMPLE
    to_fine = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1.0]])
    fine = cv2.warpPerspective(image, to_fine @ H, (out_w * s, out_h * s), flags=cv2.INTER_LINEAR, borderValue=255)
    frame = cv2.resize(fine, (out_w, out_h), interpolation=cv2.INTER_AREA).astype(float)
    frame = cv2.GaussianBlur(frame, (0, 0), 0.6) + np.random.default_rng(seed).normal(0, 1.0, frame.shape)
    truth = cv2.perspectiveTransform(points_px.reshape(1, -1, 2).astype(float), H)[0]
    return np.clip(np.round(frame), 0, 255).astype(np.uint8), truth


def orientation_cases():
    """3 families × 4 turns × 5 warps; the id runs through 0..19 so every official id is used."""
    for name, folder, prefix in FAMILIES:
        for turn in range(4):
            for w in range(len(WARPS)):
                yield pytest.param(name, folder, prefix, turn, w, (5 * turn + w) % 20, id=f"{folder}-rot{90 * turn}-warp{w}")


@pytest.mark.parametrize("name,folder,prefix,turn,warp,tag_id", list(orientation_cases()))
def test_apriltag_corner0_is_printed_top_left(name, folder, prefix, turn, warp, tag_id):
    _need(APRILTAG_IMGS)
    image, truth = printed(official(folder, prefix, tag_id), scale=24, margin=40)
    image, truth = turned(image, truth, turn)
    image, truth = warped(image, truth, WARPS[warp], seed=100 * turn + warp)
    detections = detect_aruco(image, name, refine="ecc")
    assert [d.marker_id for d in detections] == [tag_id]
    corners = detections[0].corners_px
    assert detections[0].refine_method == "ecc", detections[0].refine_note
    # corner 0 is the printed top-left: nearest to its truth of all four
    assert int(np.argmin(np.linalg.norm(truth - corners[0], axis=1))) == 0
    assert np.max(np.linalg.norm(corners - truth, axis=1)) < CORNER_TOLERANCE_PX


@pytest.mark.parametrize("refine", ["none", "subpix", "apriltag"])
@pytest.mark.parametrize("name,folder,prefix", FAMILIES)
def test_apriltag_order_and_pixel_convention_every_refiner(name, folder, prefix, refine):
    """Every refiner keeps the printed order. On a sharp, unwarped image (edges exactly on pixel
    borders) the library's own corners ("none") are at the OpenCV-convention edges within
    0.02 px: a slip of its +0.5 px pixel centres would show as 0.5 px. The refiners are within
    0.3 px (cornerSubPix and the library's edge fit on a blur-free step edge)."""
    _need(APRILTAG_IMGS)
    image, truth = printed(official(folder, prefix, 7), scale=20, margin=30)
    for turn in range(4):
        frame, points = turned(image, truth, turn)
        (detection,) = detect_aruco(frame, name, refine=refine)
        assert detection.marker_id == 7 and detection.refine_method == refine
        tolerance = 0.02 if refine == "none" else 0.3
        assert np.max(np.abs(detection.corners_px - points)) < tolerance, (turn, detection.corners_px, points)


@pytest.mark.parametrize("name,folder,prefix", FAMILIES)
def test_rendered_modules_equal_official_images(name, folder, prefix):
    """The module grid scenarios render (``aruco_modules``) is the official image, bit for bit,
    for all 20 official ids: the renderer draws tags as printed."""
    _need(APRILTAG_IMGS)
    for tag_id in range(20):
        image = official(folder, prefix, tag_id)
        assert np.array_equal(aruco_modules(name, tag_id), image[1:-1, 1:-1] < 128), tag_id
        assert np.all(image[0] == 255) and np.all(image[-1] == 255)  # the white border around


@pytest.mark.parametrize("name", [n for n, _, _ in FAMILIES])
def test_opencv_apriltag_bits_are_a_turned_copy(name):
    """OpenCV's AprilTag bits are the library's, turned (OpenCV 5.0: 180°). Measured, so an
    OpenCV that draws them upright gives 0 and ChArUco boards stay right."""
    dictionary = aruco_dictionary(name)
    k = opencv_quarter_turns(name)
    n = dictionary.markerSize + 2
    for tag_id in range(dictionary.bytesList.shape[0]):
        drawn = cv2.aruco.generateImageMarker(dictionary, tag_id, n, borderBits=1) == 0
        assert np.array_equal(np.rot90(drawn, k), aruco_modules(name, tag_id))


def test_ecc_converges_on_rendered_apriltags():
    """The renderer's modules are the ECC template: a tag drawn from them (as scenarios do),
    warped, is refined by ECC to its drawn corners (order consistent, template upright)."""
    for name, _, _ in FAMILIES:
        modules = aruco_modules(name, 11)
        image_1px = np.pad(np.where(modules, 0, 255).astype(np.uint8), 1, constant_values=255)
        image, truth = printed(image_1px, scale=20, margin=30)
        image, truth = warped(image, truth, WARPS[2], seed=3)
        (detection,) = detect_aruco(image, name, refine="ecc")
        assert detection.marker_id == 11 and detection.refine_method == "ecc", detection.refine_note
        assert np.max(np.linalg.norm(detection.corners_px - truth, axis=1)) < CORNER_TOLERANCE_PX


def test_apriltag_36h10_is_refused():
    with pytest.raises(ArucoError, match="36h10 is not supported"):
        detect_aruco(np.full((64, 64), 255, np.uint8), "DICT_APRILTAG_36h10")
    with pytest.raises(ArucoError, match="36h10 is not supported"):
        aruco_modules("DICT_APRILTAG_36h10", 0)


@pytest.mark.parametrize("name", ["DICT_4X4_50", "DICT_6X6_250", "DICT_ARUCO_ORIGINAL"])
@pytest.mark.parametrize("turn", range(4))
def test_aruco_corner0_is_opencv_top_left(name, turn):
    """ArUco: OpenCV is the reference — corner 0 is the top-left of its generated marker."""
    dictionary = aruco_dictionary(name)
    n = dictionary.markerSize + 2
    tag_id = 17 + turn
    image_1px = np.pad(cv2.aruco.generateImageMarker(dictionary, tag_id, n, borderBits=1), 1, constant_values=255)
    image, truth = printed(image_1px, scale=16, margin=30)
    image, truth = turned(image, truth, turn)
    for w, H in enumerate(WARPS[:4]):
        frame, points = warped(image, truth, H, seed=10 * turn + w)
        (detection,) = detect_aruco(frame, name, refine="ecc")
        assert detection.marker_id == tag_id
        assert int(np.argmin(np.linalg.norm(points - detection.corners_px[0], axis=1))) == 0
        assert np.max(np.linalg.norm(detection.corners_px - points, axis=1)) < CORNER_TOLERANCE_PX


SQUARE_PX, MARGIN_PX = 60, 20


@pytest.mark.parametrize("legacy", [False, True], ids=["new", "legacy"])
@pytest.mark.parametrize("name,marker_px", [("DICT_4X4_50", 36), ("DICT_5X5_100", 42), ("DICT_APRILTAG_36h11", 40)])
def test_charuco_marker_corners_match_opencv_board(name, marker_px, legacy):
    """A ChArUco board drawn by OpenCV's generator (square 60 px, markers a whole number (5–6)
    of px per module at whole-px offsets, so the drawing is exact), turned and warped: every
    detected marker's corners are the ones charuco.charuco_marker_corners assigns, mapped
    board metres → image px. The AprilTag board checks the re-ordering by OpenCV's turn."""
    squares_x, squares_y, square_m = 5, 4, 0.04
    marker_m = square_m * marker_px / SQUARE_PX
    board = cv2.aruco.CharucoBoard((squares_x, squares_y), square_m, marker_m, aruco_dictionary(name))
    board.setLegacyPattern(legacy)
    size = (squares_x * SQUARE_PX + 2 * MARGIN_PX, squares_y * SQUARE_PX + 2 * MARGIN_PX)
    image = board.generateImage(size, marginSize=MARGIN_PX, borderBits=1)
    expected = charuco_marker_corners(squares_x, squares_y, square_m, marker_m, name, legacy_pattern=legacy)
    # board frame (m, origin bottom-left, y up) → OpenCV pixels of the drawing
    px_per_m = SQUARE_PX / square_m
    height_m = squares_y * square_m

    def to_px(points_m: np.ndarray) -> np.ndarray:
        return np.column_stack([MARGIN_PX + points_m[:, 0] * px_per_m - 0.5, MARGIN_PX + (height_m - points_m[:, 1]) * px_per_m - 0.5])

    ids = sorted(expected)
    truth = np.concatenate([to_px(expected[i]) for i in ids])
    for turn, w in [(0, 0), (1, 2), (2, 1), (3, 3)]:
        frame, points = turned(image, truth, turn)
        frame, points = warped(frame, points, WARPS[w], seed=turn)
        detections = {d.marker_id: d for d in detect_aruco(frame, name, refine="ecc")}
        assert sorted(detections) == ids
        for k, marker_id in enumerate(ids):
            corners = detections[marker_id].corners_px
            assert np.max(np.linalg.norm(corners - points[4 * k : 4 * k + 4], axis=1)) < CORNER_TOLERANCE_PX, (turn, marker_id)


def test_library_detectors_free_cleanly(tmp_path):
    """pupil-apriltags 1.0.4 frees a detector's families before the detector, whose destructor
    then reads them: six detectors used and freed crash the interpreter (exit 139, every time on
    the development machine). agvviz's detectors free in the right order: created, used, freed
    (cache cleared) and created again, the process exits 0."""
    import os
    import subprocess
    import sys

    script = tmp_path / "free.py"
    script.write_text(
        "import gc, numpy as np\n"
        "from agvviz.markers.apriltag import _library_detector\n"
        "from agvviz.markers.aruco import aruco_modules\n"
        "tag = np.kron(np.pad(np.where(aruco_modules('DICT_APRILTAG_36h11', 0), 0, 255), 1, constant_values=255), np.ones((20, 20))).astype(np.uint8)\n"
        "for _ in range(2):\n"
        "    for family in ('tag36h11', 'tag16h5', 'tag25h9'):\n"
        "        for refine_edges in (False, True):\n"
        "            _library_detector(family, refine_edges).detect(tag)\n"
        "    _library_detector.cache_clear(); gc.collect()\n"
        "print('ok')\n"
    )
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, str(script)], cwd=root, env={**os.environ, "PYTHONPATH": str(root)},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", (done.returncode, done.stderr[-500:])
