"""Options several commands share: their help texts, the side files (``--markers``,
``--calibration``, ``--extrinsic``) parsed into the replay's side inputs, and the ``--jobs`` bound."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from agvviz.cli.common import fail
from agvviz.errors import InputError

SET_HELP = "key=value (repeatable); see `agvviz scenarios` / `agvviz run --help` for keys"

TOPIC_HELP = (
    "ROLE=TOPIC (repeatable): which topic plays which role, over the inferred role map "
    "(`agvviz inspect` prints it); e.g. --topic truth=/vicon/agv/pose --topic "
    "front.image=/camera/image_raw/compressed. Roles: <cam>.image, <cam>.calibration, truth, "
    "odometry, markers, tf_static, tf, uwb.range, uwb.anchors, corners"
)
ROLES_HELP = "a roles file (YAML role: topic, written by `agvviz inspect --write-roles FILE`); only its roles are used"
MARKERS_HELP = "marker map side file (agvviz.MarkerMap JSON/YAML); overrides the recording's map"
CALIBRATION_HELP = "CAM=FILE (repeatable): camera calibration side file; overrides the recording's calibration of CAM"
EXTRINSIC_HELP = (
    "CAM=x,y,z,qx,qy,qz,qw (repeatable): the camera's pose in the body frame (T_body_cam, metres, "
    "quaternion x y z w; camera frame OpenCV/ROS optical); overrides the recording's transforms"
)


JOBS_HELP = "detection worker processes (default: one per CPU; 1 = detect in this process); results do not depend on it"
CACHE_HELP = (
    "reuse and store detections (corners, ids, payloads) per recording and detection settings, so a "
    "run that only changes solve/fusion/correction settings skips detection"
)
BUDGET_HELP = (
    "add the error budget (an agvviz recording under a non-ideal realism profile): the share of the "
    "position error each error source causes, found by re-recording the scenario with that source off "
    "(minutes: once per source); in the summary and the .rrd (same as `agvviz budget`)"
)
RUN_FAIL_IF_HELP = (
    "exit 1 when this condition on the run holds, e.g. \"suspects > 0\" or \"suspects.map_entry > 0 or "
    "position_rmse_mm > 5\" (repeatable: exit 1 when any holds). Metrics: frames, solved, rejected, solved_pct, "
    "suspects, suspects_pct, suspect_stretches, suspects.<cause> (map_entry, payload, mirror_flip, extrinsic, "
    "time_offset, time_stamps, uwb, unknown), <position|heading|pitch|roll>_<rmse|median|p95|max>_<mm|deg> "
    "(with truth), reproj_<stat>_px; numbers, + - * /, comparisons, and/or, parentheses"
)
JUNIT_XML_HELP = (
    "write the --fail-if verdicts as JUnit XML to FILE for CI (one testcase per condition, a failure "
    "when it holds)"
)
CACHE_DIR_HELP = "detection cache folder (default: $AGVVIZ_CACHE_DIR, else ~/.cache/agvviz/detections)"


def side_inputs(markers: Optional[Path], calibration: list[str], extrinsic: list[str], body_frame: str):
    """Side-file values (agvviz.recording.sidefiles) for the replay; InputError on bad input."""
    from agvviz.recording import sidefiles
    from agvviz.replay.run import SideInputs

    side = SideInputs()
    if markers is not None:
        side.marker_map = sidefiles.load_marker_map(markers)
    for pair, what in [(p, "calibration") for p in calibration] + [(p, "extrinsic") for p in extrinsic]:
        cam, sep, value = pair.partition("=")
        cam, value = cam.strip(), value.strip()
        if not sep or not cam or not value:
            example = "front=calib.yaml" if what == "calibration" else "front=0.1,0,0.3,-0.5,0.5,-0.5,0.5"
            raise InputError(f"--{what} {pair!r}: expected CAM={'FILE' if what == 'calibration' else 'x,y,z,qx,qy,qz,qw'}, e.g. {example}")
        if what == "calibration":
            side.calibrations[cam] = sidefiles.load_calibration(cam, Path(value))
        else:
            side.extrinsics[cam] = sidefiles.parse_extrinsic(cam, value, body_frame)
    return side


def check_detect_jobs(jobs: Optional[int]) -> None:
    """Refuse a detection ``--jobs`` outside 1..256 (None: one per CPU)."""
    if jobs is not None and not 1 <= jobs <= 256:
        fail(f"--jobs must lie in 1..256 (or be left out for one per CPU), got {jobs}")
