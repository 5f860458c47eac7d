"""The replay graph: every run's stages, composed from what the recording holds, driven over its messages.

    source ──► sync ──► detect ──► solve ──► checks ──► fuse ──► correct ──► sinks
    (readers,  (calibration,  (corners,   (pose and   (suspects:  (camera fixes  (multi-frame   (.rrd, statistics,
     roles)     transforms,    ids,        its         no truth)   + UWB)         windows)       summary, audit)
                truth)         payloads)   diagnostics)
          └──► study (a Monte-Carlo or CNOEM grid study's trials) ──────────────────► sinks

* source — :mod:`agvviz.recording.source` (readers, role map) opened by :func:`agvviz.replay.run.prepare`;
* sync — :class:`agvviz.replay.sync.SyncState`, filled by a first pass over the non-image messages;
* detect — :mod:`agvviz.replay.detect.stage` (frame → :class:`~agvviz.model.detections.FrameDetections`),
  computed ahead by :class:`agvviz.replay.detect.pool.DetectionFeed` or read from the cache;
* solve — :class:`agvviz.replay.solve.Replay` (detections → :class:`~agvviz.model.frames.FrameResult`);
* checks — :class:`agvviz.replay.checks.CheckStage` (sets ``FrameResult.suspect`` before the frame
  reaches the sinks; ``checks=off`` leaves it out; it is handed the fuse stage's UWB fixes); at the
  end its run-level findings (a camera's stamp offset) go to the sinks in ``GraphOutcome.findings``;
* fuse — :class:`agvviz.replay.fuse.FusionReplay`;
* correct — :class:`agvviz.replay.correct.CorrectionReplay`;
* study — :func:`agvviz.replay.studies.monte_carlo.replay_trials` or
  :func:`agvviz.replay.studies.cnoem.replay_cnoem_trials`;
* sinks — anything that follows :class:`agvviz.replay.sinks.Sink` (the ``.rrd`` logger, the
  statistics, the audit's collector, a detect-only count).

**Composition** (:class:`Composition`, from the role map and the recording's messages, never
from a scenario's name): corner observations that carry a study cell (``"cell"`` in the first
``corners`` message) make a study — a CNOEM grid study when the recording has navigation
(``odometry``) to place its cycles, a Monte-Carlo study otherwise — and the study stage alone
runs; otherwise camera images give detect and solve, every camera run has fuse (which turns
UWB ranges into fixes when the recording has anchors and ranges), and correction windows
(``correction`` not ``none``) add correct. ``until`` cuts the graph after a stage: the audit
needs detect and solve, ``agvviz sweep``'s first pass detect only.

Messages flow in file order; every stage sees every message (a stage ignores what is not its
own) plus what the stage before it made of it. Stages and sinks are handed values: a frozen
snapshot of the cameras whenever they change, a :class:`~agvviz.replay.sinks.UwbSetup` with
each fused item.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator, Mapping

from agvviz.errors import InputError
from agvviz.model.frames import REJECT_TIME
from agvviz.recording.reader import MessageDecodeError, RawMetadata, ReadReport, RecordedMessage, decode
from agvviz.recording.roles import RoleMap
from agvviz.recording.source import Recording
from agvviz.model.topics import ROLE_CORNERS, ROLE_ODOMETRY, ROLE_UWB_RANGE
from agvviz.model.fusion import UwbFixResult
from agvviz.replay.checks import check_stage
from agvviz.replay.correct import CorrectionReplay, CorrectionSettings
from agvviz.replay.detect.pool import DetectionFeed
from agvviz.replay.fuse import FusionReplay
from agvviz.replay.sinks import GraphOutcome, Sink, UwbSetup
from agvviz.replay.solve import Replay
from agvviz.settings import RunSettings

#: How far a graph runs: ``detect`` (detect-only), ``solve`` (the audit), ``correct`` (a run).
UNTIL = ("detect", "solve", "correct")

STUDY_MONTE_CARLO = "monte_carlo"
STUDY_CNOEM = "cnoem"


@dataclass(frozen=True)
class Composition:
    """What a recording holds, as the graph's composition reads it (module docstring)."""

    cameras: tuple[str, ...]  # cameras with an image role
    corners: bool  # corner observations (role ``corners``)
    uwb: bool  # UWB ranges (role ``uwb.range``)
    odometry: bool
    study: str | None  # STUDY_MONTE_CARLO, STUDY_CNOEM or None

    @classmethod
    def of(cls, recording: Recording, roles: RoleMap, studies: bool = True) -> "Composition":
        """``studies=False``: no study looked for (a graph cut before correct never runs one)."""
        placed = roles.roles
        study = None
        if studies and ROLE_CORNERS in placed and _first_corners_is_study(recording, placed[ROLE_CORNERS]):
            study = STUDY_CNOEM if ROLE_ODOMETRY in placed else STUDY_MONTE_CARLO
        return cls(
            cameras=tuple(roles.cameras()), corners=ROLE_CORNERS in placed, uwb=ROLE_UWB_RANGE in placed,
            odometry=ROLE_ODOMETRY in placed, study=study,
        )

    def correction(self, settings: RunSettings) -> bool:
        """Whether the correct stage runs: asked for, on frames or corner observations."""
        return settings.correction != "none" and self.study is None


def _first_corners_is_study(recording: Recording, topic: str) -> bool:
    """Whether the recording's first corner-observation message is a study trial's (it names
    its ``cell``). Reads up to that message only."""
    items = recording.iter_raw(ReadReport(), {topic})
    try:
        for item in items:
            if isinstance(item, RawMetadata) or item.topic != topic:
                continue
            try:
                value = decode(item)
            except MessageDecodeError:  # the run's own pass reports it
                continue
            return isinstance(value, dict) and "cell" in value
        return False
    finally:
        close = getattr(items, "close", None)
        if close is not None:
            close()


class ReplayGraph:
    """The stages of one run, wired. Build it with :meth:`compose`, then :meth:`run` (push to
    the sinks) or :meth:`frames` (pull the solve stage's results)."""

    def __init__(
        self,
        solve: Replay,
        sinks: Sink | None = None,
        *,
        detect: DetectionFeed | None = None,
        fuse: FusionReplay | None = None,
        correct: CorrectionReplay | None = None,
        study: str | None = None,
        settings: RunSettings | None = None,
        progress=None,
        until: str = "correct",
    ):
        if until not in UNTIL:
            raise ValueError(f"until must be one of {UNTIL}, got {until!r}")
        self.solve = solve
        self.sinks = sinks
        self.detect = detect
        self.fuse = fuse
        self.correct = correct
        self.study = study
        self.settings = settings if settings is not None else solve.settings
        self.progress = progress  # a study's progress(trials_done)
        self.until = until
        self._cameras_version = -1
        #: the check stage (None with ``checks=off`` or a detect-only graph)
        self.checks = check_stage(self.settings, solve.sync, solve.ctx) if until != "detect" else None

    @classmethod
    def compose(
        cls,
        composition: Composition,
        settings: RunSettings,
        solve: Replay,
        sinks: Sink,
        *,
        detect: DetectionFeed | None = None,
        progress=None,
        until: str = "correct",
    ) -> "ReplayGraph":
        """The stages ``composition`` and ``settings`` call for, up to ``until``; ``detect`` the
        detect stage's feed (None: the solve stage detects in process); ``progress`` a study's
        ``progress(trials_done)``."""
        if composition.study is not None and until == "correct":
            if settings.truth == "ignore":
                raise InputError(
                    f"truth=ignore: a {composition.study} study scores every trial against the recording's "
                    "truth and has nothing to show without it; run it without --set truth=ignore"
                )
            return cls(solve, sinks, study=composition.study, settings=settings, progress=progress)
        fuse = correct = None
        if until == "correct":
            cameras = solve.ctx.cameras_snapshot()
            fuse = FusionReplay(settings, cameras, solve.sync)
            if composition.correction(settings):
                correct = CorrectionReplay(
                    CorrectionSettings(
                        solver=settings.correction, update=settings.cnoem_update,
                        cycle_distance_m=settings.cycle_distance_m, max_reproj_px=settings.max_reproj_px,
                    ),
                    cameras,
                    solve.sync,
                )
        return cls(solve, sinks, detect=detect, fuse=fuse, correct=correct, settings=settings, until=until)

    # -- driving --------------------------------------------------------------------------------
    def run(self, messages: Iterable[RecordedMessage]) -> GraphOutcome:
        """Drive every message through the stages, in file order, then flush them."""
        if self.study is not None:
            self.sinks.study(self._run_study(messages))
            return self._finished(GraphOutcome())
        if self.until == "detect":
            with self.detect as feed:
                for _, detections in feed.annotate(messages):
                    if detections is not None:
                        self.sinks.detected(detections)
            return self._finished(GraphOutcome())
        self._cameras_changed()
        for message, detections, frame in self._solved(messages):
            if frame is not None:
                self.sinks.solved(frame, detections)
            if self.until == "correct":
                self._step(message, frame)
            else:
                self._cameras_changed()
        if self.fuse is not None:
            uwb = self._uwb()
            for item in self.fuse.finish():
                self._uwb_fix(item)
                self.sinks.fused(item, uwb)
        if self.correct is not None:
            for step in self.correct.finish():
                self.sinks.corrected(step)
        return self._finished(GraphOutcome(
            has_uwb=self.fuse is not None and self.fuse.has_uwb, corrected=self.correct is not None,
            findings=self.run_findings(),
        ))

    def run_findings(self) -> tuple:
        """The check stage's findings about the whole run (:class:`~agvviz.model.suspects.RunFinding`),
        from the frames solved so far: :meth:`run` hands them to the sinks at the end; after
        :meth:`frames` is exhausted, ask here. Empty without the check stage."""
        return self.checks.run_findings() if self.checks is not None else ()

    def _finished(self, outcome: GraphOutcome) -> GraphOutcome:
        self.sinks.finished(outcome)
        return outcome

    def frames(self, messages: Iterable[RecordedMessage]) -> Iterator:
        """The solve stage's result of every camera frame of ``messages``, in order (no sinks)."""
        for _, _, frame in self._solved(messages):
            if frame is not None:
                yield frame

    def _solved(self, messages: Iterable[RecordedMessage]):
        """(message, its detections, the solve stage's frame or None) for every message."""
        if self.detect is None:
            for message in messages:
                yield message, None, self._checked(self.solve.feed(message))
            return
        with self.detect as feed:
            for message, detections in feed.annotate(messages):
                yield message, detections, self._checked(self.solve.feed(message, detections))

    def _checked(self, frame):
        """The check stage's verdict on a solve-stage frame (the frame itself without checks)."""
        if frame is None or self.checks is None:
            return frame
        return self.checks.check(frame)

    def _uwb_fix(self, item) -> None:
        """A UWB fix of the fuse stage, handed to the check stage (camera against UWB)."""
        if self.checks is not None and isinstance(item, UwbFixResult):
            fix = item.fix
            self.checks.uwb_fix(fix.log_time_ns, fix.position_m, getattr(fix, "covariance_m2", None))

    def _run_study(self, messages: Iterable[RecordedMessage]):
        from agvviz.replay.studies.cnoem import replay_cnoem_trials
        from agvviz.replay.studies.monte_carlo import replay_trials  # (scipy.stats: only when needed)

        replay_study = {STUDY_MONTE_CARLO: replay_trials, STUDY_CNOEM: replay_cnoem_trials}[self.study]
        return replay_study(messages, self.settings, progress=self.progress)

    def _cameras_changed(self) -> None:
        """Hand the stages after solve and the sinks a new snapshot when the cameras changed."""
        if self.solve.ctx.cameras_version == self._cameras_version:
            return
        self._cameras_version = self.solve.ctx.cameras_version
        cameras: Mapping = self.solve.ctx.cameras_snapshot()
        for stage in (self.fuse, self.correct):
            if stage is not None:
                stage.cameras = cameras
        self.sinks.cameras_changed(cameras)

    def _uwb(self) -> UwbSetup | None:
        fuse = self.fuse
        return UwbSetup(dict(fuse.anchors_m), fuse.tag_z_m) if fuse.has_uwb else None

    def _step(self, message: RecordedMessage, frame) -> None:
        if frame is not None and frame.rejected == REJECT_TIME:
            # A frame that cannot be placed in time (repeated or reversed time stamp) is logged
            # and counted on its own, never grouped with the frames of its time stamp.
            self.sinks.frame(frame)
            frame = None
        self._cameras_changed()
        items = self.fuse.feed(message, frame)
        if items:
            uwb = self._uwb()
            for item in items:
                self._uwb_fix(item)
                self.sinks.fused(item, uwb)
        if self.correct is not None:
            for step in self.correct.feed(message, frame):
                self.sinks.corrected(step)


def replay(messages: Iterable[RecordedMessage], settings: RunSettings) -> Iterator:
    """Per-frame results of replaying ``messages`` (in recording order) under ``settings``: a
    graph of the solve stage alone, fed without a first pass (each frame knows what came before
    it), detecting in this process."""
    return ReplayGraph(Replay(settings), until="solve").frames(messages)
