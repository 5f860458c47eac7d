"""Paper 002's correction cycle (§1.2): multi-frame marker correction of a drifting navigation.
No file I/O.

:class:`CorrectionCycle` is the algorithm:

1. a cycle starts at a frame F: the navigation pose there, ``T_world_F_nav``, is remembered;
2. every frame adds each marker sighting of every camera, with the navigation's pose of that
   camera in F, ``T_F_cam = T_world_F_nav⁻¹ · T_world_agv_nav · T_agv_cam`` (the paper's
   ``T_F^Oj``, step 4);
3. the cycle closes when the navigation has travelled ``cycle_distance_m`` since F;
4. ``T_world_F`` is optimised over the window (:mod:`agvviz.solvers.cnoem` or
   :mod:`agvviz.solvers.bundle`), started from the corrected navigation at F, with both IPPE
   poses of the window's first sighting as fallbacks
   (:func:`~agvviz.solvers.cnoem.solve_cnoem_multistart`);
5. the current pose G is corrected through the motion during the cycle,
   ``T_F_G = T_world_F_nav⁻¹ · T_world_G_nav`` (step 4 of the correction): ``T_world_G =
   T_world_F · T_F_G``. So the solution, although it describes F, is applied to where the vehicle
   is now — the latency compensation of the paper. The correction is kept as
   ``T_correction = T_world_G · T_world_G_nav⁻¹`` and applied to every later navigation pose
   until the next cycle closes; the next cycle starts at G.

A cycle whose window has fewer than ``min_sightings`` sightings, whose solver fails, whose RMS
reprojection error exceeds ``max_reproj_px`` or whose first-order position σ exceeds
``max_position_sigma_m`` closes without a correction (the event says why). The frame G that
closes a cycle is frame 0 (F) of the next one.

:class:`CorrectionReplay` feeds it from a recording: ``/agv/odometry`` (the navigation),
``/agv/ground_truth``, ``/markers/map``, the pipeline's per-camera frames (their marker
observations) and corner-only ``/markers/corners`` messages.

The values they hand on (:class:`~agvviz.model.correction.FrameSighting`,
:class:`~agvviz.model.correction.CorrectionEvent`, :class:`~agvviz.model.correction.CorrectionStep`)
are frozen, in :mod:`agvviz.model.correction`.
"""

from __future__ import annotations

from agvviz.errors import InputError

from dataclasses import dataclass, replace

import numpy as np

from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.model.messages import PoseMsg, RecordedMessage
from agvviz.replay.sync import SyncState
from agvviz.model.correction import CorrectionEvent, CorrectionStep, FrameSighting
from agvviz.model.frames import FrameResult
from agvviz.solvers import window_baselines
from agvviz.solvers.bundle import pixel_residuals_and_jacobian, solve_bundle
from agvviz.solvers.cnoem import CornerWindow, Sighting, WindowSolution, solve_cnoem_multistart
from agvviz.solvers.uncertainty import UncertaintyError
from agvviz.solvers.window_crlb import position_bound_m, window_crlb

from agvviz.model.topics import ROLE_CORNERS, ROLE_MARKER_MAP, ROLE_ODOMETRY  # noqa: E402


class CorrectionError(InputError):
    """Bad correction settings or input (unknown solver, non-positive cycle distance)."""


@dataclass(frozen=True)
class CorrectionSettings:
    """solver : "cnoem" or "bundle"; update : CNOEM's update, "lm" or "paper";
    cycle_distance_m : travel that closes a cycle; min_sightings : smallest window solved;
    max_reproj_px : largest RMS reprojection error of an accepted solution;
    max_position_sigma_m : largest first-order position σ of an accepted solution (the window
    covariance at the solution with σ_px from its residuals): a window of one far, on-axis marker
    determines F poorly and would make the navigation worse."""

    solver: str = "cnoem"
    update: str = "lm"
    cycle_distance_m: float = 3.0
    min_sightings: int = 2
    max_reproj_px: float = 3.0
    max_position_sigma_m: float = 0.05

    def __post_init__(self):
        if self.solver not in ("cnoem", "bundle"):
            raise CorrectionError(f"correction solver must be cnoem or bundle, got {self.solver!r}")
        if self.update not in ("lm", "paper"):
            raise CorrectionError(f"cnoem update must be lm or paper, got {self.update!r}")
        if not self.cycle_distance_m > 0:
            raise CorrectionError(f"cycle_distance_m must be > 0, got {self.cycle_distance_m}")
        if not self.max_position_sigma_m > 0:
            raise CorrectionError(f"max_position_sigma_m must be > 0, got {self.max_position_sigma_m}")
        if self.min_sightings < 1:
            raise CorrectionError(f"min_sightings must be ≥ 1, got {self.min_sightings}")


class CorrectionCycle:
    """The correction cycle of the module docstring. ``T_agv_cam`` : camera name → extrinsic."""

    def __init__(self, settings: CorrectionSettings, T_agv_cam: dict[str, np.ndarray]):
        self.settings = settings
        self.T_agv_cam = dict(T_agv_cam)
        self.T_correction = np.eye(4)
        self.cycle_index = 0
        self._start_new(None, None)

    def _start_new(self, T_world_F_nav: np.ndarray | None, log_time_ns: int | None) -> None:
        self.T_world_F_nav = T_world_F_nav
        self.sightings: list[Sighting] = []
        self.frame_times_ns: list[int] = [] if log_time_ns is None else [log_time_ns]
        self.travelled_m = 0.0
        self._last_position = None if T_world_F_nav is None else T_world_F_nav[:3, 3].copy()

    def corrected(self, T_world_agv_nav: np.ndarray) -> np.ndarray:
        """The navigation pose with the current correction applied."""
        return self.T_correction @ T_world_agv_nav

    def add_frame(
        self, log_time_ns: int, T_world_agv_nav: np.ndarray, sightings: list[FrameSighting]
    ) -> CorrectionEvent | None:
        """Add one frame (any number of cameras at one time); returns the event when the cycle
        closes at this frame, else None. Raises CorrectionError for a camera without extrinsic."""
        T_nav = np.asarray(T_world_agv_nav, dtype=float)
        if self.T_world_F_nav is None:
            self._start_new(T_nav, log_time_ns)
        self.travelled_m += float(np.linalg.norm(T_nav[:3, 3] - self._last_position))
        self._last_position = T_nav[:3, 3].copy()
        if self.frame_times_ns[-1] != log_time_ns:
            self.frame_times_ns.append(log_time_ns)
        T_F_agv = se3.inverse(self.T_world_F_nav) @ T_nav
        for s in sightings:
            if s.cam_name not in self.T_agv_cam:
                raise CorrectionError(f"camera {s.cam_name!r} has no extrinsic (/tf_static); cannot place its sightings")
            self.sightings.append(
                Sighting(s.marker_id, s.cam_name, len(self.frame_times_ns) - 1, s.points_world_m, s.pixels_px, s.K,
                         T_F_agv @ self.T_agv_cam[s.cam_name])
            )
        if self.travelled_m < self.settings.cycle_distance_m:
            return None
        return self._close(log_time_ns, T_nav)

    def _close(self, log_time_ns: int, T_world_G_nav: np.ndarray) -> CorrectionEvent:
        T_world_F_before = self.corrected(self.T_world_F_nav)
        T_world_G_before = self.corrected(T_world_G_nav)
        T_F_G = se3.inverse(self.T_world_F_nav) @ T_world_G_nav
        event = CorrectionEvent(
            log_time_ns, self.cycle_index, len(self.frame_times_ns), len(self.sightings), "",
            T_world_F_before, None, T_world_G_before, T_world_G_before, 0.0, frame_times_ns=list(self.frame_times_ns),
        )
        if len(self.sightings) < self.settings.min_sightings:
            reason = f"{len(self.sightings)} marker sighting(s) in the cycle, need {self.settings.min_sightings}"
            event = replace(event, reason=reason)
        else:
            window = CornerWindow.from_sightings(self.sightings)
            solution = self._solve(window, T_world_F_before)
            event = replace(event, window=window, solution=solution)
            rms = solution.iterations[-1].reproj_rms_px if solution.iterations else float("nan")
            if not solution.success:
                event = replace(event, reason=f"solver failed: {solution.reason}")
            elif not rms <= self.settings.max_reproj_px:
                reason = f"RMS reprojection error {rms:.2f} px above max_reproj_px {self.settings.max_reproj_px:g}"
                event = replace(event, reason=reason)
            elif not (sigma := self._position_sigma_m(window, solution)) <= self.settings.max_position_sigma_m:
                reason = (
                    f"position σ {sigma:.3f} m above max_position_sigma_m {self.settings.max_position_sigma_m:g} "
                    "(the window determines F poorly)"
                )
                event = replace(event, position_sigma_m=sigma, reason=reason)
            else:
                T_world_G_after = solution.T_world_F @ T_F_G
                jump_m = float(np.linalg.norm(T_world_G_after[:3, 3] - T_world_G_before[:3, 3]))
                event = replace(
                    event, position_sigma_m=sigma, T_world_F_after=solution.T_world_F,
                    T_world_G_after=T_world_G_after, jump_m=jump_m,
                )
                self.T_correction = event.T_world_G_after @ se3.inverse(T_world_G_nav)
        self.cycle_index += 1
        self._start_new(T_world_G_nav, log_time_ns)
        return event

    @staticmethod
    def _position_sigma_m(window: CornerWindow, solution: WindowSolution) -> float:
        """First-order position σ (m) of the solution: the window covariance at the solution
        with σ_px = sqrt(Σ pixel residual² / (2N − 6)); inf when undetermined."""
        f, _ = pixel_residuals_and_jacobian(window, solution.T_F_world)
        dof = f.size - 6
        if dof <= 0:
            return float("inf")
        sigma_px = float(np.sqrt(f @ f / dof))
        try:
            return position_bound_m(window_crlb(window, solution.T_world_F, max(sigma_px, 1e-6)))
        except UncertaintyError:
            return float("inf")

    def _solve(self, window: CornerWindow, T_world_F_start: np.ndarray) -> WindowSolution:
        starts = [T_world_F_start]
        candidates, _ = window_baselines.ippe_candidates(window_baselines.earliest(self.sightings))
        starts += candidates or []
        solution = solve_cnoem_multistart(window, starts, T_reference_world_F=T_world_F_start, update=self.settings.update)
        if self.settings.solver == "bundle" and solution.success:
            solution = solve_bundle(window, solution.T_world_F, cnoem_start=False)
        return solution


class CorrectionReplay:
    """Feeds :class:`CorrectionCycle` from recording messages and the pipeline's frames.

    ``cameras`` : camera name → object with ``camera`` (PinholeCamera) and ``T_agv_cam`` (as
    :class:`agvviz.replay.solve.ReplayContext` holds them; read when frames arrive, so calibrations
    recorded later than construction are seen). Frames of one time stamp are grouped; a group is
    complete when a message with a later time arrives, so :meth:`finish` must be called last.
    """

    def __init__(self, settings: CorrectionSettings, cameras: dict, sync: SyncState):
        self.settings = settings
        self.cameras = cameras
        self.sync = sync  # the sync stage: ground truth at each step's stamp
        self.cycle: CorrectionCycle | None = None
        self.map_corners: dict[str, np.ndarray] = {}
        self._nav: PoseMsg | None = None
        self._pending_time: int | None = None
        self._pending: list[FrameSighting] = []
        self._pending_any = False

    def feed(self, message: RecordedMessage, frame: FrameResult | None) -> list[CorrectionStep]:
        out = []
        if self._pending_time is not None and message.time_ns > self._pending_time:
            out += self._flush()
        if message.role == ROLE_MARKER_MAP and isinstance(message.value, dict):
            for m in message.value.get("markers", []):
                corners = np.asarray(m.get("corners_world_m", []), dtype=float)
                if m.get("frame", "world") == "world" and corners.shape == (4, 3):
                    self.map_corners[str(m.get("id"))] = corners
        elif message.role == ROLE_ODOMETRY and isinstance(message.value, PoseMsg):
            self._nav = message.value
        elif message.role == ROLE_CORNERS and isinstance(message.value, dict):
            self._add_pending(message.time_ns, self._corner_sightings(message.value))
        if frame is not None:
            self._add_pending(frame.log_time_ns, self._frame_sightings(frame))
        return out

    def finish(self) -> list[CorrectionStep]:
        return self._flush()

    def _add_pending(self, log_time_ns: int, sightings: list[FrameSighting]) -> None:
        self._pending_time = log_time_ns
        self._pending += sightings
        self._pending_any = True

    def _camera(self, cam_name: str) -> PinholeCamera | None:
        cam = self.cameras.get(cam_name)
        return None if cam is None else cam.camera

    def _frame_sightings(self, frame: FrameResult) -> list[FrameSighting]:
        camera = self._camera(frame.cam_name)
        if camera is None:
            return []
        out = []
        for obs in frame.observations:
            if obs.points_frame != "world" or len(obs.corners_px) < 4:
                continue
            ideal = camera.undistort_pixels(np.asarray(obs.corners_px, dtype=float)[:4])
            out.append(FrameSighting(obs.marker_id, frame.cam_name, np.asarray(obs.points_world_m)[:4], ideal, camera.K))
        return out

    def _corner_sightings(self, value: dict) -> list[FrameSighting]:
        cam_name = str(value.get("cam_name"))
        camera = self._camera(cam_name)
        if camera is None:
            return []
        out = []
        for m in value.get("markers", []):
            corners = self.map_corners.get(str(m.get("id")))
            px = np.asarray(m.get("corners_px", []), dtype=float)
            if corners is None or px.ndim != 2 or px.shape[0] < 4:
                continue
            out.append(FrameSighting(str(m.get("id")), cam_name, corners, camera.undistort_pixels(px[:4]), camera.K))
        return out

    def _flush(self) -> list[CorrectionStep]:
        if self._pending_time is None or not self._pending_any:
            return []
        t, sightings = self._pending_time, self._pending
        self._pending_time, self._pending, self._pending_any = None, [], False
        if self._nav is None:
            return []  # no navigation yet: nothing to correct
        if self.cycle is None:
            mounts = {n: c.T_agv_cam for n, c in self.cameras.items() if getattr(c, "T_agv_cam", None) is not None}
            self.cycle = CorrectionCycle(self.settings, mounts)
        T_nav = self._nav.T
        event = self.cycle.add_frame(t, T_nav, sightings)
        truth = self.sync.truth_at(t)
        return [CorrectionStep(t, T_nav, self.cycle.corrected(T_nav), truth, sightings, event)]


class CorrectionStats:
    """Run statistics of a correction replay (for the run summary)."""

    def __init__(self):
        self.nav_errors_m: list[float] = []
        self.corrected_errors_m: list[float] = []
        self.events: list[CorrectionEvent] = []

    def add(self, step: CorrectionStep) -> None:
        if step.T_world_agv_truth is not None:
            truth = step.T_world_agv_truth[:3, 3]
            self.nav_errors_m.append(float(np.linalg.norm(step.T_world_agv_nav[:3, 3] - truth)))
            self.corrected_errors_m.append(float(np.linalg.norm(step.T_world_agv_corrected[:3, 3] - truth)))
        if step.event is not None:
            self.events.append(step.event)

    def summary(self) -> dict:
        applied = [e for e in self.events if e.applied]

        def rms(values):
            return float(np.sqrt(np.mean(np.square(values)))) if values else None

        return {
            "cycles": len(self.events),
            "corrections_applied": len(applied),
            "cycles_without_correction": {f"cycle {e.cycle_index}": e.reason for e in self.events if not e.applied},
            "mean_jump_m": float(np.mean([e.jump_m for e in applied])) if applied else None,
            "nav_rmse_m": rms(self.nav_errors_m),
            "corrected_rmse_m": rms(self.corrected_errors_m),
            "nav_final_error_m": self.nav_errors_m[-1] if self.nav_errors_m else None,
            "corrected_final_error_m": self.corrected_errors_m[-1] if self.corrected_errors_m else None,
        }
