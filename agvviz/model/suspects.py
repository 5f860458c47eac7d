"""Suspect frames: a solved pose that disagrees with what else the log knows, checked without
truth (issue 25). Made by the check stage (:mod:`agvviz.replay.checks`), shown by the run's
``.rrd`` (``events/suspects``, the solver panel, marks on the error plots), counted in the run
summary and listed by the terminal. Frozen.

A check compares one frame's pose with an independent witness and expresses the disagreement in
standard deviations (a Mahalanobis distance with both sides' covariances, or the χ² of a test
turned into its equivalent normal σ). The frame is a suspect when the worst check exceeds its
limit; the suspect names the check, the size of the disagreement, the likely cause in plain
words, the evidence, and the next step a user can take.

Some faults are a property of the whole log, not of a frame: a camera's stamps offset from the
odometry by a constant is seen only where the vehicle's twist changes, but it misplaces every
frame of that camera. The check stage states it at the end of the run as a :class:`RunFinding`
(the graph's outcome carries it) that covers every solved frame of the camera; the per-frame
suspects stay as they were.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The checks, in the order they are run (issue 25, "every frame checked against what the log knows").
CHECK_MOTION = "motion"  # pose step against the odometry step (or a constant-velocity model)
CHECK_MARKERS = "markers"  # each marker's own pose against the frame's joint pose
CHECK_AMBIGUITY = "ambiguity"  # IPPE ratio, and whether the mirror pose agrees better with the motion
CHECK_PAYLOAD = "payload"  # a code's payload against the marker map
CHECK_CAMERAS = "cameras"  # cameras of one rig against each other at one time stamp
CHECK_UWB = "uwb"  # camera fix against the UWB fix at one time stamp
CHECK_TIME = "time"  # image stamps against the camera's frame rate
CHECKS = (CHECK_MOTION, CHECK_MARKERS, CHECK_AMBIGUITY, CHECK_PAYLOAD, CHECK_CAMERAS, CHECK_UWB, CHECK_TIME)

#: Likely causes a suspect names (its ``cause``); a stretch groups consecutive suspects of one cause.
CAUSE_MAP_ENTRY = "map_entry"  # a marker's map entry is wrong (moved or turned)
CAUSE_PAYLOAD = "payload"  # a code's payload carries wrong coordinates
CAUSE_MIRROR_FLIP = "mirror_flip"  # planar ambiguity: the mirror pose was chosen
CAUSE_EXTRINSIC = "extrinsic"  # a camera's extrinsic (mount) is not what the recording says
CAUSE_TIME_OFFSET = "time_offset"  # a camera's stamps are offset from the others / the odometry
CAUSE_TIME_STAMPS = "time_stamps"  # stamps off the frame rate (dropped or duplicated frames)
CAUSE_UWB = "uwb"  # camera and UWB disagree (NLOS ranges or a camera problem)
CAUSE_UNKNOWN = "unknown"  # a check failed and no cause explains it better
CAUSES = (CAUSE_MAP_ENTRY, CAUSE_PAYLOAD, CAUSE_MIRROR_FLIP, CAUSE_EXTRINSIC, CAUSE_TIME_OFFSET,
          CAUSE_TIME_STAMPS, CAUSE_UWB, CAUSE_UNKNOWN)


@dataclass(frozen=True)
class CheckResult:
    """One check of one frame: ``sigma`` the disagreement in standard deviations (≥ 0),
    ``limit_sigma`` the check's limit, ``detail`` the numbers behind it in plain words
    (e.g. "pose step 2.21 m, odometry step 0.05 m")."""

    check: str  # one of CHECKS
    sigma: float
    limit_sigma: float
    detail: str = ""

    @property
    def failed(self) -> bool:
        return self.sigma > self.limit_sigma


@dataclass(frozen=True)
class Suspect:
    """A frame whose pose failed at least one check.

    ``checks`` every check that ran on the frame (failed or not); ``check`` and ``sigma`` the
    worst failure; ``cause`` one of :data:`CAUSES`; ``message`` the finding in plain words with
    its evidence (e.g. "code Q015 disagrees with Q024 by 2.2 m and with the odometry by 2.2 m:
    Q015's map entry is likely wrong"); ``next_step`` what to do (e.g. "`agvviz audit` can
    estimate where it is"); ``marker_id`` / ``cam_name`` what the cause names, when it names one.
    """

    frame_index: int
    log_time_ns: int
    cam_name: str
    check: str
    sigma: float
    cause: str
    message: str
    next_step: str = ""
    marker_id: str | None = None
    checks: tuple[CheckResult, ...] = ()


@dataclass(frozen=True)
class SuspectStretch:
    """Consecutive suspect frames (of one camera, no solved clean frame between them) with one
    cause: what the terminal lists and the plots mark."""

    first_frame: int
    last_frame: int
    first_time_ns: int
    last_time_ns: int
    n_frames: int
    cause: str
    message: str  # the first suspect's message (the stretch's evidence)
    next_step: str = ""
    cam_name: str = ""
    marker_id: str | None = None
    max_sigma: float = 0.0
    run_level: bool = False  # a run-level finding's stretch (:class:`RunFinding`): every frame of the camera


@dataclass(frozen=True)
class RunFinding:
    """A finding about the whole run, made at its end from every frame (e.g. a camera's stamps
    lag the odometry by a constant): it covers ``frame_indices`` (every solved frame of
    ``cam_name``, at ``times_ns``), whether or not a frame has a :class:`Suspect` of its own.

    ``check`` and ``cause`` as a suspect's; ``sigma`` the estimate's size in its standard
    deviations, against ``limit_sigma``; ``message`` the finding with its evidence ("camera
    front's poses lag the odometry by 29 ± 2 ms (from 180 steps): its stamps lag?");
    ``offset_s`` / ``offset_sigma_s`` the estimated stamp offset and its σ (s, > 0: the poses
    lag), ``steps`` the steps it was estimated from."""

    cam_name: str
    check: str
    cause: str
    sigma: float
    limit_sigma: float
    message: str
    next_step: str = ""
    offset_s: float | None = None
    offset_sigma_s: float | None = None
    steps: int = 0
    frame_indices: tuple[int, ...] = ()
    times_ns: tuple[int, ...] = ()

    @property
    def n_frames(self) -> int:
        return len(self.frame_indices)

    @property
    def first_frame(self) -> int:
        return min(self.frame_indices)

    @property
    def last_frame(self) -> int:
        return max(self.frame_indices)

    @property
    def first_time_ns(self) -> int:
        return min(self.times_ns)

    @property
    def last_time_ns(self) -> int:
        return max(self.times_ns)
