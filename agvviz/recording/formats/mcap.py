"""The MCAP format: an ``.mcap`` file (agvviz's own recordings, Foxglove SDK files, a single
rosbag2 split file), read by the salvaging stream of :mod:`agvviz.recording.mcap_stream`.

Decoding: Foxglove protobuf messages of the recording contract become the values of
:mod:`agvviz.model.messages`, JSON channels become ``dict`` (``agvviz.*`` payloads checked
against their schema). The messages of other encodings an MCAP file may carry (ROS 2 CDR,
ROS 1) are decoded by their own formats (:func:`agvviz.recording.formats.decode`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg, PoseMsg
from agvviz.recording.images import compressed_format
from agvviz.recording.mcap_stream import iter_raw, read_file_header  # noqa: F401 — iter_raw is this format's
from agvviz.recording.raw import MessageDecodeError, RawMessage, Recording
from agvviz.recording.schemas import SCHEMAS, validate_payload
from agvviz.recording.values import calibration, cam_name, matrix_from_pose, raw_frame

#: The recording kind this format reads (:attr:`agvviz.recording.raw.Recording.kind`).
NAME = "mcap"


def recognises(path: Path) -> bool:
    """Any file the ROS 1 format did not take (one that is not MCAP is refused when opened)."""
    return not path.is_dir()


def open_recording(path: Path) -> Recording:
    """The recording of one ``.mcap`` file, with its writer's header and scenario record."""
    recording = Recording(path, [path], sys.modules[__name__])
    recording.profile, recording.library, recording.scenario = read_file_header(path)
    return recording


def describe(files: list[str]) -> str:
    """What ``inspect`` adds after the path: nothing for a single file."""
    return ""


def _stamp_ns(timestamp) -> int:
    """Nanoseconds of a ``google.protobuf.Timestamp`` (0 when unset)."""
    return int(timestamp.seconds) * 1_000_000_000 + int(timestamp.nanos)


def _decode_compressed_image(raw: RawMessage) -> CompressedFrame:
    msg = CompressedImage.FromString(raw.data)
    return CompressedFrame(
        cam_name(raw.topic, msg.frame_id), msg.frame_id, compressed_format(msg.format), msg.data,
        stamp_ns=_stamp_ns(msg.timestamp),
    )


def _decode_raw_image(raw: RawMessage) -> CompressedFrame:
    msg = RawImage.FromString(raw.data)
    return raw_frame(raw.topic, msg.frame_id, msg.encoding, msg.width, msg.height, msg.step, msg.data,
                     _stamp_ns(msg.timestamp))


def _decode_calibration(raw: RawMessage) -> CalibrationMsg:
    msg = CameraCalibration.FromString(raw.data)
    return calibration(raw.topic, msg.frame_id, msg.K, msg.D, msg.distortion_model, msg.width, msg.height,
                       _stamp_ns(msg.timestamp))


def _transform(tf: FrameTransform) -> FrameTransformMsg:
    what = f"transform {tf.parent_frame_id}->{tf.child_frame_id}"
    T = matrix_from_pose(tf.translation, tf.rotation, what)
    return FrameTransformMsg(tf.parent_frame_id, tf.child_frame_id, T, _stamp_ns(tf.timestamp))


def _decode_frame_transforms(raw: RawMessage) -> list[FrameTransformMsg]:
    return [_transform(tf) for tf in FrameTransforms.FromString(raw.data).transforms]


def _decode_frame_transform(raw: RawMessage) -> list[FrameTransformMsg]:
    return [_transform(FrameTransform.FromString(raw.data))]


def _decode_pose(raw: RawMessage) -> PoseMsg:
    msg = PoseInFrame.FromString(raw.data)
    return PoseMsg(msg.frame_id, matrix_from_pose(msg.pose.position, msg.pose.orientation, "pose"),
                   stamp_ns=_stamp_ns(msg.timestamp))


_PROTOBUF_DECODERS = {
    "foxglove.CompressedImage": _decode_compressed_image,
    "foxglove.RawImage": _decode_raw_image,
    "foxglove.CameraCalibration": _decode_calibration,
    "foxglove.FrameTransforms": _decode_frame_transforms,
    "foxglove.FrameTransform": _decode_frame_transform,
    "foxglove.PoseInFrame": _decode_pose,
}


def decodes(raw: RawMessage) -> bool:
    """True for the messages this format decodes: Foxglove protobuf schemas and JSON."""
    return (raw.message_encoding == "protobuf" and raw.schema_name in _PROTOBUF_DECODERS) or (
        raw.message_encoding == "json"
    )


def decode(raw: RawMessage) -> object:
    """The value of a Foxglove protobuf or JSON message; raises :class:`MessageDecodeError`
    (or a parser's damage error, which :func:`agvviz.recording.formats.decode` turns into one)."""
    if raw.message_encoding == "protobuf":
        return _PROTOBUF_DECODERS[raw.schema_name](raw)
    value = json.loads(raw.data)
    if raw.schema_name in SCHEMAS:
        problems = validate_payload(raw.schema_name, value)
        if problems:
            raise MessageDecodeError("; ".join(problems[:3]) + ("; ..." if len(problems) > 3 else ""))
    return value
