"""The issue 12 figures ("One replay graph"): whole `agvviz` processes on the default qr_floor
recording, paired in one run, each beside today's baseline (commit ad2bde5) and its target.

Usage:  python bench/bench_replay_graph.py [--workdir DIR] [--repeats 2] [--skip-2000]
                                          [--figures 1,2,3,4,5,6,7] [--python PYTHON]
                                          [--source TREE] [--baseline TREE]

Every measurement is a child process (`PYTHON -m agvviz ...`, and the bare OpenCV loop as
`PYTHON bench/bench_replay_graph.py --bare-loop REC`), timed by wall clock from start to exit.
Memory, two ways: GNU `/usr/bin/time`'s peak RSS of the largest single process (the command or
a child it reaped; os.wait4 in this process would not do: a child's ru_maxrss starts from the
high-water mark of the process that forked it), and the peak of the summed PSS of every process
of the child's tree, sampled every 0.2 s — the only one that sees detection workers forked by a
multiprocessing forkserver, which the command never reaps. CPU time is the tree's, as last
sampled. The commands are printed as they run (without the /usr/bin/time prefix); their output
goes to DIR/logs/.

1. `agvviz run` frames/s ÷ the bare OpenCV loop's frames/s (imdecode + detectAndDecodeMulti +
   solvePnP IPPE_SQUARE per frame, no refinement, no logging), tracking on and off, each run
   paired with the bare loop run just before it (bare, on, bare, off, … `--repeats` times);
   the median ratio of the pairs and their spread. Target (issue 27) ≥ 3.0 tracking on (issue 12's
   were 2.0 on, 1.2 off); tracking off is reported. With `--baseline TREE` each bare run is
   followed by a run of each tree, in alternating order: before and after in the same pairs.
2. `agvviz sweep --set solver=lm,p4p,ippe,sqpnp --jobs 2` wall time ÷ one `agvviz run`, both
   from a cold detection cache; median over repeats. Target ≤ 1.3.
3. A first `agvviz run` (cold cache, lm) ÷ a second one with another solver (ippe) on the
   now-detected recording; median over repeats. Target ≥ 10.
4. Peak memory (summed PSS of the process tree) of `agvviz run` on 2000 frames ÷ on 200
   frames (cold caches), and the same of `agvviz sweep --set solver=lm,ippe --jobs 2`.
   Target ≤ 1.15 (both).
5. Position and heading RMSE of each solver, tracking on and off, read from the run summary
   in each `.rrd`, against the baseline values. Target within 5 % (both), same frames solved.
6. Runs of equal settings (cold cache, warm cache, `--jobs 1`) give `.rrd` files that
   `rerun rrd compare --unordered` finds equal.
7. CPU time per frame of the detect stage (in one process on one OpenCV thread, as a worker
   detects; `--frame-costs REC`), split into decode, undistort, zxing-cpp detection, ECC
   refinement and tracking, module sampling and the rest, tracking on and off; beside the bare
   loop's decode, detect and solvePnP. Not a default figure (`--figures 7`).

"Cold" is a fresh, empty AGVVIZ_CACHE_DIR under DIR/caches/ (DIR's caches, runs and logs are
emptied at every start); every child also gets TMPDIR and XDG_CACHE_HOME inside DIR, so nothing
is written outside DIR.
Recordings are kept in DIR and reused (the 2000-frame one takes minutes to record).
Options a tree does not have yet (the `tracking` setting, `agvviz run --jobs`) are found in
`agvviz run --help`: without `tracking`, runs use the tree's only detection ("no tracking");
without `--jobs`, the `--jobs 1` comparison of figure 6 is skipped. A figure whose child fails
is reported as not measured and the others go on.
`--python` measures another tree's agvviz (its venv's interpreter): that is how the baseline
below was measured.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SWEEP_SOLVERS = ("lm", "p4p", "ippe", "sqpnp")
MEMORY_SWEEP_SOLVERS = ("lm", "ippe")  # figure 4's sweep
ACCURACY_SOLVERS = ("lm", "p4p", "ippe", "planar", "sqpnp", "epnp")
CODE_SIZE_M = 0.5  # qr_floor's default code_size_m
TIME = "/usr/bin/time"  # GNU time: peak RSS (%M, KiB) of one command
SAMPLE_S = 0.2  # interval of the process-tree samples (PSS, CPU)

# Today's baseline: commit ad2bde5 (the last commit before any issue-12 work), checked out with
# `git worktree add /tmp/h4/base ad2bde5` in its own venv, measured on this 2-core machine by
#   python bench/bench_replay_graph.py --python /tmp/h4/base/.venv/bin/python --workdir /tmp/h4/work
#          --repeats 2                  (load average 4-10 from other jobs)
#          --repeats 3                  (load 1-3)
#          --repeats 3 --skip-2000      (load 0.6-4)
#          --figures 4                  (load 2-4: the summed PSS)
# on the same recording file (qr_floor --seed 0, sha256 0bc66aa5dbde1687…; both trees record it
# byte for byte alike). That tree has no tracking, no detection cache and no `run --jobs`: every
# run detects every frame in one process (zxing-cpp first, OpenCV only as its fallback, which is
# why its run beats the bare OpenCV loop). Ratios are the medians over all pairs of the three
# invocations (per pair: run÷bare 1.16-1.94, sweep÷run 2.00-4.31, cold÷warm 0.95-1.33); frames/s
# are the medians of the quietest invocation (the last); accuracy is deterministic.
BASELINE = {
    "run_over_bare": 1.73,  # frames/s ratio (figure 1), 8 pairs
    "run_fps": 14.7,
    "bare_fps": 8.9,
    "sweep_over_run": 3.00,  # figure 2 (sweep --jobs 2), 8 pairs
    "cold_over_warm": 1.18,  # figure 3 (no cache: the second run detects again), 8 pairs
    "rss_200_mib": 311,  # figure 4, largest process (second invocation; every 200-frame run: 310-323 MiB)
    "rss_2000_mib": 531,
    "pss_200_mib": 298,  # figure 4, summed PSS of the process tree (`--figures 4`, load 2-4;
    "pss_2000_mib": 527,  # its largest-process RSS: 317 / 543 MiB)
    # figure 5: solver -> (position RMSE mm, heading RMSE deg, solved frames of 200)
    "rmse": {
        "lm": (0.32484, 0.001410, 200),
        "p4p": (0.73346, 0.010589, 200),
        "ippe": (0.33665, 0.001503, 200),
        "planar": (0.03293, 0.001345, 199),  # 1 frame solver_failed
        "sqpnp": (0.32520, 0.001406, 200),
        "epnp": (0.33665, 0.001503, 200),
    },
}


class BenchError(Exception):
    """A child failed or its output lacks what a figure needs: the figure is not measured."""


@dataclass
class Child:
    wall_s: float
    cpu_s: float  # user + system of every process of the tree, as last sampled (≈)
    max_rss_mib: float  # GNU time: the largest single process (itself or a reaped child)
    peak_pss_mib: float  # sampled: the largest sum of PSS over the tree's processes
    returncode: int
    log: Path


class TreeSampler:
    """Samples the processes below a root pid: the largest sum of their proportional set sizes
    (PSS: shared pages split between the processes sharing them, so forked workers are not
    counted twice) and each process's CPU time. Worker pools whose processes the command does
    not reap itself (a multiprocessing forkserver's children) are seen only this way."""

    def __init__(self):
        self.peak_pss_kib = 0
        self.cpu_s_by_pid: dict[int, float] = {}

    def sample(self, root: int) -> None:
        children: dict[int, list[int]] = {}
        for entry in os.scandir("/proc"):
            if entry.name.isdigit():
                stat = read_proc_file(f"/proc/{entry.name}/stat")
                if stat:  # "pid (comm) state ppid ...": comm may hold spaces and parentheses
                    fields = stat[stat.rindex(")") + 2:].split()
                    children.setdefault(int(fields[1]), []).append(int(entry.name))
        tree, todo = [], list(children.get(root, []))
        while todo:
            pid = todo.pop()
            tree.append(pid)
            todo += children.get(pid, [])
        total_kib = 0
        for pid in tree:
            rollup, stat = read_proc_file(f"/proc/{pid}/smaps_rollup"), read_proc_file(f"/proc/{pid}/stat")
            total_kib += next((int(line.split()[1]) for line in rollup.splitlines() if line.startswith("Pss:")), 0)
            if stat:
                fields = stat[stat.rindex(")") + 2:].split()  # fields[11], [12]: utime, stime (ticks)
                self.cpu_s_by_pid[pid] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        self.peak_pss_kib = max(self.peak_pss_kib, total_kib)


def read_proc_file(path: str) -> str:
    try:
        with open(path) as f:
            return f.read()
    except OSError:  # the process ended meanwhile
        return ""


@dataclass
class Tree:
    """The agvviz being measured: its interpreter and what its `agvviz run` offers."""

    python: str
    has_tracking: bool
    has_jobs: bool
    has_realism: bool = False  # scenarios take `realism` (default typical since issue 14)
    source: str | None = None  # the tree's folder, put first on PYTHONPATH (None: the interpreter's own agvviz)
    name: str = "new"

    @property
    def env(self) -> dict:
        return {"PYTHONPATH": self.source} if self.source else {}

    @property
    def agvviz(self) -> list[str]:
        return [self.python, "-m", "agvviz"]

    @property
    def rerun(self) -> Path:
        return Path(self.python).parent / "rerun"


class Bench:
    def __init__(self, workdir: Path, tree: Tree):
        self.workdir = workdir
        self.tree = tree
        self.logs = workdir / "logs"
        self.runs = workdir / "runs"
        self.caches = workdir / "caches"
        self._count = 0
        for folder in (self.logs, self.runs, self.caches, workdir / "tmp", workdir / "xdg-cache"):
            shutil.rmtree(folder, ignore_errors=True)  # what an earlier invocation left; recordings stay
            folder.mkdir(parents=True)

    def fresh_cache(self, label: str) -> Path:
        """A new, empty detection cache folder (a cold cache)."""
        self._count += 1
        folder = self.caches / f"{self._count:03d}-{label}"
        folder.mkdir()
        return folder

    def child(self, cmd: list[str], label: str, cache: Path | None = None, check: bool = True,
              tree: Tree | None = None) -> Child:
        """Run ``cmd`` (of ``tree``, default the measured one) to its end; its wall time, peak
        RSS and exit code. Raises BenchError if it fails and ``check``."""
        tree = tree or self.tree
        env = dict(os.environ, TMPDIR=str(self.workdir / "tmp"), XDG_CACHE_HOME=str(self.workdir / "xdg-cache"),
                   **tree.env)
        shown = shlex.join(cmd)
        if tree.source:
            shown = f"PYTHONPATH={shlex.quote(tree.source)} {shown}"
        if cache is not None:
            env["AGVVIZ_CACHE_DIR"] = str(cache)
            shown = f"AGVVIZ_CACHE_DIR={shlex.quote(str(cache))} {shown}"
        self._count += 1
        log = self.logs / f"{self._count:03d}-{label}.log"
        times = log.with_suffix(".time")
        print(f"  $ {shown}", flush=True)
        sampler = TreeSampler()
        with open(log, "w") as out:
            t0 = time.perf_counter()
            proc = subprocess.Popen([TIME, "-f", "%M", "-o", str(times), *cmd], stdout=out,
                                    stderr=subprocess.STDOUT, env=env, cwd=self.workdir)
            while proc.poll() is None:
                sampler.sample(proc.pid)
                time.sleep(SAMPLE_S)
            wall_s = time.perf_counter() - t0
        if proc.returncode != 0 and check:
            last = log.read_text(errors="replace").strip().splitlines()[-1:] or [""]
            raise BenchError(f"{label} exited {proc.returncode}: {last[0]} (log: {log})")
        # The last line is the format's ("Command exited with non-zero status N" may precede it).
        max_rss_kib = int(times.read_text().strip().splitlines()[-1])
        child = Child(wall_s, sum(sampler.cpu_s_by_pid.values()), max_rss_kib / 1024, sampler.peak_pss_kib / 1024,
                      proc.returncode, log)
        print(f"    exit {proc.returncode}, wall {wall_s:.1f} s, CPU ≈{child.cpu_s:.1f} s, peak RSS "
              f"{child.max_rss_mib:.0f} MiB (largest process), peak PSS {child.peak_pss_mib:.0f} MiB "
              f"(all its processes)", flush=True)
        return child

    def recording(self, duration_s: float | None) -> Path:
        """The default qr_floor recording (seed 0), or one of ``duration_s``; recorded once."""
        name = "qr_floor-seed0" + (f"-duration_s{duration_s:g}" if duration_s is not None else "")
        path = self.workdir / f"{name}.mcap"
        if not path.exists():
            partial = self.workdir / "tmp" / path.name
            sets = ["--set", f"duration_s={duration_s:g}"] if duration_s is not None else []
            # The baseline was measured in the ideal world (the only one before issue 14).
            sets += ["--set", "realism=ideal"] if self.tree.has_realism else []
            self.child(self.tree.agvviz + ["record", "qr_floor", "--seed", "0", *sets, "--out", str(partial)],
                       f"record-{name}")
            os.replace(partial, path)
        with open(path, "rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
        print(f"  recording {path} (sha256 {digest[:16]}…)")
        return path

    def run(self, recording: Path, label: str, cache: Path, sets: list[str] = (), extra: list[str] = (),
            tree: Tree | None = None) -> tuple[Child, Path]:
        tree = tree or self.tree
        rrd = self.runs / f"{label}.rrd"
        cmd = tree.agvviz + ["run", str(recording), "--out", str(rrd)]
        for s in sets:
            cmd += ["--set", s]
        return self.child(cmd + list(extra), label, cache, tree=tree), rrd

    def tracking_sets(self, on: bool) -> list[str]:
        return [f"tracking={'true' if on else 'false'}"] if self.tree.has_tracking else []

    def tracking_cases(self) -> list[tuple[str, list[str]]]:
        if not self.tree.has_tracking:
            return [("no tracking", [])]
        return [("tracking on", self.tracking_sets(True)), ("tracking off", self.tracking_sets(False))]


def summary_of(rrd: Path) -> dict:
    """The run summary stored in the `.rrd` (read with this interpreter's agvviz)."""
    from agvviz.viz.readback import document_json

    return document_json(rrd, "run/summary")


def rmse_of(summary: dict, key: str) -> float:
    try:
        return float(summary[key]["rmse"])
    except (KeyError, TypeError, ValueError) as exc:
        raise BenchError(f"the run summary has no {key}.rmse") from exc


def status(ok: bool | None) -> str:
    return "—" if ok is None else ("PASS" if ok else "FAIL")


def fmt(value: float | None, spec: str = ".2f") -> str:
    return "—" if value is None else format(value, spec)


# ---------------------------------------------------------------------------------------- figures
# Each returns rows for the closing table: (figure, measured, target text, baseline, PASS/FAIL).


def figure_1(bench: Bench, recording: Path, repeats: int, trees: list[Tree]) -> list[tuple]:
    print("\n## 1. agvviz run frames/s ÷ bare OpenCV loop frames/s (pairs: bare, then run"
          + (", then the baseline tree's run; the two runs alternate in order)" if len(trees) > 1 else ")"))
    bare_cmd = [bench.tree.python, str(Path(__file__).resolve()), "--bare-loop", str(recording)]
    cases = bench.tracking_cases()
    ratios: dict[tuple[str, str], list[float]] = {(t.name, name): [] for t in trees for name, _ in cases}
    table = []
    for r in range(1, repeats + 1):
        for name, sets in cases:
            bare = bench.child(bare_cmd, f"bare-{r}")
            printed = re.search(r"^frames (\d+) codes \d+$", bare.log.read_text(), re.MULTILINE)
            if printed is None:
                raise BenchError(f"the bare loop printed no frame count (log: {bare.log})")
            bare_frames = int(printed.group(1))
            fps_bare = bare_frames / bare.wall_s
            for tree in trees if r % 2 else trees[::-1]:
                run, rrd = bench.run(recording, f"fig1-{tree.name}-{name.replace(' ', '-')}-{r}",
                                     bench.fresh_cache("fig1"), sets, tree=tree)
                frames = int(summary_of(rrd)["frames"])
                if frames != bare_frames:
                    raise BenchError(f"agvviz run replayed {frames} frames, the bare loop {bare_frames}")
                fps_run = frames / run.wall_s
                ratios[(tree.name, name)].append(fps_run / fps_bare)
                table.append((tree.name, name, r, bare.wall_s, fps_bare, run.wall_s, fps_run, run.cpu_s,
                              run.peak_pss_mib, fps_run / fps_bare))
    print(f"\n  {'tree':5s} {'case':13s} {'pair':>4s} {'bare s':>7s} {'bare f/s':>9s} {'run s':>7s} {'run f/s':>8s} "
          f"{'run CPU s':>9s} {'run PSS MiB':>11s} {'ratio':>6s}")
    for tree_name, name, r, bs, bf, rs, rf, cpu, mib, ratio in sorted(table, key=lambda row: (row[1], row[0], row[2])):
        print(f"  {tree_name:5s} {name:13s} {r:4d} {bs:7.1f} {bf:9.2f} {rs:7.1f} {rf:8.2f} {cpu:9.1f} {mib:11.0f} {ratio:6.2f}")
    rows = []
    targets = {"tracking on": 3.0, "tracking off": None, "no tracking": None}
    for (tree_name, name), values in ratios.items():
        median = statistics.median(values)
        target = targets[name]
        spread = f"{min(values):.2f}–{max(values):.2f}"
        print(f"  {tree_name}: median ratio, {name}: {median:.2f} (pairs {spread})")
        rows.append((f"1. run ÷ bare, {name} ({tree_name})", f"{median:.2f} ({spread})", f"≥ {target}" if target else "—",
                     fmt(BASELINE["run_over_bare"]), status(median >= target if target else None)))
    return rows


def figures_2_3(bench: Bench, recording: Path, repeats: int) -> list[tuple]:
    print("\n## 2. sweep of 4 solvers ÷ one run (both cold);  3. first run (cold) ÷ second run, another solver (warm)")
    sweep_ratios, warm_ratios, floor_ratios, table = [], [], [], []
    for r in range(1, repeats + 1):
        cache = bench.fresh_cache("fig23-run")
        cold, _ = bench.run(recording, f"fig3-cold-lm-{r}", cache, ["solver=lm"])
        warm, _ = bench.run(recording, f"fig3-warm-ippe-{r}", cache, ["solver=ippe"])
        sweep = bench.child(bench.tree.agvviz + [
            "sweep", str(recording), "--set", "solver=" + ",".join(SWEEP_SOLVERS), "--jobs", "2",
            "--out-dir", str(bench.runs / f"fig2-sweep-{r}")], f"fig2-sweep-{r}", bench.fresh_cache("fig2-sweep"))
        # The least any warm run must do under the run contract: start Python, import Rerun,
        # read the recording's frames and write them into an .rrd (no solve, no other entity).
        floor = bench.child([bench.tree.python, str(Path(__file__).resolve()), "--floor-loop", str(recording),
                             str(bench.runs / f"fig3-floor-{r}.rrd")], f"fig3-floor-{r}")
        sweep_ratios.append(sweep.wall_s / cold.wall_s)
        warm_ratios.append(cold.wall_s / warm.wall_s)
        floor_ratios.append(cold.wall_s / floor.wall_s)
        table.append((r, cold.wall_s, warm.wall_s, sweep.wall_s, floor.wall_s, sweep.wall_s / cold.wall_s,
                      cold.wall_s / warm.wall_s, cold.wall_s / floor.wall_s))
    print(f"\n  {'repeat':>6s} {'run cold s':>10s} {'run warm s':>10s} {'sweep s':>8s} {'floor s':>8s} "
          f"{'sweep÷run':>9s} {'cold÷warm':>9s} {'cold÷floor':>10s}")
    for r, c, w, s, f, sr, wr, fr in table:
        print(f"  {r:6d} {c:10.1f} {w:10.1f} {s:8.1f} {f:8.1f} {sr:9.2f} {wr:9.2f} {fr:10.2f}")
    print("  floor: `import rerun` + the recording's frames copied into an .rrd (the least a warm run does);"
          " cold÷floor is the largest first÷second ratio any warm run can reach")
    sweep_median, warm_median = statistics.median(sweep_ratios), statistics.median(warm_ratios)
    return [
        ("2. sweep (4 solvers) ÷ run", f"{sweep_median:.2f}", "≤ 1.3", fmt(BASELINE["sweep_over_run"]),
         status(sweep_median <= 1.3)),
        ("3. first run ÷ second run", f"{warm_median:.2f}", "≥ 10", fmt(BASELINE["cold_over_warm"]),
         status(warm_median >= 10)),
        ("3'. first run ÷ floor (upper bound of 3.)", f"{statistics.median(floor_ratios):.2f}", "", "", ""),
    ]


def figure_4(bench: Bench, recording_200: Path, skip_2000: bool, trees: list[Tree]) -> list[tuple]:
    print("\n## 4. peak memory of agvviz run and of agvviz sweep, 200 and 2000 frames (cold caches)")
    baseline = f"{fmt(BASELINE['pss_200_mib'], '.0f')} / {fmt(BASELINE['pss_2000_mib'], '.0f')} MiB"
    recordings = {"200": recording_200} if skip_2000 else {"200": recording_200, "2000": bench.recording(200.0)}
    measured = []
    for tree in trees:
        runs, sweeps = {}, {}
        for frames, recording in recordings.items():
            label = f"{tree.name}-{frames}"
            runs[frames], _ = bench.run(recording, f"fig4-run-{label}", bench.fresh_cache(f"fig4-run-{label}"), tree=tree)
            sweeps[frames] = bench.child(tree.agvviz + [
                "sweep", str(recording), "--set", "solver=" + ",".join(MEMORY_SWEEP_SOLVERS), "--jobs", "2",
                "--out-dir", str(bench.runs / f"fig4-sweep-{label}")], f"fig4-sweep-{label}",
                bench.fresh_cache(f"fig4-sweep-{label}"), tree=tree)
        measured += [(f"run ({tree.name})", runs, baseline), (f"sweep ({tree.name})", sweeps, "—")]
    rows = []
    for what, children, base in measured:
        small = children["200"]
        if skip_2000:
            rows.append((f"4. {what} peak PSS 2000 ÷ 200 frames", f"— (200: {small.peak_pss_mib:.0f} MiB; --skip-2000)",
                         "≤ 1.15", base, "—"))
            continue
        large = children["2000"]
        ratio = large.peak_pss_mib / small.peak_pss_mib
        print(f"  {what}: summed PSS: 200 frames {small.peak_pss_mib:.0f} MiB, 2000 frames {large.peak_pss_mib:.0f} MiB, "
              f"ratio {ratio:.2f}   (largest process's RSS: {small.max_rss_mib:.0f} / {large.max_rss_mib:.0f} MiB, "
              f"ratio {large.max_rss_mib / small.max_rss_mib:.2f})")
        rows.append((f"4. {what} peak PSS 2000 ÷ 200 frames",
                     f"{ratio:.2f} ({small.peak_pss_mib:.0f} / {large.peak_pss_mib:.0f} MiB)", "≤ 1.15", base,
                     status(ratio <= 1.15)))
    print(f"  baseline (run): PSS {baseline}, largest process's RSS {fmt(BASELINE['rss_200_mib'], '.0f')} / "
          f"{fmt(BASELINE['rss_2000_mib'], '.0f')} MiB")
    return rows


def accuracy(bench: Bench, recording: Path, tree: Tree) -> list[tuple]:
    """(case, solver, solved, position RMSE mm, heading RMSE deg) of every solver, tracking on and off."""
    measured = []
    for name, sets in bench.tracking_cases():
        cache = bench.fresh_cache(f"fig5-{tree.name}")  # detected by the first solver, reused by the others
        for solver in ACCURACY_SOLVERS:
            try:
                _, rrd = bench.run(recording, f"fig5-{tree.name}-{solver}-{name.replace(' ', '-')}", cache,
                                   [f"solver={solver}", *sets], tree=tree)
                summary = summary_of(rrd)
                measured.append((name, solver, int(summary["solved"]), rmse_of(summary, "position_error_mm"),
                                 rmse_of(summary, "heading_error_deg")))
            except BenchError as exc:
                print(f"    not measured: {exc}")
                measured.append((name, solver, None, None, None))
    return measured


def figure_5(bench: Bench, recording: Path, baseline: Tree | None) -> list[tuple]:
    reference = "the baseline tree's" if baseline else "ad2bde5's"
    print(f"\n## 5. accuracy per solver (run summary in each .rrd) against {reference}, within 5 %")
    measured = accuracy(bench, recording, bench.tree)
    references = {}
    if baseline is not None:
        references = {(name, solver): (pos, hdg, solved) for name, solver, solved, pos, hdg in
                      accuracy(bench, recording, baseline) if pos is not None}
    print(f"\n  {'case':13s} {'solver':7s} {'solved':>6s} {'pos RMSE mm':>11s} {'base':>7s} {'Δ %':>6s} "
          f"{'hdg RMSE deg':>12s} {'base':>8s} {'Δ %':>6s} status")
    verdicts: dict[str, list[bool | None]] = {}
    for name, solver, solved, pos, hdg in measured:
        base = references.get((name, solver)) if baseline is not None else BASELINE["rmse"].get(solver)
        if pos is None or base is None:
            ok = None
            dpos = dhdg = None
        else:
            dpos, dhdg = 100 * (pos / base[0] - 1), 100 * (hdg / base[1] - 1)
            ok = abs(dpos) <= 5 and abs(dhdg) <= 5 and solved == base[2]
        verdicts.setdefault(name, []).append(ok)
        print(f"  {name:13s} {solver:7s} {fmt(solved, 'd'):>6s} {fmt(pos, '.4f'):>11s} "
              f"{fmt(base[0] if base else None, '.4f'):>7s} {fmt(dpos, '+.1f'):>6s} {fmt(hdg, '.5f'):>12s} "
              f"{fmt(base[1] if base else None, '.5f'):>8s} {fmt(dhdg, '+.1f'):>6s} {status(ok)}")
    rows = []
    for name, oks in verdicts.items():
        passed = sum(ok is True for ok in oks)
        verdict = None if all(ok is None for ok in oks) else all(ok is True for ok in oks)
        rows.append((f"5. RMSE ±5 %, same solved, {name}", f"{passed} of {len(oks)} solvers", "all",
                     "baseline tree" if baseline else "ad2bde5", status(verdict)))
    return rows


def figure_6(bench: Bench, recording: Path) -> list[tuple]:
    print("\n## 6. .rrd of equal settings compare equal (rerun rrd compare --unordered)")
    cache = bench.fresh_cache("fig6")
    _, cold = bench.run(recording, "fig6-cold", cache)
    _, warm = bench.run(recording, "fig6-warm", cache)
    others = [("warm cache", warm)]
    if bench.tree.has_jobs:
        _, jobs1 = bench.run(recording, "fig6-jobs1", bench.fresh_cache("fig6-jobs1"), extra=["--jobs", "1"])
        others.append(("--jobs 1", jobs1))
    rows = []
    for name, other in others:
        compare = bench.child([str(bench.tree.rerun), "rrd", "compare", "--unordered", str(cold), str(other)],
                              f"fig6-compare-{name.replace(' ', '-')}", check=False)
        equal = compare.returncode == 0
        if not equal:
            print(f"    differ: {compare.log.read_text(errors='replace').strip()[:500]}")
        rows.append((f"6. cold .rrd = {name} .rrd", "equal" if equal else "differ", "equal", "—", status(equal)))
    if not bench.tree.has_jobs:
        rows.append(("6. cold .rrd = --jobs 1 .rrd", "— (no run --jobs)", "equal", "—", "—"))
    return rows


def figure_7(bench: Bench, recording: Path, trees: list[Tree]) -> list[tuple]:
    print("\n## 7. CPU ms per frame of the detect stage (in process, one OpenCV thread), and of the bare loop")
    import json

    columns, results = [], {}
    for tree in trees:
        for name, sets in bench.tracking_cases():
            on = "true" if "tracking=true" in sets or not sets else "false"
            child = bench.child([tree.python, str(Path(__file__).resolve()), "--frame-costs", str(recording),
                                 "--tracking", on], f"fig7-{tree.name}-{name.replace(' ', '-')}", tree=tree)
            line = [x for x in child.log.read_text().splitlines() if x.startswith("{")]
            if not line:
                raise BenchError(f"--frame-costs printed nothing (log: {child.log})")
            column = f"{tree.name}, {name}"
            columns.append(column)
            results[column] = json.loads(line[-1])
    bare = bench.child([bench.tree.python, str(Path(__file__).resolve()), "--bare-loop", str(recording)], "fig7-bare")
    costs = re.search(r"^CPU ms/frame (.*)$", bare.log.read_text(), re.MULTILINE)
    labels = list(next(iter(results.values()))["cpu_s"])
    print(f"\n  {'ms per frame':42s} " + " ".join(f"{c:>18s}" for c in columns))
    for label in labels + ["other (Python: tracking, templates, checks)", "total"]:
        values = []
        for c in columns:
            r = results[c]
            known = sum(r["cpu_s"].values())
            v = {"total": r["total_s"], "other (Python: tracking, templates, checks)": r["total_s"] - known}.get(
                label, r["cpu_s"].get(label, 0.0))
            values.append(f"{1000 * v / r['frames']:18.2f}")
        print(f"  {label:42s} " + " ".join(values))
    print(f"  {'keyframes of ' + str(results[columns[0]]['frames']):42s} "
          + " ".join(f"{results[c]['keyframes']:18d}" for c in columns))
    print(f"  bare loop, CPU ms/frame: {costs.group(1) if costs else '—'}")
    first = results[columns[0]]
    return [("7. detect CPU ms/frame (" + columns[0] + ")", f"{1000 * first['total_s'] / first['frames']:.1f}",
             "", "", "")]


# ---------------------------------------------------------------------------------------- the bare loop


def bare_loop(recording: Path) -> None:
    """imdecode + detectAndDecodeMulti + solvePnP(IPPE_SQUARE) per frame of ``recording``, read
    with agvviz's reader: no undistortion, no refinement, no logging (as in bench_qr_floor.py)."""
    import cv2
    import numpy as np

    from agvviz.model.messages import CalibrationMsg, CompressedFrame
    from agvviz.recording.reader import iter_messages

    h = CODE_SIZE_M / 2
    object_points = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    detector = cv2.QRCodeDetector()
    K = dist = None
    frames = codes = 0
    cpu_s = {"decode": 0.0, "detect": 0.0, "solvePnP": 0.0}
    for msg in iter_messages(recording):
        if isinstance(msg.value, CalibrationMsg):
            K, dist = msg.value.camera.K, msg.value.camera.dist
        if not isinstance(msg.value, CompressedFrame):
            continue
        frames += 1
        t0 = time.process_time()
        gray = cv2.imdecode(np.frombuffer(msg.value.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        t1 = time.process_time()
        ok, _, corners, _ = detector.detectAndDecodeMulti(gray)
        t2 = time.process_time()
        if ok and corners is not None:
            for c in corners:
                codes += 1
                cv2.solvePnP(object_points, c.astype(np.float64), K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        t3 = time.process_time()
        for name, dt in zip(cpu_s, (t1 - t0, t2 - t1, t3 - t2)):
            cpu_s[name] += dt
    print(f"frames {frames} codes {codes}")
    print("CPU ms/frame " + " ".join(f"{name} {1000 * v / max(frames, 1):.2f}" for name, v in cpu_s.items()))


def frame_costs(recording: Path, tracking: bool) -> None:
    """CPU time per frame of this tree's detect stage, in this process on one OpenCV thread
    (what a detection worker does), split by the OpenCV and zxing-cpp calls that make it up;
    prints one JSON line. Every segment is detected by `detect_segment`, as a worker does."""
    import json
    import cv2
    import zxingcpp

    from agvviz.model.messages import CompressedFrame
    from agvviz.recording.reader import ReadReport
    from agvviz.recording.source import iter_role_messages
    from agvviz.replay.detect.stage import detect_segment
    from agvviz.replay.run import prepare
    from agvviz.settings import RunSettings

    cv2.setNumThreads(1)
    cpu_s = {"decode (imdecode)": 0.0, "undistort (remap of the frame)": 0.0, "detect (zxing-cpp)": 0.0,
             "refine and track (findTransformECC)": 0.0, "module sampling (remap at module centres)": 0.0}
    calls = dict.fromkeys(cpu_s, 0)

    def timed(owner, name, label_of):
        function = getattr(owner, name)

        def wrapper(*args, **kwargs):
            t0 = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                label = label_of(args)
                cpu_s[label] += time.process_time() - t0
                calls[label] += 1
        setattr(owner, name, wrapper)

    timed(cv2, "imdecode", lambda a: "decode (imdecode)")
    timed(cv2, "remap", lambda a: "undistort (remap of the frame)" if getattr(a[1], "ndim", 0) == 3
          else "module sampling (remap at module centres)")
    timed(zxingcpp, "read_barcodes", lambda a: "detect (zxing-cpp)")
    timed(cv2, "findTransformECC", lambda a: "refine and track (findTransformECC)")
    prepared = prepare(recording, RunSettings(tracking=tracking))
    report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    jobs = [prepared.replay.detect_job(m) for m in iter_role_messages(
        prepared.recording, prepared.roles, prepared.time_source, report) if isinstance(m.value, CompressedFrame)]
    jobs = [job for job in jobs if job is not None]
    params = prepared.replay.detect_params
    detect_segment(params, jobs[:1])  # imports and first-use costs out of the figure
    for key in cpu_s:
        cpu_s[key], calls[key] = 0.0, 0
    t0 = time.process_time()
    results = []
    for start in range(0, len(jobs), params.segment_frames):
        results += detect_segment(params, jobs[start:start + params.segment_frames])
    total_s = time.process_time() - t0
    print(json.dumps({"frames": len(jobs), "keyframes": sum(r.keyframe for r in results), "total_s": total_s,
                      "cpu_s": cpu_s, "calls": calls}))


def floor_loop(recording: Path, out: Path) -> None:
    """The least a warm run does: import Rerun, read every frame of ``recording`` with agvviz's
    reader and log its bytes as an EncodedImage into ``out`` (no detection, solve or other entity)."""
    import rerun as rr

    from agvviz.model.messages import CompressedFrame
    from agvviz.recording.reader import iter_messages

    rec = rr.RecordingStream("agvviz-floor", recording_id="floor")
    rec.save(str(out))
    frames = 0
    for msg in iter_messages(recording):
        if isinstance(msg.value, CompressedFrame):
            rec.set_time("frame", sequence=frames)
            rec.log("image", rr.EncodedImage(contents=msg.value.data, media_type="image/jpeg"))
            frames += 1
    rec.flush()
    print(f"frames {frames}")


# ---------------------------------------------------------------------------------------- main


def inspect_tree(python: str, source: str | None = None, name: str = "new") -> Tree:
    env = dict(os.environ, COLUMNS="200", **({"PYTHONPATH": source} if source else {}))
    helped = subprocess.run([python, "-m", "agvviz", "run", "--help"], capture_output=True, text=True, env=env)
    if helped.returncode != 0:
        raise SystemExit(f"error: `{python} -m agvviz run --help` exited {helped.returncode}")
    text = helped.stdout
    scenarios = subprocess.run([python, "-m", "agvviz", "scenarios"], capture_output=True, text=True, env=env).stdout
    return Tree(python=python, has_tracking="tracking (bool" in text, has_jobs="--jobs" in text,
                has_realism="realism" in scenarios, source=source, name=name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", type=Path, default=ROOT / "runs" / "bench_replay_graph",
                        help="recordings, runs, caches and logs (default runs/bench_replay_graph)")
    parser.add_argument("--repeats", type=int, default=2, help="pairs per timed figure (default 2)")
    parser.add_argument("--skip-2000", action="store_true", help="skip the 2000-frame memory run")
    parser.add_argument("--figures", default="1,2,3,4,5,6",
                        help="which figures to measure, comma-separated (2 and 3 are measured together)")
    parser.add_argument("--python", default=sys.executable,
                        help="interpreter whose agvviz is measured (default: this one)")
    parser.add_argument("--source", default=str(ROOT),
                        help="source tree measured, put first on the children's PYTHONPATH (default: this "
                             "script's tree; '' for the interpreter's own agvviz)")
    parser.add_argument("--baseline", metavar="TREE",
                        help="a second source tree (e.g. a `git worktree` of the commit before a change), run "
                             "with the same interpreter beside the measured one in figures 1, 4 and 5: "
                             "before/after pairs in one invocation")
    parser.add_argument("--bare-loop", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--floor-loop", type=Path, nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--frame-costs", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--tracking", default="true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.bare_loop is not None:
        bare_loop(args.bare_loop)
        return
    if args.floor_loop is not None:
        floor_loop(*args.floor_loop)
        return
    if args.frame_costs is not None:
        frame_costs(args.frame_costs, args.tracking == "true")
        return
    if args.repeats < 1:
        raise SystemExit("error: --repeats must be ≥ 1")
    wanted = set(args.figures.replace(" ", "").split(","))
    if not wanted <= {"1", "2", "3", "4", "5", "6", "7"}:
        raise SystemExit(f"error: --figures takes numbers from 1 to 7, got {args.figures!r}")
    if not os.access(TIME, os.X_OK):
        raise SystemExit(f"error: {TIME} (GNU time) is needed for peak memory; install the 'time' package")

    tree = inspect_tree(args.python, args.source or None)
    baseline = inspect_tree(args.python, str(Path(args.baseline).resolve()), "base") if args.baseline else None
    trees = [tree] + ([baseline] if baseline else [])
    workdir = args.workdir.resolve()
    bench = Bench(workdir, tree)
    for other in trees[1:]:
        print(f"baseline: agvviz of {other.source} (run with {other.python})")
    print(f"agvviz of {tree.source or tree.python}: tracking setting {'yes' if tree.has_tracking else 'no'}, "
          f"run --jobs {'yes' if tree.has_jobs else 'no'}; workdir {workdir}; {os.cpu_count()} CPUs; "
          f"load average {os.getloadavg()[0]:.2f}")
    recording = bench.recording(None)

    rows = []
    figures = [
        ("1", lambda: figure_1(bench, recording, args.repeats, trees)),
        ("2, 3", lambda: figures_2_3(bench, recording, args.repeats)),
        ("4", lambda: figure_4(bench, recording, args.skip_2000, trees)),
        ("5", lambda: figure_5(bench, recording, baseline)),
        ("6", lambda: figure_6(bench, recording)),
        ("7", lambda: figure_7(bench, recording, trees)),
    ]
    for name, measure in figures:
        if not wanted & set(name.split(", ")):
            continue
        try:
            rows += measure()
        except BenchError as exc:
            print(f"  figure {name} not measured: {exc}")
            rows.append((f"{name}. not measured", str(exc)[:60], "", "", "—"))

    print(f"\n## summary (load average now {os.getloadavg()[0]:.2f})")
    print(f"  {'figure':44s} {'measured':>26s} {'target':>8s} {'baseline ad2bde5':>18s} status")
    for figure, measured, target, baseline, verdict in rows:
        print(f"  {figure:44s} {measured:>26s} {target:>8s} {baseline:>18s} {verdict}")


if __name__ == "__main__":
    main()
