"""NEES of the 6-DoF pose on the `typical` world, pixel-only covariance against the full one.

Records ``--seeds`` seeds of ``qr_floor`` and ``uwb_room`` under their default (``typical``)
realism, replays each with ``lm`` twice — ``covariance=pixel`` (pixel noise only, as before
issue 25) and ``covariance=full`` (docs/uncertainty.md) — through
:func:`agvviz.replay.run.replay_frames` (no ``.rrd``), and prints per world and mode the mean,
median and 95th percentile of the frames' NEES and the share of frames under the χ² 99 % bound
of the frame's ``nees_dof`` (16.81 for 6), and the mean without the frames whose pose flipped to
the other IPPE branch (``FrameResult.flipped``: a wrong pose no covariance describes — issue
25's suspect checks name it). Goal (issue 25): mean 4.5–8 and ≥ 95 % under the bound with
``covariance=full`` on both worlds.

Each seed draws its own calibration, extrinsic and map errors (one draw per recording): the
NEES of a seed's frames share them, so the figures need many seeds, not long recordings.

    python bench/bench_nees.py                               # 20 seeds, the scenarios' lengths
    python bench/bench_nees.py --seeds 8 --duration-s 5      # shorter
    python bench/bench_nees.py --first-seed 8 --seeds 8 --worlds qr_floor   # seeds 8..15
    python bench/bench_nees.py --keep-dir runs/nees_recordings   # record once, replay again later
    python bench/bench_nees.py --modes full                  # the full covariance only
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agvviz.replay.run import replay_frames  # noqa: E402
from agvviz.scenarios import record  # noqa: E402
from agvviz.settings import RunSettings, apply_overrides  # noqa: E402

WORLDS = ("qr_floor", "uwb_room")
MODES = ("pixel", "full")
#: χ² 99 % quantiles by degrees of freedom (scipy.stats.chi2.ppf(0.99, k)).
CHI2_99 = {3: 11.345, 6: 16.812}


def figures(nees: list[tuple[float, int, bool]]) -> str:
    """mean, median, p95, the share under the χ² 99 % bound of each frame's dof, and the mean
    over the frames that did not flip."""
    if not nees:
        return "no frames with NEES"
    values = np.array([v for v, _, _ in nees])
    under = np.mean([v <= CHI2_99[dof] for v, dof, _ in nees])
    kept = np.array([v for v, _, flipped in nees if not flipped])
    return (
        f"frames {len(values):5d}  mean {values.mean():8.2f}  median {np.median(values):7.2f}  "
        f"p95 {np.percentile(values, 95):8.2f}  under χ² 99 % {100 * under:5.1f} %  "
        f"mean w/o {len(values) - len(kept)} flipped {kept.mean() if len(kept) else float('nan'):7.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=20, help="number of seeds per world")
    parser.add_argument("--first-seed", type=int, default=0, help="seeds FIRST..FIRST+N-1")
    parser.add_argument("--duration-s", type=float, default=None, help="recording length (default: the scenario's)")
    parser.add_argument("--worlds", default=",".join(WORLDS))
    parser.add_argument("--modes", default=",".join(MODES), help="covariance modes to replay with: pixel,full")
    parser.add_argument("--keep-dir", type=Path, default=None,
                        help="keep the recordings here and reuse those already there (same world, seed, length)")
    args = parser.parse_args()
    worlds = [w for w in args.worlds.split(",") if w]
    modes = [m for m in args.modes.split(",") if m]
    nees: dict[tuple[str, str], list[tuple[float, int, bool]]] = {(w, m): [] for w in worlds for m in modes}
    options = [] if args.duration_s is None else [f"duration_s={args.duration_s}"]
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    print(f"typical {', '.join(worlds)}; seeds {seeds[0]}..{seeds[-1]}; {' '.join(options) or 'scenario lengths'}; solver lm")
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep_dir or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for world in worlds:
            for seed in seeds:
                path = folder / f"{world}-{seed}-{args.duration_s or 'default'}.mcap"
                t0 = time.perf_counter()
                if not path.exists():
                    record(world, path, seed=seed, overrides=options)
                line = f"  {world} seed {seed:2d} ({time.perf_counter() - t0:.0f} s):"
                for mode in modes:
                    settings = apply_overrides(RunSettings(), ["solver=lm", f"covariance={mode}"])
                    frame_nees = [(f.nees, f.nees_dof, f.flipped) for f in replay_frames(path, settings) if f.nees is not None]
                    nees[world, mode] += frame_nees
                    mean = float(np.mean([v for v, _, _ in frame_nees])) if frame_nees else float("nan")
                    line += f"  {mode} mean {mean:.1f}"
                print(line, flush=True)
                if args.keep_dir is None:
                    path.unlink()
    print()
    for world in worlds:
        for mode in modes:
            print(f"{world:9s} covariance={mode:5s}  {figures(nees[world, mode])}")
    print("(goal with covariance=full: mean 4.5–8, ≥ 95 % under χ² 99 %)")


if __name__ == "__main__":
    main()
