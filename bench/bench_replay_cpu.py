"""The issue 27 figure "a replay's per-setting CPU": the CPU seconds of one in-process replay of
the default qr_floor recording (200 frames) whose detections are cached — what a warm run and
each follower of a sweep pay per setting, without start-up and imports.

Usage:  python bench/bench_replay_cpu.py [--workdir DIR] [--repeats 5] [--runs 3]
                                         [--solver sqpnp] [--baseline-tree DIR] [--python PYTHON]

Each repeat starts one child process per tree (``PYTHON -c ...`` with PYTHONPATH=TREE, the trees
alternating, so before and after meet the same load). The child calls
``agvviz.app.run.run_recording(REC, solver=SOLVER, jobs=1, images=False, writer_process=False)``
once to warm up (imports, the detection cache of its own AGVVIZ_CACHE_DIR, the scan cache),
then ``--runs`` times more, and reports the process CPU time (``time.process_time``) of each
of those; the figure of a repeat is their median. Printed: every repeat's figure per tree, their
median and spread and, with ``--baseline-tree``, this tree ÷ baseline pair by pair. The
recording is made once in DIR (``agvviz record qr_floor``) and reused. The machine may be shared:
quote the pairs, not one number.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import json, os, sys, time
from pathlib import Path
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings, apply_overrides
recording, out, solver, runs = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4])
settings = apply_overrides(RunSettings(), [f"solver={solver}"])
def replay():
    run_recording(recording, settings, out, jobs=1, images=False, writer_process=False)
replay()  # warm-up: imports, caches
cpu = []
for _ in range(runs):
    t0 = time.process_time()
    replay()
    cpu.append(time.process_time() - t0)
print(json.dumps(cpu))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/agvviz-bench-replay-cpu"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--runs", type=int, default=3, help="timed replays per child (their median is a repeat's figure)")
    parser.add_argument("--solver", default="sqpnp")
    parser.add_argument("--python", default=sys.executable)
    parser.add_argument("--baseline-tree", type=Path, default=None, help="another checkout measured in turn")
    args = parser.parse_args()
    work = args.workdir.resolve()
    work.mkdir(parents=True, exist_ok=True)
    recording = work / "qr_floor.mcap"
    trees = {"this tree": ROOT}
    if args.baseline_tree is not None:
        trees["baseline"] = args.baseline_tree.resolve()
    if not recording.exists():
        env = dict(os.environ, PYTHONPATH=str(ROOT), AGVVIZ_CACHE_DIR=str(work / "cache-record"))
        subprocess.run([args.python, "-m", "agvviz", "record", "qr_floor", "--out", str(recording)],
                       env=env, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    figures: dict[str, list[float]] = {name: [] for name in trees}
    for repeat in range(args.repeats):
        for name, tree in trees.items():
            tag = name.replace(" ", "_")
            env = dict(os.environ, PYTHONPATH=str(tree), AGVVIZ_CACHE_DIR=str(work / f"cache-{tag}"))
            done = subprocess.run(
                [args.python, "-c", CHILD, str(recording), str(work / f"{tag}.rrd"), args.solver, str(args.runs)],
                env=env, cwd=tree, capture_output=True, text=True, check=False,
            )
            if done.returncode != 0:
                sys.exit(f"{name}: the replay failed (exit {done.returncode}):\n{done.stderr[-2000:]}")
            cpu = json.loads(done.stdout.strip().splitlines()[-1])
            figures[name].append(statistics.median(cpu))
            print(f"  repeat {repeat + 1}, {name}: CPU s per replay {', '.join(f'{c:.3f}' for c in cpu)}", flush=True)
    print()
    for name, tree in trees.items():
        values = figures[name]
        print(f"{name} ({tree}): CPU of one replay (solver={args.solver}, 200 frames), median of each repeat: "
              f"{', '.join(f'{v:.3f}' for v in values)}; median {statistics.median(values):.3f} s "
              f"(min {min(values):.3f}, max {max(values):.3f})")
    if "baseline" in trees:
        ratios = [a / b for a, b in zip(figures["this tree"], figures["baseline"])]
        print(f"this tree ÷ baseline, repeat by repeat: {', '.join(f'{r:.3f}' for r in ratios)} "
              f"(median {statistics.median(ratios):.3f}, min {min(ratios):.3f}, max {max(ratios):.3f})")


if __name__ == "__main__":
    main()
