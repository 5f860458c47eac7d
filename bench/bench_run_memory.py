"""Where a run's peak memory is: every process of one `agvviz run`, its peak PSS and its PSS at the
moment the tree's summed PSS peaked (the figure 4 of bench_replay_graph.py), and the largest
anonymous mappings of each process at that moment (glibc's [heap], allocator arenas) — issue 27.

Usage:  python bench/bench_run_memory.py RECORDING [--tree TREE] [--python PYTHON] [--regions 4]
                                                   [--sweep lm,ippe]

With ``--sweep SOLVERS`` it runs `agvviz sweep RECORDING --set solver=SOLVERS --jobs 2` instead (the
figure 4 sweep of bench_replay_graph.py is ``--sweep lm,ippe``).

Runs `PYTHON -m agvviz run RECORDING` with TREE first on PYTHONPATH (default: this script's tree),
a fresh empty detection cache and its output in a temporary folder, sampling /proc every 0.2 s.
Processes are named by what they are: the run process; the fork server (its child running
multiprocessing.forkserver); the `.rrd` writer (the process holding an open `.rrd` file or pipe);
the fork server's other children, the detection workers.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_replay_graph import read_proc_file as _read  # this folder is on sys.path when run as a script

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_S = 0.2


def _children() -> dict[int, list[int]]:
    children: dict[int, list[int]] = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            stat = _read(f"/proc/{entry.name}/stat")
            if stat:
                children.setdefault(int(stat[stat.rindex(")") + 2:].split()[1]), []).append(int(entry.name))
    return children


def _writes_rrd(pid: int) -> bool:
    """Whether ``pid`` holds an open ``.rrd`` file or pipe (the run's writer)."""
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return False
    for fd in fds:
        try:
            if ".rrd" in os.readlink(f"/proc/{pid}/fd/{fd}"):  # the pipe or the temporary file
                return True
        except OSError:
            continue
    return False


def _pss_kib(pid: int) -> int:
    rollup = _read(f"/proc/{pid}/smaps_rollup")
    return next((int(line.split()[1]) for line in rollup.splitlines() if line.startswith("Pss:")), 0)


def _anonymous_regions(pid: int, count: int) -> list[tuple[int, str]]:
    """The ``count`` largest anonymous mappings of ``pid`` by PSS (KiB, name)."""
    regions, name = [], ""
    for line in _read(f"/proc/{pid}/smaps").splitlines():
        head = line.split(maxsplit=1)[0] if line else ""
        if not head.endswith(":"):  # a mapping's first line: range perms offset dev inode [path]
            fields = line.split()
            name = fields[5] if len(fields) > 5 else f"anonymous {fields[0]}"
        elif head == "Pss:" and (name.startswith("anonymous") or name == "[heap]"):
            regions.append((int(line.split()[1]), name))
    return sorted(regions, reverse=True)[:count]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path)
    parser.add_argument("--tree", default=str(ROOT), help="source tree put first on PYTHONPATH")
    parser.add_argument("--python", default=sys.executable)
    parser.add_argument("--regions", type=int, default=4, help="anonymous mappings shown per process")
    parser.add_argument("--sweep", metavar="SOLVERS", help="measure `agvviz sweep --set solver=SOLVERS` instead")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_run_memory-") as work:
        env = dict(os.environ, PYTHONPATH=args.tree, AGVVIZ_CACHE_DIR=str(Path(work) / "cache"), TMPDIR=work)
        cmd = [args.python, "-m", "agvviz", "run", str(args.recording), "--out", str(Path(work) / "run.rrd")]
        if args.sweep:
            cmd = [args.python, "-m", "agvviz", "sweep", str(args.recording), "--set", f"solver={args.sweep}",
                   "--jobs", "2", "--out-dir", str(Path(work) / "sweep")]
        print("$", " ".join(cmd), f"(PYTHONPATH={args.tree})", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True)
        peak_kib: dict[int, int] = {}
        seen: dict[int, tuple[float, float, str]] = {}  # pid -> (first seen, last seen, cmdline)
        parent: dict[int, int] = {}
        writers: set[int] = set()
        total_peak_kib, at_peak, peak_t, regions = 0, {}, 0.0, {}
        while proc.poll() is None:
            now = time.perf_counter() - t0
            children = _children()
            tree, todo = [proc.pid], list(children.get(proc.pid, []))
            for child in todo:
                parent.setdefault(child, proc.pid)
            while todo:
                pid = todo.pop()
                tree.append(pid)
                for grandchild in children.get(pid, []):
                    parent.setdefault(grandchild, pid)
                    todo.append(grandchild)
            sample = {pid: _pss_kib(pid) for pid in tree}
            writers |= {pid for pid in tree if pid != proc.pid and pid not in writers and _writes_rrd(pid)}
            for pid, kib in sample.items():
                peak_kib[pid] = max(peak_kib.get(pid, 0), kib)
                first, _, cmdline = seen.get(pid, (now, now, _read(f"/proc/{pid}/cmdline").replace("\0", " ")))
                seen[pid] = (first, now, cmdline)
            if sum(sample.values()) > total_peak_kib:
                total_peak_kib, at_peak, peak_t = sum(sample.values()), sample, now
                regions = {pid: _anonymous_regions(pid, args.regions) for pid in tree}
            time.sleep(SAMPLE_S)
        wall_s = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"error: agvviz exited {proc.returncode}: {proc.stderr.read().strip()[-300:]}")
    names = _names(proc.pid, seen, parent, writers)
    print(f"wall {wall_s:.1f} s; summed PSS peak {total_peak_kib / 1024:.0f} MiB at {peak_t:.1f} s")
    print(f"  {'process':28s} {'peak PSS':>9s} {'at the peak':>12s}   lived")
    for pid in sorted(seen, key=lambda p: seen[p][0]):
        first, last, _ = seen[pid]
        print(f"  {names[pid]:28s} {peak_kib[pid] / 1024:7.0f} MiB {at_peak.get(pid, 0) / 1024:8.0f} MiB   "
              f"{first:.1f}–{last:.1f} s")
        for kib, name in regions.get(pid, []):
            print(f"      {kib / 1024:6.1f} MiB  {name}")


def _names(root: int, seen: dict, parent: dict, writers: set[int]) -> dict[int, str]:
    """The run process, the fork server, the .rrd writer, the detection workers."""
    names = {root: "run process"}
    for pid, (_, _, cmdline) in seen.items():
        if pid in writers:
            names[pid] = ".rrd writer"
        elif parent.get(pid) == root and "forkserver" in cmdline:
            names[pid] = "fork server"
        elif "resource_tracker" in cmdline:
            names[pid] = "resource tracker"
    for pid in seen:
        if pid not in names and names.get(parent.get(pid)) == "fork server":
            names[pid] = f"detection worker {pid}"
        names.setdefault(pid, f"{pid} {seen[pid][2][:20]}")
    return names


if __name__ == "__main__":
    main()
