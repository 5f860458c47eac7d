"""Several cameras at one time stamp → one camera fix (paper 003 §2.2). No I/O.

Paper 003 takes "the camera that accurately recognizes the four corner points of the ArUco
code and has the best effect". Policies (run setting ``camera_select``):

``best``     the solved frame whose marker covers the most pixels (the largest code in the image
             has the smallest relative corner error, so the best-conditioned pose);
``combine``  starting from ``best``, one joint LM over the corners of every marker every camera
             that solved used (:func:`agvviz.solvers.multi_camera.refine_rig_pose`): cameras
             fixed in the world watching markers on the AGV (paper 003), or cameras on the AGV
             watching markers fixed in the world (paper 002's two cameras; the same problem
             with the unknown ``T_agv_world``); a mix of the two gets ``best``. The primary
             frame's covariance stays its own camera's.

With ``floor=True`` (run setting ``floor_constraint``, world-fixed cameras and a marker on the
AGV only) the pose is refined with the AGV on the floor — x, y, heading — on the chosen camera
(``best``) or on all (``combine``): it removes the planar-ambiguity flips of a small, far,
oblique marker.

The chosen frame becomes the *primary* result of the time stamp: its pose is the camera fix.
For ``combine`` the primary frame's pose, reprojections and errors are replaced by the joint
solution's, and every other camera's reprojected corners are recomputed from it. The outcome
is a frozen :class:`~agvviz.model.fusion.CameraSelection`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from agvviz.conventions import AGV_FRAME, WORLD_FRAME
from agvviz.geometry import euler, se3
from agvviz.geometry.plane import quad_area_px2
from agvviz.model.frames import FrameResult
from agvviz.model.fusion import CameraSelection
from agvviz.solvers.multi_camera import CAMERA_SELECT, RigView, refine_rig_pose


def _marker_area_px2(frame: FrameResult) -> float:
    obs = next(o for o in frame.observations if o.marker_id == frame.used_marker_id)
    return quad_area_px2(obs.corners_px)


def _camera_on_agv(frame: FrameResult, cameras: dict) -> bool:
    """The frame's camera rides on the AGV and every marker it used is fixed in the world."""
    cam = cameras.get(frame.cam_name)
    return (
        cam is not None and cam.camera is not None and cam.T_agv_cam is not None
        and all(o.points_frame == WORLD_FRAME for o in _used_observations(frame))
    )


def _used_observations(frame: FrameResult) -> list:
    """The observations whose points made the frame's pose (every marker of a joint solve)."""
    used = frame.used_marker_ids or (frame.used_marker_id,)
    return [o for o in frame.observations if o.marker_id in used]


def _camera_from_frames(cam, T_world_agv: np.ndarray) -> dict[str, np.ndarray]:
    """``T_cam_<frame>`` for the frames markers can be fixed in, at the AGV pose ``T_world_agv``."""
    if cam is None or cam.camera is None:
        return {}
    if cam.T_world_cam is not None:
        T_cam_world = se3.inverse(cam.T_world_cam)
        return {WORLD_FRAME: T_cam_world, AGV_FRAME: T_cam_world @ T_world_agv}
    if cam.T_agv_cam is not None:
        T_cam_agv = se3.inverse(cam.T_agv_cam)
        return {AGV_FRAME: T_cam_agv, WORLD_FRAME: T_cam_agv @ se3.inverse(T_world_agv)}
    return {}


def select_camera_fix(
    frames: list[FrameResult], cameras: dict, policy: str, gimbal_threshold: float, floor: bool = False
) -> CameraSelection:
    """Pick or combine the frames of one time stamp (module docstring).

    ``cameras`` maps camera name → the pipeline's per-camera state (``camera``, ``T_world_cam``).
    """
    if policy not in CAMERA_SELECT:
        raise ValueError(f"unknown camera_select {policy!r}; valid: {', '.join(CAMERA_SELECT)}")
    solved = [f for f in frames if f.solved]
    selection = CameraSelection(None, [f.cam_name for f in solved], frames=list(frames))
    if not solved:
        return selection
    best = max(solved, key=_marker_area_px2)
    selection = replace(selection, primary=best, used=[best.cam_name])
    if (policy == "best" or len(solved) == 1) and not floor:
        return selection
    joined = solved if policy == "combine" else [best]
    moving = all(_camera_on_agv(f, cameras) for f in joined)
    if moving and (policy == "best" or floor and len(joined) == 1):
        return selection  # the floor refinement is for world-fixed cameras
    views = []
    for frame in joined:
        cam = cameras.get(frame.cam_name)
        used = _used_observations(frame)
        if moving:
            # Cameras on the AGV, markers in the world: the same rig problem with the roles of
            # the frames swapped — unknown T_agv_world, fixed T_cam_agv, points in the world.
            points = np.vstack([o.points_world_m for o in used])
            ideal = cam.camera.undistort_pixels(np.vstack([o.corners_px for o in used]))
            views.append(RigView(cam.camera.K, se3.inverse(cam.T_agv_cam), points, ideal))
            continue
        if cam is None or cam.T_world_cam is None or any(o.points_frame != AGV_FRAME for o in used):
            return replace(
                selection,
                note="combine needs all cameras on the AGV or all fixed in the world watching markers on the AGV: used best",
            )
        ideal = cam.camera.undistort_pixels(np.vstack([o.corners_px for o in used]))
        views.append(RigView(cam.camera.K, se3.inverse(cam.T_world_cam), np.vstack([o.points_world_m for o in used]), ideal))
    try:
        if moving:
            T_agv_world, rms_px = refine_rig_pose(se3.inverse(best.T_world_agv), views)
            T_world_agv = se3.inverse(T_agv_world)
        else:
            T_world_agv, rms_px = refine_rig_pose(best.T_world_agv, views, planar=floor)
    except ValueError as exc:
        return replace(selection, note=f"joint LM failed ({exc}): used best")
    hpr_rad = np.array(euler.hpr_from_matrix(T_world_agv[:3, :3], gimbal_threshold))
    errors = {}
    if best.T_world_agv_truth is not None:
        truth = best.T_world_agv_truth
        heading_err, pitch_err, roll_err = np.degrees(euler.wrap_angle_rad(hpr_rad - best.hpr_truth_rad))
        errors = dict(
            position_error_m=float(np.linalg.norm(T_world_agv[:3, 3] - truth[:3, 3])),
            heading_error_deg=float(heading_err), pitch_error_deg=float(pitch_err), roll_error_deg=float(roll_err),
        )
    T_world_cam = T_world_agv @ cameras[best.cam_name].T_agv_cam if moving else best.T_world_cam
    joint = replace(best, T_world_agv=T_world_agv, T_world_cam=T_world_cam, reproj_rms_px=rms_px, hpr_rad=hpr_rad, **errors)
    frames_out = []
    for frame in frames:
        frame = joint if frame is best else frame
        cam = cameras.get(frame.cam_name)
        T_cam_frames = _camera_from_frames(cam, T_world_agv)
        if T_cam_frames:
            observations = []
            for obs in frame.observations:
                if obs.points_frame in T_cam_frames:
                    points_cam = se3.transform_points(T_cam_frames[obs.points_frame], obs.points_world_m)
                    if np.all(points_cam[:, 2] > 0):
                        obs = replace(obs, reprojected_px=cam.camera.project(points_cam))
                observations.append(obs)
            frame = replace(frame, observations=tuple(observations))
            if frame.cam_name == best.cam_name and frame.index == best.index:
                joint = frame
        frames_out.append(frame)
    used = [f.cam_name for f in solved] if policy == "combine" else [best.cam_name]
    return replace(selection, primary=joint, frames=frames_out, used=used)
