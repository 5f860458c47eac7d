"""Poses over time: a time series interpolated on SE(3), and a transform tree (tf buffer).

Numpy only. Time is integer nanoseconds. Interpolation between two poses ``T0`` (at t0) and
``T1`` (at t1) follows the geodesic ``T(t) = T0 · Exp(α · Log(T0⁻¹ T1))``, α = (t − t0)/(t1 − t0)
(constant body twist between the samples); a query at a sample's own time returns that
sample exactly.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from agvviz.geometry import se3


def interpolate(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """The pose a fraction ``alpha`` (0..1) of the way from ``T0`` to ``T1`` on SE(3)."""
    if alpha <= 0.0:
        return T0.copy()
    if alpha >= 1.0:
        return T1.copy()
    return T0 @ se3.exp(alpha * se3.log(se3.inverse(T0) @ T1))


class PoseSeries:
    """Poses at increasing times (insertion in any order), looked up at any time.

    :meth:`at` returns the sample at exactly ``t_ns``; else the interpolation between the
    samples either side when they are at most ``max_gap_ns`` apart; else the nearest sample
    when it is within ``max_dt_ns`` (the ends of the series); else ``None``.
    """

    def __init__(self):
        self._times: list[int] = []
        self._poses: list[np.ndarray] = []
        self._sorted = True
        self._constant = True  # every pose so far equals the first one added
        self._first_added: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self._times)

    def add(self, t_ns: int, T: np.ndarray) -> None:
        if self._times and t_ns < self._times[-1]:
            self._sorted = False
        T = np.asarray(T, dtype=float)
        if self._poses and self._constant:
            self._constant = bool(np.array_equal(T, self._first_added))
        if not self._poses:
            self._first_added = T
        self._times.append(int(t_ns))
        self._poses.append(T)

    def _sort(self) -> None:
        if not self._sorted:
            order = sorted(range(len(self._times)), key=lambda i: self._times[i])
            self._times = [self._times[i] for i in order]
            self._poses = [self._poses[i] for i in order]
            self._sorted = True

    def is_constant(self) -> bool:
        """True when the series holds one pose, or several that are all the same (exactly)."""
        return bool(self._poses) and self._constant

    def first(self) -> np.ndarray | None:
        """The earliest sample's pose (``None`` when empty)."""
        self._sort()
        return self._poses[0] if self._poses else None

    @property
    def span_ns(self) -> tuple[int, int] | None:
        self._sort()
        return (self._times[0], self._times[-1]) if self._times else None

    def at(self, t_ns: int, max_gap_ns: int, max_dt_ns: int = 0) -> np.ndarray | None:
        self._sort()
        times = self._times
        if not times:
            return None
        i = bisect.bisect_left(times, t_ns)
        if i < len(times) and times[i] == t_ns:
            return self._poses[i]
        if 0 < i < len(times):
            t0, t1 = times[i - 1], times[i]
            if t1 - t0 <= max_gap_ns:
                return interpolate(self._poses[i - 1], self._poses[i], (t_ns - t0) / (t1 - t0))
        candidates = [j for j in (i - 1, i) if 0 <= j < len(times)]
        j = min(candidates, key=lambda k: abs(times[k] - t_ns))
        return self._poses[j] if abs(times[j] - t_ns) <= max_dt_ns else None


#: ``T_frame_frame`` at the start of :meth:`TransformBuffer._chain` (read-only: shared, never returned).
_IDENTITY = np.eye(4)
_IDENTITY.setflags(write=False)


@dataclass
class TransformBuffer:
    """A tree of frames from ``/tf_static`` (fixed) and ``/tf`` (time-varying) transforms.

    :meth:`lookup` gives ``T_target_source`` at a time through any chain of parents (for
    example ``base_link → camera_link → camera_optical_frame``), up to the two frames' common
    ancestor. A frame with both a fixed and a time-varying parent uses the fixed one. A
    time-varying link named in ``hold`` (a child frame) is used at its first sample whatever
    the time — for a link that is constant (:meth:`is_constant`): a fixed transform published
    on ``/tf`` instead of ``/tf_static``.
    """

    max_gap_ns: int = 1_000_000_000  # interpolate a time-varying link over gaps up to this
    max_dt_ns: int = 100_000_000  # before its first / after its last sample: the nearest within this
    static: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)  # child -> (parent, T)
    dynamic: dict[str, tuple[str, PoseSeries]] = field(default_factory=dict)

    def add_static(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        self.static[child] = (parent, np.asarray(T_parent_child, dtype=float))

    def add(self, parent: str, child: str, T_parent_child: np.ndarray, t_ns: int) -> None:
        entry = self.dynamic.get(child)
        if entry is None or entry[0] != parent:
            entry = (parent, PoseSeries())
            self.dynamic[child] = entry
        entry[1].add(t_ns, T_parent_child)

    def frames(self) -> set[str]:
        names = set(self.static) | set(self.dynamic)
        names |= {p for p, _ in self.static.values()} | {p for p, _ in self.dynamic.values()}
        return names

    def is_constant(self, child: str) -> bool:
        """True when ``child``'s time-varying link holds one pose or never changes."""
        return child in self.dynamic and self.dynamic[child][1].is_constant()

    def samples(self, child: str) -> int:
        """Number of samples of ``child``'s time-varying link (0 when it has none)."""
        return len(self.dynamic[child][1]) if child in self.dynamic else 0

    def _parent(self, child: str, t_ns: int | None, hold=()) -> tuple[str, np.ndarray | None] | None:
        """(parent, T_parent_child or None when not available at t_ns), or None for a root."""
        if child in self.static:
            return self.static[child]
        if child in self.dynamic:
            parent, series = self.dynamic[child]
            if child in hold:
                return parent, series.first()
            if t_ns is None:
                return parent, None
            return parent, series.at(t_ns, self.max_gap_ns, self.max_dt_ns)
        return None

    def _chain(self, frame: str, t_ns: int | None, hold=()) -> list[tuple[str, np.ndarray | None]]:
        """[(frame, T_frame_start)] from ``frame`` itself up to its root (cycle-safe)."""
        chain = [(frame, _IDENTITY)]
        seen = {frame}
        T = _IDENTITY
        current = frame
        while True:
            step = self._parent(current, t_ns, hold)
            if step is None:
                return chain
            parent, T_parent_child = step
            if parent in seen:
                return chain
            T = None if (T is None or T_parent_child is None) else T_parent_child @ T
            chain.append((parent, T))
            seen.add(parent)
            current = parent

    def links(self, target: str, source: str) -> list[str] | None:
        """Child frames of the links between the two frames (each link joins a child to its
        parent), or ``None`` when they are not connected."""
        up_s = [f for f, _ in self._chain(source, None)]
        up_t = [f for f, _ in self._chain(target, None)]
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            return None
        return up_s[: up_s.index(common)] + up_t[: up_t.index(common)]

    def is_static(self, target: str, source: str) -> bool:
        """True when the two frames are connected by fixed links only."""
        links = self.links(target, source)
        return links is not None and all(f in self.static for f in links)

    def lookup(self, target: str, source: str, t_ns: int | None = None, hold=()) -> np.ndarray | None:
        """``T_target_source`` at ``t_ns`` (``None`` for fixed links only), or ``None`` when the
        frames are not connected or a time-varying link has no pose at that time. ``hold``:
        child frames whose time-varying link is taken at its first sample (see the class)."""
        if target == source:
            return np.eye(4)
        chain_s = dict(self._chain(source, t_ns, hold))
        chain_t = self._chain(target, t_ns, hold)
        for frame, T_frame_target in chain_t:
            if frame in chain_s:
                T_frame_source = chain_s[frame]
                if T_frame_source is None or T_frame_target is None:
                    return None
                return se3.inverse(T_frame_target) @ T_frame_source
        return None
