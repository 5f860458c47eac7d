"""Each ArUco corner refiner on real photographs, against references that do not use it
(issue 23 item 6; the table of docs/refinement.md).

Data: ``../shared/data/opencv_contrib_aruco/`` (``/work/shared/data/MANIFEST.md``):

* ChArUco board 5×7, square 0.04 m, marker 0.02 m, DICT_6X6_250, calibration
  ``tutorial_camera_charuco.yml``: ``img_00.jpg``–``img_03.jpg`` (``img_01.jpg`` is
  ``choriginal.jpg``) and ``chocclusion_original.jpg`` (partly occluded);
* GridBoard 5×7, marker 0.04 m, gap 0.01 m, the custom dictionary ``tutorial_dict.yml``,
  calibration ``tutorial_camera_params.yml``: ``gboriginal.png`` (no chessboard: homography
  reference only).

(``singlemarkersoriginal.jpg`` has six loose markers and no board: nothing to measure against.)

As agvviz does, each photo is undistorted first (``cv2.remap`` with the calibration) and the
markers detected on the undistorted image — by :func:`agvviz.markers.aruco.detect_aruco` with
each ``refine`` (``none``, ``subpix``, ``contour``, ``apriltag``: OpenCV's
``CORNER_REFINE_*``; ``ecc``: agvviz's template alignment). Only markers every refiner found
are compared. References:

* **saddle**: the board's chessboard corners (``cv2.aruco.CharucoDetector`` then
  ``cv2.cornerSubPix`` on the saddles, half-window 4 px), the board pose fitted to them
  (``solvePnP``) and every marker's corners projected from it. Its own floor: the saddles'
  RMS reprojection residual (printed).
* **LOO**: each marker's corners predicted by the homography board plane → image fitted to the
  *other* markers' corners of the same refiner (``bench_render_vs_photos``'s
  ``leave_one_out_residuals_px``).

Poses, against the saddle board pose (camera position in the board frame, mm; rotation, deg):
**single**: each marker alone (``solvePnPGeneric`` IPPE_SQUARE, the lower-error branch refined
by ``solvePnPRefineLM``; a pose more than 30° off is the mirror branch, counted apart); **joint**: all the photo's markers' corners in one ``solvePnP``.
Time per marker: the refiner's detection minus detection without refinement, per marker
(CPU time, one OpenCV thread, median of repeats).

    PYTHONPATH=. python bench/bench_refiners.py        (≈1 min)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

from agvviz.geometry.camera import PinholeCamera
from agvviz.markers.aruco import ARUCO_REFINE_METHODS, detect_aruco, detect_with_dictionary
from bench_render_vs_photos import leave_one_out_residuals_px, summary

#: ``../shared/data`` beside the checkout; from a worktree under /work/wt, /work/shared.
DATA = next(
    (d for d in (Path(__file__).resolve().parents[k] / "shared" / "data" / "opencv_contrib_aruco" for k in (2, 3)) if d.is_dir()),
    Path(__file__).resolve().parents[2] / "shared" / "data" / "opencv_contrib_aruco",
)
CHARUCO_PHOTOS = [DATA / f"img_0{i}.jpg" for i in range(4)] + [DATA / "chocclusion_original.jpg"]
GRID_PHOTO = DATA / "gboriginal.png"
REFINERS = ("none", "subpix", "contour", "apriltag", "ecc")
assert set(REFINERS) == set(ARUCO_REFINE_METHODS)
SADDLE_HALF_WINDOW_PX = 4
TIMING_REPEATS = 5
#: A single-marker pose this far (deg) from the board's is IPPE's mirror branch picked: a 21–32 px
#: marker seen 20–30° off its normal reprojects both branches almost equally well.
MIRROR_DEG = 30.0


def read_camera(path: Path, width: int = 640, height: int = 480) -> PinholeCamera:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    return PinholeCamera(storage.getNode("camera_matrix").mat(), storage.getNode("distortion_coefficients").mat().ravel(),
                         width, height)


def undistorted(gray: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    maps = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, (gray.shape[1], gray.shape[0]), cv2.CV_32FC2)
    return cv2.remap(gray, *maps, interpolation=cv2.INTER_LINEAR)


def marker_object_points(board) -> dict[int, np.ndarray]:
    """Marker id → its corners (4, 3) in the board frame (OpenCV's order TL, TR, BR, BL)."""
    return {int(i): np.asarray(p, float).reshape(4, 3) for i, p in zip(board.getIds().ravel(), board.getObjPoints())}


def rigid(T_points_src: np.ndarray, points_dst: np.ndarray) -> np.ndarray:
    """4×4 T with T·src = dst (Kabsch), for corner sets of one square."""
    a, b = T_points_src - T_points_src.mean(0), points_dst - points_dst.mean(0)
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, points_dst.mean(0) - R @ T_points_src.mean(0)
    return T


def pose(rvec, tvec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], np.ravel(tvec)
    return T


def pose_difference(T_cam_board: np.ndarray, T_cam_board_ref: np.ndarray) -> tuple[float, float]:
    """(camera position difference in the board frame (mm), rotation difference (deg))."""
    T_board_cam, T_board_cam_ref = np.linalg.inv(T_cam_board), np.linalg.inv(T_cam_board_ref)
    position_mm = 1e3 * float(np.linalg.norm(T_board_cam[:3, 3] - T_board_cam_ref[:3, 3]))
    R = T_cam_board[:3, :3] @ T_cam_board_ref[:3, :3].T
    angle_deg = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return position_mm, angle_deg


def single_marker_pose(corners_px: np.ndarray, side_m: float, K: np.ndarray) -> np.ndarray:
    """T_cam_marker (IPPE_SQUARE's lower-error branch, LM-refined); marker frame x right, y up."""
    h = side_m / 2
    object_points = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    _, rvecs, tvecs, errors = cv2.solvePnPGeneric(object_points, corners_px, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    best = int(np.argmin(np.ravel(errors)))
    rvec, tvec = cv2.solvePnPRefineLM(object_points, corners_px, K, None, rvecs[best].copy(), tvecs[best].copy())
    return pose(rvec, tvec)


def saddle_reference(gray: np.ndarray, board, K: np.ndarray) -> tuple[np.ndarray, float, int]:
    """(T_cam_board from the chessboard saddles, their RMS reprojection residual px, count)."""
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if ids is None or len(ids) < 6:
        raise RuntimeError("too few ChArUco corners")
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-4)
    saddles = cv2.cornerSubPix(gray, corners.astype(np.float32), (SADDLE_HALF_WINDOW_PX,) * 2, (-1, -1), criteria)
    object_points = board.getChessboardCorners()[ids.ravel()]
    ok, rvec, tvec = cv2.solvePnP(object_points, saddles, K, None)
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, K, None)
    rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - saddles.reshape(-1, 2)) ** 2, axis=1))))
    return pose(rvec, tvec), rms, len(ids)


def side_ratio(corners_px: dict[int, np.ndarray], plane_m: dict[int, np.ndarray]) -> float:
    """Median over markers of (side in the image) ÷ (side the homography of the *other* markers
    predicts): 1 when the markers' size agrees with the board layout; below 1 when a refiner's
    corners sit inside the printed squares' true corners."""
    ids = sorted(corners_px)
    ratios = []
    for i in ids:
        others = [j for j in ids if j != i]
        H, _ = cv2.findHomography(np.concatenate([plane_m[j] for j in others]), np.concatenate([corners_px[j] for j in others]), 0)
        predicted = cv2.perspectiveTransform(plane_m[i].reshape(1, 4, 2), H).reshape(4, 2)
        perimeter = lambda c: np.sum(np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1))  # noqa: E731
        ratios.append(perimeter(corners_px[i]) / perimeter(predicted))
    return float(np.median(ratios))


def refine_time_ms(detect, gray: np.ndarray, refine: str, markers: int) -> float:
    """CPU ms per marker the refiner adds to detection (median of repeats)."""

    def cpu(method):
        samples = []
        for _ in range(TIMING_REPEATS):
            t0 = time.process_time()
            detect(gray, method)
            samples.append(time.process_time() - t0)
        return float(np.median(samples))

    return 1e3 * max(cpu(refine) - cpu("none"), 0.0) / max(markers, 1)


def measure_photo(gray: np.ndarray, detect, object_points: dict[int, np.ndarray], K: np.ndarray,
                  saddle: tuple[np.ndarray, float, int] | None, stats: dict) -> None:
    found = {r: {d.marker_id: d.corners_px for d in detect(gray, r) if d.marker_id in object_points} for r in REFINERS}
    common = sorted(set.intersection(*(set(f) for f in found.values())))
    camera = PinholeCamera(K, np.zeros(5), gray.shape[1], gray.shape[0])
    side_m = float(np.linalg.norm(object_points[common[0]][1] - object_points[common[0]][0]))
    plane = {i: object_points[i][:, :2] for i in common}
    for refiner in REFINERS:
        s = stats.setdefault(refiner, {"saddle": [], "loo": [], "single_mm": [], "single_deg": [], "joint_mm": [],
                                       "joint_deg": [], "ms": [], "markers": 0, "radial": [],
                                       "side_ratio": []})
        corners = {i: found[refiner][i] for i in common}
        s["markers"] += len(common)
        s["loo"].append(leave_one_out_residuals_px(corners, plane, camera))
        s["ms"].append(refine_time_ms(detect, gray, refiner, len(found[refiner])))
        s["side_ratio"].append(side_ratio(corners, plane))
        if saddle is None:
            continue
        T_cam_board_ref = saddle[0]
        for i in common:
            predicted, _ = cv2.projectPoints(object_points[i], cv2.Rodrigues(T_cam_board_ref[:3, :3])[0],
                                             T_cam_board_ref[:3, 3], K, None)
            predicted = predicted.reshape(4, 2)
            s["saddle"].append(np.linalg.norm(predicted - corners[i], axis=1))
            outward = predicted - predicted.mean(0)
            outward /= np.linalg.norm(outward, axis=1, keepdims=True)
            s["radial"].append(np.sum((corners[i] - predicted) * outward, axis=1))
            h = side_m / 2
            T_board_marker = rigid(np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]]), object_points[i])
            T_cam_board = single_marker_pose(corners[i], side_m, K) @ np.linalg.inv(T_board_marker)
            mm, deg = pose_difference(T_cam_board, T_cam_board_ref)
            s["single_mm"].append(mm)
            s["single_deg"].append(deg)
        ok, rvec, tvec = cv2.solvePnP(np.concatenate([object_points[i] for i in common]),
                                      np.concatenate([corners[i] for i in common]), K, None)
        mm, deg = pose_difference(pose(rvec, tvec), T_cam_board_ref)
        s["joint_mm"].append(mm)
        s["joint_deg"].append(deg)


def main() -> int:
    missing = [p for p in CHARUCO_PHOTOS + [GRID_PHOTO] if not p.is_file()]
    if missing:
        print(f"skipped: real photos not found ({missing[0]}); see /work/shared/data/MANIFEST.md")
        return 0
    cv2.setNumThreads(1)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    charuco = cv2.aruco.CharucoBoard((5, 7), 0.04, 0.02, dictionary)
    camera = read_camera(DATA / "tutorial_camera_charuco.yml")
    charuco_stats: dict = {}
    floors = []
    for photo in CHARUCO_PHOTOS:
        gray = undistorted(cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE), camera)
        saddle = saddle_reference(gray, charuco, camera.K)
        floors.append((photo.name, saddle[1], saddle[2]))
        measure_photo(gray, lambda g, r: detect_aruco(g, "DICT_6X6_250", r), marker_object_points(charuco), camera.K,
                      saddle, charuco_stats)

    storage = cv2.FileStorage(str(DATA / "tutorial_dict.yml"), cv2.FILE_STORAGE_READ)
    custom = cv2.aruco.Dictionary()
    custom.readDictionary(storage.root())
    grid = cv2.aruco.GridBoard((5, 7), 0.04, 0.01, custom)
    grid_camera = read_camera(DATA / "tutorial_camera_params.yml")
    grid_stats: dict = {}
    gray = undistorted(cv2.imread(str(GRID_PHOTO), cv2.IMREAD_GRAYSCALE), grid_camera)
    measure_photo(gray, lambda g, r: detect_with_dictionary(g, custom, r), marker_object_points(grid), grid_camera.K,
                  None, grid_stats)

    print(f"ChArUco photos ({', '.join(p.name for p in CHARUCO_PHOTOS)}): "
          f"{charuco_stats['ecc']['markers']} markers (found by every refiner), undistorted first")
    print("saddle reference floor (RMS reprojection of the chessboard saddles, px): "
          + ", ".join(f"{name} {rms:.3f} ({n})" for name, rms, n in floors))
    print()
    header = ("| refine | vs saddle pose: median / RMS / p90 px | vs LOO homography: median / RMS / p90 px "
              "| outward px | single-marker pose: median / worst mm, deg | mirror picks; worst of the rest | "
              "joint pose: median / worst mm, deg | ms per marker |")
    print(header)
    print("|---|---|---|---|---|---|---|---|")
    for refiner in REFINERS:
        s = charuco_stats[refiner]
        saddle_px = summary(np.concatenate(s["saddle"]))
        loo_px = summary(np.concatenate(s["loo"]))
        single_mm, single_deg = np.array(s["single_mm"]), np.array(s["single_deg"])
        joint_mm, joint_deg = np.array(s["joint_mm"]), np.array(s["joint_deg"])
        mirror = single_deg > MIRROR_DEG
        print(f"| {refiner} | {saddle_px[0]:.3f} / {saddle_px[1]:.3f} / {saddle_px[2]:.3f} "
              f"| {loo_px[0]:.3f} / {loo_px[1]:.3f} / {loo_px[2]:.3f} "
              f"| {np.mean(np.concatenate(s['radial'])):+.3f} "
              f"| {np.median(single_mm):.1f} / {single_mm.max():.1f} mm, {np.median(single_deg):.2f} / {single_deg.max():.2f}° "
              f"| {np.sum(mirror)}; {single_mm[~mirror].max():.1f} mm, {single_deg[~mirror].max():.2f}° "
              f"| {np.median(joint_mm):.1f} / {joint_mm.max():.1f} mm, {np.median(joint_deg):.2f} / {joint_deg.max():.2f}° "
              f"| {np.median(s['ms']):.2f} |")
    print()
    print(f"GridBoard photo ({GRID_PHOTO.name}, custom dictionary, {grid_stats['ecc']['markers']} markers): "
          "LOO homography residual")
    print("| refine | median / RMS / p90 px | marker size ÷ layout's | ms per marker |")
    print("|---|---|---|---|")
    for refiner in REFINERS:
        s = grid_stats[refiner]
        loo_px = summary(np.concatenate(s["loo"]))
        print(f"| {refiner} | {loo_px[0]:.3f} / {loo_px[1]:.3f} / {loo_px[2]:.3f} | {np.median(s['side_ratio']):.4f} "
              f"| {np.median(s['ms']):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
