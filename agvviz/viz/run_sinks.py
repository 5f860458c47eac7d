"""The run's ``.rrd`` as sinks of the replay graph (:class:`agvviz.replay.sinks.Sink`): what each
callback logs, through :class:`~agvviz.viz.run_logger.RunLogger` and the modality loggers, and the
layout that fits the run's kind. :mod:`agvviz.app.run` composes them with the statistics."""

from __future__ import annotations

from typing import Mapping

from agvviz.model.fusion import FrameSetResult
from agvviz.replay.correct import CorrectionSettings
from agvviz.replay.graph import STUDY_CNOEM, STUDY_MONTE_CARLO
from agvviz.replay.sinks import NullSink
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.blueprints import (
    clipped_axis, cnoem_trials_blueprint, correction_blueprint, plot_axis, trials_blueprint, uwb_blueprint,
)
from agvviz.viz.log_correction import CorrectionLogger
from agvviz.viz.log_studies import log_cnoem_trials, log_trials
from agvviz.viz.log_uwb import FusionLogger, log_room_outline
from agvviz.viz.run_logger import RunLogger

#: Every this many frames the ``.rrd`` stream is flushed (waiting until Rerun has written what
#: was logged). Without it Rerun's file sink queues data faster than it writes, and a run's
#: peak memory grows with its length (measured: 2000 frames of images alone 274 MiB against
#: 203 MiB for 200; flushed every 20 frames, 206 against 211).
RRD_FLUSH_EVERY_FRAMES = 25  # not RunLogger.FLUSH_EVERY_FRAMES: that batches columns, this waits for the file


class RrdSink(NullSink):
    """A camera, UWB or correction run's ``.rrd``: cameras once calibration and extrinsic are
    known, every frame, UWB fusion (:class:`~agvviz.viz.log_uwb.FusionLogger`), correction
    steps (:class:`~agvviz.viz.log_correction.CorrectionLogger`), and at :meth:`close` the
    layout that fits the run's kind."""

    def __init__(self, logger: RunLogger, settings: RunSettings):
        self.logger = logger
        self.settings = settings
        self.cameras: dict = {}  # the latest snapshot (the correction logger reads it)
        self.frames_scored = 0
        self.fusion_logger = FusionLogger(logger.stream, recording_start_ns=logger.recording_start_ns)
        self.correction_logger = (
            CorrectionLogger(
                logger.stream, recording_start_ns=logger.recording_start_ns, cameras=self.cameras,
                max_reproj_px=settings.max_reproj_px, max_position_sigma_m=CorrectionSettings.max_position_sigma_m,
            )
            if settings.correction != "none" else None
        )
        self._cameras_logged: set[str] = set()
        self.room_m = None  # the UWB room's (low, high) corners, once its anchors are known

    def cameras_changed(self, cameras: Mapping) -> None:
        """Log each camera once both its calibration and its extrinsic are known."""
        self.cameras.clear()
        self.cameras.update(cameras)
        for cam_name, cam in cameras.items():
            if cam.camera is None or cam_name in self._cameras_logged:
                continue
            if cam.T_agv_cam is not None:
                self.logger.log_camera_static(cam_name, cam.camera, cam.T_agv_cam)
            elif cam.T_world_cam is not None:
                self.logger.log_fixed_camera_static(cam_name, cam.camera, cam.T_world_cam)
            else:
                continue
            self._cameras_logged.add(cam_name)

    def frame(self, frame) -> None:
        self.logger.log_frame(frame)
        self._scored()

    def fused(self, item, uwb) -> None:
        if isinstance(item, FrameSetResult):
            self.logger.log_frame(item.scored)
            for other in item.frames:
                if other is not item.scored:
                    self.logger.log_camera_view(other)
            self.logger.log_cameras_missing(item.scored, item.frames)
            self._scored()
        if uwb is not None:
            if not self.fusion_logger.anchor_ids:
                self.fusion_logger.log_anchors(uwb.anchors_m, uwb.tag_z_m, list(self.cameras))
                self.room_m = log_room_outline(self.logger.stream, uwb.anchors_m)
            self.fusion_logger.log(item)

    def corrected(self, step) -> None:
        self.correction_logger.images = self.frames_scored > 0  # a corner-only run scores no frame
        self.correction_logger.log(step)

    def _scored(self) -> None:
        self.frames_scored += 1
        if self.frames_scored % RRD_FLUSH_EVERY_FRAMES == 0:
            self.logger.stream.flush()  # bounded memory: see RRD_FLUSH_EVERY_FRAMES

    def finished(self, outcome) -> None:
        """The check stage's run-level findings (suspects log, markers on the error plots), then
        the layout that fits the run's kind (shipped when the logger closes)."""
        if outcome.findings:
            self.logger.log_run_findings(outcome.findings)
        if outcome.has_uwb:
            fixed = {name for name, cam in self.cameras.items() if cam.T_agv_cam is None}
            fusion = self.fusion_logger
            self.logger.blueprint = uwb_blueprint(
                self.logger.cam_names, fixed, fusion.anchor_ids,
                zoom_cams=self.logger.zoom_cams,
                camera_axis=self.logger.plot_axes().get(paths.ERROR_POSITION_MM),
                camera_rejected=self.logger.frames.rejected_frames > 0,
                error_axis=clipped_axis(fusion.errors_mm, "mm"),
                range_axes={a: plot_axis([extent], include_zero=False) for a, extent in fusion.range_extents.items()},
                room_m=self.room_m,
                has_truth=self.logger.has_truth,
            )
        if self.correction_logger is not None:
            self.logger.blueprint = correction_blueprint(sorted(self.cameras), self.correction_logger.cycle_axes_high())


class StudyRrdSink(NullSink):
    """A study run's ``.rrd``: its error series, report and layout."""

    def __init__(self, logger: RunLogger, study: str):
        self.logger = logger
        self._log, self._blueprint = {
            STUDY_MONTE_CARLO: (log_trials, trials_blueprint),
            STUDY_CNOEM: (log_cnoem_trials, cnoem_trials_blueprint),
        }[study]

    def study(self, outcome) -> None:
        self._log(self.logger.stream, outcome)
        self.logger.blueprint = self._blueprint(outcome)
