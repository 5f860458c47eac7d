"""Planar-prior solver vs 6-DoF LM on qr_floor: fronto-parallel (camera straight down,
``cam_lookahead_m=0``) and the default tilted mount.

Usage:  python bench/bench_planar.py [--seed 0] [--duration 10] [--set key=value ...]

For each mount: record qr_floor in the ideal world (a solver study against the CRLB; ``--set
realism=typical`` for the realistic one), replay it with ``lm`` (depth and pixel objectives) and
``planar``; print AGV position and heading RMSE over the frames all of them solved, the mean
CRLB of each model at the true pose, the mean NEES, and the error reduction planar / lm.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from agvviz import scenarios as scenario_registry
from agvviz.replay.graph import replay
from agvviz.recording.reader import iter_messages
from agvviz.settings import RunSettings


def rmse(values) -> float:
    v = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(v**2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args()
    runs = {
        "lm (depth)": RunSettings(solver="lm"),
        "lm (pixel)": RunSettings(solver="lm", objective="pixel"),
        "planar": RunSettings(solver="planar"),
    }
    with tempfile.TemporaryDirectory() as tmp:
        for lookahead in (0.0, 1.0):
            recording = Path(tmp) / f"qr_floor_{lookahead:g}.mcap"
            scenario_registry.record(
                "qr_floor", recording, seed=args.seed,
                overrides=[f"duration_s={args.duration}", f"cam_lookahead_m={lookahead}", "realism=ideal", *args.overrides],
            )
            frames = {name: {f.index: f for f in replay(iter_messages(recording), s)} for name, s in runs.items()}
            common = sorted(set.intersection(*({i for i, f in d.items() if f.solved and f.position_error_m is not None} for d in frames.values())))
            total = len(next(iter(frames.values())))
            print(f"\ncam_lookahead_m={lookahead:g} ({'fronto-parallel, camera straight down' if lookahead == 0 else 'default tilt'}): "
                  f"{len(common)} of {total} frames solved by all")
            print(f"{'solver':12s} {'pos RMSE mm':>12s} {'heading RMSE deg':>17s} {'mean CRLB mm':>13s} {'RMSE÷CRLB':>10s} {'mean NEES (dof)':>16s}")
            pos = {}
            for name, d in frames.items():
                sel = [d[i] for i in common]
                pos[name] = rmse([f.position_error_m * 1000 for f in sel])
                crlb = np.mean([f.crlb_position_m * 1000 for f in sel if f.crlb_position_m is not None])
                ratio = rmse([f.position_over_crlb for f in sel if f.position_over_crlb is not None])
                nees = [f.nees for f in sel if f.nees is not None]
                dof = sel[0].nees_dof if sel else 0
                print(f"{name:12s} {pos[name]:12.3f} {rmse([f.heading_error_deg for f in sel]):17.4f} {crlb:13.3f} "
                      f"{ratio:10.2f} {np.mean(nees):10.2f} ({dof})")
            for name in ("lm (depth)", "lm (pixel)"):
                print(f"position error reduction planar vs {name}: {pos[name] / pos['planar']:.1f}×")


if __name__ == "__main__":
    main()
