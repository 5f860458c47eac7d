"""UWB position fixes from tag–anchor ranges. Numpy only.

Two solvers, one input: anchors (N, 3) in world metres, measured 3-D ranges (N,) and the tag's
height ``tag_z_m`` (the tag rides on the AGV, whose height above the floor is known), so the
unknown is the horizontal position (x, y):

* :func:`trilateral_centroid` — paper 003 eqs 3–6. Ranges are reduced to horizontal radii
  ``s = √(r² − Δz²)``; the three anchors with the smallest radii are used; each pair of circles
  is intersected and one intersection kept per pair; the fix is the centroid of the three kept
  points. Circles that miss each other contribute the point on the line of centres where the
  radical line crosses it. Which intersection: the paper keeps the one "closer to the centre
  of the third circle"; that picks the mirror point whenever the tag is nearer the line of the
  other two anchors than its mirror image is to the third anchor (e.g. (7.2, 6.0) m in the
  8 × 7 m room with wall-centre anchors: 0.8 m off on exact ranges), so here the intersection
  that best agrees with the third range, ``min |‖p − c₃‖ − s₃|``, is kept — the same point
  wherever the paper's rule works.
* :func:`least_squares_fix` — Gauss–Newton on the 3-D range residuals over (x, y), started from
  the linearised (difference-of-squares) solution; covariance ``σ²(HᵀH)⁻¹`` and GDOP.

:func:`gate_ranges` is the NLOS/outlier gate both use: the normalised residuals of a least-
squares fit over all anchors against a χ² bound; when they fail, the anchor whose removal
lowers the cost most is dropped and the test repeats while at least three anchors remain.
"""

from __future__ import annotations

from agvviz.errors import RunError

from dataclasses import dataclass, field
import numpy as np

#: 99 % quantiles of χ² with 1..6 degrees of freedom (the residual gate's bound).
CHI2_99 = {1: 6.635, 2: 9.210, 3: 11.345, 4: 13.277, 5: 15.086, 6: 16.812}

METHODS = ("centroid", "least_squares")


class UwbLocalizationError(RunError):
    """Ranges or anchors a fix cannot be made from (too few, non-finite, wrong shapes)."""


@dataclass
class UwbFix:
    """One UWB position fix.

    position_m : (3,) world position of the tag (z = the given tag height).
    method : "centroid" | "least_squares".
    used : (N,) bool, anchors the fix used (False: removed by the gate or not one of the
        centroid's three).
    gated : (N,) bool, anchors the gate removed.
    residuals_m : (N,) measured − predicted range at the fix, for every anchor.
    gdop : geometric dilution of precision of the used anchors at the fix (2-D, unitless).
    covariance_m2 : (2, 2) covariance of (x, y) from σ²(HᵀH)⁻¹, least squares only.
    """

    position_m: np.ndarray
    method: str
    used: np.ndarray
    gated: np.ndarray
    residuals_m: np.ndarray
    gdop: float
    covariance_m2: np.ndarray | None = None
    iterations: int = 0
    log_time_ns: int = 0
    anchor_ids: list[str] = field(default_factory=list)
    ranges_m: np.ndarray | None = None


def _check(anchors_m, ranges_m, minimum: int) -> tuple[np.ndarray, np.ndarray]:
    anchors_m = np.asarray(anchors_m, dtype=float)
    ranges_m = np.asarray(ranges_m, dtype=float)
    if anchors_m.ndim != 2 or anchors_m.shape[1] != 3:
        raise UwbLocalizationError(f"anchors must have shape (N, 3), got {anchors_m.shape}")
    if ranges_m.shape != (anchors_m.shape[0],):
        raise UwbLocalizationError(
            f"need one range per anchor: {anchors_m.shape[0]} anchors, ranges shape {ranges_m.shape}"
        )
    if anchors_m.shape[0] < minimum:
        raise UwbLocalizationError(f"need at least {minimum} anchors for a 2-D fix, got {anchors_m.shape[0]}")
    if not (np.all(np.isfinite(anchors_m)) and np.all(np.isfinite(ranges_m))):
        raise UwbLocalizationError("anchors or ranges contain NaN or inf")
    if np.any(ranges_m < 0):
        raise UwbLocalizationError(f"ranges must be ≥ 0, got {ranges_m.tolist()}")
    return anchors_m, ranges_m


def horizontal_radii_m(anchors_m: np.ndarray, ranges_m: np.ndarray, tag_z_m: float) -> np.ndarray:
    """Horizontal radii ``√(r² − Δz²)`` (N,); a range shorter than the height gap gives 0."""
    dz = anchors_m[:, 2] - tag_z_m
    return np.sqrt(np.maximum(ranges_m**2 - dz**2, 0.0))


def predicted_ranges_m(anchors_m: np.ndarray, position_m: np.ndarray) -> np.ndarray:
    """3-D distances (N,) from ``position_m`` (3,) to every anchor (N, 3)."""
    return np.linalg.norm(np.asarray(anchors_m, dtype=float) - np.asarray(position_m, dtype=float), axis=1)


def gdop(anchors_m: np.ndarray, position_m: np.ndarray) -> float:
    """2-D GDOP ``√trace((HᵀH)⁻¹)`` with ``H`` the range gradients w.r.t. (x, y); inf when singular."""
    H = _range_jacobian(np.asarray(anchors_m, dtype=float), np.asarray(position_m, dtype=float))
    HtH = H.T @ H
    if np.linalg.cond(HtH) > 1e12:
        return float("inf")
    return float(np.sqrt(np.trace(np.linalg.inv(HtH))))


def _range_jacobian(anchors_m: np.ndarray, position_m: np.ndarray) -> np.ndarray:
    """∂r/∂(x, y) (N, 2) at ``position_m``."""
    diff = position_m - anchors_m
    r = np.maximum(np.linalg.norm(diff, axis=1), 1e-9)
    return diff[:, :2] / r[:, None]


def _circle_point(c1, s1, c2, s2, c3, s3) -> np.ndarray:
    """Intersection of circles (c1, s1), (c2, s2) that best agrees with the third circle
    (c3, s3); the radical-line point on the line of centres when they do not intersect
    (paper 003 eqs 3–5; see the module docstring for the choice)."""
    d_vec = c2 - c1
    d = float(np.linalg.norm(d_vec))
    if d < 1e-9:
        raise UwbLocalizationError("two anchors share one horizontal position; cannot intersect their circles")
    e = d_vec / d
    a = (s1**2 - s2**2 + d**2) / (2.0 * d)
    h2 = s1**2 - a**2
    base = c1 + a * e
    if h2 <= 0.0:
        return base
    n = np.array([-e[1], e[0]])
    p, q = base + np.sqrt(h2) * n, base - np.sqrt(h2) * n
    return p if abs(np.linalg.norm(p - c3) - s3) <= abs(np.linalg.norm(q - c3) - s3) else q


def trilateral_centroid(
    anchors_m, ranges_m, tag_z_m: float, use: np.ndarray | None = None
) -> UwbFix:
    """Paper 003's trilateral centroid (eqs 3–6) over the three usable anchors with the
    smallest horizontal radii. ``use`` (N,) bool restricts the anchors (e.g. after the gate)."""
    anchors_m, ranges_m = _check(anchors_m, ranges_m, 3)
    n = anchors_m.shape[0]
    use = np.ones(n, dtype=bool) if use is None else np.asarray(use, dtype=bool)
    if use.sum() < 3:
        raise UwbLocalizationError(f"the trilateral centroid needs 3 usable anchors, got {int(use.sum())}")
    radii = horizontal_radii_m(anchors_m, ranges_m, tag_z_m)
    candidates = np.flatnonzero(use)
    three = candidates[np.argsort(radii[candidates], kind="stable")[:3]]
    c = anchors_m[three, :2]
    s = radii[three]
    points = [
        _circle_point(c[0], s[0], c[1], s[1], c[2], s[2]),  # (x_ab, y_ab)
        _circle_point(c[1], s[1], c[2], s[2], c[0], s[0]),  # (x_bc, y_bc)
        _circle_point(c[0], s[0], c[2], s[2], c[1], s[1]),  # (x_ac, y_ac)
    ]
    xy = np.mean(points, axis=0)  # eq 6
    position = np.array([xy[0], xy[1], tag_z_m])
    used = np.zeros(n, dtype=bool)
    used[three] = True
    return UwbFix(
        position_m=position,
        method="centroid",
        used=used,
        gated=~use,
        residuals_m=ranges_m - predicted_ranges_m(anchors_m, position),
        gdop=gdop(anchors_m[used], position),
    )


def _linear_start(anchors_m: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(x, y) from the difference-of-squares linearisation (exact for exact radii)."""
    c = anchors_m[:, :2]
    A = 2.0 * (c[1:] - c[0])
    b = (radii[0] ** 2 - radii[1:] ** 2) + np.sum(c[1:] ** 2, axis=1) - np.sum(c[0] ** 2)
    xy, *_ = np.linalg.lstsq(A, b, rcond=None)
    return xy


def least_squares_fix(
    anchors_m,
    ranges_m,
    tag_z_m: float,
    sigma_m: float = 0.05,
    use: np.ndarray | None = None,
    max_iterations: int = 20,
    tol_m: float = 1e-9,
) -> UwbFix:
    """Gauss–Newton multilateration over (x, y) with the tag height fixed.

    Parameters
    ----------
    anchors_m : (N, 3), ranges_m : (N,) measured 3-D ranges, tag_z_m : tag height.
    sigma_m : range standard deviation, scales the covariance.
    use : (N,) bool, anchors to use (default all); at least 3.
    """
    anchors_m, ranges_m = _check(anchors_m, ranges_m, 3)
    n = anchors_m.shape[0]
    use = np.ones(n, dtype=bool) if use is None else np.asarray(use, dtype=bool)
    if use.sum() < 3:
        raise UwbLocalizationError(f"least squares needs 3 usable anchors, got {int(use.sum())}")
    A, r = anchors_m[use], ranges_m[use]
    xy = _linear_start(A, horizontal_radii_m(A, r, tag_z_m))
    position = np.array([xy[0], xy[1], tag_z_m])
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        H = _range_jacobian(A, position)
        residual = r - predicted_ranges_m(A, position)
        step, *_ = np.linalg.lstsq(H, residual, rcond=None)
        position[:2] += step
        if np.linalg.norm(step) < tol_m:
            break
    H = _range_jacobian(A, position)
    HtH = H.T @ H
    covariance = sigma_m**2 * np.linalg.pinv(HtH)
    return UwbFix(
        position_m=position,
        method="least_squares",
        used=use.copy(),
        gated=~use,
        residuals_m=ranges_m - predicted_ranges_m(anchors_m, position),
        gdop=gdop(A, position),
        covariance_m2=covariance,
        iterations=iterations,
    )


def _cost(anchors_m, ranges_m, tag_z_m, use) -> float:
    fix = least_squares_fix(anchors_m, ranges_m, tag_z_m, use=use)
    return float(np.sum(fix.residuals_m[use] ** 2))


def gate_ranges(
    anchors_m, ranges_m, tag_z_m: float, sigma_m: float, chi2_bound: dict[int, float] = CHI2_99
) -> np.ndarray:
    """Anchors (N,) bool that pass the residual gate (see the module docstring).

    With N anchors a 2-D fit has N − 2 degrees of freedom: four anchors can find and drop one
    bad range, three can only detect one (and then all three are kept).
    """
    anchors_m, ranges_m = _check(anchors_m, ranges_m, 3)
    use = np.ones(anchors_m.shape[0], dtype=bool)
    while use.sum() > 3:
        dof = int(use.sum()) - 2
        if _cost(anchors_m, ranges_m, tag_z_m, use) / sigma_m**2 <= chi2_bound[min(dof, max(chi2_bound))]:
            break
        trials = []
        for drop in np.flatnonzero(use):
            trial = use.copy()
            trial[drop] = False
            trials.append((_cost(anchors_m, ranges_m, tag_z_m, trial), int(drop)))
        use[min(trials)[1]] = False
    return use

