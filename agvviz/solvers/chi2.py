"""χ² tails and quantiles, the F quantile and the normal quantile, without scipy (issue 27).

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
  standard library's :class:`statistics.NormalDist`), accurate to about 1e-16;
* :func:`f_quantile` — the F(dfn, dfd) quantile (scipy.stats.f.ppf; the planar solver's prior
  test): the regularised incomplete beta function by its continued fraction (modified Lentz,
  Numerical Recipes §6.4), inverted by Newton's method on its logarithm in log x, bracketed.

They agree with scipy to ≈1e-13 relative (tests/test_chi2.py compares them over a grid);
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


def _beta_continued_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of I_x(a, b) (Numerical Recipes §6.4, betacf), modified Lentz;
    it converges fast for x < (a + 1)/(a + b + 2)."""
    c = 1.0
    d = 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (_TINY if abs(d) < _TINY else d)
    h = d
    for m in range(1, _MAX_STEPS):
        for numerator in (
            m * (b - m) * x / ((a - 1.0 + 2 * m) * (a + 2 * m)),
            -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 1.0 + 2 * m)),
        ):
            d = 1.0 + numerator * d
            d = 1.0 / (_TINY if abs(d) < _TINY else d)
            c = 1.0 + numerator / c
            c = _TINY if abs(c) < _TINY else c
            delta = d * c
            h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return h


def _stirling_remainder(x: float) -> float:
    """lgamma(x) − ((x − ½) log x − x + ½ log 2π) for x ≥ 10, by its asymptotic series."""
    x2 = x * x
    return (1.0 / 12.0 - (1.0 / 360.0 - (1.0 / 1260.0 - 1.0 / (1680.0 * x2)) / x2) / x2) / x


def _log_beta(a: float, b: float) -> float:
    """log B(a, b). With the larger argument ≥ 10, lgamma(a + b) − lgamma(b) is written out by
    Stirling's series so that the two large logarithms cancel exactly on paper, not in floats
    (plain lgamma differences lose ≈1e-13 at b = 500)."""
    small, large = min(a, b), max(a, b)
    if large < 10.0:
        return math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
    # lgamma(s + l) − lgamma(l) = (l − ½) log1p(s/l) + s log(s + l) − s + R(s + l) − R(l)
    rise = (large - 0.5) * math.log1p(small / large) + small * math.log(small + large) - small
    rise += _stirling_remainder(small + large) - _stirling_remainder(large)
    return math.lgamma(small) - rise


def _log_beta_tails(a: float, b: float, x: float) -> tuple[float, float]:
    """(log I_x(a, b), log(1 − I_x(a, b))), the regularised incomplete beta function, 0 < x < 1;
    the smaller of I and 1 − I is the one computed directly, so both logarithms keep their
    precision in either tail."""
    log_front = a * math.log(x) + b * math.log1p(-x) - _log_beta(a, b)
    if x < (a + 1.0) / (a + b + 2.0):
        log_lower = log_front + math.log(_beta_continued_fraction(a, b, x) / a)
        return log_lower, math.log1p(-math.exp(log_lower))
    log_upper = log_front + math.log(_beta_continued_fraction(b, a, 1.0 - x) / b)
    return math.log1p(-math.exp(log_upper)), log_upper


def _beta_inverse(a: float, b: float, p: float, upper: bool) -> float:
    """x with I_x(a, b) = p (``upper`` False) or 1 − I_x(a, b) = p (True), 0 < p < 1: Newton's
    method on the logarithm of that tail against u = log x (I ≈ c·x^a near 0, so nearly linear
    there), kept inside a bracket of u, halving it when a step leaves it."""
    log_p = math.log(p)
    low, high = math.log(1e-300), 0.0
    u = math.log(0.5)
    log_beta = _log_beta(a, b)
    for _ in range(_MAX_STEPS):
        x = math.exp(u)
        if x >= 1.0:
            u = 0.5 * (low + high)
            continue
        log_tail = _log_beta_tails(a, b, x)[1 if upper else 0]
        error = log_tail - log_p
        if (error > 0.0) != upper:  # the lower tail grows with u, the upper one shrinks
            high = u
        else:
            low = u
        # d log I / d u = x · x^(a−1) (1−x)^(b−1) / B(a, b) / I; of the upper tail: −(same)/(1 − I)
        log_slope = a * u + (b - 1.0) * math.log1p(-x) - log_beta - log_tail
        slope = (-1.0 if upper else 1.0) * math.exp(log_slope) if -700.0 < log_slope < 700.0 else 0.0
        new_u = u - error / slope if slope != 0.0 else math.nan
        if not low < new_u < high:  # (NaN included)
            new_u = 0.5 * (low + high)
        if abs(new_u - u) <= 4.0 * _EPS * max(1.0, abs(u)):
            return math.exp(new_u)
        u = new_u
    return math.exp(u)


def f_quantile(q: float, dfn: float, dfd: float) -> float:
    """The F(dfn, dfd) quantile ``q``, 0 < q < 1 (scipy.stats.f.ppf(q, dfn, dfd)).

    P(F ≤ x) = I_y(dfn/2, dfd/2) with y = dfn·x / (dfn·x + dfd), so x = dfd·y / (dfn·(1 − y)),
    and 1 − y solves I_(1−y)(dfd/2, dfn/2) = 1 − q. Whichever of y and 1 − y is below ½ is
    solved for (the other is 1 − it without loss), each from the tail that q or 1 − q is small in."""
    if not 0.0 < q < 1.0:
        raise ValueError(f"q must lie in (0, 1), got {q}")
    if not (dfn > 0.0 and dfd > 0.0):
        raise ValueError(f"degrees of freedom must be positive, got {dfn} and {dfd}")
    a, b = 0.5 * dfn, 0.5 * dfd
    y = _beta_inverse(a, b, q, upper=False) if q <= 0.5 else _beta_inverse(a, b, 1.0 - q, upper=True)
    if y <= 0.5:
        w = 1.0 - y
    else:
        w = _beta_inverse(b, a, 1.0 - q, upper=False) if q >= 0.5 else _beta_inverse(b, a, q, upper=True)
        y = 1.0 - w
    return dfd * y / (dfn * w)
