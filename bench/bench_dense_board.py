"""Dense boards: frames per second of agvviz's detect stage on 720p frames with 32 ArUco markers
(issue 23 item 7, goal ≥ 10 frames/s on 2 cores), and the corner error against the known truth.

The frame: a 8×4 grid of DICT_6X6_250 markers (ids 0–31, side 0.10 m, gap 0.025 m) drawn on a
white canvas at 32 texels per module from :func:`cv2.aruco.generateImageMarker`, seen by a
1280×720 pinhole camera (f = 1000 px, no distortion) 0.95 m away, tilted 22° and turned 8°: the
canvas is warped by the plane's homography at 4× supersampling and area-averaged down (marker
sides ≈90–130 px), then blurred (Gaussian σ 0.8 px), given sensor noise (σ 2 DN, seeded) and
JPEG-encoded (quality 92) — the bytes agvviz's detect stage reads. Truth: the markers' outer
corners mapped through the same homography (OpenCV pixel-centre convention).

Printed, per refiner asked for:

* in process, one OpenCV thread (as a detection worker runs): the detect stage as ``agvviz run``
  calls it (:class:`agvviz.replay.detect.stage.SegmentDetector` on a
  :class:`~agvviz.replay.detect.stage.FrameJob`: JPEG decode, ArUco detection, refinement) — median
  CPU and wall ms per frame, and the frames/s of ``--workers`` cores (workers ÷ CPU time per
  frame: what an otherwise idle machine gives);
* two worker processes (:class:`agvviz.replay.detect.pool.DetectionFeed`'s way: segments of
  frames in a process pool, ``jobs=2``): frames/s over all frames;
* the corner error against the truth (median, RMS, p90 px) and markers found.

    PYTHONPATH=. python bench/bench_dense_board.py [--frames 16] [--refine ecc subpix none]
    PYTHONPATH=. python bench/bench_dense_board.py --write-recording /tmp/dense.mcap --frames 40

``--write-recording`` writes the frames as an agvviz recording (calibration, marker map, camera
at its true pose as the vehicle) to time ``agvviz run`` as a whole process.

``--whole-run N`` times ``agvviz run REC --no-cache --jobs J`` as a whole process, N times
(start-up, detection workers, solve, logging, the .rrd written): per run the wall time, the
CPU time of the process and its detection workers (read from ``/proc`` while they run; Linux),
the run's own throughput line and its position RMSE; printed are the medians, frames ÷ wall
time, and frames ÷ (CPU time ÷ 2): the frames/s two otherwise idle cores would give.

    PYTHONPATH=. python bench/bench_dense_board.py --frames 120 --whole-run 3
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

import cv2
import numpy as np

from agvviz.geometry.camera import PinholeCamera
from agvviz.replay.detect.stage import DetectParams, FrameJob, SegmentDetector, detect_segment
from agvviz.model.messages import CalibrationMsg

DICTIONARY = "DICT_6X6_250"
COLUMNS, ROWS = 8, 4
MARKER_M, GAP_M, MARGIN_M = 0.10, 0.025, 0.05
MODULES = 8  # 6×6 bits + the one-module black border
TEXELS_PER_MODULE = 32
WIDTH_PX, HEIGHT_PX, FOCAL_PX = 1280, 720, 1000.0
SUPERSAMPLE = 4
BLUR_SIGMA_PX, NOISE_DN, BLACK_DN, WHITE_DN, JPEG_QUALITY = 0.8, 2.0, 30.0, 220.0, 92
CAMERA = PinholeCamera(
    np.array([[FOCAL_PX, 0, (WIDTH_PX - 1) / 2], [0, FOCAL_PX, (HEIGHT_PX - 1) / 2], [0, 0, 1]]),
    np.zeros(5), WIDTH_PX, HEIGHT_PX,
)
CALIBRATION = CalibrationMsg("board_cam", "cam_board_cam", CAMERA, "plumb_bob")


def board_canvas() -> tuple[np.ndarray, dict[int, np.ndarray], float]:
    """(canvas uint8, marker id → its outer corners TL, TR, BR, BL on the board in metres (x right,
    y up the printed page, the canvas's top-left corner at 0), texels per metre)."""
    texel_m = MARKER_M / MODULES / TEXELS_PER_MODULE
    ppm = 1.0 / texel_m
    width_m = 2 * MARGIN_M + COLUMNS * MARKER_M + (COLUMNS - 1) * GAP_M
    height_m = 2 * MARGIN_M + ROWS * MARKER_M + (ROWS - 1) * GAP_M
    canvas = np.full((round(height_m * ppm), round(width_m * ppm)), 255, np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
    side_tx = MODULES * TEXELS_PER_MODULE
    corners_m = {}
    for r in range(ROWS):
        for c in range(COLUMNS):
            marker_id = r * COLUMNS + c
            x0_m, y0_m = MARGIN_M + c * (MARKER_M + GAP_M), MARGIN_M + r * (MARKER_M + GAP_M)
            u0, v0 = round(x0_m * ppm), round(y0_m * ppm)
            canvas[v0 : v0 + side_tx, u0 : u0 + side_tx] = cv2.aruco.generateImageMarker(dictionary, marker_id, side_tx, borderBits=1)
            x0, y0, s = u0 * texel_m, v0 * texel_m, side_tx * texel_m
            corners_m[marker_id] = np.array([[x0, -y0], [x0 + s, -y0], [x0 + s, -y0 - s], [x0, -y0 - s]])
    return canvas, corners_m, ppm


def camera_pose(width_m: float, height_m: float) -> np.ndarray:
    """T_world_cam: 0.95 m from the board's centre, looking at it, tilted 22° and turned 8°."""
    centre = np.array([width_m / 2, -height_m / 2, 0.0])
    R_world_cam0 = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # looking down −z, image up = +y

    def rot(axis, deg):
        return cv2.Rodrigues(np.asarray(axis, float) * np.radians(deg))[0]

    R_world_cam = R_world_cam0 @ rot([1, 0, 0], 22) @ rot([0, 1, 0], 8)
    T = np.eye(4)
    T[:3, :3] = R_world_cam
    T[:3, 3] = centre - R_world_cam[:, 2] * 0.95
    return T


def render(seed: int) -> tuple[np.ndarray, bytes, dict[int, np.ndarray], np.ndarray]:
    """(gray frame, its JPEG bytes, marker id → true corners px (4, 2), T_world_cam)."""
    canvas, corners_m, ppm = board_canvas()
    height_m, width_m = canvas.shape[0] / ppm, canvas.shape[1] / ppm
    T_world_cam = camera_pose(width_m, height_m)
    T_cam_world = np.linalg.inv(T_world_cam)
    H_image_world = CAMERA.K @ np.column_stack([T_cam_world[:3, 0], T_cam_world[:3, 1], T_cam_world[:3, 3]])
    # canvas texel centres (u, v) → board metres: x = (u + 0.5)/ppm, y = −(v + 0.5)/ppm
    A_world_canvas = np.array([[1 / ppm, 0, 0.5 / ppm], [0, -1 / ppm, -0.5 / ppm], [0, 0, 1]])
    s = SUPERSAMPLE
    S_super_image = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1]])
    H_super_canvas = S_super_image @ H_image_world @ A_world_canvas
    dn = (BLACK_DN + (WHITE_DN - BLACK_DN) * canvas.astype(np.float32) / 255.0).astype(np.float32)
    super_frame = cv2.warpPerspective(
        dn, H_super_canvas, (WIDTH_PX * s, HEIGHT_PX * s), flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT, borderValue=float(0.5 * (BLACK_DN + WHITE_DN)),
    )
    frame = cv2.resize(super_frame, (WIDTH_PX, HEIGHT_PX), interpolation=cv2.INTER_AREA)
    frame = cv2.GaussianBlur(frame, (0, 0), BLUR_SIGMA_PX)
    frame = frame + np.random.default_rng(seed).normal(0.0, NOISE_DN, frame.shape).astype(np.float32)
    gray = np.clip(np.rint(frame), 0, 255).astype(np.uint8)
    ok, jpeg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    assert ok
    truth = {
        i: cv2.perspectiveTransform(c.reshape(1, 4, 2), H_image_world).reshape(4, 2) for i, c in corners_m.items()
    }
    return cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE), jpeg.tobytes(), truth, T_world_cam


def job(jpeg: bytes) -> FrameJob:
    return FrameJob("board_cam", "jpeg", jpeg, CALIBRATION)


def corner_errors_px(detections, truth: dict[int, np.ndarray]) -> np.ndarray:
    errors = [np.linalg.norm(np.asarray(d.corners_px) - truth[d.aruco_id], axis=1) for d in detections.codes if d.aruco_id in truth]
    return np.concatenate(errors) if errors else np.zeros(0)


def _detect_batch(args: tuple[DetectParams, list[bytes]]) -> int:
    params, jpegs = args
    return sum(len(d.codes) for d in detect_segment(params, [job(b) for b in jpegs]))


def measure(refine: str, frames: list[tuple[np.ndarray, bytes, dict, np.ndarray]], workers: int) -> dict:
    params = DetectParams(refine=refine, tracking=False, aruco_dictionary=DICTIONARY)
    cv2.setNumThreads(1)  # as in a detection worker
    detector = SegmentDetector(params)
    detector.detect(job(frames[0][1]))  # warm caches (undistortion maps, dictionaries, templates)
    times, cpu, errors, found = [], [], [], 0
    for _, jpeg, truth, _ in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        detections = detector.detect(job(jpeg))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        errors.append(corner_errors_px(detections, truth))
        found += len(detections.codes)
    error = np.concatenate(errors)
    segment = params.segment_frames
    batches = [(params, [f[1] for f in frames[i : i + segment]]) for i in range(0, len(frames), segment)]
    with ProcessPoolExecutor(workers) as pool:
        list(pool.map(_detect_batch, batches[:workers]))  # start the workers
        t0 = time.perf_counter()
        list(pool.map(_detect_batch, batches))
        pool_s = time.perf_counter() - t0
    return {
        "ms": 1e3 * float(np.median(times)), "cpu_ms": 1e3 * float(np.median(cpu)), "fps_pool": len(frames) / pool_s,
        "found": found / len(frames), "median": float(np.median(error)), "rms": float(np.sqrt(np.mean(error**2))),
        "p90": float(np.percentile(error, 90)),
    }


def write_recording(path: str, frames) -> None:
    from agvviz.recording.writer import RecordingWriter

    _, corners_m, _ = board_canvas()
    marker_map = {
        "dictionary": DICTIONARY,
        "markers": [
            {"id": str(i), "side_m": MARKER_M, "frame": "world", "corners_world_m": np.column_stack([c, np.zeros(4)]).tolist()}
            for i, c in sorted(corners_m.items())
        ],
    }
    with RecordingWriter(path, scenario={"name": "dense_board", "seed": 0, "options": {}}) as w:
        w.write_calibration("board_cam", CAMERA, 0)
        w.write_tf_static([("agv", "cam_board_cam", np.eye(4))], 0)
        w.write_marker_map(marker_map, 0)
        for k, (_, jpeg, _, T_world_cam) in enumerate(frames):
            t = 100_000_000 * (k + 1)
            w.write_image("board_cam", jpeg, "jpeg", t)
            w.write_pose("/agv/ground_truth", T_world_cam, "world", t)


def _process_tree_cpu_s(root_pid: int) -> dict[int, float]:
    """CPU seconds (user + system) so far of ``root_pid`` and every process under it."""
    tick = os.sysconf("SC_CLK_TCK")
    parent, cpu = {}, {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        parent[int(name)], cpu[int(name)] = int(fields[1]), (int(fields[11]) + int(fields[12])) / tick
    tree, grown = {root_pid}, True
    while grown:
        children = {pid for pid, ppid in parent.items() if ppid in tree} - tree
        tree |= children
        grown = bool(children)
    return {pid: cpu[pid] for pid in tree if pid in cpu}


def whole_run(recording: str, jobs: int) -> dict:
    """One ``agvviz run`` as a whole process: wall s, CPU s of its process tree (sampled every
    20 ms until each process ends, so a process's last ≤ 20 ms are missed), its throughput
    line and position RMSE."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "agvviz", "run", recording, "--no-cache", "--jobs", str(jobs),
                   "--out", os.path.join(tmp, "run.rrd")]
        cpu: dict[int, float] = {}
        t0 = time.perf_counter()
        with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
            while proc.poll() is None:
                cpu.update(_process_tree_cpu_s(proc.pid))
                time.sleep(0.02)
            wall_s = time.perf_counter() - t0
            out = proc.stdout.read()
    if proc.returncode != 0:
        raise SystemExit(f"agvviz run failed (exit {proc.returncode}):\n{out[-2000:]}")

    def figure(label: str) -> str:
        match = re.search(re.escape(label) + r"[^│|]*[│|]\s*([^│|]+?)\s*[│|]", out)
        return match.group(1) if match else "?"

    return {"wall_s": wall_s, "cpu_s": sum(cpu.values()), "throughput": figure("throughput (frames/s"),
            "position": figure("position RMSE / median / p95 (mm)")}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--refine", nargs="+", default=["ecc"])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--write-recording", metavar="PATH")
    parser.add_argument("--whole-run", type=int, metavar="N", help="time `agvviz run` as a whole process N times")
    parser.add_argument("--recording", metavar="PATH", help="--whole-run: this recording instead of rendering one")
    args = parser.parse_args(argv)
    if args.whole_run and args.recording:
        return print_whole_run(args.recording, args.whole_run, args.workers)
    frames = [render(seed) for seed in range(args.frames)]
    if args.write_recording:
        write_recording(args.write_recording, frames)
        print(f"wrote {args.frames} frames to {args.write_recording}")
        return 0
    if args.whole_run:
        with tempfile.TemporaryDirectory() as tmp:
            recording = os.path.join(tmp, "dense.mcap")
            write_recording(recording, frames)
            return print_whole_run(recording, args.whole_run, args.workers)
    print(f"{args.frames} frames {WIDTH_PX}×{HEIGHT_PX}, {COLUMNS * ROWS} markers {DICTIONARY}; detect stage "
          f"(JPEG decode + detection + refinement)")
    print(f"{'refine':8s} {'CPU ms/frame':>12s} {'wall ms/frame':>13s} {f'fps {args.workers} cores (CPU)':>18s} "
          f"{f'fps {args.workers} procs (wall)':>20s} {'markers':>8s} {'median px':>9s} {'RMS px':>7s} {'p90 px':>7s}")
    for refine in args.refine:
        r = measure(refine, frames, args.workers)
        print(f"{refine:8s} {r['cpu_ms']:12.1f} {r['ms']:13.1f} {args.workers * 1e3 / r['cpu_ms']:18.1f} "
              f"{r['fps_pool']:20.2f} {r['found']:8.1f} {r['median']:9.4f} {r['rms']:7.4f} {r['p90']:7.4f}")
    print("fps on n cores (CPU) = n ÷ CPU time per frame (one OpenCV thread per process, as the detection workers run); "
          "fps (wall) = frames ÷ wall time through a pool of n processes, which a busy machine lowers")
    return 0


def print_whole_run(recording: str, runs: int, jobs: int) -> int:
    from agvviz.model.messages import CompressedFrame
    from agvviz.recording.reader import iter_messages

    n_frames = sum(isinstance(m.value, CompressedFrame) for m in iter_messages(recording))
    print(f"`agvviz run {os.path.basename(recording)} --no-cache --jobs {jobs}`, {n_frames} frames, whole process, "
          f"{runs} runs (load average before: {os.getloadavg()[0]:.1f})")
    print(f"{'run':>4s} {'wall s':>7s} {'CPU s':>6s} {'frames/s (wall)':>15s} {'frames/s (2 idle cores)':>23s} "
          f"{'its throughput line':>19s}  position RMSE / median / p95 mm")
    results = []
    for k in range(runs):
        r = whole_run(recording, jobs)
        results.append(r)
        print(f"{k + 1:4d} {r['wall_s']:7.2f} {r['cpu_s']:6.2f} {n_frames / r['wall_s']:15.1f} "
              f"{n_frames / (r['cpu_s'] / 2):23.1f} {r['throughput']:>19s}  {r['position']}")
    wall, cpu = np.median([r["wall_s"] for r in results]), np.median([r["cpu_s"] for r in results])
    print(f"median: {wall:.2f} s wall, {cpu:.2f} s CPU: {n_frames / wall:.1f} frames/s (wall), "
          f"{n_frames / (cpu / 2):.1f} frames/s on 2 idle cores (frames ÷ (CPU ÷ 2)); "
          f"load average after: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
