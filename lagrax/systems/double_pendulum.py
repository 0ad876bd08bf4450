r"""The planar double pendulum, built from particle positions.

Two masses $m_1$, $m_2$ on massless rods $l_1$, $l_2$; angles $\theta_1$, $\theta_2$
from the downward vertical:

$$r_1 = l_1(\sin\theta_1, -\cos\theta_1),\quad
r_2 = r_1 + l_2(\sin\theta_2, -\cos\theta_2),\quad V = g(m_1y_1 + m_2y_2),$$

and $L = T - V$ from `lagrax.particle_lagrangian`. Small oscillations about the bottom
have the two normal-mode frequencies of `normal_mode_frequencies`.
"""

import jax.numpy as jnp

from .._eom.particles import particle_lagrangian


def positions(*, l1=1.0, l2=1.0):
    r"""$r(q, t)$ of shape `(2, 2)`, rows $r_1$, $r_2$; $q = (\theta_1, \theta_2)$."""

    def r(q, t):
        r1 = l1 * jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])
        r2 = r1 + l2 * jnp.stack([jnp.sin(q[1]), -jnp.cos(q[1])])
        return jnp.stack([r1, r2])

    return r


def lagrangian(*, m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    r"""$L = \frac12 m_1|\dot r_1|^2 + \frac12 m_2|\dot r_2|^2 - g(m_1y_1 + m_2y_2)$ by
    `lagrax.particle_lagrangian`, $q = (\theta_1, \theta_2)$."""
    # (Python numbers become an array through NumPy: no XLA computation to compile.)
    masses = jnp.array([m1, m2], dtype=float)
    return particle_lagrangian(
        masses, positions(l1=l1, l2=l2), lambda r, t: g * jnp.dot(masses, r[:, 1])
    )


def acceleration(q, qdot, t=0.0, *, m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    r"""The hand-derived closed form, with $\Delta = \theta_1 - \theta_2$ and
    $D = 2m_1 + m_2 - m_2\cos 2\Delta$:

    $$\ddot\theta_1 = \frac{-g(2m_1 + m_2)\sin\theta_1 - m_2g\sin(\theta_1 - 2\theta_2)
        - 2m_2\sin\Delta\,(l_2\dot\theta_2^2 + l_1\dot\theta_1^2\cos\Delta)}{l_1D},$$

    $$\ddot\theta_2 = \frac{2\sin\Delta\,\big((m_1 + m_2)(l_1\dot\theta_1^2
        + g\cos\theta_1) + m_2l_2\dot\theta_2^2\cos\Delta\big)}{l_2D}.$$
    """
    t1, t2 = q[0], q[1]
    w1, w2 = qdot[0], qdot[1]
    delta = t1 - t2
    sd, cd = jnp.sin(delta), jnp.cos(delta)
    D = 2 * m1 + m2 - m2 * jnp.cos(2 * delta)
    a1 = (
        -g * (2 * m1 + m2) * jnp.sin(t1)
        - m2 * g * jnp.sin(t1 - 2 * t2)
        - 2 * m2 * sd * (l2 * w2**2 + l1 * w1**2 * cd)
    ) / (l1 * D)
    a2 = (
        2
        * sd
        * ((m1 + m2) * (l1 * w1**2 + g * jnp.cos(t1)) + m2 * l2 * w2**2 * cd)
        / (l2 * D)
    )
    return jnp.stack([a1, a2])


def normal_mode_frequencies(*, m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    r"""The angular frequencies $(\omega_-, \omega_+)$ of small oscillations:

    $$\omega_\pm^2 = g\,\frac{(m_1 + m_2)(l_1 + l_2)
        \pm\sqrt{(m_1 + m_2)\big((m_1 + m_2)(l_1 + l_2)^2 - 4m_1l_1l_2\big)}}
        {2m_1l_1l_2}.$$

    (For $m_1 = m_2$, $l_1 = l_2 = l$: $\omega_\pm^2 = (2 \pm \sqrt2)\,g/l$.)
    """
    M = m1 + m2
    root = jnp.sqrt(M * (M * (l1 + l2) ** 2 - 4 * m1 * l1 * l2))
    w2 = g * (M * (l1 + l2) + jnp.array([-1.0, 1.0]) * root) / (2 * m1 * l1 * l2)
    return jnp.sqrt(w2)
