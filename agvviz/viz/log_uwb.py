"""The UWB modality of a run ``.rrd``: UWB ranging, UWB fixes, the camera choice and camera–UWB fusion.

Entities are in :mod:`agvviz.viz.paths` (the "UWB and camera–UWB fusion" section) and below;
items come from :class:`agvviz.replay.fuse.FusionReplay`. Everything is stamped with
:func:`agvviz.viz.timelines.set_stamp`: ``frame`` (the latest camera frame index), ``time`` and
``elapsed`` (seconds since the recording's first stamp).

``fusion/camera_used``            StateChange: the camera whose fix was used ("none": no camera
                                  solved), logged when it changes (a category lane, not a line)
``fusion/fused_from``             StateChange: what the fused estimate comes from (camera, UWB
                                  compensated, Kalman), logged when it changes
``errors/uwb_position_mm``        Scalars: 2-D error of each UWB fix (mm)
``errors/fused_position_mm``      Scalars: 2-D error of each fused output (mm)

The layout is :func:`agvviz.viz.blueprints.uwb_blueprint`.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from agvviz.model.fusion import FrameSetResult, RangeResult, UwbFixResult
from agvviz.viz import paths
from agvviz.viz.log_frames import trajectory
from agvviz.viz.style import (
    COLOR_ANCHOR,
    COLOR_CAMERA,
    COLOR_FUSED,
    COLOR_REJECTED,
    COLOR_STALE,
    COLOR_TRUTH,
    COLOR_UWB,
    COLOR_ZERO,
    LEGEND,
)
from agvviz.viz.timelines import set_stamp

#: State of ``fusion/camera_used`` when no camera solved.
NO_CAMERA = "none"
#: Labels and colours of the ``fusion/fused_from`` states (FusedFix.source).
SOURCE_STATES = {
    "camera": ("camera fix", COLOR_CAMERA),
    "uwb": ("UWB (compensated)", COLOR_UWB),
    "kalman": ("Kalman (camera + UWB)", COLOR_FUSED),
}

#: Colours and legend names of the three range series of each anchor.
RANGE_COLORS = {"measured": COLOR_UWB, "predicted_truth": COLOR_TRUTH, "predicted_estimate": COLOR_FUSED}
RANGE_NAMES = {"measured": "measured", "predicted_truth": "expected from truth", "predicted_estimate": "expected from fused"}
POSITION_MARKER_RADIUS = rr.Radius.ui_points(6.0)
#: The colour key above the range plots (one for the four: a legend in each would cover the data).
RANGE_KEY = "blue: measured · green: expected from truth · yellow: expected from fused · red ×: gated"


class FusionLogger:
    """Logs :class:`FusionReplay` items into ``stream`` (the run logger's recording stream)."""

    def __init__(self, stream: rr.RecordingStream, recording_start_ns: int | None = None):
        """``recording_start_ns``: the recording's first stamp (``elapsed`` counts from it);
        None: the first logged item's stamp."""
        self._rec = stream
        self.recording_start_ns = None if recording_start_ns is None else int(recording_start_ns)
        self._frame_index = 0
        self._camera_used: str | None = None
        self._source: str | None = None
        #: Every UWB fix and fused error (mm): the error plot's axis is set from them.
        self.errors_mm: list[float] = []
        #: anchor -> (shortest, longest) range of any of its series (m): each range plot's axis.
        self.range_extents: dict[str, tuple[float, float]] = {}
        self._uwb_xyz: list[np.ndarray] = []
        self._fused_xyz: list[np.ndarray] = []
        self._cam_names: list[str] = []
        self.anchor_ids: list[str] = []

    def _set_time(self, log_time_ns: int) -> None:
        if self.recording_start_ns is None:
            self.recording_start_ns = int(log_time_ns)
        set_stamp(self._rec, self._frame_index, log_time_ns, self.recording_start_ns)

    def _range_seen(self, anchor: str, range_m: float) -> None:
        low, high = self.range_extents.get(anchor, (range_m, range_m))
        self.range_extents[anchor] = (min(low, range_m), max(high, range_m))

    # -- static ---------------------------------------------------------------------------------
    def log_anchors(self, anchors_m: dict[str, np.ndarray], tag_z_m: float, cam_names: list[str]) -> None:
        """Anchors as labelled points, and the styles of every UWB/fusion series (static)."""
        rec = self._rec
        self.anchor_ids = sorted(anchors_m)
        self._cam_names = sorted(cam_names)
        rec.log(paths.UWB_RANGE_KEY, rr.TextDocument(RANGE_KEY, media_type=rr.MediaType.MARKDOWN), static=True)
        rec.log(
            paths.UWB_ANCHORS,
            rr.Points3D(
                [anchors_m[a] for a in self.anchor_ids], labels=self.anchor_ids, colors=COLOR_ANCHOR,
                radii=rr.Radius.ui_points(8.0),
            ),
            static=True,
        )
        for anchor in self.anchor_ids:
            for kind, color in RANGE_COLORS.items():
                rec.log(paths.uwb_range(anchor, kind), rr.SeriesLines(names=RANGE_NAMES[kind], colors=color, widths=1.5), static=True)
            rec.log(
                paths.uwb_gate(anchor),
                rr.SeriesPoints(names=f"{anchor} used (1) / gated (0)", colors=COLOR_REJECTED, marker_sizes=2.0),
                static=True,
            )
            rec.log(
                paths.uwb_range(anchor, "gated"),
                rr.SeriesPoints(
                    names="removed by a gate", colors=COLOR_REJECTED,
                    markers=rr.components.MarkerShape.Cross, marker_sizes=5.0,
                ),
                static=True,
            )
        for entity, name, color in (
            (paths.ERROR_FUSED_POSITION_MM, LEGEND[COLOR_FUSED] + " [mm]", COLOR_FUSED),
            (paths.UWB_GDOP, "GDOP", COLOR_ANCHOR),
        ):
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        rec.log(
            paths.ERROR_UWB_POSITION_MM,
            rr.SeriesPoints(names=LEGEND[COLOR_UWB] + " fix [mm]", colors=COLOR_UWB, marker_sizes=2.0),
            static=True,
        )
        rec.log(
            paths.FUSION_CAMERA_USED,
            rr.StateConfiguration(
                values=[*self._cam_names, NO_CAMERA],
                labels=[*(f"camera {c}" for c in self._cam_names), "no camera (code hidden)"],
                colors=[*(COLOR_CAMERA for _ in self._cam_names), COLOR_STALE],
            ),
            static=True,
        )
        rec.log(
            paths.FUSION_SOURCE,
            rr.StateConfiguration(
                values=list(SOURCE_STATES),
                labels=[label for label, _ in SOURCE_STATES.values()],
                colors=[color for _, color in SOURCE_STATES.values()],
            ),
            static=True,
        )
        for entity, color in ((paths.AGV_UWB, COLOR_UWB), (paths.AGV_FUSED, COLOR_FUSED)):
            rec.log(entity, rr.Points3D([[0.0, 0.0, tag_z_m]], colors=color, radii=POSITION_MARKER_RADIUS), static=True)

    # -- per item -------------------------------------------------------------------------------
    def log(self, item) -> None:
        if isinstance(item, FrameSetResult):
            self._frame_index = item.scored.index
            self._set_time(item.scored.log_time_ns)
            used = item.selection.primary.cam_name if item.selection.primary is not None else NO_CAMERA
            if used != self._camera_used:
                self._rec.log(paths.FUSION_CAMERA_USED, rr.StateChange(state=used))
                self._camera_used = used
        elif isinstance(item, RangeResult):
            self._set_time(item.log_time_ns)
            for kind, value in (
                ("measured", item.range_m),
                ("predicted_truth", item.predicted_truth_m),
                ("predicted_estimate", item.predicted_estimate_m),
            ):
                if value is not None:
                    self._rec.log(paths.uwb_range(item.anchor_id, kind), rr.Scalars(float(value)))
                    self._range_seen(item.anchor_id, float(value))
            for anchor, passed in item.step.range_gate.items():
                if not passed:
                    self._rec.log(paths.uwb_range(anchor, "gated"), rr.Scalars(float(item.range_m)))
                    self._rec.log(
                        paths.EVENTS_UWB_GATE,
                        rr.TextLog(f"kalman gate removed {anchor}: {item.range_m:.3f} m", level=rr.TextLogLevel.WARN),
                    )
        elif isinstance(item, UwbFixResult):
            self._log_fix(item)
        self._log_step(item)

    def _log_fix(self, item: UwbFixResult) -> None:
        fix = item.fix
        self._set_time(fix.log_time_ns)
        rec = self._rec
        position = fix.position_m
        rec.log(paths.AGV_UWB, rr.Transform3D(translation=[position[0], position[1], 0.0]))
        self._uwb_xyz.append(np.array([position[0], position[1], 0.0]))
        rec.log(paths.TRAJECTORY_UWB, trajectory(self._uwb_xyz, COLOR_UWB))
        if np.isfinite(fix.gdop):
            rec.log(paths.UWB_GDOP, rr.Scalars(float(fix.gdop)))
        if item.error_m is not None:
            rec.log(paths.ERROR_UWB_POSITION_MM, rr.Scalars(1000.0 * item.error_m))
            self.errors_mm.append(1000.0 * item.error_m)
        removed = []
        for anchor, gated, residual, range_m in zip(fix.anchor_ids, fix.gated, fix.residuals_m, fix.ranges_m):
            rec.log(paths.uwb_gate(anchor), rr.Scalars(0.0 if gated else 1.0))
            if gated:
                rec.log(paths.uwb_range(anchor, "gated"), rr.Scalars(float(range_m)))
                removed.append(f"{anchor} (residual {residual * 1000:+.0f} mm)")
        if removed:
            rec.log(
                paths.EVENTS_UWB_GATE,
                rr.TextLog(f"{fix.method} fix: residual gate removed " + ", ".join(removed), level=rr.TextLogLevel.WARN),
            )

    def _log_step(self, item) -> None:
        step = item.step
        rec = self._rec
        for event in step.events:
            rec.log(paths.EVENTS_FUSION, rr.TextLog(event.text(), level=rr.TextLogLevel.INFO))
        if step.fused is None:
            return
        xy = step.fused.position_xy_m
        rec.log(paths.AGV_FUSED, rr.Transform3D(translation=[xy[0], xy[1], 0.0]))
        self._fused_xyz.append(np.array([xy[0], xy[1], 0.0]))
        rec.log(paths.TRAJECTORY_FUSED, trajectory(self._fused_xyz, COLOR_FUSED))
        if step.fused.source != self._source:
            rec.log(paths.FUSION_SOURCE, rr.StateChange(state=step.fused.source))
            self._source = step.fused.source
        if item.fused_error_m is not None:
            rec.log(paths.ERROR_FUSED_POSITION_MM, rr.Scalars(1000.0 * item.fused_error_m))
            self.errors_mm.append(1000.0 * item.fused_error_m)


def log_room_outline(rec: rr.RecordingStream, anchors_m: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
    """The room as a grey wire box (static, :data:`~agvviz.viz.paths.UWB_ROOM`): the anchors'
    extent in x and y (they hang on the walls), from the floor to their highest. Returns its
    (low, high) corners for the 3D view to frame; None with fewer than two anchors or a flat
    extent."""
    points = np.array([np.asarray(p, dtype=float) for p in anchors_m.values()]).reshape(-1, 3)
    if len(points) < 2:
        return None
    low = np.array([points[:, 0].min(), points[:, 1].min(), 0.0])
    high = np.array([points[:, 0].max(), points[:, 1].max(), max(points[:, 2].max(), 0.0)])
    if np.any((high - low)[:2] <= 0.0):
        return None
    (x0, y0, z0), (x1, y1, z1) = low, high
    floor = [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, y0, z0]]
    ceiling = [[x, y, z1] for x, y, _ in floor]
    edges = [[[x, y, z0], [x, y, z1]] for x, y, _ in floor[:4]]
    rec.log(paths.UWB_ROOM, rr.LineStrips3D([floor, ceiling, *edges], colors=COLOR_ZERO, radii=rr.Radius.ui_points(1.0),
                                           labels=["room (from the anchors)"], show_labels=False), static=True)
    return low, high
