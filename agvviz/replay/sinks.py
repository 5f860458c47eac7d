"""Sinks: the graph's last stage — the run's ``.rrd`` (through the loggers of :mod:`agvviz.viz`),
its statistics and its summary. Nothing here decides anything about a pose; it records what the
stages before it decided.
"""

from __future__ import annotations

from typing import Callable

from agvviz.evaluation.fusion_summary import FusionStats
from agvviz.evaluation.summary import FrameScore, summarize
from agvviz.replay.correct import CorrectionSettings, CorrectionStats, CorrectionStep
from agvviz.replay.fuse import FrameSetResult
from agvviz.model.frames import FrameResult
from agvviz.settings import RunSettings
from agvviz.viz.blueprints import correction_blueprint, uwb_blueprint
from agvviz.viz.log_correction import CorrectionLogger
from agvviz.viz.log_uwb import FusionLogger
from agvviz.viz.run_logger import RunLogger


#: Every this many frames the ``.rrd`` stream is flushed (waiting until Rerun has written what
#: was logged). Without it Rerun's file sink queues data faster than it writes, and a run's
#: peak memory grows with its length (measured: 2000 frames of images alone 274 MiB against
#: 203 MiB for 200; flushed every 20 frames, 206 against 211).
RRD_FLUSH_EVERY_FRAMES = 25  # not RunLogger.FLUSH_EVERY_FRAMES: that batches columns, this waits for the file


class RunSinks:
    """Everything a run writes and counts, fed by :class:`agvviz.graph.ReplayGraph`.

    ``cameras`` is the sync stage's camera state (calibration and extrinsic per camera, read
    to log each camera once both are known); ``progress(frames_done)`` is called per scored
    frame.
    """

    def __init__(
        self,
        logger: RunLogger,
        settings: RunSettings,
        cameras: dict,
        progress: Callable[[int], None] | None = None,
    ):
        self.logger = logger
        self.settings = settings
        self.cameras = cameras
        self.progress = progress
        self.scores: list[FrameScore] = []
        self.rejections: dict[str, list] = {}  # reason -> [count, first detail]
        self.fusion_logger = FusionLogger(logger.stream, recording_start_ns=logger.recording_start_ns)
        self.fusion_stats = FusionStats()
        self.correction_logger = (
            CorrectionLogger(
                logger.stream, recording_start_ns=logger.recording_start_ns, cameras=cameras,
                max_reproj_px=settings.max_reproj_px, max_position_sigma_m=CorrectionSettings.max_position_sigma_m,
            )
            if settings.correction != "none" else None
        )
        self.correction_stats = CorrectionStats()
        self._cameras_logged: set[str] = set()

    # -- per message ----------------------------------------------------------------------------
    def cameras_changed(self) -> None:
        """Log each camera once both its calibration and its extrinsic are known."""
        for cam_name, cam in self.cameras.items():
            if cam.camera is None or cam_name in self._cameras_logged:
                continue
            if cam.T_agv_cam is not None:
                self.logger.log_camera_static(cam_name, cam.camera, cam.T_agv_cam)
            elif cam.T_world_cam is not None:
                self.logger.log_fixed_camera_static(cam_name, cam.camera, cam.T_world_cam)
            else:
                continue
            self._cameras_logged.add(cam_name)

    def frame(self, frame: FrameResult) -> None:
        """A frame logged and scored on its own (one that could not be placed in time)."""
        self.logger.log_frame(frame)
        self._score(frame)

    def fused(self, item, fusion) -> None:
        """An output of the fuse stage: a time stamp's frames (the scored one and the other
        cameras' views), a UWB range or fix."""
        if isinstance(item, FrameSetResult):
            self.logger.log_frame(item.scored)
            for other in item.frames:
                if other is not item.scored:
                    self.logger.log_camera_view(other)
            self._score(item.scored)
        if fusion.has_uwb:
            if not self.fusion_logger.anchor_ids:
                self.fusion_logger.log_anchors(fusion.anchors_m, fusion.tag_z_m, list(self.cameras))
            self.fusion_logger.log(item)
            self.fusion_stats.add(item)

    def corrected(self, step: CorrectionStep) -> None:
        self.correction_logger.log(step)
        self.correction_stats.add(step)

    def _score(self, frame: FrameResult) -> None:
        self.scores.append(FrameScore.of(frame))
        if len(self.scores) % RRD_FLUSH_EVERY_FRAMES == 0:
            self.logger.stream.flush()  # bounded memory: see RRD_FLUSH_EVERY_FRAMES
        if frame.rejected is not None:
            self.rejections.setdefault(frame.rejected, [0, frame.reject_detail or ""])[0] += 1
        if self.progress is not None:
            self.progress(len(self.scores))

    # -- at the end -----------------------------------------------------------------------------
    def summary(self, has_uwb: bool) -> dict:
        """The run summary of what was fed (the caller adds damage, detection and warnings) and
        the layout that fits the run's kind."""
        settings = self.settings
        # A corner-only correction run has no camera frames: no frame statistics to claim.
        summary = summarize(self.scores) if self.scores or self.correction_logger is None else {}
        if has_uwb:
            summary["fusion"] = {"uwb": settings.uwb, "fusion": settings.fusion, **self.fusion_stats.summary()}
            fixed = {name for name, cam in self.cameras.items() if cam.T_agv_cam is None}
            self.logger.blueprint = uwb_blueprint(
                self.logger.cam_names, fixed, self.fusion_logger.anchor_ids,
                zoom_cams=self.logger.zoom_cams, error_range_mm=self.fusion_logger.error_range_mm(),
            )
        if self.correction_logger is not None:
            summary["correction"] = {"solver": settings.correction, **self.correction_stats.summary()}
            self.logger.blueprint = correction_blueprint(sorted(self.cameras))
        return summary
