"""The issue 27 figures of the sweep `.rrd`: whole `agvviz` processes on the default qr_floor
recording (200 frames, `typical`), paired in one run, each from an empty detection cache.

Usage:  python bench/bench_sweep.py [--workdir DIR] [--repeats 3] [--solvers lm,ippe,p4p,sqpnp]
                                    [--python PYTHON]

1. Output bytes: everything `agvviz sweep --set solver=<solvers>` writes (sweep.rrd,
   ranking.csv, ranking.md) ÷ the `.rrd` of one `agvviz run`. Target ≤ 1.5 (before: 5 files of
   44 MB, ≈5).
2. Wall time: the sweep (`--jobs 2`) ÷ one cold `agvviz run`, measured in pairs (run, sweep,
   run, sweep, …, each with a fresh empty AGVVIZ_CACHE_DIR); the ratio of each pair, its median.
   Target ≤ 1.3 (before: 1.98). The machine is shared: the pairs' spread is printed too.
3. Each solver's position RMSE inside the sweep file (ranking.csv) against a standalone
   `agvviz run --set solver=S` (its summary): they must be equal.

Every measurement is a child process (`PYTHON -m agvviz ...`) timed from start to exit; its
output goes to DIR/logs/. The recording is kept in DIR and reused.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/agvviz-bench-sweep"))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--solvers", default="lm,ippe,p4p,sqpnp")
    parser.add_argument("--python", default=sys.executable)
    args = parser.parse_args()
    work = args.workdir
    for sub in ("caches", "runs", "logs", "tmp"):
        shutil.rmtree(work / sub, ignore_errors=True)
        (work / sub).mkdir(parents=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(work / "tmp"))
    recording = work / "qr_floor.mcap"
    counter = iter(range(10_000))

    def agvviz(*argv: str, cold: bool = True) -> float:
        n = next(counter)
        child_env = dict(env, AGVVIZ_CACHE_DIR=str(work / "caches" / f"c{n}")) if cold else env
        log = work / "logs" / f"{n:03d}-{argv[0]}.log"
        print("  $ agvviz " + " ".join(argv), flush=True)
        t0 = time.perf_counter()
        with open(log, "w") as out:
            done = subprocess.run([args.python, "-m", "agvviz", *argv], env=child_env, stdout=out,
                                  stderr=subprocess.STDOUT, check=False)
        wall = time.perf_counter() - t0
        if done.returncode != 0:
            sys.exit(f"agvviz {' '.join(argv)} failed (exit {done.returncode}); see {log}")
        return wall

    if not recording.exists():
        agvviz("record", "qr_floor", "--out", str(recording), cold=False)
    run_rrd = work / "runs" / "run.rrd"
    sweep_dir = work / "runs" / "sweep"
    pairs = []
    for _ in range(args.repeats):
        run_s = agvviz("run", str(recording), "--out", str(run_rrd))
        shutil.rmtree(sweep_dir, ignore_errors=True)
        sweep_s = agvviz("sweep", str(recording), "--set", f"solver={args.solvers}", "--jobs", "2",
                         "--out-dir", str(sweep_dir))
        pairs.append((run_s, sweep_s))
        print(f"  pair: run {run_s:.1f} s, sweep {sweep_s:.1f} s, ratio {sweep_s / run_s:.2f}", flush=True)

    run_bytes = run_rrd.stat().st_size
    written = sorted(p for p in sweep_dir.iterdir() if p.is_file())
    sweep_bytes = sum(p.stat().st_size for p in written)
    ratios = [s / r for r, s in pairs]
    n_solvers = len(args.solvers.split(","))
    print()
    print(f"1. output bytes: sweep of {n_solvers} solvers {sweep_bytes / 1e6:.1f} MB "
          f"({', '.join(f'{p.name} {p.stat().st_size / 1e6:.2f} MB' for p in written)}) ÷ one run "
          f"{run_bytes / 1e6:.1f} MB = {sweep_bytes / run_bytes:.2f}   (target ≤ 1.5; before ≈5)")
    print(f"2. wall: sweep ÷ one cold run, {len(pairs)} pairs: median {statistics.median(ratios):.2f} "
          f"(min {min(ratios):.2f}, max {max(ratios):.2f}); run median {statistics.median(r for r, _ in pairs):.1f} s, "
          f"sweep median {statistics.median(s for _, s in pairs):.1f} s   (target ≤ 1.3; before 1.98)")
    with open(sweep_dir / "ranking.csv", newline="") as f:
        ranking = {row["setting"]: row for row in csv.DictReader(f)}
    print("3. position RMSE [mm], in the sweep file vs a standalone run:")
    for solver in args.solvers.split(","):
        alone = work / "runs" / f"{solver}.rrd"
        agvviz("run", str(recording), "--set", f"solver={solver}", "--out", str(alone), cold=False)
        summary = _summary(alone, args.python, env)
        rmse = summary["position_error_mm"]["rmse"]
        inside = float(ranking[solver]["position_rmse_mm"])
        print(f"   {solver:6s} sweep {inside:.4g}  run {rmse:.4g}  {'equal' if f'{rmse:.4g}' == f'{inside:.4g}' else 'DIFFERENT'}")


def _summary(rrd: Path, python: str, env: dict) -> dict:
    code = ("import json,sys; from agvviz.viz.readback import document_json; from agvviz.viz import paths; "
            "print(json.dumps(document_json(sys.argv[1], paths.RUN_SUMMARY)))")
    out = subprocess.run([python, "-c", code, str(rrd)], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


if __name__ == "__main__":
    main()
