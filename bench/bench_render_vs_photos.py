"""The renderer checked against real photographs (issue 14).

Data: ``../shared/data/opencv_contrib_aruco/`` (``/work/shared/data/MANIFEST.md``): ``img_00..03.jpg``,
640×480 photos of a ChArUco board 5×7, square 0.04 m, marker 0.02 m, DICT_6X6_250, and the
calibration made from them, ``tutorial_camera_charuco.yml``.

For each photo: ArUco markers are detected with OpenCV (``ArucoDetector``, no corner
refinement) and their corners taken (a) as OpenCV gives them ("plain") and (b) refined by
agvviz's ECC template alignment (:func:`agvviz.markers.ecc.align_symbol_ecc` with the marker's
bits, as :func:`agvviz.markers.aruco.detect_aruco` does). The corners are undistorted with the
calibration, and for each marker a homography board plane → image is fitted (least squares) to
the corners of the *other* markers; the residual is the distance of this marker's four corners
from the homography's prediction (pixels). The board pose is estimated from the photo
(``solvePnP`` on the ChArUco chessboard corners), and the same board — one printed label:
the board drawn at one texel per 2.5 mm module on an A4 sheet, on a floor of the photo's wood
grey — is rendered at that pose with the photo's calibration (distortion included) by
:mod:`agvviz.sim.render` + :mod:`agvviz.sim.imaging`, under ``ideal``
(:data:`~agvviz.sim.imaging.IDEAL_IMAGING`: render_frame's defaults) and ``typical``
(:data:`~agvviz.sim.imaging.TYPICAL_IMAGING`); the same residual is measured on the renders
(``RENDERS_PER_PHOTO`` seeds each). Printed: median, RMS and p90 of the residuals, real vs
rendered, per refiner, and the ratio of the medians render/real (target: 0.7–1.3). Then the real
corners' error split into an independent and a per-marker-corner systematic part
(:func:`corner_error_components_px`: what ``agvviz audit``'s ``corner_bias_px`` default rests on).

Run: ``.venv/bin/python bench/bench_render_vs_photos.py`` (≈1 min).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.markers.aruco import aruco_modules
from agvviz.markers.ecc import align_symbol_ecc
from agvviz.sim import imaging
from agvviz.sim.render import FloorCode, FloorScene, render_irradiance

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "opencv_contrib_aruco"
PHOTOS = [DATA / f"img_0{i}.jpg" for i in range(4)]
CALIBRATION = DATA / "tutorial_camera_charuco.yml"
DICTIONARY = "DICT_6X6_250"
SQUARES = (5, 7)
SQUARE_M, MARKER_M = 0.04, 0.02
#: 6×6 bits + a one-module black border: 8 modules per marker side.
MODULE_M = MARKER_M / 8
#: The A4 sheet the board is printed on (portrait), metres.
SHEET_M = (0.210, 0.297)
#: Reflectances measured on the photos (DN, 5th/95th percentiles of dark squares and paper,
#: median of the wood around the sheet).
BLACK_DN, WHITE_DN, FLOOR_DN = 40.0, 224.0, 150.0
RENDERS_PER_PHOTO = 4
#: Print resolution of the board's texture: 8 texels per 2.5 mm module (0.3 mm ≈ 0.4 px).
TEXELS_PER_MODULE = 8
SUPERSAMPLE = 4


def load_calibration() -> PinholeCamera:
    storage = cv2.FileStorage(str(CALIBRATION), cv2.FILE_STORAGE_READ)
    K = storage.getNode("camera_matrix").mat()
    dist = storage.getNode("distortion_coefficients").mat().ravel()
    width = int(storage.getNode("image_width").real())
    height = int(storage.getNode("image_height").real())
    return PinholeCamera(K, dist, width, height)


def make_board() -> tuple[cv2.aruco.CharucoBoard, dict[int, np.ndarray]]:
    """The board and each marker's corners (4, 2) on the board plane (x right, y down, m)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
    board = cv2.aruco.CharucoBoard(SQUARES, SQUARE_M, MARKER_M, dictionary)
    corners = {
        int(i): np.asarray(points, dtype=float).reshape(4, 3)[:, :2]
        for i, points in zip(board.getIds().ravel(), board.getObjPoints())
    }
    return board, corners


def detect_corners(gray: np.ndarray) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """(plain, ecc): marker id → corners (4, 2) in the (distorted) image."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, parameters).detectMarkers(gray)
    plain, ecc = {}, {}
    if ids is None:
        return plain, ecc
    for marker_corners, marker_id in zip(corners, ids.ravel()):
        raw = marker_corners.reshape(4, 2).astype(float)
        plain[int(marker_id)] = raw
        refined, _ = align_symbol_ecc(gray, aruco_modules(DICTIONARY, int(marker_id)), raw)
        if refined is not None:
            ecc[int(marker_id)] = refined
    return plain, ecc


def leave_one_out_residuals_px(
    corners_px: dict[int, np.ndarray], board_corners_m: dict[int, np.ndarray], camera: PinholeCamera
) -> np.ndarray:
    """Per-corner distances (px) of each marker's undistorted corners from the homography
    fitted to the other markers' corners; empty when fewer than 3 markers."""
    ids = sorted(corners_px)
    if len(ids) < 3:
        return np.zeros(0)
    undistorted = {
        i: cv2.undistortPoints(corners_px[i].reshape(-1, 1, 2), camera.K, camera.dist, P=camera.K).reshape(4, 2)
        for i in ids
    }
    residuals = []
    for i in ids:
        others = [j for j in ids if j != i]
        H, _ = cv2.findHomography(
            np.concatenate([board_corners_m[j] for j in others]), np.concatenate([undistorted[j] for j in others]), 0
        )
        predicted = cv2.perspectiveTransform(board_corners_m[i].reshape(1, 4, 2), H).reshape(4, 2)
        residuals.extend(np.linalg.norm(predicted - undistorted[i], axis=1))
    return np.array(residuals)


def corner_error_components_px(corners_by_photo: list[dict[int, np.ndarray]], board_corners_m: dict[int, np.ndarray],
                               camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(independent σ, systematic σ) per image axis (px) of the corners over several photos of one
    board — the two variance components of the audit's corner model (``sigma_px`` and
    ``corner_bias_px``, :mod:`agvviz.evaluation.audit.problem`). Each marker's leave-one-out residual is taken
    back to the board plane (so a corner's systematic error stays put however the board lies in the
    photo) and scaled to px at that marker's size in the photo; per marker corner, the scatter across
    photos estimates the independent variance and the mean across photos the systematic one (its
    variance minus the independent variance over the photo count)."""
    per_corner: dict[tuple[int, int], list[np.ndarray]] = {}
    for corners_px in corners_by_photo:
        ids = sorted(corners_px)
        if len(ids) < 3:
            continue
        undistorted = {
            i: cv2.undistortPoints(corners_px[i].reshape(-1, 1, 2), camera.K, camera.dist, P=camera.K).reshape(4, 2)
            for i in ids
        }
        for i in ids:
            others = [j for j in ids if j != i]
            H, _ = cv2.findHomography(
                np.concatenate([board_corners_m[j] for j in others]), np.concatenate([undistorted[j] for j in others]), 0
            )
            predicted = cv2.perspectiveTransform(board_corners_m[i].reshape(1, 4, 2), H).reshape(4, 2)
            px_per_m = np.mean(np.linalg.norm(np.roll(predicted, -1, axis=0) - predicted, axis=1)) / MARKER_M
            on_board = cv2.perspectiveTransform(undistorted[i].reshape(1, 4, 2), np.linalg.inv(H)).reshape(4, 2)
            for c in range(4):
                per_corner.setdefault((i, c), []).append((on_board[c] - board_corners_m[i][c]) * px_per_m)
    groups = [np.array(v) for v in per_corner.values() if len(v) >= 2]
    if not groups:
        return np.full(2, np.nan), np.full(2, np.nan)
    within = np.mean([np.sum((v - v.mean(axis=0)) ** 2, axis=0) / (len(v) - 1) for v in groups], axis=0)
    means_sq = np.mean([v.mean(axis=0) ** 2 for v in groups], axis=0)
    systematic = means_sq - within * np.mean([1.0 / len(v) for v in groups])
    return np.sqrt(within), np.sqrt(np.maximum(systematic, 0.0))


def board_pose(gray: np.ndarray, board: cv2.aruco.CharucoBoard, camera: PinholeCamera) -> np.ndarray:
    """T_cam_board from the photo's ChArUco chessboard corners (solvePnP, iterative)."""
    charuco_corners, charuco_ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if charuco_ids is None or len(charuco_ids) < 6:
        raise RuntimeError("too few ChArUco corners to estimate the board pose")
    object_points = board.getChessboardCorners()[charuco_ids.ravel()]
    ok, rvec, tvec = cv2.solvePnP(object_points, charuco_corners, camera.K, camera.dist)
    if not ok:
        raise RuntimeError("solvePnP failed on the ChArUco corners")
    return se3.make(cv2.Rodrigues(rvec)[0], tvec.ravel())


def board_scene(board: cv2.aruco.CharucoBoard) -> FloorScene:
    """The board as one printed label on an A4 sheet, on the floor; world = board frame.

    The label is a square of ``n`` modules (2.5 mm) centred on the board, its texture the
    board image at one texel per module, white over the sheet and floor grey beyond it (the
    renderer looks textures up by nearest texel, so module edges are exact).
    """
    board_modules = (round(SQUARES[0] * SQUARE_M / MODULE_M), round(SQUARES[1] * SQUARE_M / MODULE_M))
    image = board.generateImage(board_modules, marginSize=0, borderBits=1)  # (rows, cols) = (112, 80)
    n = 128
    dark = np.zeros((n, n), dtype=bool)
    r0, c0 = (n - board_modules[1]) // 2, (n - board_modules[0]) // 2
    dark[r0 : r0 + board_modules[1], c0 : c0 + board_modules[0]] = image < 128
    centre_m = (SQUARES[0] * SQUARE_M / 2.0, SQUARES[1] * SQUARE_M / 2.0)
    # Marker frame (conventions): x along the board's x, y up the printed page (= −board y),
    # z out of the printed face (= −board z); the label's centre at the board's centre.
    T_world_marker = se3.make(np.diag([1.0, -1.0, -1.0]), [centre_m[0], centre_m[1], 0.0])
    side_m = n * MODULE_M
    h = side_m / 2.0
    code = FloorCode(
        marker_id="board", payload="", T_world_marker=T_world_marker, side_m=side_m, modules=dark,
        points_marker_m=np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]]), quiet_zone_modules=0,
    )
    return FloorScene(codes=(code,), floor_dn=FLOOR_DN, black_dn=BLACK_DN, white_dn=WHITE_DN)


def on_sheet(code: FloorCode, texture_dn: np.ndarray) -> np.ndarray:
    """``texture_dn`` with the texels beyond the A4 sheet (centred on the board) set to floor."""
    m = texture_dn.shape[0]
    texel_m = code.label_side_m / m
    centres_m = (np.arange(m) + 0.5) * texel_m - code.label_side_m / 2.0
    inside_x = np.abs(centres_m) <= SHEET_M[0] / 2.0
    inside_y = np.abs(centres_m) <= SHEET_M[1] / 2.0
    return np.where(inside_y[:, None] & inside_x[None, :], texture_dn, FLOOR_DN)


def render_board(
    scene: FloorScene, camera: PinholeCamera, T_world_cam: np.ndarray, errors: imaging.ImagingErrors, seed: int
) -> np.ndarray:
    """One rendered frame of the board: printed with ``errors`` (per seed), imaged with them."""
    code = scene.codes[0]
    printed = imaging.print_label(code, scene, errors, imaging.source_rngs(seed, 0, 0), TEXELS_PER_MODULE)
    texture = printed.texture_dn
    if texture is None:
        texture = imaging.ideal_texture_dn(code, scene, 1)
    printed = dataclasses.replace(printed, texture_dn=on_sheet(code, texture))
    printed_scene = dataclasses.replace(scene, codes=(printed,))
    irradiance = render_irradiance(printed_scene, camera, T_world_cam, SUPERSAMPLE, pixel_aperture=errors.pixel_aperture)
    return imaging.camera_frame(irradiance, camera, errors, imaging.source_rngs(seed, 1, 0))


def summary(residuals_px: np.ndarray) -> tuple[float, float, float]:
    """(median, RMS, p90) in px."""
    return (
        float(np.median(residuals_px)),
        float(np.sqrt(np.mean(residuals_px**2))),
        float(np.percentile(residuals_px, 90)),
    )


def measure(
    profiles: dict[str, imaging.ImagingErrors], renders_per_photo: int = RENDERS_PER_PHOTO
) -> tuple[dict[tuple[str, str], np.ndarray], dict[tuple[str, str], int]]:
    """Residuals (px) and marker counts keyed by (source, refiner); source "real" or a profile."""
    camera = load_calibration()
    board, board_corners_m = make_board()
    scene = board_scene(board)
    residuals: dict[tuple[str, str], list[np.ndarray]] = {}
    markers: dict[tuple[str, str], int] = {}
    for k, photo in enumerate(PHOTOS):
        gray = cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)
        T_world_cam = se3.inverse(board_pose(gray, board, camera))
        frames = [("real", gray)]
        for name, errors in profiles.items():
            frames += [
                (name, render_board(scene, camera, T_world_cam, errors, 100 * k + s)) for s in range(renders_per_photo)
            ]
        for source, frame in frames:
            plain, ecc = detect_corners(frame)
            for refiner, corners in (("plain", plain), ("ecc", ecc)):
                key = (source, refiner)
                residuals.setdefault(key, []).append(leave_one_out_residuals_px(corners, board_corners_m, camera))
                markers[key] = markers.get(key, 0) + len(corners)
    return {key: np.concatenate(values) for key, values in residuals.items()}, markers


def main() -> int:
    missing = [p for p in PHOTOS + [CALIBRATION] if not p.is_file()]
    if missing:
        print(f"skipped: real ChArUco photos not found ({missing[0]}); see /work/shared/data/MANIFEST.md")
        return 0
    profiles = {"ideal": imaging.IDEAL_IMAGING, "typical": imaging.TYPICAL_IMAGING, "harsh": imaging.HARSH_IMAGING}
    residuals, markers = measure(profiles)
    print(f"leave-one-marker-out homography residual (px), {len(PHOTOS)} photos, "
          f"{RENDERS_PER_PHOTO} renders per photo and profile")
    print(f"{'refiner':8s} {'frames':8s} {'markers':>7s} {'median':>7s} {'RMS':>7s} {'p90':>7s} {'median/real':>12s}")
    for refiner in ("plain", "ecc"):
        real_median = summary(residuals[("real", refiner)])[0]
        for source in ("real", *profiles):
            median, rms, p90 = summary(residuals[(source, refiner)])
            ratio = median / real_median
            print(f"{refiner:8s} {source:8s} {markers[(source, refiner)]:7d} {median:7.3f} {rms:7.3f} {p90:7.3f} {ratio:12.2f}")
    camera = load_calibration()
    _, board_corners_m = make_board()
    detected = [detect_corners(cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)) for photo in PHOTOS]
    print("real corners' error components (px, per image axis x, y; `agvviz audit`'s sigma_px and corner_bias_px):")
    for k, refiner in enumerate(("plain", "ecc")):
        independent, systematic = corner_error_components_px([d[k] for d in detected], board_corners_m, camera)
        print(f"{refiner:8s} independent {independent[0]:.3f}, {independent[1]:.3f}   "
              f"systematic per marker corner {systematic[0]:.3f}, {systematic[1]:.3f}")
    for refiner in ("plain", "ecc"):
        ratio = summary(residuals[("typical", refiner)])[0] / summary(residuals[("real", refiner)])[0]
        verdict = "met" if 0.7 <= ratio <= 1.3 else "MISSED"
        print(f"target (typical median within ±30 % of real), {refiner}: {ratio:.2f} — {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
