"""Write an audit (:mod:`agvviz.app.audit`) into an ``.rrd`` of its own; its layout is
:func:`agvviz.viz.blueprints.audit_blueprint`.

Entity tree (:mod:`agvviz.viz.paths`, block "agvviz audit"; timelines ``frame``, ``time`` and
``elapsed``, seconds since the recording's first frame: the layout's plots are against it)::

    world                                   ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/audit/markers/recorded            outlines as mapped (marker blue), labelled by id
    world/audit/markers/estimated           outlines as estimated: flagged red and thick,
                                            ok "corrected" magenta, seen too little grey
    world/audit/markers/flagged             a large point + label just beyond every flagged
                                            marker's far edge (clear of its id)
    world/audit/markers/shift               arrow mapped → estimated centre of each flagged marker
    world/audit/trajectory/estimated|start|truth   the solved vehicle path, the start, truth
    world/audit/agv                         Transform3D per frame: the solved vehicle pose
    world/audit/agv/cam_<name>/recorded|estimated  the camera's mounting as recorded / estimated
    audit/report                            TextDocument: the audit table (markdown)
    audit/residuals/<marker>                Scalars per frame: RMS corner residual (px)
    audit/odometry/xy_mm|heading_deg        Scalars per frame: odometry step residuals

Written atomically with an explicit recording stream (:class:`agvviz.viz.rrd_file.AtomicRrd`).
"""

from __future__ import annotations

import math
import os
import uuid
from pathlib import Path

import numpy as np
import rerun as rr

from agvviz.viz import paths, style
from agvviz.viz.blueprints import PlotAxis, audit_blueprint, plot_axis
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.timelines import elapsed_s

#: Width of flagged outlines vs the others (m).
FLAGGED_RADIUS_M = 0.012
OUTLINE_RADIUS_M = 0.004


def _outline(corners: np.ndarray) -> np.ndarray:
    return np.vstack([corners, corners[:1]])


def _send_scalars(rec: rr.RecordingStream, entity: str, frames: np.ndarray, stamps_ns: np.ndarray, values: np.ndarray,
                  start_ns: int) -> None:
    ok = np.isfinite(values)
    if not np.any(ok):
        return
    rec.send_columns(
        entity,
        indexes=[
            rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.asarray(frames[ok], dtype=np.int64)),
            rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.asarray(stamps_ns[ok], dtype="datetime64[ns]")),
            rr.TimeColumn(paths.TIMELINE_ELAPSED, duration=[elapsed_s(t, start_ns) for t in stamps_ns[ok]]),
        ],
        columns=rr.Scalars.columns(scalars=np.asarray(values[ok], dtype=float)),
    )


def log_audit(rec: rr.RecordingStream, result) -> None:
    """Log ``result`` (:class:`agvviz.app.audit.AuditResult`) into ``rec``."""
    from agvviz.evaluation.audit import report

    est, col = result.estimate, result.collected
    data = col.data
    rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(paths.AUDIT_REPORT, rr.TextDocument(report.markdown(est, result.title), media_type=rr.MediaType.MARKDOWN),
            static=True)
    markers = est.markers
    rec.log(paths.AUDIT_MARKERS_RECORDED, rr.LineStrips3D(
        [_outline(f.corners_world_mapped) for f in markers], colors=style.COLOR_MARKER, radii=OUTLINE_RADIUS_M,
        labels=[f.marker_id for f in markers], show_labels=True), static=True)
    colors = [style.COLOR_FLAGGED if f.flagged else (style.COLOR_SEEN_TOO_LITTLE if f.status == "seen too little" else style.COLOR_OK)
              for f in markers]
    radii = [FLAGGED_RADIUS_M if f.flagged else OUTLINE_RADIUS_M for f in markers]
    rec.log(paths.AUDIT_MARKERS_ESTIMATED, rr.LineStrips3D(
        [_outline(f.corners_world_estimated) for f in markers], colors=colors, radii=radii,
        labels=[f"{f.marker_id}: {f.status}" for f in markers], show_labels=False), static=True)
    flagged = [f for f in markers if f.flagged]
    if flagged:
        centres = np.array([f.corners_world_estimated.mean(axis=0) for f in flagged])
        mapped = np.array([f.corners_world_mapped.mean(axis=0) for f in flagged])
        labels = [f"{f.marker_id}: {', '.join(f.reasons)}" for f in flagged]
        rec.log(paths.AUDIT_MARKERS_FLAGGED, rr.Points3D(flag_positions(flagged), colors=style.COLOR_FLAGGED, radii=0.05,
                                                         labels=labels, show_labels=True), static=True)
        rec.log(paths.AUDIT_MARKERS_SHIFT, rr.Arrows3D(origins=mapped + [0, 0, 0.01], vectors=centres - mapped,
                                                       colors=style.COLOR_FLAGGED, radii=0.006), static=True)
    T = est.T_world_agv
    rec.log(paths.AUDIT_TRAJECTORY_ESTIMATED, rr.LineStrips3D([T[:, :3, 3]], colors=style.COLOR_CORRECTED, radii=0.01,
                                                              labels=["audit: solved vehicle path"], show_labels=False), static=True)
    rec.log(paths.AUDIT_TRAJECTORY_START, rr.LineStrips3D([est.T_world_agv_start[:, :3, 3]], colors=style.COLOR_CAMERA,
                                                          radii=0.004, labels=["start (per-frame solve)"], show_labels=False), static=True)
    truth_ok = np.isfinite(col.truth[:, 0, 0])
    if np.any(truth_ok):
        rec.log(paths.AUDIT_TRAJECTORY_TRUTH, rr.LineStrips3D([col.truth[truth_ok, :3, 3]], colors=style.COLOR_TRUTH,
                                                              radii=0.004, labels=["truth"], show_labels=False), static=True)
    for c in est.cameras:
        for which, T_agv_cam, color in (("recorded", c.T_agv_cam_recorded, style.COLOR_MARKER),
                                        ("estimated", c.T_agv_cam_estimated,
                                         style.COLOR_FLAGGED if c.flagged else style.COLOR_OK)):
            entity = paths.audit_camera(c.cam_name, which)
            rec.log(entity, rr.Transform3D(translation=T_agv_cam[:3, 3], mat3x3=T_agv_cam[:3, :3]), static=True)
            rec.log(entity, rr.TransformAxes3D(0.3), static=True)
            rec.log(paths.audit_camera_label(c.cam_name, which), rr.Points3D([[0, 0, 0]], colors=color, radii=0.03, labels=[f"{c.cam_name} {which}"],
                                                   show_labels=False), static=True)
    frames = col.frame_index
    stamps = data.stamps_ns
    start_ns = int(stamps[0]) if len(stamps) else 0
    for k in range(len(frames)):
        rec.set_time(paths.TIMELINE_FRAME, sequence=int(frames[k]))
        rec.set_time(paths.TIMELINE_TIME, timestamp=np.datetime64(int(stamps[k]), "ns"))
        rec.set_time(paths.TIMELINE_ELAPSED, duration=elapsed_s(int(stamps[k]), start_ns))
        rec.log(paths.AUDIT_AGV, rr.Transform3D(translation=T[k, :3, 3], mat3x3=T[k, :3, :3]))
    rec.reset_time()
    # per-marker RMS corner residual per frame
    rms = corner_rms_px(est)
    for m, f in enumerate(markers):
        sel = np.flatnonzero(data.obs_marker == m)
        if not len(sel):
            continue
        i = data.obs_frame[sel]
        order = np.argsort(i, kind="stable")
        # one colour per verdict, not per marker: flagged markers red, the others grey
        flagged = f.flagged
        rec.log(paths.audit_marker_residual(f.marker_id),
                rr.SeriesLines(names=f"{f.marker_id}{' (flagged)' if flagged else ''}",
                               colors=style.COLOR_FLAGGED if flagged else style.COLOR_SEEN_TOO_LITTLE,
                               widths=2.0 if flagged else 1.0), static=True)
        _send_scalars(rec, paths.audit_marker_residual(f.marker_id), frames[i[order]], stamps[i[order]], rms[sel][order], start_ns)
    # odometry step residuals, from consecutive solved poses
    for entity, (odo_frames, odo_stamps, values) in odometry_residuals(result).items():
        _send_scalars(rec, entity, odo_frames, odo_stamps, values, start_ns)


def corner_rms_px(estimate) -> np.ndarray:
    """Each observation's RMS corner residual (px)."""
    r = estimate.corner_residuals_px
    return np.sqrt(np.mean(np.sum(r**2, axis=-1), axis=-1)) if len(r) else np.zeros(0)


def flag_positions(flagged) -> np.ndarray:
    """Where each flagged marker's point and label go: beside its estimated outline, past its far
    edge in +y (the label is centred on the point; on the marker it covered the marker's id)."""
    out = []
    for f in flagged:
        corners = np.asarray(f.corners_world_estimated, dtype=float)
        centre = corners.mean(axis=0)
        half_m = 0.5 * float(np.ptp(corners[:, 1]))
        out.append(centre + [0.0, half_m + 0.12, 0.02])
    return np.array(out)


def odometry_residuals(result) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each odometry step residual series: entity → (frame, stamp ns, value) of each step between
    consecutive frames with odometry — position (mm) and heading (deg), the odometry's estimated
    scale and drift taken out. Empty without odometry."""
    est, col = result.estimate, result.collected
    data = col.data
    T = est.T_world_agv
    if not data.has_odom.any() or len(T) < 2:
        return {}
    from agvviz.evaluation.audit.problem import planar
    from agvviz.geometry import se3

    pairs = np.flatnonzero(data.has_odom[:-1] & data.has_odom[1:])
    if not len(pairs):
        return {}
    stamps = data.stamps_ns
    step = se3.inverse_batch(T[pairs]) @ T[pairs + 1]
    odo = se3.inverse_batch(data.T_odom_agv[pairs]) @ data.T_odom_agv[pairs + 1]
    xy, psi = planar(step)
    oxy, opsi = planar(odo)
    scale = 1.0 + (est.odometry or {}).get("scale", 0.0)
    bias = math.radians((est.odometry or {}).get("bias_deg_per_s", 0.0))
    dt = (stamps[pairs + 1] - stamps[pairs]) * 1e-9
    r_xy = np.linalg.norm(oxy - scale * xy, axis=1) * 1e3
    r_psi = np.degrees(np.angle(np.exp(1j * (opsi - psi - bias * dt))))
    where = (col.frame_index[pairs + 1], stamps[pairs + 1])
    return {paths.AUDIT_ODOMETRY_XY_MM: (*where, r_xy), paths.AUDIT_ODOMETRY_HEADING_DEG: (*where, r_psi)}


def audit_axes(result) -> dict[str, PlotAxis]:
    """The plots' y axes (by view origin): every value inside (residual sizes from 0; the
    heading residual signed, its own extremes — Rerun's auto range showed a lone tick)."""
    axes = {}
    series = {entity: values for entity, (_, _, values) in odometry_residuals(result).items()}
    series[paths.AUDIT_RESIDUALS] = corner_rms_px(result.estimate)
    for entity, values in series.items():
        finite = values[np.isfinite(values)]
        if len(finite):
            lo, hi = float(finite.min()), float(finite.max())
            axis = plot_axis([(lo, hi)], include_zero=entity != paths.AUDIT_ODOMETRY_HEADING_DEG)
            span = axis.high - axis.low
            axes[entity] = PlotAxis(low=axis.low, high=hi + 0.05 * span, marker_y=axis.marker_y)
    return axes


def write_audit_rrd(out_path: str | os.PathLike, result, recording_key: str) -> Path:
    """Write ``result`` to ``out_path`` (temporary file beside it, renamed when complete);
    ``recording_key`` (the recording's hash and the audit settings) pins the recording id."""
    inputs = [result.recording] + (sorted(result.recording.iterdir()) if result.recording.is_dir() else [])
    with AtomicRrd(
        out_path,
        recording_id=str(uuid.uuid5(uuid.NAMESPACE_URL, f"agvviz-audit:{recording_key}")),
        recording_name=f"{result.collected.recording_name} audit",
        inputs=inputs,
    ) as rrd:
        log_audit(rrd.rec, result)
        return rrd.commit(audit_blueprint(result, audit_axes(result)))
