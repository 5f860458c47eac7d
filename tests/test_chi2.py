"""agvviz.solvers.chi2 against scipy.special (the independent reference it replaces in a run).

Tolerances: the closed forms and Halley's method are accurate to a few ulp of each step;
1e-12 relative leaves room for the exp/log of the tail near 1e-289 (measured worst: 1.2e-13
for chi2_sf, 6e-16 for normal_isf, 6e-15 for chi2_quantile). A run must not import scipy.special.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.special import chdtrc, chdtri, fdtri, gammaincinv, ndtri

from agvviz.solvers import chi2


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 5, 6, 7, 8, 11, 16])
def test_chi2_sf_matches_scipy(dof):
    xs = np.concatenate([np.linspace(1e-3, 80.0, 400), [150.0, 400.0, 900.0, 1300.0]])
    for x in xs:
        reference = float(chdtrc(dof, x))
        assert chi2.chi2_sf(float(x), dof) == pytest.approx(reference, rel=1e-12, abs=0.0)
    assert chi2.chi2_sf(0.0, dof) == 1.0 and chi2.chi2_sf(float("inf"), dof) == 0.0


def test_normal_isf_matches_scipy():
    for p in np.concatenate([np.logspace(-300, -1, 300), np.linspace(0.01, 0.99, 99), [1.0 - 1e-16]]):
        assert chi2.normal_isf(float(p)) == pytest.approx(-float(ndtri(p)), rel=1e-13, abs=1e-15)
    for p in (0.0, 1.0):  # the ends, as scipy: a tail of 1 is −∞ σ, of 0 is +∞ σ
        assert chi2.normal_isf(p) == -float(ndtri(p))


@pytest.mark.parametrize("q", [0.01, 0.1, 0.5, 0.9, 0.99, 1.0 - 1e-3, 0.9999])
def test_chi2_quantile_matches_scipy(q):
    dofs = np.concatenate([np.linspace(0.5, 40.0, 157), [1.0, 2.0, 6.0, 8.0, 100.0]])
    ours = chi2.chi2_quantile(q, dofs)
    reference = 2.0 * gammaincinv(dofs / 2.0, q)
    np.testing.assert_allclose(ours, reference, rtol=1e-12, atol=0.0)
    assert ours.shape == dofs.shape


@pytest.mark.parametrize("q", [1e-6, 0.001, 0.05, 0.3, 0.5, 0.7, 0.9, 0.999, 1.0 - 1e-6])
def test_f_quantile_matches_scipy(q):
    """Both solve I_y(dfn/2, dfd/2) = q to a few ulps; the measured worst is 9e-14 (dfd = 10⁴,
    where log B(a, b) itself carries ≈1e-14), so 1e-12 fails a wrong tail or a lost digit."""
    for dfn in (1, 2, 3, 4, 5, 10, 50, 0.7):
        for dfd in (1, 2, 3, 4, 6, 8, 10, 30, 100, 1000, 10000, 2.5):
            reference = float(fdtri(dfn, dfd, q))
            assert chi2.f_quantile(q, dfn, dfd) == pytest.approx(reference, rel=1e-12, abs=0.0), (dfn, dfd)
    with pytest.raises(ValueError):
        chi2.f_quantile(1.0, 3, 2)


def test_the_flip_constants_are_scipys():
    from agvviz.replay.checks.stage import FLIP_EVIDENCE_D2, FLIP_PERSISTS_D2

    assert FLIP_EVIDENCE_D2 == pytest.approx(float(chdtri(6, 0.01)), rel=1e-14)
    assert FLIP_PERSISTS_D2 == pytest.approx(float(chdtri(6, 0.10)), rel=1e-14)


def test_chi2_sigma_matches_the_scipy_form():
    from agvviz.replay.checks.common import chi2_sigma

    for dof in (2, 3, 6):
        for d2 in (1e-300, 1e-17, 1e-9, 0.5, 4.0, 12.6, 41.0, 200.0, 1200.0):  # tiny d²: a tail of 1.0
            p = float(chdtrc(dof, d2))
            assert chi2_sigma(d2, dof) == pytest.approx(max(0.0, -float(ndtri(p))), rel=1e-12)
    assert chi2_sigma(41.0, 6) == pytest.approx(5.0, abs=0.01)  # the docstring's example


def test_the_run_path_does_not_import_scipy_special():
    code = (
        "import sys; import agvviz.app.run, agvviz.replay.checks.stage, agvviz.solvers.joint; "
        "print(sorted(m for m in sys.modules if m.startswith('scipy.special') or m == 'pyarrow.compute'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
