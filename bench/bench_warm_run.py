"""The issue 27 figure "a warm run ÷ a cold run": whole `agvviz` processes on the default qr_floor
recording (200 frames, `agvviz record qr_floor` defaults), paired in one run.

Usage:  python bench/bench_warm_run.py [--workdir DIR] [--repeats 5] [--baseline-tree DIR]
                                       [--python PYTHON]

One pair: a cold `agvviz run REC` (solver lm, a fresh empty AGVVIZ_CACHE_DIR: every frame is
detected), then a warm `agvviz run REC --set solver=ippe` with the same cache (the detections
are read from it; only the solve, checks, logging and writing remain). The figure is warm wall
time ÷ cold wall time of each pair; the pairs, their median and spread are printed, with each
run's wall and CPU seconds (CPU: the process and the children it reaped; detection workers of
a forkserver are not reaped by the command and are left out). Target ≤ 0.3 (before issue 27: 0.5).

With ``--baseline-tree DIR`` (e.g. the tree before this change:
`git -C REPO worktree add /tmp/base b72f381`) every repeat also measures that checkout's pair,
alternating with this one, so before and after meet the same load; the closing line gives the
after ÷ before ratio of the warm run's wall time, pair by pair.

Every measurement is a child process (`PYTHON -m agvviz ...`, run in the measured checkout so
`-m` finds its agvviz), timed from start to exit; its output goes to DIR/logs/. Both trees are
byte-compiled first (`compileall`), as an installed package is: otherwise a process run with
PYTHONDONTWRITEBYTECODE would compile every module at every start. The recording is kept in DIR
and reused. The machine may be shared: quote the pairs, not one number.
"""

from __future__ import annotations

import argparse
import compileall
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET = 0.3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/agvviz-bench-warm"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--python", default=sys.executable)
    parser.add_argument("--baseline-tree", type=Path, default=None, help="another checkout measured in turn")
    args = parser.parse_args()
    work = args.workdir.resolve()
    for sub in ("caches", "runs", "logs", "tmp"):
        shutil.rmtree(work / sub, ignore_errors=True)
        (work / sub).mkdir(parents=True)
    recording = work / "qr_floor.mcap"
    trees = {"this tree": ROOT}
    if args.baseline_tree is not None:
        trees["baseline"] = args.baseline_tree.resolve()
    for tree in trees.values():
        compileall.compile_dir(tree / "agvviz", quiet=1)
    counter = iter(range(100_000))

    def agvviz(tree: Path, cache: Path, *argv: str) -> tuple[float, float]:
        """(wall s, CPU s) of one `agvviz` child with AGVVIZ_CACHE_DIR=cache."""
        n = next(counter)
        env = dict(os.environ, PYTHONPATH=str(tree), TMPDIR=str(work / "tmp"), AGVVIZ_CACHE_DIR=str(cache))
        log = work / "logs" / f"{n:03d}-{argv[0]}.log"
        print(f"  $ agvviz {' '.join(argv)}   (in {tree})", flush=True)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        with open(log, "w") as out:
            done = subprocess.run([args.python, "-m", "agvviz", *argv], env=env, cwd=tree, stdout=out,
                                  stderr=subprocess.STDOUT, check=False)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if done.returncode != 0:
            sys.exit(f"agvviz {' '.join(argv)} failed (exit {done.returncode}); see {log}")
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        return wall, cpu

    if not recording.exists():
        agvviz(ROOT, work / "caches" / "record", "record", "qr_floor", "--out", str(recording))
    pairs: dict[str, list[tuple[tuple[float, float], tuple[float, float]]]] = {name: [] for name in trees}
    for repeat in range(args.repeats):
        for name, tree in trees.items():
            cache = work / "caches" / f"{name.replace(' ', '_')}-{repeat}"  # fresh and empty: cold
            tag = name.replace(" ", "_")
            cold = agvviz(tree, cache, "run", str(recording), "--out", str(work / "runs" / f"{tag}-cold.rrd"))
            warm = agvviz(tree, cache, "run", str(recording), "--set", "solver=ippe",
                          "--out", str(work / "runs" / f"{tag}-warm.rrd"))
            pairs[name].append((cold, warm))
            print(f"  {name}: cold {cold[0]:.2f} s, warm {warm[0]:.2f} s, warm ÷ cold {warm[0] / cold[0]:.3f}",
                  flush=True)

    print()
    for name, tree in trees.items():
        ratios = [w[0] / c[0] for c, w in pairs[name]]
        print(f"{name} ({tree}):")
        print(f"  warm ÷ cold, {len(ratios)} pairs: {', '.join(f'{r:.3f}' for r in ratios)}; "
              f"median {statistics.median(ratios):.3f} (min {min(ratios):.3f}, max {max(ratios):.3f})   "
              f"(target ≤ {TARGET})")
        print(f"  cold: wall median {statistics.median(c[0] for c, _ in pairs[name]):.2f} s, "
              f"CPU median {statistics.median(c[1] for c, _ in pairs[name]):.2f} s; "
              f"warm: wall median {statistics.median(w[0] for _, w in pairs[name]):.2f} s, "
              f"CPU median {statistics.median(w[1] for _, w in pairs[name]):.2f} s")
    if "baseline" in trees:
        warm_after = [w[0] for _, w in pairs["this tree"]]
        warm_before = [w[0] for _, w in pairs["baseline"]]
        per_pair = [a / b for a, b in zip(warm_after, warm_before)]
        cpu_per_pair = [a[1] / b[1] for (_, a), (_, b) in zip(pairs["this tree"], pairs["baseline"])]
        print(f"warm run, this tree ÷ baseline, pair by pair: wall {', '.join(f'{r:.2f}' for r in per_pair)} "
              f"(median {statistics.median(per_pair):.2f}); CPU {', '.join(f'{r:.2f}' for r in cpu_per_pair)} "
              f"(median {statistics.median(cpu_per_pair):.2f})")


if __name__ == "__main__":
    main()
