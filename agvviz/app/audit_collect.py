"""Recording → :class:`~agvviz.evaluation.audit.problem.AuditData`, through the run's own stages.

The recording is opened and primed exactly as ``agvviz run`` does (:func:`agvviz.replay.run.prepare`:
role map, side files, calibration, extrinsics, odometry, marker map); every frame's corners come
from the detect stage and its Parquet cache (:mod:`agvviz.replay.detect.cache`, shared with
``run``: an audit after a run detects nothing), and the solve stage (:class:`agvviz.replay.solve.Replay`)
parses the payloads, checks them against the map and names each observation's marker. Nothing
of detection, payload or map parsing is done here again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from agvviz.evaluation.audit.problem import AuditData
from agvviz.conventions import WORLD_FRAME
from agvviz.errors import InputError, RecordingError
from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners, quad_area_px2
from agvviz.recording.source import require_recording_path
from agvviz.recording.raw import ReadReport
from agvviz.recording.source import iter_role_messages
from agvviz.settings import RunSettings


@dataclass
class Collected:
    """The audit's input and where it came from."""

    data: AuditData
    marker_map: dict | None  # the map in use (side file or recording)
    recording_name: str
    recording_sha256: str
    scenario: dict | None
    frame_index: np.ndarray  # (N,) the run's frame index of each audit frame
    truth: np.ndarray  # (N, 4, 4) ground truth at each frame's stamp, NaN where none
    warnings: list[str] = field(default_factory=list)
    detection_source: str = "detected"
    cameras: dict = field(default_factory=dict)  # name -> PinholeCamera (the calibration in use)


def collect(
    recording_path: Path,
    settings: RunSettings,
    *,
    side=None,
    topics: dict[str, str] | None = None,
    roles_file: Path | None = None,
    jobs: int | None = None,
    cache_dir=None,
    progress: Callable[[int], None] | None = None,
) -> Collected:
    """Every frame's observations, odometry and first pose, the cameras and the mapped markers.

    Raises :class:`RecordingError` / :class:`InputError` (one line) for a recording without
    usable frames, camera or detections."""
    from agvviz.replay import run as runner

    recording_path = require_recording_path(recording_path)
    prepared = runner.prepare(recording_path, settings, topics, roles_file, side)
    if not prepared.usable_cameras:
        causes = "; ".join(prepared.causes) or "no camera images"
        raise RecordingError(f"{recording_path.name}: no camera whose frames an audit can use: {causes}")
    recording, replay = prepared.recording, prepared.replay
    sha = recording.sha256()
    plan = runner._detection_feed(prepared, sha, side, jobs, cache_dir)
    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    frames: dict[int, dict] = {}
    done = 0
    with plan.feed as feed:
        stream = iter_role_messages(recording, prepared.roles, prepared.time_source, read_report)
        for message, detections in feed.annotate(stream):
            result = replay.feed(message, detections)
            if result is None:
                continue
            done += 1
            if progress is not None:
                progress(done)
            frame = frames.setdefault(result.index, {"t_ns": result.log_time_ns, "obs": [], "pose": None})
            if result.T_world_agv is not None and frame["pose"] is None:
                frame["pose"] = result.T_world_agv
            frame.setdefault("truth", result.T_world_agv_truth)
            if detections is None or not result.observations:
                continue
            codes = list(detections.codes)
            for obs in result.observations:
                if obs.points_frame != WORLD_FRAME:
                    continue  # a marker on the vehicle: no placement in the world to audit
                match = None
                for det in codes:
                    if det.kind == "qr" and obs.payload and det.text == obs.payload:
                        match = det
                    elif det.kind == "aruco" and str(det.aruco_id) == obs.marker_id:
                        match = det
                    if match is not None:
                        break
                if match is None:
                    continue
                codes.remove(match)
                frame["obs"].append((result.cam_name, obs.marker_id, np.asarray(match.corners_px[:4], float),
                                     np.asarray(obs.points_world_m[:4], float)))
    plan.store(read_report)
    warnings = list(read_report.problems) + list(plan.problems)
    marker_map = replay.ctx.marker_map
    # cameras on the vehicle with a calibration
    cam_names, K, T_agv_cam, cameras = [], [], [], {}
    for name in prepared.usable_cameras:
        cam = replay.ctx.cameras.get(name)
        if cam is None or cam.camera is None:
            continue
        if cam.T_agv_cam is None:
            warnings.append(f"camera {name} is fixed in the world (no extrinsic to the body frame): not audited")
            continue
        cam_names.append(name)
        cameras[name] = cam.camera
        K.append(np.asarray(cam.camera.K, float))
        T_agv_cam.append(np.asarray(cam.T_agv_cam, float))
    if not cam_names:
        raise RecordingError(f"{recording_path.name}: no camera on the vehicle with a calibration and an extrinsic to audit")
    # markers: the map's corners where the map lists the code, else the payload's
    mapped = dict(replay.ctx.qr_map)
    if replay.ctx.aruco_map is not None:
        for marker_id, marker in replay.ctx.aruco_map.markers.items():
            if marker.frame == WORLD_FRAME:
                mapped[str(marker_id)] = np.asarray(marker.corners_m, float)
    marker_ids: list[str] = []
    marker_index: dict[str, int] = {}
    T_world_marker, points_marker = [], []
    obs_frame, obs_cam, obs_marker, obs_px = [], [], [], []
    indices = sorted(frames)
    with_obs = [k for k in indices if any(o[0] in cam_names for o in frames[k]["obs"])]
    if not with_obs:
        raise InputError(
            f"{recording_path.name}: no detection to audit: no frame shows a code that parses and agrees with the marker map"
        )
    keep = [k for k in indices if with_obs[0] <= k <= with_obs[-1]]
    odom = np.full((len(keep), 4, 4), np.nan)
    has_odom = np.zeros(len(keep), dtype=bool)
    T_init = np.full((len(keep), 4, 4), np.nan)
    truth = np.full((len(keep), 4, 4), np.nan)
    stamps = np.array([frames[k]["t_ns"] for k in keep], dtype=np.int64)
    for i, k in enumerate(keep):
        T = replay.sync.odometry_at(int(frames[k]["t_ns"]))
        if T is not None:
            odom[i], has_odom[i] = T, True
        if frames[k]["pose"] is not None:
            T_init[i] = frames[k]["pose"]
        if frames[k].get("truth") is not None:
            truth[i] = frames[k]["truth"]
        seen_here = set()
        for cam_name, marker_id, px, corners_world in frames[k]["obs"]:
            if cam_name not in cam_names or (cam_name, marker_id) in seen_here:
                continue
            seen_here.add((cam_name, marker_id))
            if marker_id not in marker_index:
                corners = mapped.get(marker_id, corners_world)
                try:
                    T_wm, pts = marker_frame_from_corners(corners)
                except DegenerateGeometryError:
                    continue
                marker_index[marker_id] = len(marker_ids)
                marker_ids.append(marker_id)
                T_world_marker.append(T_wm)
                points_marker.append(pts[:4])
            if quad_area_px2(px) <= 0.0 or not np.all(np.isfinite(px)):
                continue
            obs_frame.append(i)
            obs_cam.append(cam_names.index(cam_name))
            obs_marker.append(marker_index[marker_id])
            obs_px.append(px)
    if not has_odom.all() and has_odom.any():
        warnings.append(f"{int((~has_odom).sum())} of {len(keep)} frames have no odometry at their stamp")
    if not has_odom.any():
        # without odometry a frame without detections says nothing
        sel = np.array([i in set(obs_frame) for i in range(len(keep))], dtype=bool)
        remap = np.cumsum(sel) - 1
        obs_frame = [int(remap[i]) for i in obs_frame]
        keep = [k for k, s in zip(keep, sel) if s]
        odom, has_odom, T_init, truth, stamps = odom[sel], has_odom[sel], T_init[sel], truth[sel], stamps[sel]
    data = AuditData(
        stamps_ns=stamps, T_odom_agv=odom, has_odom=has_odom, T_init=T_init, cam_names=tuple(cam_names),
        K=np.stack(K), T_agv_cam=np.stack(T_agv_cam), marker_ids=tuple(marker_ids),
        T_world_marker=np.stack(T_world_marker) if T_world_marker else np.zeros((0, 4, 4)),
        points_marker_m=np.stack(points_marker) if points_marker else np.zeros((0, 4, 3)),
        obs_frame=np.asarray(obs_frame, dtype=int), obs_cam=np.asarray(obs_cam, dtype=int),
        obs_marker=np.asarray(obs_marker, dtype=int), obs_px=np.asarray(obs_px, float).reshape(-1, 4, 2),
    )
    name = recording_path.name if recording_path.is_dir() else recording_path.stem
    return Collected(
        data=data, marker_map=marker_map, recording_name=name, recording_sha256=sha, scenario=recording.scenario,
        frame_index=np.asarray(keep, dtype=int), truth=truth, warnings=warnings,
        detection_source="cache" if plan.from_cache else "detected", cameras=cameras,
    )
