"""``agvviz audit``: what a whole run says about the marker map and the camera calibration.

A bundle adjustment over every frame of a recording (:mod:`agvviz.evaluation.audit.problem`): unknowns are
each frame's vehicle pose, each camera's extrinsic correction, each marker's placement
correction (x, y, yaw and print scale for floor codes; 6-DoF and scale otherwise), each
marker's systematic corner error (a random effect) and the odometry's scale and heading drift;
measurements are every detected corner, the odometry between frames and the vehicle's level
(the floor it drives on, or an AUV's depth and attitude); priors are the recorded calibration
and map. Solved with ``scipy.optimize.least_squares`` on the sparse Jacobian pattern; marginal
covariances of the marker and camera blocks from a sparse LU of JᵀJ; gauge fixed on the well
seen, unflagged markers. See :mod:`agvviz.evaluation.audit.estimate` for the flags.

:func:`audit_recording` is the library entry (returns values, prints nothing);
:func:`write_outputs` writes the ``.rrd``, the corrected marker map and the extrinsic option file.
The math (:mod:`.problem`, :mod:`.estimate`, :mod:`.synthetic`) does no I/O.

Observability, in short: with one code per frame, a marker's placement is seen only through the
odometry between frames that see different codes (and through frames that see two codes at
once); its print scale through the camera height the floor fixes; the camera's pitch, roll and
height through the floor (the vehicle's own height, pitch and roll are ~0), its yaw through the
direction the odometry says the vehicle moves, its x, y through turns (hand-eye). A group of a
marker's correction whose posterior σ stays near its prior σ is *not observed* and not judged; a
marker seen in few frames, or with no group observed, is reported as *seen too little* and never
flagged.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from agvviz.app.audit_collect import Collected, collect
from agvviz.evaluation.audit.estimate import AuditEstimate, CameraFinding, MarkerFinding, estimate
from agvviz.evaluation.audit.problem import AuditData, AuditSettings, audit_setting_names
from agvviz.settings import RunSettings

__all__ = [
    "AuditData", "AuditEstimate", "AuditResult", "AuditSettings", "CameraFinding", "MarkerFinding",
    "audit_recording", "audit_setting_names", "default_paths", "split_settings", "write_outputs",
]


@dataclass
class AuditResult:
    """An audit of one recording: the findings and where they came from."""

    recording: Path
    estimate: AuditEstimate
    collected: Collected
    run_settings: RunSettings
    settings: AuditSettings
    collect_s: float
    total_s: float
    written: dict = field(default_factory=dict)  # what -> Path, after write_outputs

    @property
    def markers(self) -> list[MarkerFinding]:
        return self.estimate.markers

    @property
    def cameras(self) -> list[CameraFinding]:
        return self.estimate.cameras

    def marker(self, marker_id: str) -> MarkerFinding:
        return next(f for f in self.estimate.markers if f.marker_id == marker_id)

    @property
    def title(self) -> str:
        return f"audit of {self.recording.name}"


def split_settings(pairs: list[str]) -> tuple[list[str], list[str]]:
    """``--set`` pairs of :class:`AuditSettings` and the rest (run settings)."""
    names = audit_setting_names()
    audit, run = [], []
    for pair in pairs:
        key = pair.partition("=")[0].strip()
        (audit if key in names else run).append(pair)
    return audit, run


def solve_pose_of(settings: RunSettings):
    """The run's single-marker solver as ``solve_pose(points, px, K)`` for the audit's start
    (``planar`` needs a prior the audit does not have: ``lm`` then)."""
    from agvviz.solvers import SolverOptions, solve

    name = settings.solver if settings.solver != "planar" else "lm"
    options = SolverOptions(objective=settings.objective, max_iterations=settings.lm_max_iterations)

    def solve_pose(points_marker_m, pixels_px, K):
        result = solve(name, points_marker_m, pixels_px, K, options)
        return result.T_cam_marker if result.success else None

    return solve_pose


def audit_recording(
    recording: Path,
    run_settings: RunSettings | None = None,
    settings: AuditSettings | None = None,
    *,
    side=None,
    topics: dict[str, str] | None = None,
    roles_file: Path | None = None,
    jobs: int | None = None,
    cache_dir=None,
    progress: Callable[[int], None] | None = None,
) -> AuditResult:
    """Audit ``recording`` (module docstring). Raises an :class:`~agvviz.errors.AgvvizError`
    (one line) for input it cannot audit: no detections, one frame, NaN, an unknown camera."""
    t0 = time.perf_counter()
    run_settings = run_settings or RunSettings()
    settings = settings or AuditSettings()
    collected = collect(Path(recording), run_settings, side=side, topics=topics, roles_file=roles_file,
                        jobs=jobs, cache_dir=cache_dir, progress=progress)
    t1 = time.perf_counter()
    found = estimate(collected.data, settings, solve_pose_of(run_settings))
    return AuditResult(Path(recording), found, collected, run_settings, settings, t1 - t0, time.perf_counter() - t0)


def default_paths(recording: Path, out: Path | None) -> dict[str, Path]:
    """The outputs: the ``.rrd`` and beside it ``<stem>-markers.yaml`` and ``<stem>-extrinsic.txt``."""
    recording = Path(recording)
    rrd = Path(out) if out is not None else Path("runs") / f"{recording.stem}-audit.rrd"
    return {
        "rrd": rrd,
        "markers": rrd.with_name(f"{rrd.stem}-markers.yaml"),
        "extrinsic": rrd.with_name(f"{rrd.stem}-extrinsic.txt"),
    }


def write_outputs(result: AuditResult, paths: dict[str, Path], which: str = "flagged") -> dict[str, Path]:
    """Write the ``.rrd`` (:mod:`agvviz.viz.log_audit`), the corrected marker map (YAML, the
    ``which`` markers moved, :func:`agvviz.evaluation.audit.report.corrected_marker_map`) and the extrinsic
    option file (one ``CAM=x,y,z,qx,qy,qz,qw`` line per camera: the estimate for a flagged camera,
    the recorded value otherwise), each atomically and never over an input."""
    import yaml

    from agvviz.recording import outputs
    from agvviz.evaluation.audit import report
    from agvviz.viz.log_audit import write_audit_rrd

    inputs = [result.recording] + (sorted(result.recording.iterdir()) if result.recording.is_dir() else [])
    written = {}
    for key in ("rrd", "markers", "extrinsic"):
        outputs.prepare_output(paths[key], inputs=inputs)
    written["rrd"] = write_audit_rrd(paths["rrd"], result, recording_key(result))
    if result.collected.marker_map is not None:
        corrected, moved = report.corrected_marker_map(result.collected.marker_map, result.estimate, which)
        header = (f"# agvviz audit of {result.recording.name}: marker map with {len(moved)} marker(s) moved to their "
                  f"estimated placement ({', '.join(moved) or 'none'}); use with agvviz run --markers\n")
        written["markers"] = outputs.atomic_write_text(paths["markers"], header + yaml.safe_dump(corrected, sort_keys=False),
                                                       inputs=inputs)
    lines = [report.extrinsic_option(c, estimated=c.flagged) for c in result.estimate.cameras]
    written["extrinsic"] = outputs.atomic_write_text(paths["extrinsic"], "\n".join(lines) + "\n", inputs=inputs)
    for c in result.estimate.cameras:  # intrinsics solved: a calibration file per camera
        if c.intrinsics is None or c.cam_name not in result.collected.cameras:
            continue
        target = paths["rrd"].with_name(f"{paths['rrd'].stem}-calibration-{c.cam_name}.yaml")
        outputs.prepare_output(target, inputs=inputs)
        written[f"calibration {c.cam_name}"] = outputs.atomic_write_text(
            target, report.calibration_yaml(result.collected.cameras[c.cam_name], c), inputs=inputs)
    result.written = written
    return written


def recording_key(result: AuditResult) -> str:
    return hashlib.sha256(f"{result.collected.recording_sha256}:{result.settings}".encode()).hexdigest()
