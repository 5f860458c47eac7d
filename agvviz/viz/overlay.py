"""Write one overlay ``.rrd`` that shows several runs of the same recording on one clock.

Used by ``agvviz diff`` (two runs, keys ``a`` and ``b``) and ``agvviz sweep`` (one key per
setting). Every run keeps its own ``time`` stamps; the ``frame`` timeline is the first run's
frame index (the callers map the other runs' frames onto it). Entity tree::

    world                                   ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/markers, world/markers/fill       marker map, copied from the first run (static)
    world/trajectory/truth                  LineStrips3D, whole truth trajectory (static)
    world/trajectory/<key>                  LineStrips3D, whole estimated trajectory of a run
    world/agv/truth                         Transform3D per frame + axes + body
    world/agv/<key>                         Transform3D per solved frame of a run + axes
    image/<cam>                             EncodedImage of the first run (copied, not re-encoded)
    image/<cam>/detected                    the first run's detected corners (copied)
    image/<cam>/<key>                       each run's reprojected corners (Points2D)
    errors/<quantity>/<key>                 Scalars per frame: position_mm, heading_deg, ...
    delta/<quantity>                        Scalars per frame, B − A of |error| (diff only)
    compare/report                          TextDocument: the comparison table (static)

Written like a run: explicit recording stream with a pinned id, no wall-clock timelines,
size-only chunking, streamed to a temporary file beside the target and renamed into place.
"""

from __future__ import annotations

from agvviz.errors import InputError

import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from agvviz.viz import paths
from agvviz.viz.readback import read_rrd
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.run_logger import (
    COLOR_DETECTED,
    COLOR_TRUTH,
    DETECTED_RADIUS,
    REPROJECTED_RADIUS,
)

IMAGE_ROOT = "image"
ERRORS_ROOT = "errors"
DELTA_ROOT = "delta"
REPORT = "compare/report"
TRUTH_POSE = "world/agv/truth"
TRUTH_TRAJECTORY = "world/trajectory/truth"

#: Per-frame quantities drawn, with their axis label (the unit is part of the key).
ERROR_LABELS = {
    "position_mm": "position error [mm]",
    "heading_deg": "heading error [deg]",
    "pitch_deg": "pitch error [deg]",
    "roll_deg": "roll error [deg]",
    "reproj_px": "reprojection RMS [px]",
}
#: Run colours in order, with their names for view titles.
PALETTE = (
    (255, 140, 0), (30, 144, 255), (255, 0, 200), (240, 220, 60),
    (170, 110, 255), (0, 200, 180), (230, 60, 60), (160, 230, 120),
)
PALETTE_NAMES = ("orange", "blue", "magenta", "yellow", "violet", "teal", "red", "light green")
AXIS_LENGTH_M = 0.4
TRUTH_BODY_HALF_SIZES_M = (0.30, 0.40, 0.10)


class OverlayError(InputError):
    """Overlay input that cannot be drawn (no run, inconsistent lengths, bad key)."""


@dataclass
class OverlayRun:
    """One run to draw.

    Attributes
    ----------
    key : str
        Entity name of the run: letters, digits, ``_`` and ``-`` only.
    label : str
        Shown in legends and the report.
    frames, time_ns : (N,) int64
        The run's frames on the overlay's ``frame`` timeline and their recording time.
    T_est : (N, 4, 4) float
        Estimated ``T_world_agv``; NaN on frames the run did not solve.
    errors : dict
        Key of :data:`ERROR_LABELS` → (N,) float, NaN where unknown.
    reprojected : dict
        Camera name → {overlay frame → (K, 2) reprojected corners in image pixels}.
    """

    key: str
    label: str
    frames: np.ndarray
    time_ns: np.ndarray
    T_est: np.ndarray
    errors: dict[str, np.ndarray] = field(default_factory=dict)
    reprojected: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)


@dataclass
class OverlayTruth:
    """Ground truth on the overlay clock: frames, time_ns (N,), ``T_world_agv`` (N, 4, 4)."""

    frames: np.ndarray
    time_ns: np.ndarray
    T_world_agv: np.ndarray


def color_of(index: int) -> tuple[int, int, int]:
    return PALETTE[index % len(PALETTE)]


def _indexes(frames: np.ndarray, time_ns: np.ndarray) -> list[rr.TimeColumn]:
    return [
        rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.asarray(frames, dtype=np.int64)),
        rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.asarray(time_ns, dtype=np.int64).astype("datetime64[ns]")),
    ]


def _send_transforms(rec: rr.RecordingStream, entity: str, frames, time_ns, T: np.ndarray) -> None:
    if len(T) == 0:
        return
    rec.send_columns(
        entity,
        indexes=_indexes(frames, time_ns),
        columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]),
    )


def _send_scalars(rec: rr.RecordingStream, entity: str, frames, time_ns, values: np.ndarray) -> None:
    ok = np.isfinite(values)
    if not np.any(ok):
        return
    rec.send_columns(
        entity,
        indexes=_indexes(np.asarray(frames)[ok], np.asarray(time_ns)[ok]),
        columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)[ok]),
    )


def _send_corners(
    rec: rr.RecordingStream, entity: str, frames, time_ns, corners: dict[int, np.ndarray], color
) -> None:
    """Reprojected corners on every frame of the run (an empty batch where there are none)."""
    per_frame = [np.asarray(corners.get(int(f), np.zeros((0, 2))), dtype=float).reshape(-1, 2) for f in frames]
    if not per_frame:
        return
    positions = np.concatenate(per_frame)
    rec.send_columns(
        entity,
        indexes=_indexes(frames, time_ns),
        columns=rr.Points2D.columns(positions=positions).partition([len(p) for p in per_frame]),
    )
    rec.log(entity, rr.Points2D.from_fields(colors=color, radii=REPROJECTED_RADIUS, draw_order=11.0), static=True)


def _check(runs: list[OverlayRun]) -> None:
    if not runs:
        raise OverlayError("an overlay needs at least one run")
    keys = [run.key for run in runs]
    if len(set(keys)) != len(keys):
        raise OverlayError(f"run keys must be unique, got {keys}")
    for run in runs:
        if not run.key or not all(c.isalnum() or c in "_-" for c in run.key):
            raise OverlayError(f"run key {run.key!r} must be letters, digits, '_' or '-'")
        n = len(run.frames)
        lengths = [len(run.time_ns), len(run.T_est)] + [len(v) for v in run.errors.values()]
        if any(length != n for length in lengths):
            raise OverlayError(f"run {run.key}: arrays must all have {n} entries (one per frame)")
        unknown = set(run.errors) - set(ERROR_LABELS)
        if unknown:
            raise OverlayError(f"run {run.key}: unknown error series {sorted(unknown)}; known: {sorted(ERROR_LABELS)}")


def _eye(truth: OverlayTruth | None) -> rrb.EyeControls3D | None:
    """A view from the south-west, above, that frames the whole truth trajectory."""
    if truth is None or len(truth.T_world_agv) == 0:
        return None
    positions = truth.T_world_agv[:, :3, 3]
    low, high = positions.min(axis=0), positions.max(axis=0)
    center = (low + high) / 2.0
    extent = max(float(np.max(high - low)), 2.0)
    return rrb.EyeControls3D(
        position=center + np.array([-0.35, -0.9, 0.9]) * extent,
        look_target=center,
        eye_up=(0.0, 0.0, 1.0),
    )


def overlay_blueprint(
    runs: list[OverlayRun],
    cam_names: list[str],
    deltas: list[str],
    truth: OverlayTruth | None = None,
) -> rrb.Blueprint:
    """Default layout: 3D trajectories and the image with every run's corners on top; error
    plots of all runs (and the per-frame differences) with the comparison report below.
    Opens paused, on the ``frame`` timeline."""
    if len(runs) <= 2:
        colors = ", ".join(f"{r.label} {PALETTE_NAMES[i % len(PALETTE_NAMES)]}" for i, r in enumerate(runs))
    else:
        colors = "each run in its colour of the plot legends"
    world = rrb.Spatial3DView(origin="world", name=f"world: truth green, {colors}", eye_controls=_eye(truth))
    if cam_names:
        images = [
            rrb.Spatial2DView(
                origin=f"{IMAGE_ROOT}/{cam}",
                name=f"camera {cam} (first run's image): detected cyan; reprojected {colors}",
            )
            for cam in cam_names
        ]
        image_panel = images[0] if len(images) == 1 else rrb.Tabs(*images)
        top = rrb.Horizontal(world, image_panel, column_shares=[0.5, 0.5])
    else:
        top = world
    legend = rrb.PlotLegend(visible=True, corner=rrb.Corner2D.RightTop)
    plots = [
        rrb.TimeSeriesView(origin=f"{ERRORS_ROOT}/position_mm", name=ERROR_LABELS["position_mm"], plot_legend=legend),
        rrb.Tabs(
            *[
                rrb.TimeSeriesView(origin=f"{ERRORS_ROOT}/{key}", name=ERROR_LABELS[key], plot_legend=legend)
                for key in ("heading_deg", "pitch_deg", "roll_deg", "reproj_px")
            ]
        ),
    ]
    if deltas:
        plots.append(
            rrb.Tabs(
                *[
                    rrb.TimeSeriesView(
                        origin=f"{DELTA_ROOT}/{key}",
                        name=f"Δ |{ERROR_LABELS[key].split(' [')[0]}| B − A [{key.rsplit('_', 1)[1]}]",
                        plot_legend=rrb.PlotLegend(visible=False),
                    )
                    for key in deltas
                ]
            )
        )
    bottom = rrb.Horizontal(
        *plots,
        rrb.TextDocumentView(origin=REPORT, name="comparison"),
        column_shares=[0.22] * len(plots) + [1.0 - 0.22 * len(plots)],
    )
    return rrb.Blueprint(
        rrb.Vertical(top, bottom, row_shares=[0.58, 0.42]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_FRAME, play_state="paused"),
        auto_views=False,
    )


def write_overlay(
    out_path: str | os.PathLike,
    *,
    recording_name: str,
    runs: list[OverlayRun],
    truth: OverlayTruth | None,
    source: str | os.PathLike | None,
    cam_names: list[str],
    report_markdown: str,
    deltas: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
    inputs: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Write the overlay ``.rrd`` atomically and return its path.

    Parameters
    ----------
    out_path : path
        Target ``.rrd``; its folder is created if needed. It must not be ``source`` or one
        of ``inputs`` (:class:`~agvviz.errors.OutputError`, also through links).
    recording_name : str
        Shown in the viewer, e.g. ``diff qr_floor-lm vs qr_floor-p4p``.
    runs : list of OverlayRun
        Drawn in this order and colour (:data:`PALETTE`).
    truth : OverlayTruth, optional
    source : path, optional
        Run ``.rrd`` (the first run's) whose marker map is copied, and the images and
        detected corners of ``cam_names``.
    cam_names : list of str
        Cameras whose images and corners are drawn; empty leaves the images out (a much
        smaller file).
    report_markdown : str
        The comparison table, shown next to the plots.
    deltas : dict, optional
        Key of :data:`ERROR_LABELS` → (frames, time_ns, values): per-frame B − A series.
    inputs : paths
        Other files the overlay is made from (the runs compared).
    """
    _check(runs)
    deltas = deltas or {}
    out_path = Path(out_path)
    if out_path.suffix != ".rrd":
        raise OverlayError(f"the overlay must be a .rrd file, got {out_path}")
    recording_id = str(uuid.uuid5(uuid.NAMESPACE_URL, f"agvviz-overlay:{recording_name}"))
    sources = tuple(inputs) + ((source,) if source is not None else ())
    with AtomicRrd(out_path, recording_id=recording_id, recording_name=recording_name, inputs=sources) as rrd:
        rec = rrd.rec
        _log_static(rec, runs, truth, report_markdown)
        if source is not None:
            _copy_from_source(rec, Path(source), cam_names)
            rrd.check()
        if truth is not None:
            _send_transforms(rec, TRUTH_POSE, truth.frames, truth.time_ns, truth.T_world_agv)
        for index, run in enumerate(runs):
            solved = np.all(np.isfinite(run.T_est.reshape(len(run.T_est), 16)), axis=1)
            _send_transforms(rec, f"world/agv/{run.key}", run.frames[solved], run.time_ns[solved], run.T_est[solved])
            for key, values in run.errors.items():
                _send_scalars(rec, f"{ERRORS_ROOT}/{key}/{run.key}", run.frames, run.time_ns, values)
            if source is not None:
                for cam in cam_names:
                    _send_corners(
                        rec, f"{IMAGE_ROOT}/{cam}/{run.key}", run.frames, run.time_ns,
                        run.reprojected.get(cam, {}), color_of(index),
                    )
        for key, (frames, time_ns, values) in deltas.items():
            _send_scalars(rec, f"{DELTA_ROOT}/{key}", frames, time_ns, values)
        rrd.commit(overlay_blueprint(runs, cam_names if source is not None else [], list(deltas), truth))
    return out_path


def _log_static(
    rec: rr.RecordingStream, runs: list[OverlayRun], truth: OverlayTruth | None, report_markdown: str
) -> None:
    rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(REPORT, rr.TextDocument(report_markdown, media_type=rr.MediaType.MARKDOWN), static=True)
    if truth is not None and len(truth.T_world_agv):
        rec.log(
            TRUTH_TRAJECTORY,
            # Wider than the runs' lines, so it shows as a green rim where they lie on it.
            rr.LineStrips3D([truth.T_world_agv[:, :3, 3]], colors=COLOR_TRUTH, radii=rr.Radius.ui_points(4.0),
                            labels=["truth"], show_labels=False),
            static=True,
        )
        rec.log(TRUTH_POSE, rr.TransformAxes3D(AXIS_LENGTH_M), static=True)
        rec.log(
            f"{TRUTH_POSE}/body",
            rr.Boxes3D(half_sizes=[TRUTH_BODY_HALF_SIZES_M], centers=[(0.0, 0.0, 0.1)], colors=COLOR_TRUTH,
                       radii=rr.Radius.ui_points(1.0)),
            static=True,
        )
    for index, run in enumerate(runs):
        color = color_of(index)
        solved = np.all(np.isfinite(run.T_est.reshape(len(run.T_est), 16)), axis=1)
        if np.any(solved):
            rec.log(
                f"world/trajectory/{run.key}",
                rr.LineStrips3D([run.T_est[solved, :3, 3]], colors=color, radii=rr.Radius.ui_points(1.5),
                                labels=[run.label], show_labels=False),
                static=True,
            )
        rec.log(f"world/agv/{run.key}", rr.TransformAxes3D(AXIS_LENGTH_M), static=True)
        rec.log(
            f"world/agv/{run.key}/marker",
            rr.Points3D([(0.0, 0.0, 0.25)], colors=color, radii=rr.Radius.ui_points(6.0),
                        labels=[run.label], show_labels=False),
            static=True,
        )
        for key in ERROR_LABELS:
            rec.log(
                f"{ERRORS_ROOT}/{key}/{run.key}",
                rr.SeriesLines(names=run.label, colors=color, widths=1.5),
                static=True,
            )
    for key, label in ERROR_LABELS.items():
        rec.log(
            f"{DELTA_ROOT}/{key}",
            rr.SeriesLines(names=f"Δ {label} (B − A)", colors=(220, 220, 220), widths=1.5),
            static=True,
        )


def _copy_from_source(rec: rr.RecordingStream, source: Path, cam_names: list[str]) -> None:
    """Copy the marker map, each camera's images and detected corners of a run, chunk by chunk
    (the JPEG bytes are never decoded or re-encoded)."""
    store = read_rrd(source).store
    rec.send_chunks(store.stream().filter(content=[f"/{paths.MARKERS}", f"/{paths.MARKERS_FILL}"]))
    for cam in cam_names:
        rec.send_chunks(
            store.stream()
            .filter(content=f"/{paths.image(cam)}", is_static=False)
            .map(lambda chunk, cam=cam: chunk.with_entity_path(f"/{IMAGE_ROOT}/{cam}"))
        )
        rec.send_chunks(
            store.stream()
            .filter(content=f"/{paths.detected(cam)}", is_static=False, components="Points2D:positions")
            .map(lambda chunk, cam=cam: chunk.with_entity_path(f"/{IMAGE_ROOT}/{cam}/detected"))
        )
        rec.log(
            f"{IMAGE_ROOT}/{cam}/detected",
            rr.Points2D.from_fields(colors=COLOR_DETECTED, radii=DETECTED_RADIUS, draw_order=10.0),
            static=True,
        )
