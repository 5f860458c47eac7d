"""The issue 25 figures of the check stage (docs/suspects.md): injected faults flagged and named,
clean recordings' flag rate, and the checks' run-time cost — every replay with ``truth=ignore``
(truth is read only here, to say which frames are affected).

Usage:  python bench/bench_checks.py [--seeds 20] [--workdir DIR] [--duration-s 6] [--repeats 3]
        [--first-seed 0] [--kinds late,offset]   (a part: some seeds, some faults; --repeats 0: no cost)

Per seed, ``qr_floor`` recordings (``duration_s``, 640×512, focal 500 px, supersample 2, realism
typical): clean, and one per fault of :data:`INJECTED` — Q015 turned 90° or moved 5 cm in the
map, a 30 ms camera latency (realism) and a 30 ms stamp offset (inject), the camera knocked 1° /
2 cm at 3 s, Q015's payload 0.3 m off in a recording without a map, and mirror flips (the
planar-ambiguity recipe :data:`AMBIGUOUS`, 1280×1024). Printed:

1. injected: affected frames (truth says > 2 cm or > 1° off, or Q015 in the frame's used or
   left-out markers) flagged — a suspect of its own, or covered by a run-level finding (a camera's
   time offset, stated at the end of the run for every frame of the camera) — and of those the
   share named right: the frame's own suspect's cause (and code), else the covering finding's
   (Q015's map_entry; time_offset); target ≥ 95 % flagged, ≥ 90 % named right;
2. clean: flagged frames (as in 1) ÷ solved frames; target ≤ 1 %; then the run-level findings
   made on clean recordings and on the other faults, and the findings' offset estimates on the
   time-offset kinds;
3. cost: `run_recording` wall time (``.rrd`` written, detection cache warm) with ``checks=on`` ÷
   ``checks=off`` on the first clean recording, the median of ``--repeats`` alternating pairs;
   target ≤ 1.05.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from agvviz import scenarios
from agvviz.app.run import run_recording
from agvviz.replay.run import replay_checked, replay_frames
from agvviz.settings import RunSettings

SMALL = ["width_px=640", "height_px=512", "focal_px=500.0", "supersample=2"]
#: The planar-ambiguity recipe of docs/realism.md (small far ArUco markers, 1280×1024): mirror flips.
AMBIGUOUS = ["marker_family=DICT_4X4_1000", "code_size_m=0.06", "cam_height_m=3", "cam_lookahead_m=1",
             "grid_spacing_m=2.5", "rate_hz=5"]
CODE = "Q015"
#: The kinds whose fault is a camera time offset of 30 ms (their findings' estimates are printed).
OFFSET_KINDS = ("late", "offset")
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
    parser.add_argument("--duration-s", type=float, default=6.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--kinds", default=",".join(INJECTED), help="faults to record and replay, comma-separated")
    args = parser.parse_args()
    kinds = [k for k in args.kinds.split(",") if k]
    unknown = sorted(set(kinds) - set(INJECTED))
    if unknown:
        parser.error(f"unknown kinds {unknown}: choose from {', '.join(INJECTED)}")
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_checks_"))
    work.mkdir(parents=True, exist_ok=True)
    overrides = SMALL + [f"duration_s={args.duration_s:g}"]
    counts = {k: [0, 0, 0] for k in kinds}  # affected, flagged, named right
    clean = [0, 0]  # suspects, solved
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
        frames, findings = replay_checked(path, RunSettings(truth="ignore"))
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
            truth = {f.index: f for f in replay_frames(path, RunSettings()) if f.solved}
            frames, findings = replay_checked(path, RunSettings(truth="ignore"))
            if kind in OFFSET_KINDS:
                offsets_ms[kind] += [f.offset_s * 1000 for f in findings if f.offset_s is not None]
            else:
                other_findings[kind] += len(findings)
            for f in frames:
                t = truth.get(f.index)
                if t is None:
                    continue
                off = t.position_error_m > 0.02 or abs(t.heading_error_deg) > 1.0
                if not (off or (code is not None and code in f.used_marker_ids + f.excluded_marker_ids)):
                    continue
                said = verdict(f, findings)
                counts[kind][0] += 1
                counts[kind][1] += said is not None
                counts[kind][2] += (said is not None and said.cause == cause
                                    and (code is None or getattr(said, "marker_id", None) == code))
        print(f"seed {seed}: clean {clean[0]}/{clean[1]}, " + ", ".join(f"{k} {c[1]}/{c[0]} named {c[2]}" for k, c in counts.items()), flush=True)
    for kind, (affected, flagged, named) in counts.items():
        print(f"{kind} ({INJECTED[kind][0]}): {flagged}/{affected} affected frames flagged "
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
