"""AprilTag corner order on the official images (issue 23 item 1 figure).

Every official image of ids 0–19 of tag36h11, tag16h5 and tag25h9 (``../shared/data/apriltag_imgs``,
upright as printed) is scaled ×24 without interpolation, given a white margin, turned
0/90/180/270° and warped by the 5 homographies of tests/test_marker_orientation.py (supersampled,
blurred, noisy) — 3 families × 4 turns × 5 warps × 20 ids. Each image goes through agvviz's
detection (:func:`agvviz.markers.aruco.detect_aruco`, AprilTag library, ``refine``) and, for
comparison, through OpenCV's ArUco detector with the same OpenCV dictionary. Prints per family
the detections, how often corner 0 is the printed top-left, and the corner error against the
warped truth (px), then the total line of the issue's figure.

    python bench/bench_marker_orientation.py [--refine ecc|subpix|none|apriltag] [--ids 20]

Measured (2026-11-27, OpenCV 5.0.0, pupil-apriltags 1.0.4, refine=ecc): see docs/markers.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_marker_orientation import APRILTAG_IMGS, FAMILIES, WARPS, official, printed, turned, warped  # noqa: E402

from agvviz.markers.apriltag import APRILTAG_REFINE_METHODS  # noqa: E402
from agvviz.markers.aruco import detect_aruco  # noqa: E402
from agvviz.markers.dictionary import aruco_dictionary  # noqa: E402


def opencv_corners(image: np.ndarray, name: str, tag_id: int) -> np.ndarray | None:
    """OpenCV's ArUco detector's corners (CORNER_REFINE_SUBPIX) of ``tag_id``, its own order."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.ArucoDetector(aruco_dictionary(name), params).detectMarkers(image)
    if ids is None or tag_id not in ids.ravel():
        return None
    return corners[list(ids.ravel()).index(tag_id)].reshape(4, 2).astype(float)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--refine", default="ecc", choices=APRILTAG_REFINE_METHODS)
    parser.add_argument("--ids", type=int, default=20, help="official ids per family (1..20)")
    args = parser.parse_args()
    if not APRILTAG_IMGS.is_dir():
        print(f"official AprilTag images not found at {APRILTAG_IMGS}", file=sys.stderr)
        return 2
    total = good = 0
    t0 = time.perf_counter()
    print(f"refine={args.refine}; per family: {4 * len(WARPS) * args.ids} images (4 turns × {len(WARPS)} warps × {args.ids} ids)")
    print(f"{'family':10} {'found':>7} {'c0=TL':>7} {'err med':>8} {'err max':>8} | {'OpenCV found':>12} {'c0=TL':>6}")
    for name, folder, prefix in FAMILIES:
        n = found = top_left = cv_found = cv_top_left = 0
        errors = []
        for tag_id in range(args.ids):
            image, truth = printed(official(folder, prefix, tag_id), scale=24, margin=40)
            for turn in range(4):
                turned_image, turned_truth = turned(image, truth, turn)
                for w, H in enumerate(WARPS):
                    frame, points = warped(turned_image, turned_truth, H, seed=1000 * tag_id + 100 * turn + w)
                    n += 1
                    hits = [d for d in detect_aruco(frame, name, refine=args.refine) if d.marker_id == tag_id]
                    if hits:
                        found += 1
                        corners = hits[0].corners_px
                        top_left += int(np.argmin(np.linalg.norm(points - corners[0], axis=1))) == 0
                        errors.append(np.linalg.norm(corners - points, axis=1).max())
                    cv = opencv_corners(frame, name, tag_id)
                    if cv is not None:
                        cv_found += 1
                        cv_top_left += int(np.argmin(np.linalg.norm(points - cv[0], axis=1))) == 0
        total += n
        good += top_left
        err = np.array(errors) if errors else np.array([np.nan])
        print(
            f"{folder:10} {found:>3}/{n:<3} {top_left:>3}/{found:<3} {np.median(err):8.3f} {err.max():8.3f} | "
            f"{cv_found:>5}/{n:<6} {cv_top_left:>3}/{cv_found:<3}"
        )
    print(
        f"corner 0 = printed top-left on {good}/{total} official images "
        f"(3 families × 4 turns × {len(WARPS)} warps × {args.ids} ids); {time.perf_counter() - t0:.1f} s"
    )
    return 0 if good == total else 1


if __name__ == "__main__":
    raise SystemExit(main())
