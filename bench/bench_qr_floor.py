"""Accuracy and throughput figures for issue 2 on the default qr_floor scenario.

Usage:  python bench/bench_qr_floor.py [--seed 0] [--set key=value ...] [--keep DIR]

Prints:
1. AGV position RMSE (mm) and heading RMSE (deg) of lm, p4p and ippe on the frames all three
   solved (same frames, same corners), plus each solver's own counts; then lm with each corner
   refinement (ecc, subpix, none) to show what the refiner buys.
2. Replay throughput (frames/s) of the full `agvviz run` path (decode, undistort, detect,
   refine, solve, log to .rrd) and of a bare OpenCV loop (imdecode + QRCodeDetector
   detectAndDecodeMulti + solvePnP) over the same recording, timed in the same process run,
   and their ratio.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from agvviz import scenarios as scenario_registry
from agvviz.evaluation import FrameScore
from agvviz.geometry.plane import square_points_marker
from agvviz.replay.graph import replay
from agvviz.model.messages import CompressedFrame, CalibrationMsg
from agvviz.recording.reader import iter_messages
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings


def rmse(values) -> float:
    v = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")


def accuracy(recording: Path) -> None:
    per_solver: dict[str, dict[int, FrameScore]] = {}
    for solver in ("lm", "p4p", "ippe"):
        scores = [FrameScore.of(f) for f in replay(iter_messages(recording), RunSettings(solver=solver))]
        per_solver[solver] = {s.index: s for s in scores}
        solved = [s for s in scores if s.rejected is None]
        print(f"{solver:5s}: frames {len(scores)}, solved {len(solved)}, "
              f"rejected {len(scores) - len(solved)}")
    common = set.intersection(*(
        {i for i, s in d.items() if s.rejected is None and s.position_error_m is not None}
        for d in per_solver.values()
    ))
    print(f"\nfigures on the {len(common)} frames every solver solved:")
    print(f"{'solver':6s} {'pos RMSE mm':>12s} {'pos median mm':>14s} {'pos p95 mm':>11s} {'heading RMSE deg':>17s}")
    for solver, d in per_solver.items():
        pos = [d[i].position_error_m * 1000 for i in sorted(common)]
        hdg = [d[i].heading_error_deg for i in sorted(common)]
        print(f"{solver:6s} {rmse(pos):12.2f} {np.median(pos):14.2f} {np.percentile(pos, 95):11.2f} {rmse(hdg):17.3f}")


def refinement_sensitivity(recording: Path) -> None:
    """lm with each corner refinement: how much of the accuracy the refiner buys."""
    print("\nlm by corner refinement (each on the frames it solved):")
    print(f"{'refine':7s} {'solved':>7s} {'pos RMSE mm':>12s} {'pos p95 mm':>11s} {'heading RMSE deg':>17s}")
    for refine in ("ecc", "subpix", "none"):
        scores = [FrameScore.of(f) for f in replay(iter_messages(recording), RunSettings(solver="lm", refine=refine))]
        solved = [s for s in scores if s.rejected is None and s.position_error_m is not None]
        pos = [s.position_error_m * 1000 for s in solved]
        hdg = [s.heading_error_deg for s in solved]
        print(f"{refine:7s} {len(solved):7d} {rmse(pos):12.2f} {np.percentile(pos, 95):11.2f} {rmse(hdg):17.3f}")


def bare_opencv_loop(recording: Path) -> tuple[int, float]:
    """Baseline: imdecode + detectAndDecodeMulti + solvePnP(IPPE_SQUARE) per frame, no
    refinement, no undistortion, no logging. Returns (frames, seconds)."""
    detector = cv2.QRCodeDetector()
    K = None
    frames = 0
    object_points = square_points_marker(0.5)
    t0 = time.perf_counter()
    for msg in iter_messages(recording):
        if isinstance(msg.value, CalibrationMsg):
            K, dist = msg.value.camera.K, msg.value.camera.dist
        if not isinstance(msg.value, CompressedFrame):
            continue
        frames += 1
        gray = cv2.imdecode(np.frombuffer(msg.value.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        ok, texts, corners, _ = detector.detectAndDecodeMulti(gray)
        if ok and corners is not None:
            for c in corners:
                cv2.solvePnP(object_points, c.astype(np.float64), K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return frames, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", dest="sets", action="append", default=[], help="scenario option key=value")
    parser.add_argument("--keep", type=Path, default=None, help="keep the recording and run in this folder")
    args = parser.parse_args()

    workdir = args.keep or Path(tempfile.mkdtemp(prefix="agvviz-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    recording = workdir / "qr_floor.mcap"
    t0 = time.perf_counter()
    scenario_registry.record("qr_floor", recording, seed=args.seed, overrides=args.sets)
    print(f"recorded qr_floor (seed {args.seed}, {args.sets or 'defaults'}) in {time.perf_counter() - t0:.1f} s → {recording}\n")

    accuracy(recording)
    refinement_sensitivity(recording)

    print("\nthroughput (same recording, same process):")
    outcome = run_recording(recording, RunSettings(solver="lm"), workdir / "qr_floor-lm.rrd")
    frames_run = outcome.summary["frames"]
    fps_run = outcome.timing["frames_per_s"]
    frames_bare, seconds_bare = bare_opencv_loop(recording)
    fps_bare = frames_bare / seconds_bare
    print(f"agvviz run (lm, refine=ecc, logging): {frames_run} frames, {fps_run:.1f} frames/s "
          f"(detect {outcome.timing['detect_ms']:.1f} ms, solve {outcome.timing['solve_ms']:.2f} ms per frame)")
    print(f"bare OpenCV loop (decode+detect+solvePnP): {frames_bare} frames, {fps_bare:.1f} frames/s")
    print(f"ratio agvviz / bare OpenCV: {fps_run / fps_bare:.2f}")


if __name__ == "__main__":
    main()
