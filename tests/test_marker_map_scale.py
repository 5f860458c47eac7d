"""Issue 23: a 200 000-marker map must not need an n × n array. The unmapped-code tolerance
(agvviz.recording.contract.unmapped_tolerance_m) and the nearest-mapped-code distance of
payload_map_problem come from a k-d tree now (issue 27: numpy up to SMALL_MAP_CODES codes, so a
run on a small map does not import scipy.spatial); on small maps they equal the brute-force
pairwise formula they replace (written out here, independently)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from agvviz.recording import checks
from agvviz.recording.checks import (
    CentreIndex,
    QrMap,
    UNMAPPED_CODE_SPACINGS,
    payload_map_problem,
    qr_map_of,
    unmapped_tolerance_m,
)


def _square(centre: np.ndarray, side_m: float) -> np.ndarray:
    h = side_m / 2
    return centre + np.array([[-h, -h, 0.0], [-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0]])


def _random_map(rng: np.random.Generator, n: int, extent_m: float) -> dict[str, np.ndarray]:
    return {f"Q{i:03d}": _square(np.array([*rng.uniform(-extent_m, extent_m, 2), rng.uniform(0, 3)]), 0.3)
            for i in range(n)}


def _pairwise_tolerance_m(qr_map: dict[str, np.ndarray]) -> float:
    """The formula before issue 23: the full n × n distance matrix of the centres."""
    centres = np.array([c.mean(axis=0) for c in qr_map.values()])
    spacing = 0.0
    if len(centres) > 1:
        d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
        np.fill_diagonal(d, np.inf)
        spacing = float(d.min(axis=1).max())
    return max(1.0, UNMAPPED_CODE_SPACINGS * spacing)


@pytest.mark.parametrize("seed", range(8))
def test_tolerance_equals_the_pairwise_formula_on_small_maps(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    extent = float(rng.choice([0.5, 5.0, 50.0]))  # spacings below and above the 1 m floor
    plain = _random_map(rng, n, extent)
    want = _pairwise_tolerance_m(plain)
    # float64 distances, summed in a different order by the tree: a few ulps at most
    assert unmapped_tolerance_m(plain) == pytest.approx(want, rel=1e-12)
    assert unmapped_tolerance_m(QrMap(plain)) == pytest.approx(want, rel=1e-12)


def test_duplicate_centres_give_zero_spacing_as_before():
    corners = _square(np.array([3.0, 4.0, 0.0]), 0.5)
    qr_map = {"A": corners, "B": corners.copy(), "C": _square(np.array([3.2, 4.0, 0.0]), 0.5)}
    assert unmapped_tolerance_m(qr_map) == pytest.approx(_pairwise_tolerance_m(qr_map), rel=1e-12)


def test_unmapped_code_distance_is_to_the_nearest_mapped_centre():
    rng = np.random.default_rng(5)
    qr_map = QrMap(_random_map(rng, 40, 20.0))
    centres = np.array([c.mean(axis=0) for c in qr_map.values()])
    for _ in range(20):
        vertices = _square(np.array([*rng.uniform(-40, 40, 2), 0.0]), 0.3)
        nearest = float(np.min(np.linalg.norm(centres - vertices.mean(axis=0), axis=1)))
        problem = payload_map_problem("NEW", vertices, qr_map, unmapped_tol_m=1.0)
        assert (problem is None) == (nearest <= 1.0)
        if problem:
            assert f"puts it {nearest:.1f} m from the nearest mapped code" in problem


def test_a_200_000_code_map_is_quick_and_small():
    """Bench line (not a timing assertion): the tree over 200 000 centres. The old formula
    needed 200 000² × 3 float64 ≈ 900 GiB."""
    rng = np.random.default_rng(23)
    n = 200_000
    centres = np.column_stack([rng.uniform(0, 2000, n), rng.uniform(0, 2000, n), np.zeros(n)])
    offsets = np.array([[-0.1, -0.1, 0.0], [-0.1, 0.1, 0.0], [0.1, 0.1, 0.0], [0.1, -0.1, 0.0]])
    marker_map = {"dictionary": "qr", "markers": [
        {"id": f"Q{i}", "corners_world_m": (c + offsets).tolist()} for i, c in enumerate(centres)]}
    start = time.perf_counter()
    qr_map = qr_map_of(marker_map)
    tol = unmapped_tolerance_m(qr_map)
    problem = payload_map_problem("NEW", offsets + [5000.0, 5000.0, 0.0], qr_map, tol)
    elapsed = time.perf_counter() - start
    print(f"\nbench: 200 000-code map: qr_map_of + unmapped_tolerance_m + one unmapped check in {elapsed:.2f} s "
          f"(tolerance {tol:.2f} m)")
    assert len(qr_map) == n and tol > 1.0 and problem is not None and "not in the marker map" in problem


@pytest.mark.parametrize("seed", range(3))
def test_numpy_search_and_tree_give_the_same_distances(seed, monkeypatch):
    """The small-map numpy search (blocks of rows) and the k-d tree return equal distances: each
    code's nearest neighbour and a point's nearest centre, duplicates included."""
    rng = np.random.default_rng(seed)
    plain = _random_map(rng, 700, 30.0)  # more rows than one numpy block
    plain["DUP"] = plain["Q007"].copy()
    monkeypatch.setattr(checks, "SMALL_MAP_CODES", 10**9)
    by_numpy = CentreIndex(plain)
    monkeypatch.setattr(checks, "SMALL_MAP_CODES", 0)
    by_tree = CentreIndex(plain)
    assert by_numpy._tree is None and by_tree._tree is not None
    np.testing.assert_allclose(
        by_numpy.nearest_neighbour_distances_m(), by_tree.nearest_neighbour_distances_m(), rtol=1e-12, atol=0
    )
    for point in rng.uniform(-60, 60, (20, 3)):
        assert by_numpy.nearest_distance_m(point) == pytest.approx(by_tree.nearest_distance_m(point), rel=1e-12)


def test_a_small_map_does_not_import_scipy_spatial():
    """A run on a small map (every scenario's) pays no scipy.spatial import (issue 27)."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from agvviz.recording.checks import QrMap, unmapped_tolerance_m, payload_map_problem\n"
        "m = QrMap({f'Q{i}': np.eye(4, 3) + i for i in range(50)})\n"
        "unmapped_tolerance_m(m); payload_map_problem('NEW', np.eye(4, 3) + 99, m)\n"
        "print('scipy.spatial' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
