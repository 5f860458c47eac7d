"""Joint solve (markers=all) against the largest marker alone (markers=largest) on a rendered map.

Records ``qr_floor`` with a dense grid of small markers (default: AprilTag 36h11, 2–6 in view)
under the ``typical`` realism profile, replays it both ways and prints, per setting, the AGV
position RMSE against truth and, for the joint solve, the RMSE over the RMS of the per-frame
Cramér–Rao bound of all corners used (at the run's pooled pixel σ; goal ≤ 1.1) and the NEES.

    python bench/bench_joint.py                          # AprilTag 36h11, seeds 0-2, 10 s each
    python bench/bench_joint.py --family qr --seeds 0    # QR codes
    python bench/bench_joint.py --set realism=ideal      # any scenario option
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agvviz.replay import run as runner  # noqa: E402
from agvviz.scenarios import record as record_scenario  # noqa: E402
from agvviz.settings import RunSettings, apply_overrides  # noqa: E402


def replay_frames(recording: Path, overrides: list[str]) -> list:
    """Every frame result of ``recording`` replayed under the run settings ``overrides``."""
    return list(runner.replay_frames(recording, apply_overrides(RunSettings(), overrides)))


def rms(values) -> float:
    values = np.asarray([v for v in values if v is not None], dtype=float)
    return float(np.sqrt(np.mean(values**2))) if len(values) else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--family", default="DICT_APRILTAG_36h11", help="qr_floor marker_family (qr, DICT_...)")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--set", action="append", default=[], help="extra scenario option key=value")
    args = parser.parse_args()
    options = [
        f"duration_s={args.duration}", "code_size_m=0.25", "grid_spacing_m=1.25", *args.set,
    ]
    if args.family != "qr":
        options.append(f"marker_family={args.family}")
    print(f"qr_floor {' '.join(options)}; seeds {args.seeds}")
    errors = collections.defaultdict(list)
    crlb_all, ratio_all, nees_all, in_view, left_out = [], [], [], collections.Counter(), 0
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            recording = Path(tmp) / f"seed{seed}.mcap"
            t0 = time.perf_counter()
            record_scenario("qr_floor", recording, seed=seed, overrides=options)
            print(f"  seed {seed}: recorded in {time.perf_counter() - t0:.0f} s", flush=True)
            for mode in ("largest", "all"):
                frames = replay_frames(recording, [f"markers={mode}"])
                solved = [f for f in frames if f.solved]
                errors[mode] += [f.position_error_m for f in solved if f.position_error_m is not None]
                if mode == "all":
                    crlb_all += [f.crlb_position_m for f in solved if f.crlb_position_m is not None]
                    ratio_all += [f.position_over_crlb for f in solved if f.position_over_crlb is not None]
                    nees_all += [f.nees for f in solved if f.nees is not None]
                    in_view.update(len(f.observations) for f in frames)
                    left_out += sum(len(f.excluded_marker_ids) for f in frames)
                errors[f"solved_{mode}"].append(f"{len(solved)}/{len(frames)}")
    print(f"markers in view per frame (count of frames): {dict(sorted(in_view.items()))}; markers left out: {left_out}")
    rmse_largest, rmse_all = rms(errors["largest"]), rms(errors["all"])
    print(f"markers=largest: position RMSE {1000 * rmse_largest:.2f} mm  (solved {', '.join(errors['solved_largest'])})")
    print(f"markers=all:     position RMSE {1000 * rmse_all:.2f} mm  (solved {', '.join(errors['solved_all'])})")
    crlb = rms(crlb_all)
    print(f"joint: RMS CRLB of all corners {1000 * crlb:.2f} mm; RMSE / RMS CRLB = {rmse_all / crlb:.2f}; "
          f"RMS of per-frame error / CRLB = {rms(ratio_all):.2f} (goal <= 1.1); NEES mean {np.mean(nees_all):.1f} (6 = consistent)")


if __name__ == "__main__":
    main()
