"""Decoded values built the same way by every recording format
(:mod:`agvviz.recording.formats`): a camera's name, a pose matrix, a lossless frame from an
uncompressed image, a checked calibration, and the image size bound of the recording contract."""

from __future__ import annotations

import math

import numpy as np

from agvviz.geometry import PinholeCamera, se3
from agvviz.model.messages import CalibrationMsg, CompressedFrame
from agvviz.model.topics import CAMERA_TOPIC_RE
from agvviz.recording.images import ImageEncodingError, raw_to_png
from agvviz.recording.raw import MessageDecodeError

#: Largest image side (px) a calibration may declare and a frame may have. Real machine-vision
#: sensors stay below 16384 px (16k line-scan cameras are the largest); beyond it an image
#: would only allocate gigabytes (undistortion maps of a 2^32-1 px wide image: terabytes).
MAX_IMAGE_SIDE_PX = 16384


def cam_name(topic: str, frame_id: str) -> str:
    """``<name>`` of ``/cam/<name>/...``; otherwise the frame id without ``cam_`` (a role map
    gives other files' cameras their names, :mod:`agvviz.recording.roles`)."""
    match = CAMERA_TOPIC_RE.match(topic)
    if match:
        return match.group(1)
    return frame_id.removeprefix("cam_") or topic


def matrix_from_pose(position, orientation, what: str) -> np.ndarray:
    t = (float(position.x), float(position.y), float(position.z))
    q = (float(orientation.x), float(orientation.y), float(orientation.z), float(orientation.w))
    # (plain floats: this runs for every pose message, and numpy's per-call cost was most of it)
    if not all(map(math.isfinite, t + q)) or math.hypot(*q) < 1e-9:
        raise MessageDecodeError(f"{what}: translation/quaternion must be finite with a non-zero quaternion")
    return se3.from_quaternion_xyzw(np.array(q), np.array(t))


def raw_frame(topic: str, frame_id: str, encoding: str, width: int, height: int, step: int,
              data: bytes, stamp_ns: int, big_endian: bool = False) -> CompressedFrame:
    """An uncompressed frame as a lossless PNG :class:`CompressedFrame`
    (:mod:`agvviz.recording.images`); raises :class:`MessageDecodeError`."""
    try:
        png = raw_to_png(encoding, int(width), int(height), int(step), bytes(data), bool(big_endian))
    except ImageEncodingError as exc:
        raise MessageDecodeError(str(exc)) from None
    return CompressedFrame(cam_name(topic, frame_id), frame_id, "png", png, stamp_ns=stamp_ns,
                           source_encoding=encoding)


#: Distortion models a calibration may name → accepted coefficient counts.
DISTORTION_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,), "": (0,)}


def calibration(topic: str, frame_id: str, K, D, distortion_model: str, width: int, height: int,
                stamp_ns: int = 0) -> CalibrationMsg:
    """A checked :class:`CalibrationMsg` from K (9), D and the image size (Foxglove
    ``CameraCalibration`` and ROS ``CameraInfo`` alike); raises :class:`MessageDecodeError`.

    ``equidistant`` (a fisheye lens) is refused by name: its model is OpenCV's ``fisheye``
    module, which the replay does not implement.
    """
    K = np.array(list(K), dtype=float)
    if K.size == 9 and np.all(K == 0):
        raise MessageDecodeError("K is all zeros: the camera is not calibrated (give --calibration CAM=FILE)")
    if K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0 or K[8] != 1.0:
        raise MessageDecodeError(f"K must be 9 finite numbers with fx, fy > 0 and K[2,2] = 1, got {list(K)}")
    problem = image_size_problem(width, height)
    if problem:
        raise MessageDecodeError(f"calibration {problem}")
    D = list(D)
    model = distortion_model or ""
    if model == "equidistant" or model == "fisheye":
        raise MessageDecodeError(
            f"distortion model {model!r} (fisheye) is not supported: the replay models plumb_bob "
            "and rational_polynomial lenses; undistort the images or give a pinhole calibration"
        )
    if len(D) == 0:
        dist = np.zeros(5)
    elif model in DISTORTION_MODELS and len(D) in DISTORTION_MODELS[model]:
        dist = np.array(D, dtype=float)
    elif model == "plumb_bob" and len(D) == 8 and not any(D[5:]):
        dist = np.array(D[:5], dtype=float)  # some drivers pad plumb_bob to 8
    else:
        raise MessageDecodeError(
            f"distortion {model!r} with {len(D)} coefficients is not supported; expected "
            "plumb_bob with 5 coefficients (k1, k2, p1, p2, k3), rational_polynomial with 8, or none"
        )
    try:
        camera = PinholeCamera(K.reshape(3, 3), dist, int(width), int(height))
    except ValueError as exc:
        raise MessageDecodeError(str(exc)) from None
    return CalibrationMsg(cam_name(topic, frame_id), frame_id, camera, model, stamp_ns=stamp_ns)


def image_size_problem(width: int, height: int) -> str | None:
    """Why ``width`` × ``height`` px cannot be a camera's image size, or ``None``: each side
    must be 1..:data:`MAX_IMAGE_SIDE_PX` px."""
    if not (0 < width <= MAX_IMAGE_SIDE_PX and 0 < height <= MAX_IMAGE_SIDE_PX):
        return (
            f"image size {width}x{height} px is outside 1..{MAX_IMAGE_SIDE_PX} px per side "
            "(the recording contract's bound)"
        )
    return None
