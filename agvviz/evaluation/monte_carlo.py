"""Paper 000 §6 Monte-Carlo study: solve every trial of a ``p4p_monte_carlo`` recording with
every solver, score the marker translation t against truth and the Cramér–Rao bound, and
write the comparison with the paper's figures 3–15 as markdown. No file I/O.

Quantity scored: t, the marker centre in the camera frame (the paper's t of T_cam_marker).
Its bound is sqrt(trace) of the CRLB's position block (:func:`uncertainty.position_covariance`
at the true pose), i.e. the smallest RMS ‖t̂ − t‖ an unbiased estimator can have.

Solvers: ``p4p`` (paper eqs 7–21), ``lm`` (paper eq 23, the ``depth`` objective — the
paper's LM), ``lm_pixel`` (eq 22, maximum likelihood), both vectorised
(:mod:`agvviz.solvers.lm_batch`; a frame whose batched P4P start fails is solved by
:func:`agvviz.solvers.solve`, which falls back to an IPPE start), and OpenCV's ``ippe`` and
``sqpnp``; ``lm_amb`` is lm_pixel with the replay's ambiguity resolution (``lowest_error``):
pixel LM from P4P and from both IPPE poses, the lowest reprojection error kept. Failed solves
are counted and left out of the statistics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from agvviz.errors import RecordingError
from agvviz.model.messages import CalibrationMsg, RecordedMessage
from agvviz.solvers import SolverOptions, solve
from agvviz.solvers import uncertainty
from agvviz.solvers.ambiguity import ippe_pair
from agvviz.solvers.lm_batch import p4p_batch, refine_lm_batch, solve_lm_batch

SOLVERS = ("p4p", "lm", "lm_pixel", "lm_amb", "ippe", "sqpnp")
#: LM iteration budget of the study: ill-conditioned (fronto-parallel) cells crawl along a flat
#: valley for 50–100 Gauss–Newton steps before the default stopping rule fires; the study
#: measures accuracy, so they get room (the run setting lm_max_iterations defaults to 50).
MC_LM_MAX_ITERATIONS = 200
from agvviz.model.topics import CORNERS_TOPIC, ROLE_CORNERS  # noqa: E402

#: Paper 000 §6 figures with numbers: figure → (cell id, solver, mean t (m), variance of t (m²)).
#: Figures 9–11 (the SNR sweep of t1, t2, t3) are plots without numbers in the text; their cells
#: are ``paper_h0.2667_z2_snr{15..24}_n4`` and the .rrd plots them. §6.2 group 1 prints the pixel
#: coordinates of the z = 2 m view although t3 = 4 m; its means (≈3.8) say z = 4 m was used.
PAPER_FIGURES = {
    3: ("paper_h0.1333_z2_snr15_n4", "p4p", (0.0468, 0.0468, 1.8696), (2.6e-5, 2.77e-5, 1.3e-2)),
    4: ("paper_h0.1333_z2_snr15_n4", "lm", (0.0494, 0.0495, 1.9555), (1.6e-5, 1.57e-5, 1.9e-3)),
    5: ("paper_h0.2667_z2_snr15_n4", "p4p", (0.0497, 0.0495, 1.9885), (2.6e-5, 2.7e-5, 4.1e-4)),
    6: ("paper_h0.2667_z2_snr15_n4", "lm", (0.05, 0.0499, 1.9902), (2.3e-5, 2.5e-5, 4.6e-4)),
    7: ("paper_h0.2667_z2_snr22_n4", "p4p", (0.0487, 0.0488, 1.9506), (1.1e-4, 1.3e-5, 3.7e-3)),
    8: ("paper_h0.2667_z2_snr22_n4", "lm", (0.0489, 0.0490, 1.9509), (1.1e-4, 1.3e-5, 3.3e-3)),
    12: ("paper_h0.2667_z4_snr22_n4", "lm", (0.0504, 0.0492, 3.7869), (2.4e-4, 2.5e-5, 3.3e-2)),
    13: ("paper_h0.2667_z4_snr22_n8", "lm", (0.0492, 0.0491, 3.7646), (1.2e-4, 1.2e-5, 2.2e-2)),
    14: ("paper_h0.1333_z4_snr22_n4", "lm", (0.0459, 0.0453, 3.5480), (2.1e-4, 2.2e-4, 9.7e-2)),
    15: ("paper_h0.1333_z4_snr22_n8", "lm", (0.0488, 0.0488, 3.7663), (1.3e-4, 1.3e-5, 2.4e-2)),
}

LM_VARIANTS = ("lm", "lm_pixel", "lm_amb")

#: "Well-conditioned" cells of the issue's target: tilted view, code ≥ 150 px, σ ≤ 1 px.
WELL_CONDITIONED = {"min_tilt_deg": 1.0, "min_code_px": 150.0, "max_sigma_px": 1.0}


@dataclass
class CellTrials:
    """All trials of one cell: pixels (T, N, 2), the marker points (N, 3), truth, σ."""

    cell_id: str
    points_marker_m: np.ndarray
    T_cam_marker_truth: np.ndarray
    sigma_px: float
    pixels_px: list = field(default_factory=list)


@dataclass
class SolverStats:
    n_ok: int
    n_failed: int
    mean_t_m: np.ndarray  # (3,)
    var_t_m2: np.ndarray  # (3,) sample variance (ddof 1)
    rmse_t_m: float  # sqrt(mean ‖t̂ − t‖²)


@dataclass
class CellResult:
    cell_id: str
    sigma_px: float
    n_points: int
    tilt_deg: float
    code_side_px: float
    crlb_t_m: float  # sqrt(trace) of the CRLB position block
    crlb_var_t_m2: np.ndarray  # (3,) diagonal of the CRLB position block
    stats: dict[str, SolverStats]
    #: solver → (trials,) ‖t̂ − t‖ of every trial in recording order (m), NaN where it failed.
    errors_t_m: dict[str, np.ndarray] = field(default_factory=dict)


def collect(messages: Iterable[RecordedMessage]) -> tuple[np.ndarray, dict[str, CellTrials]]:
    """(K, cells) from a p4p_monte_carlo recording's messages (file order): the calibration and
    every corner-observation message (role ``corners``) that carries a ``cell``. Raises
    :class:`RecordingError` when either is missing or a trial message is malformed."""
    K = None
    cells: dict[str, CellTrials] = {}
    for message in messages:
        value = message.value
        if isinstance(value, CalibrationMsg):
            K = value.camera.K
        elif message.role == ROLE_CORNERS and isinstance(value, dict) and "cell" in value:
            try:
                marker = value["markers"][0]
                cell = cells.get(str(value["cell"]))
                if cell is None:
                    cell = cells[str(value["cell"])] = CellTrials(
                        str(value["cell"]),
                        np.asarray(marker["points_marker_m"], dtype=float),
                        np.asarray(marker["T_cam_marker_truth"], dtype=float),
                        float(value["noise_sigma_px"]),
                    )
                corners_px = np.asarray(marker["corners_px"], dtype=float)
                n_points = len(cell.points_marker_m)
                if n_points < 4 or cell.points_marker_m.shape != (n_points, 3) or cell.T_cam_marker_truth.shape != (4, 4):
                    raise ValueError("points_marker_m must be (N ≥ 4, 3) and T_cam_marker_truth (4, 4)")
                if not (cell.sigma_px > 0 and np.isfinite(cell.sigma_px)):
                    raise ValueError(f"noise_sigma_px must be a positive number, got {cell.sigma_px}")
                if corners_px.shape != (n_points, 2):
                    raise ValueError(f"corners_px has shape {corners_px.shape}, the cell's points need ({n_points}, 2)")
            except (KeyError, IndexError, TypeError, ValueError) as exc:
                detail = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
                raise RecordingError(
                    f"{message.topic} message at {message.time_ns} ns is not a p4p_monte_carlo trial: {detail}"
                ) from None
            cell.pixels_px.append(corners_px)
    if K is None:
        raise RecordingError("the recording has no camera calibration; record it with the p4p_monte_carlo scenario")
    if not cells:
        raise RecordingError(
            f"the recording has no corner messages ({CORNERS_TOPIC}) with a 'cell': not a p4p_monte_carlo recording"
        )
    return K, cells


def solve_all(name: str, points: np.ndarray, pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(T, 4, 4) poses of solver ``name`` for every trial (NaN where it failed)."""
    n = pixels.shape[0]
    stacked = np.broadcast_to(points, (n,) + points.shape)
    if name == "p4p":
        return p4p_batch(stacked, pixels, K).T_cam_marker
    if name in ("lm", "lm_pixel"):
        objective = "depth" if name == "lm" else "pixel"
        batch = solve_lm_batch(stacked, pixels, K, objective=objective, max_iterations=MC_LM_MAX_ITERATIONS)
        T = batch.T_cam_marker
        for k in np.flatnonzero(~batch.ok):
            options = SolverOptions(objective=objective, max_iterations=MC_LM_MAX_ITERATIONS)
            single = solve("lm", points, pixels[k], K, options)
            T[k] = single.T_cam_marker if single.success else np.nan
        return T
    if name == "lm_amb":
        candidates = [solve_all("lm_pixel", points, pixels, K)]
        starts = np.full((2, n, 4, 4), np.nan)
        for k in range(n):
            pair, _ = ippe_pair(points, pixels[k], K)
            if pair is not None:
                starts[0, k], starts[1, k] = pair.T_best_cam_marker, pair.T_other_cam_marker
        for start in starts:
            candidates.append(
                refine_lm_batch(start, stacked, pixels, K, objective="pixel", max_iterations=MC_LM_MAX_ITERATIONS).T_cam_marker
            )
        rms = np.array([_rms_px(T, stacked, pixels, K) for T in candidates])  # (3, n), NaN where failed
        best = np.argmin(np.where(np.isfinite(rms), rms, np.inf), axis=0)
        T = np.stack(candidates)[best, np.arange(n)]
        T[~np.any(np.isfinite(rms), axis=0)] = np.nan
        return T
    T = np.full((n, 4, 4), np.nan)
    for k in range(n):
        result = solve(name, points, pixels[k], K)
        if result.success:
            T[k] = result.T_cam_marker
    return T


def _rms_px(T: np.ndarray, points: np.ndarray, pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n,) RMS reprojection error of poses T (n, 4, 4); NaN where T is NaN."""
    w = np.einsum("nij,npj->npi", T[:, :3, :3], points) + T[:, None, :3, 3]
    proj = w @ K.T
    return np.sqrt(np.mean(np.sum((proj[..., :2] / proj[..., 2:3] - pixels) ** 2, axis=2), axis=1))


def evaluate_cell(cell: CellTrials, K: np.ndarray, solvers=SOLVERS) -> CellResult:
    """Statistics of t for every solver on one cell, and the cell's CRLB."""
    pixels = np.asarray(cell.pixels_px, dtype=float)
    T_true = cell.T_cam_marker_truth
    t_true = T_true[:3, 3]
    bound = uncertainty.position_covariance(
        uncertainty.crlb(T_true, cell.points_marker_m, K, cell.sigma_px), T_true
    )
    stats = {}
    errors = {}
    for name in solvers:
        T = solve_all(name, cell.points_marker_m, pixels, K)
        ok = np.all(np.isfinite(T), axis=(1, 2))
        t = T[ok, :3, 3]
        errors[name] = np.where(ok, np.linalg.norm(T[:, :3, 3] - t_true, axis=1), np.nan)
        stats[name] = SolverStats(
            n_ok=int(ok.sum()),
            n_failed=int((~ok).sum()),
            mean_t_m=t.mean(axis=0) if len(t) else np.full(3, np.nan),
            var_t_m2=t.var(axis=0, ddof=1) if len(t) > 1 else np.full(3, np.nan),
            rmse_t_m=float(np.sqrt(np.mean(np.sum((t - t_true) ** 2, axis=1)))) if len(t) else float("nan"),
        )
    vertices = uncertainty.se3.transform_points(T_true, cell.points_marker_m[:4])
    px = (vertices @ K.T)[:, :2] / vertices[:, 2:3]
    side_px = float(np.mean(np.linalg.norm(np.roll(px, -1, axis=0) - px, axis=1)))
    tilt_deg = float(np.degrees(np.arccos(np.clip(T_true[2, 2], -1.0, 1.0))))
    return CellResult(
        cell.cell_id, cell.sigma_px, len(cell.points_marker_m), tilt_deg, side_px,
        uncertainty.position_bound_m(bound), np.diag(bound).copy(), stats, errors,
    )


def is_well_conditioned(result: CellResult) -> bool:
    c = WELL_CONDITIONED
    return (
        result.tilt_deg >= c["min_tilt_deg"]
        and result.code_side_px >= c["min_code_px"]
        and result.sigma_px <= c["max_sigma_px"]
    )


def checks(results: dict[str, CellResult]) -> dict:
    """The issue's figures: each LM variant's RMSE ÷ CRLB in well-conditioned cells; cells
    where an LM variant is worse (RMSE) than ippe or p4p."""
    well = {cid: r for cid, r in results.items() if is_well_conditioned(r)}
    ratios = {name: {cid: r.stats[name].rmse_t_m / r.crlb_t_m for cid, r in well.items()} for name in LM_VARIANTS}
    worse = {}
    for name in LM_VARIANTS:
        worse[name] = [
            (cid, peer, r.stats[name].rmse_t_m, r.stats[peer].rmse_t_m)
            for cid, r in results.items()
            for peer in ("ippe", "p4p")
            if r.stats[name].rmse_t_m > r.stats[peer].rmse_t_m
        ]
    return {
        "well_conditioned_cells": len(well),
        "max_rmse_over_crlb": {name: max(v.values()) if v else float("nan") for name, v in ratios.items()},
        "worse_than_peer": worse,
    }


def _fmt3(values, spec: str) -> str:
    return "[" + ", ".join(format(float(v), spec) for v in values) + "]"


def report_markdown(results: dict[str, CellResult], trials: int) -> str:
    """The study report: paper comparison, every cell's RMSE vs CRLB, and the checks."""
    lines = [
        "# Paper 000 §6 Monte-Carlo study (p4p_monte_carlo)",
        "",
        f"{trials} trials per cell. t = marker centre in the camera frame (m). SNR: signal power = mean "
        "square of the 4 vertices' noise-free pixel coordinates (principal point (0, 0)), "
        "σ² = P / 10^(SNR/10) on every coordinate (MATLAB awgn 'measured'); 8-point cells use "
        "their 4-point twin's σ. CRLB: sqrt(trace) of the Cramér–Rao bound on t at the true pose. "
        "lm = paper eq 23 (depth objective, the paper's LM), lm_pixel = eq 22 (ML), both from "
        "the P4P start; lm_amb = lm_pixel from P4P and from both IPPE poses, lowest reprojection "
        f"error kept (the replay's ambiguity=lowest_error). LM budget {MC_LM_MAX_ITERATIONS} "
        "iterations. Failed solves are left out of the statistics (counted in the last columns). "
        "Variances are sample variances (ddof 1).",
        "",
        "## Against the paper's figures 3–8, 12–15",
        "",
        "| fig | cell | σ px | solver | paper mean t | ours mean t | paper var t | ours var t | CRLB var t |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for fig, (cid, solver, mean, var) in PAPER_FIGURES.items():
        if cid not in results:
            continue
        r = results[cid]
        s = r.stats[solver]
        lines.append(
            f"| {fig} | {cid} | {r.sigma_px:.2f} | {solver} | {_fmt3(mean, '.4f')} | {_fmt3(s.mean_t_m, '.4f')} "
            f"| {_fmt3(var, '.2g')} | {_fmt3(s.var_t_m2, '.2g')} | {_fmt3(r.crlb_var_t_m2, '.2g')} |"
        )
    lines += [
        "",
        "Figures 9–11 (t1, t2, t3 of p4p and lm over SNR 15–24 dB, h = 0.2667 m, z = 2 m, 4 points) "
        "are plotted in the .rrd (`mc/paper/h0.2667_z2_n4/...`); the paper gives no numbers for them.",
        "",
        "## Every cell: RMSE of t (mm) and RMSE ÷ CRLB",
        "",
        "| cell | σ px | code px | tilt° | N | CRLB mm | " + " | ".join(f"{s} mm" for s in SOLVERS)
        + " | lm÷CRLB | lm_pixel÷CRLB | lm_amb÷CRLB | failed (" + "/".join(SOLVERS) + ") | well-cond. |",
        "| --- " * (6 + len(SOLVERS) + 5) + "|",
    ]
    for cid, r in results.items():
        rm = [r.stats[s].rmse_t_m * 1000 for s in SOLVERS]
        failed = "/".join(str(r.stats[s].n_failed) for s in SOLVERS)
        lines.append(
            f"| {cid} | {r.sigma_px:.3g} | {r.code_side_px:.0f} | {r.tilt_deg:.0f} | {r.n_points} | "
            f"{r.crlb_t_m * 1000:.3g} | " + " | ".join(f"{v:.3g}" for v in rm)
            + "".join(f" | {r.stats[v].rmse_t_m / r.crlb_t_m:.3f}" for v in LM_VARIANTS) + f" | {failed} | "
            + ("yes" if is_well_conditioned(r) else "") + " |"
        )
    summary = checks(results)
    lines += [
        "",
        "## Checks",
        "",
        f"- well-conditioned cells (tilt ≥ 1°, code ≥ 150 px, σ ≤ 1 px): {summary['well_conditioned_cells']}",
        "- max RMSE ÷ CRLB there: "
        + ", ".join(f"{v} {summary['max_rmse_over_crlb'][v]:.3f}" for v in LM_VARIANTS) + " (target ≤ 1.05)",
    ]
    for name in LM_VARIANTS:
        worse = summary["worse_than_peer"][name]
        lines.append(f"- cells where {name} has a larger RMSE than ippe or p4p: {len(worse)} of {len(results) * 2} comparisons")
        for cid, peer, mine, theirs in worse:
            lines.append(f"  - {cid}: {name} {mine * 1000:.3f} mm > {peer} {theirs * 1000:.3f} mm")
    return "\n".join(lines) + "\n"
