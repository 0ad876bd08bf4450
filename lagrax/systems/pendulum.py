r"""The simple pendulum: mass $m$ on a massless rod of length $r$ under gravity $g$.

One coordinate, $\theta$ from the downward vertical:
$L = \frac12 m r^2\dot\theta^2 + m g r\cos\theta$, so
$\ddot\theta + (g/r)\sin\theta = 0$.
Released from rest at amplitude $\theta_0$ its period is
$T = 2\pi\sqrt{r/g}\,/\,\mathrm{AGM}(1, \cos(\theta_0/2))$.
"""

import math

import jax
import jax.numpy as jnp

from .._checks import as_real_promoting_ints, positive_array
from ._sweep_spec import SweepSpec


# "quarter": the well is mirror-symmetric, and stopping at the bottom keeps the
# releases just below the hump well conditioned.
SWEEP = SweepSpec(
    "simple pendulum",
    "θ₀ (rad)",
    amplitudes=(1e-3, math.pi - 1e-3),
    bounds=(0.0, math.pi),
    method="quarter",
    default=True,
)


def lagrangian(*, m=1.0, r=1.0, g=1.0):
    r"""$L = \frac12 m r^2\dot\theta^2 + m g r\cos\theta$ with $q = (\theta,)$."""

    def L(q, qdot, t):
        return 0.5 * m * r**2 * qdot[0] ** 2 + m * g * r * jnp.cos(q[0])

    return L


def acceleration(q, qdot=None, t=0.0, *, m=1.0, r=1.0, g=1.0):
    r"""The hand-derived equation of motion $\ddot\theta = -(g/r)\sin\theta$.

    Elementwise in `q` (shape `(1,)` as everywhere, or any shape); `qdot`, `t` and `m`
    do not enter (`acceleration(theta, r=..., g=...)` is the same call).
    """
    return -(g / r) * jnp.sin(q)


def small_amplitude_period(*, r=1.0, g=1.0):
    r"""$T_0 = 2\pi\sqrt{r/g}$, the limit of the period as the amplitude goes to 0."""
    return 2 * jnp.pi * jnp.sqrt(jnp.asarray(r) / g)


def _agm(a, b, iterations=12):
    # Quadratic convergence: 12 steps take AGM(1, b) to round-off for b >= 1e-300
    # (b = cos(θ₀/2) >= 5e-4 on the sweep's range needs 5). A fixed count keeps the
    # function branch-free under jit, vmap and grad.
    def step(carry, _):
        a, b = carry
        return (0.5 * (a + b), jnp.sqrt(a * b)), None

    (a, b), _ = jax.lax.scan(step, (a, b), None, length=iterations)
    return 0.5 * (a + b)


def period(amplitude, *, m=1.0, r=1.0, g=1.0):
    r"""Exact period of the pendulum released from rest at angle `amplitude`.

    $$T = \frac{2\pi\sqrt{r/g}}{\mathrm{AGM}(1, \cos(\theta_0/2))}$$

    (equivalent to $4\sqrt{r/g}\,K(\sin^2(\theta_0/2))$), accurate to a few ulps in
    float64, differentiable, and elementwise over arrays.

    **Arguments:** `amplitude`: $\theta_0$ in radians (real; integers are promoted to
    float); `r`, `g`: length and gravity, positive; `m` does not enter.

    **Returns:** $T$; `inf` where $|\theta_0| \ge \pi$ (at $\pi$ the bob balances
    forever, beyond it a release from rest is a swing of amplitude $2\pi - |\theta_0|$
    about the other side, not this amplitude).

    **Raises:**

    - `TypeError`: `amplitude`, `r` or `g` is not real (a string, complex, `None`).
    - `ValueError`: `r` or `g` is not positive (checked when its value is known, i.e.
        not under `jit`/`vmap`).
    """
    theta0 = jnp.abs(as_real_promoting_ints(amplitude, "amplitude"))
    r = positive_array(r, "r")
    g = positive_array(g, "g")
    inside = theta0 < jnp.pi
    b = jnp.cos(jnp.where(inside, theta0, 0.0) / 2)
    T = small_amplitude_period(r=r, g=g) / _agm(jnp.ones_like(b), b)
    return jnp.where(inside, T, jnp.inf)
