"""One entry point for every single-frame pose solver: :func:`solve`.

Every solver takes coplanar marker-frame points (z = 0; first four TL, TR, BR, BL, optionally
the edge midpoints after) and their pixels in an IDEAL pinhole image (undistorted), and
returns the marker pose in the camera frame, ``p_cam = T_cam_marker @ p_marker``.

Bad numbers never raise: the result then has ``T_cam_marker = None`` and a ``reason``.
Only an unknown solver name raises ``ValueError``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agvviz.geometry import se3
from agvviz.solvers.types import LmIteration
from agvviz.solvers.lm import OBJECTIVES, refine_lm, reprojection_rms_px
from agvviz.solvers.opencv_peers import solve_opencv
from agvviz.solvers.p4p import solve_p4p
from agvviz.solvers.planar import PlanarPrior, solve_planar

SOLVER_NAMES = ("p4p", "lm", "ippe", "ippe_square", "sqpnp", "epnp", "iterative", "planar")

#: Marker points with |z| above this fraction of their spread in x, y are refused.
_PLANE_REL_TOL = 1e-9
#: Singular-value ratio below which all points count as lying on one line (or one point).
_COLLINEAR_REL_TOL = 1e-9


@dataclass(frozen=True)
class SolverOptions:
    """Settings of :func:`solve`; only ``lm`` reads them.

    objective : "depth" = paper 000 eq 23 (residual z'·(p' − p)), "pixel" = eq 22.
    max_iterations : LM trial steps; when they run out the best pose so far is returned.
    initial_damping : LM λ relative to mean(diag(JᵀJ)); ÷10 on an accepted step, ×10 on a
        rejected one (see :mod:`agvviz.solvers.lm`).
    step_tol : converged when the tangent step norm ‖δ‖ falls below this.
    cost_rel_tol : converged when a step changes the cost by at most this fraction.
    """

    objective: str = "depth"
    max_iterations: int = 50
    initial_damping: float = 1e-3
    step_tol: float = 1e-12
    cost_rel_tol: float = 1e-14


@dataclass
class SolveResult:
    """What a solver returned.

    T_cam_marker : (4, 4) marker pose in the camera frame, ``None`` on failure.
    reason : "" on success, else why the solve failed.
    iterations : LM only (empty otherwise); ``iterations[0]`` is the start (P4P) cost.
    reproj_rms_px : RMS over all given points of the Euclidean pixel distance between the
        returned pose's projection and the given pixels; ``None`` on failure.
    path : LM only: the pose (4, 4) kept after each record of ``iterations``.
    """

    T_cam_marker: np.ndarray | None
    reason: str
    iterations: list[LmIteration] = field(default_factory=list)
    reproj_rms_px: float | None = None
    path: list[np.ndarray] = field(default_factory=list)

    @property
    def success(self) -> bool:
        return self.T_cam_marker is not None and self.reason == ""


def _spans_a_plane(points_2d: np.ndarray) -> bool:
    """True when 2-D points (N, 2) are neither all coincident nor all on one line."""
    centred = points_2d - points_2d.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    return bool(sv[0] > 0.0 and sv[1] > _COLLINEAR_REL_TOL * sv[0])


def _input_problem(points_marker_m, pixels_px, K) -> str:
    """Why the inputs cannot be solved, or "" when they can."""
    if points_marker_m.ndim != 2 or points_marker_m.shape[1] != 3:
        return f"shape mismatch: points_marker_m must be (N, 3), got {points_marker_m.shape}"
    if pixels_px.ndim != 2 or pixels_px.shape[1] != 2:
        return f"shape mismatch: pixels_px must be (N, 2), got {pixels_px.shape}"
    if points_marker_m.shape[0] != pixels_px.shape[0]:
        return (
            f"shape mismatch: {points_marker_m.shape[0]} marker points but "
            f"{pixels_px.shape[0]} pixels"
        )
    if K.shape != (3, 3):
        return f"shape mismatch: K must be (3, 3), got {K.shape}"
    if points_marker_m.shape[0] < 4:
        return "fewer than 4 points"
    if not (
        np.isfinite(points_marker_m).all() and np.isfinite(pixels_px).all()
        and np.isfinite(K).all()
    ):
        return "non-finite input"
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and np.array_equal(K[2], [0, 0, 1])):
        return "invalid camera matrix: need fx, fy > 0, K[1, 0] = 0 and last row (0, 0, 1)"
    spread_m = float(np.max(np.abs(points_marker_m[:, :2] - points_marker_m[:, :2].mean(axis=0))))
    if np.max(np.abs(points_marker_m[:, 2])) > _PLANE_REL_TOL * spread_m:
        return "marker points are not on the z = 0 plane of the marker frame"
    if not _spans_a_plane(pixels_px):
        return "degenerate: pixels collinear"
    if not _spans_a_plane(points_marker_m[:, :2]):
        return "degenerate: marker points collinear"
    return ""


def solve(
    name: str,
    points_marker_m: np.ndarray,
    pixels_px: np.ndarray,
    K: np.ndarray,
    options: SolverOptions = SolverOptions(),
    prior: PlanarPrior | None = None,
) -> SolveResult:
    """Marker pose in the camera frame from N ≥ 4 coplanar points and their ideal pixels.

    Parameters
    ----------
    name : one of :data:`SOLVER_NAMES`.
        ``p4p`` — paper 000 eqs 7–21 on the first 4 points;
        ``lm`` — Levenberg–Marquardt on SE(3) over all points, started from ``p4p``
        (from ``ippe`` when ``p4p`` fails);
        ``ippe``, ``ippe_square``, ``sqpnp``, ``epnp``, ``iterative`` — ``cv2.solvePnP``;
        ``planar`` — x, y, heading of a ground vehicle under ``prior``
        (:mod:`agvviz.solvers.planar`; needs ``prior``).
    points_marker_m : (N, 3) marker-frame points with z = 0.
    pixels_px : (N, 2) pixels of those points in an ideal (undistorted) pinhole image.
    K : (3, 3) camera matrix (upper triangular, last row 0 0 1).
    options : LM settings (ignored by the other solvers; ``planar`` reads max_iterations).
    prior : camera mounting and the code's floor pose, for ``planar`` only.

    Returns
    -------
    SolveResult; on failure ``T_cam_marker`` is ``None`` and ``reason`` says why.

    Raises
    ------
    ValueError : ``name`` is not a known solver, or ``options.objective`` is not a known LM
        objective (the message lists the valid ones).
    """
    if name not in SOLVER_NAMES:
        raise ValueError(f"unknown solver {name!r}; valid solvers: {', '.join(SOLVER_NAMES)}")
    if options.objective not in OBJECTIVES:
        raise ValueError(
            f"unknown LM objective {options.objective!r}; valid: {', '.join(OBJECTIVES)}"
        )
    points_marker_m = np.asarray(points_marker_m, dtype=float)
    pixels_px = np.asarray(pixels_px, dtype=float)
    K = np.asarray(K, dtype=float)
    problem = _input_problem(points_marker_m, pixels_px, K)
    if problem:
        return SolveResult(None, problem)

    iterations: list[LmIteration] = []
    path: list[np.ndarray] = []
    if name == "planar":
        if prior is None:
            return SolveResult(
                None,
                "planar needs a PlanarPrior (camera mounting T_agv_cam and the code's "
                "T_world_marker); agvviz run passes them from /tf_static and the payload",
            )
        solution, reason = solve_planar(
            points_marker_m, pixels_px, K, prior, max_iterations=options.max_iterations
        )
        T = None if solution is None else solution.T_cam_marker
    elif name == "p4p":
        T, reason = solve_p4p(points_marker_m, pixels_px, K)
    elif name == "lm":
        T_start, p4p_reason = solve_p4p(points_marker_m, pixels_px, K)
        if T_start is None:
            T_start, ippe_reason = solve_opencv("ippe", points_marker_m, pixels_px, K)
            if T_start is not None and not _all_in_front(T_start, points_marker_m):
                T_start, ippe_reason = None, "point behind camera"
        if T_start is None:
            T, reason = None, f"no start pose: p4p: {p4p_reason}; ippe: {ippe_reason}"
        else:
            T, reason, iterations = refine_lm(
                T_start,
                points_marker_m,
                pixels_px,
                K,
                objective=options.objective,
                max_iterations=options.max_iterations,
                initial_damping=options.initial_damping,
                step_tol=options.step_tol,
                cost_rel_tol=options.cost_rel_tol,
                path_out=path,
            )
    else:
        T, reason = solve_opencv(name, points_marker_m, pixels_px, K)

    if T is None:
        return SolveResult(None, reason, iterations, path=path)
    if not se3.is_rigid(T):
        return SolveResult(None, "non-finite or non-rigid result", iterations, path=path)
    if not _all_in_front(T, points_marker_m):
        return SolveResult(None, "point behind camera", iterations, path=path)
    return SolveResult(T, "", iterations, reprojection_rms_px(T, points_marker_m, pixels_px, K), path)


def _all_in_front(T_cam_marker: np.ndarray, points_marker_m: np.ndarray) -> bool:
    """True when every point has positive depth in the camera frame."""
    return bool((se3.transform_points(T_cam_marker, points_marker_m)[:, 2] > 0.0).all())
