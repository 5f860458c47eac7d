"""What ``agvviz run`` and ``agvviz sweep`` start before their command line is imported: the
fork server their processes are forked from (issue 27).

That server imports Rerun, OpenCV, NumPy and agvviz's replay and logging modules (≈0.65 s of
CPU) before it forks anything: a run's ``.rrd`` writer and detection workers, a local sweep's
pool. Started from the command's own body, it began only once typer, rich, NumPy and the
settings were imported (≈0.3 s into the process): the writer of a warm run (detections cached)
was ready ≈0.9 s in, after the run had solved most of its frames, and the run waited for it at
the end. Started from :func:`agvviz.__main__.main` before the command line is imported, the
server's imports overlap the command line's on the other core (a warm run ≈5 % shorter).

Only the arguments' words are looked at, not parsed: the command's name (the first word),
``--help``, and a sweep's ``--scheduler`` (a sweep on a Dask cluster forks nothing here). The
server is the same for every run (the writer's modules import the detection workers' too) and
for every local sweep; one that is not used (an option refused) ends with the process.
"""

from __future__ import annotations


def start_fork_server_for(argv: list[str]) -> None:
    """Start the fork server ``argv`` (the arguments after the program name) will use:
    :func:`start_run_fork_server` for ``run``, the local pool's
    (:func:`agvviz.app.cluster.start_fork_server`) for ``sweep`` without ``--scheduler``;
    nothing for the other commands or a request for help."""
    if not argv or "--help" in argv:
        return
    if argv[0] == "run":
        start_run_fork_server()
    elif argv[0] == "sweep" and not any(a == "--scheduler" or a.startswith("--scheduler=") for a in argv):
        from agvviz.app.cluster import start_fork_server

        _started(start_fork_server)


def start_run_fork_server() -> None:
    """Start the fork server of a run's ``.rrd`` writer and detection workers
    (:func:`agvviz.replay.detect.workers.start_fork_server`; a no-op where there is none or one
    runs already), the writer's allocator settings first
    (:func:`~agvviz.replay.detect.workers.writer_allocator_settings`: a writer spawned where
    there is no fork server reads them too); without waiting for its imports."""
    from agvviz.replay.detect.workers import start_fork_server, writer_allocator_settings

    writer_allocator_settings()
    _started(start_fork_server)


def _started(start) -> None:
    """``start()``; a server that cannot start (no memory or processes left) is not an error
    here: the command's own start of its processes reports it, as one line."""
    try:
        start()
    except OSError:
        pass
