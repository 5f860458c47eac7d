"""``agvviz run`` as a library call: replay a recording and write the run ``.rrd``.

:func:`run_recording` checks the output, prepares the recording (:func:`agvviz.replay.run.prepare`),
builds the manifest and the recording id, plans the detect stage and its cache, runs the replay
graph (:func:`agvviz.replay.run.run_graph`) into the run's sinks — the ``.rrd``
(:class:`agvviz.viz.run_sinks.RrdSink`, :class:`~agvviz.viz.run_sinks.StudyRrdSink`) and the statistics
(:class:`agvviz.evaluation.summary.RunStatistics`, which assembles the summary) — and turns a
run without a usable frame into one error. It returns values and prints nothing; the CLI prints
:meth:`RunOutcome.summary_rows`.
"""

from __future__ import annotations

import time
import uuid
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from agvviz import __version__
from agvviz.errors import InputError, RunError
from agvviz.evaluation.summary import RunStatistics, timing
from agvviz.recording.reader import ReadReport
from agvviz.recording.source import require_recording_path
from agvviz.model.topics import ROLE_CORNERS, ROLE_MARKER_MAP, image_role
from agvviz.replay.graph import STUDY_CNOEM, STUDY_MONTE_CARLO, Composition
from agvviz.replay.run import (
    UNUSABLE_REJECTIONS,
    NoUsableFrameError,
    Prepared,
    SideInputs,
    detection_cache_path,
    detection_plan,
    prepare,
    recording_start_ns,
    run_graph,
    run_warnings,
    unusable_run_error,
)
from agvviz.replay.sinks import FanOut
from agvviz.settings import RunSettings, as_dict, inapplicable, without
from agvviz.viz.run_process import rrd_writer

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
    #: The recording's first stamp (ns): the terminal gives suspect stretches' times from it.
    recording_start_ns: int | None = None

    def summary_rows(self) -> list[tuple[str, str]]:
        """The summary table ``agvviz run`` prints: (metric, value) rows of the summary and the
        timing; the summary's ``recording_damage`` and ``warnings`` are printed below it."""
        from agvviz.evaluation.summary_table import summary_rows

        return summary_rows(self.summary, self.timing)


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


def _run_study(
    prepared: Prepared, composition: Composition, settings: RunSettings, out_path: Path, inputs: list[Path],
    manifest: dict, recording_id: str, progress: Callable[[int], None] | None,
    on_total: Callable[[int], None] | None,
) -> RunOutcome:
    """Run a study recording: a Monte-Carlo study (every trial solved by every study solver)
    or a CNOEM grid study (every cycle solved by every study method); the error series and
    report logged beside the manifest and summary. ``progress(trials_done)`` as trials are
    solved, ``on_total(trials)`` once."""
    from agvviz.replay.studies.monte_carlo import trials_timing
    from agvviz.viz.run_logger import RunLogger
    from agvviz.viz.run_sinks import StudyRrdSink

    trial_role = {STUDY_MONTE_CARLO: ROLE_CORNERS, STUDY_CNOEM: ROLE_MARKER_MAP}[composition.study]  # one message per trial
    if on_total is not None and trial_role in prepared.roles.roles:
        on_total(prepared.scan.topics[prepared.roles.roles[trial_role]].count)
    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    t_start = time.perf_counter()
    with RunLogger(out_path, recording_name=manifest["recording_name"], recording_id=recording_id, inputs=inputs) as logger:
        logger.log_manifest(manifest)
        stats = RunStatistics(settings)
        sink = FanOut([StudyRrdSink(logger, composition.study), stats])
        run_graph(prepared, settings, sink, read_report, composition=composition, progress=progress)
        summary = stats.summary(
            recording_damage=read_report.problems,
            warnings=run_warnings(list(stats.study_outcome.warnings), read_report),
        )
        logger.log_summary(summary)
        sink.close()
    return RunOutcome(
        out_path=out_path, summary=summary, manifest=manifest, read_report=read_report,
        timing=trials_timing(stats.study_outcome, time.perf_counter() - t_start),
    )


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
    images: bool = True,
    writer_process: bool = True,
    executor: Executor | None = None,
    on_detected: Callable[[], None] | None = None,
    durable: bool = True,
    on_published: Callable[[], None] | None = None,
) -> RunOutcome:
    """Replay ``recording_path`` (an ``.mcap`` or a rosbag2 directory) under ``settings``
    and write the run to ``out_path``.

    ``topics`` (role → topic, ``--topic``) and ``roles_file`` (``--roles``) override the
    inferred role map; ``side`` holds side-file values. ``progress(done)`` is called after
    every unit of work — a frame; a corner-observation message in a corner-only correction run;
    a trial in a study — and ``on_total(units)`` once their number is known (not at all when it
    is not known in advance: a UWB-only run). Returns the
    run summary and manifest (both also stored in the ``.rrd``) and the wall-clock timing
    (not stored). Raises :class:`RunError` — and writes nothing — when the recording has no
    camera image or none of its frames can be used, one line per cause.

    ``jobs`` detection worker processes (default: one per CPU; 1 = detect in this process), or
    ``executor``, a process pool of the caller's of ``jobs`` processes to detect on (a local
    sweep's, whose processes then solve its other settings); ``cache_dir`` the detection cache
    folder (None: :func:`agvviz.replay.detect.cache.default_cache_dir`, False: no cache). None
    of them changes the run's results. ``on_detected()`` is called once the run's detections
    are stored in the cache, as soon as the last one is back (a sweep's lead: the other
    settings start from them while it finishes); not when they came from the cache.

    ``error_budget`` (an :class:`agvviz.evaluation.error_budget.ErrorBudget` of this recording
    under these settings, from :func:`agvviz.app.budget.error_budget`) goes into
    the run: ``summary["error_budget"]`` and the budget's table, bar chart and per-frame series
    in the ``.rrd`` (:mod:`agvviz.viz.log_budget`), with a layout that shows them.

    ``images=False`` (``run --images none``) leaves the camera images out of the ``.rrd``: the
    layers only, for long logs (the manifest is a full run's: a sweep's layers equal a standalone
    run's); ``agvviz view`` adds the frames from the recording (:mod:`agvviz.viz.frames`).

    ``writer_process`` (default): the ``.rrd`` is written by a process of its own
    (:mod:`agvviz.viz.run_process`), beside the replay; False: in this process (a sweep's runs,
    which already keep every core busy). ``durable=False``: the ``.rrd`` is a scratch file the
    caller reads back and removes (a sweep's layers-only runs): it is not synced to the disk
    before it is moved into place (:class:`agvviz.viz.rrd_file.AtomicRrd`). ``on_published`` is
    called the moment the ``.rrd`` is in place (:func:`agvviz.recording.outputs.when_published`;
    the ``run`` command: a signal no longer interrupts it).
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
    prepared = prepare(recording_path, settings, topics, roles_file, side, cache_dir=cache_dir)
    recording, roles, replay = prepared.recording, prepared.roles, prepared.replay
    if not prepared.can_run:
        raise unusable_run_error(recording, {}, prepared.causes)
    # A study recording goes to its study stage, not the camera or correction replay.
    composition = Composition.of(recording, roles)
    study = composition.study
    if study is None and roles.cameras():
        # frames of a marker family the run cannot use (no map, or another map's family): one
        # line naming the family and what to run next, before any work (issue 23)
        from agvviz.replay.detect.family_scan import family_check

        # Frames with an entry in the detection cache (same recording content, detection
        # settings and marker family) passed this check when they were detected: their scan
        # (≈30 ms) is not made again, the marker map is checked still.
        entry = detection_cache_path(prepared, recording.sha256(), side, cache_dir)
        family_check(prepared, str(recording_path), frames_checked=entry is not None and entry.is_file())
    corners_only = not composition.cameras and composition.corners and not composition.uwb
    if corners_only and settings.correction == "none" and study is None:
        raise InputError(
            f"{recording.path.name} holds corner observations and no camera images: only the multi-frame "
            "correction replays them; give --set correction=cnoem (or correction=bundle)"
        )
    # Settings the recording has no data for (or that the other settings switch off) are reset
    # and kept out of the run's name; the manifest names them (settings.inapplicable).
    ignored = {} if study is not None else inapplicable(
        settings, has_uwb=composition.uwb, has_odometry=composition.odometry, n_cameras=len(composition.cameras),
    )
    ignored_settings = {name: {"value": getattr(settings, name), "reason": why} for name, why in ignored.items()}
    settings = without(settings, ignored)
    if out_path is None:
        out_path = default_run_path(recording_path, settings)
        outputs.prepare_output(out_path, inputs=inputs)
    if on_published is not None:
        outputs.when_published(out_path, on_published)
    # The progress unit: a camera run's frames (the busiest camera's image count), a corner-only
    # correction run's corner-observation messages; a run of neither (UWB alone) has no total
    # known in advance: its bar counts without one.
    progress_role = ROLE_CORNERS if corners_only and study is None else None
    if on_total is not None and study is None:
        if progress_role is not None:
            on_total(prepared.scan.topics[roles.roles[ROLE_CORNERS]].count)
        elif roles.cameras():
            on_total(max(prepared.scan.topics[roles.roles[image_role(c)]].count for c in roles.cameras()))

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

    if study is not None:  # a Monte-Carlo or CNOEM grid study: its study stage
        return _run_study(prepared, composition, settings, out_path, inputs, manifest, recording_id, progress, on_total)

    read_report = ReadReport(messages=0, chunks_ok=0, chunks_lost=0, problems=[])
    detection = detection_plan(prepared, recording_sha256, side, jobs, cache_dir, executor)
    if on_detected is not None:
        detection.store_when_detected(read_report, on_detected)
    # The .rrd is written by a process of its own (viz.run_process): this one solves meanwhile
    # (in this process when asked: a sweep's runs).
    with rrd_writer(
        out_path, settings, in_process=not writer_process,
        recording_name=recording_name, recording_id=recording_id, inputs=tuple(inputs),
        recording_start_ns=recording_start_ns(prepared), max_reproj_px=settings.max_reproj_px, images=images,
        durable=durable,
    ) as writer:
        logger = writer.logger
        logger.log_manifest(manifest)
        if replay.ctx.marker_map is not None:
            logger.log_world_static(_markers_from_map(replay.ctx.marker_map))
        rrd = writer.sink
        stats = RunStatistics(settings, progress if progress_role is None else None)
        sinks = FanOut([rrd, stats])
        t_start = time.perf_counter()
        graph = run_graph(prepared, settings, sinks, read_report, composition=composition, detection=detection,
                          progress=progress if progress_role is not None else None, progress_role=progress_role)
        wall_time_s = time.perf_counter() - t_start
        scores = stats.scores
        correction_only = graph.corrected and not scores  # corner observations, no frame
        if not scores and not correction_only and not graph.has_uwb:
            lines = prepared.causes + read_report.problems[-5:] or ["the image topics hold no decodable frame"]
            raise NoUsableFrameError(
                f"no camera frame of {recording.path.name} could be read; no .rrd written: " + "; ".join(lines), lines
            )
        if scores and all(s.rejected in UNUSABLE_REJECTIONS for s in scores):
            raise unusable_run_error(recording, stats.rejections, prepared.causes)
        detection.store(read_report)
        summary = stats.summary(
            recording_damage=read_report.problems,
            detection=detection.summary(),
            warnings=run_warnings(replay.warnings() + prepared.causes + detection.warnings(), read_report),
            truth=replay.truth_status(),
            error_budget=error_budget.summary() if error_budget is not None else None,
        )
        if error_budget is not None:
            logger.log_error_budget(error_budget)
        logger.log_summary(summary)
        sinks.close()
    return RunOutcome(
        out_path=out_path,
        summary=summary,
        manifest=manifest,
        read_report=read_report,
        timing={**timing(scores, wall_time_s), **detection.timing()},
        recording_start_ns=writer.recording_start_ns,
    )


# -- CI gates: run --fail-if and --junit-xml ---------------------------------------------------
def check_gates(conditions, junit_path: Path | None = None, inputs=()) -> None:
    """Refuse, before any work, a ``run --fail-if`` condition that does not parse (an unknown
    metric lists the known ones) and a ``--junit-xml`` path that cannot be written or is an
    input (:class:`~agvviz.errors.InputError`, :class:`~agvviz.errors.OutputError`)."""
    from agvviz.evaluation import gates
    from agvviz.recording import outputs

    gates.parse_conditions(list(conditions), gates.run_metric_names(), runs=())
    if junit_path is not None:
        outputs.prepare_output(junit_path, inputs=inputs, option="--junit-xml")


def gate_run(outcome: RunOutcome, conditions, junit_path: Path | None = None, inputs=()) -> list:
    """``agvviz run --fail-if``: each condition over the run's summary
    (:func:`agvviz.evaluation.gates.run_gates`), and the verdicts as JUnit XML at ``junit_path``
    (written atomically; its ``system-out`` lists the suspect stretches). Returns the
    :class:`~agvviz.evaluation.gates.Gate` of each condition; the caller exits 1 when one holds."""
    from agvviz.evaluation import gates, suspect_report

    verdicts = gates.run_gates(list(conditions), outcome.summary)
    if junit_path is not None:
        details = suspect_report.stretch_lines(outcome.summary, outcome.recording_start_ns)
        write_junit(
            junit_path, "run", f"agvviz run {outcome.manifest.get('recording_name', '')}".strip(), verdicts,
            properties={"rrd": str(outcome.out_path), "recording": str(outcome.manifest.get("recording", "")),
                        "recording_sha256": str(outcome.manifest.get("recording_sha256", ""))},
            details=("suspect stretches:\n" + "\n".join(details)) if details else "",
            inputs=inputs,
        )
    return verdicts


def write_junit(path: Path, command: str, suite: str, verdicts: list, *, properties: dict | None = None,
                details: str = "", inputs=()) -> Path:
    """The verdicts of ``--fail-if`` gates as JUnit XML at ``path`` (atomic: a complete file or
    none; never over an input)."""
    from agvviz.evaluation.junit import junit_xml
    from agvviz.recording import outputs

    return outputs.atomic_write_text(
        path, junit_xml(command, suite, verdicts, properties=properties, details=details), inputs=inputs
    )


# -- the frames of a layers-only run (run --images none), for agvviz view ------------------------
def layers_only_frames(run_file: Path, recording: Path | None, out_dir: Path) -> Path | None:
    """For a run written with ``--images none``: its recording's camera frames as an ``.rrd`` in
    ``out_dir`` under the run's recording id, so a viewer given both files shows the complete
    run (:mod:`agvviz.viz.frames`); None for a run that holds its images.

    ``recording`` defaults to the manifest's file name looked up beside the run, in the current
    folder and in ``recordings/``. :class:`~agvviz.errors.InputError` (one line) when it is not
    found or holds none of the run's frames (another recording)."""
    from agvviz.app import run_series
    from agvviz.replay.run import recording_images
    from agvviz.viz import paths
    from agvviz.viz.frames import write_frames_rrd
    from agvviz.viz.readback import document_json, read_rrd, recording_id_of

    contents = read_rrd(run_file)
    if paths.RUN_MANIFEST not in contents.entity_paths:
        return None
    manifest = document_json(contents, paths.RUN_MANIFEST)
    # Layers only: a camera whose images the recording has (an image role) but the run does not.
    from agvviz.model.topics import camera_of_role

    recorded = {cam[0] for role in manifest.get("roles", {}) if (cam := camera_of_role(role)) and cam[1] == "image"}
    if not recorded & set(run_series.cameras_of(contents)) or paths.camera_images(contents.entity_paths):
        return None
    name = str(manifest.get("recording", ""))
    if recording is None:
        candidates = [Path(run_file).parent / name, Path.cwd() / name, Path("recordings") / name]
        recording = next((c for c in candidates if name and c.exists()), None)
        if recording is None:
            raise InputError(f"{run_file} holds the layers only (run --images none); its recording {name!r} is not "
                             f"beside it, here or in recordings/: give it with --recording")
    recording = require_recording_path(recording)
    fixed = run_series.fixed_cameras_of(contents)
    path, logged, _ = write_frames_rrd(
        Path(out_dir) / f"{Path(run_file).stem}.frames.rrd",
        recording_id=recording_id_of(run_file), recording_name=str(manifest.get("recording_name", name)),
        images=recording_images(recording, manifest.get("roles", {}), manifest.get("time_source", "log")),
        clocks=run_series.image_clocks(contents),
        entity_of={cam: paths.image(cam, cam in fixed) for cam in run_series.cameras_of(contents)},
        inputs=(run_file, recording),
    )
    if logged == 0:
        path.unlink(missing_ok=True)
        raise InputError(f"{recording} holds none of the frames of {run_file}: it is not the recording the run "
                         f"was made from ({name})")
    return path
