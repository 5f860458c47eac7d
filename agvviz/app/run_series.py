"""Reading a run ``.rrd`` back into per-frame arrays (:func:`load_run`, a
:class:`~agvviz.evaluation.comparison.RunSeries`), and the pieces of a run the overlays of
``diff`` and ``sweep`` show (its cameras, reprojected corners, error series and truth).
The ``.rrd`` alone is enough: it is read through Rerun's API (:mod:`agvviz.viz.readback`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from agvviz.evaluation.comparison import DIRECT, RunSeries
from agvviz.viz import paths
from agvviz.viz.overlay import OverlayTruth
from agvviz.viz.readback import (
    RrdContents,
    RrdReadError,
    SETTING_SEPARATOR,
    document_json,
    frame_stamps,
    frame_times,
    points2d,
    read_rrd,
    scalar_series,
    sweep_index,
    transforms,
)

#: Per-frame error series of a run: quantity key → (entity, scale to the quantity's unit).
ERROR_ENTITIES = {
    "position": (paths.ERROR_POSITION_MM, 1.0),
    "heading": (paths.ERROR_HEADING_DEG, 1.0),
    "pitch": (paths.ERROR_PITCH_DEG, 1.0),
    "roll": (paths.ERROR_ROLL_DEG, 1.0),
    "reproj": (paths.ERROR_REPROJ_RMS_PX, 1.0),
}

#: Detected-corner entity of a camera on the AGV and of one fixed in the world (uwb_room's
#: wall cameras, ``world/cameras/cam_<name>``): every camera logs one row per frame there.
_CAMERA_DETECTED = {
    fixed: re.compile("^" + re.escape(paths.detected("\0", fixed)).replace("\x00", "(?P<cam>[^/]+)") + "$")
    for fixed in (False, True)
}



# -- reading runs --------------------------------------------------------------------------
def cameras_of(contents: RrdContents) -> list[str]:
    """Names of the cameras whose corners a run ``.rrd`` holds, sorted: those on the AGV and
    those fixed in the world (:func:`fixed_cameras_of` tells which)."""
    return sorted({
        m["cam"] for p in contents.entity_paths for pattern in _CAMERA_DETECTED.values() if (m := pattern.match(p))
    })


def fixed_cameras_of(contents: RrdContents) -> set[str]:
    """Names of the cameras fixed in the world (``world/cameras/cam_<name>``) whose corners a
    run ``.rrd`` holds: their images and corners are under :func:`paths.image` ``(cam, fixed=True)``."""
    return {m["cam"] for p in contents.entity_paths if (m := _CAMERA_DETECTED[True].match(p))}


def load_run(path: str | os.PathLike | RrdContents) -> RunSeries:
    """Read a run ``.rrd`` back into per-frame arrays (clock, solved, errors, poses).

    The frame clock comes from the detected-corner entities (logged on every frame) of the
    cameras on the AGV and of those fixed in the world (a camera–UWB run's wall cameras log
    every time stamp's views under one frame index), the solved frames from the estimated pose
    ``world/agv/camera``, the errors from ``errors/*`` and the settings from ``run/manifest``.

    In a camera–UWB run too, ``world/agv/camera`` and ``errors/position_mm`` are the camera
    pipeline's estimate of each frame (the chosen camera's fix), what the run summary's
    ``position_error_mm`` is computed from; the fused estimate (``errors/fused_position_mm``,
    2-D, per UWB fix and frame) is not part of the series (:func:`agvviz.app.diff.diff` notes its summary).

    Raises
    ------
    RrdReadError
        The file is not a run ``.rrd`` (no manifest, no camera frames).
    """
    contents = path if isinstance(path, RrdContents) else read_rrd(path)
    path = contents.path
    if paths.RUN_MANIFEST not in contents.entity_paths:
        index = sweep_index(contents)
        if index:
            raise RrdReadError(
                f"{path} is a sweep .rrd of {len(index)} settings: name one as {path}{SETTING_SEPARATOR}LABEL "
                f"(its settings: {', '.join(e['label'] for e in index)})"
            )
        raise RrdReadError(f"{path} is not an agvviz run: it has no {paths.RUN_MANIFEST}")
    manifest = document_json(contents, paths.RUN_MANIFEST)
    clock: dict[int, int] = {}
    fixed = fixed_cameras_of(contents)
    for cam in cameras_of(contents):
        clock.update(frame_times(contents, paths.detected(cam, cam in fixed), "Points2D:positions"))
    if not clock:
        raise RrdReadError(f"{path} holds no camera frames")
    frames = np.array(sorted(clock), dtype=np.int64)
    time_ns = np.array([clock[f] for f in frames], dtype=np.int64)
    where = {int(f): k for k, f in enumerate(frames)}

    def poses(entity: str) -> np.ndarray:
        T = np.full((len(frames), 4, 4), np.nan)
        if _has_temporal(contents, entity, "Transform3D:translation"):
            entity_frames, _, entity_T = transforms(contents, entity)
            for f, pose in zip(entity_frames, entity_T):
                if int(f) in where:
                    T[where[int(f)]] = pose
        return T

    T_est = poses(paths.AGV_CAMERA)
    errors = {}
    for key, (entity, scale) in ERROR_ENTITIES.items():
        values = np.full(len(frames), np.nan)
        if _has_temporal(contents, entity, "Scalars:scalars"):
            idx, series = scalar_series(contents, entity)
            for f, v in zip(idx, series):
                if int(f) in where:
                    values[where[int(f)]] = v * scale
        errors[key] = values
    return RunSeries(
        name=str(manifest.get("recording_name", Path(path).stem)),
        frames=frames,
        time_ns=time_ns,
        solved=np.all(np.isfinite(T_est.reshape(len(frames), 16)), axis=1),
        errors=errors,
        T_truth=poses(paths.AGV_TRUTH),
        T_est=T_est,
        settings=dict(manifest.get("settings", {})),
        manifest=manifest,
        summary=(document_json(contents, paths.RUN_SUMMARY) or {}) if paths.RUN_SUMMARY in contents.entity_paths else {},
    )


def _has_temporal(contents: RrdContents, entity: str, component: str) -> bool:
    """Whether ``entity`` has per-frame ``component`` data (run entities also carry static
    styles or axes, so their mere presence says nothing; a run may have solved no frame)."""
    if entity not in contents.entity_paths:
        return False
    chunks = contents.store.stream().filter(content=f"/{entity}", is_static=False, components=component)
    return any(chunk.num_rows > 0 for chunk in chunks)


def reprojected_corners(path: Path | RrdContents, cams: list[str]) -> dict[str, dict[int, np.ndarray]]:
    """Each camera's reprojected corners per frame of a run, the camera on the AGV or fixed in
    the world (as that run logged it)."""
    contents = path if isinstance(path, RrdContents) else read_rrd(path)
    fixed = fixed_cameras_of(contents)
    return {
        cam: points2d(contents, paths.reprojected(cam, cam in fixed))
        for cam in cams
        if paths.reprojected(cam, cam in fixed) in contents.entity_paths
    }



def overlay_errors(run: RunSeries, rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
    rows = np.arange(len(run.frames)) if rows is None else rows
    return {f"{q.key}_{q.unit}": run.errors[q.key][rows] for q in DIRECT}


def overlay_truth(run: RunSeries) -> OverlayTruth | None:
    known = np.all(np.isfinite(run.T_truth.reshape(len(run.frames), 16)), axis=1)
    if not np.any(known):
        return None
    return OverlayTruth(run.frames[known], run.time_ns[known], run.T_truth[known])


def image_clocks(contents: RrdContents) -> dict[str, list[tuple[int, int, int]]]:
    """Each camera's clock in a run: ``(frame, time_ns, elapsed_ns)`` of every frame it logged
    (its detected corners are logged on every frame), for :mod:`agvviz.viz.frames`."""
    fixed = fixed_cameras_of(contents)
    return {
        cam: frame_stamps(contents, paths.detected(cam, cam in fixed), "Points2D:positions")
        for cam in cameras_of(contents)
    }
