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
    world/error/<key>                       Arrows3D per frame: the run's position error (estimate
                                            − truth) × magnification, from the truth position
    world/error_path/<key>                  LineStrips3D (static): truth + that error, the
                                            run's path with its errors magnified
    image/<cam>                             EncodedImage of the first run (copied, not re-encoded;
                                            a camera on the AGV or one fixed in the world alike)
    image/<cam>/detected                    the first run's detected corners (copied)
    image/<cam>/<key>                       each run's reprojected corners (Points2D)
    errors/<quantity>/<key>                 Scalars per frame: position_mm, heading_deg, ...
    delta/<quantity>                        Scalars per frame, B − A of |error| (diff only)
    delta/<quantity>/zero                   Scalars: the zero line (no difference) across it
    compare/report                          TextDocument: the comparison table (static); in a
                                            sweep the ranking with p-values and the verdict
    compare/key                             TextDocument (static): each run's colour, the 3D
                                            error magnification (the views' one key)
    settings/<key>/...                      each run's layers, every entity of its run .rrd
                                            under the prefix except the camera images
                                            (``layers=``; a sweep, ``diff --out``)
    sweep/index                             TextDocument (static): JSON, one entry per run:
                                            key, label, rank, settings (``index=``)

With ``layers`` and ``index`` the file is a sweep ``.rrd`` (issue 27): ``FILE#LABEL`` reads one
run back (:func:`agvviz.viz.readback.read_rrd`). With ``frames`` the images come from the
recording (logged once, :mod:`agvviz.viz.frames`) instead of being copied from ``source``.

Timelines: ``frame`` (what the viewer opens on), ``elapsed`` (since the source run's recording
start, else the first frame drawn) and ``time`` (the runs' absolute stamps). Written like a run:
pinned recording id, size-only chunking, a temporary file renamed into place.
"""

from __future__ import annotations

import json
import math
import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np
import rerun as rr

from agvviz.errors import InputError
from agvviz.viz import paths
from agvviz.viz.frames import CameraClock, RecordedImage, log_images
from agvviz.viz.blueprints import ERROR_LABELS, format_magnification, overlay_blueprint
from agvviz.viz.log_frames import DETECTED_RADIUS, REPROJECTED_RADIUS
from agvviz.viz.readback import RrdContents, as_int64, read_rrd
from agvviz.viz import rrd_file
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.style import COLOR_DELTA, COLOR_DETECTED, COLOR_TRUTH, COLOR_ZERO, color_name, color_of

#: The per-frame Δ series and its zero line.
AXIS_LENGTH_M = 0.4
TRUTH_BODY_HALF_SIZES_M = (0.30, 0.40, 0.10)
#: Length [m] the larger run's 95th-percentile position error is magnified to, at most: about the
#: AGV body's size, visible in a view of the whole trajectory.
ERROR_VECTOR_TARGET_M = 0.5
#: Camera images are written out (a flush) after this many bytes, or rows of image chunks: Rerun
#: queues what it is given without bound (a sweep's 2000 frames piled up: +100-200 MB).
FLUSH_IMAGE_BYTES = 8 << 20
FLUSH_IMAGE_ROWS = 32
FLUSH_LAYER_ROWS = 4096  # copied layers, rows sent between flushes: ≈50 small entities, not 50 waits


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
    reprojected : dict or callable
        Camera name → {overlay frame → (K, 2) reprojected corners in image pixels}; or a
        function returning that dict, called when the run is drawn and its result dropped
        after (a sweep holds one setting's corners at a time, not every setting's).
    T_truth : (N, 4, 4) float, optional
        The run's own truth ``T_world_agv`` on its frames (NaN where unknown); given, the 3D
        view draws the run's position error on each frame as a magnified arrow.
    short_label : str, optional
        Short name (e.g. ``A``, ``#1``); ``label`` when not given.
    """

    key: str
    label: str
    frames: np.ndarray
    time_ns: np.ndarray
    T_est: np.ndarray
    errors: dict[str, np.ndarray] = field(default_factory=dict)
    reprojected: dict[str, dict[int, np.ndarray]] | Callable[[], dict] = field(default_factory=dict)
    T_truth: np.ndarray | None = None
    short_label: str | None = None


@dataclass
class OverlayTruth:
    """Ground truth on the overlay clock: frames, time_ns (N,), ``T_world_agv`` (N, 4, 4)."""

    frames: np.ndarray
    time_ns: np.ndarray
    T_world_agv: np.ndarray


@dataclass(frozen=True)
class _Clock:
    """The overlay's timelines: ``frame``, ``time`` and ``elapsed`` (since ``origin_ns``)."""

    origin_ns: int

    def indexes(self, frames: np.ndarray, time_ns: np.ndarray) -> list[rr.TimeColumn]:
        time_ns = np.asarray(time_ns, dtype=np.int64)
        return [
            rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.asarray(frames, dtype=np.int64)),
            rr.TimeColumn(paths.TIMELINE_TIME, timestamp=time_ns.astype("datetime64[ns]")),
            rr.TimeColumn(paths.TIMELINE_ELAPSED, duration=(time_ns - self.origin_ns).astype("timedelta64[ns]")),
        ]


def _send_transforms(rec: rr.RecordingStream, clock: _Clock, entity: str, frames, time_ns, T: np.ndarray) -> None:
    if len(T) == 0:
        return
    rec.send_columns(
        entity,
        indexes=clock.indexes(frames, time_ns),
        columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]),
    )


def _send_scalars(rec: rr.RecordingStream, clock: _Clock, entity: str, frames, time_ns, values: np.ndarray) -> None:
    ok = np.isfinite(values)
    if not np.any(ok):
        return
    rec.send_columns(
        entity,
        indexes=clock.indexes(np.asarray(frames)[ok], np.asarray(time_ns)[ok]),
        columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)[ok]),
    )


def _send_corners(
    rec: rr.RecordingStream, clock: _Clock, entity: str, frames, time_ns, corners: dict[int, np.ndarray], color
) -> None:
    """Reprojected corners on every frame of the run (an empty batch where there are none)."""
    per_frame = [np.asarray(corners.get(int(f), np.zeros((0, 2))), dtype=float).reshape(-1, 2) for f in frames]
    if not per_frame:
        return
    positions = np.concatenate(per_frame)
    rec.send_columns(
        entity,
        indexes=clock.indexes(frames, time_ns),
        columns=rr.Points2D.columns(positions=positions).partition([len(p) for p in per_frame]),
    )
    rec.log(entity, rr.Points2D.from_fields(colors=color, radii=REPROJECTED_RADIUS, draw_order=11.0), static=True)


def position_errors_m(run: OverlayRun) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``run`` with both an estimate and a truth, and the position error vectors
    ``p_est − p_truth`` [m] in world coordinates on them: (rows (M,), (M, 3)). Empty without
    ``run.T_truth``."""
    if run.T_truth is None:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    n = len(run.frames)
    known = np.all(np.isfinite(run.T_est.reshape(n, 16)), axis=1)
    known &= np.all(np.isfinite(run.T_truth.reshape(n, 16)), axis=1)
    rows = np.flatnonzero(known)
    return rows, run.T_est[rows, :3, 3] - run.T_truth[rows, :3, 3]


def error_magnification(error_vectors_m: list[np.ndarray], target_m: float = ERROR_VECTOR_TARGET_M) -> float:
    """The factor the 3D view magnifies position errors by: the largest 1-2-5 step (1, 2, 5,
    10, 20, ...) that keeps the larger run's 95th-percentile error at most ``target_m`` long;
    never below 1 (errors are never shrunk). One factor for all runs, so lengths compare."""
    lengths = [np.linalg.norm(v, axis=1) for v in error_vectors_m if len(v)]
    p95_m = max((float(np.percentile(length, 95)) for length in lengths), default=0.0)
    if not p95_m > 0.0 or target_m / p95_m <= 1.0:
        return 1.0
    ratio = target_m / p95_m
    decade = 10.0 ** math.floor(math.log10(ratio))
    step = max(m for m in (1.0, 2.0, 5.0) if m * decade <= ratio * (1.0 + 1e-12))
    return step * decade


def _send_error_vectors(
    rec: rr.RecordingStream, clock: _Clock, run: OverlayRun, index: int, magnification: float
) -> None:
    """The run's position error on each frame it and its truth know, (estimate − truth) ×
    ``magnification``, as an arrow from the truth position; on its other frames (rejected,
    unsolved, no truth) an empty batch, so no earlier arrow stays drawn as if current."""
    rows, errors_m = position_errors_m(run)
    if len(rows) == 0:
        return
    entity = paths.overlay_error_vector(run.key)
    # one arrow on each known row, none on the others (the run's frames in order)
    per_frame = np.zeros(len(run.frames), dtype=np.int64)
    per_frame[rows] = 1
    indexes = clock.indexes(run.frames, run.time_ns)
    rec.send_columns(
        entity,
        indexes=indexes,
        columns=rr.Arrows3D.columns(origins=run.T_truth[rows, :3, 3], vectors=errors_m * magnification).partition(per_frame),
    )
    # No text on screen: the runs' arrows share their origin and their tips meet where the runs
    # agree, so labels there would collide. The key (COMPARE_KEY) names each run's colour and the
    # view titles the magnification, once; the label shows on hover.
    rec.log(
        entity,
        rr.Arrows3D.from_fields(
            colors=color_of(index), radii=rr.Radius.ui_points(4.0), labels=[run.label], show_labels=False
        ),
        static=True,
    )
    rec.log(
        paths.overlay_error_path(run.key),
        rr.LineStrips3D([run.T_truth[rows, :3, 3] + errors_m * magnification], colors=color_of(index),
                        radii=rr.Radius.ui_points(1.0), labels=[run.label], show_labels=False),
        static=True,
    )


def key_markdown(runs: list[OverlayRun], truth: bool, magnification: float | None, images: bool) -> str:
    """The overlay's colour key (:data:`paths.COMPARE_KEY`), one line: each run's label and colour
    in the overlay's order, then what else is drawn (truth, detected corners) and the 3D error
    magnification. One key for every view: the 3D views carry no per-run labels (they would
    collide where the runs agree) and the plots no legends (Rerun 0.41 draws them on the data)."""
    items = [f"**{run.label}** {color_name(i)}" for i, run in enumerate(runs)]
    if truth:
        items.append("truth green")
    if images:
        items.append("detected corners cyan")
    line = " · ".join(items)
    if magnification is not None:
        line += f" — 3D arrows: error (estimate − truth) {format_magnification(magnification)} from the true position"
    return line + "\n"


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
        lengths += [len(run.T_truth)] if run.T_truth is not None else []
        if any(length != n for length in lengths):
            raise OverlayError(f"run {run.key}: arrays must all have {n} entries (one per frame)")
        unknown = set(run.errors) - set(ERROR_LABELS)
        if unknown:
            raise OverlayError(f"run {run.key}: unknown error series {sorted(unknown)}; known: {sorted(ERROR_LABELS)}")


def write_overlay(
    out_path: str | os.PathLike,
    *,
    recording_name: str,
    runs: list[OverlayRun],
    truth: OverlayTruth | None,
    source: str | os.PathLike | RrdContents | None,
    cam_names: list[str],
    report_markdown: str,
    deltas: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
    inputs: tuple[str | os.PathLike, ...] = (),
    fixed_cams: set[str] | frozenset[str] = frozenset(),
    layers: dict[str, str | os.PathLike | RrdContents] | None = None,
    index: list[dict] | None = None,
    frames: tuple[Iterable[RecordedImage], dict[str, CameraClock]] | None = None,
    frames_from: str | os.PathLike | None = None,
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
        Drawn in this order and colour (:data:`agvviz.viz.style.PALETTE`).
    truth : OverlayTruth, optional
    source : path or RrdContents, optional
        Run ``.rrd`` (the first run's; its path, or opened already) whose marker map is copied, and the images and
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
    fixed_cams : set of str
        Those of ``cam_names`` fixed in the world (``world/cameras/cam_<name>``, e.g. uwb_room's
        wall cameras): their images and detected corners are read from there, not the AGV's.
    layers : dict, optional
        Run key → run ``.rrd`` (full or layers-only; its path, or opened already) whose every entity but the camera images
        is copied under ``settings/<key>/`` (:func:`paths.sweep_setting`), chunk by chunk.
    index : list of dict, optional
        One entry per run of ``layers`` (key, label, rank, settings): ``sweep/index``.
    frames : (images, clocks), optional
        The recording's camera images (:data:`agvviz.viz.frames.RecordedImage`) and each
        camera's clock in the first run: logged under ``image/<cam>`` for ``cam_names`` in
        place of copying them from ``source``.
    frames_from : path, optional
        A sweep ``.rrd`` whose frames (``image/<cam>``) are copied in place of ``source``'s
        (a diff of two settings of one sweep: their layers hold no images).
    """
    _check(runs)
    deltas = deltas or {}
    out_path = Path(out_path)
    if out_path.suffix != ".rrd":
        raise OverlayError(f"the overlay must be a .rrd file, got {out_path}")
    recording_id = str(uuid.uuid5(uuid.NAMESPACE_URL, f"agvviz-overlay:{recording_name}"))
    sources = tuple(inputs) + ((_opened(source).path,) if source is not None else ())
    # Error arrows only when some run has frames with both an estimate and a truth.
    error_vectors_m = [position_errors_m(run)[1] for run in runs]
    magnification = error_magnification(error_vectors_m) if any(len(v) for v in error_vectors_m) else None
    store = _opened(source).store if source is not None else None
    clock = _Clock(_elapsed_origin_ns(store, runs, truth))
    with AtomicRrd(out_path, recording_id=recording_id, recording_name=recording_name, inputs=sources) as rrd:
        rec = rrd.rec
        _log_static(rec, runs, truth, report_markdown, list(deltas))
        rec.log(paths.COMPARE_KEY, rr.TextDocument(
            key_markdown(runs, truth is not None and len(truth.T_world_agv) > 0, magnification,
                         bool(cam_names) and store is not None),
            media_type=rr.MediaType.MARKDOWN), static=True)
        if store is not None:
            _copy_from_source(rec, store, cam_names, fixed_cams, images=frames is None and frames_from is None)
            rrd.check()
        if frames_from is not None:
            frames_store = read_rrd(frames_from).store
            for cam in cam_names:
                _send_paced(rec, frames_store.stream().filter(
                    content=f"/{paths.overlay_image(cam)}", is_static=False,
                    components=["EncodedImage:blob", "EncodedImage:media_type"]))
            rrd.check()
        if frames is not None and cam_names:
            images, clocks = frames
            log_images(rec, _paced_images(rec, images), {c: clocks.get(c, []) for c in cam_names},
                       {c: paths.overlay_image(c) for c in cam_names})
            rec.reset_time()
            rrd.check()
        layer_entities = {}  # run key → the entities its layers hold (for the layout)
        for key, run in (layers or {}).items():
            layer_entities[key] = _copy_layers(rec, key, run)
            rrd.check()
        if index is not None:
            rec.log(paths.SWEEP_INDEX, rr.TextDocument(_index_markdown(index), media_type=rr.MediaType.MARKDOWN),
                    static=True)
        if truth is not None:
            _send_transforms(rec, clock, paths.AGV_TRUTH, truth.frames, truth.time_ns, truth.T_world_agv)
        for index, run in enumerate(runs):
            solved = np.all(np.isfinite(run.T_est.reshape(len(run.T_est), 16)), axis=1)
            _send_transforms(
                rec, clock, paths.overlay_agv(run.key), run.frames[solved], run.time_ns[solved], run.T_est[solved]
            )
            if magnification is not None:
                _send_error_vectors(rec, clock, run, index, magnification)
            for key, values in run.errors.items():
                _send_scalars(rec, clock, paths.overlay_error(key, run.key), run.frames, run.time_ns, values)
            if store is not None:
                reprojected = run.reprojected() if callable(run.reprojected) else run.reprojected
                for cam in cam_names:
                    _send_corners(
                        rec, clock, paths.overlay_reprojected(cam, run.key), run.frames, run.time_ns,
                        reprojected.get(cam, {}), color_of(index),
                    )
        for key, (frames, time_ns, values) in deltas.items():
            _send_scalars(rec, clock, paths.overlay_delta(key), frames, time_ns, values)
            _send_zero_line(rec, clock, key, frames, time_ns)
        rrd.commit(overlay_blueprint(
            runs, cam_names if store is not None else [], list(deltas), truth, magnification, fixed_cams,
            layer_entities=layer_entities,
        ))
    return out_path


def _send_zero_line(rec: rr.RecordingStream, clock: _Clock, key: str, frames, time_ns) -> None:
    """The zero line of a Δ plot: 0 on its first and last frame (a straight line between)."""
    if len(frames) == 0:
        return
    ends = [0, len(frames) - 1]
    _send_scalars(rec, clock, paths.overlay_delta_zero(key), np.asarray(frames)[ends], np.asarray(time_ns)[ends],
                  np.zeros(2))


def _elapsed_origin_ns(store, runs: list[OverlayRun], truth: OverlayTruth | None) -> int:
    """Origin of the ``elapsed`` timeline: the source run's own (``time − elapsed`` of its
    first per-frame row, so copied images and drawn series agree), else the first stamp drawn."""
    if store is not None:
        # Only the entity of that first row is read: a stream of every per-frame chunk is
        # loaded ahead of its reader, the whole file for a small one, even if one chunk is used.
        entity = _first_temporal_entity(store)
        stream = store.stream().filter(is_static=False, **({"content": entity} if entity else {}))
        for chunk in stream:
            names = chunk.timeline_names
            if paths.TIMELINE_TIME in names and paths.TIMELINE_ELAPSED in names and chunk.num_rows:
                batch = chunk.to_record_batch()  # as_int64: no pyarrow.compute (≈0.08 s of a sweep's end)
                time_ns = as_int64(batch.column(paths.TIMELINE_TIME))[0].as_py()
                elapsed_ns = as_int64(batch.column(paths.TIMELINE_ELAPSED))[0].as_py()
                return int(time_ns) - int(elapsed_ns)
            break  # the run logs every per-frame row on the same timelines: one chunk tells
    firsts = [int(np.min(run.time_ns)) for run in runs if len(run.time_ns)]
    if truth is not None and len(truth.time_ns):
        firsts.append(int(np.min(truth.time_ns)))
    return min(firsts, default=0)


def _first_temporal_entity(store) -> str | None:
    """The entity of the first per-frame chunk of ``store`` in file order, from the chunk index
    of a store read from a file (no chunk data loaded); None for a store in memory."""
    chunk_index = getattr(store, "_chunk_index", None)  # Rerun's LazyStore (0.41), private
    if chunk_index is None:
        return None
    table = chunk_index().to_arrow()
    entities, static = table.column("chunk_entity_path").to_pylist(), table.column("chunk_is_static").to_pylist()
    return next((entity for entity, fixed in zip(entities, static) if not fixed), None)


def _log_static(
    rec: rr.RecordingStream, runs: list[OverlayRun], truth: OverlayTruth | None, report_markdown: str,
    deltas: list[str],
) -> None:
    rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(paths.COMPARE_REPORT, rr.TextDocument(report_markdown, media_type=rr.MediaType.MARKDOWN), static=True)
    if truth is not None and len(truth.T_world_agv):
        rec.log(
            paths.TRAJECTORY_TRUTH,
            # Wider than the runs' lines, so it shows as a green rim where they lie on it.
            rr.LineStrips3D([truth.T_world_agv[:, :3, 3]], colors=COLOR_TRUTH, radii=rr.Radius.ui_points(4.0),
                            labels=["truth"], show_labels=False),
            static=True,
        )
        rec.log(paths.AGV_TRUTH, rr.TransformAxes3D(AXIS_LENGTH_M), static=True)
        rec.log(
            paths.AGV_TRUTH_BODY,
            rr.Boxes3D(half_sizes=[TRUTH_BODY_HALF_SIZES_M], centers=[(0.0, 0.0, 0.1)], colors=COLOR_TRUTH,
                       radii=rr.Radius.ui_points(1.0), fill_mode="majorwireframe"),  # arrows show inside
            static=True,
        )
    for index, run in enumerate(runs):
        color = color_of(index)
        solved = np.all(np.isfinite(run.T_est.reshape(len(run.T_est), 16)), axis=1)
        if np.any(solved):
            rec.log(
                paths.overlay_trajectory(run.key),
                rr.LineStrips3D([run.T_est[solved, :3, 3]], colors=color, radii=rr.Radius.ui_points(1.5),
                                labels=[run.label], show_labels=False),
                static=True,
            )
        rec.log(paths.overlay_agv(run.key), rr.TransformAxes3D(AXIS_LENGTH_M), static=True)
        rec.log(
            paths.overlay_agv_marker(run.key),
            rr.Points3D([(0.0, 0.0, 0.25)], colors=color, radii=rr.Radius.ui_points(6.0),
                        labels=[run.label], show_labels=False),
            static=True,
        )
        for key in ERROR_LABELS:
            rec.log(
                paths.overlay_error(key, run.key),
                rr.SeriesLines(names=run.label, colors=color, widths=1.5),
                static=True,
            )
    for key in deltas:
        rec.log(
            paths.overlay_delta(key),
            rr.SeriesLines(names="Δ = B − A (positive: B worse)", colors=COLOR_DELTA, widths=1.5),
            static=True,
        )
        rec.log(
            paths.overlay_delta_zero(key),
            rr.SeriesLines(names="0 = no difference", colors=COLOR_ZERO, widths=1.0),
            static=True,
        )


def _opened(run: str | os.PathLike | RrdContents) -> RrdContents:
    """A run ``.rrd`` by its path, or opened by the caller (a sweep opens each run once)."""
    return run if isinstance(run, RrdContents) else read_rrd(run)


def _copy_layers(rec: rr.RecordingStream, key: str, run: str | os.PathLike | RrdContents) -> set[str]:
    """Copy every entity of the run ``.rrd`` ``run`` (a path, or opened) but its camera images and
    properties under ``settings/<key>/``, chunk by chunk, unchanged; returns its entity paths. One
    entity at a time, written out (``flush``) every :data:`FLUSH_LAYER_ROWS` rows: Rerun loads a
    stream's chunks ahead of the writer (a run's layers in one stream: ≈45 MB at 2000 frames)."""
    store = _opened(run).store
    entities = sorted(p.lstrip("/") for p in store.schema().entity_paths())
    left_out = {"__properties", *paths.camera_images(entities)}
    prefix, rows = "/" + paths.sweep_setting(key), []

    def moved(chunk):
        rows.append(chunk.num_rows)
        return chunk.with_entity_path(prefix + chunk.entity_path)

    for entity in entities:
        if entity in left_out or entity.startswith("__properties/"):
            continue
        rec.send_chunks(store.stream().filter(content=f"/{entity}").map(moved))
        if sum(rows) >= FLUSH_LAYER_ROWS:
            rec.flush()
            rows.clear()
    rec.flush()
    return set(entities)


def _paced_images(rec: rr.RecordingStream, images: Iterable[RecordedImage]) -> Iterator[RecordedImage]:
    """``images`` as they come, the stream flushed after every :data:`FLUSH_IMAGE_BYTES` of
    them: the file is written as fast as the frames are logged, not queued in memory. A flush
    cuts the chunk being batched, so it comes only right after an image the batcher has cut a
    chunk at anyway (one of at least ``rrd_file.BATCHER_FLUSH_NUM_BYTES``): the chunks are an
    unpaced write's (`rerun rrd compare --unordered` finds them equal). Smaller frames are not
    paced."""
    given = 0
    for image in images:
        yield image  # logged when the next one is asked for
        given += len(image[3])
        if given >= FLUSH_IMAGE_BYTES and len(image[3]) >= rrd_file.BATCHER_FLUSH_NUM_BYTES:
            rec.flush()
            given = 0


def _send_paced(rec: rr.RecordingStream, chunks: Iterable) -> None:
    """Send ``chunks`` (camera images) one by one, a flush after every :data:`FLUSH_IMAGE_ROWS`."""
    rows = 0
    for chunk in chunks:
        rec.send_chunks(chunk)
        rows += chunk.num_rows
        if rows >= FLUSH_IMAGE_ROWS:
            rec.flush()
            rows = 0


def _index_markdown(index: list[dict]) -> str:
    """``sweep/index``: the runs of a sweep ``.rrd`` as a table and a JSON block (read back by
    :func:`agvviz.viz.readback.sweep_index`)."""
    rows = [f"| {e.get('rank') or '—'} | {e['label']} | `{paths.sweep_setting(e['key'])}` |" for e in index]
    block = json.dumps({"settings": index}, indent=2, sort_keys=True)
    return "\n".join(["# settings in this file", "", "| rank | setting | entity root |", "| --- | --- | --- |", *rows,
                      "", "```json", block, "```", ""])


def _copy_from_source(
    rec: rr.RecordingStream, store, cam_names: list[str], fixed_cams: set[str] | frozenset[str] = frozenset(),
    images: bool = True,
) -> None:
    """Copy the marker map, each camera's images (unless ``images`` is False) and detected
    corners of a run (its store), chunk by chunk (the JPEG bytes are never decoded or
    re-encoded); a camera of ``fixed_cams`` from its world-fixed entity."""
    rec.send_chunks(store.stream().filter(content=[f"/{paths.MARKERS}", f"/{paths.MARKERS_FILL}"]))
    for cam in cam_names if images else []:
        _send_paced(
            rec,
            store.stream()
            .filter(content=f"/{paths.image(cam, cam in fixed_cams)}", is_static=False)
            .map(lambda chunk, cam=cam: chunk.with_entity_path(f"/{paths.overlay_image(cam)}")),
        )
    for cam in cam_names:
        rec.send_chunks(
            store.stream()
            .filter(content=f"/{paths.detected(cam, cam in fixed_cams)}", is_static=False,
                    components="Points2D:positions")
            .map(lambda chunk, cam=cam: chunk.with_entity_path(f"/{paths.overlay_detected(cam)}"))
        )
        rec.log(
            paths.overlay_detected(cam),
            rr.Points2D.from_fields(colors=COLOR_DETECTED, radii=DETECTED_RADIUS, draw_order=10.0),
            static=True,
        )
