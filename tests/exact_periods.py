"""Exact periods (40 digits) that the error estimate is checked against, shared with
`benchmarks/accuracy.py --periods`: the pendulum's, and the asymmetric well's
(V = x²/2 + x³/3, hump 1/6 at x = -1) with its releases up to near the hump."""

import mpmath
import numpy as np
from scipy.optimize import brentq


def pendulum_period(a):
    """The pendulum's period from rest at the float64 `a` (g = r = 1), to 40 digits
    (the AGM in float64 loses ~1e-14 within 1e-3 of π: cos(a/2) is ~5e-4 there)."""
    with mpmath.workdps(40):
        k = mpmath.cos(mpmath.mpf(float(a)) / 2)
        return float(2 * mpmath.pi / mpmath.agm(1, k))


def hump_releases(n, height=0.99):
    """`n` releases from rest in the asymmetric well, on both sides of its bottom, up
    to `height` times the hump's."""
    V = lambda x: 0.5 * x**2 + x**3 / 3
    left = brentq(lambda x: V(x) - height / 6, -1, 0)
    right = brentq(lambda x: V(x) - height / 6, 0, 2)
    half = n // 2
    return np.concatenate(
        [np.linspace(left, -1e-3, half), np.linspace(1e-3, right, n - half)]
    )


def well_period(x0):
    """The asymmetric well's period from rest at the float64 `x0`, to 40 digits.

    E - V = (x - r)(x - a)(b - x)/3 with r < a <= x <= b; x = a + (b - a)(1 - cos φ)/2
    takes the square roots at the turning points out of the integrand:
    T = 2 ∫_0^π dφ / sqrt(2 (x(φ) - r) / 3)."""
    with mpmath.workdps(40):
        x0 = mpmath.mpf(float(x0))
        E = x0**2 / 2 + x0**3 / 3
        cubic = [-mpmath.mpf(1) / 3, -mpmath.mpf(1) / 2, 0, E]
        r, a, b = sorted(mpmath.re(z) for z in mpmath.polyroots(cubic, extraprec=200))
        x = lambda p: a + (b - a) * (1 - mpmath.cos(p)) / 2
        f = lambda p: 1 / mpmath.sqrt(2 * (x(p) - r) / 3)
        return float(2 * mpmath.quad(f, [0, mpmath.pi]))
