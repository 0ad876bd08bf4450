r"""A bead on a hoop of radius $R$ spun about its vertical diameter at rate $\Omega$.

The embedding depends on time explicitly: with $\theta$ from the bottom of the hoop,

$$r(\theta, t) = R(\sin\theta\cos\Omega t, \sin\theta\sin\Omega t, -\cos\theta),\qquad
L = \tfrac12 mR^2(\dot\theta^2 + \Omega^2\sin^2\theta) + mgR\cos\theta.$$

The energy $T + V$ is not conserved (the motor driving the hoop does work) but the
Jacobi integral $h = \frac12 mR^2(\dot\theta^2 - \Omega^2\sin^2\theta) - mgR\cos\theta$
is. For $\Omega^2 > g/R$ the bottom is unstable and the bead settles about
$\cos\theta^* = g/(R\Omega^2)$.
"""

import jax.numpy as jnp

from .._eom.particles import particle_lagrangian


def positions(*, R=1.0, Omega=1.0):
    r"""$r(q, t) = R(\sin\theta\cos\Omega t, \sin\theta\sin\Omega t, -\cos\theta)$,
    shape `(1, 3)`: explicit time."""

    def r(q, t):
        theta = q[0]
        s = jnp.sin(theta)
        angle = Omega * t
        return (
            R
            * jnp.stack([s * jnp.cos(angle), s * jnp.sin(angle), -jnp.cos(theta)])[None]
        )

    return r


def constraints(*, R=1.0, Omega=1.0):
    r"""Two time-dependent constraints: on the sphere $|r| = R$, and in the hoop's plane
    $r\cdot n(t) = 0$ with normal $n(t) = (-\sin\Omega t, \cos\Omega t, 0)$."""

    def f(r, t):
        angle = Omega * t
        normal = jnp.stack([-jnp.sin(angle), jnp.cos(angle), jnp.zeros_like(angle)])
        return jnp.stack([jnp.sum(r[0] ** 2) - R**2, jnp.dot(r[0], normal)])

    return f


def lagrangian(*, m=1.0, R=1.0, Omega=1.0, g=1.0):
    r"""$L = \frac12 m|\dot r|^2 - mgz$ by `lagrax.particle_lagrangian` from the
    rotating `positions`, $q = (\theta,)$."""
    masses = jnp.reshape(jnp.asarray(m, dtype=float), (1,))
    return particle_lagrangian(
        masses, positions(R=R, Omega=Omega), lambda r, t: masses[0] * g * r[0, 2]
    )


def acceleration(q, qdot, t=0.0, *, m=1.0, R=1.0, Omega=1.0, g=1.0):
    r"""The hand-derived equation of motion
    $\ddot\theta = \sin\theta\,(\Omega^2\cos\theta - g/R)$."""
    theta = q[0]
    return jnp.stack([jnp.sin(theta) * (Omega**2 * jnp.cos(theta) - g / R)])


def jacobi_integral(q, qdot, *, m=1.0, R=1.0, Omega=1.0, g=1.0):
    r"""The conserved Jacobi integral
    $h = \frac12 mR^2(\dot\theta^2 - \Omega^2\sin^2\theta) - mgR\cos\theta$."""
    theta = q[0]
    return 0.5 * m * R**2 * (
        qdot[0] ** 2 - Omega**2 * jnp.sin(theta) ** 2
    ) - m * g * R * jnp.cos(theta)


def equilibrium(*, R=1.0, Omega=1.0, g=1.0):
    r"""The stable equilibrium $\theta^* \ge 0$: $\arccos(g/R\Omega^2)$ when
    $R\Omega^2 > g$, else the bottom, $0$."""
    ratio = g / (R * jnp.asarray(Omega, dtype=float) ** 2)
    return jnp.where(ratio < 1, jnp.arccos(jnp.minimum(ratio, 1.0)), 0.0)


def small_oscillation_frequency(*, R=1.0, Omega=1.0, g=1.0):
    r"""The angular frequency of small oscillations about the stable equilibrium:
    $\sqrt{g/R - \Omega^2}$ about the bottom when $\Omega^2 < g/R$, else
    $\Omega\sin\theta^* = \sqrt{\Omega^2 - g^2/(R^2\Omega^2)}$."""
    Omega2 = jnp.asarray(Omega, dtype=float) ** 2
    return jnp.where(
        Omega2 < g / R,
        jnp.sqrt(jnp.abs(g / R - Omega2)),
        jnp.sqrt(jnp.abs(Omega2 - (g / R) ** 2 / Omega2)),
    )
