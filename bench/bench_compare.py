"""Figures for issue 5 (compare runs): time to diff two 1000-frame runs, size of the overlay,
time to sweep 6 settings over the default recording.

Usage:  python bench/bench_compare.py [--frames 1000] [--jobs 2] [--keep DIR] [--skip-sweep]

1. Records qr_floor (default options in the ideal world, 10 Hz) long enough for ``--frames`` frames, replays it
   with lm and p4p (as a 2-setting sweep, in parallel), then times ``agvviz diff`` on the two
   runs: in-process per step (read back, compare with 2000 bootstrap resamples, write overlay)
   and end to end through the CLI (a fresh process, imports included); prints the overlay
   sizes with and without images.
2. Records the default qr_floor in the ideal world (20 s at 10 Hz = 200 frames) and times
   ``agvviz sweep --set solver=p4p,lm,ippe --set lm.max_iters=3,10`` (6 settings).

The machine's other load changes every timing here: read them with ``uptime`` next to them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from agvviz import scenarios as scenario_registry
from agvviz.app.diff import diff
from agvviz.app.sweep import parse_grid, sweep


def _mb(path: Path) -> str:
    return f"{path.stat().st_size / 1e6:.1f} MB"


def _load() -> str:
    return "load average " + ", ".join(f"{x:.1f}" for x in os.getloadavg())


def bench_diff(tmp: Path, frames: int, jobs: int) -> None:
    recording = tmp / "qr_floor_long.mcap"
    t0 = time.perf_counter()
    scenario_registry.record("qr_floor", recording, seed=0, overrides=[f"duration_s={frames / 10}", "rate_hz=10", "realism=ideal"])
    print(f"recorded {frames} frames in {time.perf_counter() - t0:.0f} s ({_mb(recording)})")
    t0 = time.perf_counter()
    runs = sweep(recording, parse_grid(["solver=lm,p4p"]), out_dir=tmp / "long", jobs=jobs, images=False)
    print(f"replayed lm and p4p over {frames} frames in {time.perf_counter() - t0:.0f} s ({_load()})")
    a, b = (next(e.out_path for e in runs.entries if e.label == label) for label in ("lm", "p4p"))
    print(f"run sizes: lm {_mb(a)}, p4p {_mb(b)}")

    outcome = diff(a, b)
    print("diff in-process, table only: " + ", ".join(f"{k} {v:.2f} s" for k, v in outcome.seconds.items()))
    overlay = tmp / "overlay.rrd"
    outcome = diff(a, b, overlay_path=overlay)
    print("diff in-process with overlay: " + ", ".join(f"{k} {v:.2f} s" for k, v in outcome.seconds.items())
          + f" (total {sum(outcome.seconds.values()):.2f} s)")
    small = diff(a, b, overlay_path=tmp / "overlay_no_images.rrd", images=False).overlay_path
    print(f"overlay size: {_mb(overlay)} with A's images, {_mb(small)} without (--no-images)")
    agvviz = Path(sys.executable).with_name("agvviz")
    t0 = time.perf_counter()
    subprocess.run([agvviz, "diff", a, b, "--out", tmp / "overlay_cli.rrd"], check=True, capture_output=True)
    print(f"`agvviz diff A B --out overlay.rrd` end to end: {time.perf_counter() - t0:.2f} s ({_load()})")
    c = outcome.comparison
    row = c.row("position_rmse_mm")
    print(f"  {len(c.common)} common frames; position RMSE lm {row.a:.3f} mm, p4p {row.b:.3f} mm, "
          f"p = {row.p_value:.2g}")


def bench_sweep(tmp: Path, jobs: int) -> None:
    recording = tmp / "qr_floor.mcap"
    scenario_registry.record("qr_floor", recording, seed=0, overrides=["realism=ideal"])
    t0 = time.perf_counter()
    outcome = sweep(recording, parse_grid(["solver=p4p,lm,ippe", "lm.max_iters=3,10"]), out_dir=tmp / "sweep",
                    jobs=jobs)
    elapsed = time.perf_counter() - t0
    frames = outcome.entries[0].metrics.get("frames") or 0
    print(f"sweep of 6 settings over the default recording ({frames} frames) with --jobs {jobs}: "
          f"{elapsed:.0f} s ({_load()})")
    for e in outcome.entries:
        rmse = e.metrics.get("position_rmse_mm")
        print(f"  #{e.rank or '-'} {e.label}: solved {e.metrics.get('solved')}, position RMSE "
              f"{'—' if rmse is None else f'{rmse:.3f}'} mm, {e.timing.get('time_per_frame_ms', 0):.0f} ms/frame"
              + ("" if e.ok else f" FAILED {e.error}"))
    print(f"sweep overlay: {_mb(outcome.overlay_path)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=1000, help="frames of each diffed run")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--keep", type=Path, help="keep the files in this folder")
    parser.add_argument("--skip-sweep", action="store_true")
    parser.add_argument("--skip-diff", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.keep or Path(scratch)
        tmp.mkdir(parents=True, exist_ok=True)
        if not args.skip_diff:
            bench_diff(tmp, args.frames, args.jobs)
        if not args.skip_sweep:
            bench_sweep(tmp, args.jobs)


if __name__ == "__main__":  # required: the sweep's worker processes are spawned
    main()
