"""Replay of multi-camera frames, UWB ranges and their fusion (paper 003). No I/O of its own.

:class:`FusionReplay` sits beside :class:`agvviz.replay.solve.Replay`: the runner hands it every
recording message together with the per-camera :class:`~agvviz.model.frames.FrameResult` the
pipeline made of it (or None). It

* groups the frames of one time stamp (several cameras) and turns them into one camera fix
  (:func:`agvviz.replay.multicam.select_camera_fix`) — a recording with one camera gives sets of one;
* turns ``/uwb/range`` messages into ranges (eq 1 applied to the recorded timestamps) and,
  through :class:`agvviz.uwb.UwbTracker`, into UWB fixes;
* feeds camera fixes, UWB fixes and ranges to the fusion component in time order.

It returns what happened as :class:`~agvviz.model.fusion.FrameSetResult`,
:class:`~agvviz.model.fusion.RangeResult` and :class:`~agvviz.model.fusion.UwbFixResult` items, in time order, for the run logger and the statistics. A frame set
is complete when a message with a later time arrives, so :meth:`FusionReplay.finish` must be
called after the last message.
"""

from __future__ import annotations

import numpy as np

from agvviz.fusion import FusionStep, KalmanSettings, make_fusion
from agvviz.model.fusion import FrameSetResult, RangeResult, UwbFixResult
from agvviz.replay.multicam import select_camera_fix
from agvviz.model.messages import FrameTransformMsg
from agvviz.recording.reader import RecordedMessage
from agvviz.model.frames import FrameResult
from agvviz.replay.sync import SyncState
from agvviz.settings import RunSettings
from agvviz.uwb import RangeRecord, UwbTracker, range_from_timestamps_m
from agvviz.uwb.localize import predicted_ranges_m

from agvviz.model.topics import ROLE_UWB_ANCHORS, ROLE_UWB_RANGE  # noqa: E402
TAG_FRAME = "uwb_tag"


class FusionReplay:
    """See the module docstring. ``cameras`` is a read-only snapshot of the cameras' state
    (:class:`~agvviz.model.cameras.CameraState` by name), replaced by the graph whenever a camera
    changes and read when a frame set is completed; ``sync`` the sync stage, whose
    ground truth (interpolated at each stamp) scores ranges, fixes and fused positions."""

    def __init__(self, settings: RunSettings, cameras: dict, sync: SyncState):
        self.settings = settings
        self.cameras = cameras
        self.sync = sync
        self.anchors_m: dict[str, np.ndarray] = {}
        self.tag_z_m: float | None = None
        self.tracker: UwbTracker | None = None
        self.fusion = make_fusion("camera_only", {}, 0.0)
        self._pending: list[FrameResult] = []
        self._camera_available = False
        self._estimate_xy: np.ndarray | None = None

    @property
    def has_uwb(self) -> bool:
        return self.tracker is not None

    def _start_uwb(self) -> None:
        """Tracker and fusion once both the anchors and the tag mount are known."""
        if self.tracker is not None or not self.anchors_m or self.tag_z_m is None:
            return
        s = self.settings
        self.tracker = UwbTracker(
            self.anchors_m, self.tag_z_m, method=s.uwb, gate=s.uwb_gate == "residual", sigma_m=s.uwb_sigma_m
        )
        kalman = KalmanSettings(
            camera_sigma_m=s.camera_sigma_m, range_sigma_m=s.uwb_sigma_m, range_gate_chi2=s.kalman_gate_chi2
        )
        self.fusion = make_fusion(s.fusion, self.anchors_m, self.tag_z_m, kalman)

    def feed(self, message: RecordedMessage, frame: FrameResult | None) -> list:
        """Consume one message (and the pipeline's frame result for it); returns the items
        completed by it, in time order."""
        out = []
        if self._pending and message.time_ns != self._pending[0].log_time_ns:
            out.append(self._complete_frame_set())
        value = message.value
        if isinstance(value, list) and value and isinstance(value[0], FrameTransformMsg):
            for tf in value:
                if tf.parent_frame == "agv" and tf.child_frame == TAG_FRAME:
                    # The tag is taken to sit above the AGV origin; its height is what counts.
                    self.tag_z_m = float(tf.T_parent_child[2, 3])
            self._start_uwb()
        elif message.role == ROLE_UWB_ANCHORS and isinstance(value, dict):
            self.anchors_m = {str(a["id"]): np.asarray(a["position_m"], dtype=float) for a in value["anchors"]}
            self._start_uwb()
        elif message.role == ROLE_UWB_RANGE and isinstance(value, dict) and self.tracker is not None:
            out += self._range(message.time_ns, value)
        if frame is not None:
            self._pending.append(frame)
        return out

    def finish(self) -> list:
        """Complete the last frame set."""
        return [self._complete_frame_set()] if self._pending else []

    # -- internals --------------------------------------------------------------------------
    def _truth_xy(self, t_ns: int) -> np.ndarray | None:
        truth = self.sync.truth_at(t_ns)
        return None if truth is None else truth[:2, 3].copy()

    def _note_fused(self, step: FusionStep, truth_xy: np.ndarray | None) -> float | None:
        """Remember the fused position as the current estimate; its 2-D error, if known."""
        if step.fused is None:
            return None
        self._estimate_xy = step.fused.position_xy_m
        return None if truth_xy is None else float(np.linalg.norm(step.fused.position_xy_m - truth_xy))

    def _complete_frame_set(self) -> FrameSetResult:
        frames, self._pending = self._pending, []
        selection = select_camera_fix(
            frames, self.cameras, self.settings.camera_select, self.settings.gimbal_threshold,
            floor=self.settings.floor_constraint,
        )
        xy = None if selection.primary is None else selection.primary.T_world_agv[:2, 3].copy()
        self._camera_available = xy is not None
        step = self.fusion.camera(frames[0].log_time_ns, xy)
        truth = frames[0].T_world_agv_truth
        error = self._note_fused(step, None if truth is None else truth[:2, 3])
        if xy is not None and self._estimate_xy is None:
            self._estimate_xy = xy
        return FrameSetResult(selection.frames, selection, step, self._camera_available, error)

    def _range(self, log_time_ns: int, msg: dict) -> list:
        anchor = str(msg["anchor"])
        range_m = float(msg["range_m"])
        tof_range_m = float(range_from_timestamps_m(msg["t1_ns"], msg["t2_ns"], msg["t3_ns"], msg["t4_ns"]))
        truth_xy = self._truth_xy(log_time_ns)
        anchor_m = self.anchors_m.get(anchor)

        def predicted(xy):
            if xy is None or anchor_m is None:
                return None
            return float(predicted_ranges_m(anchor_m[None], [xy[0], xy[1], self.tag_z_m])[0])

        predicted_estimate = predicted(self._estimate_xy)  # before this range updates it
        step = self.fusion.uwb_range(log_time_ns, anchor, range_m)
        error = self._note_fused(step, truth_xy)
        out = [
            RangeResult(
                log_time_ns, anchor, range_m, tof_range_m, predicted(truth_xy), predicted_estimate,
                step, self._camera_available, error,
            )
        ]
        fix = self.tracker.add(RangeRecord(log_time_ns, anchor, range_m))
        if fix is not None:
            fix_truth = self._truth_xy(fix.log_time_ns)
            fix_step = self.fusion.uwb_fix(fix)
            error = self._note_fused(fix_step, fix_truth)
            if self._estimate_xy is None:
                self._estimate_xy = fix.position_m[:2].copy()
            out.append(UwbFixResult(fix, fix_truth, fix_step, self._camera_available, error))
        return out
