"""Log UWB ranging, UWB fixes, the camera choice and camera–UWB fusion into a run ``.rrd``.

Entities are in :mod:`agvviz.viz.paths` (the "UWB and camera–UWB fusion" section); items come
from :class:`agvviz.graph.fuse.FusionReplay`. Everything is logged on the ``time``
timeline and on ``frame`` (the latest camera frame index), never with wall-clock values.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from agvviz.graph.fuse import FrameSetResult, RangeResult, UwbFixResult
from agvviz.viz import paths
from agvviz.viz.run_logger import _trajectory
from agvviz.viz.style import COLOR_ANCHOR, COLOR_CAMERA, COLOR_FUSED, COLOR_REJECTED, COLOR_TRUTH, COLOR_UWB

#: Colours of the three range series of each anchor.
RANGE_COLORS = {"measured": COLOR_UWB, "predicted_truth": COLOR_TRUTH, "predicted_estimate": COLOR_FUSED}
POSITION_MARKER_RADIUS = rr.Radius.ui_points(6.0)


class FusionLogger:
    """Logs :class:`FusionReplay` items into ``stream`` (the run logger's recording stream)."""

    def __init__(self, stream: rr.RecordingStream):
        self._rec = stream
        self._frame_index = 0
        self._uwb_xyz: list[np.ndarray] = []
        self._fused_xyz: list[np.ndarray] = []
        self._cam_names: list[str] = []
        self.anchor_ids: list[str] = []

    def _set_time(self, log_time_ns: int) -> None:
        self._rec.set_time(paths.TIMELINE_FRAME, sequence=int(self._frame_index))
        self._rec.set_time(paths.TIMELINE_TIME, timestamp=np.datetime64(int(log_time_ns), "ns"))

    # -- static ---------------------------------------------------------------------------------
    def log_anchors(self, anchors_m: dict[str, np.ndarray], tag_z_m: float, cam_names: list[str]) -> None:
        """Anchors as labelled points, and the styles of every UWB/fusion series (static)."""
        rec = self._rec
        self.anchor_ids = sorted(anchors_m)
        self._cam_names = sorted(cam_names)
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
                name = {"measured": "measured", "predicted_truth": "from truth", "predicted_estimate": "from estimate"}[kind]
                rec.log(paths.uwb_range(anchor, kind), rr.SeriesLines(names=f"{anchor} {name} [m]", colors=color, widths=1.5), static=True)
            rec.log(
                paths.uwb_gate(anchor),
                rr.SeriesPoints(names=f"{anchor} used (1) / gated (0)", colors=COLOR_REJECTED, marker_sizes=2.0),
                static=True,
            )
            rec.log(
                paths.uwb_range(anchor, "gated"),
                rr.SeriesPoints(
                    names=f"{anchor} range removed by a gate [m]", colors=COLOR_REJECTED,
                    markers=rr.components.MarkerShape.Cross, marker_sizes=5.0,
                ),
                static=True,
            )
        for entity, name, color in (
            (paths.ERROR_UWB_POSITION_M, "UWB fix error [m] (2-D)", COLOR_UWB),
            (paths.ERROR_FUSED_POSITION_M, "fused error [m] (2-D)", COLOR_FUSED),
            (paths.UWB_GDOP, "GDOP", COLOR_ANCHOR),
        ):
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        used_name = "camera used: " + ", ".join(f"{i} {c}" for i, c in enumerate(self._cam_names)) + ", -1 none"
        rec.log(paths.FUSION_CAMERA_USED, rr.SeriesPoints(names=used_name, colors=COLOR_CAMERA, marker_sizes=2.0), static=True)
        for entity, color in ((paths.AGV_UWB, COLOR_UWB), (paths.AGV_FUSED, COLOR_FUSED)):
            rec.log(entity, rr.Points3D([[0.0, 0.0, tag_z_m]], colors=color, radii=POSITION_MARKER_RADIUS), static=True)

    # -- per item -------------------------------------------------------------------------------
    def log(self, item) -> None:
        if isinstance(item, FrameSetResult):
            self._frame_index = item.scored.index
            self._set_time(item.scored.log_time_ns)
            used = item.selection.primary.cam_name if item.selection.primary is not None else None
            index = self._cam_names.index(used) if used in self._cam_names else -1
            self._rec.log(paths.FUSION_CAMERA_USED, rr.Scalars(float(index)))
        elif isinstance(item, RangeResult):
            self._set_time(item.log_time_ns)
            for kind, value in (
                ("measured", item.range_m),
                ("predicted_truth", item.predicted_truth_m),
                ("predicted_estimate", item.predicted_estimate_m),
            ):
                if value is not None:
                    self._rec.log(paths.uwb_range(item.anchor_id, kind), rr.Scalars(float(value)))
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
        rec.log(paths.TRAJECTORY_UWB, _trajectory(self._uwb_xyz, COLOR_UWB))
        if np.isfinite(fix.gdop):
            rec.log(paths.UWB_GDOP, rr.Scalars(float(fix.gdop)))
        if item.error_m is not None:
            rec.log(paths.ERROR_UWB_POSITION_M, rr.Scalars(item.error_m))
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
        rec.log(paths.TRAJECTORY_FUSED, _trajectory(self._fused_xyz, COLOR_FUSED))
        if item.fused_error_m is not None:
            rec.log(paths.ERROR_FUSED_POSITION_M, rr.Scalars(item.fused_error_m))
