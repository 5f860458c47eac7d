"""The issue 25 figures of the check stage (docs/suspects.md): injected faults flagged and named,
clean recordings' flag rate, and the checks' run-time cost — every replay with ``truth=ignore``
(truth is read only here, to say which frames are affected).

Usage:  python bench/bench_checks.py [--seeds 20] [--workdir DIR] [--duration-s 6] [--repeats 3] [--offline]
        [--first-seed 0] [--kinds late,offset]   (a part: some seeds, some faults; --repeats 0: no cost)

``--offline`` solves each recording once (checks off; the solve-stage frames, the odometry and
the marker map kept in ``WORKDIR/solved/``, reused on the next run) and runs the check stage on
them in this process — the same suspects as a replay (the check stage never reads truth, and
runs on exactly these frames in the replay graph), in a fraction of the time when only the
checks changed.

Per seed, ``qr_floor`` recordings (``duration_s``, 640×512, focal 500 px, supersample 2, realism
typical): clean, and one per fault of :data:`INJECTED` — Q015 turned 90° or moved 5 cm in the
map, a 30 ms camera latency (realism) and a 30 ms stamp offset (inject), the camera knocked 1° /
2 cm at 3 s, Q015's payload 0.3 m off in a recording without a map, and mirror flips (the
planar-ambiguity recipe :data:`AMBIGUOUS`, 1280×1024). Printed:

1. injected: affected frames (truth says > 2 cm or > 1° off, or Q015 in the frame's used or
   left-out markers) flagged — a suspect of its own, or covered by a run-level finding (a camera's
   time offset, stated at the end of the run for every frame of the camera) — and of those the
   share named right: the frame's own suspect's cause (and code), else the covering finding's
   (Q015's map_entry; time_offset); target ≥ 95 % flagged, ≥ 90 % named right. Mirror flips: a frame is
   affected when its chosen pose *is* the flipped one — it has a mirror pose
   (``T_world_agv_ghost``), the truth is nearer the mirror pose than the chosen one (rotation
   angle: the two IPPE branches differ in the tilt), and the chosen pose is off by more than its
   covariance says (NEES over χ²'s 99 % quantile, 16.8 for 6 DoF). With 6 cm codes at 3 m a
   right pose is often > 2 cm or 1° off within its honest covariance: those frames are not
   flips, and no check should flag them. The frames > 2 cm or > 1° off are printed too (the
   figure the bench reported before, as ``mirror (> 2 cm or 1° off)``);
2. clean: flagged frames (as in 1) ÷ solved frames; target ≤ 1 %; then the run-level findings
   made on clean recordings and on the other faults, and the offsets found on the time-offset kinds;
3. cost: `run_recording` wall time (``.rrd`` written, detection cache warm) with ``checks=on`` ÷
   ``checks=off`` on the first clean recording, the median of ``--repeats`` alternating pairs;
   target ≤ 1.05.
"""

from __future__ import annotations

import argparse
import math
import pickle
import statistics
import tempfile
import time
from pathlib import Path

from scipy.special import chdtri
import numpy as np

from agvviz import scenarios
from agvviz.app.run import run_recording
from agvviz.model.frames import FrameResult
from agvviz.replay.run import replay_checked, replay_frames
from agvviz.settings import RunSettings
from agvviz.solvers.ambiguity import rotation_distance_rad

SMALL = ["width_px=640", "height_px=512", "focal_px=500.0", "supersample=2"]
#: The planar-ambiguity recipe of docs/realism.md (small far ArUco markers, 1280×1024): mirror flips.
AMBIGUOUS = ["marker_family=DICT_4X4_1000", "code_size_m=0.06", "cam_height_m=3", "cam_lookahead_m=1",
             "grid_spacing_m=2.5", "rate_hz=5"]
CODE = "Q015"
#: kind -> (recording overrides, the cause a suspect must name, the code it must name or None)
INJECTED = {
    "turned": ("inject=marker:Q015:yaw_deg=90", "map_entry", CODE),
    "moved": ("inject=marker:Q015:dx_m=0.05", "map_entry", CODE),
    "late": ("realism_set=timing.latency_s=0.03", "time_offset", None),
    "offset": ("inject=timing:front:offset_ms=30", "time_offset", None),
    "knocked": ("inject=camera:front:pitch_deg=1,dz_m=0.02,from_s=3", "extrinsic", None),
    "payload": ("write_map=false;inject=payload:Q015:dx_m=0.3", "payload", CODE),
    "mirror": ("", "mirror_flip", None),
}
#: The faults a run-level time-offset finding names.
OFFSET_KINDS = ("late", "offset")


def is_flipped(scored: FrameResult) -> bool:
    """True when ``scored`` (a replay with truth) chose the mirror pose: it has one, the truth is
    nearer it than the chosen pose (rotation angle), and the chosen pose's NEES is over χ²'s
    99 % quantile (off by more than its covariance says)."""
    T_ghost, T_truth = scored.T_world_agv_ghost, scored.T_world_agv_truth
    if T_ghost is None or T_truth is None or scored.nees is None or not math.isfinite(scored.nees):
        return False
    nearer_ghost = rotation_distance_rad(T_ghost, T_truth) < rotation_distance_rad(scored.T_world_agv, T_truth)
    return nearer_ghost and scored.nees > float(chdtri(scored.nees_dof or 6, 0.01))


def tally(count: list[int], said, named: bool) -> None:
    """Add a frame whose verdict is ``said`` (:func:`verdict`) to ``count`` = [affected, flagged, named right]."""
    count[0] += 1
    count[1] += said is not None
    count[2] += named


def solved_frames(path: Path, folder: Path):
    """(frames, odometry series, marker map) of ``path``'s solve stage with ``checks=off``, kept in
    ``folder`` (pickle, keyed by the recording's name and size)."""
    from agvviz.recording.reader import ReadReport
    from agvviz.replay.graph import ReplayGraph
    from agvviz.replay.run import iter_role_messages, prepare

    folder.mkdir(parents=True, exist_ok=True)
    kept = folder / f"{path.stem}-{path.stat().st_size}.pkl"
    if kept.exists():
        return pickle.loads(kept.read_bytes())
    prepared = prepare(path, RunSettings(checks="off"), None, None, None)
    graph = ReplayGraph(prepared.replay, until="solve")
    report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    frames = list(graph.frames(iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, report)))
    value = (frames, graph.solve.sync.odometry, graph.solve.ctx.qr_map)
    kept.write_bytes(pickle.dumps(value))
    return value


def checked_offline(path: Path, folder: Path, settings: RunSettings):
    """``path``'s solve-stage frames (:func:`solved_frames`) through a fresh check stage: (checked
    frames, the stage's run-level findings)."""
    from agvviz.replay.checks import CheckSettings, CheckStage
    from agvviz.replay.sync import ODOMETRY_MAX_GAP_NS

    frames, odometry, qr_map = solved_frames(path, folder)
    stage = CheckStage(CheckSettings.of(settings), lambda t: odometry.at(t, ODOMETRY_MAX_GAP_NS, ODOMETRY_MAX_GAP_NS),
                       lambda: qr_map, lambda: None if odometry is None else odometry.span_ns)
    checked = [stage.check(f) for f in frames]
    return checked, stage.run_findings()


#: Floors (checks_pose_floor_m, checks_pose_floor_deg) whose clean motion d² ``--offline`` prints.
FLOORS = ((0.002, 0.1), (0.0005, 0.02), (0.0, 0.0))


def clean_motion_d2(paths: list[Path], folder: Path, floor_m: float, floor_deg: float):
    """Every motion check's d² = δᵀC⁻¹δ (6 dof) on the clean recordings under these floors, and
    the frames flagged."""
    from agvviz.replay.checks import CheckSettings, CheckStage
    from agvviz.replay.sync import ODOMETRY_MAX_GAP_NS

    settings = RunSettings(checks_pose_floor_m=floor_m, checks_pose_floor_deg=floor_deg)
    d2, flagged = [], 0
    for path in paths:
        frames, odometry, qr_map = solved_frames(path, folder)
        stage = CheckStage(CheckSettings.of(settings),
                           lambda t, o=odometry: o.at(t, ODOMETRY_MAX_GAP_NS, ODOMETRY_MAX_GAP_NS), lambda q=qr_map: q)
        motion = stage._motion

        def recorded(frame, state, odometry_now, motion=motion, stage=stage):
            out = motion(frame, state, odometry_now)
            if out is not None and state in stage.cameras.values():  # (not a stretch's own test)
                d2.append(stage.last_motion_d2)
            return out

        stage._motion = recorded
        flagged += sum(stage.check(f).suspect is not None for f in frames)
    return np.array(d2), flagged


def verdict(frame, findings):
    """What a user is told about a solved ``frame``: its own suspect, else the run-level finding
    that covers it (same camera, its index), else None."""
    if not frame.solved:
        return None
    if frame.suspect is not None:
        return frame.suspect
    return next((f for f in findings if f.cam_name == frame.cam_name and frame.index in f.frame_indices), None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--kinds", default=",".join(INJECTED), help="faults to record and replay, comma-separated")
    parser.add_argument("--duration-s", type=float, default=6.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--offline", action="store_true", help="solve once, check in process (see the docstring)")
    args = parser.parse_args()
    kinds = [k for k in args.kinds.split(",") if k]
    unknown = sorted(set(kinds) - set(INJECTED))
    if unknown:
        parser.error(f"unknown kinds {unknown}: choose from {', '.join(INJECTED)}")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_checks_"))
    work.mkdir(parents=True, exist_ok=True)
    overrides = SMALL + [f"duration_s={args.duration_s:g}"]

    def checked(path: Path):
        """(frames, run-level findings) of a truth=ignore replay, and the frames scored with truth
        by index (truth read only to say which frames are affected)."""
        if args.offline:  # one solve: the check stage never reads truth; the frames keep it for judging
            frames, findings = checked_offline(path, work / "solved", RunSettings())
            return frames, findings, {f.index: f for f in frames if f.solved}
        frames, findings = replay_checked(path, RunSettings(truth="ignore"))
        return frames, findings, {f.index: f for f in replay_frames(path, RunSettings()) if f.solved}

    counts = {k: [0, 0, 0] for k in kinds}  # affected, flagged, named right
    if "mirror" in kinds:
        counts["mirror_off"] = [0, 0, 0]  # mirror recordings, frames > 2 cm or > 1° off (not the affected ones)
    clean = [0, 0]  # flagged, solved
    clean_paths = []
    clean_findings = 0  # run-level findings on clean recordings
    offsets_ms = {kind: [] for kind in OFFSET_KINDS if kind in kinds}  # the findings' offset estimates
    other_findings = {kind: 0 for kind in kinds if kind not in OFFSET_KINDS}  # findings on other faults
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    for seed in seeds:
        path = work / f"clean-{seed}.mcap"
        if not path.exists():
            scenarios.record("qr_floor", path, seed=seed, overrides=overrides)
        clean_paths.append(path)
        frames, findings, _ = checked(path)
        clean_findings += len(findings)
        for f in frames:
            if f.solved:
                clean[0] += verdict(f, findings) is not None
                clean[1] += 1
        for kind in kinds:
            override, cause, code = INJECTED[kind]
            path = work / f"{kind}-{seed}.mcap"
            if not path.exists():
                base = AMBIGUOUS + [f"duration_s={args.duration_s:g}"] if kind == "mirror" else overrides
                extra = [o for o in override.split(";") if o and not o.startswith("inject=")]
                injects = ";".join(o[len("inject="):] for o in override.split(";") if o.startswith("inject="))
                scenarios.record("qr_floor", path, seed=seed,
                                 overrides=base + extra + ([f"inject={injects}"] if injects else []))
            frames, findings, truth = checked(path)
            if kind in OFFSET_KINDS:
                offsets_ms[kind] += [f.offset_s * 1000 for f in findings if f.offset_s is not None]
            else:
                other_findings[kind] += len(findings)
            for f in frames:
                t = truth.get(f.index)
                if t is None:
                    continue
                off = t.position_error_m > 0.02 or abs(t.heading_error_deg) > 1.0
                said = verdict(f, findings)
                named = (said is not None and said.cause == cause
                         and (code is None or getattr(said, "marker_id", None) == code))
                if kind == "mirror":
                    if off:
                        tally(counts["mirror_off"], said, named)
                    affected = is_flipped(t)
                else:
                    affected = off or (code is not None and code in f.used_marker_ids + f.excluded_marker_ids)
                if affected:
                    tally(counts[kind], said, named)
        print(f"seed {seed}: clean {clean[0]}/{clean[1]}, " + ", ".join(f"{k} {c[1]}/{c[0]} named {c[2]}" for k, c in counts.items()), flush=True)
    for kind, (affected, flagged, named) in counts.items():
        what = {"mirror": "flipped (truth nearer the mirror pose, NEES > χ² 99 %)",
                "mirror_off": "> 2 cm or 1° off, flips or not"}.get(kind, INJECTED.get(kind, ("",))[0])
        print(f"{kind} ({what}): {flagged}/{affected} affected frames flagged "
              f"({100 * flagged / max(affected, 1):.1f} %), cause named right {named}/{flagged} "
              f"({100 * named / max(flagged, 1):.1f} %)")
    print(f"clean typical: {clean[0]}/{clean[1]} solved frames flagged ({100 * clean[0] / max(clean[1], 1):.2f} %), "
          f"{clean_findings} run-level finding(s) in {args.seeds} recordings")
    for kind, values in offsets_ms.items():
        if values:
            print(f"{kind}: run-level time offset found in {len(values)}/{args.seeds} recordings, estimate "
                  f"{statistics.mean(values):.1f} ms mean, {min(values):.1f}–{max(values):.1f} ms (injected 30 ms)")
        else:
            print(f"{kind}: no run-level time offset found in {args.seeds} recordings")
    if other_findings:
        print("run-level findings on the other faults: " + ", ".join(f"{k} {n}" for k, n in other_findings.items()))
    if args.offline:
        for floor_m, floor_deg in FLOORS:
            d2, flagged = clean_motion_d2(clean_paths, work / "solved", floor_m, floor_deg)
            print(f"floors {floor_m * 1000:g} mm, {floor_deg:g}°: clean frames flagged {flagged}; motion-check d² "
                  f"mean {d2.mean():.2f}, p99 {np.percentile(d2, 99):.1f}, max {d2.max():.1f} over {len(d2)} "
                  f"(χ²₆: mean 6, 99 % 16.8; the 5σ limit 41.0)")
    if args.repeats <= 0:
        return
    rec = clean_paths[0]
    run_recording(rec, RunSettings(), work / "warm.rrd")  # fill the detection cache
    ratios = []
    for _ in range(args.repeats):
        walls = {}
        for checks in ("on", "off"):
            t0 = time.perf_counter()
            run_recording(rec, RunSettings(checks=checks), work / f"cost-{checks}.rrd")
            walls[checks] = time.perf_counter() - t0
        ratios.append(walls["on"] / walls["off"])
        print(f"  run wall time checks on {walls['on']:.2f} s, off {walls['off']:.2f} s", flush=True)
    print(f"cost: wall time checks on ÷ off = {statistics.median(ratios):.3f} (median of {len(ratios)})")


if __name__ == "__main__":
    main()
