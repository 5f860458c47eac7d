"""The rejected frames on a run's plots: a red cross per rejected frame on the plot of each
per-frame series (:data:`agvviz.viz.paths.REJECTION_MARKED`), where the series itself has no value
(issue 26: a rejected frame is a gap, never a value drawn at 0 or at the value it was rejected
for).

A cross sits on the limit the frame broke (``max_reproj_px`` on the reprojection plot for a frame
rejected for its reprojection), else just above the plot's data (the marker band of
:class:`agvviz.viz.blueprints.PlotAxis`). One entity per series and reason
(``errors/rejected/<series>/<reason>``), its series name the reason in words, so hovering a cross
says why; the rejections log has each frame's detail. Logged when the run closes, where the
plots' axes are known.
"""

from __future__ import annotations

import rerun as rr

from agvviz.model import frames as frames_model
from agvviz.model.frames import REJECT_REPROJECTION
from agvviz.viz import paths
from agvviz.viz.columns import Columns, Stamp
from agvviz.viz.style import COLOR_REJECTED

#: What each rejection reason means, for the crosses' names.
REJECTION_WORDS = {
    frames_model.REJECT_NO_MARKER: "no code found",
    frames_model.REJECT_DECODE: "code found, payload not decoded",
    frames_model.REJECT_PAYLOAD: "payload refused by the parser",
    frames_model.REJECT_GEOMETRY: "code corners degenerate",
    frames_model.REJECT_SOLVER: "the solver found no pose",
    frames_model.REJECT_NO_CALIBRATION: "no calibration yet",
    frames_model.REJECT_NO_EXTRINSIC: "no camera mount (extrinsic) yet",
    frames_model.REJECT_IMAGE: "image unreadable",
    frames_model.REJECT_CALIBRATION_SIZE: "image size differs from the calibration",
    frames_model.REJECT_TIME: "time stamp not after the previous image",
    frames_model.REJECT_MAP_MISMATCH: "payload disagrees with the marker map",
}


def rejection_name(reason: str, max_reproj_px: float | None = None, at_limit: bool = False) -> str:
    """The series name of a cross: what hovering it says."""
    words = REJECTION_WORDS.get(reason, reason.replace("_", " "))
    if reason == REJECT_REPROJECTION:
        limit = "" if max_reproj_px is None else f" {max_reproj_px:g} px"
        words = f"reprojection RMS above max_reproj_px{limit}" + (" (cross at the limit)" if at_limit else "")
    return f"rejected: {words}"


def log_rejection_markers(
    rec: rr.RecordingStream,
    columns: Columns,
    rejections: list[tuple[Stamp, str]],
    marker_y: dict[str, float],
    max_reproj_px: float | None,
    series: tuple[str, ...] = paths.REJECTION_MARKED,
) -> None:
    """A cross per rejected frame (``rejections``: (stamp, reason)) on the plot of each of
    ``series``: at ``max_reproj_px`` on the reprojection plot for a frame rejected for its
    reprojection, else at ``marker_y[series]`` (a series without an axis gets none)."""
    for reason in dict.fromkeys(reason for _, reason in rejections):
        stamps = [stamp for stamp, r in rejections if r == reason]
        for entity in series:
            at_limit = entity == paths.ERROR_REPROJ_RMS_PX and reason == REJECT_REPROJECTION and max_reproj_px is not None
            y = max_reproj_px if at_limit else marker_y.get(entity)
            if y is None:
                continue
            marker = paths.error_rejected(entity, reason)
            rec.log(
                marker,
                rr.SeriesPoints(
                    names=rejection_name(reason, max_reproj_px, at_limit),
                    colors=COLOR_REJECTED,
                    markers=rr.components.MarkerShape.Cross,
                    marker_sizes=5.0,
                ),
                static=True,
            )
            columns.extend(marker, stamps, y)
