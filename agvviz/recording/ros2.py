"""ROS 2 messages (CDR) → agvviz's decoded values, through ``mcap-ros2-support``.

The CDR bytes are decoded by ``mcap_ros2``'s dynamic decoder, built from the ``ros2msg``
schema text the file itself carries (every rosbag2 MCAP file embeds its message definitions),
so no message layout is hand-written here. A definition ``mcap_ros2`` refuses — a bag
converted from ROS 1 by ``rosbags-convert`` with its default type store keeps ROS 1's
upper-case ``CameraInfo`` fields ``K``, ``D``, ``R``, ``P`` and ``std_msgs/Header``'s ``seq``,
and ``mcap_ros2`` accepts lower-case field names only — is decoded by ``rosbags``' CDR
deserialiser built from the same text. The decoded messages (and ROS 1 ones,
:mod:`agvviz.recording.ros1`, through :func:`ros_value`) become the same values the Foxglove
decoders give (:mod:`agvviz.recording.reader`):

========================================  ==================================================
ROS 2 type                                value
========================================  ==================================================
sensor_msgs/msg/CompressedImage           :class:`CompressedFrame` (format → jpeg / png)
sensor_msgs/msg/Image                     :class:`CompressedFrame` (lossless PNG, see
                                          :mod:`agvviz.recording.images`)
sensor_msgs/msg/CameraInfo                :class:`CalibrationMsg` (plumb_bob,
                                          rational_polynomial; equidistant is refused)
tf2_msgs/msg/TFMessage                    ``list[FrameTransformMsg]`` (also ROS 1's
                                          ``tf/tfMessage``)
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

import contextlib
import hashlib
import io

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
TF1_MESSAGE = "tf/msg/tfMessage"  # ROS 1's original tf (before tf2), same layout
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
#: The ROS 2 types this module decodes.
DECODED_TYPES = (
    COMPRESSED_IMAGE, IMAGE, CAMERA_INFO, TF_MESSAGE, TF1_MESSAGE, TRANSFORM_STAMPED,
    POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY,
)
IMAGE_TYPES = (COMPRESSED_IMAGE, IMAGE)
POSE_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY)
TRANSFORM_TYPES = (TF_MESSAGE, TF1_MESSAGE, TRANSFORM_STAMPED)

_factory = DecoderFactory()
_decoders: dict[tuple[str, str], object] = {}


def frame_id(name: str) -> str:
    """A ROS frame id without the ROS 1 leading ``/``."""
    return name[1:] if name.startswith("/") else name


def _decoder(raw: RawMessage):
    """A decoder of ``raw``'s CDR bytes built from the schema text the file carries:
    ``mcap_ros2``'s, or — for a definition it refuses, such as the ROS 1 ``float64[9] K`` and
    ``float64[] D`` of a bag converted from ROS 1 with ``rosbags-convert``'s default (copied)
    type store: ``mcap_ros2`` allows lower-case field names only — ``rosbags``' CDR
    deserialiser built from the same text."""
    key = (raw.schema_name, hashlib.sha1(raw.schema_data).hexdigest())
    decoder = _decoders.get(key)
    if decoder is None:
        schema = Schema(id=len(_decoders) + 1, name=raw.schema_name, encoding="ros2msg", data=raw.schema_data)
        try:
            with contextlib.redirect_stderr(io.StringIO()):  # its parser prints the error too
                decoder = _factory.decoder_for("cdr", schema)
        except Exception as exc:  # mcap_ros2's parser raises NameError, ValueError, its own errors
            decoder = _rosbags_decoder(raw, exc)
        if decoder is None:
            decoder = MessageDecodeError(f"no CDR decoder for {raw.schema_name}")
        _decoders[key] = decoder
    if isinstance(decoder, MessageDecodeError):
        raise decoder
    return decoder


def _rosbags_decoder(raw: RawMessage, why: Exception):
    """``rosbags``' CDR deserialiser for ``raw``'s schema text, or a :class:`MessageDecodeError`
    saying why neither decoder can read it."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    try:
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(raw.schema_data.decode("utf-8"), raw.schema_name))
    except Exception as exc:
        return MessageDecodeError(
            f"the message definition of {raw.schema_name} does not parse (mcap_ros2: {why}; rosbags: {exc})"
        )
    name = raw.schema_name

    def decode(data: bytes):
        try:
            return store.deserialize_cdr(data, name)
        except Exception as exc:  # damaged bytes
            raise MessageDecodeError(f"payload does not decode as {name}: {type(exc).__name__}: {exc}") from None

    return decode


def _field(msg, name: str):
    """Field ``name`` of a decoded message, or its upper-case ROS 1 spelling (``CameraInfo``'s
    ``K``, ``D``: ROS 1 definitions, in a ROS 1 bag or a ROS 2 bag converted from one)."""
    try:
        return getattr(msg, name)
    except AttributeError:
        return getattr(msg, name.upper())


def _stamp(header) -> int:
    stamp = header.stamp
    nanos = stamp.nanosec if hasattr(stamp, "nanosec") else stamp.nsec
    return int(stamp.sec) * 1_000_000_000 + int(nanos)


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
    if raw.schema_name not in DECODED_TYPES:
        return raw.data
    return ros_value(raw.schema_name, _decoder(raw)(raw.data), raw.topic)


def ros_value(name: str, msg, topic: str) -> object:
    """The value (see the module table) of a decoded ROS message of type ``name`` (ROS 2 form,
    ``pkg/msg/Type``) on ``topic``: a ROS 2 message (``mcap_ros2`` or ``rosbags``) or a ROS 1
    one (``rosbags``, :mod:`agvviz.recording.ros1`; upper-case ``K``/``D``, ``tf/tfMessage``)."""
    if name == COMPRESSED_IMAGE:
        fid = frame_id(msg.header.frame_id)
        return CompressedFrame(_cam_name(topic, fid), fid, compressed_format(msg.format), bytes(msg.data),
                               stamp_ns=_stamp(msg.header))
    if name == IMAGE:
        return raw_frame(topic, frame_id(msg.header.frame_id), msg.encoding, msg.width, msg.height,
                         msg.step, bytes(msg.data), _stamp(msg.header), bool(msg.is_bigendian))
    if name == CAMERA_INFO:
        return calibration(topic, frame_id(msg.header.frame_id), _field(msg, "k"), _field(msg, "d"),
                           msg.distortion_model, msg.width, msg.height, _stamp(msg.header))
    if name in (TF_MESSAGE, TF1_MESSAGE):
        return [_transform(tf) for tf in msg.transforms]
    if name == TRANSFORM_STAMPED:
        return [_transform(msg)]
    if name == POSE_STAMPED:
        return _pose(msg.header, msg.pose)
    if name == POSE_WITH_COVARIANCE_STAMPED:
        return _pose(msg.header, msg.pose.pose)
    if name == ODOMETRY:
        return _pose(msg.header, msg.pose.pose, msg.child_frame_id)
    raise MessageDecodeError(f"{name} is not a type agvviz decodes")  # pragma: no cover


__all__ = ["decode_ros2", "ros_value", "frame_id", "DECODED_TYPES", "CalibrationMsg"]
