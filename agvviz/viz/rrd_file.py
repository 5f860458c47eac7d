"""One way to write an ``.rrd`` atomically and reproducibly.

:class:`AtomicRrd` opens a data-only :class:`rerun.RecordingStream` (pinned recording id, no
log time or tick, no properties, chunks cut by size only) that streams into a temporary file
beside the target, so memory stays flat; :meth:`AtomicRrd.commit` sends the layout (active and
default, so the file opens in it), writes the footer and renames the file into place;
:meth:`AtomicRrd.discard` deletes it. Used as a context manager, an exception discards.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import rerun as rr
import rerun.blueprint as rrb

#: The chunk batcher never cuts a chunk on a wall-clock tick (a day is "never" here), so the
#: same data gives the same chunks and `rerun rrd compare --unordered` finds two runs equal.
BATCHER_FLUSH_TICK_S = 86_400.0


class AtomicRrd:
    """A recording stream writing ``out_path`` only once it is complete.

    Parameters
    ----------
    out_path : path
        The ``.rrd`` to write; its folder must exist (``FileNotFoundError`` otherwise).
    recording_id : str
        Pinned so identical inputs give comparable files.
    recording_name : str
        Shown in the viewer.
    """

    def __init__(self, out_path: str | os.PathLike, *, recording_id: str, recording_name: str):
        self.out_path = Path(out_path)
        if not self.out_path.parent.is_dir():
            raise FileNotFoundError(
                f"cannot write {self.out_path}: folder {self.out_path.parent} does not exist"
            )
        # A fresh name (not mkstemp) so Rerun creates the file with the usual permissions.
        self._tmp_path = self.out_path.with_name(f".{self.out_path.name}.{uuid.uuid4().hex}.tmp")
        self.rec = rr.RecordingStream(
            "agvviz",
            recording_id=recording_id,
            send_properties=False,
            batcher_config=rr.ChunkBatcherConfig(flush_tick=BATCHER_FLUSH_TICK_S),
        )
        self.rec.set_log_time_enabled(False)
        self.rec.set_log_tick_enabled(False)
        self.rec.save(self._tmp_path)
        self.rec.send_recording_name(recording_name)
        self.closed = False

    def commit(self, blueprint: rrb.Blueprint | None = None) -> Path:
        """Send ``blueprint`` (the file's layout), finish the file and move it into place."""
        if self.closed:
            raise RuntimeError(f"{self.out_path} was already committed or discarded")
        self.closed = True
        try:
            if blueprint is not None:
                rr.send_blueprint(blueprint, make_active=True, make_default=True, recording=self.rec)
            self.rec.flush()
            self.rec.disconnect()
            os.replace(self._tmp_path, self.out_path)
        except BaseException:
            self._tmp_path.unlink(missing_ok=True)
            raise
        return self.out_path

    def discard(self) -> None:
        """Stop writing and delete the unfinished file; ``out_path`` is left untouched."""
        if self.closed:
            return
        self.closed = True
        self.rec.disconnect()
        self._tmp_path.unlink(missing_ok=True)

    def __enter__(self) -> "AtomicRrd":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()
