r"""Huygens' cycloidal pendulum: a bob of mass $m$ on an inverted cycloid of radius $R$.

In Huygens' coordinate $\theta$ (the angle the generating circle has rolled; cusp at
$\theta = 0$, lowest point at $\theta = \pi$),
$x = R(\theta - \sin\theta)$, $z = R(1 - \cos\theta)$ (downwards) and

$$L = mR^2\dot\theta^2(1 - \cos\theta) - mgR(1 + \cos\theta),$$

whose mass $2mR^2(1 - \cos\theta)$ vanishes at the cusp. With $u = \cos(\theta/2)$ the
same system is the harmonic oscillator $L = 8mR^2\dot u^2 - 2mgRu^2$,
$\ddot u = -(g/4R)u$, regular everywhere: the period is $4\pi\sqrt{R/g}$ for every
amplitude, the cusp included.
"""

import math

import jax.numpy as jnp
import numpy as np

from .._checks import positive_array
from ._sweep_spec import SweepSpec


def lagrangian(*, m=1.0, R=1.0, g=1.0):
    r"""$L = mR^2\dot\theta^2(1 - \cos\theta) - mgR(1 + \cos\theta)$, $q = (\theta,)$.

    Written as $2mR^2\dot\theta^2\sin^2(\theta/2) - 2mgR\cos^2(\theta/2)$: the same
    function without the cancellation of $1 - \cos\theta$ near the cusp (which is
    exactly 0 in float64 for $|\theta| < 10^{-8}$).
    """

    def L(q, qdot, t):
        s = jnp.sin(q[0] / 2)
        c = jnp.cos(q[0] / 2)
        return 2 * m * R**2 * qdot[0] ** 2 * s**2 - 2 * m * g * R * c**2

    return L


def lagrangian_u(*, m=1.0, R=1.0, g=1.0):
    r"""The same pendulum in $u = \cos(\theta/2)$: $L = 8mR^2\dot u^2 - 2mgRu^2$.

    $u = 0$ at the bottom, $u = \pm 1$ at the cusps; regular everywhere.
    """

    def L(q, qdot, t):
        return 8 * m * R**2 * qdot[0] ** 2 - 2 * m * g * R * q[0] ** 2

    return L


def acceleration(q, qdot, t=0.0, *, m=1.0, R=1.0, g=1.0):
    r"""The equation of motion in $\theta$,

    $$2R\ddot\theta\sin(\theta/2) + R\dot\theta^2\cos(\theta/2) - g\cos(\theta/2) = 0,$$

    solved for $\ddot\theta$ (valid off the cusp). Elementwise in `q`, `qdot` (shape
    `(1,)`, or the scalars $\theta$, $\dot\theta$); `t` and `m` do not enter.
    """
    return (g - R * qdot**2) * jnp.cos(q / 2) / (2 * R * jnp.sin(q / 2))


def acceleration_u(q, qdot, t=0.0, *, m=1.0, R=1.0, g=1.0):
    r"""The equation of motion in $u = \cos(\theta/2)$: $\ddot u = -(g/4R)\,u$."""
    return -(g / (4 * R)) * q


def period(amplitude=None, *, m=1.0, R=1.0, g=1.0):
    r"""$T = 4\pi\sqrt{R/g}$, independent of the amplitude (broadcast to its shape).

    **Raises:** `TypeError` if `R` or `g` is not real; `ValueError` if either is not
    positive (checked when its value is known, i.e. not under `jit`/`vmap`).
    """
    R = positive_array(R, "R")
    g = positive_array(g, "g")
    T = 4 * jnp.pi * jnp.sqrt(R / g)
    if amplitude is None:
        return T
    return jnp.broadcast_to(T, jnp.shape(amplitude))


def theta_from_u(u):
    r"""$\theta = 2\arccos(u) \in [0, 2\pi]$ for $u \in [-1, 1]$.

    (Maps $u = 1 \to \theta = 0$, the cusp; $u = 0 \to \theta = \pi$, the bottom.)
    """
    return 2 * jnp.arccos(u)


def position(theta, *, R=1.0):
    r"""The bob's position $(x, z) = (R(\theta - \sin\theta), R(1 - \cos\theta))$."""
    return jnp.stack([R * (theta - jnp.sin(theta)), 2 * R * jnp.sin(theta / 2) ** 2])


# Swept in u = cos(θ/2) = sin(a/2), regular at the cusp where the θ form's mass
# vanishes; the amplitude a = π − θ₀ is the angle the generating circle has rolled
# from the bottom (a = π: release at the cusp).
SWEEP = SweepSpec(
    "cycloidal pendulum",
    "a = π − θ₀ (rad)",
    amplitudes=(1e-3, math.pi),
    bounds=(0.0, math.pi),
    method="quarter",
    lagrangian=lagrangian_u,
    release_point=lambda a: np.sin(np.asarray(a) / 2),
    default=True,
)
