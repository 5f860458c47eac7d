"""Turn a stream of single tag–anchor ranges into UWB fixes (rounds of ranges). Numpy only.

UWB tags range to one anchor at a time (round robin). :class:`UwbTracker` keeps the latest
range of each anchor of the current round; a fix is made when every anchor has reported, or
when an anchor reports again while at least three others already have (a missed reply does
not stall the fixes). The fix carries the time of the round's newest range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.uwb.localize import METHODS, UwbFix, gate_ranges, least_squares_fix, trilateral_centroid


@dataclass(frozen=True)
class RangeRecord:
    """One measured range: when, which anchor, how far (m)."""

    log_time_ns: int
    anchor_id: str
    range_m: float


class UwbTracker:
    """Fixes from ranges, with paper 003's centroid or least squares and the residual gate.

    Parameters
    ----------
    anchors_m : dict anchor id → (3,) world position.
    tag_z_m : height of the tag above the floor (from the AGV's tag mount).
    method : "centroid" | "least_squares".
    gate : apply :func:`~agvviz.uwb.localize.gate_ranges` before solving.
    sigma_m : range standard deviation for the gate and the covariance.
    max_range_m : ranges outside [0, max_range_m] are refused outright (counted in
        :attr:`refused`), never used.
    """

    def __init__(
        self,
        anchors_m: dict[str, np.ndarray],
        tag_z_m: float,
        method: str = "least_squares",
        gate: bool = True,
        sigma_m: float = 0.05,
        max_range_m: float = 100.0,
    ):
        if method not in METHODS:
            raise ValueError(f"unknown UWB method {method!r}; valid: {', '.join(METHODS)}")
        if len(anchors_m) < 3:
            raise ValueError(f"a 2-D UWB fix needs at least 3 anchors, got {len(anchors_m)}")
        self.anchor_ids = sorted(anchors_m)
        self.anchors_m = np.array([np.asarray(anchors_m[a], dtype=float) for a in self.anchor_ids])
        self.tag_z_m = float(tag_z_m)
        self.method = method
        self.gate = gate
        self.sigma_m = float(sigma_m)
        self.max_range_m = float(max_range_m)
        self.refused = 0
        self._round: dict[str, RangeRecord] = {}

    def add(self, record: RangeRecord) -> UwbFix | None:
        """Consume one range; returns a fix when it completes a round, else None."""
        if record.anchor_id not in self.anchor_ids or not (
            np.isfinite(record.range_m) and 0.0 <= record.range_m <= self.max_range_m
        ):
            self.refused += 1
            return None
        fix = None
        if record.anchor_id in self._round and len(self._round) >= 3:
            fix = self._solve()
            self._round = {}
        self._round[record.anchor_id] = record
        if len(self._round) == len(self.anchor_ids):
            fix = self._solve()
            self._round = {}
        return fix

    def _solve(self) -> UwbFix:
        ids = [a for a in self.anchor_ids if a in self._round]
        index = [self.anchor_ids.index(a) for a in ids]
        anchors = self.anchors_m[index]
        ranges = np.array([self._round[a].range_m for a in ids])
        use = (
            gate_ranges(anchors, ranges, self.tag_z_m, self.sigma_m)
            if self.gate
            else np.ones(len(ids), dtype=bool)
        )
        if self.method == "centroid":
            fix = trilateral_centroid(anchors, ranges, self.tag_z_m, use=use)
        else:
            fix = least_squares_fix(anchors, ranges, self.tag_z_m, self.sigma_m, use=use)
        fix.log_time_ns = max(self._round[a].log_time_ns for a in ids)
        fix.anchor_ids = ids
        fix.ranges_m = ranges
        return fix
