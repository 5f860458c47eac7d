"""Logging a recorded image's bytes as they are: the one way a camera frame goes into an ``.rrd``
(a run's :class:`~agvviz.viz.log_frames.FrameLogger`, the frames of :mod:`agvviz.viz.frames`)."""

from __future__ import annotations

import pyarrow as pa
import rerun as rr

from agvviz.viz.columns import ArrowBatch

#: Image formats of a recording's frames and their media types.
MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}


_BLOB_TYPE = rr.components.BlobBatch._ARROW_DATATYPE
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


def log_encoded_image(rec: rr.RecordingStream, entity: str, image_format: str, image_bytes: bytes) -> None:
    """Log a recorded image's bytes as they are (an EncodedImage) at ``entity`` on the time set:
    the one way a camera frame is logged (a run, :mod:`agvviz.viz.frames`)."""
    # What rr.EncodedImage(contents=..., media_type=...) logs, without building the
    # archetype: the blob wraps the bytes without a copy, the media type is built once.
    data = pa.py_buffer(image_bytes)
    blob = pa.ListArray.from_arrays(
        pa.array([0, data.size], type=pa.int32()),
        pa.Array.from_buffers(pa.uint8(), data.size, [None, data]),
        type=_BLOB_TYPE,
    )
    rec.log(entity, [rr.DescribedComponentBatch(ArrowBatch(blob), _BLOB_DESCRIPTOR), _media_type_batch(MEDIA_TYPES[image_format])])
