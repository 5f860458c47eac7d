"""Issue 23 figure: a recording written as a ROS 1 bag by ``rosbags`` replays to the native
per-frame errors (within 1e-6 m).

Usage:  python bench/bench_ros1.py [--duration 3] [--out DIR]

Records a qr_floor recording (``agvviz record qr_floor --set duration_s=3 --seed 1``) and
re-writes its content as a ROS 1 bag with ``rosbags.rosbag1.Writer`` and the ROS 1 Noetic
type store — the writer of tests/test_ros1_bag.py: ``sensor_msgs/CompressedImage`` (the
recorded JPEG bytes), ``CameraInfo`` (ROS 1 ``K``/``D``), a latched ``/tf_static`` with a
three-link camera chain, ``PoseStamped`` truth, ``nav_msgs/Odometry`` and ``/tf``; log times
7 ms after the header stamps; the marker map as a ``--markers`` side file. The same bag is
also converted to ROS 2 with ``rosbags``' converter, once keeping the ROS 1 definitions (its
default) and once into the ROS 2 Humble type store. Then ``agvviz run`` (the CLI, default
settings) replays each file and the per-frame position errors it logged
(``errors/position_mm``) are compared with the native run's, frame by frame.

Prints one row per file: run exit code, frames, solved, position RMSE, and the largest
per-frame difference from the native run (m). Needs the test extra (rosbags).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def agvviz(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "agvviz", *args], capture_output=True, text=True, cwd=ROOT)


def run_errors(recording: Path, out: Path, *extra: str) -> tuple[int, dict[int, float], dict, str]:
    """(exit code, frame index → position error m, run summary, error text) of ``agvviz run``."""
    from agvviz.viz import paths
    from agvviz.viz.readback import document_json, read_rrd, scalar_series

    done = agvviz("run", str(recording), "--out", str(out), *extra)
    if done.returncode != 0:
        return done.returncode, {}, {}, (done.stdout + done.stderr).strip().splitlines()[-1]
    contents = read_rrd(out)
    frames, values_mm = scalar_series(contents, paths.ERROR_POSITION_MM)
    summary = document_json(contents, paths.RUN_SUMMARY)
    return 0, {int(f): v / 1000.0 for f, v in zip(frames, values_mm)}, summary, ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3.0, help="recording length, s")
    parser.add_argument("--out", type=Path, default=None, help="folder for the files (default: a temporary one)")
    args = parser.parse_args()

    from rosbags.convert import convert
    from rosbags.typesys import Stores, get_typestore

    import test_ros1_bag as t

    out = args.out or Path(tempfile.mkdtemp(prefix="bench_ros1_"))
    out.mkdir(parents=True, exist_ok=True)
    native = out / "qr_floor.mcap"
    native.unlink(missing_ok=True)
    done = agvviz("record", "qr_floor", "--set", f"duration_s={args.duration:g}", "--seed", "1", "--out", str(native))
    if done.returncode != 0:
        sys.exit(f"agvviz record failed: {done.stdout}{done.stderr}")
    content = t.native_content(native)
    markers = out / "map.json"
    markers.write_text(json.dumps(content["marker_map"]))
    bag = out / "qr_floor.bag"
    bag.unlink(missing_ok=True)
    t.write_ros1_bag(bag, t.ros1_messages(content))
    files = [("native .mcap (agvviz)", native, ()), ("ROS 1 .bag (rosbags)", bag, ("--markers", str(markers)))]
    for label, store in (("ROS 2, ROS 1 definitions kept", None), ("ROS 2, Humble type store", Stores.ROS2_HUMBLE)):
        converted = out / ("converted_copy" if store is None else "converted_humble")
        if not converted.exists():
            convert([bag], converted, "mcap", 8, None, "file", None,
                    get_typestore(store) if store else None, [], [], [], [])
        files.append((label, converted, ("--markers", str(markers))))

    print(f"qr_floor, duration {args.duration:g} s, seed 1, default settings; files in {out}")
    print(f"{'file':<32} {'exit':>4} {'frames':>6} {'solved':>6} {'RMSE mm':>8} {'max |Δ| vs native (m)':>22}")
    print("(RMSE and |Δ| over the frames scored against truth; |Δ| per frame, same frame index)")
    reference: dict[int, float] | None = None
    worst_all = 0.0
    for label, path, extra in files:
        code, errors, summary, why = run_errors(path, out / f"{path.stem}.rrd", *extra)
        if code != 0:
            print(f"{label:<32} {code:>4}  {why}")
            worst_all = float("inf")
            continue
        values = np.array(list(errors.values()))
        rmse_mm = float(np.sqrt(np.mean(values**2)) * 1000) if values.size else float("nan")
        if reference is None:
            reference, delta = errors, "—"
        elif sorted(errors) != sorted(reference):
            delta = f"frames differ ({len(errors)} vs {len(reference)})"
            worst_all = float("inf")
        else:
            worst = max(abs(errors[k] - reference[k]) for k in reference)
            worst_all = max(worst_all, worst)
            delta = f"{worst:.1e}"
        print(f"{label:<32} {code:>4} {summary.get('frames', '?'):>6} {summary.get('solved', '?'):>6} "
              f"{rmse_mm:>8.3f} {delta:>22}")
    print(f"largest per-frame difference from native: {worst_all:.1e} m "
          f"({'within' if worst_all <= 1e-6 else 'NOT within'} 1e-6 m)")


if __name__ == "__main__":
    main()
