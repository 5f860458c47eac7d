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
from agvviz.evaluation import FrameScore, summarize
from agvviz.pipeline import Replay
from agvviz.recording.reader import (
    CalibrationMsg,
    ReadReport,
    iter_messages,
    read_scenario_metadata,
)
from agvviz.settings import RunSettings, as_dict
from agvviz.viz.run_logger import RunLogger

MARKER_MAP_TOPIC = "/markers/map"


class RunError(ValueError):
    """A run that cannot start: bad paths, output would overwrite the input."""


@dataclass
class RunOutcome:
    out_path: Path
    summary: dict
    manifest: dict
    read_report: ReadReport


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
        corners = np.asarray(m.get("corners_world_m", []), dtype=float)
        if corners.shape == (4, 3) and np.all(np.isfinite(corners)):
            markers.append((str(m.get("id")), corners))
    return markers


def run_recording(
    recording_path: Path,
    settings: RunSettings,
    out_path: Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> RunOutcome:
    """Replay ``recording_path`` under ``settings`` and write the run to ``out_path``.

    ``progress(frames_done)`` is called after every frame. Returns the run summary and
    manifest (both also stored in the ``.rrd``).
    """
    recording_path = Path(recording_path)
    if not recording_path.is_file():
        raise RunError(f"recording not found: {recording_path}")
    out_path = Path(out_path) if out_path is not None else default_run_path(recording_path, settings)
    if out_path.suffix != ".rrd":
        raise RunError(f"output must be a .rrd file, got {out_path}")
    if out_path.resolve() == recording_path.resolve():
        raise RunError("the output path is the recording itself; refusing to overwrite an input")
    out_path.parent.mkdir(parents=True, exist_ok=True)

    recording_sha256 = file_sha256(recording_path)
    scenario = read_scenario_metadata(recording_path)
    scenario_name = scenario["name"] if scenario else recording_path.stem
    recording_name = f"{scenario_name}-{settings.label()}"
    recording_id = str(
        uuid.uuid5(uuid.NAMESPACE_URL, f"agvviz:{recording_sha256}:{sorted(as_dict(settings).items())}")
    )
    manifest = {
        "agvviz_version": __version__,
        "recording": str(recording_path),
        "recording_sha256": recording_sha256,
        "scenario": scenario,
        "settings": as_dict(settings),
        "recording_name": recording_name,
    }

    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    scores: list[FrameScore] = []
    with RunLogger(out_path, recording_name=recording_name, recording_id=recording_id) as logger:
        logger.log_manifest(manifest)
        replay = Replay(settings)
        cameras_logged: set[str] = set()
        t_start = time.perf_counter()
        for message in iter_messages(recording_path, report=read_report):
            if message.topic == MARKER_MAP_TOPIC and isinstance(message.value, dict):
                logger.log_world_static(_markers_from_map(message.value))
            frame = replay.feed(message)
            if isinstance(message.value, (CalibrationMsg, list)):
                # Log each camera once both its calibration and its extrinsic are known.
                for cam_name, cam in replay.ctx.cameras.items():
                    ready = cam.camera is not None and cam.T_agv_cam is not None
                    if ready and cam_name not in cameras_logged:
                        logger.log_camera_static(cam_name, cam.camera, cam.T_agv_cam)
                        cameras_logged.add(cam_name)
            if frame is None:
                continue
            logger.log_frame(frame)
            scores.append(FrameScore.of(frame))
            if progress is not None:
                progress(len(scores))
        wall_time_s = time.perf_counter() - t_start
        summary = summarize(scores, wall_time_s)
        summary["recording_damage"] = list(read_report.problems)
        logger.log_summary(summary)
    return RunOutcome(out_path=out_path, summary=summary, manifest=manifest, read_report=read_report)
