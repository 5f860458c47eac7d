"""A decoded ROS message (ROS 1 or ROS 2, from ``rosbags`` or ``mcap_ros2``) → agvviz's values,
for the ROS formats (:mod:`agvviz.recording.formats.ros2`, :mod:`agvviz.recording.formats.ros1`):

========================================  ==================================================
ROS type (ROS 2 form)                     value
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

Other types stay ``bytes`` (they are listed by ``inspect`` and ignored by a run). Every value
carries the header stamp in ``stamp_ns``. Frame ids lose a leading ``/`` (ROS 1 style). ROS
optical frames are OpenCV's camera convention already (REP 103, :mod:`agvviz.conventions`).
The values are the ones the Foxglove decoders give (:mod:`agvviz.recording.formats.mcap`).
"""

from __future__ import annotations

from agvviz.model.messages import CompressedFrame, FrameTransformMsg, PoseMsg
from agvviz.recording.images import compressed_format
from agvviz.recording.raw import MessageDecodeError
from agvviz.recording.values import cam_name, calibration, matrix_from_pose, raw_frame

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


def frame_id(name: str) -> str:
    """A ROS frame id without the ROS 1 leading ``/``."""
    return name[1:] if name.startswith("/") else name


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
    T = matrix_from_pose(tf.transform.translation, tf.transform.rotation, f"transform {parent}->{child}")
    return FrameTransformMsg(parent, child, T, _stamp(tf.header))


def _pose(header, pose, child: str = "") -> PoseMsg:
    return PoseMsg(frame_id(header.frame_id), matrix_from_pose(pose.position, pose.orientation, "pose"),
                   _stamp(header), frame_id(child))


def ros_value(name: str, msg, topic: str) -> object:
    """The value (see the module table) of a decoded ROS message of type ``name`` (ROS 2 form,
    ``pkg/msg/Type``) on ``topic``: a ROS 2 message (``mcap_ros2`` or ``rosbags``) or a ROS 1
    one (``rosbags``, :mod:`agvviz.recording.formats.ros1`; upper-case ``K``/``D``, ``tf/tfMessage``)."""
    if name == COMPRESSED_IMAGE:
        fid = frame_id(msg.header.frame_id)
        return CompressedFrame(cam_name(topic, fid), fid, compressed_format(msg.format), bytes(msg.data),
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
