"""Issue 23 figures for starting without a map and large maps.

Usage:  python bench/bench_nomap.py [--workdir DIR] [--markers 200000]

1. A QR map of ``--markers`` codes (default 200 000, random on a 2 km square): time and peak
   Python memory (tracemalloc) of ``qr_map_of`` + ``unmapped_tolerance_m`` + one unmapped-code
   check — the k-d tree; the n × n × 3 float64 array it replaces is printed for comparison.
2. The family scan (``agvviz.markers.scan.scan_frame``, all nine families) per frame on the
   real photos of ``../shared/data/opencv_contrib_aruco`` and on a rendered 1280×720 frame.
3. What ``agvviz run`` pays for its family check on a QR recording with its map (qr_floor,
   10 s at 10 Hz, recorded into DIR): ``family_check`` wall time.
4. ``inspect``'s scan of a 20-frame recording of the four real ChArUco photos: every family on
   every frame, against every family on the first 6 (the default) and the families seen after.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _data_dir() -> Path:
    for base in (REPO.parent, REPO.parents[1]):
        if (base / "shared" / "data").is_dir():
            return base / "shared" / "data"
    return REPO.parent / "shared" / "data"


def big_map(n: int) -> None:
    from agvviz.recording.checks import payload_map_problem, qr_map_of, unmapped_tolerance_m

    rng = np.random.default_rng(23)
    centres = np.column_stack([rng.uniform(0, 2000, n), rng.uniform(0, 2000, n), np.zeros(n)])
    offsets = np.array([[-0.1, -0.1, 0.0], [-0.1, 0.1, 0.0], [0.1, 0.1, 0.0], [0.1, -0.1, 0.0]])
    marker_map = {"dictionary": "qr", "markers": [
        {"id": f"Q{i}", "corners_world_m": (c + offsets).tolist()} for i, c in enumerate(centres)]}
    tracemalloc.start()
    start = time.perf_counter()
    qr_map = qr_map_of(marker_map)
    tol = unmapped_tolerance_m(qr_map)
    payload_map_problem("NEW", offsets + [5000.0, 5000.0, 0.0], qr_map, tol)
    elapsed = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    old_gib = n * n * 3 * 8 / 2**30
    print(f"1. {n} QR codes: qr_map_of + unmapped_tolerance_m + 1 unmapped check {elapsed:.2f} s, "
          f"peak {peak / 2**20:.0f} MiB (tolerance {tol:.2f} m); the pairwise array needed {old_gib:,.0f} GiB")


def scan_speed() -> None:
    from agvviz.markers.scan import FamilyScan, scan_frame

    photos = sorted((_data_dir() / "opencv_contrib_aruco").glob("*.jpg"))
    if not photos:
        print("2. real photos not found; skipped")
    for photo in photos:
        gray = cv2.imread(str(photo), cv2.IMREAD_GRAYSCALE)
        scan = FamilyScan()
        times = []
        for _ in range(3):
            start = time.perf_counter()
            markers = scan_frame(gray)
            times.append(time.perf_counter() - start)
        scan.add("cam", markers)
        found = ", ".join(f"{f.dictionary} ({len(f.ids)} ids)" for f in scan.found()) or "nothing"
        print(f"2. {photo.name} {gray.shape[1]}×{gray.shape[0]}: {min(times) * 1000:.0f} ms/frame (best of 3); found {found}")
    frame = np.full((720, 1280), 190, np.uint8)
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    for k in range(8):
        tag = cv2.copyMakeBorder(cv2.aruco.generateImageMarker(d, k, 100, borderBits=1), 20, 20, 20, 20,
                                 cv2.BORDER_CONSTANT, value=255)
        x, y = 40 + (k % 4) * 300, 60 + (k // 4) * 320
        frame[y:y + 140, x:x + 140] = tag
    start = time.perf_counter()
    markers = scan_frame(frame)
    print(f"2. rendered 1280×720, 8 AprilTags: {(time.perf_counter() - start) * 1000:.0f} ms/frame, "
          f"{len(markers)} detections")


def run_check(workdir: Path) -> None:
    from agvviz import scenarios as scenario_registry
    from agvviz.replay.detect.family_scan import family_check
    from agvviz.replay.run import prepare
    from agvviz.settings import RunSettings

    recording = workdir / "qr_floor_10s.mcap"
    if not recording.exists():
        scenario_registry.record("qr_floor", recording, seed=1, overrides=["duration_s=10", "rate_hz=10"])
    prepared = prepare(recording, RunSettings())
    start = time.perf_counter()
    family_check(prepared, str(recording))
    print(f"3. run's family check on qr_floor (10 s, 10 Hz, 1280×1024, QR map): {time.perf_counter() - start:.2f} s")


def scan_charuco_recording(workdir: Path) -> None:
    """A 20-frame Foxglove MCAP of the four real ChArUco photos (cycled): inspect's scan."""
    import foxglove
    from foxglove.channels import CompressedImageChannel

    from agvviz.replay.detect.family_scan import scan_recording
    from agvviz.replay.run import prepare
    from agvviz.settings import RunSettings

    photos = [(_data_dir() / "opencv_contrib_aruco" / f"img_0{i}.jpg") for i in range(4)]
    if not all(p.is_file() for p in photos):
        print("4. ChArUco photos not found; skipped")
        return
    path = workdir / "charuco20.mcap"
    context = foxglove.Context()
    writer = foxglove.open_mcap(path, allow_overwrite=True, context=context)
    try:
        channel = CompressedImageChannel("/cam/image", context=context)
        for k in range(20):
            t = 1_700_000_000_000_000_000 + k * 100_000_000
            channel.log(foxglove.messages.CompressedImage(
                timestamp=foxglove.messages.Timestamp(t // 10**9, t % 10**9), frame_id="cam", format="jpeg",
                data=photos[k % 4].read_bytes()), log_time=t)
    finally:
        writer.close()
    prepared = prepare(path, RunSettings())
    for probe in (20, 6):
        start = time.perf_counter()
        scan = scan_recording(prepared, probe_frames=probe)
        found = ", ".join(f"{f.dictionary} ({len(f.ids)} ids, {f.frames_seen}/{f.frames_sampled} frames)" for f in scan.found())
        print(f"4. scan of 20 ChArUco frames, all families on the first {probe}: "
              f"{time.perf_counter() - start:.1f} s; found {found}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--markers", type=int, default=200_000)
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench_nomap_"))
    workdir.mkdir(parents=True, exist_ok=True)
    big_map(args.markers)
    scan_speed()
    run_check(workdir)
    scan_charuco_recording(workdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
