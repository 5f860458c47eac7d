"""Write agvviz recordings (MCAP, DESIGN §4).

Foxglove messages are protobuf-encoded (schemas registered with
``mcap_protobuf.schema.register_schema``), custom messages JSON-encoded with the ``agvviz.*``
JSON Schemas of :mod:`agvviz.recording.schemas`, side by side on one plain ``mcap`` Writer.

Chunks: 1 MiB, **uncompressed**, each with its CRC. Recordings are dominated by JPEG/PNG
frames, which compression does not shrink; uncompressed chunks cost no CPU on write or read,
keep damage local (a flipped byte spoils one chunk, found by its CRC, never a decompressor
failure) and every MCAP reader opens them. A 1 MiB chunk holds a few 1280×1024 JPEG frames,
so one damaged chunk loses only those.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema

import agvviz
from agvviz.model import topics
from agvviz.conventions import camera_frame
from agvviz.geometry import PinholeCamera, se3
from agvviz.recording.schemas import SCENARIO_METADATA, SCHEMAS, validate_payload

#: Maximum uncompressed chunk size in bytes (see the module docstring).
CHUNK_SIZE_BYTES = 1024 * 1024
#: Image formats accepted by :meth:`RecordingWriter.write_image`.
IMAGE_FORMATS = ("jpeg", "png")


def _to_json_value(value):
    """``json.dumps`` hook: numpy arrays and scalars become plain lists and numbers."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def _dumps(value) -> str:
    return json.dumps(value, allow_nan=False, separators=(",", ":"), default=_to_json_value)


def _set_time(stamp, log_time_ns: int) -> None:
    stamp.seconds, stamp.nanos = divmod(int(log_time_ns), 1_000_000_000)


def _check_cam_name(cam_name: str) -> None:
    if not isinstance(cam_name, str) or not cam_name or any(c in cam_name for c in "/ \t\n"):
        raise ValueError(f"camera name {cam_name!r} must be a non-empty string without '/' or spaces")


def _check_rigid(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if not se3.is_rigid(T):
        raise ValueError(f"{what} must be a finite 4x4 rigid transform, got {T.tolist()}")
    return T


class RecordingWriter:
    """Context manager writing one recording atomically.

    The file is written to a temporary file in the destination folder and moved onto ``path``
    with ``os.replace`` when the ``with`` block exits cleanly; on an exception the temporary
    file is deleted and ``path`` is left untouched. Messages must be written in
    non-decreasing log time per topic (``ValueError`` otherwise).

    Parameters
    ----------
    path : str or Path
        Destination ``.mcap`` file. Never the input of anything that reads while this writes.
    scenario : dict
        ``{"name": str, "seed": int, "options": dict}``; stored as the MCAP metadata record
        ``agvviz.scenario`` with string values ``name``, ``seed``, ``options`` (JSON) and
        ``agvviz_version``.
    """

    def __init__(self, path, *, scenario: dict):
        self.path = Path(path)
        missing = {"name", "seed", "options"} - set(scenario)
        if missing:
            raise ValueError(f"scenario is missing {sorted(missing)}; expected keys name, seed, options")
        if not isinstance(scenario["options"], dict):
            raise ValueError(f"scenario options must be a dict, got {type(scenario['options']).__name__}")
        self._scenario = {
            "name": str(scenario["name"]),
            "seed": str(int(scenario["seed"])),
            "options": _dumps(scenario["options"]),
            "agvviz_version": agvviz.__version__,
        }
        self._file = None
        self._tmp_path: Path | None = None
        self._writer: Writer | None = None
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str, str]] = {}  # topic -> (id, schema, encoding)
        self._last_time_ns: dict[str, int] = {}
        self._sequence: dict[str, int] = {}

    # -- context manager ------------------------------------------------------------------
    def __enter__(self) -> "RecordingWriter":
        from agvviz.recording import outputs

        folder = self.path.parent
        if not folder.is_dir():
            raise outputs.OutputError(f"cannot write {self.path}: folder {folder} does not exist; create it first")
        # agvviz's temporary name (pid inside): removed when interrupted, or by the next
        # command writing here if this process is killed; created with the usual permissions.
        self._tmp_path = outputs.temp_path(self.path)
        outputs.register_temp(self._tmp_path)
        try:
            handle = os.open(self._tmp_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except OSError as exc:
            outputs.release_temp(self._tmp_path)
            self._tmp_path = None
            raise outputs.output_error(exc, self.path) from exc
        self._file = os.fdopen(handle, "wb")
        try:
            self._writer = Writer(
                self._file, chunk_size=CHUNK_SIZE_BYTES, compression=CompressionType.NONE,
                enable_data_crcs=True,  # DataEnd CRC: the reader then catches damaged metadata
            )
            self._writer.start(profile="", library=f"agvviz {agvviz.__version__}")
            self._writer.add_metadata(SCENARIO_METADATA, self._scenario)
        except BaseException:
            self._discard()
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self._discard()
            return
        from agvviz.recording import outputs

        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())  # a full disk shows here at the latest, not after the rename
            self._file.close()
            outputs.publish(self._tmp_path, self.path)
        except OSError as exc:
            self._discard()
            raise outputs.output_error(exc, self.path) from exc
        except BaseException:
            self._discard()
            raise

    def _discard(self) -> None:
        from agvviz.recording import outputs

        if self._file is not None and not self._file.closed:
            try:
                self._file.close()
            except OSError:  # e.g. the disk is full: the buffered rest cannot be written
                pass
        if self._tmp_path is not None:
            self._tmp_path.unlink(missing_ok=True)
            outputs.release_temp(self._tmp_path)

    # -- channels -------------------------------------------------------------------------
    def _schema_id(self, name: str, register) -> int:
        if self._writer is None:
            raise RuntimeError("RecordingWriter must be used as a context manager (with ... as w)")
        if name not in self._schema_ids:
            self._schema_ids[name] = register()
        return self._schema_ids[name]

    def _channel(self, topic: str, schema_name: str, encoding: str, schema_id: int) -> int:
        if topic not in self._channels:
            channel_id = self._writer.register_channel(topic, encoding, schema_id)
            self._channels[topic] = (channel_id, schema_name, encoding)
        channel_id, known_schema, known_encoding = self._channels[topic]
        if (known_schema, known_encoding) != (schema_name, encoding):
            raise ValueError(
                f"topic {topic} already carries {known_schema} ({known_encoding}); "
                f"cannot also write {schema_name} ({encoding}) on it"
            )
        return channel_id

    def _add(self, topic: str, channel_id: int, data: bytes, log_time_ns: int) -> None:
        log_time_ns = int(log_time_ns)
        if log_time_ns < 0:
            raise ValueError(f"{topic}: log time must be >= 0 ns, got {log_time_ns}")
        last = self._last_time_ns.get(topic)
        if last is not None and log_time_ns < last:
            raise ValueError(
                f"{topic}: log time {log_time_ns} ns is before the previous message's {last} ns; "
                "write messages in non-decreasing log time per topic"
            )
        self._last_time_ns[topic] = log_time_ns
        sequence = self._sequence.get(topic, 0)
        self._sequence[topic] = sequence + 1
        self._writer.add_message(
            channel_id, log_time=log_time_ns, data=data, publish_time=log_time_ns, sequence=sequence
        )

    def _write_protobuf(self, topic: str, message, log_time_ns: int) -> None:
        cls = type(message)
        name = cls.DESCRIPTOR.full_name
        schema_id = self._schema_id(name, lambda: register_schema(self._writer, cls))
        channel_id = self._channel(topic, name, "protobuf", schema_id)
        self._add(topic, channel_id, message.SerializeToString(), log_time_ns)

    # -- messages -------------------------------------------------------------------------
    def write_calibration(self, cam_name: str, camera: PinholeCamera, log_time_ns: int) -> None:
        """``/cam/<name>/calibration`` (foxglove.CameraCalibration, plumb_bob, frame ``cam_<name>``).

        Writes K (3×3 row-major), D (k1, k2, p1, p2, k3), R = identity and P = [K | 0].
        """
        _check_cam_name(cam_name)
        if camera.width_px <= 0 or camera.height_px <= 0:
            raise ValueError(
                f"camera {cam_name}: image size {camera.width_px}x{camera.height_px} px; "
                "a recorded calibration needs width_px and height_px > 0"
            )
        msg = CameraCalibration(
            frame_id=camera_frame(cam_name),
            width=int(camera.width_px),
            height=int(camera.height_px),
            distortion_model="plumb_bob",
            D=[float(v) for v in camera.dist],
            K=[float(v) for v in camera.K.ravel()],
            R=[float(v) for v in np.eye(3).ravel()],
            P=[float(v) for v in np.hstack([camera.K, np.zeros((3, 1))]).ravel()],
        )
        _set_time(msg.timestamp, log_time_ns)
        self._write_protobuf(topics.camera_calibration_topic(cam_name), msg, log_time_ns)

    def write_tf_static(self, transforms: list[tuple[str, str, np.ndarray]], log_time_ns: int) -> None:
        """``/tf_static`` (foxglove.FrameTransforms): ``(parent, child, T_parent_child 4×4)`` each."""
        msg = FrameTransforms()
        for parent, child, T_parent_child in transforms:
            T = _check_rigid(T_parent_child, f"transform {parent}->{child}")
            if not parent or not child:
                raise ValueError(f"transform frames must be non-empty, got {parent!r} -> {child!r}")
            tf = msg.transforms.add(parent_frame_id=parent, child_frame_id=child)
            _set_time(tf.timestamp, log_time_ns)
            tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in T[:3, 3])
            q = se3.to_quaternion_xyzw(T)
            tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = (float(v) for v in q)
        self._write_protobuf(topics.TF_STATIC_TOPIC, msg, log_time_ns)

    def write_image(self, cam_name: str, data: bytes, image_format: str, log_time_ns: int) -> None:
        """``/cam/<name>/image`` (foxglove.CompressedImage, frame ``cam_<name>``), bytes as given."""
        _check_cam_name(cam_name)
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image format {image_format!r} not supported; use one of {IMAGE_FORMATS}")
        msg = CompressedImage(frame_id=camera_frame(cam_name), data=bytes(data), format=image_format)
        _set_time(msg.timestamp, log_time_ns)
        self._write_protobuf(topics.camera_image_topic(cam_name), msg, log_time_ns)

    def write_pose(self, topic: str, T_frame_agv: np.ndarray, frame_id: str, log_time_ns: int) -> None:
        """A foxglove.PoseInFrame: the AGV's pose ``T_frame_agv`` (4×4) in frame ``frame_id``
        (``/agv/ground_truth`` in ``world``, ``/agv/odometry`` in ``odom``)."""
        T = _check_rigid(T_frame_agv, f"{topic} pose")
        if not frame_id:
            raise ValueError(f"{topic}: frame_id must be non-empty")
        msg = PoseInFrame(frame_id=frame_id)
        _set_time(msg.timestamp, log_time_ns)
        p, q = msg.pose.position, msg.pose.orientation
        p.x, p.y, p.z = (float(v) for v in T[:3, 3])
        q.x, q.y, q.z, q.w = (float(v) for v in se3.to_quaternion_xyzw(T))
        self._write_protobuf(topic, msg, log_time_ns)

    def write_json(self, topic: str, schema_name: str, payload: dict, log_time_ns: int) -> None:
        """A JSON-encoded message of custom schema ``schema_name`` (an ``agvviz.*`` name of
        :data:`agvviz.recording.schemas.SCHEMAS`). The payload is validated first; numpy
        arrays and scalars are converted to lists and numbers."""
        if schema_name not in SCHEMAS:
            raise ValueError(f"unknown schema {schema_name!r} for {topic}; known: {', '.join(SCHEMAS)}")
        try:
            text = _dumps(payload)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{topic}: payload is not JSON-serializable ({exc})") from None
        problems = validate_payload(schema_name, json.loads(text))
        if problems:
            raise ValueError(f"{topic}: payload does not match {schema_name}: " + "; ".join(problems))
        schema_id = self._schema_id(
            schema_name,
            lambda: self._writer.register_schema(
                schema_name, "jsonschema", json.dumps(SCHEMAS[schema_name]).encode()
            ),
        )
        channel_id = self._channel(topic, schema_name, "json", schema_id)
        self._add(topic, channel_id, text.encode(), log_time_ns)

    def write_metadata(self, name: str, values: dict[str, str]) -> None:
        """An MCAP metadata record ``name`` (string keys and values), e.g.
        :data:`agvviz.recording.schemas.REALISM_METADATA`; not ``agvviz.scenario`` (written
        by the constructor)."""
        if self._writer is None:
            raise RuntimeError("RecordingWriter must be used as a context manager (with ... as w)")
        if not name or name == SCENARIO_METADATA:
            raise ValueError(f"metadata name {name!r} is empty or reserved")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in values.items()):
            raise ValueError(f"metadata {name}: keys and values must be strings")
        self._writer.add_metadata(name, dict(values))

    def write_marker_map(self, marker_map: dict, log_time_ns: int) -> None:
        """``/markers/map`` (agvviz.MarkerMap, see :data:`agvviz.recording.schemas.MARKER_MAP`)."""
        self.write_json(topics.MARKER_MAP_TOPIC, "agvviz.MarkerMap", marker_map, log_time_ns)
