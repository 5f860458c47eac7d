"""An audit's findings as table rows, markdown and the corrected side files.

* :func:`marker_rows` / :func:`camera_rows` — the terminal table's rows (strings);
* :func:`markdown` — the same as markdown, for the ``.rrd``;
* :func:`corrected_marker_map` — the marker map with the flagged markers moved to their
  estimated placement (a side file ``agvviz run --markers`` accepts; a corrected QR code loses its
  ``payload`` entry: its printed payload still says the old placement, which the map no longer
  agrees with — the run then refuses that code's payload, which is the point: re-lay or reprint it);
* :func:`extrinsic_option` — ``CAM=x,y,z,qx,qy,qz,qw`` for ``agvviz run --extrinsic``;
* :func:`calibration_yaml` — a ROS camera_info YAML for ``agvviz run --calibration`` (when the
  intrinsics were solved).

No files are written here (:func:`agvviz.app.audit.write_outputs` does, atomically).
"""

from __future__ import annotations

import copy
import math
import re

import numpy as np

from agvviz.evaluation.audit.estimate import AuditEstimate, CameraFinding, MarkerFinding
from agvviz.geometry import se3

MARKER_COLUMNS = ("marker", "status", "frames", "dx (mm)", "dy (mm)", "yaw (deg)", "scale (%)", "other", "why")
CAMERA_COLUMNS = ("camera", "status", "dx (mm)", "dy (mm)", "dz (mm)", "rot x/pitch (deg)", "rot y/roll (deg)", "rot z/yaw (deg)", "why")


def _pm(value: float, sigma: float, unit_scale: float, digits: int) -> str:
    if not math.isfinite(value):
        return "—"
    if not math.isfinite(sigma):
        return f"{value * unit_scale:+.{digits}f}"
    return f"{value * unit_scale:+.{digits}f} ± {sigma * unit_scale:.{digits}f}"


def _why(f) -> str:
    if f.status == "seen too little":
        return f.seen_little_why if isinstance(f, MarkerFinding) else ""
    parts = []
    for group in f.reasons:
        parts.append(f"{group} {f.distances.get(group, float('nan')):.1f}σ")
    if isinstance(f, MarkerFinding) and f.unobserved:
        parts.append(f"{'/'.join(f.unobserved)} not observed")
    text = ", ".join(parts)
    if isinstance(f, MarkerFinding) and f.init_gross is not None:
        text += ("; " if text else "") + f"start: grossly off ({f.init_gross[0]:+.0f}°)"
    return text


def _natural(marker_id: str) -> tuple:
    """Sort key: ids by their numbers (2 before 10, Q9 before Q10), then by text."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", marker_id) if part)


def marker_rows(estimate: AuditEstimate) -> list[tuple[str, ...]]:
    """One row per marker: flagged first, then ok, then seen too little; by id within."""
    order = {"flagged": 0, "ok": 1, "seen too little": 2}
    rows = []
    for f in sorted(estimate.markers, key=lambda f: (order[f.status], _natural(f.marker_id))):
        d, s = f.delta, f.sigma
        tilt = f"tilt {_pm(d[4], s[4], 180 / math.pi, 2)}/{_pm(d[5], s[5], 180 / math.pi, 2)}°"
        other = tilt if f.floor else f"dz {_pm(d[2], s[2], 1e3, 1)} mm, {tilt}"
        rows.append((
            f.marker_id, f.status, str(f.frames), _pm(d[0], s[0], 1e3, 1), _pm(d[1], s[1], 1e3, 1),
            _pm(d[3], s[3], 180 / math.pi, 2), _pm(d[6], s[6], 100.0, 2), other, _why(f),
        ))
    return rows


def camera_rows(estimate: AuditEstimate) -> list[tuple[str, ...]]:
    rows = []
    for c in estimate.cameras:
        e, s = c.correction, c.sigma
        rows.append((
            c.cam_name, c.status, *(_pm(e[k], s[k], 1e3, 1) for k in range(3)),
            *(_pm(e[k], s[k], 180 / math.pi, 3) for k in range(3, 6)), _why(c),
        ))
    return rows


def summary_lines(estimate: AuditEstimate) -> list[str]:
    e = estimate
    flagged = [f.marker_id for f in e.markers if f.flagged]
    little = [f.marker_id for f in e.markers if f.status == "seen too little"]
    lines = [
        f"markers: {len(e.markers)} seen, {len(flagged)} flagged ({', '.join(flagged) or 'none'}), "
        f"{len(little)} seen too little ({', '.join(little) or 'none'})",
        f"cameras flagged: {', '.join(c.cam_name for c in e.cameras if c.flagged) or 'none'}",
        f"corner σ {e.sigma_px:.3f} px; σ0 {e.sigma0:.2f} (covariances × max(1, σ0²)); "
        f"{e.n_params} unknowns, {e.n_residuals} residuals, {e.iterations} evaluations, {e.solve_s:.2f} s",
    ]
    if e.odometry is not None:
        o = e.odometry
        lines.append(f"odometry: scale error {o['scale'] * 100:+.2f} ± {o['scale_sigma'] * 100:.2f} %, heading drift "
                     f"{o['bias_deg_per_s']:+.3f} ± {o['bias_sigma_deg_per_s']:.3f} deg/s")
    for c in e.cameras:
        if c.intrinsics is not None:
            parts = ", ".join(f"{n} {_pm(v, sg, 1.0, 2)}" for n, v, sg in zip(("dfx", "dfy", "dcx", "dcy"), c.intrinsics,
                                                                              c.intrinsics_sigma))
            lines.append(f"camera {c.cam_name} intrinsics (px): {parts}")
    lines.append(f"gauge: {e.gauge}")
    lines.extend(f"note: {m}" for m in e.messages)
    return lines


def markdown(estimate: AuditEstimate, title: str) -> str:
    def table(columns, rows):
        out = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        out += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(out)

    parts = [f"# {title}", "", *(f"- {line}" for line in summary_lines(estimate)), "",
             "## Cameras (correction recorded → estimated, AGV frame)", "", table(CAMERA_COLUMNS, camera_rows(estimate)),
             "", "## Markers (placement error: true − mapped)", "", table(MARKER_COLUMNS, marker_rows(estimate))]
    return "\n".join(parts) + "\n"


def corrected_marker_map(marker_map: dict, estimate: AuditEstimate, which: str = "flagged") -> tuple[dict, list[str]]:
    """The marker map with the ``which`` ("flagged" or "all" estimated, never "seen too
    little") markers at their estimated corners and printed side. Returns (map, ids moved)."""
    out = copy.deepcopy(marker_map)
    by_id = {f.marker_id: f for f in estimate.markers}
    moved = []
    for entry in out.get("markers", []):
        f = by_id.get(str(entry.get("id")))
        if f is None or f.status == "seen too little" or (which == "flagged" and not f.flagged):
            continue
        entry["corners_world_m"] = np.round(f.corners_world_estimated, 6).tolist()
        entry["side_m"] = round(float(f.side_mapped_m * (1.0 + f.delta[6])), 6)
        entry.pop("payload", None)
        moved.append(f.marker_id)
    return out, moved


def extrinsic_option(camera: CameraFinding, estimated: bool = True) -> str:
    """``CAM=x,y,z,qx,qy,qz,qw`` of the estimated (or recorded) ``T_body_cam``."""
    T = camera.T_agv_cam_estimated if estimated else camera.T_agv_cam_recorded
    q = se3.to_quaternion_xyzw(T)
    values = list(T[:3, 3]) + list(q)
    return f"{camera.cam_name}=" + ",".join(f"{v:.9g}" for v in values)


def calibration_yaml(camera, finding: CameraFinding) -> str:
    """A ROS ``camera_info`` YAML (``agvviz run --calibration CAM=FILE``) of ``camera`` (the
    calibration in use, :class:`agvviz.geometry.PinholeCamera`) with ``finding``'s solved
    intrinsics corrections applied (distortion as recorded)."""
    K = np.array(camera.K, dtype=float)
    if finding.intrinsics is not None:
        K[0, 0] += finding.intrinsics[0]
        K[1, 1] += finding.intrinsics[1]
        K[0, 2] += finding.intrinsics[2]
        K[1, 2] += finding.intrinsics[3]
    D = [float(v) for v in np.asarray(camera.dist, dtype=float).ravel()]
    lines = [
        f"image_width: {int(camera.width_px)}",
        f"image_height: {int(camera.height_px)}",
        f"camera_name: {finding.cam_name}",
        "camera_matrix:",
        "  rows: 3",
        "  cols: 3",
        f"  data: [{', '.join(f'{v:.9g}' for v in K.ravel())}]",
        f"distortion_model: {'plumb_bob' if len(D) <= 5 else 'rational_polynomial'}",
        "distortion_coefficients:",
        "  rows: 1",
        f"  cols: {len(D)}",
        f"  data: [{', '.join(f'{v:.9g}' for v in D)}]",
    ]
    return "\n".join(lines) + "\n"
