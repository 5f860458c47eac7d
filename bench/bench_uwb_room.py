"""Paper 003's figures on the uwb_room scenario, side by side with the paper's.

Usage:  python bench/bench_uwb_room.py [--fixes 100] [--duration 40] [--seed 0] [--keep DIR]
                                        [--only grid,path,blocked,resolution]
                                        [--set key=value ...]

1. static grid (§3.2, Tables 1–2): 30 points on a 120 cm grid, ``--fixes`` camera frames and
   UWB rounds each; mean 2-D error of the camera fix (best camera, and the joint multi-camera
   LM) and of the UWB fix (trilateral centroid, least squares; residual gate on);
2. dynamic path without blocking (§3.3, Table 3): camera and UWB mean errors;
3. blocked stretch (Table 4): mean error of the fused position while the cameras are blocked,
   paper 003's mean compensation and the Kalman filter;
4. resolution study (Table 5) at 1280×1024, 640×480, 320×240: static error at (240, 240) cm,
   dynamic camera error, blocked fused error (mean compensation, as the paper).

Errors are 2-D (eq 17), in mm, mean over fixes as in the paper. Each recording is replayed
through the camera pipeline once; the fusion variants reuse its frame results.
"""

from __future__ import annotations

import dataclasses

import argparse
import copy
import tempfile
from pathlib import Path


from agvviz import scenarios as scenario_registry
from agvviz.evaluation.fusion_summary import FusionStats
from agvviz.replay.fuse import FusionReplay
from agvviz.replay.solve import Replay
from agvviz.model.messages import CompressedFrame, RecordedMessage
from agvviz.recording.reader import iter_messages
from agvviz.settings import RunSettings

RESOLUTIONS = ((1280, 1024), (640, 480), (320, 240))
#: ``--set`` options added to every recording's overrides (e.g. ``realism=typical``).
EXTRA: list[str] = []


def replay_once(recording: Path) -> tuple[list, dict]:
    """(message, frame result) pairs with images dropped, and the pipeline's camera state."""
    replay = Replay(RunSettings())
    pairs = []
    for message in iter_messages(recording):
        frame = replay.feed(message)
        if frame is not None:
            frame = dataclasses.replace(frame, image_bytes=b"")
        light = RecordedMessage(message.topic, message.log_time_ns, message.schema_name, None) if isinstance(
            message.value, CompressedFrame) else message
        pairs.append((light, frame))
    return pairs, replay


def fusion_summary(pairs: list, replay, **settings) -> dict:
    """The fusion statistics of one setting over replayed pairs (``replay``: the solve stage
    that made them, for its cameras and its sync stage's ground truth)."""
    fusion = FusionReplay(RunSettings(**settings), replay.ctx.cameras, replay.sync)
    stats = FusionStats()
    for message, frame in copy.deepcopy(pairs):
        for item in fusion.feed(message, frame):
            stats.add(item)
    for item in fusion.finish():
        stats.add(item)
    return stats.summary()


def record(tmp: Path, name: str, seed: int, overrides: list[str]) -> Path:
    path = tmp / f"{name}.mcap"
    scenario_registry.record("uwb_room", path, seed=seed, overrides=[*overrides, *EXTRA])
    return path


def mean(summary: dict, key: str) -> float:
    value = summary[key]["mean"]
    return float("nan") if value is None else value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fixes", type=int, default=20, help="fixes per static point (paper: 100)")
    parser.add_argument("--duration", type=float, default=40.0, help="path length in seconds")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--keep", type=Path, default=None, help="keep the recordings in this folder")
    parser.add_argument("--only", default="grid,path,blocked,resolution")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                        help="scenario option for every recording, e.g. realism=typical (repeatable)")
    args = parser.parse_args()
    EXTRA[:] = args.sets
    parts = set(args.only.split(","))
    tmp = args.keep or Path(tempfile.mkdtemp(prefix="bench_uwb_room_"))
    tmp.mkdir(parents=True, exist_ok=True)
    no_block = [f"duration_s={args.duration}", "block_start_s=0", "block_end_s=0"]
    blocked = [f"duration_s={args.duration}"]

    if "grid" in parts:
        rec = record(tmp, "grid", args.seed, ["variant=static_grid", f"fixes_per_point={args.fixes}"])
        pairs, cams = replay_once(rec)
        best = fusion_summary(pairs, cams, camera_select="best", uwb="centroid", fusion="camera_only")
        combine = fusion_summary(pairs, cams, camera_select="combine", uwb="least_squares", fusion="camera_only")
        print(f"\n1. static grid, 30 points x {args.fixes} fixes, 1280x1024 (mean 2-D error, mm)")
        print(f"   camera, best camera      {mean(best, 'camera_xy_error_mm'):7.2f}   (fix rate {best['camera_fix_rate']:.2f})"
              "   paper Table 2: 4.4-14.4 mm, goal <= 6.75")
        print(f"   camera, joint LM         {mean(combine, 'camera_xy_error_mm'):7.2f}")
        print(f"   UWB, trilateral centroid {mean(best, 'uwb_xy_error_mm'):7.2f}   paper Table 1: 58-89 mm")
        print(f"   UWB, least squares       {mean(combine, 'uwb_xy_error_mm'):7.2f}")

    if "path" in parts:
        rec = record(tmp, "path", args.seed, no_block)
        pairs, cams = replay_once(rec)
        best = fusion_summary(pairs, cams, camera_select="best", uwb="centroid", fusion="camera_only")
        combine = fusion_summary(pairs, cams, camera_select="combine", uwb="least_squares", fusion="camera_only")
        print(f"\n2. dynamic path, {args.duration:g} s at 0.2 m/s, no blocking (mean 2-D error, mm)")
        print(f"   camera, best camera      {mean(best, 'camera_xy_error_mm'):7.2f}   paper Table 3: 10.5-14.4 mm, goal <= 12.9")
        print(f"   camera, joint LM         {mean(combine, 'camera_xy_error_mm'):7.2f}")
        print(f"   UWB, trilateral centroid {mean(best, 'uwb_xy_error_mm'):7.2f}   paper Table 3: 89-97 mm")
        print(f"   UWB, least squares       {mean(combine, 'uwb_xy_error_mm'):7.2f}")

    if "blocked" in parts:
        rec = record(tmp, "blocked", args.seed, blocked)
        pairs, cams = replay_once(rec)
        print(f"\n3. blocked stretch (14-24 s of {args.duration:g} s): fused error while blocked (mean 2-D, mm)")
        for fusion, uwb, note in (
            ("mean_compensation", "centroid", "paper Table 4: 44-63 mm (about 50)"),
            ("mean_compensation", "least_squares", ""),
            ("kalman", "least_squares", "goal <= 25 mm"),
        ):
            s = fusion_summary(pairs, cams, fusion=fusion, uwb=uwb)
            print(f"   {fusion:17s} ({uwb:13s}) {mean(s, 'fused_blocked_xy_error_mm'):7.2f}   "
                  f"switches {s['switches']}, mean jump {mean(s, 'switch_jump_mm'):.1f} mm   {note}")

    if "resolution" in parts:
        print("\n4. resolution study (Table 5), mean 2-D errors in mm; paper in brackets")
        paper = {1280: (6.75, 12.857, 50.125), 640: (15.72, 19.374, 66.581), 320: (33.51, 45.718, 89.743)}
        print(f"   {'resolution':10s} {'static (240,240)':>22s} {'dynamic':>20s} {'blocked (mean comp.)':>26s} {'fix rate':>9s}")
        for w, h in RESOLUTIONS:
            res = [f"width_px={w}", f"height_px={h}"]
            static = record(tmp, f"static_{w}", args.seed, ["variant=static_grid", "static_point_m=2.4,2.4", "fixes_per_point=100", *res])
            s_static = fusion_summary(*replay_once(static), fusion="camera_only")
            pairs, cams = replay_once(record(tmp, f"blocked_{w}", args.seed, blocked + res))
            s_block = fusion_summary(pairs, cams, fusion="mean_compensation", uwb="centroid")
            dyn_pairs, dyn_cams = replay_once(record(tmp, f"path_{w}", args.seed, no_block + res))
            s_dyn = fusion_summary(dyn_pairs, dyn_cams, fusion="camera_only")
            p = paper[w]
            print(f"   {w}x{h:<5d} {mean(s_static, 'camera_xy_error_mm'):10.2f} [{p[0]:6.2f}]   "
                  f"{mean(s_dyn, 'camera_xy_error_mm'):9.2f} [{p[1]:6.2f}]   "
                  f"{mean(s_block, 'fused_blocked_xy_error_mm'):12.2f} [{p[2]:7.2f}]   {s_dyn['camera_fix_rate']:8.2f}")
    print(f"\nrecordings in {tmp}")


if __name__ == "__main__":
    main()
