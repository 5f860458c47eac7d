"""Log one replay run into a Rerun recording and save it as one ``.rrd``.

The entity tree is in :mod:`agvviz.viz.paths`; the default layout in
:mod:`agvviz.viz.blueprint`. The logger owns an explicit ``rr.RecordingStream`` (never the
global one) that buffers everything in memory until :meth:`RunLogger.save`, which streams
the buffer plus the default blueprint into a temporary file next to the target and then
renames it into place. Wall-clock ``log_time``/``log_tick`` timelines and the wall-clock
start-time property are disabled and chunks are cut by size only (no wall-clock batcher
tick), so the file depends only on the data: two identical runs compare equal with
``rerun rrd compare --unordered`` (row ids and file bytes still differ).

Logging cost (issue 12): every per-frame value except the image — scalar series (errors,
reprojection, uncertainty, LM iterations), poses, corners, codes seen, trajectories, the
covariance ellipsoid, the LM bar charts, paths and text, and the Clears that end them — is held
in memory and sent as columns (one ``send_columns`` per entity) every
:data:`FLUSH_EVERY_FRAMES` frames and at :meth:`RunLogger.close`, instead of building a Rerun
archetype per frame. The image is logged per frame (it is large) from its bytes without an
archetype. The styling of every per-frame entity (colours, radii, draw order) is logged once as
static data, so a frame carries only what changes. The data are those the per-frame archetypes
carried (same entities, components, values and timelines; only the chunking differs).
Every per-frame log is stamped on ``frame``, ``time`` and ``elapsed``
(:func:`agvviz.viz.timelines.set_stamp`).
"""

from __future__ import annotations

from agvviz.errors import RunError

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import rerun as rr

from agvviz.evaluation.summary_table import markdown_table, summary_rows
from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.markers.charuco import is_chessboard_id
from agvviz.model.frames import FrameResult, LmIteration
from agvviz.viz import paths
from agvviz.viz.blueprint import default_blueprint
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.style import (
    COLOR_CAMERA,
    COLOR_DETECTED,
    COLOR_GHOST,
    COLOR_HEADING,
    COLOR_MARKER,
    COLOR_MARKER_FILL,
    COLOR_OBSERVED,
    COLOR_PITCH,
    COLOR_REJECTED,
    COLOR_REPROJECTED,
    COLOR_ROLL,
    COLOR_STALE,
    COLOR_THRESHOLD,
    COLOR_TRUTH,
)
from agvviz.viz.timelines import elapsed_s, set_stamp


#: Media type of each ``FrameResult.image_format``.
MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}

#: The 3σ covariance ellipsoid is magnified by a power of ten chosen once per run, from its
#: first covariance, so that its largest 3σ half-axis is drawn about this long (m): comparable
#: with the body, whether σ is 0.1 mm or 5 mm. Its label and the 3D view's title give the factor.
COV_DRAWN_HALF_AXIS_M = 0.25
#: Ambiguity ratios above this are plotted at this value (exact fits give inf).
AMBIGUITY_RATIO_CAP = 100.0
#: The rejected IPPE mirror pose (the ghost) is drawn only when the ambiguity ratio
#: rms(mirror) / rms(chosen) is below this. With a code's 4 corners each pose leaves 2 residual
#: degrees of freedom; were both poses equally right, the cost ratio (ratio²) would follow
#: F(2, 2), P(F ≥ f) = 1 / (1 + f): a ratio of 4 (cost ratio 16) still happens by noise alone
#: in 1/17 ≈ 6 % of frames. Below it the data cannot reject the mirror pose at about the 5 %
#: level — a real contender; above it the mirror pose is no contender and is not drawn.
GHOST_MAX_AMBIGUITY_RATIO = 4.0

#: Nominal AGV body drawn around the body frame (half sizes x, y, z in m; centre on the
#: floor-origin's vertical). A visual marker only: the recording does not carry a body size.
AGV_BODY_HALF_SIZES_M = (0.30, 0.40, 0.10)
AGV_BODY_CENTER_M = (0.0, 0.0, 0.10)
AGV_AXIS_LENGTH_M = 0.5
#: The covariance ellipsoid is drawn this far above the body's top (m), so the opaque-looking
#: body never hides it.
COV_ABOVE_BODY_M = 0.05
#: Distance of the image plane drawn in the camera frustum (m).
FRUSTUM_IMAGE_PLANE_M = 0.4
#: Point radii in the image view (UI points, so they keep their size when zooming).
DETECTED_RADIUS = rr.Radius.ui_points(5.0)
REPROJECTED_RADIUS = rr.Radius.ui_points(2.5)
LM_ITERATION_RADIUS = rr.Radius.ui_points(2.0)
#: A trajectory is redrawn every frame from at most this many of its points (evenly spread,
#: first and newest always kept), so logging cost per frame stays bounded on long runs.
MAX_TRAJECTORY_POINTS = 400
#: Per-frame scalar series are sent as columns every this many frames (and at close).
FLUSH_EVERY_FRAMES = 64
#: A code whose longest detected edge is shorter than this fraction of the image width (a code a
#: few UI points wide in an image panel) also gets a zoomed view: a crop of the recorded image
#: around it, ZOOM_CROP_CODE_SIDES code sides wide (at least ZOOM_MIN_CROP_PX), so a ≈15 px
#: code fills its own panel.
ZOOM_CODE_BELOW_FRACTION = 0.05
#: Every crop is resized to this side (nearest neighbour: pixels stay visible as blocks), so
#: the zoomed image keeps one size (the viewer refuses a stream of images changing size).
ZOOM_SIDE_PX = 256
ZOOM_CROP_CODE_SIDES = 3.0
ZOOM_MIN_CROP_PX = 32

#: (frame index, log_time_ns, elapsed seconds) of one log.
Stamp = tuple[int, int, float]

#: Per-frame scalar series: (entity, legend name, colour).
_FRAME_SERIES = (
    (paths.ERROR_POSITION_MM, "position error [mm] (camera estimate)", COLOR_CAMERA),
    (paths.ERROR_HEADING_DEG, "heading error [deg]", COLOR_HEADING),
    (paths.ERROR_PITCH_DEG, "pitch error [deg]", COLOR_PITCH),
    (paths.ERROR_ROLL_DEG, "roll error [deg]", COLOR_ROLL),
    (paths.ERROR_REPROJ_RMS_PX, "reprojection RMS [px]", COLOR_REPROJECTED),
    (paths.ERROR_NEES, "NEES (expected: dof)", COLOR_CAMERA),
    (paths.ERROR_POSITION_OVER_CRLB, "position error ÷ CRLB", COLOR_REPROJECTED),
    (paths.ERROR_CRLB_POSITION_M, "CRLB position [m]", COLOR_TRUTH),
    (paths.ERROR_POSITION_SIGMA_M, "covariance position σ [m]", COLOR_CAMERA),
    (paths.SOLVER_AMBIGUITY_RATIO, f"IPPE ambiguity ratio (capped at {AMBIGUITY_RATIO_CAP:g})", COLOR_GHOST),
    (paths.LM_ITERATIONS, "LM trial steps per frame", COLOR_CAMERA),
)
#: LM series per iteration (``lm_iter`` columns): (entity, legend name, colour).
_ITERATION_SERIES = (
    (paths.LM_COST, "LM cost", COLOR_CAMERA),
    (paths.LM_LOG10_COST, "log10 LM cost", COLOR_CAMERA),
    (paths.LM_REPROJ_RMS_PX, "LM reprojection RMS [px]", COLOR_REPROJECTED),
    (paths.LM_DAMPING, "LM damping λ", COLOR_OBSERVED),
    (paths.LM_STEP_NORM, "LM step norm", COLOR_OBSERVED),
)


class RunLogError(RunError):
    """Input the run logger cannot log (wrong shape, unknown image format, used after save)."""


class _Columns:
    """Per-frame data held until :meth:`flush`, then sent as one column chunk per entity:
    scalars, the Clears that break a series' line at rejected frames, LM iteration scalars and
    LM iteration points (these two also on the ``lm_iter`` timeline)."""

    def __init__(self):
        self._scalars: dict[str, list[tuple[Stamp, float]]] = {}
        self._gaps: dict[str, list[Stamp]] = {}
        self._iterations: dict[str, list[tuple[Stamp, np.ndarray]]] = {}
        self._points: dict[str, list[tuple[Stamp, list[np.ndarray]]]] = {}
        self._transforms: dict[str, list[tuple[Stamp, np.ndarray]]] = {}
        #: (entity, kind) -> rows of one per-frame archetype (see :data:`_ROW_COLUMNS`).
        self._rows: dict[tuple[str, str], list[tuple[Stamp, tuple]]] = {}

    def row(self, entity: str, kind: str, stamp: Stamp, *payload) -> None:
        """One frame's value of ``entity`` as an archetype of ``kind`` (a key of _ROW_COLUMNS)."""
        self._rows.setdefault((entity, kind), []).append((stamp, payload))

    def scalar(self, entity: str, stamp: Stamp, value: float) -> None:
        self._scalars.setdefault(entity, []).append((stamp, float(value)))

    def gap(self, entity: str, stamp: Stamp) -> None:
        self._gaps.setdefault(entity, []).append(stamp)

    def iterations(self, entity: str, stamp: Stamp, values) -> None:
        self._iterations.setdefault(entity, []).append((stamp, np.asarray(values, dtype=float)))

    def iteration_points(self, entity: str, stamp: Stamp, points_px: list[np.ndarray]) -> None:
        self._points.setdefault(entity, []).append((stamp, points_px))

    def transform(self, entity: str, stamp: Stamp, T_parent_child: np.ndarray) -> None:
        self._transforms.setdefault(entity, []).append((stamp, T_parent_child))

    def flush(self, rec: rr.RecordingStream) -> None:
        for entity, rows in self._transforms.items():
            T = np.array([T for _, T in rows])
            rec.send_columns(
                entity,
                indexes=_time_columns([stamp for stamp, _ in rows]),
                columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]),
            )
        for (entity, kind), rows in self._rows.items():
            rec.send_columns(
                entity,
                indexes=_time_columns([stamp for stamp, _ in rows]),
                columns=_ROW_COLUMNS[kind]([payload for _, payload in rows]),
            )
        for entity, rows in self._scalars.items():
            rec.send_columns(
                entity,
                indexes=_time_columns([stamp for stamp, _ in rows]),
                columns=rr.Scalars.columns(scalars=np.array([value for _, value in rows])),
            )
        for entity, stamps in self._gaps.items():
            rec.send_columns(
                entity,
                indexes=_time_columns(stamps),
                columns=rr.Clear.columns(is_recursive=np.zeros(len(stamps), dtype=bool)),
            )
        for entity, rows in self._iterations.items():
            counts = [len(values) for _, values in rows]
            rec.send_columns(
                entity,
                indexes=_iteration_time_columns([stamp for stamp, _ in rows], counts),
                columns=rr.Scalars.columns(scalars=np.concatenate([values for _, values in rows])),
            )
        for entity, rows in self._points.items():
            counts = [len(per_iteration) for _, per_iteration in rows]
            arrays = [points for _, per_iteration in rows for points in per_iteration]
            rec.send_columns(
                entity,
                indexes=_iteration_time_columns([stamp for stamp, _ in rows], counts),
                columns=rr.Points2D.columns(positions=np.concatenate(arrays)).partition([len(a) for a in arrays]),
            )
        self._scalars, self._gaps, self._iterations, self._points, self._transforms = {}, {}, {}, {}, {}
        self._rows = {}


class _ArrowBatch:
    """A ready Arrow array as a component batch (for :class:`rr.ComponentColumn`)."""

    def __init__(self, array: pa.Array):
        self._array = array

    def as_arrow_array(self) -> pa.Array:
        return self._array


def _lengths(groups) -> np.ndarray:
    return np.fromiter((len(g) for g in groups), dtype=np.int64, count=len(groups))


def _points2d_columns(rows) -> rr.ComponentColumnList:
    """Rows (positions (n, 2), labels [n]) as one Points2D row each."""
    positions = [p for p, _ in rows]
    labels = [label for _, row_labels in rows for label in row_labels]
    return rr.Points2D.columns(positions=np.concatenate(positions), labels=labels).partition(_lengths(positions))


def _strips3d_columns(rows) -> rr.ComponentColumnList:
    """Rows (strips [k], labels [k]) as one LineStrips3D row each."""
    strips = [strip for row_strips, _ in rows for strip in row_strips]
    labels = [label for _, row_labels in rows for label in row_labels]
    return rr.LineStrips3D.columns(strips=strips, labels=labels).partition(_lengths([s for s, _ in rows]))


def _strip3d_columns(rows) -> rr.ComponentColumnList:
    """Rows (one strip,) as one LineStrips3D row each (a trajectory)."""
    return rr.LineStrips3D.columns(strips=[strip for (strip,) in rows])


def _strips2d_columns(rows) -> list[rr.ComponentColumn]:
    """Rows (strips (k, m, 2) or k arrays (m_i, 2),) as one LineStrips2D row each: the Arrow
    array built in one go (float32 points, one offset per strip), what
    ``rr.LineStrips2D.columns(strips=...)`` builds strip by strip (an LM path of 128 points is
    128 strips a frame)."""
    points, strip_lengths, row_lengths = [], [], []
    for (row_strips,) in rows:
        if isinstance(row_strips, np.ndarray) and row_strips.ndim == 3:
            k, m = row_strips.shape[:2]
            points.append(row_strips.reshape(-1, 2))
            strip_lengths.append(np.full(k, m, dtype=np.int64))
        else:
            k = len(row_strips)
            points += [np.asarray(strip, dtype=float).reshape(-1, 2) for strip in row_strips]
            strip_lengths.append(_lengths(row_strips))
        row_lengths.append(k)
    flat = np.concatenate(points).astype(np.float32).ravel() if points else np.zeros(0, np.float32)
    offsets = np.zeros(sum(row_lengths) + 1, dtype=np.int32)
    np.cumsum(np.concatenate(strip_lengths) if strip_lengths else np.zeros(0, np.int64), out=offsets[1:])
    strips = pa.ListArray.from_arrays(
        pa.array(offsets), pa.FixedSizeListArray.from_arrays(pa.array(flat), type=_STRIP2D_TYPE.value_type), type=_STRIP2D_TYPE
    )
    return [rr.ComponentColumn(rr.LineStrips2D.descriptor_strips(), _ArrowBatch(strips), lengths=row_lengths)]


def _ellipsoid_columns(rows) -> rr.ComponentColumnList:
    """Rows (half_sizes (3,), centre (3,), quaternion xyzw (4,), label) as one ellipsoid each."""
    half_sizes, centres, quaternions, labels = zip(*rows)
    return rr.Ellipsoids3D.columns(
        half_sizes=np.array(half_sizes),
        centers=np.array(centres),
        quaternions=np.array(quaternions),
        labels=list(labels),
    )


def _markdown_columns(rows) -> rr.ComponentColumnList:
    """Rows (markdown text,) as one TextDocument row each."""
    return rr.TextDocument.columns(text=[text for (text,) in rows], media_type=[rr.MediaType.MARKDOWN] * len(rows))


def _bar_chart_columns(rows) -> list[rr.ComponentColumn]:
    """Rows (float64 values (n,),) as one BarChart row each: the TensorData array is built in one
    go (shape [n], no names, an F64 buffer), what ``rr.BarChart(values)`` logs per call."""
    values = [v for (v,) in rows]
    data_type = rr.components.TensorDataBatch._ARROW_DATATYPE
    n_rows = len(values)
    lengths = _lengths(values)
    offsets = np.zeros(n_rows + 1, dtype=np.int32)
    np.cumsum(lengths, out=offsets[1:])
    shape_type = data_type.field("shape").type
    shape = pa.ListArray.from_arrays(
        pa.array(np.arange(n_rows + 1, dtype=np.int32)), pa.array(lengths.astype(np.uint64))
    ).cast(shape_type)
    names = pa.nulls(n_rows, type=data_type.field("names").type)
    buffer_type = data_type.field("buffer").type
    f64 = [f.name for f in buffer_type].index("F64")
    flat = np.concatenate(values).astype(np.float64) if n_rows else np.zeros(0)
    child = pa.ListArray.from_arrays(pa.array(offsets), pa.array(flat)).cast(buffer_type[f64].type)
    children = [pa.nulls(0, type=f.type) for f in buffer_type]
    children[f64] = child
    buffer = pa.Array.from_buffers(
        type=buffer_type,
        length=n_rows,
        buffers=[
            None,
            pa.array(np.full(n_rows, f64, dtype=np.int8)).buffers()[1],
            pa.array(np.arange(n_rows, dtype=np.int32)).buffers()[1],
        ],
        children=children,
    )
    tensors = pa.StructArray.from_arrays([shape, names, buffer], fields=list(data_type)).cast(data_type)
    return [rr.ComponentColumn(rr.BarChart.descriptor_values(), _ArrowBatch(tensors))]


_BLOB_TYPE = rr.components.BlobBatch._ARROW_DATATYPE
_STRIP2D_TYPE = rr.components.LineStrip2DBatch._ARROW_DATATYPE
_BLOB_DESCRIPTOR = rr.EncodedImage.descriptor_blob()
_MEDIA_TYPE_BATCHES: dict[str, rr.DescribedComponentBatch] = {}


def _media_type_batch(media_type: str) -> rr.DescribedComponentBatch:
    """``EncodedImage:media_type`` = ``media_type`` (built once per media type)."""
    batch = _MEDIA_TYPE_BATCHES.get(media_type)
    if batch is None:
        batch = _MEDIA_TYPE_BATCHES[media_type] = rr.DescribedComponentBatch(
            rr.components.MediaTypeBatch([media_type]), rr.EncodedImage.descriptor_media_type()
        )
    return batch


class _Track:
    """Positions (m) appended one per frame into a growing array (no list → array per frame)."""

    def __init__(self):
        self._xyz = np.zeros((256, 3))
        self._n = 0

    def append(self, position_m: np.ndarray) -> None:
        if self._n == len(self._xyz):
            self._xyz = np.concatenate([self._xyz, np.zeros_like(self._xyz)])
        self._xyz[self._n] = position_m
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def array(self) -> np.ndarray:
        return self._xyz[: self._n]


#: Builders of per-frame archetype columns, by the ``kind`` given to :meth:`_Columns.row`.
_ROW_COLUMNS = {
    "points2d": _points2d_columns,
    "strips3d": _strips3d_columns,
    "strip3d": _strip3d_columns,
    "strips2d": _strips2d_columns,
    "ellipsoid": _ellipsoid_columns,
    "markdown": _markdown_columns,
    "bar_chart": _bar_chart_columns,
}


def _time_columns(stamps: list[Stamp]) -> list[rr.TimeColumn]:
    """``frame``, ``time`` and ``elapsed`` index columns of ``stamps``."""
    frames, times_ns, elapsed = zip(*stamps)
    return [
        rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.asarray(frames, dtype=np.int64)),
        rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.asarray(times_ns, dtype=np.int64).astype("datetime64[ns]")),
        rr.TimeColumn(paths.TIMELINE_ELAPSED, duration=np.asarray(elapsed, dtype=float)),
    ]


def _iteration_time_columns(stamps: list[Stamp], counts: list[int]) -> list[rr.TimeColumn]:
    """``lm_iter`` (0..n-1 per frame) plus each frame's stamp repeated over its iterations."""
    repeated = [stamp for stamp, n in zip(stamps, counts) for _ in range(n)]
    lm_iter = np.concatenate([np.arange(n) for n in counts]) if counts else np.zeros(0, dtype=np.int64)
    return [rr.TimeColumn(paths.TIMELINE_LM_ITER, sequence=lm_iter), *_time_columns(repeated)]


class RunLogger:
    """Logs a run (static world, cameras, per-frame results, manifest, summary) to one ``.rrd``.

    Data streams to a temporary ``.rrd`` beside ``out_path`` as it is logged (memory does not
    grow with the run); :meth:`close` adds the default blueprint and renames the file into
    place, :meth:`discard` deletes it. Used as a context manager, an exception discards.

    Parameters
    ----------
    out_path : path
        The ``.rrd`` to write; its folder is created if needed. Replaced only by a complete
        file; a write failure (disk full, read-only) raises ``OutputError`` and leaves no
        temporary file.
    recording_name : str
        Shown in the viewer (scenario + setting).
    recording_id : str
        Rerun recording id; pin it so repeated runs produce comparable files.
    recording_start_ns : int, optional
        The recording's first stamp: ``elapsed`` counts from it. None: the first logged
        frame's ``log_time_ns``.
    max_reproj_px : float, optional
        The run's ``max_reproj_px`` setting, drawn as a threshold line on the reprojection
        plot; None: no line.
    """

    def __init__(
        self,
        out_path: str | os.PathLike,
        *,
        recording_name: str,
        recording_id: str,
        inputs: tuple[str | os.PathLike, ...] = (),
        recording_start_ns: int | None = None,
        max_reproj_px: float | None = None,
    ):
        # OutputError (from agvviz.errors) when out_path is an input or cannot be written.
        self._file = AtomicRrd(out_path, recording_id=recording_id, recording_name=recording_name, inputs=inputs)
        self._rec = self._file.rec
        #: ``elapsed`` = log time − this (ns); set from the first frame when not given.
        self.recording_start_ns = None if recording_start_ns is None else int(recording_start_ns)
        self.max_reproj_px = None if max_reproj_px is None else float(max_reproj_px)
        self._cam_names: list[str] = []
        self._image_width_px: dict[str, int] = {}
        self._fixed_cams: set[str] = set()
        #: Layout shipped at :meth:`close`; None: :func:`default_blueprint` of the cameras.
        self.blueprint = None
        self._start_time_sent = False
        self._saved = False
        self._trajectory_truth_m = _Track()
        self._trajectory_camera_m = _Track()
        self._columns = _Columns()
        self._frames_buffered = 0
        self._last_stamp: Stamp = (0, 0, 0.0)  # the stamp of the frame being logged
        # What the previous frame left drawn, so a state is logged only when it changes.
        self._camera_body_label: str | None = None  # None: not drawn yet; "": solved
        self._ghost_drawn = False
        self._lm_bars_drawn = False
        self._lm_points_drawn: set[str] = set()  # cameras whose LM points/path show now
        self._zoomed: set[str] = set()  # cameras whose zoom shows a crop now
        # What the run held, for the layout.
        self._zoom_cams: set[str] = set()
        self._lm_iterated = False
        self._rejected_frames = 0
        self._first_pose: np.ndarray | None = None
        self._cov_scale: float | None = None  # the ellipsoid's magnification (set once)
        self._budget_sources: list[str] | None = None  # an error budget was logged: its sources
        try:
            self._log_static_styles()
        except BaseException:  # no `with` block owns the file yet: discard it here
            self._file.discard()
            raise

    # -- static content --------------------------------------------------------------------
    def _log_static_styles(self) -> None:
        rec = self._rec
        rec.log(paths.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for entity, name, color in _FRAME_SERIES + _ITERATION_SERIES:
            rec.log(entity, rr.SeriesLines(names=name, colors=color, widths=1.5), static=True)
        if self.max_reproj_px is not None:
            rec.log(
                paths.ERROR_REPROJ_THRESHOLD_PX,
                rr.SeriesLines(
                    names=f"max_reproj_px = {self.max_reproj_px:g} px (above: frame rejected)",
                    colors=COLOR_THRESHOLD,
                    widths=1.0,
                ),
                static=True,
            )
        rec.log(
            paths.ERROR_REJECTED,
            rr.SeriesPoints(
                names="rejected frame (reasons: rejections log)",
                colors=COLOR_REJECTED,
                markers=rr.components.MarkerShape.Cross,
                marker_sizes=4.0,
            ),
            static=True,
        )
        for entity, color in (
            (paths.LM_LOG10_COST_PER_ITERATION, COLOR_CAMERA),
            (paths.LM_LOG10_DAMPING_PER_ITERATION, COLOR_OBSERVED),
            (paths.LM_LOG10_STEP_NORM_PER_ITERATION, COLOR_OBSERVED),
        ):  # a colour per BarChart call would cost more than its values
            rec.log(entity, [rr.components.ColorBatch([color]).described(rr.BarChart.descriptor_color())], static=True)
        for entity in (paths.AGV_TRUTH, paths.AGV_CAMERA):
            rec.log(entity, rr.TransformAxes3D(AGV_AXIS_LENGTH_M), static=True)
        rec.log(paths.AGV_TRUTH_BODY, self._body(COLOR_TRUTH, "truth"), static=True)
        rec.log(paths.TRAJECTORY_TRUTH, rr.LineStrips3D.from_fields(colors=COLOR_TRUTH, radii=rr.Radius.ui_points(2.0)), static=True)
        rec.log(paths.TRAJECTORY_CAMERA, rr.LineStrips3D.from_fields(colors=COLOR_CAMERA, radii=rr.Radius.ui_points(2.0)), static=True)
        rec.log(
            paths.AGV_CAMERA_POSITION_COV,
            rr.Ellipsoids3D.from_fields(
                colors=COLOR_CAMERA, fill_mode=rr.components.FillMode.MajorWireframe, show_labels=True
            ),
            static=True,
        )
        rec.log(
            paths.MARKERS_SEEN,
            rr.LineStrips3D.from_fields(colors=COLOR_DETECTED, radii=rr.Radius.ui_points(3.0), show_labels=True),
            static=True,
        )

    def _log_camera_styles(self, cam_name: str, fixed: bool) -> None:
        """Static colours, sizes and draw order of the per-frame 2D entities of ``cam_name``."""
        rec = self._rec
        for entity, color, radius, order, labels in (
            (paths.detected(cam_name, fixed), COLOR_DETECTED, DETECTED_RADIUS, 10.0, False),
            (paths.reprojected(cam_name, fixed), COLOR_REPROJECTED, REPROJECTED_RADIUS, 11.0, False),
            (paths.lm_iteration(cam_name, fixed), COLOR_OBSERVED, LM_ITERATION_RADIUS, 12.0, False),
            (paths.marker_ids(cam_name, fixed), COLOR_DETECTED, rr.Radius.ui_points(1.0), 13.0, True),
            (f"{paths.zoom(cam_name)}/image/detected", COLOR_DETECTED, DETECTED_RADIUS, 10.0, False),
            (f"{paths.zoom(cam_name)}/image/reprojected", COLOR_REPROJECTED, REPROJECTED_RADIUS, 11.0, False),
        ):
            rec.log(
                entity,
                rr.Points2D.from_fields(colors=color, radii=radius, draw_order=order, show_labels=labels),
                static=True,
            )
        rec.log(
            paths.lm_path(cam_name, fixed),
            rr.LineStrips2D.from_fields(colors=COLOR_OBSERVED, radii=rr.Radius.ui_points(1.0), draw_order=9.0),
            static=True,
        )

    def log_world_static(self, markers: list[tuple[str, np.ndarray]]) -> None:
        """Log the marker map: outlines with an id label and faint faces (static).

        Parameters
        ----------
        markers : list of (marker_id, corners_world_m)
            ``corners_world_m`` (4, 3) in world metres, order TL, TR, BR, BL.
        """
        self._check_open()
        if not markers:
            return
        ids = [str(marker_id) for marker_id, _ in markers]
        corners = [
            _as_array(c, (4, 3), f"corners_world_m of marker {marker_id!r}") for marker_id, c in markers
        ]
        outlines = [np.vstack([c, c[:1]]) for c in corners]  # closed loop TL→TR→BR→BL→TL
        self._rec.log(
            paths.MARKERS,
            rr.LineStrips3D(outlines, colors=COLOR_MARKER, labels=ids, radii=rr.Radius.ui_points(1.5)),
            static=True,
        )
        vertices = np.concatenate(corners, axis=0)
        quads = np.arange(len(corners))[:, None] * 4
        triangles = np.concatenate([quads + [0, 1, 2], quads + [0, 2, 3]], axis=0)
        self._rec.log(
            paths.MARKERS_FILL,
            rr.Mesh3D(
                vertex_positions=vertices,
                triangle_indices=triangles,
                vertex_colors=np.tile(COLOR_MARKER_FILL, (len(vertices), 1)),
            ),
            static=True,
        )

    def log_camera_static(self, cam_name: str, camera: PinholeCamera, T_agv_cam: np.ndarray) -> None:
        """Log camera ``cam_name``: extrinsic ``T_agv_cam`` and its Pinhole (static).

        The camera hangs under the estimated AGV pose, so its frustum shows where the
        pipeline places the camera. The Pinhole ignores lens distortion (Rerun draws an
        ideal pinhole); the recorded image and corners stay in distorted pixels.

        Parameters
        ----------
        cam_name : str
            Camera name (entity ``cam_<name>``).
        camera : PinholeCamera
            Intrinsics ``K`` and image size; the size must be known (> 0).
        T_agv_cam : (4, 4) array
            Camera pose in the AGV body frame.
        """
        self._check_open()
        if camera.width_px <= 0 or camera.height_px <= 0:
            raise RunLogError(
                f"camera {cam_name!r} has no image size ({camera.width_px}×{camera.height_px} px): "
                "log the camera with the width/height from its calibration"
            )
        T_agv_cam = _as_transform(T_agv_cam, f"T_agv_cam of camera {cam_name!r}")
        entity = paths.camera(cam_name)
        self._rec.log(entity, _transform3d(T_agv_cam), static=True)
        self._rec.log(entity, _pinhole(camera), static=True)
        self._log_camera_styles(cam_name, fixed=False)
        self._image_width_px[cam_name] = int(camera.width_px)
        if cam_name not in self._cam_names:
            self._cam_names.append(cam_name)

    def log_fixed_camera_static(self, cam_name: str, camera: PinholeCamera, T_world_cam: np.ndarray) -> None:
        """Log camera ``cam_name`` fixed in the world (paper 003): ``T_world_cam`` and its
        Pinhole under ``world/cameras`` (static); its images and corners go there too."""
        self._check_open()
        T_world_cam = _as_transform(T_world_cam, f"T_world_cam of camera {cam_name!r}")
        entity = paths.camera(cam_name, fixed=True)
        self._rec.log(entity, _transform3d(T_world_cam), static=True)
        self._rec.log(entity, _pinhole(camera), static=True)
        self._log_camera_styles(cam_name, fixed=True)
        self._image_width_px[cam_name] = int(camera.width_px)
        self._fixed_cams.add(cam_name)
        if cam_name not in self._cam_names:
            self._cam_names.append(cam_name)

    @property
    def stream(self) -> rr.RecordingStream:
        """The recording stream, for loggers of other modalities (UWB, fusion)."""
        return self._rec

    @property
    def cam_names(self) -> list[str]:
        return list(self._cam_names)

    @property
    def zoom_cams(self) -> list[str]:
        """Cameras that had a small code at least once (they have a zoomed view)."""
        return sorted(self._zoom_cams)

    # -- per frame -------------------------------------------------------------------------
    def _stamp(self, frame: FrameResult) -> Stamp:
        """Set ``frame``, ``time`` and ``elapsed`` for ``frame``'s logs; return them."""
        if self.recording_start_ns is None:
            self.recording_start_ns = int(frame.log_time_ns)
        set_stamp(self._rec, frame.index, frame.log_time_ns, self.recording_start_ns)
        self._last_stamp = (
            int(frame.index), int(frame.log_time_ns), elapsed_s(frame.log_time_ns, self.recording_start_ns)
        )
        return self._last_stamp

    def log_camera_view(self, frame: FrameResult) -> None:
        """Log only the image and corners of ``frame`` — another camera's view of a time
        stamp whose pose and errors :meth:`log_frame` logged from the chosen camera."""
        self._check_open()
        _check_frame(frame)
        self._stamp(frame)
        self._log_image(frame)
        self._log_corners(frame)

    def log_frame(self, frame: FrameResult) -> None:
        """Log everything one frame produced at ``time = log_time_ns`` and ``frame = index``.

        The estimated pose is shown for solved frames only; on a rejected frame the estimate
        keeps its last pose and its body turns grey with the reason as label, and the error
        lines break. The frame is checked completely before anything is logged, so a bad
        frame logs nothing.
        """
        self._check_open()
        self._file.check()  # stop at once when the disk is full, not after the whole run
        _check_frame(frame)
        stamp = self._stamp(frame)
        if not self._start_time_sent:
            self._rec.send_recording_start_time_nanos(int(self.recording_start_ns))
            self._start_time_sent = True
        self._log_image(frame)
        self._log_corners(frame)
        self._log_markers_seen(frame)
        self._log_poses(frame, stamp)
        self._log_errors(frame, stamp)
        self._log_lm(frame, stamp)
        self._log_uncertainty(frame, stamp)
        self._frames_buffered += 1
        if self._frames_buffered >= FLUSH_EVERY_FRAMES:
            self._flush()

    def _flush(self) -> None:
        self._columns.flush(self._rec)
        self._frames_buffered = 0

    def _log_image(self, frame: FrameResult) -> None:
        if not frame.image_bytes:
            return  # corner-only recordings carry no image
        # What rr.EncodedImage(contents=..., media_type=...) logs, without building the
        # archetype: the blob wraps the bytes without a copy, the media type is built once.
        data = pa.py_buffer(frame.image_bytes)
        blob = pa.ListArray.from_arrays(
            pa.array([0, data.size], type=pa.int32()),
            pa.Array.from_buffers(pa.uint8(), data.size, [None, data]),
            type=_BLOB_TYPE,
        )
        self._rec.log(
            paths.image(frame.cam_name, frame.cam_name in self._fixed_cams),
            [rr.DescribedComponentBatch(_ArrowBatch(blob), _BLOB_DESCRIPTOR), _media_type_batch(MEDIA_TYPES[frame.image_format])],
        )

    def _log_corners(self, frame: FrameResult) -> None:
        """Detected and reprojected corners, each code's id at its centre, and the zoomed view
        of a small code. Empty batches on frames without corners, so the previous frame's
        points vanish."""
        detected, detected_ids, reprojected, reprojected_ids, centres = [], [], [], [], []
        for obs in frame.observations:
            corners = np.asarray(obs.corners_px, dtype=float)
            detected.append(corners)
            # A ChArUco board's saddles carry their own label (board<k>:chessboard).
            detected_ids += [obs.marker_id] * len(corners)
            centres.append((corners if is_chessboard_id(obs.marker_id) else corners[:4]).mean(axis=0))
            if obs.reprojected_px is not None:
                reproj = np.asarray(obs.reprojected_px, dtype=float)
                reprojected.append(reproj)
                reprojected_ids += [obs.marker_id] * len(reproj)
        fixed = frame.cam_name in self._fixed_cams
        stamp = self._last_stamp
        row = self._columns.row
        row(
            paths.detected(frame.cam_name, fixed), "points2d", stamp,
            np.concatenate(detected) if detected else np.zeros((0, 2)), detected_ids,
        )
        row(
            paths.reprojected(frame.cam_name, fixed), "points2d", stamp,
            np.concatenate(reprojected) if reprojected else np.zeros((0, 2)), reprojected_ids,
        )
        row(
            paths.marker_ids(frame.cam_name, fixed), "points2d", stamp,
            np.array(centres) if centres else np.zeros((0, 2)),
            [f"id {obs.marker_id}" for obs in frame.observations],
        )
        self._log_zoom(frame)

    def _log_zoom(self, frame: FrameResult) -> None:
        """A crop of the image around the smallest code when it is under ZOOM_CODE_BELOW_FRACTION
        of the image width (a camera logged without its size is never zoomed)."""
        cam = frame.cam_name
        below_px = ZOOM_CODE_BELOW_FRACTION * self._image_width_px.get(cam, 0)
        small = []  # (longest edge, observation) of the codes under the threshold
        if below_px > 0 and frame.image_bytes:
            for obs in frame.observations:
                if is_chessboard_id(obs.marker_id):
                    continue  # saddles, not a code's outline
                edge_px = _longest_edge_px(np.asarray(obs.corners_px, float)[:4])
                if edge_px < below_px:
                    small.append((edge_px, obs))
        crop = None
        if small:
            _, obs = min(small, key=lambda edge_obs: edge_obs[0])
            crop = _crop_around(frame.image_bytes, np.asarray(obs.corners_px, float)[:4])
        root = paths.zoom(cam)
        if crop is None:
            if cam in self._zoomed:
                self._rec.log(root, rr.Clear(recursive=True))
                self._zoomed.discard(cam)
            return
        png, origin_px, px_per_image_px = crop
        obs_points = [(np.asarray(o.corners_px, float), o.reprojected_px) for o in frame.observations]
        detected = (np.concatenate([c for c, _ in obs_points]) - origin_px) * px_per_image_px
        reprojected = [np.asarray(r, float) for _, r in obs_points if r is not None]
        rec = self._rec
        rec.log(f"{root}/image", rr.EncodedImage(contents=png, media_type="image/png"))
        rec.log(f"{root}/image/detected", rr.Points2D(detected))
        rec.log(
            f"{root}/image/reprojected",
            rr.Points2D(
                (np.concatenate(reprojected) - origin_px) * px_per_image_px if reprojected else np.zeros((0, 2))
            ),
        )
        self._zoomed.add(cam)
        self._zoom_cams.add(cam)

    def _log_markers_seen(self, frame: FrameResult) -> None:
        """The outline and id of every code of this frame in 3D (world-fixed codes only)."""
        outlines, labels = [], []
        for obs in frame.observations:
            if obs.points_frame != "world":
                continue
            corners = np.asarray(obs.points_world_m, dtype=float)
            corners = _outline_of_points(corners) if is_chessboard_id(obs.marker_id) else corners[:4]
            outlines.append(np.vstack([corners, corners[:1]]))
            used = (
                " (used)" if obs.marker_id in (frame.used_marker_ids or (frame.used_marker_id,))
                else " (left out)" if obs.marker_id in frame.excluded_marker_ids else ""
            )
            labels.append(f"id {obs.marker_id}{used}")
        self._columns.row(paths.MARKERS_SEEN, "strips3d", self._last_stamp, outlines, labels)

    def _log_poses(self, frame: FrameResult, stamp: Stamp) -> None:
        rec = self._rec
        if frame.T_world_agv_truth is not None:
            T_truth = np.asarray(frame.T_world_agv_truth, dtype=float)
            self._columns.transform(paths.AGV_TRUTH, stamp, T_truth)
            self._trajectory_truth_m.append(T_truth[:3, 3])
            self._columns.row(paths.TRAJECTORY_TRUTH, "strip3d", stamp, _thinned(self._trajectory_truth_m.array()))
        if frame.solved:
            T_est = np.asarray(frame.T_world_agv, dtype=float)
            if self._first_pose is None:
                self._first_pose = T_est
            self._columns.transform(paths.AGV_CAMERA, stamp, T_est)
            if self._camera_body_label != "":
                rec.log(paths.AGV_CAMERA_BODY, self._body(COLOR_CAMERA))
                self._camera_body_label = ""
            self._trajectory_camera_m.append(T_est[:3, 3])
            self._columns.row(paths.TRAJECTORY_CAMERA, "strip3d", stamp, _thinned(self._trajectory_camera_m.array()))
        else:
            # The estimate entity keeps its last pose; grey it so a stale pose is not mistaken
            # for this frame's answer.
            stale = "no estimate yet" if not self._trajectory_camera_m else "last estimate"
            label = f"rejected: {frame.rejected} ({stale})"
            if label != self._camera_body_label:
                rec.log(paths.AGV_CAMERA_BODY, self._body(COLOR_STALE, label))
                self._camera_body_label = label

    def _log_errors(self, frame: FrameResult, stamp: Stamp) -> None:
        columns = self._columns
        for entity, value in (
            (paths.ERROR_POSITION_MM, None if frame.position_error_m is None else 1000.0 * frame.position_error_m),
            (paths.ERROR_HEADING_DEG, frame.heading_error_deg),
            (paths.ERROR_PITCH_DEG, frame.pitch_error_deg),
            (paths.ERROR_ROLL_DEG, frame.roll_error_deg),
            (paths.ERROR_REPROJ_RMS_PX, frame.reproj_rms_px),
        ):
            if value is not None:
                columns.scalar(entity, stamp, value)
            elif not frame.solved:
                columns.gap(entity, stamp)  # the line breaks at a rejected frame
        if self.max_reproj_px is not None:
            columns.scalar(paths.ERROR_REPROJ_THRESHOLD_PX, stamp, self.max_reproj_px)
        if not frame.solved:
            self._rejected_frames += 1
            columns.scalar(paths.ERROR_REJECTED, stamp, 0.0)
            detail = f" — {frame.reject_detail}" if frame.reject_detail else ""
            self._rec.log(
                paths.EVENTS_REJECTIONS,
                rr.TextLog(
                    f"frame {frame.index} ({frame.cam_name}): {frame.rejected}{detail}",
                    level=rr.TextLogLevel.WARN,
                ),
            )

    def _log_uncertainty(self, frame: FrameResult, stamp: Stamp) -> None:
        """NEES, error ÷ CRLB, ambiguity ratio, flips, the covariance ellipsoid and the ghost."""
        rec = self._rec
        columns = self._columns
        for entity, value in (
            (paths.ERROR_NEES, frame.nees),
            (paths.ERROR_POSITION_OVER_CRLB, frame.position_over_crlb),
            (paths.ERROR_CRLB_POSITION_M, frame.crlb_position_m),
            (paths.ERROR_POSITION_SIGMA_M, frame.position_sigma_m),
        ):
            if value is not None and math.isfinite(value):
                columns.scalar(entity, stamp, value)
            elif not frame.solved:
                columns.gap(entity, stamp)
        if frame.ambiguity_ratio is not None:
            columns.scalar(paths.SOLVER_AMBIGUITY_RATIO, stamp, min(float(frame.ambiguity_ratio), AMBIGUITY_RATIO_CAP))
        elif not frame.solved:
            columns.gap(paths.SOLVER_AMBIGUITY_RATIO, stamp)
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
            if self._cov_scale is None:
                self._cov_scale = _cov_scale(np.asarray(frame.position_cov_world_m2, dtype=float))
            columns.row(paths.AGV_CAMERA_POSITION_COV, "ellipsoid", stamp, *_covariance_ellipsoid(frame, self._cov_scale))
        else:
            columns.gap(paths.AGV_CAMERA_POSITION_COV, stamp)
        ratio = frame.ambiguity_ratio
        if frame.solved and frame.T_world_agv_ghost is not None and ratio is not None and ratio < GHOST_MAX_AMBIGUITY_RATIO:
            rec.log(paths.AGV_GHOST, _transform3d(np.asarray(frame.T_world_agv_ghost, dtype=float)))
            label = f"IPPE mirror pose: ambiguity ratio {ratio:.2f} < {GHOST_MAX_AMBIGUITY_RATIO:g}"
            rec.log(paths.AGV_GHOST_BODY, self._body(COLOR_GHOST, label))
            self._ghost_drawn = True
        elif self._ghost_drawn:
            rec.log(paths.AGV_GHOST_BODY, rr.Clear(recursive=False))
            self._ghost_drawn = False

    def _log_lm(self, frame: FrameResult, stamp: Stamp) -> None:
        """The frame's solve: LM iterations as bar charts (log10) and lm_iter columns, the
        reprojected points of each iteration, and a line of text; or "closed-form"."""
        rec = self._rec
        iterations: tuple[LmIteration, ...] = tuple(frame.lm_iterations)
        self._columns.row(paths.LM_THIS_FRAME, "markdown", stamp, _lm_text(frame))
        if not iterations:
            self._log_lm_points(frame, stamp, ())
            if self._lm_bars_drawn:
                for entity in (
                    paths.LM_LOG10_COST_PER_ITERATION,
                    paths.LM_LOG10_DAMPING_PER_ITERATION,
                    paths.LM_LOG10_STEP_NORM_PER_ITERATION,
                ):
                    rec.log(entity, rr.Clear(recursive=False))
                self._lm_bars_drawn = False
            return
        self._lm_iterated = True
        self._lm_bars_drawn = True
        cost = np.array([it.cost for it in iterations], dtype=float)
        damping = np.array([it.damping for it in iterations], dtype=float)
        step = np.array([it.step_norm for it in iterations], dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            log10_cost = np.log10(cost)
        for entity, values in (
            (paths.LM_LOG10_COST_PER_ITERATION, log10_cost),
            (paths.LM_LOG10_DAMPING_PER_ITERATION, damping),
            (paths.LM_LOG10_STEP_NORM_PER_ITERATION, step),
        ):
            with np.errstate(divide="ignore", invalid="ignore"):
                logged = values if entity == paths.LM_LOG10_COST_PER_ITERATION else np.log10(values)
            # Bar i is record i (the step norm: trial step i + 1; record 0, the start, has no
            # step). No abscissa: it would triple the logging cost of a bar chart.
            logged = logged[1:] if entity == paths.LM_LOG10_STEP_NORM_PER_ITERATION else logged
            self._columns.row(entity, "bar_chart", stamp, np.where(np.isfinite(logged), logged, np.nan))
        columns = self._columns
        columns.scalar(paths.LM_ITERATIONS, stamp, len(iterations) - 1)
        for entity, values in (
            (paths.LM_COST, cost),
            (paths.LM_LOG10_COST, np.where(np.isfinite(log10_cost), log10_cost, np.nan)),
            (paths.LM_REPROJ_RMS_PX, [it.reproj_rms_px for it in iterations]),
            (paths.LM_DAMPING, damping),
            (paths.LM_STEP_NORM, step),
        ):
            columns.iterations(entity, stamp, values)
        # One (N, 2) array in image pixels per LM record (the solve stage's lm_iteration_px).
        self._log_lm_points(frame, stamp, frame.lm_iteration_px)

    def _log_lm_points(self, frame: FrameResult, stamp: Stamp, per_iteration_px) -> None:
        """Each LM iteration's reprojected points (``lm_iter`` columns) and each point's path
        start → final (this frame); both cleared on a frame without them."""
        fixed = frame.cam_name in self._fixed_cams
        points_entity, path_entity = paths.lm_iteration(frame.cam_name, fixed), paths.lm_path(frame.cam_name, fixed)
        if len(per_iteration_px) and len(per_iteration_px) == len(frame.lm_iterations):
            arrays = [np.asarray(p, dtype=float).reshape(-1, 2) for p in per_iteration_px]
            self._columns.iteration_points(points_entity, stamp, arrays)
            tracks = np.stack(arrays, axis=1)  # (N points, iterations, 2): each point's path
            self._columns.row(path_entity, "strips2d", stamp, tracks)
            self._lm_points_drawn.add(frame.cam_name)
        elif frame.cam_name in self._lm_points_drawn:
            self._columns.gap(points_entity, stamp)  # frame/time/elapsed only: lm_iter untouched
            self._columns.gap(path_entity, stamp)
            self._lm_points_drawn.discard(frame.cam_name)

    # -- run documents ---------------------------------------------------------------------
    def log_manifest(self, manifest: dict) -> None:
        """Log the run manifest (settings, recording hash, version) as static markdown."""
        self._check_open()
        text = _markdown_document("Run manifest", manifest)
        self._rec.log(paths.RUN_MANIFEST, _markdown(text), static=True)

    def log_error_budget(self, budget) -> None:
        """Log an :class:`agvviz.evaluation.error_budget.ErrorBudget` of this run (its table,
        bar chart of shares and per-frame series, :mod:`agvviz.viz.budget_logger`); the default
        layout then shows them."""
        from agvviz.viz import budget_logger

        self._check_open()
        budget_logger.log_budget(self._rec, budget, self.recording_start_ns)
        self._budget_sources = [s.source for s in budget.sources]

    def log_summary(self, summary: dict) -> None:
        """Log the run summary as static markdown: the terminal's table
        (:func:`agvviz.evaluation.summary_table.summary_rows`, without the wall-clock rows),
        recording damage and warnings, then the whole summary as a JSON block."""
        self._check_open()
        self._rec.log(paths.RUN_SUMMARY, _markdown(_summary_markdown(summary)), static=True)

    # -- output ----------------------------------------------------------------------------
    def close(self) -> None:
        """Finish the file: send the buffered columns, ship the default blueprint, write the
        footer, move it into place."""
        self._check_open()
        self._flush()
        self._saved = True
        blueprint = self.blueprint
        if blueprint is None:
            blueprint = default_blueprint(
                self._cam_names,
                fixed_cams=self._fixed_cams,
                zoom_cams=self.zoom_cams,
                lm_iterates=self._lm_iterated,
                has_rejections=self._rejected_frames > 0,
                has_threshold=self.max_reproj_px is not None,
                ghost_max_ratio=GHOST_MAX_AMBIGUITY_RATIO,
                cov_scale=self._cov_scale,
                start_m=None if self._first_pose is None else tuple(self._first_pose[:3, 3]),
                budget_sources=self._budget_sources,
            )
        self._file.commit(blueprint)

    def discard(self) -> None:
        """Stop logging and delete the unfinished file; ``out_path`` is left untouched."""
        self._saved = True
        self._file.discard()

    def __enter__(self) -> "RunLogger":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()
        elif not self._saved:
            self.close()

    # -- helpers ---------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._saved:
            raise RunLogError("this RunLogger was already closed; create a new one for another run")

    @staticmethod
    def _body(color: tuple[int, int, int], label: str = "") -> rr.Boxes3D:
        """The nominal AGV body box; labelled only when it needs explaining (stale pose)."""
        return rr.Boxes3D(
            half_sizes=[AGV_BODY_HALF_SIZES_M],
            centers=[AGV_BODY_CENTER_M],
            colors=color,
            labels=[label] if label else [],  # empty clears a previous stale label
            radii=rr.Radius.ui_points(1.5),
        )


def _cov_scale(position_cov_m2: np.ndarray) -> float:
    """The power of ten (≥ 1) that draws the largest 3σ half-axis about COV_DRAWN_HALF_AXIS_M."""
    largest_3sigma_m = 3.0 * math.sqrt(max(float(np.max(np.linalg.eigvalsh(position_cov_m2))), 0.0))
    if largest_3sigma_m <= 0.0 or not math.isfinite(largest_3sigma_m):
        return 1.0
    return float(10.0 ** max(0, round(math.log10(COV_DRAWN_HALF_AXIS_M / largest_3sigma_m))))


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


def _lm_text(frame: FrameResult) -> str:
    """One line on what the solver did in ``frame`` (and which markers made the pose)."""
    text = _solve_text(frame)
    markers = ""
    if len(frame.used_marker_ids) > 1:
        markers = f"markers {', '.join(frame.used_marker_ids)} jointly"
    if frame.excluded_marker_ids:
        markers += f"{'; ' if markers else ''}**left out {', '.join(frame.excluded_marker_ids)}**"
    if markers:
        text = f"{markers} — {text}"
    if frame.marker_note:
        text += f"  \n{frame.marker_note}"
    return text


def _solve_text(frame: FrameResult) -> str:
    iterations = frame.lm_iterations
    outcome = "solved" if frame.solved else f"rejected: {frame.rejected}"
    if not iterations:
        if frame.solved:
            rms = "" if frame.reproj_rms_px is None else f"; reprojection RMS {frame.reproj_rms_px:.3g} px"
            return f"**closed-form solver: no iterations** (frame {frame.index}, {outcome}{rms})"
        return f"**no solve** (frame {frame.index}, {outcome})"
    first, last = iterations[0], iterations[-1]
    steps = len(iterations) - 1
    accepted = sum(it.accepted for it in iterations[1:])
    return (
        f"**LM, frame {frame.index}** ({outcome}): {steps} trial steps, {accepted} accepted; "
        f"cost (½ sum of squared residuals) {first.cost:.3g} → {last.cost:.3g}; reprojection RMS "
        f"{first.reproj_rms_px:.3g} → {last.reproj_rms_px:.3g} px"
    )


def _longest_edge_px(corners_px: np.ndarray) -> float:
    """Longest edge of a code's outline (TL, TR, BR, BL) in pixels."""
    return float(np.max(np.linalg.norm(corners_px - np.roll(corners_px, 1, axis=0), axis=1)))


def _crop_around(image_bytes: bytes, corners_px: np.ndarray) -> tuple[bytes, np.ndarray, float] | None:
    """PNG of a square crop of the image centred on the code, resized to ZOOM_SIDE_PX; the
    crop's top-left pixel and the zoom's pixels per image pixel. None when the image does not
    decode."""
    image = cv2.imdecode(np.frombuffer(image_bytes, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    height, width = image.shape[:2]
    side = int(max(ZOOM_MIN_CROP_PX, math.ceil(ZOOM_CROP_CODE_SIDES * _longest_edge_px(corners_px))))
    centre = corners_px.mean(axis=0)
    x0 = int(np.clip(round(centre[0] - side / 2), 0, max(width - side, 0)))
    y0 = int(np.clip(round(centre[1] - side / 2), 0, max(height - side, 0)))
    crop = image[y0 : y0 + side, x0 : x0 + side]
    if crop.shape[0] != crop.shape[1]:  # an image smaller than the crop: pad it square
        side = max(crop.shape[:2])
        crop = cv2.copyMakeBorder(crop, 0, side - crop.shape[0], 0, side - crop.shape[1], cv2.BORDER_CONSTANT)
    zoomed = cv2.resize(crop, (ZOOM_SIDE_PX, ZOOM_SIDE_PX), interpolation=cv2.INTER_NEAREST)
    ok, png = cv2.imencode(".png", zoomed)
    if not ok:
        return None
    return png.tobytes(), np.array([x0, y0], dtype=float), ZOOM_SIDE_PX / side


def _summary_markdown(summary: dict) -> str:
    """The run summary panel: the terminal table when the summary has its sections (any other
    dict: key/value rows), damage and warnings, then the JSON block."""
    rows = summary_rows(summary, {})
    if not rows:
        return _markdown_document("Run summary", summary)
    notes = [f"- recording damage: {p}" for p in summary.get("recording_damage", [])]
    notes += [f"- warning: {w}" for w in summary.get("warnings", [])]
    block = _json_block("run summary", summary)
    parts = ["### Run summary", markdown_table(rows)]
    if notes:
        parts.append("\n".join(notes))
    parts.append(f"#### Full summary (JSON)\n\n```json\n{block}\n```\n")
    return "\n\n".join(parts)


def _thinned(positions_m: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """At most MAX_TRAJECTORY_POINTS of ``positions_m``, evenly spread, first and last kept."""
    n = len(positions_m)
    if n <= MAX_TRAJECTORY_POINTS and isinstance(positions_m, np.ndarray):
        return positions_m.copy()
    keep = np.unique(np.linspace(0, n - 1, min(n, MAX_TRAJECTORY_POINTS)).round().astype(int))
    if isinstance(positions_m, np.ndarray):
        return positions_m[keep]
    return np.array([positions_m[i] for i in keep])


def _pinhole(camera: PinholeCamera) -> rr.Pinhole:
    """The frustum of ``camera`` (an ideal pinhole: Rerun does not draw lens distortion)."""
    return rr.Pinhole(
        image_from_camera=camera.K,
        resolution=[camera.width_px, camera.height_px],
        camera_xyz=rr.ViewCoordinates.RDF,
        image_plane_distance=FRUSTUM_IMAGE_PLANE_M,
        color=COLOR_CAMERA,
    )


def _outline_of_points(points_m: np.ndarray) -> np.ndarray:
    """The convex hull (in their plane) of coplanar 3-D points: a board's saddles seen."""
    centre = points_m.mean(axis=0)
    if len(points_m) < 3:
        return points_m
    _, _, Vt = np.linalg.svd(points_m - centre)
    uv = ((points_m - centre) @ Vt[:2].T).astype(np.float32)
    hull = cv2.convexHull(uv, returnPoints=False).ravel()
    return points_m[hull]


def _check_frame(frame: FrameResult) -> None:
    """Raise RunLogError if ``frame`` cannot be logged as it is."""
    where = f"frame {frame.index}"
    if frame.image_format not in MEDIA_TYPES:
        raise RunLogError(
            f"{where}: image_format {frame.image_format!r} is not one of {sorted(MEDIA_TYPES)}"
        )
    for obs in frame.observations:
        _as_array(obs.corners_px, (-1, 2), f"{where}: corners_px of marker {obs.marker_id!r}")
        if obs.reprojected_px is not None:
            _as_array(obs.reprojected_px, (-1, 2), f"{where}: reprojected_px of marker {obs.marker_id!r}")
    if frame.T_world_agv_truth is not None:
        _as_transform(frame.T_world_agv_truth, f"{where}: T_world_agv_truth")
    if frame.T_world_agv_ghost is not None:
        _as_transform(frame.T_world_agv_ghost, f"{where}: T_world_agv_ghost")
    if frame.position_cov_world_m2 is not None:
        _as_array(frame.position_cov_world_m2, (3, 3), f"{where}: position_cov_world_m2")
    if frame.solved:
        if frame.T_world_agv is None:
            raise RunLogError(f"{where} is solved (rejected is None) but has no T_world_agv")
        _as_transform(frame.T_world_agv, f"{where}: T_world_agv")


def _as_array(value, shape: tuple[int, int], what: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (-1 = any length), else RunLogError."""
    a = np.asarray(value, dtype=float)
    if a.ndim != 2 or any(want not in (-1, got) for want, got in zip(shape, a.shape)):
        raise RunLogError(f"{what} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise RunLogError(f"{what} contains NaN or inf")
    return a


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def _as_transform(T, what: str) -> np.ndarray:
    T = _as_array(T, (4, 4), what)
    # np.allclose(T[3], [0, 0, 0, 1]) (rtol 1e-5, atol 1e-8) for finite T, without its overhead
    if not np.all(np.abs(T[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW):
        raise RunLogError(f"{what} is not a homogeneous transform (last row {T[3].tolist()})")
    return T


def _transform3d(T_parent_child: np.ndarray) -> rr.Transform3D:
    """Transform3D placing the child entity at ``T_parent_child`` in its parent."""
    return rr.Transform3D(translation=T_parent_child[:3, 3], mat3x3=T_parent_child[:3, :3])


def _trajectory(positions_m: list[np.ndarray], color: tuple[int, int, int]) -> rr.LineStrips3D:
    """The trajectory so far, thinned to at most MAX_TRAJECTORY_POINTS (first and last kept)."""
    return rr.LineStrips3D([_thinned(positions_m)], colors=color, radii=rr.Radius.ui_points(2.0))


def _markdown(text: str) -> rr.TextDocument:
    return rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN)


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _json_block(what: str, content: dict) -> str:
    """``content`` as indented JSON (RunLogError when it is not serialisable)."""
    try:
        return json.dumps(content, indent=2, sort_keys=True, default=_json_default, allow_nan=True)
    except TypeError as exc:
        raise RunLogError(f"{what} is not JSON serialisable: {exc}") from exc


def _markdown_document(title: str, content: dict) -> str:
    """Markdown: a key/value table (nested dicts flattened with dots) and a JSON block."""
    block = _json_block(title.lower(), content)
    rows = []
    for key, value in _flatten(json.loads(block)):
        if isinstance(value, float):
            text = f"{value:.6g}" if math.isfinite(value) else str(value)
        else:
            text = json.dumps(value) if isinstance(value, list) else str(value)
        escaped = text.replace("|", "\\|")
        rows.append(f"| {key} | {escaped} |")
    table = "\n".join(["| key | value |", "| --- | --- |", *rows])
    return f"# {title}\n\n{table}\n\n```json\n{block}\n```\n"


def _flatten(content: dict, prefix: str = ""):
    for key, value in content.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value
