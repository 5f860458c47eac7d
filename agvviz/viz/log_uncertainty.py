"""The pose uncertainty of each frame in a run's ``.rrd``: NEES, position error ÷ CRLB, the CRLB
and covariance σ, the IPPE ambiguity ratio and branch flips, the 3σ covariance ellipsoid above
the body, and the rejected mirror pose (the ghost) when it is a real contender.

:class:`UncertaintyLogger` is one of the modality loggers a
:class:`agvviz.viz.run_logger.RunLogger` holds; its per-frame values go through the run's
:class:`agvviz.viz.columns.Columns`.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr

from agvviz.geometry import se3
from agvviz.model.frames import FrameResult
from agvviz.viz import paths
from agvviz.viz.columns import Columns, Stamp
from agvviz.viz.log_frames import AGV_BODY_CENTER_M, AGV_BODY_HALF_SIZES_M, agv_body, transform3d
from agvviz.viz.style import COLOR_CAMERA, COLOR_GHOST, COLOR_REPROJECTED, COLOR_THRESHOLD, COLOR_TRUTH

#: The 3σ position ellipsoid is drawn magnified by this one factor in every run (docs/uncertainty.md):
#: on the ``typical`` qr_floor (σ ≈ 5 mm with ``covariance=full``) its 3σ half-axes come out
#: ≈ 0.15 m, beside a 0.6 × 0.8 m body; a 1 mm σ draws 3 cm, a 50 mm σ 1.5 m. Its label and
#: the 3D view's title give it.
COV_MAGNIFICATION = 10.0
#: χ² 99 % quantiles by degrees of freedom (the NEES view's bound: a consistent covariance
#: leaves 1 % of frames above it); 6 for a 6-DoF pose, 3 for ``planar``.
CHI2_99 = {3: 11.344867, 6: 16.811894}
#: Ambiguity ratios above this are plotted at this value (exact fits give inf).
AMBIGUITY_RATIO_CAP = 100.0
#: The rejected IPPE mirror pose (the ghost) is drawn only when the ambiguity ratio
#: rms(mirror) / rms(chosen) is below this. With a code's 4 corners each pose leaves 2 residual
#: degrees of freedom; were both poses equally right, the cost ratio (ratio²) would follow
#: F(2, 2), P(F ≥ f) = 1 / (1 + f): a ratio of 4 (cost ratio 16) still happens by noise alone
#: in 1/17 ≈ 6 % of frames. Below it the data cannot reject the mirror pose at about the 5 %
#: level — a real contender; above it the mirror pose is no contender and is not drawn.
GHOST_MAX_AMBIGUITY_RATIO = 4.0
#: The covariance ellipsoid is drawn this far above the body's top (m), so the opaque-looking
#: body never hides it.
COV_ABOVE_BODY_M = 0.05

#: Per-frame uncertainty series: (entity, legend name, colour).
UNCERTAINTY_SERIES = (
    (paths.ERROR_NEES, "NEES", COLOR_CAMERA),
    (paths.ERROR_NEES_EXPECTED, "expected NEES: dof (χ² mean)", COLOR_TRUTH),
    (paths.ERROR_POSITION_OVER_CRLB, "position error ÷ CRLB", COLOR_REPROJECTED),
    (paths.ERROR_CRLB_POSITION_M, "CRLB position [m]", COLOR_TRUTH),
    (paths.ERROR_POSITION_SIGMA_M, "covariance position σ [m]", COLOR_CAMERA),
    (paths.SOLVER_AMBIGUITY_RATIO, f"IPPE ambiguity ratio (capped at {AMBIGUITY_RATIO_CAP:g})", COLOR_GHOST),
)


class UncertaintyLogger:
    """Logs each frame's uncertainty into ``rec`` (per-frame values into ``columns``)."""

    def __init__(self, rec: rr.RecordingStream, columns: Columns):
        self._rec = rec
        self._columns = columns
        #: The ellipsoid's magnification, :data:`COV_MAGNIFICATION` once one was drawn (else None).
        self.cov_scale: float | None = None
        self._ghost_drawn = False  # the previous frame left the ghost drawn

    def log_styles(self) -> None:
        """The static styles of the uncertainty series and of the ellipsoid."""
        rec = self._rec
        for entity, name, color in UNCERTAINTY_SERIES:
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        rec.log(
            paths.ERROR_NEES_BOUND_99,
            rr.SeriesLines(names="χ²(dof) 99 % bound (above: inconsistent)", colors=COLOR_THRESHOLD, widths=1.0),
            static=True,
        )
        rec.log(
            paths.AGV_CAMERA_POSITION_COV,
            rr.Ellipsoids3D.from_fields(
                # The label (σ in mm) shows on hover: on screen it covered the code ids beside the body,
                # and the 3D view's title already says "position 3σ ×10".
                colors=COLOR_CAMERA, fill_mode=rr.components.FillMode.MajorWireframe, show_labels=False
            ),
            static=True,
        )

    def log(self, frame: FrameResult, stamp: Stamp) -> None:
        """NEES, error ÷ CRLB, ambiguity ratio, flips, the covariance ellipsoid and the ghost."""
        rec = self._rec
        columns = self._columns
        for entity, value in (
            (paths.ERROR_NEES, frame.nees),
            (paths.ERROR_POSITION_OVER_CRLB, frame.position_over_crlb),
            (paths.ERROR_CRLB_POSITION_M, frame.crlb_position_m),
            (paths.ERROR_POSITION_SIGMA_M, frame.position_sigma_m),
        ):
            if not frame.solved:  # a rejected frame has no value: the line breaks
                columns.gap(entity, stamp)
            elif value is not None and math.isfinite(value):
                columns.scalar(entity, stamp, value)
        if frame.solved and frame.nees is not None and frame.nees_dof in CHI2_99:
            columns.scalar(paths.ERROR_NEES_EXPECTED, stamp, float(frame.nees_dof))
            columns.scalar(paths.ERROR_NEES_BOUND_99, stamp, CHI2_99[frame.nees_dof])
        if not frame.solved:  # the ambiguity of a pose that was rejected is no value of the run
            columns.gap(paths.SOLVER_AMBIGUITY_RATIO, stamp)
        elif frame.ambiguity_ratio is not None:
            columns.scalar(paths.SOLVER_AMBIGUITY_RATIO, stamp, min(float(frame.ambiguity_ratio), AMBIGUITY_RATIO_CAP))
        if frame.flipped and frame.solved:
            rec.log(
                paths.EVENTS_FLIPS,
                rr.TextLog(
                    f"frame {frame.index}: pose flipped to the branch the previous frame rejected "
                    f"(ambiguity ratio {frame.ambiguity_ratio:.2f}, chosen by {frame.ambiguity_rule})",
                    level=rr.TextLogLevel.WARN,
                ),
            )
        if frame.solved and frame.position_cov_world_m2 is not None:
            self.cov_scale = COV_MAGNIFICATION
            columns.row(paths.AGV_CAMERA_POSITION_COV, "ellipsoid", stamp, *_covariance_ellipsoid(frame, self.cov_scale))
        else:
            columns.gap(paths.AGV_CAMERA_POSITION_COV, stamp)
        ratio = frame.ambiguity_ratio
        if frame.solved and frame.T_world_agv_ghost is not None and ratio is not None and ratio < GHOST_MAX_AMBIGUITY_RATIO:
            rec.log(paths.AGV_GHOST, transform3d(np.asarray(frame.T_world_agv_ghost, dtype=float)))
            label = f"IPPE mirror pose: ambiguity ratio {ratio:.2f} < {GHOST_MAX_AMBIGUITY_RATIO:g}"
            rec.log(paths.AGV_GHOST_BODY, agv_body(COLOR_GHOST, label))
            self._ghost_drawn = True
        elif self._ghost_drawn:
            rec.log(paths.AGV_GHOST_BODY, rr.Clear(recursive=False))
            self._ghost_drawn = False


def _covariance_ellipsoid(frame: FrameResult, scale: float) -> tuple[np.ndarray, tuple, np.ndarray, str]:
    """The 3σ position ellipsoid magnified ×``scale`` in the AGV frame, centred
    COV_ABOVE_BODY_M above the body's top (its colour and fill are static): half sizes, centre,
    quaternion (xyzw) and label."""
    R_world_agv = np.asarray(frame.T_world_agv, dtype=float)[:3, :3]
    cov_agv = R_world_agv.T @ np.asarray(frame.position_cov_world_m2, dtype=float) @ R_world_agv
    cov_agv = 0.5 * (cov_agv + cov_agv.T)
    eigenvalues, axes = np.linalg.eigh(cov_agv)
    if np.linalg.det(axes) < 0:
        axes[:, 0] = -axes[:, 0]
    sigma_mm = 1000.0 * math.sqrt(max(float(np.sum(eigenvalues)), 0.0))
    half_z_m = 3.0 * scale * math.sqrt(max(float(cov_agv[2, 2]), 0.0))
    top_m = AGV_BODY_CENTER_M[2] + AGV_BODY_HALF_SIZES_M[2]
    return (
        3.0 * scale * np.sqrt(np.clip(eigenvalues, 0.0, None)),
        (0.0, 0.0, top_m + COV_ABOVE_BODY_M + half_z_m),
        np.asarray(se3.to_quaternion_xyzw(axes), dtype=float),
        f"position 3σ ×{scale:g} (σ = {sigma_mm:.2f} mm), drawn above the body",
    )

