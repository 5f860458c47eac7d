"""Decoded recording messages: the values every recording format's reader yields and the
replay's stages consume (a camera frame, a calibration, transforms, a pose), whatever file
they came from (:mod:`agvviz.recording.formats`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agvviz.geometry import PinholeCamera
from agvviz.model.topics import native_role


@dataclass(frozen=True)
class CompressedFrame:
    """One encoded camera frame; ``data`` is the recorded bytes, never re-encoded."""

    cam_name: str
    frame_id: str
    image_format: str  # "jpeg" | "png" (Foxglove CompressedImage.format, as recorded)
    data: bytes
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none
    source_encoding: str = ""  # for an uncompressed frame: its encoding (the PNG is lossless)


@dataclass(frozen=True)
class CalibrationMsg:
    """A camera's intrinsics; ``distortion_model`` is "plumb_bob", "rational_polynomial" (or
    "" when D is empty)."""

    cam_name: str
    frame_id: str
    camera: PinholeCamera
    distortion_model: str
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none


@dataclass(frozen=True)
class FrameTransformMsg:
    """``T_parent_child`` (4×4): the child frame's pose in the parent frame."""

    parent_frame: str
    child_frame: str
    T_parent_child: np.ndarray
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none


@dataclass(frozen=True)
class PoseMsg:
    """A pose ``T`` (4×4) in frame ``frame_id`` (for the AGV: ``T_<frame_id>_agv``);
    ``child_frame`` is the frame posed when the message names it (``nav_msgs/Odometry``)."""

    frame_id: str
    T: np.ndarray
    stamp_ns: int = field(default=0, compare=False)  # the message's own stamp (header), 0 when none
    child_frame: str = ""


@dataclass(frozen=True)
class RecordedMessage:
    """One decoded message.

    ``value`` is a :class:`CompressedFrame`, :class:`CalibrationMsg`,
    ``list[FrameTransformMsg]``, :class:`PoseMsg`, a JSON value (``dict`` for agvviz
    messages) or ``bytes`` for schemas the readers do not decode.

    ``role`` is what the message is for the replay (:mod:`agvviz.model.topics`); when not
    given it is the role of ``topic`` under agvviz's own naming. ``stamp_ns`` is the time the
    replay places the message at when it is not the log time (a header stamp, see
    :mod:`agvviz.recording.source`); :attr:`time_ns` is the one to use.
    """

    topic: str
    log_time_ns: int
    schema_name: str
    value: object
    role: str = ""
    stamp_ns: int | None = None

    def __post_init__(self):
        if not self.role:
            object.__setattr__(self, "role", native_role(self.topic))

    @property
    def time_ns(self) -> int:
        """The message's time on the replay's clock: ``stamp_ns`` when set, else the log time."""
        return self.log_time_ns if self.stamp_ns is None else self.stamp_ns
