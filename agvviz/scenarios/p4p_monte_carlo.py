"""p4p_monte_carlo — paper 000 §6's Monte-Carlo study of P4P vs the manifold LM, plus cells
where the Cramér–Rao bound is the yardstick. Corner observations only, no images.

Paper cells (``cells=paper``; §6.1 and §6.2, figures 3–15): camera f = 1562.5 px, principal
point (0, 0) (pixel coordinates are relative to the principal point, as in the paper's
tables), R = I, t = (0.05, 0.05, z) m with z ∈ {2, 4}; a square code of half-side
h ∈ {0.1333, 0.2667} m; 4 points (vertices) or 8 (vertices and edge midpoints, §6.2);
additive white Gaussian noise at SNR 15, 16, …, 24 dB.

SNR definition (MATLAB ``awgn(x, snr, 'measured')``, which the paper's "dB additive white
Gaussian noise" suggests): the signal power is the mean square of the noise-free pixel
coordinates of the four VERTICES (8 numbers, relative to the principal point), and the
noise on every coordinate of every point has σ² = P / 10^(SNR/10). The 8-point cells use
the σ of their 4-point twin, so 4 and 8 points are compared at equal noise. This definition
reproduces the paper's P4P spread in figure 3 (σ ≈ 19.8 px, std of t3 0.11 m vs the paper's
0.114 m). The σ of every cell is written into each message (``noise_sigma_px``).

CRLB cells (``cells=crlb``): the same camera and t, the code tilted about its x axis by
0°, 30° or 60° (R = Rx(tilt)), geometries (h, z) = (0.2667, 2) — ≈417 px — and
(0.1333, 4) — ≈104 px, σ ∈ {0.25, 0.5, 1, 2} px, 4 or 8 points.

Recorded: the calibration of camera ``mc`` once, then one ``/markers/corners``
(``agvviz.CornerObservations``) message per trial with its cell, trial index, σ, the
marker-frame points and the true ``T_cam_marker``. ``duration_s``/``rate_hz`` do not apply:
nothing moves; ``trials`` sets the sample size.

``realism`` (the error sources of :mod:`agvviz.sim.realism`) accepts only ``ideal``: the study
measures the solvers against its own noise model and the CRLB.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agvviz.model import topics
from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.settings import setting
from agvviz.settings import validate as check_fields
from agvviz.geometry.euler import Rx
from agvviz.geometry.plane import square_points_marker

NAME = "p4p_monte_carlo"
DESCRIPTION = "Paper 000 §6: Monte-Carlo P4P/LM/IPPE/SQPnP study vs the paper's figures 3–15 and the CRLB"

CAM_NAME = "mc"
FOCAL_PX = 1562.5
#: Nominal image size written into the calibration (the study never renders an image).
IMAGE_SIZE_PX = 1024
TRANSLATION_XY_M = (0.05, 0.05)
PAPER_HALF_SIDES_M = (0.1333, 0.2667)
PAPER_DEPTHS_M = (2.0, 4.0)
PAPER_SNR_DB = tuple(range(15, 25))
CRLB_TILTS_DEG = (0.0, 30.0, 60.0)
CRLB_GEOMETRIES = ((0.2667, 2.0), (0.1333, 4.0))
CRLB_SIGMAS_PX = (0.25, 0.5, 1.0, 2.0)
POINT_COUNTS = (4, 8)
START_TIME_NS = 1_700_000_000_000_000_000
TRIAL_PERIOD_NS = 1_000_000



@dataclass(frozen=True)
class Options:
    trials: int = setting(1000, "noisy trials per cell (paper 000 §6: 1000)", min=1, max=100000)
    cells: str = setting("all", "which cells: paper (§6 parameters, SNR 15–24 dB), crlb (tilted views, σ in px) or all")
    realism: str = setting("ideal", "error sources: a solver study keeps the ideal world (its noise is the study's own)", ("ideal",))


@dataclass(frozen=True)
class Cell:
    """One study cell: a true pose, a code, a point count and a noise level."""

    cell_id: str
    kind: str  # "paper" or "crlb"
    half_side_m: float
    depth_m: float
    tilt_deg: float
    n_points: int
    sigma_px: float
    snr_db: float | None  # paper cells only

    @property
    def T_cam_marker(self) -> np.ndarray:
        return se3.make(Rx(math.radians(self.tilt_deg)), [*TRANSLATION_XY_M, self.depth_m])

    @property
    def points_marker_m(self) -> np.ndarray:
        return square_points_marker(2.0 * self.half_side_m, with_midpoints=self.n_points == 8)

    @property
    def code_side_px(self) -> float:
        """Mean side of the code's image (px)."""
        px = project(self.T_cam_marker, square_points_marker(2.0 * self.half_side_m))
        return float(np.mean(np.linalg.norm(np.roll(px, -1, axis=0) - px, axis=1)))


def camera() -> PinholeCamera:
    K = np.array([[FOCAL_PX, 0.0, 0.0], [0.0, FOCAL_PX, 0.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, np.zeros(5), IMAGE_SIZE_PX, IMAGE_SIZE_PX)


def project(T_cam_marker: np.ndarray, points_marker_m: np.ndarray) -> np.ndarray:
    w = se3.transform_points(T_cam_marker, points_marker_m)
    return FOCAL_PX * w[:, :2] / w[:, 2:3]


def sigma_from_snr_px(T_cam_marker: np.ndarray, half_side_m: float, snr_db: float) -> float:
    """σ (px) of SNR ``snr_db``: mean square of the 4 vertices' pixel coordinates / 10^(SNR/10)."""
    px = project(T_cam_marker, square_points_marker(2.0 * half_side_m))
    return float(math.sqrt(np.mean(px**2) / 10.0 ** (snr_db / 10.0)))


def cells(which: str) -> list[Cell]:
    """Every cell of ``which`` ("paper", "crlb" or "all"), in recording order."""
    out = []
    if which in ("paper", "all"):
        for h in PAPER_HALF_SIDES_M:
            for z in PAPER_DEPTHS_M:
                T = se3.make(np.eye(3), [*TRANSLATION_XY_M, z])
                for snr in PAPER_SNR_DB:
                    sigma = sigma_from_snr_px(T, h, snr)
                    for n in POINT_COUNTS:
                        out.append(Cell(f"paper_h{h:g}_z{z:g}_snr{snr}_n{n}", "paper", h, z, 0.0, n, sigma, float(snr)))
    if which in ("crlb", "all"):
        for tilt in CRLB_TILTS_DEG:
            for h, z in CRLB_GEOMETRIES:
                for sigma in CRLB_SIGMAS_PX:
                    for n in POINT_COUNTS:
                        out.append(Cell(f"crlb_tilt{tilt:g}_h{h:g}_z{z:g}_s{sigma:g}_n{n}", "crlb", h, z, tilt, n, sigma, None))
    return out


def validate(options: Options) -> None:
    """Raise ``ValueError`` naming the first impossible option."""
    check_fields(options)
    if options.trials < 1:
        raise ValueError(f"trials must be ≥ 1, got {options.trials}")
    if options.cells not in ("paper", "crlb", "all"):
        raise ValueError(f"cells must be paper, crlb or all, got {options.cells!r}")


def record(writer, options: Options, seed: int, progress: Callable[[int, int], None] | None = None) -> None:
    """Write the calibration and one CornerObservations message per trial.

    Random draws: ``np.random.default_rng(seed)``, one (trials, N, 2) normal block per cell in
    cell order — the same seed and options give identical messages.
    """
    validate(options)
    rng = np.random.default_rng(seed)
    writer.write_calibration(CAM_NAME, camera(), START_TIME_NS)
    study = cells(options.cells)
    total = len(study) * options.trials
    k = 0
    for cell in study:
        points = cell.points_marker_m
        clean_px = project(cell.T_cam_marker, points)
        noise = rng.normal(0.0, cell.sigma_px, (options.trials, len(points), 2))
        truth = cell.T_cam_marker.tolist()
        points_list = points.tolist()
        for trial in range(options.trials):
            message = {
                "cam_name": CAM_NAME,
                "cell": cell.cell_id,
                "trial": trial,
                "noise_sigma_px": cell.sigma_px,
                "markers": [
                    {
                        "id": "M0",
                        "corners_px": (clean_px + noise[trial]).tolist(),
                        "points_marker_m": points_list,
                        "T_cam_marker_truth": truth,
                    }
                ],
            }
            writer.write_json(topics.CORNERS_TOPIC, "agvviz.CornerObservations", message, START_TIME_NS + k * TRIAL_PERIOD_NS)
            k += 1
        if progress is not None:
            progress(k, total)
