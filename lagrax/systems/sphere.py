r"""A particle on a sphere ($n = 2$), and held by an arm from a pole ($n = 1$).

A particle of mass $m$ on the sphere $|r| = R$ (centre at the origin, gravity $g$ along
$-z$) needs two coordinates, the polar angle $\theta$ from the north pole $(0, 0, R)$
and the azimuth $\phi$:

$$r = R(\sin\theta\cos\phi, \sin\theta\sin\phi, \cos\theta),\qquad
L = \tfrac12 mR^2(\dot\theta^2 + \sin^2\theta\,\dot\phi^2) - mgR\cos\theta.$$

Held by a massless arm of length $l$ ($0 < l < 2R$) anchored at the north pole, it
keeps to the circle of latitude $z_0 = R - l^2/2R$, of radius
$\rho = l\sqrt{1 - l^2/4R^2}$: one coordinate, the azimuth $\phi$, and
$L = \frac12 m\rho^2\dot\phi^2$ (constant height, so gravity does no work).
"""

import jax.numpy as jnp

from .._eom.particles import particle_lagrangian


def positions(*, R=1.0):
    r"""$r(q, t) = R(\sin\theta\cos\phi, \sin\theta\sin\phi, \cos\theta)$, $q = (\theta,
    \phi)$, shape `(1, 3)`."""

    def r(q, t):
        theta, phi = q[0], q[1]
        s = jnp.sin(theta)
        return R * jnp.stack([s * jnp.cos(phi), s * jnp.sin(phi), jnp.cos(theta)])[None]

    return r


def constraints(*, R=1.0):
    r"""One constraint, $f(r, t) = (|r|^2 - R^2,)$: the sphere."""

    def f(r, t):
        return jnp.stack([jnp.sum(r[0] ** 2) - R**2])

    return f


def lagrangian(*, m=1.0, R=1.0, g=0.0):
    r"""$L = \frac12 mR^2(\dot\theta^2 + \sin^2\theta\,\dot\phi^2) - mgR\cos\theta$,
    built by `lagrax.particle_lagrangian` from `positions` and $V = mgz$."""
    masses = jnp.reshape(jnp.asarray(m, dtype=float), (1,))
    return particle_lagrangian(
        masses, positions(R=R), lambda r, t: masses[0] * g * r[0, 2]
    )


def acceleration(q, qdot, t=0.0, *, m=1.0, R=1.0, g=0.0):
    r"""The hand-derived equations of motion, $q = (\theta, \phi)$ (off the poles):

    $$\ddot\theta = \sin\theta\cos\theta\,\dot\phi^2 + \frac gR\sin\theta,\qquad
    \ddot\phi = -2\frac{\cos\theta}{\sin\theta}\dot\theta\dot\phi.$$
    """
    theta = q[0]
    thetadot, phidot = qdot[0], qdot[1]
    s, c = jnp.sin(theta), jnp.cos(theta)
    return jnp.stack([s * c * phidot**2 + (g / R) * s, -2 * c / s * thetadot * phidot])


def great_circle(t, r0, v0):
    r"""Exact free motion on a sphere ($g = 0$): a great circle at constant speed.

    $$r(t) = r_0\cos\omega t + \frac{v_0}{\omega}\sin\omega t,\qquad
    \omega = |v_0|/|r_0|,$$

    for $r_0$ on the sphere and $v_0 \ne 0$ tangent to it ($r_0\cdot v_0 = 0$).

    **Arguments:** `t`: times (any shape); `r0`, `v0`: shape `(3,)`.

    **Returns:** positions of shape `t.shape + (3,)`.
    """
    t = jnp.asarray(t)
    omega = jnp.linalg.norm(v0) / jnp.linalg.norm(r0)
    return jnp.multiply.outer(jnp.cos(omega * t), r0) + jnp.multiply.outer(
        jnp.sin(omega * t), v0 / omega
    )


def arm_height(*, R=1.0, l=1.0):
    r"""$z_0 = R - l^2/2R$, the height of the circle the arm allows."""
    return R - l**2 / (2 * R)


def arm_radius(*, R=1.0, l=1.0):
    r"""$\rho = l\sqrt{1 - l^2/4R^2}$, the radius of that circle."""
    return l * jnp.sqrt(1 - l**2 / (4 * R**2))


def arm_positions(*, R=1.0, l=1.0):
    r"""$r(q, t) = (\rho\cos\phi, \rho\sin\phi, z_0)$, $q = (\phi,)$, shape `(1, 3)`."""
    z0 = arm_height(R=R, l=l)
    rho = arm_radius(R=R, l=l)

    def r(q, t):
        phi = q[0]
        return jnp.stack([rho * jnp.cos(phi), rho * jnp.sin(phi), z0 + 0 * phi])[None]

    return r


def arm_constraints(*, R=1.0, l=1.0):
    r"""Two constraints: the sphere and the arm from the north pole $P = (0, 0, R)$,

    $f(r, t) = (|r|^2 - R^2,\ |r - P|^2 - l^2)$."""

    def f(r, t):
        pole = jnp.array([0.0, 0.0, R], dtype=r.dtype)
        return jnp.stack(
            [jnp.sum(r[0] ** 2) - R**2, jnp.sum((r[0] - pole) ** 2) - l**2]
        )

    return f


def arm_lagrangian(*, m=1.0, R=1.0, l=1.0, g=0.0):
    r"""$L = \frac12 m\rho^2\dot\phi^2 - mgz_0$, built by `particle_lagrangian`."""
    masses = jnp.reshape(jnp.asarray(m, dtype=float), (1,))
    return particle_lagrangian(
        masses, arm_positions(R=R, l=l), lambda r, t: masses[0] * g * r[0, 2]
    )


def arm_acceleration(q, qdot, t=0.0, *, m=1.0, R=1.0, l=1.0, g=0.0):
    r"""The hand-derived equation of motion on the arm's circle: $\ddot\phi = 0$."""
    return jnp.zeros_like(qdot)
