"""Imported last by the fork server (:func:`agvviz.replay.detect.workers.start_fork_server`),
once it has imported what its processes need: every object it holds moves into the garbage
collector's permanent generation (:func:`gc.freeze`).

A process forked from the server shares its memory pages until it writes to them. Without this,
the first full collection in a forked process (a detection worker, the ``.rrd`` writer) walks
every object inherited from the server and writes to each one's header: every page holding one
becomes the process's own copy, tens of MiB per process, and the longer the run, the surer that
collection comes. Frozen objects are never walked (nor freed: they are the imported modules,
which live as long as the process anyway). Python's documentation of :func:`gc.freeze`
recommends exactly this before forking.
"""

import gc

gc.freeze()
