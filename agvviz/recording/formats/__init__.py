"""Recording formats, registered in one place (in the style of ``mcap``'s decoder factories).

A format is one module with the same small set of names:

* ``NAME`` — the recording kind (:attr:`agvviz.recording.raw.Recording.kind`);
* ``recognises(path) -> bool`` — is this path (file or directory) mine?
* ``open_recording(path) -> Recording`` — its files in order, its writer's header and
  counts; raises :class:`~agvviz.errors.RecordingError` with what to do;
* ``iter_raw(file, topics, report, digest=None, verified=False)`` — one file's
  :class:`~agvviz.recording.raw.RawMessage` and :class:`~agvviz.recording.raw.RawMetadata`
  in file order, salvaging damage into the :class:`~agvviz.recording.raw.ReadReport` (and
  the file's bytes into ``digest``); ``verified``: the file was read whole before and found
  intact (:meth:`~agvviz.recording.raw.Recording.mark_verified`), checks that cannot find
  anything new (CRCs, repeated messages) may be skipped;
* ``decodes(raw) -> bool`` and ``decode(raw)`` — the messages it decodes (by encoding: an
  MCAP file may carry ROS 2 or ROS 1 messages) into :mod:`agvviz.model.messages` values;
* ``describe(files) -> str`` — what ``agvviz inspect`` adds after the path.

Adding a format: a module here and one entry in :data:`FORMATS`.
"""

from __future__ import annotations

from pathlib import Path

from agvviz.errors import RecordingError
from agvviz.recording.formats import mcap, ros1, ros2
from agvviz.recording.raw import DAMAGE_ERRORS, MessageDecodeError, RawMessage

#: Every format, in the order a path is offered to them: the first that recognises it opens it
#: (a ``.bag`` or a folder of bags, then a directory as a rosbag2 bag, then a file as MCAP).
FORMATS = (ros1, ros2, mcap)


def format_of(path: Path):
    """The format (module) that reads ``path``."""
    for fmt in FORMATS:
        if fmt.recognises(path):
            return fmt
    raise RecordingError(  # pragma: no cover — the MCAP format takes every file
        f"{path}: not a recording agvviz reads; give an .mcap recording, a rosbag2 directory or a ROS 1 .bag"
    )


def by_name(name: str):
    """The format whose ``NAME`` is ``name`` (a recording's kind)."""
    for fmt in FORMATS:
        if fmt.NAME == name:
            return fmt
    raise KeyError(name)


def decode(raw: RawMessage) -> object:
    """The value of a raw message (see :class:`agvviz.model.messages.RecordedMessage`): the
    format that decodes its encoding decodes it; ``bytes`` when none does.

    Raises :class:`MessageDecodeError` when the payload does not decode as its schema says.
    """
    try:
        for fmt in FORMATS:
            if fmt.decodes(raw):
                return fmt.decode(raw)
    except MessageDecodeError:
        raise
    except DAMAGE_ERRORS as exc:
        what = raw.schema_name or raw.message_encoding
        raise MessageDecodeError(f"payload does not decode as {what}: {exc}") from None
    return raw.data
