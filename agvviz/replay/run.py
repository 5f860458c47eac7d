"""Library API behind ``agvviz run``: replay a recording and write the run ``.rrd``.

The CLI stays a thin layer over :func:`run_recording`, which returns values and prints nothing.
"""

from __future__ import annotations

import hashlib
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from agvviz import __version__
from agvviz.conventions import camera_frame
from agvviz.errors import InputError, OutputError, RunError
from agvviz.evaluation.summary import timing
from agvviz.replay.detect import cache as detect_cache
from agvviz.replay.detect.pool import DetectionFeed, default_jobs
from agvviz.replay.graph import ReplayGraph
from agvviz.replay.sinks import RunSinks
from agvviz.replay.solve import Replay
from agvviz.model.messages import CalibrationMsg, FrameTransformMsg
from agvviz.recording.mcap_records import DATA_SECTION_CRC_PROBLEM
from agvviz.recording.raw import ReadReport, Recording
from agvviz.recording.roles import IMAGE_TYPES, RoleMap
from agvviz.recording.source import (
    Scan,
    iter_role_messages,
    open_recording,
    require_recording_path,
    resolve_roles,
    scan,
)
from agvviz.model.topics import ROLE_CORNERS, ROLE_MARKER_MAP, ROLE_ODOMETRY, ROLE_UWB_RANGE, calibration_role, image_role
from agvviz.model.frames import (
    REJECT_CALIBRATION_SIZE,
    REJECT_IMAGE,
    REJECT_NO_CALIBRATION,
    REJECT_NO_EXTRINSIC,
    REJECT_TIME,
    FrameResult,
)
from agvviz.settings import RunSettings, as_dict, inapplicable, without
from agvviz.viz.run_logger import RunLogger


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
    path = Path(recording_path)
    name = path.name if path.is_dir() else path.stem
    return Path("runs") / f"{name}-{settings.label()}.rrd"


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


@dataclass
class SideInputs:
    """Values from side files, fed to the replay before the recording's messages; each
    overrides the recording's own value (the marker map; a camera's calibration; a camera's
    extrinsic ``T_body_cam`` — ``T_parent_child`` of the transform, whatever its parent's name)."""

    marker_map: dict | None = None
    calibrations: dict[str, CalibrationMsg] = field(default_factory=dict)
    extrinsics: dict[str, FrameTransformMsg] = field(default_factory=dict)

    def describe(self) -> dict:
        return {
            "markers": self.marker_map is not None,
            "calibration": sorted(self.calibrations),
            "extrinsic": sorted(self.extrinsics),
        }


#: Rejections that say a frame could not be used at all (as opposed to a frame whose markers
#: were not found or not solved): a run whose every frame is one of these fails.
UNUSABLE_REJECTIONS = (REJECT_NO_CALIBRATION, REJECT_NO_EXTRINSIC, REJECT_IMAGE, REJECT_CALIBRATION_SIZE, REJECT_TIME)


@dataclass
class Prepared:
    """A recording opened, scanned and given its role map, with the replay's sync stage
    filled by the first pass (:func:`prepare`)."""

    recording: Recording
    scan: Scan
    roles: RoleMap
    body_frame: str
    time_source: str
    replay: Replay
    causes: list[str]  # why a camera's frames cannot be used, one line each
    usable_cameras: list[str]

    @property
    def can_run(self) -> bool:
        """A camera whose frames can be used, or corner observations / UWB ranges to replay."""
        return bool(self.usable_cameras) or ROLE_CORNERS in self.roles.roles or ROLE_UWB_RANGE in self.roles.roles


def _camera_causes(prepared_scan: Scan, roles: RoleMap, replay: Replay) -> tuple[list[str], list[str]]:
    """(usable cameras, one line per camera that cannot be used and why)."""
    causes, usable = [], []
    for cam_name in roles.cameras():
        topic = roles.roles[image_role(cam_name)]
        info = prepared_scan.topics[topic]
        why = []
        image_problem = prepared_scan.first_problem.get(topic)
        if image_problem and not info.frame_id:
            why.append(f"its frames do not decode ({image_problem})")
        cam = replay.ctx.cameras.get(cam_name)
        calib_topic = roles.roles.get(calibration_role(cam_name))
        if replay.sync.calibration_at(cam_name, 2**62) is None:
            if calib_topic is None:
                why.append(
                    f"no calibration (no CameraInfo/CameraCalibration topic paired with it; give "
                    f"--calibration {cam_name}=FILE or --topic {cam_name}.calibration=TOPIC)"
                )
            else:
                problem = prepared_scan.first_problem.get(calib_topic, "no valid message")
                why.append(f"no usable calibration on {calib_topic} ({problem}; give --calibration {cam_name}=FILE)")
        elif cam is not None and cam.camera is None and cam.calibration_problem:
            why.append(cam.calibration_problem)
        frame_id = info.frame_id
        if cam_name not in replay.sync.side_extrinsics:
            connected = replay.sync.tf.links(replay.sync.body_frame, frame_id or camera_frame(cam_name)) is not None
            T_body, T_world, reason = replay.sync.extrinsic(cam_name, frame_id, None)
            if not connected and T_body is None and T_world is None:
                why.append(reason)
        if why:
            causes.append(f"camera {cam_name} ({topic}): " + "; ".join(why))
        else:
            usable.append(cam_name)
    return usable, causes


def prepare(
    recording_path,
    settings: RunSettings,
    topics: dict[str, str] | None = None,
    roles_file: Path | None = None,
    side: SideInputs | None = None,
) -> Prepared:
    """Open and scan the recording, resolve its role map, build the replay and fill its sync
    stage with every non-image message (first pass). Shared by ``run`` and ``inspect``."""
    recording = open_recording(recording_path)
    recording_scan = scan(recording, ReadReport())
    roles = resolve_roles(recording_scan, topics, roles_file)
    body_frame = settings.body_frame if settings.body_frame != "auto" else recording.default_body_frame(
        recording_scan.tf_frames
    )
    time_source = recording.time_source(settings.time_source)
    side = side or SideInputs()
    for option, names in (("--calibration", side.calibrations), ("--extrinsic", side.extrinsics)):
        unknown = sorted(set(names) - set(roles.cameras()))
        if unknown and roles.cameras():
            raise InputError(
                f"{option} {unknown[0]}=...: the recording has no camera {unknown[0]!r}; its cameras: "
                f"{', '.join(roles.cameras())} (`agvviz inspect` shows the role map)"
            )
    replay = Replay(settings, body_frame=body_frame)
    replay.camera_frames = {
        cam: recording_scan.topics[roles.roles[image_role(cam)]].frame_id for cam in roles.cameras()
    }
    replay.set_side_inputs(
        side.marker_map, side.calibrations, {cam: tf.T_parent_child for cam, tf in side.extrinsics.items()}
    )
    replay.prime(iter_role_messages(recording, roles, time_source, ReadReport(), images=False,
                                    raw=recording_scan.context))
    usable, causes = _camera_causes(recording_scan, roles, replay)
    if not roles.cameras() and ROLE_CORNERS not in roles.roles and ROLE_UWB_RANGE not in roles.roles:
        image_topics = [t for t, i in recording_scan.topics.items() if i.schema_name in IMAGE_TYPES]
        if image_topics:
            causes = [f"no camera images placed: {t}: {roles.unplaced.get(t, 'not placed')}" for t in image_topics]
        else:
            kinds = sorted({i.schema_name or "(no schema)" for i in recording_scan.topics.values()})
            causes = [
                f"no camera images: {recording.path.name} has no image topic (CompressedImage, Image, "
                f"RawImage); its {len(recording_scan.topics)} topic(s) carry {', '.join(kinds[:8]) or 'nothing'}"
                + (" …" if len(kinds) > 8 else "")
            ]
    return Prepared(recording, recording_scan, roles, body_frame, time_source, replay, causes, usable)


class NoUsableFrameError(RunError):
    """A recording with no camera image, or none of whose frames can be used; ``causes`` holds
    one line per cause (the message joins them)."""

    def __init__(self, message: str, causes: list[str]):
        super().__init__(message)
        self.causes = list(causes)


def _unusable_run_error(recording: Recording, rejections: dict[str, list], causes: list[str]) -> RunError:
    """The error of a run whose frames could none be used: one line per cause
    (``rejections``: reason → [count, first detail])."""
    lines = list(causes)
    for reason, (count, detail) in rejections.items():
        lines.append(f"{count} frame(s) rejected as {reason}" + (f" (first: {detail})" if detail else ""))
    lines = list(dict.fromkeys(lines))
    return NoUsableFrameError(
        f"no frame of {recording.path.name} could be used; no .rrd written: " + "; ".join(lines), lines
    )


@dataclass
class DetectionPlan:
    """The detect stage of one run: its feed (pool or cache) and where its output is stored."""

    feed: DetectionFeed
    cache_path: Path | None
    from_cache: bool
    problems: list[str] = field(default_factory=list)

    def store(self, read_report: ReadReport) -> None:
        """Store a complete, undamaged detection pass in the cache (a failure to write it is a
        warning: the run itself is fine)."""
        if self.from_cache or self.cache_path is None or read_report.problems or not self.feed.frames:
            return
        try:
            detect_cache.save(self.cache_path, self.feed.frames)
        except (OSError, OutputError) as exc:
            self.problems.append(f"the detection cache was not stored ({exc}); runs will detect again")

    def summary(self) -> dict:
        """What the detect stage did (the same whether detected now or read from the cache)."""
        params = self.feed.params
        return {
            "tracking": params.tracks,
            "keyframe_every": params.keyframe_every,
            "keyframes": self.feed.keyframes,
            "tracked_frames": self.feed.tracked_frames,
        }

    def timing(self) -> dict:
        """Not stored in the ``.rrd``: where detections came from and on how many workers."""
        return {
            "detection_source": "cache" if self.from_cache else "detected",
            "detect_workers": 0 if self.from_cache else self.feed.jobs,
        }

    def warnings(self) -> list[str]:
        return list(self.problems) + ([self.feed.cache_mismatch] if self.feed.cache_mismatch else [])


def _detection_inputs(prepared: "Prepared", side: SideInputs | None) -> dict:
    """Everything besides the recording's bytes and the detect parameters that decides which
    frames are detected with which calibration (the cache key's inputs)."""
    side = side or SideInputs()
    calibrations = {}
    for cam, calib in sorted(side.calibrations.items()):
        c = calib.camera
        calibrations[cam] = [c.width_px, c.height_px, np.asarray(c.K, float).tolist(), np.asarray(c.dist, float).tolist()]
    return {
        "images": {cam: prepared.roles.roles[image_role(cam)] for cam in prepared.roles.cameras()},
        "calibration_roles": {
            cam: prepared.roles.roles.get(calibration_role(cam)) for cam in prepared.roles.cameras()
        },
        "time_source": prepared.time_source,
        "side_calibrations": calibrations,
        # Tracking predicts codes from odometry through the camera's extrinsic:
        "odometry": prepared.roles.roles.get(ROLE_ODOMETRY),
        "body_frame": prepared.body_frame,
        "side_extrinsics": {
            cam: np.asarray(tf.T_parent_child, float).round(12).tolist() for cam, tf in sorted(side.extrinsics.items())
        },
    }


def _detection_feed(
    prepared: "Prepared", recording_sha256: str, side: SideInputs | None, jobs: int | None,
    cache_dir: Path | None | bool,
) -> DetectionPlan:
    params = prepared.replay.detect_params
    cache_path = None
    cached = None
    if cache_dir is not False:
        folder = Path(cache_dir) if cache_dir not in (None, True) else detect_cache.default_cache_dir()
        cache_path = detect_cache.entry_path(
            folder, recording_sha256, detect_cache.cache_key(params, _detection_inputs(prepared, side))
        )
        cached = detect_cache.load(cache_path)
    # Worker processes take a while to start: not worth it for a few segments of work.
    frames = sum(prepared.scan.topics[prepared.roles.roles[image_role(c)]].count for c in prepared.roles.cameras())
    workers = min(jobs or default_jobs(), max(1, frames // (2 * params.segment_frames)))
    feed = DetectionFeed(
        params, prepared.replay.detect_job, jobs=workers, cached=cached,
        keep=cache_path is not None and cached is None,
    )
    return DetectionPlan(feed, cache_path, cached is not None)


def _run_trials(
    prepared: Prepared, settings: RunSettings, out_path: Path, inputs: list[Path], manifest: dict,
    recording_id: str, progress: Callable[[int], None] | None, on_total: Callable[[int], None] | None,
    study: str = "monte_carlo",
) -> RunOutcome:
    """Run a study recording: a Monte-Carlo study (``study="monte_carlo"``,
    :func:`agvviz.replay.studies.monte_carlo.is_trials_recording`; every trial solved by every study solver)
    or a CNOEM grid study (``study="cnoem"``, :func:`agvviz.replay.studies.cnoem.is_cnoem_trials_recording`;
    every cycle solved by every study method); the error series and report logged beside the
    manifest and summary. ``progress(trials_done)`` as trials are solved, ``on_total(trials)`` once."""
    from agvviz.replay.studies.cnoem import replay_cnoem_trials
    from agvviz.replay.studies.monte_carlo import replay_trials, trials_timing
    from agvviz.viz.trials_logger import cnoem_trials_blueprint, log_cnoem_trials, log_trials, trials_blueprint

    replay_study, log_study, study_blueprint, trial_role = {  # trial_role: one message per trial
        "monte_carlo": (replay_trials, log_trials, trials_blueprint, ROLE_CORNERS),
        "cnoem": (replay_cnoem_trials, log_cnoem_trials, cnoem_trials_blueprint, ROLE_MARKER_MAP),
    }[study]
    if on_total is not None and trial_role in prepared.roles.roles:
        on_total(prepared.scan.topics[prepared.roles.roles[trial_role]].count)
    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    t_start = time.perf_counter()
    with RunLogger(out_path, recording_name=manifest["recording_name"], recording_id=recording_id, inputs=inputs) as logger:
        logger.log_manifest(manifest)
        messages = iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, read_report)
        trials = replay_study(messages, settings, progress=progress)
        log_study(logger.stream, trials)
        summary = {
            **trials.summary,
            "recording_damage": list(read_report.problems),
            "warnings": run_warnings(list(trials.warnings), read_report),
        }
        logger.blueprint = study_blueprint(trials)
        logger.log_summary(summary)
    return RunOutcome(
        out_path=out_path, summary=summary, manifest=manifest, read_report=read_report,
        timing=trials_timing(trials, time.perf_counter() - t_start),
    )


def recording_start_ns(prepared: Prepared) -> int | None:
    """The first stamp of the messages a run replays — the origin of its ``elapsed`` timeline —
    when the run uses log times; ``None`` (the first frame's stamp) with header stamps, which
    the scan does not see."""
    if prepared.time_source != "log":
        return None
    firsts = [prepared.scan.first_ns[t] for t in prepared.roles.role_of() if t in prepared.scan.first_ns]
    return min(firsts) if firsts else None


def run_recording(
    recording_path: Path,
    settings: RunSettings,
    out_path: Path | None = None,
    progress: Callable[[int], None] | None = None,
    *,
    topics: dict[str, str] | None = None,
    roles_file: Path | None = None,
    side: SideInputs | None = None,
    on_total: Callable[[int], None] | None = None,
    jobs: int | None = None,
    cache_dir: Path | None | bool = None,
    error_budget=None,
) -> RunOutcome:
    """Replay ``recording_path`` (an ``.mcap`` or a rosbag2 directory) under ``settings``
    and write the run to ``out_path``.

    ``topics`` (role → topic, ``--topic``) and ``roles_file`` (``--roles``) override the
    inferred role map; ``side`` holds side-file values. ``progress(frames_done)`` is called
    after every frame, ``on_total(frames)`` once the number of frames is known. Returns the
    run summary and manifest (both also stored in the ``.rrd``) and the wall-clock timing
    (not stored). Raises :class:`RunError` — and writes nothing — when the recording has no
    camera image or none of its frames can be used, one line per cause.

    ``jobs`` detection worker processes (default: one per CPU; 1 = detect in this process);
    ``cache_dir`` the detection cache folder (None: :func:`agvviz.replay.detect.cache.default_cache_dir`,
    False: no cache). Neither changes the run's results.

    ``error_budget`` (an :class:`agvviz.evaluation.error_budget.ErrorBudget` of this recording
    under these settings, from :func:`agvviz.evaluation.error_budget.error_budget`) goes into
    the run: ``summary["error_budget"]`` and the budget's table, bar chart and per-frame series
    in the ``.rrd`` (:mod:`agvviz.viz.budget_logger`), with a layout that shows them.
    """
    recording_path = require_recording_path(recording_path)
    if out_path is not None and Path(out_path).suffix != ".rrd":
        raise RunError(f"output must be a .rrd file, got {out_path}")
    # OutputError when out_path is the recording (also through a link; for a bag directory,
    # any of its files) or cannot be written.
    from agvviz.recording import outputs

    inputs = [recording_path] + (sorted(recording_path.iterdir()) if recording_path.is_dir() else [])
    if out_path is not None:
        out_path = Path(out_path)
        outputs.prepare_output(out_path, inputs=inputs)
    prepared = prepare(recording_path, settings, topics, roles_file, side)
    recording, roles, replay = prepared.recording, prepared.roles, prepared.replay
    if not prepared.can_run:
        raise _unusable_run_error(recording, {}, prepared.causes)
    from agvviz.replay.studies.cnoem import is_cnoem_trials_recording
    from agvviz.replay.studies.monte_carlo import is_trials_recording  # (scipy.stats: only when needed)

    # A study recording goes to its trials stage, not the camera or correction replay.
    study = (
        "monte_carlo" if is_trials_recording(recording.scenario, roles)
        else "cnoem" if is_cnoem_trials_recording(recording.scenario, roles)
        else None
    )
    if study is None and roles.cameras():
        # frames of a marker family the run cannot use (no map, or another map's family): one
        # line naming the family and what to run next, before any work (issue 23)
        from agvviz.replay.detect.family_scan import family_check

        family_check(prepared, str(recording_path))
    corners_only = not roles.cameras() and ROLE_CORNERS in roles.roles and ROLE_UWB_RANGE not in roles.roles
    if corners_only and settings.correction == "none" and study is None:
        raise InputError(
            f"{recording.path.name} holds corner observations and no camera images: only the multi-frame "
            "correction replays them; give --set correction=cnoem (or correction=bundle)"
        )
    # Settings the recording has no data for (or that the other settings switch off) are reset
    # and kept out of the run's name; the manifest names them (settings.inapplicable).
    ignored = {} if study is not None else inapplicable(
        settings, has_uwb=ROLE_UWB_RANGE in roles.roles, has_odometry=ROLE_ODOMETRY in roles.roles,
        n_cameras=len(roles.cameras()),
    )
    ignored_settings = {name: {"value": getattr(settings, name), "reason": why} for name, why in ignored.items()}
    settings = without(settings, ignored)
    if out_path is None:
        out_path = default_run_path(recording_path, settings)
        outputs.prepare_output(out_path, inputs=inputs)
    if on_total is not None:
        on_total(max((prepared.scan.topics[roles.roles[image_role(c)]].count for c in roles.cameras()), default=0))

    recording_sha256 = recording.sha256()
    scenario = recording.scenario
    scenario_name = scenario["name"] if scenario else recording.name
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
        "ignored_settings": ignored_settings,
        "recording_name": recording_name,
        "roles": dict(sorted(roles.roles.items())),
        "unplaced_topics": dict(sorted(roles.unplaced.items())),
        "body_frame": prepared.body_frame,
        "time_source": prepared.time_source,
        "side_files": (side or SideInputs()).describe(),
    }

    if study is not None:  # a Monte-Carlo or CNOEM grid study: its trials stage
        return _run_trials(prepared, settings, out_path, inputs, manifest, recording_id, progress, on_total, study)

    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    detection = _detection_feed(prepared, recording_sha256, side, jobs, cache_dir)
    with RunLogger(
        out_path, recording_name=recording_name, recording_id=recording_id, inputs=inputs,
        recording_start_ns=recording_start_ns(prepared), max_reproj_px=settings.max_reproj_px,
    ) as logger:
        logger.log_manifest(manifest)
        if replay.ctx.marker_map is not None:
            logger.log_world_static(_markers_from_map(replay.ctx.marker_map))
        sinks = RunSinks(logger, settings, replay.ctx.cameras, progress)
        graph = ReplayGraph.compose(settings, detection.feed, replay, sinks)
        t_start = time.perf_counter()
        graph.run(iter_role_messages(recording, roles, prepared.time_source, read_report))
        wall_time_s = time.perf_counter() - t_start
        scores = sinks.scores
        has_uwb = graph.fuse.has_uwb
        correction_only = graph.correct is not None and not scores  # corner observations, no frame
        if not scores and not correction_only and not has_uwb:
            lines = prepared.causes + read_report.problems[-5:] or ["the image topics hold no decodable frame"]
            raise NoUsableFrameError(
                f"no camera frame of {recording.path.name} could be read; no .rrd written: " + "; ".join(lines), lines
            )
        if scores and all(s.rejected in UNUSABLE_REJECTIONS for s in scores):
            raise _unusable_run_error(recording, sinks.rejections, prepared.causes)
        summary = sinks.summary(has_uwb)
        summary["recording_damage"] = list(read_report.problems)
        detection.store(read_report)
        summary["detection"] = detection.summary()
        summary["warnings"] = run_warnings(replay.warnings() + prepared.causes + detection.warnings(), read_report)
        summary["truth"] = replay.truth_status()
        if error_budget is not None:
            summary["error_budget"] = error_budget.summary()
            logger.log_error_budget(error_budget)
        logger.log_summary(summary)
    return RunOutcome(
        out_path=out_path,
        summary=summary,
        manifest=manifest,
        read_report=read_report,
        timing={**timing(scores, wall_time_s), **detection.timing()},
    )


def replay_frames(
    recording_path: Path,
    settings: RunSettings,
    *,
    topics: dict[str, str] | None = None,
    roles_file: Path | None = None,
    side: SideInputs | None = None,
) -> Iterator[FrameResult]:
    """The solve stage's result of every camera frame of ``recording_path`` under ``settings``,
    in recording order, detected in this process and written nowhere (no ``.rrd``, no cache):
    what benches and tests compare frame by frame. Raises like :func:`prepare`."""
    prepared = prepare(require_recording_path(recording_path), settings, topics, roles_file, side)
    report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    for message in iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, report):
        result = prepared.replay.feed(message)
        if result is not None:
            yield result


def detect_recording(
    recording_path: Path,
    settings: RunSettings,
    *,
    topics: dict[str, str] | None = None,
    roles_file: Path | None = None,
    side: SideInputs | None = None,
    jobs: int | None = None,
    cache_dir: Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Run the detect stage over ``recording_path`` and store its output in the detection
    cache (``cache_dir``, default :func:`agvviz.replay.detect.cache.default_cache_dir`), so that
    every later run whose detection settings are equal
    (:func:`agvviz.replay.detect.stage.detection_settings`) only solves. A no-op when the cache holds
    them already. Returns ``{"source": "cache" | "detected", "frames": n, "cache": path}``;
    raises like :func:`run_recording` on a recording it cannot read."""
    recording_path = require_recording_path(recording_path)
    prepared = prepare(recording_path, settings, topics, roles_file, side)
    if not prepared.can_run:
        raise _unusable_run_error(prepared.recording, {}, prepared.causes)
    plan = _detection_feed(prepared, prepared.recording.sha256(), side, jobs, cache_dir if cache_dir is not None else None)
    if plan.from_cache:
        return {"source": "cache", "frames": len(plan.feed.cached), "cache": str(plan.cache_path)}
    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    frames = 0
    with plan.feed as feed:
        stream = iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, read_report)
        for _, detections in feed.annotate(stream):
            if detections is not None:
                frames += 1
                if progress is not None:
                    progress(frames)
    plan.store(read_report)
    if plan.problems:
        raise OutputError(plan.problems[0])
    return {"source": "detected", "frames": frames, "cache": str(plan.cache_path)}
