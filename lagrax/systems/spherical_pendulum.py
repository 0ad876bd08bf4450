r"""The spherical pendulum: mass $m$ on a massless rod of length $l$, swinging in 3-D.

With $\theta$ from the downward vertical and $\phi$ the azimuth,
$r = l(\sin\theta\cos\phi, \sin\theta\sin\phi, -\cos\theta)$ and

$$L = \tfrac12 ml^2(\dot\theta^2 + \sin^2\theta\,\dot\phi^2) + mgl\cos\theta.$$

$p_\phi = ml^2\sin^2\theta\,\dot\phi$ is conserved ($\phi$ is cyclic). A conical
pendulum at constant $\theta_0 \in (0, \pi/2)$ turns at
$\dot\phi^2 = g/(l\cos\theta_0)$.
"""

import jax.numpy as jnp


def positions(*, l=1.0):
    r"""$r(q, t) = l(\sin\theta\cos\phi, \sin\theta\sin\phi, -\cos\theta)$, shape
    `(1, 3)`, for `lagrax.particle_lagrangian` with $V = mgz$."""

    def r(q, t):
        theta, phi = q[0], q[1]
        s = jnp.sin(theta)
        return (
            l * jnp.stack([s * jnp.cos(phi), s * jnp.sin(phi), -jnp.cos(theta)])[None]
        )

    return r


def lagrangian(*, m=1.0, l=1.0, g=1.0):
    r"""$L = \frac12 ml^2(\dot\theta^2 + \sin^2\theta\,\dot\phi^2) + mgl\cos\theta$,
    written by hand, $q = (\theta, \phi)$."""

    def L(q, qdot, t):
        theta = q[0]
        kinetic = qdot[0] ** 2 + jnp.sin(theta) ** 2 * qdot[1] ** 2
        return 0.5 * m * l**2 * kinetic + m * g * l * jnp.cos(theta)

    return L


def acceleration(q, qdot, t=0.0, *, m=1.0, l=1.0, g=1.0):
    r"""The hand-derived equations of motion (off the axis, $\sin\theta \ne 0$):

    $$\ddot\theta = \sin\theta\cos\theta\,\dot\phi^2 - \frac gl\sin\theta,\qquad
    \ddot\phi = -2\frac{\cos\theta}{\sin\theta}\dot\theta\dot\phi.$$
    """
    theta = q[0]
    thetadot, phidot = qdot[0], qdot[1]
    s, c = jnp.sin(theta), jnp.cos(theta)
    return jnp.stack([s * c * phidot**2 - (g / l) * s, -2 * c / s * thetadot * phidot])


def conical_rate(theta0, *, l=1.0, g=1.0):
    r"""$\dot\phi = \sqrt{g/(l\cos\theta_0)}$: the azimuthal rate of the conical
    pendulum at constant $\theta_0 \in (0, \pi/2)$ (from $\ddot\theta = 0$)."""
    return jnp.sqrt(g / (l * jnp.cos(theta0)))
