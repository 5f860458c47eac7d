"""A sweep's ``.rrd`` (issue 27): the frames and the static world once, each setting's layers
under ``settings/<key>/`` (its layers-only run, copied as chunks), the ranking with p-values and
the verdict (:func:`agvviz.app.sweep_report.ranking_markdown`) and a layout that overlays the
settings (:func:`agvviz.viz.overlay.write_overlay`), once every setting has ended and been
ranked (:func:`write_sweep_file`). The entries are :class:`agvviz.app.sweep.SweepEntry`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from agvviz.app import run_series
from agvviz.app.sweep_report import ranking_markdown
from agvviz.evaluation.comparison import RunSeries, match_frames
from agvviz.replay.run import recording_images
from agvviz.viz import paths
from agvviz.viz.overlay import OverlayRun, write_overlay
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
