"""Log one replay run into a Rerun recording and save it as one ``.rrd``: the orchestrator.

:class:`RunLogger` owns the file and holds one logger per modality of a frame —
:class:`~agvviz.viz.log_frames.FrameLogger` (map, cameras, images, corners, poses, trajectories,
errors), :class:`~agvviz.viz.log_lm.LmLogger` (the solver's iterations) and
:class:`~agvviz.viz.log_uncertainty.UncertaintyLogger` (covariance, NEES, CRLB, ambiguity) — plus
:class:`~agvviz.viz.log_findings.FindingLogger` (the check stage's run-level findings, at the end), and
logs the run's documents (manifest, summary, error budget). UWB and correction runs add their
loggers (:mod:`agvviz.viz.log_uwb`, :mod:`agvviz.viz.log_correction`) on :attr:`RunLogger.stream`;
study runs log with :mod:`agvviz.viz.log_studies`.

The entity tree is in :mod:`agvviz.viz.paths`; the layouts in :mod:`agvviz.viz.blueprints`. The
logger owns an explicit ``rr.RecordingStream`` (never the global one) that streams into a
temporary file next to the target; :meth:`RunLogger.close` adds the default blueprint and renames
it into place. Wall-clock ``log_time``/``log_tick`` timelines and the wall-clock start-time
property are disabled and chunks are cut by size only (no wall-clock batcher tick), so the file
depends only on the data: two identical runs compare equal with ``rerun rrd compare --unordered``
(row ids and file bytes still differ).

Logging cost (issue 12): every per-frame value except the image is held in memory
(:class:`agvviz.viz.columns.Columns`) and sent as columns every :data:`FLUSH_EVERY_FRAMES`
frames and at :meth:`RunLogger.close`, instead of building a Rerun archetype per frame. The
styling of every per-frame entity (colours, radii, draw order) is logged once as static data, so
a frame carries only what changes. Every per-frame log is stamped on ``frame``, ``time`` and
``elapsed`` (:func:`agvviz.viz.timelines.set_stamp`).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import rerun as rr

from agvviz.evaluation.summary_table import markdown_table, summary_rows
from agvviz.geometry.camera import PinholeCamera
from agvviz.model.frames import FrameResult
from agvviz.viz import paths
from agvviz.viz.blueprints import PlotAxis, default_blueprint, plot_axis, run_plot_axes
from agvviz.viz.columns import Columns, Stamp
from agvviz.viz.log_findings import FindingLogger
from agvviz.viz.log_frames import FrameLogger, RunLogError, check_frame
from agvviz.viz.log_lm import LmLogger
from agvviz.viz.log_uncertainty import GHOST_MAX_AMBIGUITY_RATIO, UncertaintyLogger
from agvviz.viz.rrd_file import AtomicRrd
from agvviz.viz.timelines import elapsed_s, set_stamp

#: Per-frame values are sent as columns every this many frames (and at close). Each send costs
#: ≈12 ms for the ≈40 entities whatever their rows: 256 rather than 64 frames took ≈45 ms off a
#: 200-frame run (a sweep's setting: 0.73 → 0.69 s); what waits is a few hundred frames' values.
FLUSH_EVERY_FRAMES = 256
#: A camera without a frame at a time stamp missed one (a dropped image) when this many of its
#: shortest frame intervals have passed since its last frame: 1 for a synchronised camera, under
#: 0.75 for cameras that fire between each other's stamps (half a period for two alternating).
DROPPED_AFTER_PERIODS = 0.75


class RunLogger:
    """Logs a run (static world, cameras, per-frame results, manifest, summary) to one ``.rrd``.

    Data streams to a temporary ``.rrd`` beside ``out_path`` as it is logged (memory does not
    grow with the run); :meth:`close` adds the default blueprint and renames the file into
    place, :meth:`discard` deletes it. Used as a context manager, an exception discards.

    Parameters
    ----------
    out_path : path
        The ``.rrd`` to write; its folder is created if needed. Replaced only by a complete
        file; a write failure (disk full, read-only) raises ``OutputError`` and leaves no
        temporary file.
    recording_name : str
        Shown in the viewer (scenario + setting).
    recording_id : str
        Rerun recording id; pin it so repeated runs produce comparable files.
    recording_start_ns : int, optional
        The recording's first stamp: ``elapsed`` counts from it. None: the first logged
        frame's ``log_time_ns``.
    max_reproj_px : float, optional
        The run's ``max_reproj_px`` setting, drawn as a threshold line on the reprojection
        plot; None: no line.
    images : bool
        False: the camera images are left out (``run --images none`` and a sweep's layers:
        every other entity is logged as in a full run; :mod:`agvviz.viz.frames` adds the
        frames from the recording).
    tmp_path : path, optional
        The temporary file's name (default: one of this process's beside ``out_path``).
    """

    def __init__(
        self,
        out_path: str | os.PathLike,
        *,
        recording_name: str,
        recording_id: str,
        inputs: tuple[str | os.PathLike, ...] = (),
        recording_start_ns: int | None = None,
        max_reproj_px: float | None = None,
        images: bool = True,
        tmp_path: str | os.PathLike | None = None,
        durable: bool = True,
    ):
        # OutputError (from agvviz.errors) when out_path is an input or cannot be written.
        self._file = AtomicRrd(out_path, recording_id=recording_id, recording_name=recording_name, inputs=inputs,
                               tmp_path=tmp_path, durable=durable)
        self._rec = self._file.rec
        #: ``elapsed`` = log time − this (ns); set from the first frame when not given.
        self.recording_start_ns = None if recording_start_ns is None else int(recording_start_ns)
        self.max_reproj_px = None if max_reproj_px is None else float(max_reproj_px)
        #: Layout shipped at :meth:`close`; None: :func:`default_blueprint` of the cameras.
        self.blueprint = None
        self._start_time_sent = False
        self._saved = False
        self._columns = Columns()
        self._frames_buffered = 0
        self._frames_logged = 0
        self._camera_last_ns: dict[str, int] = {}  # camera -> stamp of its last frame (log_cameras_missing)
        self._camera_period_ns: dict[str, int] = {}  # camera -> its shortest frame interval so far
        #: The modality loggers.
        self.frames = FrameLogger(self._rec, self._columns, self.max_reproj_px)
        self.frames.images = bool(images)
        self.lm = LmLogger(self._rec, self._columns)
        self.uncertainty = UncertaintyLogger(self._rec, self._columns)
        self.findings = FindingLogger(self._rec, self._columns)  # run-level findings, at the end
        self._budget_sources: list[str] | None = None  # an error budget was logged: its sources
        try:
            self.frames.log_styles()
            self.uncertainty.log_styles()
            self.lm.log_styles()
        except BaseException:  # no `with` block owns the file yet: discard it here
            self._file.discard()
            raise

    # -- static content --------------------------------------------------------------------
    def log_world_static(self, markers: list[tuple[str, np.ndarray]]) -> None:
        """Log the marker map (static): :meth:`FrameLogger.log_world_static`."""
        self._check_open()
        self.frames.log_world_static(markers)

    def log_camera_static(self, cam_name: str, camera: PinholeCamera, T_agv_cam: np.ndarray) -> None:
        """Log camera ``cam_name`` on the AGV (static): :meth:`FrameLogger.log_camera_static`."""
        self._check_open()
        self.frames.log_camera_static(cam_name, camera, T_agv_cam)

    def log_fixed_camera_static(self, cam_name: str, camera: PinholeCamera, T_world_cam: np.ndarray) -> None:
        """Log camera ``cam_name`` fixed in the world (static):
        :meth:`FrameLogger.log_fixed_camera_static`."""
        self._check_open()
        self.frames.log_fixed_camera_static(cam_name, camera, T_world_cam)

    @property
    def stream(self) -> rr.RecordingStream:
        """The recording stream, for loggers of other modalities (UWB, fusion, correction, studies)."""
        return self._rec

    @property
    def cam_names(self) -> list[str]:
        return self.frames.cam_names

    @property
    def zoom_cams(self) -> list[str]:
        """Cameras that had a small code at least once (they have a zoomed view)."""
        return self.frames.zoom_cams

    # -- per frame -------------------------------------------------------------------------
    def _stamp(self, frame: FrameResult) -> Stamp:
        """Set ``frame``, ``time`` and ``elapsed`` for ``frame``'s logs; return them."""
        if self.recording_start_ns is None:
            self.recording_start_ns = int(frame.log_time_ns)
        set_stamp(self._rec, frame.index, frame.log_time_ns, self.recording_start_ns)
        return int(frame.index), int(frame.log_time_ns), elapsed_s(frame.log_time_ns, self.recording_start_ns)

    def log_camera_view(self, frame: FrameResult) -> None:
        """Log only the image and corners of ``frame`` — another camera's view of a time
        stamp whose pose and errors :meth:`log_frame` logged from the chosen camera."""
        self._check_open()
        check_frame(frame)
        stamp = self._stamp(frame)
        self.frames.log_image(frame)
        self.frames.log_corners(frame, stamp)

    def log_frame(self, frame: FrameResult) -> None:
        """Log everything one frame produced at ``time = log_time_ns`` and ``frame = index``.

        The estimated pose is shown for solved frames only; on a rejected frame the estimate
        keeps its last pose and its body turns grey with the reason as label, and the error
        lines break. The frame is checked completely before anything is logged, so a bad
        frame logs nothing.
        """
        self._check_open()
        self._file.check()  # stop at once when the disk is full, not after the whole run
        check_frame(frame)
        stamp = self._stamp(frame)
        if not self._start_time_sent:
            self._rec.send_recording_start_time_nanos(int(self.recording_start_ns))
            self._start_time_sent = True
        frames = self.frames
        frames.log_image(frame)
        frames.log_corners(frame, stamp)
        frames.log_markers_seen(frame, stamp)
        frames.log_poses(frame, stamp)
        frames.log_errors(frame, stamp)
        self.findings.plotted(frame, stamp)
        self.lm.log(frame, stamp, frame.cam_name in frames.fixed_cams)
        self.uncertainty.log(frame, stamp)
        self._frames_buffered += 1
        self._frames_logged += 1
        if self._frames_buffered >= FLUSH_EVERY_FRAMES:
            self._flush()

    def log_cameras_missing(self, frame: FrameResult, frames: list[FrameResult]) -> None:
        """``frames``: every frame of one time stamp (``frame`` the one it was logged at). A camera
        without a frame here whose own frame was due — at least DROPPED_AFTER_PERIODS of its
        shortest frame interval since its last frame: a dropped image, not a camera that fires at
        other stamps — gets its zoom panel saying so (:meth:`FrameLogger.log_zoom_dropped`)
        instead of keeping the previous crop."""
        self._check_open()
        now_ns = int(frame.log_time_ns)
        for other in frames:
            cam, stamp_ns = other.cam_name, int(other.log_time_ns)
            last_ns = self._camera_last_ns.get(cam)
            if last_ns is not None and stamp_ns > last_ns:
                self._camera_period_ns[cam] = min(self._camera_period_ns.get(cam, stamp_ns - last_ns), stamp_ns - last_ns)
            self._camera_last_ns[cam] = stamp_ns
        present = {other.cam_name for other in frames}
        due = {
            cam for cam, last_ns in self._camera_last_ns.items()
            if cam not in present and cam in self._camera_period_ns
            and now_ns - last_ns >= DROPPED_AFTER_PERIODS * self._camera_period_ns[cam]
        }
        if due:
            self._stamp(frame)
            self.frames.log_zoom_dropped(due)

    def _flush(self) -> None:
        self._columns.flush(self._rec)
        self._frames_buffered = 0

    def log_run_findings(self, findings) -> None:
        """The check stage's run-level findings (``GraphOutcome.findings``): a row each in the
        suspects log at its first frame, and the suspect markers at every frame it covers
        (:class:`~agvviz.viz.log_findings.FindingLogger`)."""
        self._check_open()

        def stamp_at(index: int, log_time_ns: int) -> None:
            start_ns = self.recording_start_ns if self.recording_start_ns is not None else log_time_ns
            set_stamp(self._rec, index, log_time_ns, start_ns)

        self.findings.log(findings, stamp_at)

    # -- run documents ---------------------------------------------------------------------
    def log_manifest(self, manifest: dict) -> None:
        """Log the run manifest (settings, recording hash, version) as static markdown."""
        self._check_open()
        text = _markdown_document("Run manifest", manifest)
        self._rec.log(paths.RUN_MANIFEST, _markdown(text), static=True)

    def log_error_budget(self, budget) -> None:
        """Log an :class:`agvviz.evaluation.error_budget.ErrorBudget` of this run (its table,
        bar chart of shares and per-frame series, :mod:`agvviz.viz.log_budget`); the default
        layout then shows them."""
        from agvviz.viz import log_budget

        self._check_open()
        log_budget.log_budget(self._rec, budget, self.recording_start_ns)
        self._budget_sources = [s.source for s in budget.sources]

    def log_summary(self, summary: dict) -> None:
        """Log the run summary as static markdown: the terminal's table in its units (mm, °, px;
        :func:`agvviz.evaluation.summary_table.summary_rows`, without the wall-clock rows),
        recording damage and warnings into ``run/summary``; the whole summary as a JSON block
        into ``run/summary_json`` (a tab of its own, behind the table)."""
        self._check_open()
        self._rec.log(paths.RUN_SUMMARY, _markdown(_summary_markdown(summary)), static=True)
        block = _json_block("run summary", summary)
        self._rec.log(paths.RUN_SUMMARY_JSON, _markdown(f"### Run summary (JSON, every figure unrounded)\n\n```json\n{block}\n```\n"), static=True)

    # -- output ----------------------------------------------------------------------------
    def plot_axes(self) -> dict[str, PlotAxis]:
        """The y axis of each per-frame series' plot from the frames logged so far
        (:func:`agvviz.viz.blueprints.run_plot_axes`): every value inside, the rejected-frame
        crosses above them."""
        return run_plot_axes(
            self._columns.extents, max_reproj_px=self.max_reproj_px, rejection_reasons=self.frames.rejection_reasons()
        )

    @property
    def has_truth(self) -> bool:
        """False when frames were logged and none carried ground truth (``truth=ignore``, or a
        recording without it): no error can be scored. True before any frame (nothing known)."""
        return self.frames.truth_frames > 0 or self._frames_logged == 0

    def log_no_truth(self) -> None:
        """The note a run without ground truth shows where its error plots would be
        (``run/no_truth``, static; :func:`agvviz.viz.blueprints.no_truth_view`)."""
        self._check_open()
        text = (
            "**No ground truth** (none recorded, or `truth=ignore`): position, heading, pitch and roll "
            "errors, NEES and error ÷ CRLB cannot be scored, so they are not plotted. Without truth: "
            "the **position σ**, the **reprojection RMS**, the **suspects** log, the 3σ ellipsoid in 3D; "
            "with UWB the **GDOP** and the gates."
        )
        self._rec.log(paths.RUN_NO_TRUTH, _markdown(text), static=True)

    def close(self, publish: bool = True) -> Path:
        """Finish the file: log the rejected-frame crosses where the plots' axes put them, send
        the buffered columns, ship the default blueprint, write the footer, move it into place
        (``publish=False``: leave it at its temporary path, see
        :meth:`agvviz.viz.rrd_file.AtomicRrd.commit`). Returns where the file is."""
        self._check_open()
        axes = self.plot_axes()
        if not self.has_truth:
            self.log_no_truth()
        self.frames.log_rejection_markers({entity: axis.marker_y for entity, axis in axes.items()})
        self._flush()
        self._saved = True
        blueprint = self.blueprint
        if blueprint is None:
            blueprint = default_blueprint(
                self.frames.cam_names,
                fixed_cams=self.frames.fixed_cams,
                zoom_cams=self.zoom_cams,
                lm_iterates=self.lm.iterated,
                has_rejections=self.frames.rejected_frames > 0,
                has_threshold=self.max_reproj_px is not None,
                ghost_max_ratio=GHOST_MAX_AMBIGUITY_RATIO,
                cov_scale=self.uncertainty.cov_scale,
                scene_m=self.frames.scene_extent_m(),
                budget_sources=self._budget_sources,
                has_suspects=self.frames.suspect_frames > 0 or self.findings.findings_logged > 0,
                axes=axes,
                max_reproj_px=self.max_reproj_px,
                has_truth=self.has_truth,
                sigma_axis=plot_axis([self._columns.extents[paths.ERROR_POSITION_SIGMA_M]])
                if paths.ERROR_POSITION_SIGMA_M in self._columns.extents else None,
            )
        return self._file.commit(blueprint, publish=publish)

    def discard(self) -> None:
        """Stop logging and delete the unfinished file; ``out_path`` is left untouched."""
        self._saved = True
        self._file.discard()

    def __enter__(self) -> "RunLogger":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()
        elif not self._saved:
            self.close()

    # -- helpers ---------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._saved:
            raise RunLogError("this RunLogger was already closed; create a new one for another run")


def _summary_markdown(summary: dict) -> str:
    """The run summary panel: the terminal table when the summary has its sections (any other
    dict: key/value rows), damage and warnings; the JSON goes to its own tab
    (``run/summary_json``)."""
    rows = summary_rows(summary, {})
    if not rows:
        return _markdown_document("Run summary", summary, with_json=False)
    notes = [f"- recording damage: {p}" for p in summary.get("recording_damage", [])]
    notes += [f"- warning: {w}" for w in summary.get("warnings", [])]
    parts = ["### Run summary", markdown_table(rows)]
    if notes:
        parts.append("\n".join(notes))
    parts.append("*The whole summary (every figure unrounded): the tab \"summary (JSON)\".*")
    return "\n\n".join(parts)



def _markdown(text: str) -> rr.TextDocument:
    return rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN)


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _json_block(what: str, content: dict) -> str:
    """``content`` as indented JSON (RunLogError when it is not serialisable)."""
    try:
        return json.dumps(content, indent=2, sort_keys=True, default=_json_default, allow_nan=True)
    except TypeError as exc:
        raise RunLogError(f"{what} is not JSON serialisable: {exc}") from exc


def _markdown_document(title: str, content: dict, with_json: bool = True) -> str:
    """Markdown: a key/value table (nested dicts flattened with dots) and a JSON block (unless
    ``with_json`` is False)."""
    block = _json_block(title.lower(), content)
    rows = []
    for key, value in _flatten(json.loads(block)):
        if isinstance(value, float):
            text = f"{value:.6g}" if math.isfinite(value) else str(value)
        else:
            text = json.dumps(value) if isinstance(value, list) else str(value)
        escaped = text.replace("|", "\\|")
        rows.append(f"| {key} | {escaped} |")
    table = "\n".join(["| key | value |", "| --- | --- |", *rows])
    if not with_json:
        return f"# {title}\n\n{table}\n"
    return f"# {title}\n\n{table}\n\n```json\n{block}\n```\n"


def _flatten(content: dict, prefix: str = ""):
    for key, value in content.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value
