"""The library run: prepare a recording, run the replay graph over it into given sinks, detect only.

:func:`prepare` opens and scans a recording, resolves its role map and fills the sync stage
(shared by ``run``, ``inspect`` and the audit); :func:`detection_plan` is the detect stage's
feed (worker pool or cache); :func:`run_graph` drives :class:`agvviz.replay.graph.ReplayGraph`
over the recording into the sinks it is given; :func:`replay_frames` (and :func:`replay_checked`,
with the run-level findings) and
:func:`detect_recording` are the solve-only and detect-only runs. The application run (the
manifest, the ``.rrd`` and its sinks, the summary) is :func:`agvviz.app.run.run_recording`.
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from agvviz.conventions import camera_frame
from agvviz.errors import InputError, OutputError, RunError
from agvviz.model.frames import REJECT_NO_CALIBRATION, REJECT_NO_EXTRINSIC, FrameResult
from agvviz.model.suspects import RunFinding
from agvviz.model.frames import REJECT_CALIBRATION_SIZE, REJECT_IMAGE, REJECT_TIME
from agvviz.recording.mcap_records import DATA_SECTION_CRC_PROBLEM
from agvviz.model.messages import CalibrationMsg, FrameTransformMsg, RecordedMessage
from agvviz.recording.reader import ReadReport
from agvviz.recording import scan_cache
from agvviz.recording.roles import IMAGE_TYPES, RoleMap
from agvviz.recording.source import (
    Recording,
    Scan,
    iter_role_messages,
    open_recording,
    require_recording_path,
    resolve_roles,
)
from agvviz.model.topics import ROLE_CORNERS, ROLE_ODOMETRY, ROLE_UWB_RANGE, calibration_role, image_role
from agvviz.replay.detect import cache as detect_cache
from agvviz.replay.detect.pool import DetectionFeed, default_jobs
from agvviz.replay.graph import Composition, GraphOutcome, ReplayGraph
from agvviz.replay.sinks import NullSink, Sink
from agvviz.replay.solve import Replay
from agvviz.settings import RunSettings


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
    cache_dir: Path | None | bool = False,
) -> Prepared:
    """Open and scan the recording, resolve its role map, build the replay and fill its sync
    stage with every non-image message (first pass). Shared by ``run`` and ``inspect``.
    ``cache_dir`` (as :func:`detection_plan`'s; default False: none) keeps the scan and sha256
    there (:mod:`agvviz.recording.scan_cache`): a second run of the same file reads it once."""
    recording = open_recording(recording_path)
    recording_scan = scan_cache.cached_scan(recording, scan_cache.cache_folder(cache_dir))
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


def unusable_run_error(recording: Recording, rejections: dict[str, list], causes: list[str]) -> RunError:
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
    stored: bool = False

    def store(self, read_report: ReadReport, frames: list | None = None) -> bool:
        """Store a complete, undamaged detection pass (``frames``, default the feed's) in the
        cache, once (a failure to write it is a warning: the run itself is fine); whether it is
        stored."""
        frames = self.feed.frames if frames is None else frames
        if self.stored or self.from_cache or self.cache_path is None or read_report.problems or not frames:
            return self.stored
        try:
            detect_cache.save(self.cache_path, frames)
        except (OSError, OutputError) as exc:
            self.problems.append(f"the detection cache was not stored ({exc}); runs will detect again")
            return False
        self.stored = True
        return True

    def store_when_detected(self, read_report: ReadReport, then: Callable[[], None]) -> None:
        """Store the detections as soon as the last one is back, while the replay finishes,
        and then call ``then()`` (a sweep's lead: its group's other settings start from them).
        The file has been read to its end by then, so ``read_report`` is complete."""
        def complete(frames: list) -> None:
            if self.store(read_report, frames):
                then()

        self.feed.on_complete = complete

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


def detection_inputs(prepared: "Prepared", side: SideInputs | None) -> dict:
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


def detection_cache_path(
    prepared: "Prepared", recording_sha256: str, side: SideInputs | None, cache_dir: Path | None | bool,
) -> Path | None:
    """Where the detection cache keeps the detections of ``prepared`` (its recording's
    ``recording_sha256``, its detection settings and inputs); None without a cache
    (``cache_dir`` False)."""
    if cache_dir is False:
        return None
    key = detect_cache.cache_key(prepared.replay.detect_params, detection_inputs(prepared, side))
    return detect_cache.entry_path(scan_cache.cache_folder(cache_dir), recording_sha256, key)


def detection_plan(
    prepared: "Prepared", recording_sha256: str, side: SideInputs | None, jobs: int | None,
    cache_dir: Path | None | bool, executor: Executor | None = None,
) -> DetectionPlan:
    """The detect stage of a run of ``prepared``: the cache entry of its recording
    (``recording_sha256``) and detection settings, read when it is there (``cache_dir``: None
    the default folder, False no cache), else a worker pool of at most ``jobs`` processes, or
    ``executor``, a process pool of the caller's (``jobs``: its processes; see
    :class:`DetectionFeed`)."""
    params = prepared.replay.detect_params
    cache_path = detection_cache_path(prepared, recording_sha256, side, cache_dir)
    cached = detect_cache.load(cache_path) if cache_path is not None else None
    # Worker processes take a while to start: not worth it for a few segments of work.
    frames = sum(prepared.scan.topics[prepared.roles.roles[image_role(c)]].count for c in prepared.roles.cameras())
    workers = min(jobs or default_jobs(), max(1, frames // (2 * params.segment_frames)))
    feed = DetectionFeed(
        params, prepared.replay.detect_job, jobs=workers, cached=cached,
        keep=cache_path is not None and cached is None, executor=executor,
    )
    return DetectionPlan(feed, cache_path, cached is not None)


def run_graph(
    prepared: Prepared,
    settings: RunSettings,
    sinks: Sink,
    read_report: ReadReport,
    *,
    composition: Composition | None = None,
    detection: DetectionPlan | None = None,
    progress: Callable[[int], None] | None = None,
    until: str = "correct",
    progress_role: str | None = None,
) -> GraphOutcome:
    """Run the graph over ``prepared`` (its messages read once more, in file order, problems
    into ``read_report``) into ``sinks``: the stages its ``composition``
    (:meth:`Composition.of`) and ``settings`` call for, up to ``until``; ``detection`` the
    detect stage's plan (None: the solve stage detects in process); ``progress`` a study's
    ``progress(trials_done)``, or with ``progress_role`` ``progress(messages_done)`` after each
    message of that role is through the graph (a corner-only correction run's unit)."""
    if composition is None:
        composition = Composition.of(prepared.recording, prepared.roles, studies=until == "correct")
    graph = ReplayGraph.compose(
        composition, settings, prepared.replay, sinks,
        detect=detection.feed if detection is not None else None, progress=progress, until=until,
    )
    messages = iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, read_report)
    if progress_role is not None and progress is not None:
        messages = _counted(messages, progress_role, progress)
    return graph.run(messages)


def _counted(messages: Iterable[RecordedMessage], role: str, progress: Callable[[int], None]) -> Iterator[RecordedMessage]:
    """``messages``, calling ``progress(n)`` once the n-th message of ``role`` is handled (when
    the graph asks for the next message, or the messages end)."""
    done = 0
    for message in messages:
        yield message
        if message.role == role:
            done += 1
            progress(done)


def recording_start_ns(prepared: Prepared) -> int | None:
    """The first stamp of the messages a run replays — the origin of its ``elapsed`` timeline —
    when the run uses log times; ``None`` (the first frame's stamp) with header stamps, which
    the scan does not see."""
    if prepared.time_source != "log":
        return None
    firsts = [prepared.scan.first_ns[t] for t in prepared.roles.role_of() if t in prepared.scan.first_ns]
    return min(firsts) if firsts else None


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
    graph, messages = _solve_graph(recording_path, settings, topics, roles_file, side)
    yield from graph.frames(messages)


def replay_checked(
    recording_path: Path,
    settings: RunSettings,
    *,
    topics: dict[str, str] | None = None,
    roles_file: Path | None = None,
    side: SideInputs | None = None,
) -> tuple[list[FrameResult], tuple[RunFinding, ...]]:
    """:func:`replay_frames` as a list, with the check stage's run-level findings
    (:class:`~agvviz.model.suspects.RunFinding`: a camera's stamp offset, covering frames of the
    list) — what benches and tests of the checks compare. Raises like :func:`prepare`."""
    graph, messages = _solve_graph(recording_path, settings, topics, roles_file, side)
    frames = list(graph.frames(messages))
    return frames, graph.run_findings()


def _solve_graph(recording_path: Path, settings: RunSettings, topics, roles_file, side):
    """The replay graph cut after solve (and the checks) for ``recording_path``, and the
    messages it replays (:func:`replay_frames`, :func:`replay_checked`)."""
    prepared = prepare(require_recording_path(recording_path), settings, topics, roles_file, side)
    report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    graph = ReplayGraph(prepared.replay, until="solve")
    return graph, iter_role_messages(prepared.recording, prepared.roles, prepared.time_source, report)


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
    raises like :func:`agvviz.app.run.run_recording` on a recording it cannot read."""
    recording_path = require_recording_path(recording_path)
    prepared = prepare(recording_path, settings, topics, roles_file, side)
    if not prepared.can_run:
        raise unusable_run_error(prepared.recording, {}, prepared.causes)
    if prepared.roles.cameras():
        # as `agvviz run` does before it detects: an entry in the cache means frames that
        # passed this check (agvviz.app.run skips the frame scan then)
        from agvviz.replay.detect.family_scan import family_check

        family_check(prepared, str(recording_path))
    plan = detection_plan(prepared, prepared.recording.sha256(), side, jobs, cache_dir if cache_dir is not None else None)
    if plan.from_cache:
        return {"source": "cache", "frames": len(plan.feed.cached), "cache": str(plan.cache_path)}
    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    count = _DetectedCount(progress)
    run_graph(prepared, settings, count, read_report, detection=plan, until="detect")
    plan.store(read_report)
    if plan.problems:
        raise OutputError(plan.problems[0])
    return {"source": "detected", "frames": count.frames, "cache": str(plan.cache_path)}


class _DetectedCount(NullSink):
    """The detect-only run's sink: counts the frames detected, ``progress(frames)`` per frame."""

    def __init__(self, progress: Callable[[int], None] | None):
        self.progress = progress
        self.frames = 0

    def detected(self, detections) -> None:
        self.frames += 1
        if self.progress is not None:
            self.progress(self.frames)


def recording_images(
    recording_path, roles: dict[str, str], time_source: str, cache_dir: Path | None | bool = False,
) -> Iterator[tuple[str, int, str, bytes]]:
    """``(camera, time_ns, image_format, bytes)`` of every camera image of a recording, in file
    order, as a run whose manifest has ``roles`` (role → topic) and ``time_source`` read them:
    the time is the replay clock's (the header stamp under ``time_source="header"``, else the
    log time); undecodable images are left out (the run rejected them too). For the frames of a
    layers-only run and of a sweep ``.rrd`` (:mod:`agvviz.viz.frames`). ``cache_dir`` (as
    :func:`prepare`'s): where a run kept the recording's scan, which says whether the file was
    found intact (then it is read without its CRC checks)."""
    from agvviz.model.messages import CompressedFrame
    from agvviz.model.topics import camera_of_role
    from agvviz.recording.formats import decode
    from agvviz.recording.raw import MessageDecodeError, RawMetadata

    recording = open_recording(recording_path)
    folder = scan_cache.cache_folder(cache_dir)
    if folder is not None:
        scan_cache.load(folder, recording)  # marks it verified when a run found it intact
    cam_of_topic = {}
    for role, topic in roles.items():
        cam = camera_of_role(role)
        if cam is not None and cam[1] == "image":
            cam_of_topic[topic] = cam[0]
    for item in recording.iter_raw(ReadReport(), set(cam_of_topic)):
        if isinstance(item, RawMetadata) or item.topic not in cam_of_topic:
            continue
        try:
            value = decode(item)
        except MessageDecodeError:
            continue
        if not isinstance(value, CompressedFrame):
            continue
        time_ns = item.log_time_ns
        if time_source == "header" and getattr(value, "stamp_ns", 0):
            time_ns = value.stamp_ns
        yield cam_of_topic[item.topic], int(time_ns), value.image_format, value.data
