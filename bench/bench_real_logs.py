"""The issue 11 table: a robot's own log, written by independent writers, through `agvviz
inspect` and `agvviz run`.

Usage:  python bench/bench_real_logs.py [--out DIR]

Records a tiny qr_floor recording (4 frames, 640×512) and re-writes its content with rosbags
(ROS 2 bags: a two-file rosbag2 directory, a single file, the same on agvviz's topic names, one
without calibration) and the Foxglove SDK (RawImage mono8; images before their calibration and
truth) — the writers of tests/test_real_logs.py — then runs the CLI on each file and on the
real bags of ../shared/data/rosbag2_mcap (when present) and prints one row per file: inspect's
exit code and verdict, run's exit code, frames, solved, position RMSE, or its error. Needs the
test extra (rosbags, foxglove-sdk).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def write_files(out: Path) -> list[Path]:
    import foxglove

    import test_real_logs as t
    from agvviz.scenarios import record

    native = out / "native.mcap"
    record("qr_floor", native, seed=1, overrides=["duration_s=0.4", "width_px=640", "height_px=512", "focal_px=500", "realism=ideal"])
    content = t.content.__wrapped__(native)
    m = foxglove.messages
    with foxglove.open_mcap(out / "foxglove_raw.mcap", allow_overwrite=True):
        t0 = content["images"][0][0]
        foxglove.log("/tf_static", t._fx_tf_static(content, t0), log_time=t0)
        for (ts, jpeg), (_, T) in zip(content["images"], content["truth"]):
            g = t.grey(jpeg)
            foxglove.log("/front/calibration", t._fx_calibration(content["calibration"], ts), log_time=ts)
            foxglove.log("/front/image", m.RawImage(timestamp=t._ts(ts), frame_id="cam_front", width=g.shape[1],
                         height=g.shape[0], encoding="mono8", step=g.shape[1], data=g.tobytes()), log_time=ts)
            foxglove.log("/ground_truth/pose", m.PoseInFrame(timestamp=t._ts(ts), frame_id="world",
                                                             pose=t._fx_pose(T)), log_time=ts)
    with foxglove.open_mcap(out / "image_first.mcap", allow_overwrite=True):
        for (ts, jpeg), (_, T) in zip(content["images"], content["truth"]):
            foxglove.log("/front/compressed", m.CompressedImage(timestamp=t._ts(ts), frame_id="cam_front",
                                                                format="jpeg", data=jpeg), log_time=ts)
            foxglove.log("/front/camera_info", t._fx_calibration(content["calibration"], ts), log_time=ts)
            foxglove.log("/vicon/agv/pose", m.PoseInFrame(timestamp=t._ts(ts), frame_id="world",
                                                          pose=t._fx_pose(T)), log_time=ts)
        foxglove.log("/tf_static", t._fx_tf_static(content, content["images"][-1][0]), log_time=content["images"][-1][0])
    msgs = t.ros_messages(content)
    t.write_bag(out / "ros_bag", msgs, split=len(msgs) // 2)
    t.write_bag(out / "ros_bag_single", msgs)
    rename = {"/front/image_raw/compressed": "/cam/front/image", "/front/camera_info": "/cam/front/calibration",
              "/ground_truth/pose": "/agv/ground_truth", "/odom": "/agv/odometry"}
    compressed = [x for x in msgs if x[0] != "/front/image_raw"]
    t.write_bag(out / "ros_bag_agvviz_names", [(rename.get(a, a), b, c, d) for a, b, c, d in compressed])
    t.write_bag(out / "ros_bag_no_calibration", [x for x in t.ros_messages(content, calibration=False)])
    files = [native, out / "foxglove_raw.mcap", out / "ros_bag", out / "ros_bag_single" / "ros_bag_single_0.mcap",
             out / "ros_bag_agvviz_names", out / "image_first.mcap", out / "ros_bag_no_calibration"]
    real = ROOT.parent / "shared" / "data" / "rosbag2_mcap"
    return files + (sorted(p.parent for p in real.rglob("metadata.yaml")) if real.is_dir() else [])


def row(path: Path, out: Path) -> str:
    agvviz = [sys.executable, "-m", "agvviz"]
    inspected = subprocess.run(agvviz + ["inspect", str(path)], capture_output=True, text=True)
    verdict = next((line for line in inspected.stdout.splitlines() if line.startswith("contract:")), "")
    replay = [line for line in inspected.stdout.splitlines() if line.startswith("replay:")]
    rrd = out / "run.rrd"
    ran = subprocess.run(agvviz + ["run", str(path), "--out", str(rrd)], capture_output=True, text=True)
    text = ran.stdout + ran.stderr
    cells = [re.search(rf"│ {name}\s+│\s+(\S+)", text) for name in ("frames", "solved")]
    rmse = re.search(r"position RMSE / median / p95 \(mm\)\s+│\s+(\S+)", text)
    error = next((line for line in text.splitlines() if line.startswith("error:")), "")
    result = (
        f"frames {cells[0].group(1)}, solved {cells[1].group(1)}, RMSE {rmse.group(1)} mm" if cells[0] and rmse
        else error[:140]
    )
    written = "rrd written" if rrd.exists() else "no rrd"
    rrd.unlink(missing_ok=True)
    return (f"| {path.name} | {inspected.returncode}: {verdict} {replay[-1] if replay else ''} | "
            f"{ran.returncode}: {result} ({written}) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="keep the files here (default: a temporary folder)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        print("| file | inspect (exit: verdict, replay) | run (exit: result) |")
        print("| --- | --- | --- |")
        for path in write_files(out):
            print(row(path, out), flush=True)


if __name__ == "__main__":
    main()
