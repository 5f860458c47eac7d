"""Issue 10's robustness campaign as a script: try agvviz as a hostile user would, print the
table (category × tried / clean error / ok / crash / hang / partial output / input modified /
silent wrong) and write a markdown report with every failing case's command and stderr tail.

    python bench/robustness_campaign.py                    # the whole campaign, 2 jobs
    python bench/robustness_campaign.py --fast             # the default-test subset
    python bench/robustness_campaign.py --only "run dup-"  --workdir /tmp/rb   # some cases, keep files
    python bench/robustness_campaign.py --out runs/robustness.md --jobs 2 --seed 10 --seeds 4

Exit status 1 when any case is a crash, hang, input modified or silent wrong. Deterministic:
every random draw comes from the seed. Same harness as tests/robustness (pytest -m campaign).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "robustness"))

from robustness_cases import CAMPAIGN_SEED, run_campaign  # noqa: E402
from robustness_harness import FORBIDDEN, table  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=2, help="cases at a time (default 2)")
    parser.add_argument("--seed", type=int, default=CAMPAIGN_SEED, help="first corruption seed")
    parser.add_argument("--seeds", type=int, default=4, help="number of corruption seeds (random damage per seed)")
    parser.add_argument("--fast", action="store_true", help="only the default-test subset")
    parser.add_argument("--out", type=Path, default=REPO / "runs" / "robustness.md", help="markdown report")
    parser.add_argument("--only", default=None, help="only the cases whose id contains this text")
    parser.add_argument("--workdir", type=Path, default=None, help="keep the case files here")
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error("--jobs must be >= 1")
    root = args.workdir or Path(tempfile.mkdtemp(prefix="agvviz-robustness-"))
    try:
        results, text = run_campaign(root, jobs=args.jobs, seed=args.seed, n_seeds=args.seeds,
                                     report_path=args.out, fast=args.fast, only=args.only)
    finally:
        if args.workdir is None:
            shutil.rmtree(root, ignore_errors=True)
    print()
    print(table(results))
    print(f"\nreport: {args.out}")
    failing = [r for r in results if r.failed]
    for r in failing:
        print("\n" + r.describe())
    return 1 if any(r.klass in FORBIDDEN for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
