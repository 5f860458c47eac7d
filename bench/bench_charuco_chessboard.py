"""The joint solve with and without a ChArUco board's chessboard (saddle) corners, on the real
ChArUco photos, against the pose from OpenCV's own chessboard corners (docs/joint-solve.md).

Data: ``../shared/data/opencv_contrib_aruco/img_00–03.jpg`` with their calibration, written
as a ROS 2 bag exactly as ``tests/test_charuco_bag.py`` does (its ``write_bag`` and its
reference ``chessboard_pose``: ``CharucoDetector.detectBoard`` on the recorded image,
``cornerSubPix`` half-window 3, ``solvePnP`` with the distortion). Replayed in process with
``--markers`` = the board side file and ``ambiguity=lowest_error``:

* **markers only**: the board's ``boards`` entry removed from the map (its 17 markers kept) —
  the joint solve before chessboard corners joined it;
* **markers + chessboard**: the map as the side file gives it (``board0:chessboard`` joins);
* **largest**: ``markers=largest`` (paper 000's one marker).

Per photo: camera position difference (mm) and rotation difference (deg) from the reference,
the views used and the frame's note.

    PYTHONPATH=. python bench/bench_charuco_chessboard.py      (≈15 s)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from agvviz.geometry import se3, so3  # noqa: E402
from agvviz.markers.charuco import charuco_marker_corners  # noqa: E402
from agvviz.recording.sidefiles import load_calibration, load_marker_map, parse_extrinsic  # noqa: E402
from agvviz.replay.run import SideInputs, replay_frames  # noqa: E402
from agvviz.settings import RunSettings, apply_overrides  # noqa: E402
from test_charuco_bag import BOARD, CALIBRATION, CAM, DICTIONARY, PHOTOS, chessboard_pose, write_bag_and_board  # noqa: E402


def replay(bag: Path, marker_map: dict, overrides: list[str]) -> list:
    settings = apply_overrides(RunSettings(), ["ambiguity=lowest_error", *overrides])
    side = SideInputs()
    side.marker_map = marker_map
    side.calibrations[CAM] = load_calibration(CAM, CALIBRATION)
    side.extrinsics[CAM] = parse_extrinsic(CAM, "0,0,0,0,0,0,1", settings.body_frame)
    return list(replay_frames(bag, settings, side=side))


def main() -> None:
    if not all(p.is_file() for p in PHOTOS):
        sys.exit(f"real ChArUco photos not found: {PHOTOS[0].parent}")
    board = charuco_marker_corners(BOARD["squares_x"], BOARD["squares_y"], BOARD["square_length_m"],
                                   BOARD["marker_length_m"], DICTIONARY)
    references = [chessboard_pose(photo, board) for photo in PHOTOS]
    with tempfile.TemporaryDirectory() as tmp:
        bag, markers = write_bag_and_board(Path(tmp))
        with_board = load_marker_map(markers)
        without = {k: v for k, v in with_board.items() if k != "boards"}
        runs = {
            "largest": replay(bag, with_board, ["markers=largest"]),
            "markers only": replay(bag, without, []),
            "markers + chessboard": replay(bag, with_board, []),
        }
    print("| photo | " + " | ".join(runs) + " |")
    print("| --- |" + " --- |" * len(runs))
    notes = []
    for i, (photo, T_cam_board_ref) in enumerate(zip(PHOTOS, references)):
        cells = []
        for name, frames in runs.items():
            frame = frames[i]
            if frame.T_world_cam is None:
                cells.append(f"rejected ({frame.rejected})")
                continue
            T_board_cam = np.asarray(frame.T_world_cam, dtype=float)
            offset_mm = 1000.0 * np.linalg.norm(T_board_cam[:3, 3] - se3.inverse(T_cam_board_ref)[:3, 3])
            angle_deg = np.degrees(np.linalg.norm(so3.log(T_cam_board_ref[:3, :3] @ T_board_cam[:3, :3])))
            used = [u for u in frame.used_marker_ids if not u.endswith(":chessboard")]
            board_used = any(u.endswith(":chessboard") for u in frame.used_marker_ids)
            what = f"{len(used)} marker{'s' if len(used) != 1 else ''}" + (" + chessboard" if board_used else "")
            cells.append(f"{offset_mm:.2f} mm, {angle_deg:.3f}° ({what})")
            if frame.marker_note:
                notes.append(f"{photo.name} {name}: {frame.marker_note}")
        print(f"| {photo.name} | " + " | ".join(cells) + " |")
    for note in notes:
        print("  " + note)


if __name__ == "__main__":
    main()
