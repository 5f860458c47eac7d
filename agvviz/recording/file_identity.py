"""What identifies files on disk as they are now, without reading them: the key under which a
recording's scan is cached (:mod:`agvviz.recording.scan_cache`) and its bytes are trusted to be
those a read found intact (:meth:`agvviz.recording.raw.Recording.mark_verified`).

Standard library only: the scan cache asks before the fork server starts.
"""

from __future__ import annotations

import os
from pathlib import Path


def files_key(paths) -> list[list]:
    """Per file, in order: its resolved path, size, mtime_ns, ctime_ns and inode. A file written,
    replaced, touched or moved has another key. Raises ``OSError`` when one cannot be stat'ed."""
    key = []
    for path in paths:
        st = os.stat(path)
        key.append([str(Path(path).resolve()), st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino])
    return key
