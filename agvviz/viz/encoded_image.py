"""Logging a recorded image's bytes as they are: the one way a camera frame goes into an ``.rrd``
(a run's :class:`~agvviz.viz.log_frames.FrameLogger`, the frames of :mod:`agvviz.viz.frames`).

A camera's frames are sent in groups of :data:`IMAGES_PER_CHUNK`, one ``send_columns`` chunk per
group (issue 27, peak memory): Rerun's file footer keeps a row of bookkeeping for every chunk of
the file until it is written, and one chunk per image (≈300 kB JPEG, above the batcher's cut) made
the writer's memory grow with the run's length. The rows are those ``rr.log`` of an
``rr.EncodedImage`` gives (the same entity, components, values and timelines); only the chunking
differs, and it depends only on the data: two runs of equal settings give equal chunks.
"""

from __future__ import annotations

from typing import Callable, Sequence

import pyarrow as pa
import rerun as rr

from agvviz.viz.columns import ArrowBatch

#: Image formats of a recording's frames and their media types.
MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}
#: A camera's images are sent as one chunk every this many frames (and whenever the logger
#: flushes or closes). 8 JPEG frames of the default camera are ≈2.4 MB held at most per camera;
#: a 2000-frame run has 250 image chunks instead of 2000.
IMAGES_PER_CHUNK = 8

_BLOB_TYPE = rr.components.BlobBatch._ARROW_DATATYPE
_BLOB_DESCRIPTOR = rr.EncodedImage.descriptor_blob()
_MEDIA_TYPE_DESCRIPTOR = rr.EncodedImage.descriptor_media_type()

#: Index columns (``frame``, ``time``, ``elapsed``) of a list of stamps, in the stamps' own form.
IndexColumns = Callable[[list[tuple]], list[rr.TimeColumn]]


def encoded_image_columns(image_formats: Sequence[str], images: Sequence[bytes]) -> list[rr.ComponentColumn]:
    """The ``EncodedImage`` blob and media type columns of ``images`` (one row each): the bytes
    as they are, in one Arrow buffer (one copy of the group's bytes), never decoded."""
    data = pa.py_buffer(b"".join(images))
    offsets = [0]
    for image in images:
        offsets.append(offsets[-1] + len(image))
    blobs = pa.ListArray.from_arrays(
        pa.array(offsets, type=pa.int32()),
        pa.Array.from_buffers(pa.uint8(), data.size, [None, data]),
        type=_BLOB_TYPE,
    )
    media_types = rr.components.MediaTypeBatch([MEDIA_TYPES[f] for f in image_formats])
    return [
        rr.ComponentColumn(_BLOB_DESCRIPTOR, ArrowBatch(blobs)),
        rr.ComponentColumn(_MEDIA_TYPE_DESCRIPTOR, media_types),
    ]


class ImageChunks:
    """Recorded images held per entity and sent as one chunk of :data:`IMAGES_PER_CHUNK` rows
    (:meth:`add`), or fewer at :meth:`flush`. ``indexes`` turns the held stamps into the index
    columns the rest of the file uses for the same frames."""

    def __init__(self, rec: rr.RecordingStream, indexes: IndexColumns):
        self._rec = rec
        self._indexes = indexes
        #: entity -> [(stamp, image format, bytes)] not sent yet.
        self._held: dict[str, list[tuple[tuple, str, bytes]]] = {}

    def add(self, entity: str, stamp: tuple, image_format: str, image_bytes: bytes) -> int:
        """Hold one image of ``entity`` at ``stamp``; send the entity's group when it is full.
        Returns the bytes sent (0: still held)."""
        held = self._held.setdefault(entity, [])
        held.append((stamp, image_format, image_bytes))
        return self._send(entity) if len(held) >= IMAGES_PER_CHUNK else 0

    def flush(self) -> int:
        """Send every held image (a chunk per entity, in the order the entities came). Returns the
        bytes sent."""
        return sum(self._send(entity) for entity in list(self._held))

    def _send(self, entity: str) -> int:
        held = self._held.pop(entity, [])
        if not held:
            return 0
        stamps, image_formats, images = zip(*held)
        self._rec.send_columns(
            entity, indexes=self._indexes(list(stamps)), columns=encoded_image_columns(image_formats, images)
        )
        return sum(len(image) for image in images)
