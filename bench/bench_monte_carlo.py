"""Paper 000 §6 Monte-Carlo study: record p4p_monte_carlo, solve every trial with p4p, lm,
lm_pixel, lm_amb, ippe and sqpnp through the library's trials stage (agvviz.replay.studies.monte_carlo, the same
as `agvviz run` on the recording), and write the report (markdown table + .rrd with the plots).

Usage:  python bench/bench_monte_carlo.py [--trials 1000] [--cells all] [--seed 0] [--out DIR]

Writes DIR/p4p_monte_carlo.mcap (the recording), DIR/p4p_monte_carlo_report.md and
DIR/p4p_monte_carlo_report.rrd; prints the report's checks.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from agvviz import scenarios as scenario_registry
from agvviz.replay.studies.monte_carlo import replay_trials
from agvviz.recording.reader import iter_messages
from agvviz.settings import RunSettings
from agvviz.viz.log_studies import write_monte_carlo_report_rrd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--cells", default="all", choices=("paper", "crlb", "all"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    recording = args.out / "p4p_monte_carlo.mcap"
    t0 = time.perf_counter()
    scenario_registry.record(
        "p4p_monte_carlo", recording, seed=args.seed, overrides=[f"trials={args.trials}", f"cells={args.cells}"]
    )
    print(f"recorded {recording} in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    outcome = replay_trials(iter_messages(recording), RunSettings())
    print(
        f"solved {len(outcome.results)} cells × {outcome.trials_per_cell} trials × {len(outcome.solvers)} solvers "
        f"in {time.perf_counter() - t0:.1f} s"
    )
    md_path = args.out / "p4p_monte_carlo_report.md"
    tmp = md_path.with_name(f".{md_path.name}.tmp")
    tmp.write_text(outcome.report_markdown)
    os.replace(tmp, md_path)
    write_monte_carlo_report_rrd(md_path.with_suffix(".rrd"), outcome.results, outcome.report_markdown)
    summary = outcome.checks
    print(f"report: {md_path} and {md_path.with_suffix('.rrd')}")
    print(f"well-conditioned cells: {summary['well_conditioned_cells']}; max RMSE/CRLB: {summary['max_rmse_over_crlb']}")
    for name, worse in summary["worse_than_peer"].items():
        print(f"{name} worse than ippe or p4p in {len(worse)} comparisons")


if __name__ == "__main__":
    main()
