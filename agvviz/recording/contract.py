"""Check a recording against the recording contract (DESIGN §4) in one streaming pass.

:func:`inspect_recording` summarises topics, cameras, static transforms and the scenario, and
lists *violations* (the file is readable but breaks the contract) separately from *damage*
(parts of the file could not be read). :func:`format_report` renders it for the CLI.

The checks a replay must apply too live here, so ``inspect`` and ``run`` agree on what is
wrong with a recording:

* :func:`frame_problem` — an image's format, emptiness, size bound (read cheaply from the
  JPEG/PNG header) and size against its camera's calibration;
* :class:`TimeChecks` — image time stamps that repeat or go backwards per camera, a recording
  whose images all share one time stamp or whose messages all sit at log time 0, and ground
  truth that does not overlap the images in time;
* :func:`payload_map_problem` — a QR payload's world coordinates against the recording's own
  marker map (``/markers/map``).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.geometry import PinholeCamera
from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg, PoseMsg
from agvviz.recording.formats import by_name, decode
from agvviz.recording.mcap_stream import parse_scenario_metadata
from agvviz.recording.raw import MessageDecodeError, RawMetadata, ReadReport
from agvviz.recording.values import MAX_IMAGE_SIDE_PX, image_size_problem
from agvviz.recording.schemas import SCENARIO_METADATA, SCHEMAS
from agvviz.model.topics import (
    CAMERA_TOPIC_RE,
    CORNERS_TOPIC,
    GROUND_TRUTH_TOPIC,
    MARKER_MAP_TOPIC,
    ODOMETRY_TOPIC,
    TF_STATIC_TOPIC,
    UWB_ANCHORS_TOPIC,
    UWB_RANGE_TOPIC,
    ROLE_MARKER_MAP,
    ROLE_TF_STATIC,
    ROLE_TRUTH,
    camera_calibration_topic,
    camera_of_role,
)
from agvviz.model.frames import (  # the frame rejection reasons of the checks below
    REJECT_CALIBRATION_SIZE,
    REJECT_IMAGE,
    REJECT_MAP_MISMATCH,
    REJECT_TIME,
)

#: Image formats of the recording contract (``foxglove.CompressedImage.format``).
IMAGE_FORMATS = ("jpeg", "png")

#: A QR payload vertex may differ from the marker map's corner of the same id by this much (m).
#: Both come from one survey: the payload rounds to 0.1 mm, so honest pairs agree to 0.05 mm;
#: 10 mm is 200× that, yet below the ≈6–21 mm position accuracy of a single-code pose at the
#: design geometry (DESIGN §8), so a disagreement that passes cannot move a pose by more than
#: the pose's own uncertainty.
PAYLOAD_MAP_TOLERANCE_M = 0.010
#: A code whose id the map does not list is accepted only within this many times the map's
#: largest nearest-neighbour spacing (at least 1 m) of a mapped code: on the surveyed floor or
#: one grid step beside it (a map that misses a code), never kilometres away.
UNMAPPED_CODE_SPACINGS = 2.0


def image_header_size(data: bytes, image_format: str) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG IHDR or a JPEG SOF marker, without decoding; ``None``
    when the header cannot be read (then the data is no image: :func:`frame_problem` rejects it)."""
    try:
        if image_format == "png":
            if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
                return struct.unpack(">II", data[16:24])
            return None
        if image_format == "jpeg":
            if data[:2] != b"\xff\xd8":
                return None
            at = 2
            while at + 4 <= len(data):
                if data[at] != 0xFF:
                    return None
                marker = data[at + 1]
                if marker == 0xFF:  # fill byte
                    at += 1
                    continue
                if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
                    at += 2
                    continue
                (length,) = struct.unpack(">H", data[at + 2 : at + 4])
                if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                    height, width = struct.unpack(">HH", data[at + 5 : at + 9])
                    return width, height
                if marker == 0xDA or length < 2:  # start of scan before any frame header
                    return None
                at += 2 + length
    except struct.error:
        return None
    return None


def frame_problem(
    image_format: str, data: bytes, camera: PinholeCamera | None, size: tuple[int, int] | None = None
) -> tuple[str, str] | None:
    """Why a recorded camera frame cannot be used, as ``(reason, detail)``, or ``None``.

    ``size`` is the frame's ``(width, height)`` when already known (a decoded image); otherwise
    it is read from the JPEG/PNG header (no decoding). Checks, in order: empty frame, format
    outside :data:`IMAGE_FORMATS`, a side outside 1..:data:`MAX_IMAGE_SIDE_PX` px, and a size
    that differs from ``camera``'s calibration (when given). Shared by ``inspect`` and ``run``.
    """
    if len(data) == 0:
        return REJECT_IMAGE, f"{image_format or 'image'} frame is empty (0 bytes)"
    if image_format not in IMAGE_FORMATS:
        return REJECT_IMAGE, (
            f"image format {image_format!r} is not in the recording contract "
            f"({' or '.join(IMAGE_FORMATS)})"
        )
    if size is None:
        size = image_header_size(data, image_format)
    if size is None:
        return REJECT_IMAGE, (
            f"{image_format} frame has no readable {image_format.upper()} header "
            f"({len(data)} bytes starting {data[:4].hex()}): not an image, or damaged"
        )
    width, height = (int(v) for v in size)
    problem = image_size_problem(width, height)
    if problem:
        return REJECT_IMAGE, f"{image_format} frame: {problem}"
    if camera is not None and (width, height) != (camera.width_px, camera.height_px):
        return REJECT_CALIBRATION_SIZE, (
            f"the image is {width}x{height} px but its calibration is for "
            f"{camera.width_px}x{camera.height_px} px; the intrinsics do not apply to it"
        )
    return None


def _span(first_ns: int, last_ns: int) -> str:
    """``start 2023-11-14 22:13:20.000 UTC, duration 1 min 12.4 s`` (a stamp before 2001 is
    taken as time since the start of a simulation or bag clock: ``start 0.000 s``)."""
    seconds = (last_ns - first_ns) / 1e9
    minutes, rest_s = divmod(abs(seconds), 60.0)
    hours, minutes = divmod(int(minutes), 60)
    sign = "-" if seconds < 0 else ""
    if hours:
        duration = f"{sign}{hours} h {minutes:02d} min {rest_s:04.1f} s"
    elif minutes:
        duration = f"{sign}{minutes} min {rest_s:.1f} s"
    else:
        duration = f"{seconds:.3f} s"
    return f"start {_format_ns(first_ns)}, duration {duration}"


class TimeChecks:
    """Time-stamp checks shared by ``inspect`` and ``run``: feed every message with
    :meth:`message` (images return their per-frame verdict), then read :meth:`problems`."""

    def __init__(self):
        self._last_image: dict[str, int] = {}
        self._images: dict[str, list[int]] = {}  # topic -> [count, not increasing, first, last]
        self._truth: list[int] | None = None  # [first, last]
        self._messages = 0
        self._nonzero = False

    def message(self, topic: str, log_time_ns: int, is_image: bool, is_truth: bool | None = None) -> str | None:
        """Record one message; for an image, why its time stamp cannot be used, or ``None``.

        An image whose log time is not after the previous image of the same topic (repeated
        or reversed time stamps) cannot be matched to ground truth or odometry: a replay
        rejects it (:data:`REJECT_TIME`).
        """
        self._messages += 1
        self._nonzero = self._nonzero or log_time_ns != 0
        if is_truth or (is_truth is None and topic == GROUND_TRUTH_TOPIC):
            if self._truth is None:
                self._truth = [log_time_ns, log_time_ns]
            self._truth = [min(self._truth[0], log_time_ns), max(self._truth[1], log_time_ns)]
        if not is_image:
            return None
        stats = self._images.setdefault(topic, [0, 0, log_time_ns, log_time_ns])
        stats[0] += 1
        stats[2], stats[3] = min(stats[2], log_time_ns), max(stats[3], log_time_ns)
        last = self._last_image.get(topic)
        if last is not None and log_time_ns <= last:
            stats[1] += 1
            self._last_image[topic] = max(last, log_time_ns)
            what = "repeats" if log_time_ns == last else "goes back from"
            return (
                f"log time {log_time_ns} ns {what} the previous image's {last} ns on {topic}: "
                "time stamps must increase per camera"
            )
        self._last_image[topic] = log_time_ns
        return None

    def truth_vs_images(self) -> tuple[tuple[int, int], tuple[int, int]] | None:
        """((first, last) truth log time, (first, last) image log time) in ns, or ``None`` when
        no truth or no image has been seen."""
        if self._truth is None or not self._images:
            return None
        first = min(v[2] for v in self._images.values())
        last = max(v[3] for v in self._images.values())
        return (self._truth[0], self._truth[1]), (first, last)

    def problems(self, truth_max_dt_ns: int = 0) -> list[str]:
        """Recording-level problems found so far (one line each)."""
        lines = []
        if self._messages > 1 and not self._nonzero:
            lines.append(
                f"every message ({self._messages}) has log time 0: the recording has no time "
                "stamps, so frames cannot be told apart in time nor matched to ground truth"
            )
        for topic, (count, bad, first, last) in sorted(self._images.items()):
            if count > 1 and first == last and self._nonzero:
                lines.append(
                    f"{topic}: all {count} images share one log time ({first} ns): "
                    f"{count - 1} of them cannot be placed in time"
                )
            elif bad:
                lines.append(
                    f"{topic}: {bad} of {count} images have a log time not after the previous "
                    "image's (time stamps repeated or reversed); they cannot be placed in time"
                )
        if self._truth is not None and self._images:
            first = min(v[2] for v in self._images.values())
            last = max(v[3] for v in self._images.values())
            t0, t1 = self._truth
            if t1 < first - truth_max_dt_ns or t0 > last + truth_max_dt_ns:
                lines.append(
                    f"ground truth ({GROUND_TRUTH_TOPIC}, {_span(t0, t1)}) does not overlap the "
                    f"images ({_span(first, last)}) in time: no frame can be scored against truth"
                )
        return lines


class QrMap(dict):
    """World corners (4, 3) per id of a QR marker map (a dict, built once and not changed), with
    a k-d tree of the codes' centres built on first use: the nearest mapped code to a point and
    each code's nearest neighbour cost O(log n) and O(n log n) in memory O(n), whatever the map
    size (a 200 000-code map: no n × n array)."""

    _tree = None

    def centre_tree(self):
        """``scipy.spatial.cKDTree`` of the codes' centres (the mean of their 4 corners)."""
        if self._tree is None:
            self._tree = _centre_tree(self)
        return self._tree


def _centre_tree(qr_map: dict):
    from scipy.spatial import cKDTree

    centres = np.array([np.asarray(c, dtype=float).mean(axis=0) for c in qr_map.values()]).reshape(-1, 3)
    return cKDTree(centres)


def _tree_of(qr_map: dict):
    return qr_map.centre_tree() if isinstance(qr_map, QrMap) else _centre_tree(qr_map)


def qr_map_of(marker_map: dict) -> QrMap:
    """World corners (4, 3) per id of a QR ``agvviz.MarkerMap`` (dictionary ``"qr"``); empty
    for ArUco maps and for markers mounted on the vehicle."""
    out = QrMap()
    if not isinstance(marker_map, dict) or marker_map.get("dictionary") != "qr":
        return out
    for entry in marker_map.get("markers", []):
        if entry.get("frame", "world") != "world":
            continue
        corners = np.asarray(entry.get("corners_world_m"), dtype=float)
        if corners.shape == (4, 3) and np.all(np.isfinite(corners)):
            out[str(entry.get("id"))] = corners
    return out


def unmapped_tolerance_m(qr_map: dict[str, np.ndarray]) -> float:
    """How far from the nearest mapped code a code the map does not list may be (m):
    :data:`UNMAPPED_CODE_SPACINGS` × the largest nearest-neighbour distance between mapped
    codes' centres, at least 1 m. Nearest neighbours come from a k-d tree (memory O(n))."""
    spacing = 0.0
    if len(qr_map) > 1:
        tree = _tree_of(qr_map)
        distances, _ = tree.query(tree.data, k=2)  # itself, then its nearest
        spacing = float(distances[:, 1].max())
    return max(1.0, UNMAPPED_CODE_SPACINGS * spacing)


def payload_map_problem(
    marker_id: str, points_world_m: np.ndarray, qr_map: dict[str, np.ndarray], unmapped_tol_m: float | None = None
) -> str | None:
    """Why a QR payload (its id and world points; the first four are the vertices) disagrees
    with the recording's marker map, or ``None``. No map, no check."""
    if not qr_map:
        return None
    vertices = np.asarray(points_world_m, dtype=float)[:4]
    mapped = qr_map.get(marker_id)
    if mapped is not None:
        error = float(np.max(np.linalg.norm(vertices - mapped, axis=1)))
        if error > PAYLOAD_MAP_TOLERANCE_M:
            return (
                f"code {marker_id}: payload vertices are up to {error * 1000:.1f} mm from the marker "
                f"map's corners of that id (tolerance {PAYLOAD_MAP_TOLERANCE_M * 1000:g} mm)"
            )
        return None
    tol = unmapped_tolerance_m(qr_map) if unmapped_tol_m is None else unmapped_tol_m
    centre = vertices.mean(axis=0)
    nearest = float(_tree_of(qr_map).query(centre, k=1)[0])
    if nearest > tol:
        return (
            f"code {marker_id} is not in the marker map and its payload puts it {nearest:.1f} m "
            f"from the nearest mapped code (at most {tol:.1f} m accepted)"
        )
    return None

_CAMERA_TOPIC = CAMERA_TOPIC_RE

#: Fixed topics of the contract → (accepted schema names, message encoding).
_FIXED_TOPICS = {
    TF_STATIC_TOPIC: (("foxglove.FrameTransforms",), "protobuf"),
    GROUND_TRUTH_TOPIC: (("foxglove.PoseInFrame",), "protobuf"),
    ODOMETRY_TOPIC: (("foxglove.PoseInFrame",), "protobuf"),
    UWB_RANGE_TOPIC: (("agvviz.UwbRange",), "json"),
    UWB_ANCHORS_TOPIC: (("agvviz.UwbAnchors",), "json"),
    MARKER_MAP_TOPIC: (("agvviz.MarkerMap",), "json"),
    CORNERS_TOPIC: (("agvviz.CornerObservations",), "json"),
}
_CAMERA_TOPICS = {
    "image": (("foxglove.CompressedImage", "foxglove.RawImage"), "protobuf"),
    "calibration": (("foxglove.CameraCalibration",), "protobuf"),
}
#: Most examples quoted per violation kind (the count is always given).
_MAX_EXAMPLES = 1


@dataclass
class TopicSummary:
    """One topic: its schema and encoding, message count and log-time span (ns)."""

    topic: str
    schema_name: str
    encoding: str
    count: int
    first_ns: int
    last_ns: int


@dataclass
class InspectReport:
    """Everything :func:`inspect_recording` found. ``ok`` when no violation and no damage."""

    path: Path
    topics: list[TopicSummary] = field(default_factory=list)
    start_ns: int | None = None
    end_ns: int | None = None
    cameras: dict[str, CalibrationMsg] = field(default_factory=dict)
    transforms: list[FrameTransformMsg] = field(default_factory=list)
    scenario: dict | None = None
    violations: list[str] = field(default_factory=list)
    damage: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # worth knowing, not a violation
    native: bool = True  # an agvviz recording (the contract's naming applies)
    kind: str = "mcap"  # the format's NAME (agvviz.recording.formats): "mcap" | "rosbag2" | "rosbag1"
    files: list[str] = field(default_factory=list)
    bag_message_count: int | None = None  # rosbag2 metadata.yaml
    bag_topic_counts: dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.violations and not self.damage


def _expected_channel(topic: str) -> tuple[tuple[str, ...], str] | None:
    """(accepted schema names, encoding) the contract fixes for ``topic``, or ``None``."""
    if topic in _FIXED_TOPICS:
        return _FIXED_TOPICS[topic]
    match = _CAMERA_TOPIC.match(topic)
    return _CAMERA_TOPICS[match.group(2)] if match else None


class _Tally:
    """Counts repeated per-message violations so each kind is reported once with a count."""

    def __init__(self):
        self._entries: dict[str, list] = {}

    def add(self, key: str, example: str) -> None:
        entry = self._entries.setdefault(key, [0, []])
        entry[0] += 1
        if len(entry[1]) < _MAX_EXAMPLES:
            entry[1].append(example)

    def lines(self) -> list[str]:
        return [
            f"{key} ({count} message{'s' if count != 1 else ''}; e.g. {'; '.join(examples)})"
            for key, (count, examples) in self._entries.items()
        ]


def inspect_recording(path, roles=None, time_source: str = "auto") -> InspectReport:
    """Summarise ``path`` (an ``.mcap`` or a rosbag2 directory) and check it (one streaming
    pass): against the recording contract for agvviz's own recordings; for other files
    (ROS 2 bags, Foxglove SDK files) the contract's naming does not apply — their topics are
    read through the role map ``roles`` (:class:`agvviz.recording.roles.RoleMap`, inferred
    when not given) and a missing ``agvviz.scenario`` record is a note. Image time checks use
    the time a run uses (``time_source``: ``header`` stamps or ``log`` times; ``auto`` as a run).

    Raises :class:`agvviz.errors.RecordingError` when the path is missing or not a
    recording.
    """
    from agvviz.recording.source import open_recording, resolve_roles, scan

    recording = open_recording(path)
    if roles is None:
        roles = resolve_roles(scan(recording, ReadReport()))
    role_of = roles.role_of()
    native = recording.native
    header_time = recording.time_source(time_source) == "header"
    report = InspectReport(
        path=Path(path), native=native, kind=recording.kind, files=[f.name for f in recording.files],
        bag_message_count=recording.bag_message_count, bag_topic_counts=dict(recording.bag_topic_counts),
    )
    read = ReadReport()
    summaries: dict[str, TopicSummary] = {}
    channel_checked: set[tuple[str, str, str]] = set()
    tally = _Tally()
    image_cameras: set[str] = set()
    transforms: dict[tuple[str, str], FrameTransformMsg] = {}
    scenario_seen = False
    time_checks = TimeChecks()

    for item in recording.iter_raw(read):
        if isinstance(item, RawMetadata):
            if item.name == SCENARIO_METADATA:
                scenario_seen = True
                try:
                    report.scenario = parse_scenario_metadata(item.values)
                except ValueError as exc:
                    report.violations.append(
                        f"metadata: {exc}; expected string values name, seed, "
                        "options (JSON object), agvviz_version"
                    )
            continue
        topic, t_ns = item.topic, item.log_time_ns
        role = role_of.get(topic, "")
        cam_role = camera_of_role(role)
        is_image = cam_role is not None and cam_role[1] == "image"
        # images: reported by time_checks.problems(); with header time, checked once decoded
        checked_time = False
        if not (header_time and role):
            time_checks.message(topic, t_ns, is_image, is_truth=role == ROLE_TRUTH)
            checked_time = True
        summary = summaries.get(topic)
        if summary is None:
            summary = TopicSummary(topic, item.schema_name, item.message_encoding, 0, t_ns, t_ns)
            summaries[topic] = summary
        elif t_ns < summary.last_ns and not is_image:
            tally.add(
                f"{topic}: log time goes backwards; expected non-decreasing log times per topic",
                f"{t_ns} ns after {summary.last_ns} ns",
            )
        summary.count += 1
        summary.last_ns = max(summary.last_ns, t_ns)
        summary.first_ns = min(summary.first_ns, t_ns)

        channel_key = (topic, item.schema_name, item.message_encoding)
        if channel_key not in channel_checked:
            channel_checked.add(channel_key)
            if native:
                report.violations += _channel_violations(topic, item.schema_name, item.message_encoding)
        if not role and not native:
            continue  # a topic the replay does not use: listed, not decoded

        try:
            value = decode(item)
        except MessageDecodeError as exc:
            schema = item.schema_name or item.message_encoding
            tally.add(f"{topic}: payload does not match {schema}", f"at {t_ns} ns: {exc}")
            if not checked_time:
                time_checks.message(topic, t_ns, is_image, is_truth=role == ROLE_TRUTH)
            continue
        if not checked_time:
            stamp = getattr(value, "stamp_ns", 0) or (
                value[0].stamp_ns if isinstance(value, list) and value and isinstance(value[0], FrameTransformMsg) else 0
            )
            time_checks.message(topic, stamp or t_ns, is_image, is_truth=role == ROLE_TRUTH)
        if isinstance(value, CompressedFrame) and is_image:
            cam_name = cam_role[0]
            image_cameras.add(cam_name)
            if native and value.frame_id != camera_frame(cam_name):
                expected = camera_frame(cam_name)
                tally.add(f"{topic}: image frame_id is not {expected!r}", f"got {value.frame_id!r}")
            calibration = report.cameras.get(cam_name)
            problem = frame_problem(value.image_format, value.data, calibration.camera if calibration else None)
            if problem is not None:
                reason, detail = problem
                tally.add(f"{topic}: frames a replay rejects as {reason}", f"at {t_ns} ns: {detail}")
        elif isinstance(value, CalibrationMsg) and cam_role is not None and cam_role[1] == "calibration":
            cam_name = cam_role[0]
            if native and value.frame_id != camera_frame(cam_name):
                expected = camera_frame(cam_name)
                tally.add(f"{topic}: calibration frame_id is not {expected!r}", f"got {value.frame_id!r}")
            report.cameras[cam_name] = value
        elif role == ROLE_TF_STATIC and isinstance(value, list):
            for tf in value:
                transforms[(tf.parent_frame, tf.child_frame)] = tf
        elif role == ROLE_TRUTH and isinstance(value, PoseMsg) and value.frame_id != WORLD_FRAME and native:
            tally.add(f"{topic}: frame_id is not {WORLD_FRAME!r}", f"got {value.frame_id!r}")
        elif role == ROLE_MARKER_MAP and isinstance(value, dict):
            for problem in _marker_map_payload_problems(value):
                tally.add(f"{topic}: a code's payload disagrees with its map entry", problem)

    report.topics = sorted(summaries.values(), key=lambda s: s.topic)
    if summaries:
        report.start_ns = min(s.first_ns for s in summaries.values())
        report.end_ns = max(s.last_ns for s in summaries.values())
    report.transforms = list(transforms.values())
    report.violations += tally.lines()
    report.violations += time_checks.problems()
    for cam_name in sorted(image_cameras) if native else []:
        if cam_name not in report.cameras:
            report.violations.append(
                f"camera {cam_name}: images but no valid calibration; expected "
                f"{camera_calibration_topic(cam_name)} (foxglove.CameraCalibration)"
            )
        if not any((parent, camera_frame(cam_name)) in transforms for parent in (AGV_FRAME, WORLD_FRAME)):
            report.violations.append(
                f"camera {cam_name}: no /tf_static transform {AGV_FRAME} -> {camera_frame(cam_name)} "
                f"or {WORLD_FRAME} -> {camera_frame(cam_name)}; expected the camera's mounting pose "
                "T_agv_cam (on the AGV) or T_world_cam (fixed in the world)"
            )
    if not scenario_seen and native:
        report.violations.append(
            f"metadata: no {SCENARIO_METADATA!r} record; expected the scenario name, seed, "
            "options and agvviz version (written by RecordingWriter)"
        )
    elif not scenario_seen:
        report.notes.append(
            f"no {SCENARIO_METADATA!r} metadata: not an agvviz recording (written by "
            f"{recording.library or 'an unnamed writer'}{', profile ' + recording.profile if recording.profile else ''}); "
            "its topics are read through the role map below"
        )
    if recording.bag_message_count is not None:
        read_total = sum(s.count for s in summaries.values())
        mismatched = [
            f"{t}: metadata.yaml {n}, read {summaries[t].count if t in summaries else 0}"
            for t, n in sorted(recording.bag_topic_counts.items())
            if (summaries[t].count if t in summaries else 0) != n
        ]
        if read_total != recording.bag_message_count or mismatched:
            report.damage.append(
                f"metadata.yaml counts {recording.bag_message_count} messages, the files hold {read_total}"
                + (f" ({'; '.join(mismatched[:5])})" if mismatched else "")
            )
    report.damage += list(read.problems)
    return report


def _marker_map_payload_problems(marker_map: dict) -> list[str]:
    """Map entries whose ``payload`` (the text printed on the code) disagrees with the entry's
    own id or corners, by the replay's rule (:func:`payload_map_problem`)."""
    from agvviz.markers.payload import PayloadError, parse_payload

    qr_map = qr_map_of(marker_map)
    problems = []
    for entry in marker_map.get("markers", []) if qr_map else []:
        text, marker_id = entry.get("payload"), str(entry.get("id"))
        if not isinstance(text, str) or marker_id not in qr_map:
            continue
        try:
            payload = parse_payload(text)
        except PayloadError as exc:
            problems.append(f"code {marker_id}: payload refused: {exc}")
            continue
        if payload.marker_id != marker_id:
            problems.append(f"map entry {marker_id} carries the payload of code {payload.marker_id}")
            continue
        problem = payload_map_problem(marker_id, payload.points_world_m, {marker_id: qr_map[marker_id]})
        if problem:
            problems.append(problem)
    return problems


def _channel_violations(topic: str, schema_name: str, encoding: str) -> list[str]:
    """Schema/encoding violations of one channel."""
    expected = _expected_channel(topic)
    if expected is not None:
        names, expected_encoding = expected
        if schema_name not in names or encoding != expected_encoding:
            return [
                f"{topic}: schema {schema_name or '(none)'} with {encoding or '(no)'} encoding; "
                f"expected {' or '.join(names)} with {expected_encoding} encoding"
            ]
        return []
    if schema_name.startswith("agvviz.") and schema_name not in SCHEMAS:
        return [f"{topic}: unknown schema {schema_name}; expected one of {', '.join(SCHEMAS)}"]
    if encoding == "json" and not schema_name.startswith(("agvviz.", "foxglove.")):
        return [
            f"{topic}: JSON channel with schema {schema_name or '(none)'}; "
            "expected a JSON Schema named agvviz.*"
        ]
    return []


def _format_ns(t_ns: int | None, start_ns: int | None = None) -> str:
    """A time stamp for people: ``+72.400 s`` after ``start_ns`` when given; else a UTC date and
    time (``2023-11-14 22:13:20.000 UTC``) for stamps from 2001 on, seconds (``3.900 s``) for
    earlier ones (a simulation or bag clock from zero); ``-`` for none."""
    import datetime

    if t_ns is None:
        return "-"
    if start_ns is not None:
        return f"{'+' if t_ns >= start_ns else '-'}{abs(t_ns - start_ns) / 1e9:.3f} s"
    if t_ns < 978_307_200 * 10**9:  # 2001-01-01 UTC
        return f"{t_ns / 1e9:.3f} s"
    seconds, nanos = divmod(t_ns, 10**9)
    when = datetime.datetime.fromtimestamp(seconds, tz=datetime.timezone.utc)
    return f"{when:%Y-%m-%d %H:%M:%S}.{nanos // 10**6:03d} UTC"


def format_report(report: InspectReport) -> str:
    """Plain multi-line text: topics, cameras, transforms, scenario, then the verdict."""
    lines = [f"recording: {report.path}" + by_name(report.kind).describe(report.files)]
    if report.bag_message_count is not None:
        lines.append(f"metadata.yaml: {report.bag_message_count} messages in {len(report.bag_topic_counts)} topic(s)")
    span = _span(report.start_ns, report.end_ns) if report.start_ns is not None else "no messages"
    lines.append(f"time span: {span}")
    lines.append("")
    header = ("topic", "schema", "count", "first", "last")
    rows = [
        (
            s.topic,
            f"{s.schema_name or '(none)'} [{s.encoding}]",
            str(s.count),
            _format_ns(s.first_ns, report.start_ns),
            _format_ns(s.last_ns, report.start_ns),
        )
        for s in report.topics
    ]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
    lines.append("")
    lines.append("cameras:" if report.cameras else "cameras: none")
    for cam_name, calib in sorted(report.cameras.items()):
        cam = calib.camera
        K = cam.K
        lines.append(
            f"  {cam_name} ({calib.frame_id}): {cam.width_px}x{cam.height_px} px, "
            f"fx={K[0, 0]:.3f} fy={K[1, 1]:.3f} cx={K[0, 2]:.3f} cy={K[1, 2]:.3f} skew={K[0, 1]:.3g}, "
            f"D[{calib.distortion_model or 'none'}]=[{', '.join(f'{d:.6g}' for d in cam.dist)}]"
        )
    lines.append("transforms (tf_static):" if report.transforms else "transforms (tf_static): none")
    for tf in report.transforms:
        t = tf.T_parent_child[:3, 3]
        lines.append(f"  {tf.parent_frame} -> {tf.child_frame}: t = [{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m")
    if report.scenario is None:
        lines.append("scenario: none")
    else:
        s = report.scenario
        lines.append(
            f"scenario: {s['name']} seed={s['seed']} agvviz {s['agvviz_version']} "
            f"options={s['options']}"
        )
    lines.append("")
    for note in report.notes:
        lines.append(f"note: {note}")
    for problem in report.damage:
        lines.append(f"damage: {problem}")
    for violation in report.violations:
        lines.append(f"violation: {violation}")
    if report.ok and not report.native:
        lines.append("contract: OK (read as a third-party file: agvviz's topic naming does not apply)")
    elif report.ok:
        lines.append("contract: OK")
    else:
        lines.append(
            f"contract: {len(report.violations)} violation(s), "
            f"{len(report.damage)} damage problem(s)"
        )
    return "\n".join(lines)
