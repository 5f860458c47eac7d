"""The issue 27 figures of the sweep `.rrd`: whole `agvviz` processes on the default qr_floor
recording (200 frames, `typical`), paired in one run, each from an empty detection cache.

Usage:  python bench/bench_sweep.py [--workdir DIR] [--repeats 3] [--solvers lm,ippe,p4p,sqpnp]
                                    [--python PYTHON] [--baseline-tree DIR] [--skip-rmse] [--timeline]

1. Output bytes: everything `agvviz sweep --set solver=<solvers>` writes into its folder
   (sweep.rrd, ranking.csv, ranking.md; before issue 27: a run per setting and overlay.rrd)
   ÷ the `.rrd` of one `agvviz run`. Target ≤ 1.5 (before: 5 files of 44 MB, ≈5).
2. Wall time: the sweep (`--jobs 2`) ÷ one cold `agvviz run`, measured in pairs (run, sweep,
   each with a fresh empty AGVVIZ_CACHE_DIR); the ratio of each pair, their median and spread;
   and the same for the CPU seconds of each command's whole process tree (sampled from /proc
   every 0.2 s; less load-dependent than wall time).
   Target ≤ 1.3 (before: 1.98 on a quiet machine). The machine is shared: quote the pairs.
   With ``--baseline-tree DIR`` every repeat also measures that checkout's pair (e.g. the tree
   before issue 27), alternating with this one, so before and after meet the same load.
   Then, in the same repeat, `agvviz diff sweep.rrd#<first solver> sweep.rrd#<second>` of that
   sweep: its wall and CPU seconds (user + system of the reaped process, from getrusage; the
   diff reads, compares — bootstrap and Wilcoxon — and prints), paired between the trees.
3. Each solver's position RMSE inside the sweep file (ranking.csv) against a standalone
   `agvviz run --set solver=S` (its summary): they must be equal.

With ``--timeline`` it only times one cold sweep of this tree (and one of ``--baseline-tree``) and
prints how busy its processes kept the machine: the CPU of the sweep's process tree (read from
/proc every 0.1 s, Linux only) in cores per half second, and each process's CPU seconds with its
start time and command line.

Every measurement is a child process (`PYTHON -m agvviz ...`, run in the measured checkout so
`-m` finds its agvviz) timed from start to exit; its output goes to DIR/logs/. The recording is
kept in DIR and reused.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
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
    parser.add_argument("--baseline-tree", type=Path, default=None, help="another checkout measured in turn")
    parser.add_argument("--skip-rmse", action="store_true", help="leave figure 3 out")
    parser.add_argument("--timeline", action="store_true", help="only the CPU timeline of one cold sweep")
    args = parser.parse_args()
    work = args.workdir.resolve()
    for sub in ("caches", "runs", "logs", "tmp"):
        shutil.rmtree(work / sub, ignore_errors=True)
        (work / sub).mkdir(parents=True)
    recording = work / "qr_floor.mcap"
    counter = iter(range(10_000))
    reaped_cpu = [0.0]  # CPU seconds of the last command's reaped processes (getrusage)

    def agvviz(tree: Path, *argv: str, cold: bool = True) -> tuple[float, float]:
        n = next(counter)
        env = dict(os.environ, PYTHONPATH=str(tree), TMPDIR=str(work / "tmp"))
        if cold:
            env["AGVVIZ_CACHE_DIR"] = str(work / "caches" / f"c{n}")
        log = work / "logs" / f"{n:03d}-{argv[0]}.log"
        print(f"  $ agvviz {' '.join(argv)}   (in {tree})", flush=True)
        t0 = time.perf_counter()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu_s: dict[int, float] = {}  # the child's process tree: pid → CPU seconds at its last sample
        with open(log, "w") as out:
            child = subprocess.Popen([args.python, "-m", "agvviz", *argv], env=env, cwd=tree, stdout=out,
                                     stderr=subprocess.STDOUT)
            while child.poll() is None:
                cpu_s.update(_tree_cpu_s(child.pid))
                time.sleep(0.2)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if child.returncode != 0:
            sys.exit(f"agvviz {' '.join(argv)} failed (exit {child.returncode}); see {log}")
        reaped_cpu[0] = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
        return wall, sum(cpu_s.values())

    if not recording.exists():
        agvviz(ROOT, "record", "qr_floor", "--out", str(recording), cold=False)
    if args.timeline:
        timed = {"this tree": ROOT, **({"baseline": args.baseline_tree.resolve()} if args.baseline_tree else {})}
        for n, (name, tree) in enumerate(timed.items()):
            env = dict(os.environ, PYTHONPATH=str(tree), TMPDIR=str(work / "tmp"),
                       AGVVIZ_CACHE_DIR=str(work / "caches" / f"t{n}"))
            argv = [args.python, "-m", "agvviz", "sweep", str(recording), "--set", f"solver={args.solvers}", "--jobs",
                    "2", "--out-dir", str(work / "runs" / f"timeline{n}")]
            print(f"{name} ({tree}):")
            _timeline(argv, env, tree, work / "logs" / f"timeline{n}.log")
        return
    trees = {"this tree": ROOT}
    if args.baseline_tree is not None:
        trees["baseline"] = args.baseline_tree.resolve()
    pairs = {name: [] for name in trees}
    cpu_pairs = {name: [] for name in trees}  # CPU seconds of each process tree (user + system)
    diffs = {name: [] for name in trees}  # (wall s, CPU s) of each `agvviz diff` of two settings
    first, second = args.solvers.split(",")[:2]
    written = {}
    for _ in range(args.repeats):
        for name, tree in trees.items():
            run_rrd = work / "runs" / f"{name.replace(' ', '_')}-run.rrd"
            sweep_dir = work / "runs" / f"{name.replace(' ', '_')}-sweep"
            run_s, run_cpu_s = agvviz(tree, "run", str(recording), "--out", str(run_rrd))
            shutil.rmtree(sweep_dir, ignore_errors=True)
            sweep_s, sweep_cpu_s = agvviz(tree, "sweep", str(recording), "--set", f"solver={args.solvers}", "--jobs",
                                          "2", "--out-dir", str(sweep_dir))
            pairs[name].append((run_s, sweep_s))
            sweep_file = sweep_dir / "sweep.rrd"
            diff_s, _ = agvviz(tree, "diff", f"{sweep_file}#{first}", f"{sweep_file}#{second}", cold=False)
            diffs[name].append((diff_s, reaped_cpu[0]))
            cpu_pairs[name].append((run_cpu_s, sweep_cpu_s))
            written[name] = (run_rrd, sweep_dir)
            print(f"  {name}: run {run_s:.1f} s, sweep {sweep_s:.1f} s, ratio {sweep_s / run_s:.2f}; CPU run "
                  f"{run_cpu_s:.1f} s, sweep {sweep_cpu_s:.1f} s, ratio {sweep_cpu_s / run_cpu_s:.2f}; "
                  f"diff {diff_s:.2f} s, CPU {reaped_cpu[0]:.2f} s", flush=True)

    n_solvers = len(args.solvers.split(","))
    print()
    for name in trees:
        run_rrd, sweep_dir = written[name]
        files = sorted(p for p in sweep_dir.iterdir() if p.is_file())
        sweep_bytes = sum(p.stat().st_size for p in files)
        ratios = [s / r for r, s in pairs[name]]
        print(f"{name} ({trees[name]}):")
        print(f"1. output bytes: sweep of {n_solvers} solvers, {len(files)} files, {sweep_bytes / 1e6:.1f} MB "
              f"({', '.join(f'{p.name} {p.stat().st_size / 1e6:.2f}' for p in files)}) ÷ one run "
              f"{run_rrd.stat().st_size / 1e6:.1f} MB = {sweep_bytes / run_rrd.stat().st_size:.2f}   (target ≤ 1.5)")
        print(f"2. wall: sweep ÷ one cold run, {len(ratios)} pairs {', '.join(f'{r:.2f}' for r in ratios)}: "
              f"median {statistics.median(ratios):.2f}; run median {statistics.median(r for r, _ in pairs[name]):.1f} s, "
              f"sweep median {statistics.median(s for _, s in pairs[name]):.1f} s   (target ≤ 1.3)")
        cpu_ratios = [s / r for r, s in cpu_pairs[name]]
        print(f"   CPU (all processes): sweep ÷ run, pairs {', '.join(f'{r:.2f}' for r in cpu_ratios)}: median "
              f"{statistics.median(cpu_ratios):.2f}; run median {statistics.median(r for r, _ in cpu_pairs[name]):.1f} s, "
              f"sweep median {statistics.median(s for _, s in cpu_pairs[name]):.1f} s")
        diff_walls, diff_cpus = [w for w, _ in diffs[name]], [c for _, c in diffs[name]]
        print(f"   diff {first} vs {second} of the sweep: wall {', '.join(f'{w:.2f}' for w in diff_walls)} s, "
              f"median {statistics.median(diff_walls):.2f} s; CPU {', '.join(f'{c:.2f}' for c in diff_cpus)} s, "
              f"median {statistics.median(diff_cpus):.2f} s")
    if "baseline" in trees:
        ratios = [a[1] / b[1] for a, b in zip(cpu_pairs["this tree"], cpu_pairs["baseline"])]
        diff_ratios = [a[1] / b[1] for a, b in zip(diffs["this tree"], diffs["baseline"])]
        print(f"this tree ÷ baseline, repeat by repeat: sweep CPU {', '.join(f'{r:.2f}' for r in ratios)} (median "
              f"{statistics.median(ratios):.2f}); diff CPU {', '.join(f'{r:.2f}' for r in diff_ratios)} (median "
              f"{statistics.median(diff_ratios):.2f})")
    if args.skip_rmse:
        return
    _, sweep_dir = written["this tree"]
    with open(sweep_dir / "ranking.csv", newline="") as f:
        ranking = {row["setting"]: row for row in csv.DictReader(f)}
    print("3. position RMSE [mm], in the sweep file vs a standalone run:")
    for solver in args.solvers.split(","):
        alone = work / "runs" / f"{solver}.rrd"
        agvviz(ROOT, "run", str(recording), "--set", f"solver={solver}", "--out", str(alone), cold=False)
        rmse = _summary(alone, args.python, ROOT)["position_error_mm"]["rmse"]
        inside = float(ranking[solver]["position_rmse_mm"])
        same = f"{rmse:.4g}" == f"{inside:.4g}"
        print(f"   {solver:6s} sweep {inside:.4g}  run {rmse:.4g}  {'equal' if same else 'DIFFERENT'}")


def _tree_cpu_s(root: int) -> dict[int, float]:
    """User + system CPU seconds of process ``root`` and of each of its descendants, from /proc
    (Linux). A process that ends between two samples loses what it used since the last one."""
    tick = os.sysconf("SC_CLK_TCK")
    children: dict[int, list[int]] = {}
    cpu_s: dict[int, float] = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            children.setdefault(int(fields[1]), []).append(int(name))
            cpu_s[int(name)] = (int(fields[11]) + int(fields[12])) / tick
    found, stack = {}, [root]
    while stack:
        pid = stack.pop()
        found[pid] = cpu_s.get(pid, 0.0)
        stack += children.get(pid, [])
    return found


def _timeline(argv: list[str], env: dict, tree: Path, log: Path, every_s: float = 0.1) -> None:
    """Run ``argv`` and print the CPU its process tree used over time (cores per half second)
    and per process, from /proc (user + system time of each process, sampled every ``every_s``)."""
    t0 = time.perf_counter()
    with open(log, "w") as out:
        child = subprocess.Popen(argv, env=env, cwd=tree, stdout=out, stderr=subprocess.STDOUT)
        last: dict[int, float] = {}
        seen: dict[int, tuple[float, str]] = {}
        bins: dict[int, float] = {}
        while child.poll() is None:
            time.sleep(every_s)
            now = time.perf_counter() - t0
            cpu = _tree_cpu_s(child.pid)
            bins[int(now / 0.5)] = bins.get(int(now / 0.5), 0.0) + sum(v - last.get(p, 0.0) for p, v in cpu.items())
            last.update(cpu)
            for pid in cpu.keys() - seen.keys():
                try:
                    with open(f"/proc/{pid}/cmdline") as f:
                        seen[pid] = (now, f.read().replace("\0", " ").strip()[:80])
                except OSError:
                    seen[pid] = (now, "?")
    wall = time.perf_counter() - t0
    print(f"sweep: exit {child.returncode}, {wall:.1f} s wall, {sum(last.values()):.1f} s CPU "
          f"({sum(last.values()) / wall:.2f} cores on average); log {log}")
    print("   t [s]  cores busy (process tree)")
    for b in range(int(wall / 0.5) + 1):
        cores = bins.get(b, 0.0) / 0.5
        print(f"  {b * 0.5:5.1f}  {cores:4.2f} {'#' * round(cores * 20)}")
    print("  CPU [s]  from [s]  process")
    for pid, cpu_s in sorted(last.items(), key=lambda kv: -kv[1]):
        print(f"  {cpu_s:7.2f}  {seen[pid][0]:7.1f}  {seen[pid][1]}")


def _summary(rrd: Path, python: str, tree: Path) -> dict:
    code = ("import json,sys; from agvviz.viz.readback import document_json; from agvviz.viz import paths; "
            "print(json.dumps(document_json(sys.argv[1], paths.RUN_SUMMARY)))")
    out = subprocess.run([python, "-c", code, str(rrd)], env=dict(os.environ, PYTHONPATH=str(tree)), cwd=tree,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


if __name__ == "__main__":
    main()
