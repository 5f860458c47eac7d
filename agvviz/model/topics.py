"""Topic names and roles — the one place in agvviz that knows a topic's name.

The replay consumes **roles**, not topics (DESIGN §4 "Roles, not topics"). A role map (see
:mod:`agvviz.recording.roles`) says which topic of a file plays which role; every consumer
(``pipeline``, ``fusion_replay``, ``correction``, ``inspect``) dispatches on
:attr:`agvviz.model.messages.RecordedMessage.role`.

Roles and agvviz's own topic for each:

- ``<cam>.image`` — ``/cam/<cam>/image``: camera frames (one camera per image topic);
- ``<cam>.calibration`` — ``/cam/<cam>/calibration``: that camera's intrinsics;
- ``truth`` — ``/agv/ground_truth``: ground-truth pose of the body frame in the world;
- ``odometry`` — ``/agv/odometry``: drifting navigation / dead reckoning;
- ``markers`` — ``/markers/map``: the marker map (``agvviz.MarkerMap``);
- ``corners`` — ``/markers/corners``: corner observations without images;
- ``uwb.range`` — ``/uwb/range``: UWB two-way ranges;
- ``uwb.anchors`` — ``/uwb/anchors``: UWB anchor positions;
- ``tf_static`` — ``/tf_static``: fixed transforms (camera extrinsics, chains);
- ``tf`` — ``/tf``: time-varying transforms.
"""

from __future__ import annotations

import re

# -- agvviz's own topic names (the recording contract, DESIGN §4) --------------------------------
TF_STATIC_TOPIC = "/tf_static"
TF_TOPIC = "/tf"
GROUND_TRUTH_TOPIC = "/agv/ground_truth"
ODOMETRY_TOPIC = "/agv/odometry"
MARKER_MAP_TOPIC = "/markers/map"
CORNERS_TOPIC = "/markers/corners"
UWB_RANGE_TOPIC = "/uwb/range"
UWB_ANCHORS_TOPIC = "/uwb/anchors"
CAMERA_TOPIC_RE = re.compile(r"^/cam/([^/]+)/(image|calibration)$")


def camera_image_topic(cam_name: str) -> str:
    """agvviz's image topic of camera ``cam_name``."""
    return f"/cam/{cam_name}/image"


def camera_calibration_topic(cam_name: str) -> str:
    """agvviz's calibration topic of camera ``cam_name``."""
    return f"/cam/{cam_name}/calibration"


def is_camera_image_topic(topic: str) -> bool:
    match = CAMERA_TOPIC_RE.match(topic)
    return bool(match) and match.group(2) == "image"


# -- roles ----------------------------------------------------------------------------------------
ROLE_TRUTH = "truth"
ROLE_ODOMETRY = "odometry"
ROLE_MARKER_MAP = "markers"
ROLE_CORNERS = "corners"
ROLE_UWB_RANGE = "uwb.range"
ROLE_UWB_ANCHORS = "uwb.anchors"
ROLE_TF_STATIC = "tf_static"
ROLE_TF = "tf"
IMAGE_SUFFIX = "image"
CALIBRATION_SUFFIX = "calibration"

#: Roles that are not per camera, with agvviz's own topic for each.
NATIVE_TOPICS = {
    ROLE_TRUTH: GROUND_TRUTH_TOPIC,
    ROLE_ODOMETRY: ODOMETRY_TOPIC,
    ROLE_MARKER_MAP: MARKER_MAP_TOPIC,
    ROLE_CORNERS: CORNERS_TOPIC,
    ROLE_UWB_RANGE: UWB_RANGE_TOPIC,
    ROLE_UWB_ANCHORS: UWB_ANCHORS_TOPIC,
    ROLE_TF_STATIC: TF_STATIC_TOPIC,
    ROLE_TF: TF_TOPIC,
}
_CAM_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def image_role(cam_name: str) -> str:
    """The image role of camera ``cam_name`` (``front.image``)."""
    return f"{cam_name}.{IMAGE_SUFFIX}"


def calibration_role(cam_name: str) -> str:
    """The calibration role of camera ``cam_name`` (``front.calibration``)."""
    return f"{cam_name}.{CALIBRATION_SUFFIX}"


def camera_of_role(role: str) -> tuple[str, str] | None:
    """``(cam_name, "image" | "calibration")`` of a camera role, else ``None``."""
    cam, sep, kind = role.rpartition(".")
    if sep and kind in (IMAGE_SUFFIX, CALIBRATION_SUFFIX) and _CAM_NAME.match(cam) and cam != "uwb":
        return cam, kind
    return None


def valid_role(role: str) -> bool:
    return role in NATIVE_TOPICS or camera_of_role(role) is not None


def role_help() -> str:
    """One line naming every role, for ``--help`` and error messages."""
    return (
        "<cam>.image, <cam>.calibration (cam: letters, digits, _ or -), "
        + ", ".join(NATIVE_TOPICS)
    )


def native_role(topic: str) -> str:
    """The role of ``topic`` under agvviz's own naming, or ``""``."""
    match = CAMERA_TOPIC_RE.match(topic)
    if match:
        cam, kind = match.groups()
        return image_role(cam) if kind == "image" else calibration_role(cam)
    for role, native in NATIVE_TOPICS.items():
        if native == topic:
            return role
    return ""
