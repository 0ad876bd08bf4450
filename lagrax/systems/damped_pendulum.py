r"""A pendulum in air: drag as a Cartesian force on the bob, or as a Rayleigh function.

Mass $m$ on a rod of length $l$, $\theta$ from the downward vertical,
$r = l(\sin\theta, -\cos\theta)$ and $L = \frac12 ml^2\dot\theta^2 + mgl\cos\theta$.
The air pushes on the bob with $F = -b\dot r - c|\dot r|\dot r$ (linear and quadratic
drag). Kept apart from $L$, it enters as a generalized force either way:

$$Q = \frac{\partial r}{\partial\theta}\cdot F
= -bl^2\dot\theta - cl^3|\dot\theta|\dot\theta
= -\frac{\partial R}{\partial\dot\theta},\qquad
R = \tfrac12 bl^2\dot\theta^2 + \tfrac13 cl^3|\dot\theta|^3,$$

so $\ddot\theta = -(g/l)\sin\theta - (b/m)\dot\theta - (cl/m)|\dot\theta|\dot\theta$.
"""

import jax.numpy as jnp

from .._eom.particles import dissipation_force, generalized_force, particle_lagrangian


def positions(*, l=1.0):
    r"""$r(q, t) = l(\sin\theta, -\cos\theta)$, shape `(1, 2)`."""

    def r(q, t):
        return l * jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])[None]

    return r


def lagrangian(*, m=1.0, l=1.0, g=1.0):
    r"""$L = \frac12 m|\dot r|^2 - mgy$ by `lagrax.particle_lagrangian`,
    $q = (\theta,)$."""
    masses = jnp.reshape(jnp.asarray(m, dtype=float), (1,))
    return particle_lagrangian(
        masses, positions(l=l), lambda r, t: masses[0] * g * r[0, 1]
    )


def _speed(v):
    # |v| with a zero (not NaN) derivative at v = 0, for gradients through the drag.
    s = jnp.sum(v * v, axis=-1, keepdims=True)
    positive = s > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, s, 1.0)), 0.0)


def air_drag(*, b=0.0, c=0.0):
    r"""The Cartesian drag $F(r, v, t) = -bv - c|v|v$, shape `(N, d)`."""

    def F(r, v, t):
        return -b * v - c * _speed(v) * v

    return F


def drag_force(*, l=1.0, b=0.0, c=0.0):
    r"""The drag as a generalized force, $Q = (\partial r/\partial\theta)^\top F$, by
    `lagrax.generalized_force` from the Cartesian `air_drag`."""
    return generalized_force(positions(l=l), air_drag(b=b, c=c))


def rayleigh_function(*, l=1.0, b=0.0, c=0.0):
    r"""$R(q, \dot q, t) = \frac12 bl^2\dot\theta^2 + \frac13 cl^3|\dot\theta|^3$,
    written by hand in the coordinate."""

    def R(q, qdot, t):
        w = qdot[0]
        return 0.5 * b * l**2 * w**2 + c * l**3 * jnp.abs(w) ** 3 / 3

    return R


def rayleigh_force(*, l=1.0, b=0.0, c=0.0):
    r"""The same drag as $Q = -\partial R/\partial\dot q$, by
    `lagrax.dissipation_force`."""
    return dissipation_force(rayleigh_function(l=l, b=b, c=c))


#: The module's non-conservative force, under the name every system module uses.
force = drag_force


def acceleration(q, qdot, t=0.0, *, m=1.0, l=1.0, g=1.0, b=0.0, c=0.0):
    r"""The hand-derived damped equation

    $$\ddot\theta = -\frac gl\sin\theta - \frac bm\dot\theta
        - \frac{cl}{m}|\dot\theta|\dot\theta.$$
    """
    theta, w = q[0], qdot[0]
    return jnp.stack(
        [-(g / l) * jnp.sin(theta) - (b / m) * w - (c * l / m) * jnp.abs(w) * w]
    )
