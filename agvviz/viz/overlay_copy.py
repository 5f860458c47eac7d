"""What an overlay ``.rrd`` (:mod:`agvviz.viz.overlay`) copies from run files, chunk by chunk
(the JPEG bytes are never decoded or re-encoded), and the pacing that keeps a copy from piling
up in memory: a run's layers under ``settings/<key>/``, the source run's map, images and
detected corners, the recording's frames as they are logged.
"""

from __future__ import annotations

import os
from typing import Iterable, Iterator

import rerun as rr

from agvviz.viz import paths, rrd_file
from agvviz.viz.frames import RecordedImage
from agvviz.viz.log_frames import DETECTED_RADIUS
from agvviz.viz.readback import RrdContents, read_rrd
from agvviz.viz.style import COLOR_DETECTED

#: Camera images are written out (a flush) after this many bytes, or rows of image chunks:
#: Rerun queues what it is given without bound, and frames given faster than the file was
#: written piled up in the process (a sweep's 2000 frames: +100-200 MB).
FLUSH_IMAGE_BYTES = 8 << 20
FLUSH_IMAGE_ROWS = 32


def opened(run: str | os.PathLike | RrdContents) -> RrdContents:
    """A run ``.rrd`` by its path, or opened by the caller (a sweep opens each run once)."""
    return run if isinstance(run, RrdContents) else read_rrd(run)


def copy_layers(rec: rr.RecordingStream, key: str, run: str | os.PathLike | RrdContents) -> set[str]:
    """Copy every entity of the run ``.rrd`` ``run`` (a path, or opened) but its camera images (and the
    recording's properties) under ``settings/<key>/``, chunk by chunk, unchanged. Returns the
    run's entity paths (without the prefix).

    One entity at a time, each written out (``flush``) before the next is read: Rerun loads a
    whole stream's chunks ahead of the writer, so a run's layers copied in one stream were
    held in memory whole (≈45 MB at 2000 frames); one entity's are a few MB."""
    store = opened(run).store
    entities = sorted(p.lstrip("/") for p in store.schema().entity_paths())
    left_out = {"__properties", *paths.camera_images(entities)}
    prefix = "/" + paths.sweep_setting(key)
    for entity in entities:
        if entity in left_out or entity.startswith("__properties/"):
            continue
        rec.send_chunks(
            store.stream().filter(content=f"/{entity}")
            .map(lambda chunk: chunk.with_entity_path(prefix + chunk.entity_path))
        )
        rec.flush()
    return set(entities)


def paced_images(rec: rr.RecordingStream, images: Iterable[RecordedImage]) -> Iterator[RecordedImage]:
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


def send_paced(rec: rr.RecordingStream, chunks: Iterable) -> None:
    """Send ``chunks`` (camera images) one by one, a flush after every :data:`FLUSH_IMAGE_ROWS`."""
    rows = 0
    for chunk in chunks:
        rec.send_chunks(chunk)
        rows += chunk.num_rows
        if rows >= FLUSH_IMAGE_ROWS:
            rec.flush()
            rows = 0


def copy_from_source(
    rec: rr.RecordingStream, store, cam_names: list[str], fixed_cams: set[str] | frozenset[str] = frozenset(),
    images: bool = True,
) -> None:
    """Copy the marker map, each camera's images (unless ``images`` is False) and detected
    corners of a run (its store), chunk by chunk (the JPEG bytes are never decoded or
    re-encoded); a camera of ``fixed_cams`` from its world-fixed entity."""
    rec.send_chunks(store.stream().filter(content=[f"/{paths.MARKERS}", f"/{paths.MARKERS_FILL}"]))
    for cam in cam_names if images else []:
        send_paced(
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
