"""Read a run ``.rrd`` back with Rerun's own chunk API (``rerun.chunk.RrdReader``).

Used by the tests and by ``agvviz diff``. Entity paths are given and returned as in
:mod:`agvviz.viz.paths` (no leading slash). Every function accepts a path or the
:class:`RrdContents` from :func:`read_rrd` (open once, query many times); chunk data is
loaded only for the entity asked for.
"""

from __future__ import annotations

from agvviz.errors import InputError

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
from rerun.chunk import ChunkStore, LazyStore, RrdReader

from agvviz.viz import paths

_ROW_ID = "rerun.controls.RowId"


class RrdReadError(InputError):
    """The ``.rrd`` is missing, unreadable, or lacks the entity/component asked for."""


@dataclass
class RrdContents:
    """An opened run ``.rrd``: its recording store and the entity paths it holds. For one
    setting of a sweep ``.rrd`` (``FILE#SETTING``), that setting's layers with the
    ``settings/<key>/`` prefix taken off, as in a run ``.rrd``; ``setting`` its label."""

    path: Path
    store: LazyStore | ChunkStore
    entity_paths: set[str]
    setting: str | None = None


#: ``FILE#SETTING`` names one setting inside a sweep ``.rrd`` (``sweep.rrd#ippe``,
#: ``sweep.rrd#solver=ippe``): wherever a run ``.rrd`` is read (diff, export, readback).
SETTING_SEPARATOR = "#"


def split_setting(path: str | os.PathLike) -> tuple[Path, str | None]:
    """``"runs/s.rrd#ippe"`` → ``(Path("runs/s.rrd"), "ippe")``; a path without ``#`` (or a
    file whose name holds one) → ``(path, None)``."""
    text = os.fspath(path)
    if SETTING_SEPARATOR not in text or Path(text).exists():
        return Path(text), None
    file, _, setting = text.rpartition(SETTING_SEPARATOR)
    return Path(file), setting.strip()


def read_rrd(path: str | os.PathLike) -> RrdContents:
    """Open the recording in ``path`` (chunk data stays on disk until queried); ``FILE#SETTING``
    opens one setting of a sweep ``.rrd`` (:func:`setting_contents`)."""
    path, setting = split_setting(path)
    if setting is not None:
        return setting_contents(read_rrd(path), setting)
    if not path.is_file():
        raise RrdReadError(f"no .rrd file at {path}" + (" (that is a folder)" if path.is_dir() else ""))
    _check_magic(path)
    try:
        store = RrdReader(path).store()
        entity_paths = {p.lstrip("/") for p in store.schema().entity_paths()}
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # noqa: BLE001 — Rerun raises RuntimeError, or panics, on damage
        raise RrdReadError(f"cannot read {path}: {_one_line(exc)}; {_REWRITE}") from exc
    return RrdContents(path=path, store=store, entity_paths=entity_paths)


_REWRITE = "write it again with `agvviz run` (or `agvviz diff --out`)"


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 300 else text[:297] + "..."


def _check_magic(path: Path) -> None:
    """Refuse at once what is not a complete ``.rrd`` (empty, another format, cut short)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - 32))
            tail = f.read()
    except OSError as exc:
        raise RrdReadError(f"cannot read {path}: {exc.strerror or exc}") from exc
    if size == 0:
        raise RrdReadError(f"{path} is empty, not a run .rrd; {_REWRITE}")
    if head != b"RRF2":
        raise RrdReadError(f"{path} is not a Rerun .rrd file (it does not start with 'RRF2'); "
                           "give a run written by `agvviz run`")
    if b"RRF2FOOT" not in tail:
        raise RrdReadError(f"{path} is incomplete (cut short: it has no .rrd footer); {_REWRITE}")


def sweep_index(src: str | os.PathLike | RrdContents) -> list[dict]:
    """The settings of a sweep ``.rrd`` (:data:`paths.SWEEP_INDEX`): one dict per setting with
    ``key``, ``label``, ``rank`` and ``settings``; empty for a file that is no sweep."""
    contents = _contents(src)
    if paths.SWEEP_INDEX not in contents.entity_paths:
        return []
    return list(document_json(contents, paths.SWEEP_INDEX).get("settings", []))


def select_setting(index: list[dict], setting: str, where: str = "the sweep") -> dict:
    """The entry of ``index`` that ``setting`` names: its label (``ippe``,
    ``lm-lm_max_iterations=3``) or key (``s2_ippe``), else ``name=value`` pairs joined by
    ``,`` that exactly one setting has (``solver=ippe``). One-line :class:`RrdReadError` otherwise."""
    labels = ", ".join(entry["label"] for entry in index) or "none"
    for entry in index:
        if setting in (entry["label"], entry["key"]):
            return entry
    pairs = [part.partition("=") for part in setting.split(",") if part.strip()]
    if pairs and all(sep and name.strip() for name, sep, _ in pairs):
        matches = [
            entry for entry in index
            if all(name.strip() in entry["settings"] and str(entry["settings"][name.strip()]) == value.strip()
                   for name, _, value in pairs)
        ]
        if len(matches) == 1:
            return matches[0]
        if len(matches) > 1:
            raise RrdReadError(f"{where}: {setting!r} fits {len(matches)} settings "
                               f"({', '.join(m['label'] for m in matches)}); give one label")
    raise RrdReadError(f"{where} has no setting {setting!r}; its settings: {labels}")


def setting_contents(contents: RrdContents, setting: str) -> RrdContents:
    """One setting of the sweep ``.rrd`` ``contents``: its layers (``settings/<key>/...``)
    re-pathed as in a run ``.rrd``, in memory (the layers hold no images: small)."""
    index = sweep_index(contents)
    if not index:
        raise RrdReadError(f"{contents.path} is no sweep .rrd (it has no {paths.SWEEP_INDEX}); "
                           f"'{SETTING_SEPARATOR}{setting}' picks a setting inside one")
    entry = select_setting(index, setting, str(contents.path))
    prefix = "/" + paths.sweep_setting(entry["key"])
    try:
        store = (
            contents.store.stream()
            .filter(content=f"{prefix}/**")
            .map(lambda chunk: chunk.with_entity_path(chunk.entity_path[len(prefix):] or "/"))
            .collect()
        )
        entity_paths = {p.lstrip("/") for p in store.schema().entity_paths()}
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # noqa: BLE001 — Rerun raises RuntimeError, or panics, on damage
        raise RrdReadError(f"cannot read setting {entry['label']} of {contents.path}: {_one_line(exc)}") from exc
    return RrdContents(path=contents.path, store=store, entity_paths=entity_paths, setting=entry["label"])


def _contents(src: str | os.PathLike | RrdContents) -> RrdContents:
    return src if isinstance(src, RrdContents) else read_rrd(src)


def _int_times(batch: pa.RecordBatch) -> pa.RecordBatch:
    """``batch`` with timestamp/duration timelines as int64 nanoseconds (not datetime objects)."""
    columns = [
        as_int64(col) if pa.types.is_timestamp(col.type) or pa.types.is_duration(col.type) else col
        for col in batch.columns
    ]
    return pa.RecordBatch.from_arrays(columns, names=batch.schema.names)


def as_int64(column: pa.Array) -> pa.Array:
    """A timestamp or duration column as its stored int64 values — what ``cast(pa.int64())``
    gives — read from the same buffers: ``Array.cast`` imports pyarrow.compute, ≈0.3 s of CPU
    the first time (a sweep reading its settings back, a diff)."""
    return pa.Array.from_buffers(pa.int64(), len(column), column.buffers(), null_count=column.null_count,
                                 offset=column.offset)


def has_rows(src: str | os.PathLike | RrdContents, entity: str, component: str) -> bool:
    """Whether ``entity`` has any row carrying ``component`` (e.g. a run's ``world/agv/truth``
    holds its static body but no transform when the run had no truth); :class:`RrdReadError`
    only for damaged data."""
    return bool(_rows(src, entity, component, required=False))


def _rows(
    src: str | os.PathLike | RrdContents, entity: str, component: str, required: bool = True, values: bool = True,
) -> list[dict]:
    """Rows of ``entity`` that carry ``component``, each as {column name: value} (row id,
    timelines present on that row's chunk, the component), sorted by row id = logging order.
    None is :class:`RrdReadError` unless ``required`` is False (then an empty list). With
    ``values`` False the rows hold the row id and timelines only (the component's values are
    not turned into Python objects: a run's clock from its corners without the corners)."""
    contents = _contents(src)
    entity = entity.lstrip("/")
    if entity not in contents.entity_paths:
        if not required:
            return []
        raise RrdReadError(f"{contents.path} has no entity {entity!r}")
    rows = []
    try:
        for chunk in contents.store.stream().filter(content=f"/{entity}", components=component):
            if chunk.entity_path.lstrip("/") == entity:
                batch = _int_times(chunk.to_record_batch())
                if not values and batch.column(component).null_count:  # (filter imports pyarrow.compute)
                    batch = batch.filter(batch.column(component).is_valid())
                    batch = batch.select([name for name in batch.schema.names if ":" not in name])
                rows += batch.to_pylist()
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # noqa: BLE001 — damaged chunk data
        raise RrdReadError(f"cannot read {entity!r} from {contents.path}: {_one_line(exc)}; {_REWRITE}") from exc
    if values:
        rows = [row for row in rows if row.get(component) is not None]
    if not rows and required:
        raise RrdReadError(f"{contents.path}: entity {entity!r} has no {component!r} data")
    return sorted(rows, key=lambda row: row[_ROW_ID])


def scalar_series(
    src: str | os.PathLike | RrdContents, entity: str, timeline: str = paths.TIMELINE_FRAME
) -> tuple[np.ndarray, np.ndarray]:
    """One-value Scalars of ``entity`` over ``timeline``, in logging order.

    Returns
    -------
    indices : (N,) int64
        Values of ``timeline``: frame index by default, ``lm_iter`` for solver columns,
        integer nanoseconds for ``time``.
    values : (N,) float64
    """
    indices, values = [], []
    for row in _rows(src, entity, "Scalars:scalars"):
        if row.get(timeline) is None:
            raise RrdReadError(f"entity {entity!r} has rows without timeline {timeline!r}")
        scalars = row["Scalars:scalars"]
        if len(scalars) != 1:
            raise RrdReadError(f"entity {entity!r}: expected one scalar per row, got {len(scalars)}")
        indices.append(row[timeline])
        values.append(scalars[0])
    return np.array(indices, dtype=np.int64), np.array(values, dtype=np.float64)


def points2d(src: str | os.PathLike | RrdContents, entity: str) -> dict[int, np.ndarray]:
    """Points2D positions of ``entity`` per frame (the last logged in each frame), (N, 2) px.

    Frames where an empty batch was logged map to a (0, 2) array.
    """
    return {
        int(row[paths.TIMELINE_FRAME]): np.array(row["Points2D:positions"], dtype=np.float64).reshape(-1, 2)
        for row in _rows(src, entity, "Points2D:positions")
    }


def line_strips2d(src: str | os.PathLike | RrdContents, entity: str) -> dict[int, list[np.ndarray]]:
    """LineStrips2D strips of ``entity`` per frame (the last logged in each frame), each (m, 2) px."""
    return {
        int(row[paths.TIMELINE_FRAME]): [
            np.array(strip, dtype=np.float64).reshape(-1, 2) for strip in row["LineStrips2D:strips"]
        ]
        for row in _rows(src, entity, "LineStrips2D:strips")
    }


def encoded_images(src: str | os.PathLike | RrdContents, entity: str) -> dict[int, tuple[bytes, str]]:
    """EncodedImage bytes and media type of ``entity`` per frame (the last logged in each frame)."""
    contents = _contents(src)
    media = {
        int(row[paths.TIMELINE_FRAME]): row["EncodedImage:media_type"][0]
        for row in _rows(contents, entity, "EncodedImage:media_type")
    }
    result = {}
    for row in _rows(contents, entity, "EncodedImage:blob"):
        frame = int(row[paths.TIMELINE_FRAME])
        result[frame] = (bytes(row["EncodedImage:blob"][0]), media[frame])
    return result


def text_document(src: str | os.PathLike | RrdContents, entity: str) -> str:
    """Text of the (last logged) TextDocument of ``entity``, e.g. ``run/summary``."""
    return _rows(src, entity, "TextDocument:text")[-1]["TextDocument:text"][0]


def text_documents(src: str | os.PathLike | RrdContents, entity: str) -> dict[int, str]:
    """Per-frame TextDocument text of ``entity`` (e.g. ``solver/lm/this_frame``), by frame index."""
    return {
        int(row[paths.TIMELINE_FRAME]): row["TextDocument:text"][0]
        for row in _rows(src, entity, "TextDocument:text")
        if row.get(paths.TIMELINE_FRAME) is not None
    }


def document_json(src: str | os.PathLike | RrdContents, entity: str) -> dict:
    """The JSON block of a run document (``run/manifest`` or ``run/summary``) as a dict. The
    summary's JSON is its own entity (``run/summary_json``); an ``.rrd`` written before the split
    holds it under the table in ``run/summary``."""
    if entity == paths.RUN_SUMMARY:
        contents = _contents(src)
        if paths.RUN_SUMMARY_JSON in contents.entity_paths:
            src, entity = contents, paths.RUN_SUMMARY_JSON
    text = text_document(src, entity)
    start = text.find("```json\n")
    end = text.find("\n```", start + 1)
    if start < 0 or end < 0:
        raise RrdReadError(f"entity {entity!r} holds no ```json block")
    try:
        return json.loads(text[start + len("```json\n") : end])
    except ValueError as exc:
        raise RrdReadError(f"entity {entity!r} holds a damaged JSON block: {exc}") from exc


def text_logs(src: str | os.PathLike | RrdContents, entity: str) -> list[tuple[int, str, str]]:
    """TextLog entries of ``entity`` as (frame, level, text), in logging order."""
    contents = _contents(src)
    levels = {row[_ROW_ID]: row["TextLog:level"][0] for row in _rows(contents, entity, "TextLog:level")}
    return [
        (int(row[paths.TIMELINE_FRAME]), levels.get(row[_ROW_ID], ""), row["TextLog:text"][0])
        for row in _rows(contents, entity, "TextLog:text")
    ]


def transforms(
    src: str | os.PathLike | RrdContents, entity: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Temporal Transform3D (translation + mat3x3) of ``entity``, e.g. ``world/agv/truth``.

    Rerun stores both as float32 (≈1 µm at 10 m) and the matrix column-major.

    Returns
    -------
    frames : (N,) int64
        Frame index of each row, in logging order.
    time_ns : (N,) int64
        ``time`` timeline of each row (integer nanoseconds).
    T_parent_entity : (N, 4, 4) float64
        The pose of ``entity`` in its parent.
    """
    contents = _contents(src)
    rows = [
        row for row in _rows(contents, entity, "Transform3D:translation")
        if row.get(paths.TIMELINE_FRAME) is not None
    ]
    if not rows:
        raise RrdReadError(f"entity {entity!r} has no Transform3D on the {paths.TIMELINE_FRAME!r} timeline")
    matrices = {row[_ROW_ID]: row["Transform3D:mat3x3"] for row in _rows(contents, entity, "Transform3D:mat3x3")}
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    for k, row in enumerate(rows):
        mat = matrices.get(row[_ROW_ID])
        if mat is None or len(row["Transform3D:translation"]) != 1 or len(mat) != 1:
            raise RrdReadError(f"entity {entity!r}: expected one translation and one mat3x3 per row")
        T[k, :3, 3] = row["Transform3D:translation"][0]
        T[k, :3, :3] = np.asarray(mat[0], dtype=np.float64).reshape(3, 3).T  # column-major
    frames = np.array([row[paths.TIMELINE_FRAME] for row in rows], dtype=np.int64)
    time_ns = np.array([row.get(paths.TIMELINE_TIME, -1) for row in rows], dtype=np.int64)
    return frames, time_ns, T


def frame_times(src: str | os.PathLike | RrdContents, entity: str, component: str) -> dict[int, int]:
    """Frame index → ``time`` (ns) of every row of ``entity`` carrying ``component``.

    On a run ``.rrd`` the detected corners (``Points2D:positions``) are logged on every frame,
    so they give the clock of the whole run, rejected frames included.
    """
    return {
        int(row[paths.TIMELINE_FRAME]): int(row[paths.TIMELINE_TIME])
        for row in _rows(src, entity, component, values=False)
        if row.get(paths.TIMELINE_FRAME) is not None and row.get(paths.TIMELINE_TIME) is not None
    }


def scalar_entities(src: str | os.PathLike | RrdContents) -> dict[str, set[str]]:
    """Every entity holding Scalars → the timelines its Scalars rows carry (e.g. ``frame``,
    ``time``, ``elapsed``; ``lm_iter`` too for the solver's per-iteration columns)."""
    contents = _contents(src)
    found = {}
    for entity in sorted(contents.entity_paths):
        rows = _rows(contents, entity, "Scalars:scalars", required=False)
        if rows:
            found[entity] = {key for row in rows for key, value in row.items()
                             if ":" not in key and key != _ROW_ID and value is not None}
    return found


def series_name(src: str | os.PathLike | RrdContents, entity: str) -> str:
    """The name a plot gives the series of ``entity`` (its static SeriesPoints or SeriesLines
    name): what its legend and a hover over it say."""
    contents = _contents(src)
    for component in ("SeriesPoints:names", "SeriesLines:names"):
        rows = _rows(contents, entity, component, required=False)
        if rows:
            return rows[-1][component][0]
    raise RrdReadError(f"{contents.path}: entity {entity!r} has no series name")


def frame_stamps(src: str | os.PathLike | RrdContents, entity: str, component: str) -> list[tuple[int, int, int]]:
    """``(frame, time_ns, elapsed_ns)`` of every row of ``entity`` carrying ``component``, in
    logging order: on a run's detected corners, the clock its frames were logged on."""
    return [
        (int(row[paths.TIMELINE_FRAME]), int(row[paths.TIMELINE_TIME]), int(row.get(paths.TIMELINE_ELAPSED) or 0))
        for row in _rows(src, entity, component, values=False)
        if row.get(paths.TIMELINE_FRAME) is not None and row.get(paths.TIMELINE_TIME) is not None
    ]


def recording_id_of(path: str | os.PathLike) -> str:
    """The Rerun recording id of the ``.rrd`` at ``path`` (a frames file written for it shares it)."""
    try:
        recordings = RrdReader(Path(path)).recordings()
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # noqa: BLE001
        raise RrdReadError(f"cannot read {path}: {_one_line(exc)}; {_REWRITE}") from exc
    if not recordings:
        raise RrdReadError(f"{path} holds no recording; {_REWRITE}")
    return recordings[0].recording_id


@dataclass(frozen=True)
class BlueprintView:
    """One view of the default layout shipped in a ``.rrd`` (:func:`blueprint_views`)."""

    kind: str  # Rerun's view class: "3D", "2D", "TimeSeries", "TextDocument", "StateTimeline", …
    name: str
    origin: str
    contents: tuple[str, ...]  # the view's content queries (entity paths, ``$origin/**``, …)
    eye_position: tuple[float, float, float] | None = None  # a 3D view's eye (world, m)
    eye_look_target: tuple[float, float, float] | None = None
    eye_tracking_entity: str | None = None


def blueprint_views(path: str | os.PathLike) -> list[BlueprintView]:
    """Every view of the layout the ``.rrd`` at ``path`` ships (its blueprint store): what a user
    sees when the file opens. :class:`RrdReadError` when the file has no blueprint."""
    try:
        reader = RrdReader(Path(path))
        stores = reader.blueprints()
        if not stores:
            raise RrdReadError(f"{path} ships no layout (blueprint)")
        by_view: dict[str, dict] = {}
        for chunk in reader.store(store=stores[0]).stream():
            parts = chunk.entity_path.strip("/").split("/")
            if len(parts) < 2 or parts[0] != "view":
                continue
            fields = by_view.setdefault(parts[1], {})
            batch = chunk.to_record_batch()
            # Only the component columns ("Archetype:field"): the index columns hold nanosecond
            # time stamps, which pyarrow turns into Python values only through pandas.
            batch = batch.select([name for name in batch.schema.names if ":" in name])
            for row in batch.to_pylist():
                fields.update({key: value for key, value in row.items() if value is not None})
    except RrdReadError:
        raise
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # noqa: BLE001 — Rerun raises RuntimeError, or panics, on damage
        raise RrdReadError(f"cannot read the layout of {path}: {_one_line(exc)}") from exc

    def first(fields: dict, key: str):
        value = fields.get(key)
        return value[0] if value else None

    def vector(fields: dict, key: str):
        value = first(fields, key)
        return None if value is None else tuple(float(v) for v in value)

    return [
        BlueprintView(
            kind=first(fields, "ViewBlueprint:class_identifier") or "",
            name=first(fields, "ViewBlueprint:display_name") or "",
            origin=first(fields, "ViewBlueprint:space_origin") or "",
            contents=tuple(fields.get("ViewContents:query") or ()),
            eye_position=vector(fields, "EyeControls3D:position"),
            eye_look_target=vector(fields, "EyeControls3D:look_target"),
            eye_tracking_entity=first(fields, "EyeControls3D:tracking_entity") or None,
        )
        for fields in by_view.values()
        if "ViewBlueprint:class_identifier" in fields
    ]
