"""ROS 2 messages (CDR) → agvviz's decoded values, through ``mcap-ros2-support``.

The CDR bytes are decoded by ``mcap_ros2``'s dynamic decoder, built from the ``ros2msg``
schema text the file itself carries (every rosbag2 MCAP file embeds its message definitions),
so no message layout is hand-written here. The decoded messages become the same values the
Foxglove decoders give (:mod:`agvviz.recording.reader`):

========================================  ==================================================
ROS 2 type                                value
========================================  ==================================================
sensor_msgs/msg/CompressedImage           :class:`CompressedFrame` (format → jpeg / png)
sensor_msgs/msg/Image                     :class:`CompressedFrame` (lossless PNG, see
                                          :mod:`agvviz.recording.images`)
sensor_msgs/msg/CameraInfo                :class:`CalibrationMsg` (plumb_bob,
                                          rational_polynomial; equidistant is refused)
tf2_msgs/msg/TFMessage                    ``list[FrameTransformMsg]``
geometry_msgs/msg/TransformStamped        ``list[FrameTransformMsg]`` (one)
geometry_msgs/msg/PoseStamped             :class:`PoseMsg`
geometry_msgs/msg/PoseWithCovarianceStamped  :class:`PoseMsg` (covariance not used)
nav_msgs/msg/Odometry                     :class:`PoseMsg` (``child_frame`` = child_frame_id)
========================================  ==================================================

Other ROS 2 types stay ``bytes`` (they are listed by ``inspect`` and ignored by a run).
Every value carries the header stamp in ``stamp_ns``. Frame ids lose a leading ``/`` (ROS 1
style). ROS optical frames are OpenCV's camera convention already (REP 103,
:mod:`agvviz.conventions`).
"""

from __future__ import annotations

import hashlib

from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from agvviz.recording.images import compressed_format
from agvviz.recording.reader import (
    CalibrationMsg,
    CompressedFrame,
    FrameTransformMsg,
    MessageDecodeError,
    PoseMsg,
    RawMessage,
    _cam_name,
    _matrix_from_pose,
    calibration,
    raw_frame,
)

COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
#: The ROS 2 types this module decodes.
DECODED_TYPES = (
    COMPRESSED_IMAGE, IMAGE, CAMERA_INFO, TF_MESSAGE, TRANSFORM_STAMPED,
    POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY,
)
IMAGE_TYPES = (COMPRESSED_IMAGE, IMAGE)
POSE_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY)
TRANSFORM_TYPES = (TF_MESSAGE, TRANSFORM_STAMPED)

_factory = DecoderFactory()
_decoders: dict[tuple[str, str], object] = {}


def frame_id(name: str) -> str:
    """A ROS frame id without the ROS 1 leading ``/``."""
    return name[1:] if name.startswith("/") else name


def _decoder(raw: RawMessage):
    key = (raw.schema_name, hashlib.sha1(raw.schema_data).hexdigest())
    decoder = _decoders.get(key)
    if decoder is None:
        schema = Schema(id=len(_decoders) + 1, name=raw.schema_name, encoding="ros2msg", data=raw.schema_data)
        decoder = _factory.decoder_for("cdr", schema)
        if decoder is None:
            raise MessageDecodeError(f"no CDR decoder for {raw.schema_name}")
        _decoders[key] = decoder
    return decoder


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _transform(tf) -> FrameTransformMsg:
    parent, child = frame_id(tf.header.frame_id), frame_id(tf.child_frame_id)
    T = _matrix_from_pose(tf.transform.translation, tf.transform.rotation, f"transform {parent}->{child}")
    return FrameTransformMsg(parent, child, T, _stamp(tf.header))


def _pose(header, pose, child: str = "") -> PoseMsg:
    return PoseMsg(frame_id(header.frame_id), _matrix_from_pose(pose.position, pose.orientation, "pose"),
                   _stamp(header), frame_id(child))


def decode_ros2(raw: RawMessage) -> object:
    """The value of a CDR message (see the module table); ``bytes`` for other types.

    Raises :class:`MessageDecodeError` (or an exception of the reader's damage list, which
    :func:`agvviz.recording.reader.decode` turns into one) when the bytes do not decode.
    """
    name = raw.schema_name
    if name not in DECODED_TYPES:
        return raw.data
    msg = _decoder(raw)(raw.data)
    if name == COMPRESSED_IMAGE:
        fid = frame_id(msg.header.frame_id)
        return CompressedFrame(_cam_name(raw.topic, fid), fid, compressed_format(msg.format), bytes(msg.data),
                               stamp_ns=_stamp(msg.header))
    if name == IMAGE:
        return raw_frame(raw.topic, frame_id(msg.header.frame_id), msg.encoding, msg.width, msg.height,
                         msg.step, bytes(msg.data), _stamp(msg.header), bool(msg.is_bigendian))
    if name == CAMERA_INFO:
        return calibration(raw.topic, frame_id(msg.header.frame_id), msg.k, msg.d, msg.distortion_model,
                           msg.width, msg.height, _stamp(msg.header))
    if name == TF_MESSAGE:
        return [_transform(tf) for tf in msg.transforms]
    if name == TRANSFORM_STAMPED:
        return [_transform(msg)]
    if name == POSE_STAMPED:
        return _pose(msg.header, msg.pose)
    if name == POSE_WITH_COVARIANCE_STAMPED:
        return _pose(msg.header, msg.pose.pose)
    if name == ODOMETRY:
        return _pose(msg.header, msg.pose.pose, msg.child_frame_id)
    return raw.data  # pragma: no cover


__all__ = ["decode_ros2", "frame_id", "DECODED_TYPES", "CalibrationMsg"]
