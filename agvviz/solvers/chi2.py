"""χ² tails and quantiles, and the normal quantile, without scipy (issue 27).

A run needs three of scipy.special's functions (the joint solve's χ² outlier limit, the check
stage's σ scale); importing scipy.special costs ≈0.25 s of every run's start (it pulls in
numpy.f2py and numpy.testing through scipy's array-API layer). These are the textbook forms:

* :func:`chi2_sf` — the upper tail of χ²_dof for an integer dof, in closed form (even dof: a
  Poisson sum; odd dof: erfc plus a finite sum; Abramowitz & Stegun 26.4.4–26.4.5);
* :func:`chi2_quantile` — the χ² quantile for any dof > 0, as scipy.stats.chi2.ppf defines it
  (2·P⁻¹(dof/2, q)): Halley's method on the regularised incomplete gamma function, computed by
  its series below a + 1 and by its continued fraction (modified Lentz) above (Numerical
  Recipes §6.2), started from the Wilson–Hilferty approximation;
* :func:`normal_isf` — the normal upper-tail quantile, −Φ⁻¹(p) by Wichura's AS 241 (the
  standard library's :class:`statistics.NormalDist`), accurate to about 1e-16.

They agree with scipy.special to ≈1e-13 relative (tests/test_chi2.py compares them over a grid);
a value is not bit-identical to scipy's. Pure maths: no I/O.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np

_STANDARD_NORMAL = NormalDist()
_EPS = 1e-16
_TINY = 1e-300
_MAX_STEPS = 500


def chi2_sf(x: float, dof: int) -> float:
    """P(χ²_dof > x) for an integer ``dof`` ≥ 1 (scipy.special.chdtrc(dof, x))."""
    dof = int(dof)
    if dof < 1:
        raise ValueError(f"dof must be a positive integer, got {dof}")
    if not x > 0.0:
        return 1.0
    if math.isinf(x):
        return 0.0
    half = 0.5 * x
    if dof % 2 == 0:  # e^(−x/2) Σ_{k<dof/2} (x/2)^k / k!
        term, total = 1.0, 1.0
        for k in range(1, dof // 2):
            term *= half / k
            total += term
        return math.exp(-half + math.log(total))
    # erfc(√(x/2)) + √(2x/π) e^(−x/2) Σ_{k=1}^{(dof−1)/2} x^(k−1) / (3·5·…·(2k−1))
    tail = math.erfc(math.sqrt(half))
    if dof == 1:
        return tail
    term, total = 1.0, 1.0
    for k in range(2, (dof - 1) // 2 + 1):
        term *= x / (2 * k - 1)
        total += term
    return tail + math.exp(-half + math.log(total) + 0.5 * math.log(2.0 * x / math.pi))


def normal_isf(p: float) -> float:
    """The z with P(N(0,1) > z) = p (−scipy.special.ndtri(p)): −∞ at p = 1, +∞ at p = 0."""
    if p >= 1.0:
        return -math.inf
    if p <= 0.0:
        return math.inf
    return -_STANDARD_NORMAL.inv_cdf(p)


def _gamma_p_q(a: float, x: float) -> tuple[float, float]:
    """(P(a, x), Q(a, x)), the regularised lower and upper incomplete gamma functions, each
    computed directly where it is the smaller (no cancellation in the tail that matters)."""
    if x <= 0.0:
        return 0.0, 1.0
    log_front = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1.0:  # series for P
        term = total = 1.0 / a
        ap = a
        for _ in range(_MAX_STEPS):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) < abs(total) * _EPS:
                break
        p = math.exp(log_front + math.log(total))
        return p, 1.0 - p
    # continued fraction for Q (modified Lentz)
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, _MAX_STEPS):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = _TINY if abs(d) < _TINY else d
        c = b + an / c
        c = _TINY if abs(c) < _TINY else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    q = math.exp(log_front + math.log(h))
    return 1.0 - q, q


def _gamma_p_inverse(a: float, q: float) -> float:
    """x with P(a, x) = q, 0 < q < 1 (scipy.special.gammaincinv(a, q))."""
    upper = 1.0 - q  # the target in the form that is computed directly in the tail
    dof = 2.0 * a
    z = normal_isf(upper) if 0.0 < upper < 1.0 else 0.0
    wilson_hilferty = dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3
    x = max(0.5 * wilson_hilferty, 1e-3 * a, 1e-300)
    log_gamma = math.lgamma(a)
    for _ in range(100):
        p, q_now = _gamma_p_q(a, x)
        error = (p - q) if p < 0.5 else (upper - q_now)  # P − q, from the smaller of P and Q
        density = math.exp(-x + (a - 1.0) * math.log(x) - log_gamma)  # dP/dx
        if density == 0.0:
            break
        step = error / density
        # Halley: f''/f' = (a − 1)/x − 1
        step /= max(0.5, min(2.0, 1.0 - 0.5 * step * ((a - 1.0) / x - 1.0)))
        new_x = x - step
        if new_x <= 0.0:
            new_x = 0.5 * x
        if abs(new_x - x) <= 4.0 * _EPS * new_x:
            return new_x
        x = new_x
    return x


def chi2_quantile(q: float, dofs) -> np.ndarray:
    """The χ² quantile ``q`` (0 < q < 1) for each of ``dofs`` (> 0, not necessarily integer):
    scipy.stats.chi2.ppf(q, dofs), i.e. 2·gammaincinv(dof/2, q)."""
    dofs = np.asarray(dofs, dtype=float)
    out = np.array([2.0 * _gamma_p_inverse(0.5 * dof, q) for dof in dofs.reshape(-1)], dtype=float)
    return out.reshape(dofs.shape)
