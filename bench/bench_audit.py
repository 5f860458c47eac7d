"""The issue 15 figures (`agvviz audit`): its time on the default qr_floor recording, how it
grows with frames and markers, and its miss / false-flag rates over many seeds.

Usage:  python bench/bench_audit.py [--workdir DIR] [--seeds 20] [--skip-recording]

1. Time of `audit_recording` on the default qr_floor recording (20 s, 10 Hz, 1280×1024, seed 1,
   recorded into DIR once and reused): first with a cold detection cache (detection included),
   then again from the cache (collect = reading + the solve stage's payload parsing; solve = the
   bundle adjustment with its covariance).
2. Scaling (corner-level simulation, agvviz.evaluation.audit.synthetic, so detection does not count): the
   solve time against frames (duration 10…80 s on the same track: markers stay ~20) and against
   markers (grid_spacing_m 1.5 → 0.75 m: 2–4× more codes per frame, the same 200 frames).
3. Rates over --seeds seeds (synthetic, the default 20 s track) with the issue's injected
   errors — one code moved 5 cm, one turned 90°, one printed 2 % large, the camera pitched 1°
   and 2 cm higher: miss rate (an injected error not flagged in its group), false-flag rate
   (clean markers flagged / clean markers judged), injected estimates beyond 3σ, and the share
   of clean-marker components beyond 3σ (a check of the σ), under the ideal and typical
   profiles; then the clean recording (no injection): markers flagged, camera flagged.
   Under ``harsh`` the audit is not trustworthy (the intrinsics errors it does not estimate
   bias everything; see docs/audit.md) — measured and printed too, as a warning.
4. (``--figures 4``) The rates of 3 under ``typical`` with 0.3 px of per-marker systematic
   corner error in the simulation (what real corners carry, ``bench_render_vs_photos.py``), the
   audit's random effect for it off (``corner_bias_px=0``) and on (the default).
5. (``--figures 5``) ``harsh`` with the same corner errors, audited with ``intrinsics=true`` —
   what the audit's calibration-error note suggests.
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

INJECT = "marker:Q040:dx_m=0.05;marker:Q047:yaw_deg=90;marker:Q050:scale=0.02;camera:front:pitch_deg=1,dz_m=0.02"
INJECTED = {"Q040": ("position", 0), "Q047": ("yaw", 3), "Q050": ("scale", 6)}


def figure_1(workdir: Path, skip_recording: bool) -> None:
    from agvviz import scenarios as scenario_registry
    from agvviz.app.audit import audit_recording
    from agvviz.settings import RunSettings

    rec = workdir / "qr_floor-seed1.mcap"
    if not rec.exists():
        if skip_recording:
            print("1. skipped (no recording and --skip-recording)")
            return
        t = time.perf_counter()
        scenario_registry.record("qr_floor", rec, seed=1, overrides=[])
        print(f"   recorded {rec} in {time.perf_counter() - t:.1f} s")
    cache = workdir / "cache"
    shutil.rmtree(cache, ignore_errors=True)
    for label in ("cold cache", "warm cache"):
        result = audit_recording(rec, RunSettings(), cache_dir=cache)
        e = result.estimate
        print(f"1. default qr_floor ({label}): total {result.total_s:.2f} s = collect {result.collect_s:.2f} s "
              f"(detection source: {result.collected.detection_source}) + solve {e.solve_s:.2f} s; "
              f"{result.collected.data.n_frames} frames, {len(e.markers)} markers, {len(result.collected.data.obs_frame)} "
              f"observations, {e.n_params} unknowns, {e.n_residuals} residuals; flagged: "
              f"{[f.marker_id for f in e.markers if f.flagged] or 'none'}")


def _solve_time(options, seed: int = 1, sim_bias_px: float = 0.0, audit_bias_px: float | None = None,
                **audit_changes) -> tuple[float, object, object]:
    """Simulate (independent corner σ 0.1 px, plus ``sim_bias_px`` of per-marker systematic
    corner error) and audit with the corner σ known and ``corner_bias_px`` = ``audit_bias_px``
    (None: the default)."""
    from agvviz.evaluation.audit.estimate import estimate
    from agvviz.evaluation.audit.problem import AuditSettings
    from agvviz.evaluation.audit.synthetic import simulate, solver

    syn = simulate(options, seed, sigma_px=0.1, corner_bias_px=sim_bias_px)
    if audit_bias_px is not None:
        audit_changes["corner_bias_px"] = audit_bias_px
    settings = AuditSettings(sigma_px=0.1, **audit_changes)
    t = time.perf_counter()
    est = estimate(syn.data, settings, solver())
    return time.perf_counter() - t, syn, est


def figure_2() -> None:
    from agvviz.scenarios import qr_floor as q

    print("2. scaling (synthetic corners; solve time incl. start, covariance, gauge re-solves)")
    print(f"   {'frames':>6} {'markers':>7} {'obs':>6} {'unknowns':>8} {'solve s':>8} {'ms/frame':>8}")
    for duration in (10.0, 20.0, 40.0, 80.0):
        dt, syn, est = _solve_time(q.Options(duration_s=duration))
        d = syn.data
        print(f"   {d.n_frames:6d} {len(d.marker_ids):7d} {len(d.obs_frame):6d} {est.n_params:8d} {dt:8.2f} {1e3 * dt / d.n_frames:8.1f}")
    print(f"   {'spacing':>7} {'markers':>7} {'obs':>6} {'unknowns':>8} {'solve s':>8} {'ms/obs':>8}")
    for spacing, size in ((1.5, 0.5), (1.0, 0.5), (0.75, 0.4)):
        dt, syn, est = _solve_time(q.Options(grid_spacing_m=spacing, code_size_m=size))
        d = syn.data
        print(f"   {spacing:7.2f} {len(d.marker_ids):7d} {len(d.obs_frame):6d} {est.n_params:8d} {dt:8.2f} {1e3 * dt / len(d.obs_frame):8.2f}")


def rates(profile: str, seeds: int, inject: str, sim_bias_px: float = 0.0, audit_bias_px: float | None = None,
          **audit_changes) -> dict:
    from agvviz.scenarios import qr_floor as q

    o = q.Options(realism=profile, inject=inject)
    out = {"misses": 0, "injected": 0, "false": 0, "justified": 0, "clean": 0, "beyond3": 0, "cam_miss": 0, "cam_false": 0,
           "cam_beyond3": 0, "z": [], "times": [], "calibration_note": 0}
    for seed in range(seeds):
        dt, syn, est = _solve_time(o, seed, sim_bias_px, audit_bias_px, **audit_changes)
        out["calibration_note"] += any("calibration error" in m for m in est.messages)
        out["times"].append(dt)
        for f in est.markers:
            if f.status == "seen too little":
                continue
            z = (f.delta - syn.marker_truth[f.marker_id]) / f.sigma
            if inject and f.marker_id in INJECTED:
                group, k = INJECTED[f.marker_id]
                out["injected"] += 1
                out["misses"] += not (f.flagged and group in f.reasons)
                out["beyond3"] += abs(z[k]) > 3
            else:
                out["clean"] += 1
                truth = syn.marker_truth[f.marker_id]
                # a flag is false unless the marker's true (drawn) error reaches a minimum size
                justified = (np.linalg.norm(truth[:3]) >= 0.01 or abs(math.degrees(truth[3])) >= 1.0
                             or math.degrees(np.linalg.norm(truth[4:6])) >= 1.0 or abs(truth[6]) >= 0.005)
                out["false"] += f.flagged and not justified
                out["justified"] += f.flagged and justified
                out["z"].extend(z[np.isfinite(z)])
        cam = est.cameras[0]
        zc = (cam.correction - syn.camera_truth["front"]) / cam.sigma
        if inject:
            out["cam_miss"] += set(cam.reasons) != {"translation", "rotation"}
            out["cam_beyond3"] += bool(np.any(np.abs(zc[[2, 3]]) > 3))
        else:
            out["cam_false"] += cam.flagged
            out["cam_beyond3"] += bool(np.any(np.abs(zc) > 3))
    return out


def figure_3(seeds: int, profiles=("ideal", "typical", "harsh"), sim_bias_px: float = 0.0,
             audit_bias_px: float | None = None, label: str = "3.", **audit_changes) -> None:
    print(f"{label} rates over {seeds} seeds (synthetic corners σ 0.1 px independent, {sim_bias_px:g} px systematic per "
          f"marker corner; audit corner_bias_px={'default' if audit_bias_px is None else f'{audit_bias_px:g}'} "
          f"{' '.join(f'{k}={v}' for k, v in audit_changes.items())}; default 20 s track)")
    for profile in profiles:
        for inject in (INJECT, ""):
            r = rates(profile, seeds, inject, sim_bias_px, audit_bias_px, **audit_changes)
            z = np.abs(np.array(r["z"]))
            what = "injected" if inject else "clean"
            line = (f"   {profile:8s} {what:8s}: false flags {r['false']}/{r['clean']} clean markers "
                    f"({100 * r['false'] / max(r['clean'], 1):.2f} %; {r['justified']} more flagged for a drawn error "
                    f"above the minimum size), clean components beyond 3σ of the truth "
                    f"{100 * np.mean(z > 3):.2f} % (normal: 0.27 %), solve {np.mean(r['times']):.2f} s mean, "
                    f"calibration-error note on {r['calibration_note']}/{seeds}")
            if inject:
                line += (f"; misses {r['misses']}/{r['injected']} ({100 * r['misses'] / max(r['injected'], 1):.1f} %), "
                         f"injected beyond 3σ {r['beyond3']}/{r['injected']}, camera missed {r['cam_miss']}/{seeds}, "
                         f"camera dz/pitch beyond 3σ {r['cam_beyond3']}/{seeds}")
            else:
                line += (f"; camera flagged {r['cam_false']}/{seeds} (a drawn calibration error may justify it), "
                         f"camera beyond 3σ of its true correction {r['cam_beyond3']}/{seeds}")
            print(line, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--skip-recording", action="store_true")
    parser.add_argument("--figures", default="1,2,3")
    parser.add_argument("--profiles", default="ideal,typical,harsh")
    args = parser.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench_audit_"))
    workdir.mkdir(parents=True, exist_ok=True)
    figures = {int(f) for f in args.figures.split(",")}
    if 1 in figures:
        figure_1(workdir, args.skip_recording)
    if 2 in figures:
        figure_2()
    if 3 in figures:
        figure_3(args.seeds, tuple(args.profiles.split(",")))
    if 4 in figures:
        # real corners carry a per-marker systematic error (bench_render_vs_photos: ≈0.3 px with
        # ECC): the audit with its random effect off (corner_bias_px=0, the old model) and on
        for audit_bias in (0.0, None):
            figure_3(args.seeds, ("typical",), sim_bias_px=0.3, audit_bias_px=audit_bias, label="4.")
    if 5 in figures:
        # harsh with the intrinsics solved, as the calibration-error note suggests
        figure_3(args.seeds, ("harsh",), sim_bias_px=0.3, label="5.", intrinsics=True)


if __name__ == "__main__":
    main()
