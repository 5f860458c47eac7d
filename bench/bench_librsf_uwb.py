"""UWB localisation on real data: the Labyrinth set (libRSF ``Indoor_UWB``, 2-D, 4 anchors).

Usage:  python bench/bench_librsf_uwb.py [--data ../shared/data/librsf_uwb/Indoor_UWB]

Feeds the 233 recorded ranges (round robin over anchors 105, 107, 108, 109) to
:class:`agvviz.uwb.UwbTracker` — a fix per completed round — with the trilateral centroid
(paper 003 eqs 3–6) and with least squares, each with and without the residual gate, and
prints the 2-D error of every fix against the ground truth at the fix's time (mean, RMSE,
median, p95 in mm). Anchors and tag are taken as coplanar (the set is 2-D).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from agvviz.uwb import RangeRecord, UwbTracker

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "librsf_uwb" / "Indoor_UWB"


def load(data: Path) -> tuple[list[tuple[float, str, float]], dict[str, np.ndarray], dict[float, np.ndarray]]:
    """Ranges (t_s, anchor id, range_m), anchors (id → (x, y, 0)), truth (t_s → (x, y))."""
    ranges, anchors = [], {}
    for line in (data / "Indoor_UWB_Input.txt").read_text().splitlines():
        f = line.split()
        if f and f[0] == "range2":
            ranges.append((float(f[1]), f[6], float(f[2])))
            anchors[f[6]] = np.array([float(f[4]), float(f[5]), 0.0])
    truth = {}
    for line in (data / "Indoor_UWB_GT.txt").read_text().splitlines():
        f = line.split()
        if f and f[0] == "point2":
            truth[float(f[1])] = np.array([float(f[2]), float(f[3])])
    return ranges, anchors, truth


def errors_m(ranges, anchors, truth, method: str, gate: bool) -> np.ndarray:
    tracker = UwbTracker(anchors, 0.0, method=method, gate=gate, sigma_m=0.1)
    out = []
    for t_s, anchor, range_m in ranges:
        fix = tracker.add(RangeRecord(int(round(t_s * 1e9)), anchor, range_m))
        if fix is not None:
            out.append(float(np.linalg.norm(fix.position_m[:2] - truth[t_s])))
    return np.array(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"no Labyrinth data at {args.data} (see ../shared/data/MANIFEST.md)")
    ranges, anchors, truth = load(args.data)
    print(f"{len(ranges)} ranges, anchors {sorted(anchors)}")
    print(f"{'method':14s} {'gate':9s} {'fixes':>5s} {'mean mm':>8s} {'RMSE mm':>8s} {'median mm':>9s} {'p95 mm':>7s}")
    for method in ("centroid", "least_squares"):
        for gate in (True, False):
            e = errors_m(ranges, anchors, truth, method, gate) * 1000
            print(f"{method:14s} {'residual' if gate else 'none':9s} {len(e):5d} {e.mean():8.1f} "
                  f"{np.sqrt(np.mean(e**2)):8.1f} {np.median(e):9.1f} {np.percentile(e, 95):7.1f}")


if __name__ == "__main__":
    main()
