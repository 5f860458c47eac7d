"""The sync stage of the replay graph (DESIGN §2): what holds at each image's stamp.

:class:`SyncState` gathers the messages that are not camera frames — calibrations, static
and time-varying transforms, ground truth, odometry, the marker map — and answers, for one
image of one camera at time t:

* its **calibration**: the latest calibration of that camera stamped at or before t, else its
  earliest one (a calibration applies to every frame whatever order the file holds them in);
* its **extrinsic** ``T_body_cam``: the transform buffer's chain from the body frame (a
  setting: ``agv`` for agvviz recordings, ``base_link`` for ROS logs) to the image's frame id
  (any chain: ``base_link → camera_link → camera_optical_frame``), at t; or, for a camera
  fixed in the world, ``T_world_cam``. A link of that chain published on ``/tf`` (time-varying)
  that appears only once or never changes is a fixed mount published on the wrong topic: it
  is treated as static (valid at every frame, not only near its stamps) and :attr:`notes`
  says so (the run summary's warnings, ``inspect``);
* **ground truth** (none with ``truth=ignore``) and **odometry** at t, interpolated on SE(3) between the samples either
  side (at most ``truth_max_gap_ns`` apart), or the nearest sample within
  ``truth_max_dt_ns``.

Side files (``--calibration``, ``--extrinsic``, ``--markers``) override the recording's value
for their camera (or the map) whatever the recording holds.

A run fills the state in a first pass over the file (:meth:`add` every non-image message)
before it replays the images, so the result does not depend on the order of messages in
the file. Fed message by message instead (the library's streaming use), it knows what came
before each frame.
"""

from __future__ import annotations

import bisect

import numpy as np

from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.geometry.tf_buffer import PoseSeries, TransformBuffer
from agvviz.model.messages import CalibrationMsg, FrameTransformMsg, PoseMsg, RecordedMessage
from agvviz.model.topics import (
    ROLE_MARKER_MAP,
    ROLE_ODOMETRY,
    ROLE_TF,
    ROLE_TRUTH,
    camera_of_role,
)

#: Odometry (used by ``ambiguity=odometry`` only) may be interpolated over gaps up to this.
ODOMETRY_MAX_GAP_NS = 500_000_000


def _same_camera(a: CalibrationMsg, b: CalibrationMsg) -> bool:
    ca, cb = a.camera, b.camera
    return (
        ca.width_px == cb.width_px and ca.height_px == cb.height_px
        and np.array_equal(ca.K, cb.K) and np.array_equal(ca.dist, cb.dist)
    )


class SyncState:
    """Calibration, extrinsics, truth and odometry at any stamp (see the module docstring)."""

    def __init__(
        self,
        body_frame: str = AGV_FRAME,
        world_frame: str = WORLD_FRAME,
        truth_max_dt_ns: int = 5_000_000,
        truth_max_gap_ns: int = 50_000_000,
        ignore_truth: bool = False,
    ):
        self.body_frame = body_frame
        #: ``truth=ignore``: ground-truth messages are taken and dropped, as if the recording had none.
        self.ignore_truth = ignore_truth
        self.world_frame = world_frame
        self.truth_max_dt_ns = truth_max_dt_ns
        self.truth_max_gap_ns = truth_max_gap_ns
        self.calibrations: dict[str, list[tuple[int, CalibrationMsg]]] = {}
        self.side_calibrations: dict[str, CalibrationMsg] = {}
        self.side_extrinsics: dict[str, np.ndarray] = {}  # cam -> T_body_cam
        self.side_marker_map: dict | None = None
        self.tf = TransformBuffer(max_gap_ns=max(truth_max_gap_ns, 1_000_000_000))
        self.truth = PoseSeries()
        self.truth_frames: set[str] = set()
        self.odometry = PoseSeries()
        self.marker_map: dict | None = None
        #: Warnings about how the recording was read, one per subject (a /tf link held static).
        self.notes: dict[str, str] = {}

    # -- filling ------------------------------------------------------------------------------
    def add_calibration(self, cam_name: str, calib: CalibrationMsg, t_ns: int) -> None:
        entries = self.calibrations.setdefault(cam_name, [])
        if entries and _same_camera(entries[-1][1], calib) and t_ns >= entries[-1][0]:
            return  # a repeated CameraInfo (ROS publishes one per frame)
        if entries and t_ns < entries[-1][0]:
            bisect.insort_right(entries, (t_ns, calib), key=lambda e: e[0])
        else:
            entries.append((t_ns, calib))

    def add_transforms(self, transforms: list[FrameTransformMsg], static: bool, message: RecordedMessage) -> None:
        for tf in transforms:
            if static:
                self.tf.add_static(tf.parent_frame, tf.child_frame, tf.T_parent_child)
            else:
                t_ns = tf.stamp_ns if message.stamp_ns is not None and tf.stamp_ns else message.log_time_ns
                self.tf.add(tf.parent_frame, tf.child_frame, tf.T_parent_child, t_ns)

    def add(self, message: RecordedMessage) -> bool:
        """Take a non-image message; True when it was one the sync stage keeps."""
        value, role = message.value, message.role
        cam = camera_of_role(role)
        if isinstance(value, CalibrationMsg):
            name = cam[0] if cam else value.cam_name
            self.add_calibration(name, value, message.time_ns)
            return True
        if role == ROLE_TRUTH and self.ignore_truth and isinstance(value, (list, PoseMsg)):
            return True  # truth=ignore: consumed, never stored
        if role == ROLE_TRUTH and isinstance(value, list) and len(value) == 1 and isinstance(value[0], FrameTransformMsg):
            # truth published as a TransformStamped (motion capture): T_world_body
            self.truth.add(message.time_ns, value[0].T_parent_child)
            self.truth_frames.add(value[0].parent_frame)
            return True
        if isinstance(value, list) and value and all(isinstance(v, FrameTransformMsg) for v in value):
            # agvviz's own /tf_static carries FrameTransforms; any other topic holding
            # transforms under the tf role is time-varying.
            self.add_transforms(value, static=role != ROLE_TF, message=message)
            return True
        if isinstance(value, PoseMsg) and role == ROLE_TRUTH:
            self.truth.add(message.time_ns, value.T)
            self.truth_frames.add(value.frame_id)
            return True
        if isinstance(value, PoseMsg) and role == ROLE_ODOMETRY:
            self.odometry.add(message.time_ns, value.T)
            return True
        if role == ROLE_MARKER_MAP and isinstance(value, dict):
            self.marker_map = value
            return True
        return False

    # -- queries ------------------------------------------------------------------------------
    def calibration_at(self, cam_name: str, t_ns: int) -> CalibrationMsg | None:
        side = self.side_calibrations.get(cam_name)
        if side is not None:
            return side
        entries = self.calibrations.get(cam_name)
        if not entries:
            return None
        i = bisect.bisect_right(entries, t_ns, key=lambda e: e[0])
        return entries[max(i - 1, 0)][1]

    def extrinsic(self, cam_name: str, frame_id: str, t_ns: int) -> tuple[np.ndarray | None, np.ndarray | None, str]:
        """``(T_body_cam, T_world_cam, why_not)``: one of the two poses, or both ``None`` and
        the reason."""
        side = self.side_extrinsics.get(cam_name)
        if side is not None:
            return side, None, ""
        frames = [f for f in dict.fromkeys((frame_id, camera_frame(cam_name))) if f]
        for name in frames:
            T = self.tf.lookup(self.body_frame, name, t_ns, hold=self._held_links(cam_name, name))
            if T is not None:
                return T, None, ""
        for name in frames:
            if self.tf.links(self.body_frame, name) is not None:
                continue  # rides on the body (a time-varying link without a pose at t_ns)
            for world in dict.fromkeys((self.world_frame, *sorted(self.truth_frames))):
                if world == self.body_frame:
                    continue
                T = self.tf.lookup(world, name, t_ns)
                if T is not None:
                    return None, T, ""  # a camera fixed in the world
        known = sorted(self.tf.frames())
        for name in frames:
            links = self.tf.links(self.body_frame, name)
            if links is None:
                continue
            missing = [
                c for c in links if c in self.tf.dynamic and c not in self.tf.static and not self.tf.is_constant(c)
            ]
            described = ", ".join(
                f"{self.tf.dynamic[c][0]} → {c} ({self.tf.samples(c)} samples, "
                f"{(span[0] / 1e9):.3f}–{(span[1] / 1e9):.3f} s)"
                for c in missing[:3] if (span := self.tf.dynamic[c][1].span_ns) is not None
            )
            return None, None, (
                f"the camera extrinsic (transform chain from body frame {self.body_frame!r} to camera frame "
                f"{name!r}) has a time-varying link (/tf) that changes and has no pose within "
                f"{self.tf.max_gap_ns / 1e9:g} s of this frame: {described}; give the mount with "
                f"--extrinsic {cam_name}=x,y,z,qx,qy,qz,qw (or publish it on /tf_static)"
            )
        return None, None, (
            f"no transform chain from body frame {self.body_frame!r} (or world frame "
            f"{self.world_frame!r}) to camera frame {frames[0]!r}"
            + (f"; frames in the transforms: {', '.join(known[:12])}{' …' if len(known) > 12 else ''}" if known else "; the recording has no transforms")
            + f" (set --set body_frame=..., or give --extrinsic {cam_name}=x,y,z,qx,qy,qz,qw)"
        )

    def _held_links(self, cam_name: str, frame: str) -> set[str]:
        """Child frames of the body → ``frame`` chain whose /tf link is constant (one sample, or
        never changing): held static, each with a note."""
        links = self.tf.links(self.body_frame, frame) or []
        held = {c for c in links if c not in self.tf.static and self.tf.is_constant(c)}
        for child in set(links) - held:
            self.notes.pop(child, None)  # fed message by message: a link that has since changed
        for child in sorted(held):
            if child in self.notes:
                continue
            parent, series = self.tf.dynamic[child]
            n = len(series)
            how = (f"only once (stamp {series.span_ns[0] / 1e9:.3f} s)" if n == 1
                   else f"{n} times without ever changing")
            self.notes[child] = (
                f"camera {cam_name}: its extrinsic link {parent} → {child} is published on /tf (time-varying) "
                f"{how}, not on /tf_static: treated as static, valid at every frame (publish it on /tf_static "
                f"or give --extrinsic {cam_name}=x,y,z,qx,qy,qz,qw to state the mount)"
            )
        return held

    def truth_at(self, t_ns: int) -> np.ndarray | None:
        return self.truth.at(t_ns, self.truth_max_gap_ns, self.truth_max_dt_ns)

    def odometry_at(self, t_ns: int) -> np.ndarray | None:
        return self.odometry.at(t_ns, ODOMETRY_MAX_GAP_NS, ODOMETRY_MAX_GAP_NS)

    def effective_marker_map(self) -> dict | None:
        return self.side_marker_map if self.side_marker_map is not None else self.marker_map
