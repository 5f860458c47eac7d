"""A sweep's ``.rrd`` (issue 27): the frames and the static world once, each setting's layers
under ``settings/<key>/`` (its layers-only run, copied as chunks), the ranking with p-values and
the verdict (:func:`agvviz.app.sweep_report.ranking_markdown`) and a layout that overlays the
settings, written with :class:`agvviz.viz.overlay.OverlayFile`.

:class:`SweepFile` begins it while the settings still run — the frames once the first setting
has ended, each setting's layers as it ends — so that only the ranking and the drawing are left
once the last has ended; :func:`write_sweep_file` finishes it (or writes it whole). The entries
are :class:`agvviz.app.sweep.SweepEntry`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from agvviz.app import run_series
from agvviz.app.sweep_report import ranking_markdown
from agvviz.evaluation.comparison import RunSeries, match_frames
from agvviz.replay.run import recording_images
from agvviz.viz import paths
from agvviz.viz.overlay import OverlayFile, OverlayRun, write_overlay
from agvviz.viz.readback import RrdContents


def _reprojected_reader(run: RrdContents, cams: list[str], to_first: dict[int, int]):
    """A function reading a setting's reprojected corners (its ``run``), its frames mapped
    onto the sweep's clock (``to_first``): called by the writer when it draws that setting, so
    one setting's corners are in memory at a time."""
    def read() -> dict[str, dict[int, np.ndarray]]:
        return {
            cam: {to_first[f]: pts for f, pts in per.items() if f in to_first}
            for cam, per in run_series.reprojected_corners(run, cams).items()
        }
    return read


def write_sweep_file(
    out: Path, recording: Path, ranked: list, series: dict[int, RunSeries],
    entries: list, rank_by: str, images: bool, cache_dir: Path | None = None,
    early: "SweepFile | None" = None,
) -> Path:
    """The sweep ``.rrd``: the settings that ran drawn together on the best one's clock, each
    one's layers under ``settings/<key>/``, the frames once (from the recording, or copied from
    the best setting's kept run), the ranking document and the index."""
    index_of = {id(e): i for i, e in enumerate(entries)}
    ok = [e for e in ranked if e.ok]
    first = series[index_of[id(ok[0])]]
    first_contents = ok[0].run
    cams = run_series.cameras_of(first_contents) if images else []
    # Layers-only runs: the frames come from the recording, on the best run's clock.
    clocks = run_series.image_clocks(first_contents) if cams and not paths.camera_images(first_contents.entity_paths) else None
    runs = []
    for entry in ok:
        s = series[index_of[id(entry)]]
        ia, ib = match_frames(first.time_ns, s.time_ns)
        to_first = {int(s.frames[j]): int(first.frames[i]) for i, j in zip(ia, ib)}
        runs.append(OverlayRun(
            entry.key, f"#{entry.rank} {entry.label}",
            first.frames[ia], first.time_ns[ia], s.T_est[ib], run_series.overlay_errors(s, ib),
            _reprojected_reader(entry.run, cams, to_first) if images else {},
            T_truth=None if s.T_truth is None else s.T_truth[ib], short_label=f"#{entry.rank}",
        ))
    index = [
        {"key": e.key, "label": e.label, "rank": e.rank, "settings": series[index_of[id(e)]].settings}
        for e in ok
    ]
    drawing = dict(
        runs=runs,
        truth=run_series.overlay_truth(first),
        source=ok[0].run,
        cam_names=cams,
        fixed_cams=run_series.fixed_cameras_of(first_contents) & set(cams),
        report_markdown=ranking_markdown(recording.name, ranked, rank_by),
        index=index,
    )
    if early is not None and early.holds(cams if clocks is not None else None, clocks, {e.key for e in ok}):
        return early.finish(**drawing)
    if early is not None:
        early.discard()  # its frames went on another clock: written anew
    frames = None
    if clocks is not None:
        frames = (
            recording_images(recording, first.manifest.get("roles", {}), first.manifest.get("time_source", "log"),
                             cache_dir),
            clocks,
        )
    return write_overlay(
        out, recording_name=sweep_file_name(recording), inputs=(recording, *[e.run_path for e in ok]),
        layers={e.key: e.run for e in ok}, frames=frames, **drawing,
    )


def sweep_file_name(recording: Path) -> str:
    """The recording name of a recording's sweep ``.rrd`` (shown in the viewer)."""
    return f"sweep {recording.stem}"


class SweepFile:
    """A recording's sweep ``.rrd`` begun while its settings still run (issue 27): when the
    first setting ends, the frames (from the recording, on that run's clock; layers-only runs),
    then each setting's layers as it ends; what is left once the last has ended is the ranking
    and the drawing (:func:`_write_sweep_file` calls :meth:`finish`). When the best setting's
    clock is not the one the frames went on (a sweep over ``time_source``), the file is
    discarded and written anew."""

    def __init__(self, path: Path, recording: Path, entries: list, images: bool, cache_dir: Path | None):
        self.path, self.recording, self.images, self.cache_dir = path, recording, images, cache_dir
        self.inputs = (recording, *[e.run_path for e in entries])
        self.overlay: OverlayFile | None = None
        self.frames: tuple[list[str], dict] | None = None  # (cameras, clocks) the frames went on
        self.layers: set[str] = set()  # keys of the settings whose layers are in
        self.image_clocks = run_series.image_clocks  # the clock the frames go on (a test shifts it)

    def add(self, entry, run: RunSeries) -> None:
        """``entry`` ended and was read back (``run``): its layers go in — after the frames, on
        its clock, when it is the first."""
        if self.overlay is None:
            self.overlay = OverlayFile(self.path, recording_name=sweep_file_name(self.recording), inputs=self.inputs)
            cams = run_series.cameras_of(entry.run) if self.images else []
            if cams and not paths.camera_images(entry.run.entity_paths):
                images = recording_images(self.recording, run.manifest.get("roles", {}),
                                          run.manifest.get("time_source", "log"), self.cache_dir)
                self.overlay.log_frames(images, self.image_clocks(entry.run), cams)
                self.frames = self.overlay.frames_logged
        self.overlay.copy_layers(entry.key, entry.run)
        self.layers.add(entry.key)

    def holds(self, cams: list[str] | None, clocks: dict | None, keys: set[str]) -> bool:
        """Whether this file has the frames of ``cams`` on ``clocks`` (None: no frames from the
        recording) and the layers of exactly the settings ``keys``."""
        if self.overlay is None or self.layers != keys:
            return False
        if cams is None:
            return self.frames is None
        return self.frames == (list(cams), {c: clocks.get(c, []) for c in cams})

    def finish(self, **drawing) -> Path:
        path = self.overlay.finish(**drawing)
        self.overlay = None
        return path

    def discard(self) -> None:
        """Remove the unfinished file, if any (a finished one stays)."""
        if self.overlay is not None:
            self.overlay.discard()
            self.overlay = None
