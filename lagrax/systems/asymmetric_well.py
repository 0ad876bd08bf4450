r"""An asymmetric well: mass $m$ in the potential $V = \frac12 k x^2 + \frac13 a x^3$.

$$L = \tfrac12 m\dot x^2 - \tfrac12 k x^2 - \tfrac13 a x^3,
\qquad m\ddot x = -kx - ax^2.$$

For $a > 0$ the well at $x = 0$ is steeper on the right than on the left, where it ends
in a barrier at $x_b = -k/a$ of height $V_b = k^3/(6a^2)$: released from rest at
$x_0$ with $V(x_0) < V_b$ (and on the near side of the barrier) the motion oscillates
between $x_0$ and a turning point that is not $-x_0$; above the barrier it escapes. The
period has no closed form (an elliptic integral of the cubic); its small-amplitude
expansion is $T = T_0\,(1 + \frac{5}{12}\frac{a^2 x_0^2}{k^2} + O(x_0^3))$ with
$T_0 = 2\pi\sqrt{m/k}$ (Landau & Lifshitz, Mechanics §28). The test oracle for
`lagrax.quadrature_period` and periods by simulation.
"""

import jax.numpy as jnp

from ._sweep_spec import SweepSpec


def lagrangian(*, m=1.0, k=1.0, a=1.0):
    r"""$L = \frac12 m\dot x^2 - \frac12 k x^2 - \frac13 a x^3$, with $q = (x,)$."""

    def L(q, qdot, t):
        x = q[0]
        return 0.5 * m * qdot[0] ** 2 - 0.5 * k * x**2 - a * x**3 / 3

    return L


def potential(x, *, k=1.0, a=1.0):
    r"""$V(x) = \frac12 k x^2 + \frac13 a x^3$."""
    return 0.5 * k * x**2 + a * x**3 / 3


def acceleration(q, qdot=None, t=0.0, *, m=1.0, k=1.0, a=1.0):
    r"""The hand-derived equation of motion $\ddot x = -(kx + ax^2)/m$.

    Elementwise in `q`; `qdot` and `t` do not enter (they may be left out)."""
    return -(k * q + a * q**2) / m


def barrier(*, k=1.0, a=1.0):
    r"""The barrier top $(x_b, V_b) = (-k/a, k^3/(6a^2))$; oscillation needs $V < V_b$.

    (For $a > 0$; the barrier is then on the left of the well.)
    """
    return -k / a, k**3 / (6 * a**2)


def small_amplitude_period(*, m=1.0, k=1.0):
    r"""$T_0 = 2\pi\sqrt{m/k}$, the limit of the period as the amplitude goes to 0."""
    return 2 * jnp.pi * jnp.sqrt(jnp.asarray(m) / k)


def period_expansion(x0, *, m=1.0, k=1.0, a=1.0):
    r"""$T \approx T_0(1 + \frac{5}{12} a^2 x_0^2 / k^2)$: the period to second order in
    the release point $x_0$ (relative error $O(x_0^3)$)."""
    x0 = jnp.asarray(x0)
    return small_amplitude_period(m=m, k=k) * (1 + 5 * a**2 * x0**2 / (12 * k**2))


def _sweep_range(*, k=1.0, a=1.0):
    # Release points up to 0.98 of x0 = k/(2a), where the far turning point reaches
    # the barrier's height; no default range for a well without a barrier.
    if k > 0 and a > 0:
        return 1e-3 * k / a, 0.49 * k / a
    return None


SWEEP = SweepSpec("asymmetric well", "x₀", amplitudes=_sweep_range)
