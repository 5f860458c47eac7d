"""The detection cache: a recording's detect-stage output, stored once, reused by every run
and sweep setting that only changes what comes after detection (solver, fusion, correction…).

One Parquet file per (recording content, detection inputs):
``<cache dir>/<recording sha256>/<key>.parquet``, one row per detected frame in file order.
The key hashes everything detections depend on besides the recording's bytes — agvviz's
version (a new version invalidates every entry), the detection settings, the marker family,
the role map's image topics, the time source and the calibrations from side files — so a
changed input is a different key, never a stale hit. Entries are written atomically (a
complete file or none) and an unreadable entry is ignored (and replaced).

The cache folder: ``$AGVVIZ_CACHE_DIR``, else ``$XDG_CACHE_HOME/agvviz/detections``, else
``~/.cache/agvviz/detections``. Delete it at any time.
"""

from __future__ import annotations

import hashlib
import json
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from agvviz import __version__
from agvviz.recording import outputs
from agvviz.recording.scan_cache import CACHE_ENV, default_cache_dir  # noqa: F401 — this module's API
from agvviz.replay.detect.stage import DETECT_REVISION, DetectParams
from agvviz.model.detections import CodeDetection, FrameDetections
from agvviz.replay.detect.pool import DetectedFrame
from agvviz.markers.charuco import ChessboardCorners



def cache_key(params: DetectParams, inputs: dict) -> str:
    """Hash of agvviz's version, the detect parameters and the other detection ``inputs``
    (JSON-able: image roles, time source, side-file calibrations…)."""
    text = json.dumps(
        {"agvviz": __version__, "detect_revision": DETECT_REVISION, "params": params.__dict__, "inputs": inputs},
        sort_keys=True, default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def entry_path(cache_dir: Path, recording_sha256: str, key: str) -> Path:
    return Path(cache_dir) / recording_sha256 / f"{key}.parquet"


def _points(a) -> list[float] | None:
    return None if a is None else np.asarray(a, dtype=float).reshape(-1).tolist()


def _array(values, columns: int = 2) -> np.ndarray | None:
    return None if values is None else np.asarray(values, dtype=float).reshape(-1, columns)


#: Frames per Parquet row group: an entry is written and read a row group at a time, so what
#: Arrow holds meanwhile does not grow with the recording's length (issue 27).
FRAMES_PER_ROW_GROUP = 256


def save(path: Path, frames: list[DetectedFrame]) -> None:
    """Write ``frames`` to ``path`` atomically (:func:`agvviz.recording.outputs.atomic_writer`),
    :data:`FRAMES_PER_ROW_GROUP` at a time; :class:`~agvviz.errors.OutputError` when it cannot
    be written."""
    import pyarrow.parquet as pq

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    schema = _schema()
    with _arrow_memory_returned(), outputs.atomic_writer(path) as file, pq.ParquetWriter(file, schema) as writer:
        for start in range(0, len(frames), FRAMES_PER_ROW_GROUP):
            writer.write_table(_table(frames[start:start + FRAMES_PER_ROW_GROUP], schema))


def _table(frames: list[DetectedFrame], schema):
    import pyarrow as pa

    rows = []
    for f in frames:
        d = f.detections
        rows.append({
            "seq": f.seq, "cam_name": f.cam_name, "log_time_ns": f.log_time_ns,
            "reject_reason": d.reject[0] if d.reject else None,
            "reject_detail": d.reject[1] if d.reject else None,
            "drop_image": d.drop_image, "detect_s": d.detect_s, "keyframe": d.keyframe,
            "tracked": d.tracked, "note": d.note,
            "codes": [
                {
                    "kind": c.kind, "corners_px": _points(c.corners_px), "raw_corners_px": _points(c.raw_corners_px),
                    "text": c.text, "payload_bytes": c.payload_bytes, "aruco_id": c.aruco_id,
                    "n_modules": c.n_modules, "finder_px": _points(c.finder_px),
                    "finder_modules": _points(c.finder_modules), "refine_method": c.refine_method,
                    "refine_note": c.refine_note,
                }
                for c in d.codes
            ],
            "chessboards": [
                {"board_index": b.board_index, "corner_ids": [int(i) for i in b.corner_ids],
                 "corners_px": _points(b.corners_px), "note": b.note, "misplaced_ids": list(b.misplaced_ids)}
                for b in d.chessboards
            ],
        })
    return pa.Table.from_pylist(rows, schema=schema)


def _schema():
    import pyarrow as pa

    code_type = pa.struct([
        ("kind", pa.string()), ("corners_px", pa.list_(pa.float64())), ("raw_corners_px", pa.list_(pa.float64())),
        ("text", pa.string()), ("payload_bytes", pa.binary()), ("aruco_id", pa.int64()),
        ("n_modules", pa.int64()), ("finder_px", pa.list_(pa.float64())),
        ("finder_modules", pa.list_(pa.float64())), ("refine_method", pa.string()), ("refine_note", pa.string()),
    ])
    return pa.schema([
        ("seq", pa.int64()), ("cam_name", pa.string()), ("log_time_ns", pa.int64()),
        ("reject_reason", pa.string()), ("reject_detail", pa.string()), ("drop_image", pa.bool_()),
        ("detect_s", pa.float64()), ("keyframe", pa.bool_()), ("tracked", pa.int64()), ("note", pa.string()),
        ("codes", pa.list_(code_type)),
        ("chessboards", pa.list_(pa.struct([
            ("board_index", pa.int64()), ("corner_ids", pa.list_(pa.int64())),
            ("corners_px", pa.list_(pa.float64())), ("note", pa.string()), ("misplaced_ids", pa.list_(pa.int64())),
        ]))),
    ])


@contextmanager
def _arrow_memory_returned():
    """Give the memory Arrow's allocator kept after the block back to the system: it keeps what
    was freed for later, and a cache entry is written or read once per run (issue 27: at 2000
    frames, ≈20 MiB kept through the rest of the run)."""
    try:
        yield
    finally:
        import pyarrow as pa

        pa.default_memory_pool().release_unused()


def load(path: Path) -> list[DetectedFrame] | None:
    """The cached frames at ``path``, or None when there is no readable entry. Detection time is
    reported as 0 for cached frames (nothing was detected in this run)."""
    if not path.is_file():
        return None
    try:
        import pyarrow.parquet as pq

        # ParquetFile, not pq.read_table: read_table goes through pyarrow.dataset, whose import
        # pulls in pandas (≈0.5 s of a warm run's start, issue 27). A row group at a time.
        with _arrow_memory_returned(), pq.ParquetFile(path) as parquet:
            frames = [_frame(row) for group in range(parquet.num_row_groups)
                      for row in parquet.read_row_group(group).to_pylist()]
        if [f.seq for f in frames] != list(range(len(frames))):
            return None
        return frames
    except Exception:  # noqa: BLE001 - a damaged entry is a miss, and is rewritten
        return None


def _frame(r: dict) -> DetectedFrame:
    """One row of an entry as the frame it stores."""
    codes = tuple(
        CodeDetection(
            kind=c["kind"], corners_px=_array(c["corners_px"]), raw_corners_px=_array(c["raw_corners_px"]),
            text=c["text"], payload_bytes=c["payload_bytes"], aruco_id=c["aruco_id"],
            n_modules=c["n_modules"], finder_px=_array(c["finder_px"]),
            finder_modules=_array(c["finder_modules"]), refine_method=c["refine_method"] or "",
            refine_note=c["refine_note"] or "",
        )
        for c in r["codes"]
    )
    chessboards = tuple(
        ChessboardCorners(int(b["board_index"]), np.asarray(b["corner_ids"], dtype=int),
                          _array(b["corners_px"]), b["note"] or "", tuple(b["misplaced_ids"] or ()))
        for b in r["chessboards"]
    )
    reject = (r["reject_reason"], r["reject_detail"] or "") if r["reject_reason"] else None
    detections = FrameDetections(
        codes=codes, reject=reject, drop_image=bool(r["drop_image"]), detect_s=0.0,
        keyframe=bool(r["keyframe"]), tracked=int(r["tracked"]), note=r["note"] or "",
        chessboards=chessboards,
    )
    return DetectedFrame(int(r["seq"]), r["cam_name"], int(r["log_time_ns"]), detections)
