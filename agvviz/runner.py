"""Library API behind ``agvviz run``: replay a recording and write the run ``.rrd``.

The CLI stays a thin layer over :func:`run_recording`, which returns values and prints nothing.
"""

from __future__ import annotations

import hashlib
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from agvviz import __version__
from agvviz.errors import RunError
from agvviz.evaluation.summary import FrameScore, summarize, timing
from agvviz.evaluation.fusion_summary import FusionStats
from agvviz.fusion_replay import FrameSetResult, FusionReplay
from agvviz.pipeline import Replay
from agvviz.recording.contract import REJECT_TIME
from agvviz.recording.reader import (
    DATA_SECTION_CRC_PROBLEM,
    CalibrationMsg,
    ReadReport,
    iter_messages,
    read_scenario_metadata,
)
from agvviz.settings import RunSettings, as_dict
from agvviz.viz.run_logger import RunLogger
from agvviz.viz.uwb_blueprint import uwb_blueprint
from agvviz.viz.uwb_logger import FusionLogger
from agvviz.correction import CorrectionReplay, CorrectionSettings, CorrectionStats
from agvviz.viz.correction_logger import CorrectionLogger, correction_blueprint

MARKER_MAP_TOPIC = "/markers/map"


@dataclass
class RunOutcome:
    """What a run wrote: ``summary`` and ``manifest`` are stored in the ``.rrd``; ``timing``
    (wall-clock figures, see :func:`agvviz.evaluation.summary.timing`) is not, so the same
    recording and settings always give an equal ``.rrd``."""

    out_path: Path
    summary: dict
    manifest: dict
    read_report: ReadReport
    timing: dict


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def default_run_path(recording_path: Path, settings: RunSettings) -> Path:
    return Path("runs") / f"{Path(recording_path).stem}-{settings.label()}.rrd"


def _markers_from_map(marker_map: dict) -> list[tuple[str, np.ndarray]]:
    markers = []
    for m in marker_map.get("markers", []):
        if m.get("frame", "world") != "world":
            continue  # a marker on the AGV (paper 003) has no fixed place in the world
        corners = np.asarray(m.get("corners_world_m", []), dtype=float)
        if corners.shape == (4, 3) and np.all(np.isfinite(corners)):
            markers.append((str(m.get("id")), corners))
    return markers


def run_warnings(replay_warnings: list[str], read_report: ReadReport) -> list[str]:
    """The run summary's ``warnings``: what makes the run's numbers doubtful although it
    completed — the replay's recording-level findings (time stamps, ground truth that scored
    nothing; the checks ``inspect`` applies too) and metadata that a damaged data section
    leaves untrustworthy. Damage itself is listed under ``recording_damage``."""
    warnings = list(replay_warnings)
    if DATA_SECTION_CRC_PROBLEM in read_report.problems:
        warnings.append(
            "the recording's data section CRC does not match: the scenario metadata (name, seed, "
            "options) in this run's manifest may be damaged"
        )
    return warnings


def run_recording(
    recording_path: Path,
    settings: RunSettings,
    out_path: Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> RunOutcome:
    """Replay ``recording_path`` under ``settings`` and write the run to ``out_path``.

    ``progress(frames_done)`` is called after every frame. Returns the run summary and
    manifest (both also stored in the ``.rrd``) and the wall-clock timing (not stored).
    """
    recording_path = Path(recording_path)
    if not recording_path.is_file():
        raise RunError(f"recording not found: {recording_path}")
    out_path = Path(out_path) if out_path is not None else default_run_path(recording_path, settings)
    if out_path.suffix != ".rrd":
        raise RunError(f"output must be a .rrd file, got {out_path}")
    # OutputError when out_path is the recording (also through a link) or cannot be written.
    from agvviz import outputs

    outputs.prepare_output(out_path, inputs=(recording_path,))

    recording_sha256 = file_sha256(recording_path)
    scenario = read_scenario_metadata(recording_path)
    scenario_name = scenario["name"] if scenario else recording_path.stem
    recording_name = f"{scenario_name}-{settings.label()}"
    recording_id = str(
        uuid.uuid5(uuid.NAMESPACE_URL, f"agvviz:{recording_sha256}:{sorted(as_dict(settings).items())}")
    )
    # Only what is the same for every identical run: the file name, not the path it was
    # given by (the sha256 identifies the content).
    manifest = {
        "agvviz_version": __version__,
        "recording": recording_path.name,
        "recording_sha256": recording_sha256,
        "scenario": scenario,
        "settings": as_dict(settings),
        "recording_name": recording_name,
    }

    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    scores: list[FrameScore] = []
    with RunLogger(
        out_path, recording_name=recording_name, recording_id=recording_id, inputs=(recording_path,)
    ) as logger:
        logger.log_manifest(manifest)
        replay = Replay(settings)
        # Frames of one time stamp (several cameras) → one camera fix; UWB; fusion.
        fusion = FusionReplay(settings, replay.ctx.cameras)
        fusion_logger = FusionLogger(logger.stream)
        fusion_stats = FusionStats()
        cameras_logged: set[str] = set()
        correction = None
        if settings.correction != "none":
            correction = CorrectionReplay(
                CorrectionSettings(
                    solver=settings.correction, update=settings.cnoem_update,
                    cycle_distance_m=settings.cycle_distance_m, max_reproj_px=settings.max_reproj_px,
                ),
                replay.ctx.cameras,
            )
            correction_logger = CorrectionLogger(logger.stream)
            correction_stats = CorrectionStats()

        def log_item(item) -> None:
            if isinstance(item, FrameSetResult):
                logger.log_frame(item.scored)
                for other in item.frames:
                    if other is not item.scored:
                        logger.log_camera_view(other)
                scores.append(FrameScore.of(item.scored))
                if progress is not None:
                    progress(len(scores))
            if fusion.has_uwb:
                if not fusion_logger.anchor_ids:
                    fusion_logger.log_anchors(fusion.anchors_m, fusion.tag_z_m, list(replay.ctx.cameras))
                fusion_logger.log(item)
                fusion_stats.add(item)

        t_start = time.perf_counter()
        for message in iter_messages(recording_path, report=read_report):
            if message.topic == MARKER_MAP_TOPIC and isinstance(message.value, dict):
                logger.log_world_static(_markers_from_map(message.value))
            frame = replay.feed(message)
            if frame is not None and frame.rejected == REJECT_TIME:
                # A frame that cannot be placed in time (repeated or reversed time stamp) is
                # logged and counted on its own, never grouped with the frames of its time stamp.
                logger.log_frame(frame)
                scores.append(FrameScore.of(frame))
                if progress is not None:
                    progress(len(scores))
                frame = None
            if isinstance(message.value, (CalibrationMsg, list)):
                # Log each camera once both its calibration and its extrinsic are known.
                for cam_name, cam in replay.ctx.cameras.items():
                    if cam.camera is None or cam_name in cameras_logged:
                        continue
                    if cam.T_agv_cam is not None:
                        logger.log_camera_static(cam_name, cam.camera, cam.T_agv_cam)
                    elif cam.T_world_cam is not None:
                        logger.log_fixed_camera_static(cam_name, cam.camera, cam.T_world_cam)
                    else:
                        continue
                    cameras_logged.add(cam_name)
            for item in fusion.feed(message, frame):
                log_item(item)
            if correction is not None:
                for step in correction.feed(message, frame):
                    correction_logger.log(step)
                    correction_stats.add(step)
        for item in fusion.finish():
            log_item(item)
        if correction is not None:
            for step in correction.finish():
                correction_logger.log(step)
                correction_stats.add(step)
        wall_time_s = time.perf_counter() - t_start
        summary = summarize(scores)
        if fusion.has_uwb:
            summary["fusion"] = {"uwb": settings.uwb, "fusion": settings.fusion, **fusion_stats.summary()}
            fixed = {name for name, cam in replay.ctx.cameras.items() if cam.T_agv_cam is None}
            logger.blueprint = uwb_blueprint(logger.cam_names, fixed, fusion_logger.anchor_ids)
        if correction is not None:
            summary["correction"] = {"solver": settings.correction, **correction_stats.summary()}
            logger.blueprint = correction_blueprint(sorted(replay.ctx.cameras))
        summary["recording_damage"] = list(read_report.problems)
        summary["warnings"] = run_warnings(replay.warnings(), read_report)
        logger.log_summary(summary)
    return RunOutcome(
        out_path=out_path,
        summary=summary,
        manifest=manifest,
        read_report=read_report,
        timing=timing(scores, wall_time_s),
    )
