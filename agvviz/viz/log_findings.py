"""The check stage's run-level findings in a run's ``.rrd`` (issue 25): a finding about the whole
log (:class:`~agvviz.model.suspects.RunFinding`, e.g. a camera's stamp offset) is known only at
the end of the run, after its frames were logged. :class:`FindingLogger` remembers where each
solved frame sits on the error plots and, at the end, logs one row per finding in the suspects log
(``events/suspects``, at the finding's first frame) and the suspect marker (``errors/suspect/*``)
at every frame it covers that had none — the same marker a suspect frame gets, so the plots show
the whole stretch.
"""

from __future__ import annotations

from typing import Callable, Iterable

import rerun as rr

from agvviz.evaluation.suspect_report import cause_words, finding_line, suspect_line
from agvviz.model.frames import FrameResult
from agvviz.model.suspects import RunFinding, Suspect
from agvviz.viz import paths
from agvviz.viz.columns import Columns, Stamp


def error_values(frame: FrameResult) -> tuple[tuple[str, float | None], ...]:
    """(entity, value or None) of a frame's error plots: position (mm), heading, pitch, roll
    (deg), reprojection RMS (px)."""
    return (
        (paths.ERROR_POSITION_MM, None if frame.position_error_m is None else 1000.0 * frame.position_error_m),
        (paths.ERROR_HEADING_DEG, frame.heading_error_deg),
        (paths.ERROR_PITCH_DEG, frame.pitch_error_deg),
        (paths.ERROR_ROLL_DEG, frame.roll_error_deg),
        (paths.ERROR_REPROJ_RMS_PX, frame.reproj_rms_px),
    )


class FindingLogger:
    """Marks of run-level findings on the frames the run logged with their errors
    (:meth:`plotted`); ``findings_logged`` counts the findings, ``frames_marked`` the frames a
    finding marked."""

    def __init__(self, rec: rr.RecordingStream, columns: Columns):
        self._rec = rec
        self._columns = columns
        #: (camera, frame index) -> (stamp, ((entity, value), …) of its marked series, marked already)
        self._plotted: dict[tuple[str, int], tuple[Stamp, tuple, bool]] = {}
        self.frames_marked = 0
        self.findings_logged = 0

    def plotted(self, frame: FrameResult, stamp: Stamp) -> None:
        """A frame logged on the error plots (a solved one is remembered; marked already when it is a suspect)."""
        if not frame.solved:
            return
        marked = tuple((entity, value) for entity, value in error_values(frame)
                       if value is not None and entity in paths.SUSPECT_MARKED)
        self._plotted[(frame.cam_name, frame.index)] = (stamp, marked, frame.suspect is not None)

    def log(self, findings: Iterable[RunFinding], stamp_at: Callable[[int, int], None]) -> None:
        """One row each in the suspects log at its first frame (``stamp_at(index, log_time_ns)``
        sets the timelines there) and the suspect markers at every frame it covers that had none."""
        for finding in findings:
            if not finding.frame_indices:
                continue
            first = finding.frame_indices.index(finding.first_frame)
            stamp_at(finding.first_frame, finding.times_ns[first])
            self._rec.log(paths.EVENTS_SUSPECTS, rr.TextLog(finding_row(finding), level=rr.TextLogLevel.WARN))
            self.findings_logged += 1
            for index in finding.frame_indices:
                key = (finding.cam_name, index)
                plotted = self._plotted.get(key)
                if plotted is None or plotted[2]:
                    continue  # not on the plots (another camera's stamp), or marked already
                stamp, values, _ = plotted
                for entity, value in values:
                    self._columns.scalar(paths.error_suspect(entity), stamp, value)
                self._plotted[key] = (stamp, values, True)
                self.frames_marked += 1


# -- log rows ------------------------------------------------------------------------------------
# A log panel shows a row's first line, cut at the panel's width (≈ 55 characters in the default
# layout, beside the frame column): the key facts come first there — likely cause, where, how far
# (and the frames a run-level finding covers) — and the whole sentence of the terminal report
# follows on the next lines of the same row (click the row's "…" to expand it).


def suspect_row(suspect: Suspect) -> str:
    """``marker map entry (Q015, front) · 377σ`` then :func:`suspect_line` (which names the frame)."""
    where = ", ".join(x for x in (suspect.marker_id, suspect.cam_name) if x)
    head = cause_words(suspect.cause) + (f" ({where})" if where else "")
    return f"{head} · {suspect.sigma:.0f}σ\n{suspect_line(suspect)}"


def finding_row(finding: RunFinding) -> str:
    """``frames 0–57: camera time offset (front) · 14σ`` then :func:`finding_line`."""
    head = f"frames {finding.first_frame}–{finding.last_frame}: {cause_words(finding.cause)} ({finding.cam_name})"
    return f"{head} · {finding.sigma:.0f}σ\n{finding_line(finding)}"


def rejection_row(frame: FrameResult) -> str:
    """``frame 12 (front): reprojection`` then the rejection's detail, when it has one."""
    head = f"frame {frame.index} ({frame.cam_name}): {frame.rejected}"
    return f"{head}\n{frame.reject_detail}" if frame.reject_detail else head
