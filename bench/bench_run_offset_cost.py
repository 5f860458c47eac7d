"""The cost of the check stage's run-level time-offset fit (docs/suspects.md, "Run-level findings"):
CPU time of ``ReplayGraph.run_findings`` at the end of a replay, per clean step, against the
replay's own CPU time — on a clean qr_floor recording (the fit is skipped) and one with a 30 ms
stamp offset (the fit runs).

Usage:  python bench/bench_run_offset_cost.py [--seed 3] [--workdir DIR] [--repeats 10]

Records (or reuses) ``clean-<seed>.mcap`` and ``offset-<seed>.mcap`` in the work directory, as
bench/bench_checks.py does (6 s, 640×512, ``inject=timing:front:offset_ms=30``).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from agvviz import scenarios
from agvviz.recording.reader import ReadReport
from agvviz.replay.graph import ReplayGraph
from agvviz.replay.run import iter_role_messages, prepare
from agvviz.settings import RunSettings

SMALL = ["duration_s=6", "width_px=640", "height_px=512", "focal_px=500.0", "supersample=2"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_offset_cost_"))
    work.mkdir(parents=True, exist_ok=True)
    for kind, extra in (("clean", []), ("offset", ["inject=timing:front:offset_ms=30"])):
        path = work / f"{kind}-{args.seed}.mcap"
        if not path.exists():
            scenarios.record("qr_floor", path, seed=args.seed, overrides=SMALL + extra)
        prepared = prepare(path, RunSettings(truth="ignore"), None, None, None)
        graph = ReplayGraph(prepared.replay, until="solve")
        report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
        t0 = time.process_time()
        frames = list(graph.frames(iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, report)))
        replay_s = time.process_time() - t0
        t0 = time.process_time()
        for _ in range(args.repeats):
            findings = graph.run_findings()
        fit_s = (time.process_time() - t0) / args.repeats
        steps = sum(len(state.offset_steps) for state in graph.checks.cameras.values())
        print(f"{kind}: {len(frames)} frames, replay {replay_s:.2f} s CPU; run-level fit {fit_s * 1000:.1f} ms "
              f"({fit_s / max(steps, 1) * 1e6:.0f} µs per clean step, {steps} steps; {100 * fit_s / replay_s:.1f} % "
              f"of the replay), findings: {len(findings)}")


if __name__ == "__main__":
    main()
