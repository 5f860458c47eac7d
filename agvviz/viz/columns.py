"""Per-frame values held in memory and sent to Rerun as columns — shared by the frame, LM and
uncertainty loggers of a run (:mod:`agvviz.viz.run_logger`).

Every per-frame value except the image is buffered in :class:`Columns` and sent as one
``send_columns`` per entity at each flush (issue 12): the data are those the per-frame archetypes
would carry (same entities, components, values and timelines; only the chunking differs).
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import rerun as rr

from agvviz.viz import paths

#: (frame index, log_time_ns, elapsed seconds) of one log.
Stamp = tuple[int, int, float]

_STRIP2D_TYPE = rr.components.LineStrip2DBatch._ARROW_DATATYPE


class Columns:
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
        #: entity -> (lowest, highest) finite per-frame scalar of the whole run (kept across
        #: flushes): the plots' axes are set from them so no value is cut off.
        self.extents: dict[str, tuple[float, float]] = {}

    def row(self, entity: str, kind: str, stamp: Stamp, *payload) -> None:
        """One frame's value of ``entity`` as an archetype of ``kind`` (a key of _ROW_COLUMNS)."""
        self._rows.setdefault((entity, kind), []).append((stamp, payload))

    def scalar(self, entity: str, stamp: Stamp, value: float) -> None:
        value = float(value)
        self._scalars.setdefault(entity, []).append((stamp, value))
        if math.isfinite(value):
            low, high = self.extents.get(entity, (value, value))
            self.extents[entity] = (min(low, value), max(high, value))

    def extend(self, entity: str, stamps: list[Stamp], value: float) -> None:
        """The same ``value`` at each of ``stamps`` (markers drawn at one height)."""
        self._scalars.setdefault(entity, []).extend((stamp, float(value)) for stamp in stamps)

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
                indexes=time_columns([stamp for stamp, _ in rows]),
                columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]),
            )
        for (entity, kind), rows in self._rows.items():
            rec.send_columns(
                entity,
                indexes=time_columns([stamp for stamp, _ in rows]),
                columns=_ROW_COLUMNS[kind]([payload for _, payload in rows]),
            )
        for entity, rows in self._scalars.items():
            rec.send_columns(
                entity,
                indexes=time_columns([stamp for stamp, _ in rows]),
                columns=rr.Scalars.columns(scalars=np.array([value for _, value in rows])),
            )
        for entity, stamps in self._gaps.items():
            rec.send_columns(
                entity,
                indexes=time_columns(stamps),
                columns=rr.Clear.columns(is_recursive=np.zeros(len(stamps), dtype=bool)),
            )
        for entity, rows in self._iterations.items():
            counts = [len(values) for _, values in rows]
            rec.send_columns(
                entity,
                indexes=iterationtime_columns([stamp for stamp, _ in rows], counts),
                columns=rr.Scalars.columns(scalars=np.concatenate([values for _, values in rows])),
            )
        for entity, rows in self._points.items():
            counts = [len(per_iteration) for _, per_iteration in rows]
            arrays = [points for _, per_iteration in rows for points in per_iteration]
            rec.send_columns(
                entity,
                indexes=iterationtime_columns([stamp for stamp, _ in rows], counts),
                columns=rr.Points2D.columns(positions=np.concatenate(arrays)).partition([len(a) for a in arrays]),
            )
        self._scalars, self._gaps, self._iterations, self._points, self._transforms = {}, {}, {}, {}, {}
        self._rows = {}
        # Arrow's allocator keeps what the columns' arrays freed for later; given back at each
        # flush (≈0.05 ms), it does not pile up over a long run (issue 27: ≈6 MiB at 2000 frames).
        pa.default_memory_pool().release_unused()


class ArrowBatch:
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
    return [rr.ComponentColumn(rr.LineStrips2D.descriptor_strips(), ArrowBatch(strips), lengths=row_lengths)]


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
    # Every array is built with its final type: Array.cast would import pyarrow.compute (≈30 ms
    # of a run's start, issue 27) for a cast that changes only the field names and nullability.
    shape = pa.ListArray.from_arrays(
        pa.array(np.arange(n_rows + 1, dtype=np.int32)), pa.array(lengths.astype(np.uint64)), type=shape_type
    )
    names = pa.nulls(n_rows, type=data_type.field("names").type)
    buffer_type = data_type.field("buffer").type
    f64 = [f.name for f in buffer_type].index("F64")
    flat = np.concatenate(values).astype(np.float64) if n_rows else np.zeros(0)
    child = pa.ListArray.from_arrays(pa.array(offsets), pa.array(flat), type=buffer_type[f64].type)
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
    tensors = pa.StructArray.from_arrays([shape, names, buffer], fields=list(data_type))
    return [rr.ComponentColumn(rr.BarChart.descriptor_values(), ArrowBatch(tensors))]



#: Builders of per-frame archetype columns, by the ``kind`` given to :meth:`Columns.row`.
_ROW_COLUMNS = {
    "points2d": _points2d_columns,
    "strips3d": _strips3d_columns,
    "strip3d": _strip3d_columns,
    "strips2d": _strips2d_columns,
    "ellipsoid": _ellipsoid_columns,
    "markdown": _markdown_columns,
    "bar_chart": _bar_chart_columns,
}


def time_columns(stamps: list[Stamp]) -> list[rr.TimeColumn]:
    """``frame``, ``time`` and ``elapsed`` index columns of ``stamps``."""
    frames, times_ns, elapsed = zip(*stamps)
    return [
        rr.TimeColumn(paths.TIMELINE_FRAME, sequence=np.asarray(frames, dtype=np.int64)),
        rr.TimeColumn(paths.TIMELINE_TIME, timestamp=np.asarray(times_ns, dtype=np.int64).astype("datetime64[ns]")),
        rr.TimeColumn(paths.TIMELINE_ELAPSED, duration=np.asarray(elapsed, dtype=float)),
    ]


def iterationtime_columns(stamps: list[Stamp], counts: list[int]) -> list[rr.TimeColumn]:
    """``lm_iter`` (0..n-1 per frame) plus each frame's stamp repeated over its iterations."""
    repeated = [stamp for stamp, n in zip(stamps, counts) for _ in range(n)]
    lm_iter = np.concatenate([np.arange(n) for n in counts]) if counts else np.zeros(0, dtype=np.int64)
    return [rr.TimeColumn(paths.TIMELINE_LM_ITER, sequence=lm_iter), *time_columns(repeated)]
