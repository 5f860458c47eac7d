"""Which marker family a recording shows, from a sample of its frames (issue 23: starting
without a map). Reads frames through the recording's role map; the scan itself is
:mod:`agvviz.markers.scan`.

* :func:`scan_recording` — up to ``frames_per_camera`` frames per camera, spread evenly over
  the recording (only those are decoded), every family tried: what ``agvviz inspect`` lists.
* :func:`family_check` — what ``agvviz run`` checks before replaying: with no marker map, frames
  that show ArUco/AprilTag markers (not QR codes, which carry their own coordinates) cannot be
  used, and with a map, frames that show another family than the map's cannot either; both are
  one line naming what was found and the command to run next (:class:`FamilyMismatchError`).
  It stops reading as soon as the expected family has been seen in :data:`MIN_FRAMES` frames.
* :func:`map_skeleton_yaml` — the side-file map (``--markers``) with every id seen and the
  fields the user must fill in, for ``agvviz inspect --write-markers``.
"""

from __future__ import annotations

from collections import Counter
from typing import Callable

import cv2
import numpy as np

from agvviz.errors import InputError
from agvviz.markers.scan import (
    DEFAULT_FRAMES_PER_CAMERA,
    MIN_FRAMES,
    QR_FAMILY,
    SCAN_FAMILIES,
    FamilyFinding,
    FamilyScan,
    family_label,
    sample_indices,
    scan_frame,
)
from agvviz.model.messages import CompressedFrame
from agvviz.recording.formats import decode
from agvviz.recording.raw import MessageDecodeError, ReadReport
from agvviz.recording.roles import camera_of_role


class FamilyMismatchError(InputError):
    """The frames show a marker family the run cannot use as given (no map, or another map)."""


#: Sampled frames of a camera scanned for every family; after them, only the families seen so
#: far are looked for (when any was): identification against the 1000-id dictionaries costs
#: ≈0.1 s per family on a cluttered 640×480 frame (docs/starting-without-a-map.md).
PROBE_FRAMES = 6


def scan_recording(
    prepared,
    frames_per_camera: int = DEFAULT_FRAMES_PER_CAMERA,
    families: tuple[str, ...] = SCAN_FAMILIES,
    stop: Callable[[FamilyScan], bool] | None = None,
    probe_frames: int = PROBE_FRAMES,
) -> FamilyScan:
    """Scan up to ``frames_per_camera`` frames per camera of ``prepared`` (a
    :class:`agvviz.replay.run.Prepared`) for ``families`` — all of them on a camera's first
    ``probe_frames`` sampled frames, then only those seen so far (all again while none has
    been) — stopping early when ``stop(scan)`` holds after a frame. Frames that cannot be
    decoded are skipped (a run reports them)."""
    roles, recording_scan = prepared.roles, prepared.scan
    wanted: dict[str, tuple[str, set[int]]] = {}  # topic → (camera, sampled indices)
    for role, topic in roles.roles.items():
        cam = camera_of_role(role)
        if cam is None or cam[1] != "image" or topic not in recording_scan.topics:
            continue
        wanted[topic] = (cam[0], set(sample_indices(recording_scan.topics[topic].count, frames_per_camera)))
    result = FamilyScan()
    if not wanted:
        return result
    seen = {topic: 0 for topic in wanted}
    seen_families: dict[str, set[str]] = {}
    left = sum(len(indices) for _, indices in wanted.values())
    for item in prepared.recording.iter_raw(ReadReport(), set(wanted)):
        topic = getattr(item, "topic", None)
        if topic not in wanted:
            continue
        cam, indices = wanted[topic]
        index = seen[topic]
        seen[topic] += 1
        if index not in indices:
            continue
        left -= 1
        gray = _gray(item)
        if gray is not None:
            tried = families
            if result.frames_sampled(cam) >= probe_frames and seen_families.get(cam):
                tried = tuple(f for f in families if f in seen_families[cam])
            markers = scan_frame(gray, tried)
            seen_families.setdefault(cam, set()).update(m.family for m in markers)
            result.add(cam, markers)
            if stop is not None and stop(result):
                break
        if left <= 0:
            break
    return result


def _gray(item) -> np.ndarray | None:
    try:
        value = decode(item)
    except MessageDecodeError:
        return None
    if not isinstance(value, CompressedFrame) or not value.data:
        return None
    gray = cv2.imdecode(np.frombuffer(value.data, np.uint8), cv2.IMREAD_GRAYSCALE)
    return gray if gray is not None and gray.size else None


def _map_family(marker_map: dict | None) -> str | None:
    """The family a marker map names (``qr`` or an OpenCV dictionary), None without a map."""
    if not isinstance(marker_map, dict):
        return None
    dictionary = marker_map.get("dictionary")
    return dictionary if isinstance(dictionary, str) and dictionary else None


def _seen_enough(family: str) -> Callable[[FamilyScan], bool]:
    def stop(scan: FamilyScan) -> bool:
        return any(f.family == family for f in scan.found() if f.frames_seen >= MIN_FRAMES)
    return stop


def _ids_text(finding: FamilyFinding, limit: int = 8) -> str:
    ids = sorted(finding.ids, key=lambda i: (isinstance(i, str), i))
    text = ", ".join(str(i) for i in ids[:limit])
    return text + (f", … ({len(ids)} ids)" if len(ids) > limit else "")


def map_problem(prepared) -> str:
    """Why the marker map in use (the recording's ``/markers/map`` or ``--markers``) cannot be
    used as it is, or ``""``: what the replay refused it for (e.g. an ArUco id listed twice,
    which would otherwise only show as every frame rejected ``no_marker``), or a QR map listing
    an id twice (the replay would keep the last silently)."""
    ctx = prepared.replay.ctx
    if ctx.marker_map is None:
        return ""
    if ctx.marker_map_problem:
        return ctx.marker_map_problem
    if _map_family(ctx.marker_map) == QR_FAMILY:
        counts = Counter(str(m.get("id")) for m in ctx.marker_map.get("markers", []) if isinstance(m, dict))
        repeated = sorted(i for i, n in counts.items() if n > 1)
        if repeated:
            return f"marker map: id {repeated[0]} appears more than once" + (
                f" (and {len(repeated) - 1} more repeated id(s))" if len(repeated) > 1 else "")
    return ""


def family_check(
    prepared, recording_arg: str, frames_per_camera: int = DEFAULT_FRAMES_PER_CAMERA, frames_checked: bool = False,
) -> None:
    """Refuse, before a run, frames whose marker family the run cannot use
    (:class:`FamilyMismatchError`, one line naming the family and the command to run next):

    * no marker map and the frames show ArUco/AprilTag markers but no QR code;
    * a map of one family and frames that show another, none of the map's;
    * a map the replay refuses (:func:`map_problem`), e.g. an id listed twice.

    Nothing is refused when the expected family is seen, or when no family is (the run then
    rejects its frames as it always did). ``recording_arg`` is the recording as the user named
    it, for the command in the message. ``frames_checked``: these frames passed the check under
    the same expected family before (their detections are in the cache): the map alone is
    checked."""
    marker_map = prepared.replay.ctx.marker_map
    problem = map_problem(prepared)
    if problem:
        raise InputError(f"the marker map cannot be used: {problem.removeprefix('marker map: ')}")
    if frames_checked:
        return
    expected = _map_family(marker_map) or QR_FAMILY
    if not prepared.roles.cameras():
        return
    from agvviz.markers.dictionary import is_aruco_dictionary

    if expected != QR_FAMILY and not is_aruco_dictionary(expected):
        return  # a map the replay refuses anyway, with its own reason
    quick = scan_recording(prepared, frames_per_camera, (expected,), stop=_seen_enough(expected))
    if quick.found():
        return
    others = tuple(f for f in SCAN_FAMILIES if f != expected)
    full = scan_recording(prepared, frames_per_camera, others)
    found = full.found()
    if not found:
        return
    main = found[0]
    what = f"{family_label(main.dictionary)} markers (ids {_ids_text(main)}; {main.frames_seen} of {main.frames_sampled} sampled frames)"
    if marker_map is None:
        if main.family == QR_FAMILY:
            return
        raise FamilyMismatchError(
            f"no marker map, and the frames show {what}: their positions must come from a map. "
            f"Write one with `agvviz inspect {recording_arg} --write-markers map.yaml`, fill in each "
            f"marker's side_m and pose, then `agvviz run {recording_arg} --markers map.yaml`"
        )
    raise FamilyMismatchError(
        f"the marker map says {family_label(expected)}, but the frames show {what} and no {expected} "
        f"marker: give a map of {main.dictionary} (`agvviz inspect {recording_arg} --write-markers "
        f"map.yaml` writes a skeleton) or check the map's dictionary"
    )


def mismatch_line(prepared, scan: FamilyScan) -> str | None:
    """``inspect``'s line for a map (the recording's or --markers) whose family the sampled
    frames did not show (the caller scanned for it first) while ``scan`` found others; None
    without a map or when the scan found nothing."""
    expected = _map_family(prepared.replay.ctx.marker_map)
    found = scan.found()
    if expected is None or not found:
        return None
    return (f"map says {expected}, frames show {', '.join(f.dictionary for f in found)}: "
            f"a run would find none of the map's markers")


def scan_lines(scan: FamilyScan) -> list[str]:
    """``inspect``'s listing: per camera the families seen (believed ones first)."""
    lines = []
    for cam in scan.cameras():
        n = scan.frames_sampled(cam)
        findings = scan.findings(cam)
        if not findings:
            lines.append(f"  {cam}: no marker of any family in {n} sampled frame(s)")
            continue
        lines.append(f"  {cam} ({n} sampled frame(s)):")
        lines += [f"    {f.describe()}" for f in findings]
    return lines


def map_skeleton_yaml(scan: FamilyScan, recording_name: str) -> str:
    """A ``--markers`` side file with every id the scan believes in, for the user to fill in:
    ``side_m`` and ``pose`` are left empty (``null``), which the side-file reader refuses with
    a line naming the entry until they are filled in. One dictionary per map: the main family;
    other believed families are listed in a comment. QR codes carry their own coordinates and
    need no map: :class:`InputError` when QR is all the scan found, or nothing."""
    found = [f for f in scan.found() if f.family != QR_FAMILY]
    if not found:
        seen_qr = any(f.family == QR_FAMILY for f in scan.found())
        raise InputError(
            "--write-markers: the sampled frames show "
            + ("only QR codes, which carry their own positions (no map needed)" if seen_qr else "no marker of any family")
            + "; no map written"
        )
    main = found[0]
    cams = ", ".join(scan.cameras())
    ids = sorted(main.ids)
    lines = [
        f"# agvviz marker map skeleton for {recording_name}, written by `agvviz inspect --write-markers`.",
        f"# The sampled frames of camera(s) {cams} show {family_label(main.dictionary)} markers:",
        f"# {len(ids)} id(s), seen in {main.frames_seen} of {main.frames_sampled} sampled frames, "
        f"{main.side_px[1]:.0f} px across (median).",
    ]
    for other in found[1:]:
        lines.append(f"# Also seen (one dictionary per map; not listed): {other.dictionary} ids {_ids_text(other, 20)}.")
    lines += [
        "#",
        "# FILL IN for every marker (world frame, metres; docs/starting-without-a-map.md):",
        "#   side_m: the printed side of the marker's black square (AprilTag: the black border, its \"tag size\")",
        "#   pose:   [x, y, z, qx, qy, qz, qw] of the marker frame in the world: origin at the marker centre,",
        "#           x along the printed top edge (left → right), y up the printed face, z out of the face",
        "#   or, instead of pose, corners_world_m: [[x, y, z] × 4] TL, TR, BR, BL as printed (side_m optional)",
        "#   frame: agv   for a marker mounted on the vehicle (pose/corners in the body frame)",
        "# Remove markers you do not know the position of; a marker left null is refused by name.",
        "# A dictionary that holds every id seen: any larger one of the same family works too.",
        f"dictionary: {main.dictionary}",
        "markers:",
    ]
    for marker_id in ids:
        lines += [
            f"  - id: {marker_id}    # seen in {main.ids[marker_id]} sampled frame(s)",
            "    side_m: null    # FILL IN (m)",
            "    pose: null      # FILL IN [x, y, z, qx, qy, qz, qw] — or corners_world_m instead",
        ]
    return "\n".join(lines) + "\n"
