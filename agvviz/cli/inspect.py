"""``agvviz inspect``: what a recording holds (topics, contract, role map), whether a run can use
its frames, and which marker families the frames show (:mod:`agvviz.recording.contract`,
:func:`agvviz.replay.run.prepare`, :mod:`agvviz.replay.detect.family_scan`).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from agvviz.cli.common import console, handle_errors
from agvviz.cli.options import CALIBRATION_HELP, EXTRINSIC_HELP, MARKERS_HELP, ROLES_HELP, TOPIC_HELP, side_inputs
from agvviz.errors import InputError
from agvviz.recording import outputs
from agvviz.settings import RunSettings, apply_overrides


@handle_errors
def inspect(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="recording: an .mcap file, a rosbag2 directory or a ROS 1 .bag (or folder of them)"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="run settings that change what a run can use (body_frame, time_source, ...)"),
    topic: List[str] = typer.Option([], "--topic", metavar="ROLE=TOPIC", help=TOPIC_HELP),
    roles: Optional[Path] = typer.Option(None, "--roles", help=ROLES_HELP),
    write_roles: Optional[Path] = typer.Option(None, "--write-roles", help="write the role map to this file (edit it, then run --roles FILE)"),
    write_markers: Optional[Path] = typer.Option(None, "--write-markers", help="write a marker map skeleton (YAML, for --markers) with every marker id the frames show; fill in each marker's side_m and pose (docs/starting-without-a-map.md)"),
    markers: Optional[Path] = typer.Option(None, "--markers", help=MARKERS_HELP),
    calibration: List[str] = typer.Option([], "--calibration", metavar="CAM=FILE", help=CALIBRATION_HELP),
    extrinsic: List[str] = typer.Option([], "--extrinsic", metavar="CAM=POSE", help=EXTRINSIC_HELP),
) -> None:
    """Print topics, counts, time span, cameras, calibration, the role map and whether a run can use the frames; check agvviz recordings against the recording contract.

    Exits with code 1 when the file violates the contract, is damaged, or holds no frame a run could use (the causes are listed, as `run` would give them).

    Marker families: without a marker map, sampled frames (up to 20 per camera) are scanned for QR, ArUco and AprilTag families and each camera's families, ids, counts and apparent sizes are listed; frames of ArUco/AprilTag markers with no map (or a map of another family) make it exit 1. --write-markers FILE writes a map skeleton to fill in (docs/starting-without-a-map.md).

    Example: agvviz inspect rosbag2_dir --topic truth=/vicon/agv/pose --write-roles roles.yaml

    Example: agvviz inspect robot.mcap --write-markers map.yaml
    """
    from agvviz.recording.contract import format_report, inspect_recording
    from agvviz.recording.roles import parse_topic_options
    from agvviz.replay.run import prepare

    settings = apply_overrides(RunSettings(), list(set_))
    topic_map = parse_topic_options(list(topic))
    if write_markers is not None:  # before minutes of reading: never over an input
        outputs.check_not_input(write_markers, [p for p in (recording, markers, roles) if p is not None], option="--write-markers")
    side = side_inputs(markers, list(calibration), list(extrinsic), settings.body_frame)
    prepared = prepare(recording, settings, topic_map, roles, side)
    report = inspect_recording(recording, roles=prepared.roles, time_source=settings.time_source)
    console.print(format_report(report), highlight=False, markup=False, soft_wrap=True)
    lines = ["", f"roles (body frame {prepared.body_frame}, time from {prepared.time_source}; override with --topic ROLE=TOPIC):"]
    lines += prepared.roles.lines() or ["  none"]
    marker_lines, family_problem = _marker_scan_lines(recording, prepared, markers, write_markers)
    if family_problem:
        lines.append(f"replay: {family_problem}")
        lines.append("replay: a run would fail (`agvviz run` exits 2 naming the family)")
    elif prepared.usable_cameras:
        lines.append(f"replay: frames of camera(s) {', '.join(prepared.usable_cameras)} can be used")
    for cause in prepared.causes:
        lines.append(f"replay: {cause}")
    for note in prepared.replay.sync.notes.values():
        lines.append(f"replay: warning: {note}")
    if not prepared.can_run:
        lines.append("replay: a run would fail (no frame can be used; `agvviz run` exits non-zero)")
    lines += marker_lines
    console.print("\n".join(lines), highlight=False, markup=False, soft_wrap=True)
    if write_roles is not None:
        outputs.atomic_write_text(write_roles, prepared.roles.to_yaml(), inputs=[recording])
        console.print(f"roles written: {write_roles} (use it with --roles {write_roles})", highlight=False,
                      markup=False, soft_wrap=True)
    if not report.ok or not prepared.can_run or family_problem:
        raise typer.Exit(code=1)


def _marker_scan_lines(recording: Path, prepared, markers: Optional[Path], write_markers: Optional[Path]) -> tuple[list[str], str]:
    """inspect's marker families (issue 23): without a map (or with --write-markers) the sampled
    frames are scanned for every common family; with a map, for its family first, and for the
    others only when the map's is not seen. Writes the map skeleton when asked. Returns the
    lines and, when a run would refuse the frames' family (no map, or another map), why."""
    from agvviz.replay.detect.family_scan import map_problem, map_skeleton_yaml, mismatch_line, scan_lines, scan_recording
    from agvviz.markers.scan import MIN_FRAMES, SCAN_FAMILIES

    if not prepared.roles.cameras():
        if write_markers is not None:
            raise InputError(f"--write-markers: {recording} has no camera images to find markers in; no map written")
        return [], ""
    marker_map = prepared.replay.ctx.marker_map
    family = marker_map.get("dictionary") if isinstance(marker_map, dict) else None
    lines = [""]
    broken = map_problem(prepared)
    if broken:
        lines.append(f"markers: the marker map cannot be used: {broken.removeprefix('marker map: ')}")
        if write_markers is None:
            return lines, f"the marker map cannot be used ({broken.removeprefix('marker map: ')})"
    map_seen = False
    if family is not None:
        quick = scan_recording(prepared, families=(family,),
                               stop=lambda s: any(f.frames_seen >= MIN_FRAMES for f in s.found()))
        map_seen = bool(quick.found())
        if map_seen and write_markers is None:
            return lines + [f"markers: the map's family ({family}) is seen in the sampled frames"], ""
    scan = scan_recording(prepared, families=SCAN_FAMILIES)
    lines.append("markers seen in sampled frames (no map needed to list them; family, ids ×frames, apparent side):")
    lines += scan_lines(scan)
    mismatch = None if map_seen else mismatch_line(prepared, scan)
    problem = ""
    found = scan.found()
    if mismatch:
        lines.append(f"markers: {mismatch}")
        problem = mismatch
    elif family is None and found and all(f.family != "qr" for f in found):
        lines.append(f"markers: no marker map — write one with `agvviz inspect {recording} --write-markers map.yaml`, "
                     f"fill it in, then `agvviz run {recording} --markers map.yaml`")
        problem = f"the frames show {found[0].dictionary} markers and no marker map places them"
    if write_markers is not None:
        text = map_skeleton_yaml(scan, prepared.recording.name)
        outputs.atomic_write_text(write_markers, text, inputs=[recording] + ([markers] if markers else []))
        lines.append(f"marker map skeleton written: {write_markers} (fill in side_m and pose of each marker, then "
                     f"agvviz run {recording} --markers {write_markers})")
    return lines, problem
