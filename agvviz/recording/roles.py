"""The role map: which topic of a recording plays which role for the replay.

agvviz's own recordings use the names of :mod:`agvviz.model.topics`. For any other file
(a ROS 2 bag, a Foxglove SDK file) the map is *inferred* from each topic's schema, name and
frame id (:func:`infer_roles`), printed by ``agvviz inspect``, and can be overridden with
``--topic ROLE=TOPIC`` or a roles file (``inspect --write-roles FILE`` writes one; ``--roles
FILE`` reads it). Every topic that could not be placed is listed with the reason.

Inference rules:

* **cameras** — one camera per image topic (``foxglove.CompressedImage|RawImage``,
  ``sensor_msgs/msg/CompressedImage|Image``). The camera is named after the topic's
  namespace without the image-transport words (``/front/image_raw/compressed`` → ``front``,
  ``/camera/color/image_raw`` → ``camera_color``); ``/cam/<name>/image`` → ``<name>``.
  Two image topics of one camera (same namespace and frame id, e.g. ``image_raw`` and
  ``image_raw/compressed``) give one camera: the uncompressed stream is kept (lossless). Depth
  images are not camera frames.
* **calibration** — a ``CameraInfo`` / ``foxglove.CameraCalibration`` topic is paired with the
  camera whose image topic lies in the same namespace (longest match), else with the camera
  whose frames carry the same frame id.
* **truth / odometry** — pose topics (``PoseStamped``, ``PoseWithCovarianceStamped``,
  ``nav_msgs/msg/Odometry``, ``foxglove.PoseInFrame``): a name saying ground truth
  (``ground_truth``, ``groundtruth``, ``truth``, ``gt``, ``vicon``, ``mocap``, ``optitrack``,
  ``qualisys``) → truth; a name saying ``odom`` or the type ``Odometry`` → odometry. Several
  candidates for one role are all left unplaced, with the choice to make.
* **transforms** — ``/tf_static`` and ``/tf`` (TF messages or Foxglove FrameTransform(s)).
* **markers, UWB, corners** — the ``agvviz.*`` JSON schemas.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from agvviz.errors import InputError
from agvviz.model.topics import (
    CAMERA_TOPIC_RE,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    NATIVE_TOPICS,
    ROLE_CORNERS,
    ROLE_MARKER_MAP,
    ROLE_ODOMETRY,
    ROLE_TF,
    ROLE_TF_STATIC,
    ROLE_TRUTH,
    ROLE_UWB_ANCHORS,
    ROLE_UWB_RANGE,
    calibration_role,
    camera_of_role,
    image_role,
    role_help,
    valid_role,
)

COMPRESSED_IMAGE_TYPES = ("foxglove.CompressedImage", "sensor_msgs/msg/CompressedImage")
RAW_IMAGE_TYPES = ("foxglove.RawImage", "sensor_msgs/msg/Image")
IMAGE_TYPES = COMPRESSED_IMAGE_TYPES + RAW_IMAGE_TYPES
CALIBRATION_TYPES = ("foxglove.CameraCalibration", "sensor_msgs/msg/CameraInfo")
TRANSFORM_TYPES = (
    "foxglove.FrameTransforms", "foxglove.FrameTransform",
    "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped",
    "tf/msg/tfMessage",  # ROS 1's original tf
)
POSE_TYPES = (
    "foxglove.PoseInFrame", "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry",
)
_JSON_ROLES = {
    "agvviz.MarkerMap": ROLE_MARKER_MAP,
    "agvviz.UwbRange": ROLE_UWB_RANGE,
    "agvviz.UwbAnchors": ROLE_UWB_ANCHORS,
    "agvviz.CornerObservations": ROLE_CORNERS,
}
#: Schema names each role accepts.
#: A motion-capture bridge may publish truth as a TransformStamped (vicon_bridge does).
TRUTH_TYPES = POSE_TYPES + ("geometry_msgs/msg/TransformStamped",)
ROLE_TYPES = {
    ROLE_TRUTH: TRUTH_TYPES,
    ROLE_ODOMETRY: POSE_TYPES,
    ROLE_TF_STATIC: TRANSFORM_TYPES,
    ROLE_TF: TRANSFORM_TYPES,
    **{role: (schema,) for schema, role in _JSON_ROLES.items()},
}
_TRUTH_WORDS = {"ground_truth", "groundtruth", "truth", "gt", "vicon", "mocap", "optitrack", "qualisys"}
_TRANSPORT_WORDS = {
    "image", "image_raw", "image_rect", "image_rect_color", "image_color", "image_mono",
    "image_rect_raw", "image_rect_mono", "raw", "compressed", "rect", "color_raw", "theora",
}
_NAME_CHARS = re.compile(r"[^A-Za-z0-9_-]+")


@dataclass
class TopicInfo:
    """What role inference knows about one topic: schema, count and the first message's
    frame id (``""`` when it has none or did not decode)."""

    topic: str
    schema_name: str
    encoding: str
    count: int = 0
    frame_id: str = ""
    child_frame: str = ""


@dataclass
class RoleMap:
    """``roles``: role → topic; ``unplaced``: topic → why it plays no role; ``origin``:
    role → how it was chosen (``inferred``, ``--topic``, ``roles file``, ``agvviz naming``)."""

    roles: dict[str, str] = field(default_factory=dict)
    unplaced: dict[str, str] = field(default_factory=dict)
    origin: dict[str, str] = field(default_factory=dict)

    def role_of(self) -> dict[str, str]:
        """topic → role."""
        return {topic: role for role, topic in self.roles.items()}

    def cameras(self) -> list[str]:
        """Names of the cameras that have an image role."""
        return sorted(c[0] for role in self.roles if (c := camera_of_role(role)) and c[1] == "image")

    def image_topics(self) -> set[str]:
        return {topic for role, topic in self.roles.items() if (c := camera_of_role(role)) and c[1] == "image"}

    def lines(self) -> list[str]:
        """The map as text, one line per role then one per unplaced topic."""
        out = [f"  {role:<22} {topic}   ({self.origin.get(role, 'inferred')})" for role, topic in sorted(self.roles.items())]
        out += [f"  (unplaced) {topic}: {why}" for topic, why in sorted(self.unplaced.items())]
        return out

    def to_yaml(self) -> str:
        """A roles file (``--roles FILE``): YAML ``roles: {role: topic}``, unplaced topics as
        comments."""
        import yaml

        text = "# agvviz roles file: role -> topic (agvviz run --roles FILE); edit freely\n"
        text += yaml.safe_dump({"roles": dict(sorted(self.roles.items()))}, sort_keys=False)
        for topic, why in sorted(self.unplaced.items()):
            text += f"# unplaced {topic}: {why}\n"
        return text


def read_roles_file(path) -> dict[str, str]:
    """role → topic from a roles file (YAML ``roles: {role: topic}``). Raises InputError."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"--roles {path}: cannot read ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise InputError(f"--roles {path}: not YAML ({exc})") from None
    roles = data.get("roles") if isinstance(data, dict) else None
    if not isinstance(roles, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in roles.items()):
        raise InputError(f"--roles {path}: expected a mapping 'roles: {{ROLE: TOPIC, ...}}' of strings")
    return dict(roles)


def parse_topic_options(pairs: list[str]) -> dict[str, str]:
    """role → topic from ``--topic ROLE=TOPIC`` options. Raises InputError."""
    out = {}
    for pair in pairs:
        role, sep, topic = pair.partition("=")
        role, topic = role.strip(), topic.strip()
        if not sep or not role or not topic:
            raise InputError(f"--topic {pair!r}: expected ROLE=TOPIC, e.g. truth=/vicon/agv/pose")
        if not valid_role(role):
            raise InputError(f"--topic {pair!r}: unknown role {role!r}; roles: {role_help()}")
        out[role] = topic
    return out


def _segments(topic: str) -> list[str]:
    return [s for s in topic.split("/") if s]


def _namespace(topic: str) -> str:
    return "/" + "/".join(_segments(topic)[:-1])


def camera_name_for(topic: str, frame_id: str = "") -> str:
    """The camera name an image topic gets (see the module rules)."""
    match = CAMERA_TOPIC_RE.match(topic)
    if match:
        return match.group(1)
    words = [s for s in _segments(topic) if s.lower() not in _TRANSPORT_WORDS]
    name = _NAME_CHARS.sub("_", "_".join(words)).strip("_")
    if not name:
        name = _NAME_CHARS.sub("_", frame_id).strip("_") or "camera"
    return name[:64]


def _is_depth(topic: str) -> bool:
    return any("depth" in s.lower() for s in _segments(topic))


def _words(topic: str) -> set[str]:
    out = set()
    for s in _segments(topic):
        s = s.lower()
        out.add(s)
        out.update(w for w in re.split(r"[^a-z0-9]+", s) if w)
    return out


def _check_fixed(fixed: dict[str, str], topics: dict[str, TopicInfo], source: str) -> None:
    for role, topic in fixed.items():
        if topic not in topics:
            raise InputError(
                f"{source} {role}={topic}: the recording has no topic {topic!r}; its topics: "
                + ", ".join(sorted(topics))
            )
        schema = topics[topic].schema_name
        cam = camera_of_role(role)
        accepted = (IMAGE_TYPES if cam[1] == "image" else CALIBRATION_TYPES) if cam else ROLE_TYPES.get(role, ())
        if schema not in accepted:
            raise InputError(
                f"{source} {role}={topic}: {topic} carries {schema or '(no schema)'}, but {role} needs "
                + " or ".join(accepted)
            )
    by_topic: dict[str, str] = {}
    for role, topic in fixed.items():
        if topic in by_topic:
            raise InputError(f"{source}: topic {topic} is given two roles, {by_topic[topic]} and {role}")
        by_topic[topic] = role


def infer_roles(
    topics: dict[str, TopicInfo],
    fixed: dict[str, str] | None = None,
    fixed_origin: str = "--topic",
    infer: bool = True,
) -> RoleMap:
    """The role map of a recording with ``topics``; ``fixed`` roles (from ``--topic`` or a
    roles file) are taken as given (checked: the topic exists and its type fits the role)
    and the rest inferred (unless ``infer`` is False). Raises InputError for a bad fixed role."""
    fixed = dict(fixed or {})
    _check_fixed(fixed, topics, fixed_origin)
    result = RoleMap()
    for role, topic in fixed.items():
        result.roles[role] = topic
        result.origin[role] = fixed_origin
    taken = set(fixed.values())
    if not infer:
        for topic in topics:
            if topic not in taken:
                result.unplaced[topic] = "not in the roles file"
        return result
    free = [t for t in sorted(topics) if t not in taken]

    def place(role: str, topic: str, origin: str = "inferred") -> bool:
        if role in result.roles:
            result.unplaced[topic] = f"{role} is already {result.roles[role]}"
            return False
        result.roles[role] = topic
        result.origin[role] = origin
        taken.add(topic)
        return True

    # agvviz's own names first.
    for topic in free:
        info = topics[topic]
        match = CAMERA_TOPIC_RE.match(topic)
        if match and info.schema_name in (IMAGE_TYPES if match.group(2) == "image" else CALIBRATION_TYPES):
            cam = match.group(1)
            place(image_role(cam) if match.group(2) == "image" else calibration_role(cam), topic, "agvviz naming")
            continue
        for role, native in NATIVE_TOPICS.items():
            if native == topic and info.schema_name in ROLE_TYPES.get(role, ()):
                # /tf and /tf_static are ROS's names as much as agvviz's
                place(role, topic, "inferred" if role in (ROLE_TF, ROLE_TF_STATIC) else "agvviz naming")
    free = [t for t in free if t not in taken]

    # Cameras: one per image topic.
    cam_topics: dict[str, str] = {  # cam -> image topic (fixed ones included)
        c[0]: t for r, t in result.roles.items() if (c := camera_of_role(r)) and c[1] == "image"
    }
    image_free = [t for t in free if topics[t].schema_name in IMAGE_TYPES]
    # Uncompressed streams first, so that they win over their compressed twins.
    image_free.sort(key=lambda t: (topics[t].schema_name not in RAW_IMAGE_TYPES, t))
    for topic in image_free:
        info = topics[topic]
        if _is_depth(topic):
            result.unplaced[topic] = "a depth image, not a camera frame"
            continue
        name = camera_name_for(topic, info.frame_id)
        twin = next(
            (
                other for cam, other in cam_topics.items()
                if camera_name_for(other, topics[other].frame_id) == name
                and topics[other].frame_id == info.frame_id
            ),
            None,
        )
        if twin is not None:
            result.unplaced[topic] = (
                f"the same camera as {twin} (same namespace and frame id {info.frame_id!r}); that "
                f"stream is used — choose this one with --topic {name}.image={topic}"
            )
            continue
        base, k = name, 2
        while image_role(name) in result.roles:
            name, k = f"{base}_{k}", k + 1
        place(image_role(name), topic)
        cam_topics[name] = topic
    free = [t for t in free if t not in taken and t not in result.unplaced]

    # Calibrations: by namespace, then by frame id.
    for topic in [t for t in free if topics[t].schema_name in CALIBRATION_TYPES]:
        info = topics[topic]
        ns = _namespace(topic)
        candidates = [
            (len(ns), cam) for cam, img in cam_topics.items()
            if calibration_role(cam) not in result.roles and (img + "/").startswith(ns.rstrip("/") + "/") and ns != "/"
        ]
        how = f"namespace {ns}"
        if not candidates and info.frame_id:
            candidates = [
                (0, cam) for cam, img in cam_topics.items()
                if calibration_role(cam) not in result.roles and topics[img].frame_id == info.frame_id
            ]
            how = f"frame id {info.frame_id!r}"
        if len(candidates) > 1 and info.frame_id:  # several in the namespace: the frame id decides
            same = [c for c in candidates if topics[cam_topics[c[1]]].frame_id == info.frame_id]
            candidates = same or candidates
        if len(candidates) == 1:
            cam = candidates[0][1]
            place(calibration_role(cam), topic, f"inferred: {how}")
        elif candidates:
            result.unplaced[topic] = (
                f"could belong to cameras {', '.join(c for _, c in candidates)} ({how}); "
                f"choose with --topic CAM.calibration={topic}"
            )
        else:
            result.unplaced[topic] = (
                f"no camera image topic in its namespace {ns} or with its frame id {info.frame_id!r}; "
                f"pair it with --topic CAM.calibration={topic}"
            )
    free = [t for t in free if t not in taken and t not in result.unplaced]

    # Transforms.
    for topic in [t for t in free if topics[t].schema_name in TRANSFORM_TYPES]:
        if topics[topic].schema_name == "geometry_msgs/msg/TransformStamped" and _words(topic) & _TRUTH_WORDS:
            continue  # a motion-capture pose: placed with the poses below
        if topic in (TF_STATIC_TOPIC, "tf_static"):
            place(ROLE_TF_STATIC, topic)
        elif topic in (TF_TOPIC, "tf"):
            place(ROLE_TF, topic)
        elif "static" in topic.lower() and ROLE_TF_STATIC not in result.roles:
            place(ROLE_TF_STATIC, topic)
        else:
            result.unplaced[topic] = (
                "a transform topic other than /tf and /tf_static; use it with --topic tf=TOPIC "
                "or --topic tf_static=TOPIC"
            )
    free = [t for t in free if t not in taken and t not in result.unplaced]

    # Poses: truth and odometry.
    poses = [t for t in free if topics[t].schema_name in TRUTH_TYPES]
    truth = [t for t in poses if _words(t) & _TRUTH_WORDS]
    odom = [
        t for t in poses if t not in truth
        and ("odom" in t.lower() or topics[t].schema_name == "nav_msgs/msg/Odometry")
    ]
    for role, candidates in ((ROLE_TRUTH, truth), (ROLE_ODOMETRY, odom)):
        if role in result.roles:
            for t in candidates:
                result.unplaced[t] = f"{role} is already {result.roles[role]}"
        elif len(candidates) == 1:
            place(role, candidates[0])
        else:
            for t in candidates:
                result.unplaced[t] = (
                    f"one of {len(candidates)} candidates for {role} ({', '.join(candidates)}); "
                    f"choose with --topic {role}={t}"
                )
    for t in poses:
        if t not in taken and t not in result.unplaced:
            result.unplaced[t] = (
                "a pose topic whose name says neither ground truth (ground_truth, truth, gt, vicon, "
                f"mocap, optitrack) nor odometry; use it with --topic truth={t} or --topic odometry={t}"
            )
    free = [t for t in free if t not in taken and t not in result.unplaced]

    # agvviz JSON channels under other names.
    for topic in free:
        role = _JSON_ROLES.get(topics[topic].schema_name)
        if role is not None:
            place(role, topic)
        elif topic not in result.unplaced:
            schema = topics[topic].schema_name or "(no schema)"
            result.unplaced[topic] = f"type {schema} is not used by the replay"
    return result
