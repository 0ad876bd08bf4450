r"""A pendulum whose support is shaken: a moving support as explicit time in $r(q, t)$.

Mass $m$ on a rod of length $l$ hung from a support at
$s(t) = (a_x\cos\omega t, a_y\cos\omega t)$; $\theta$ from the downward vertical:

$$r = s(t) + l(\sin\theta, -\cos\theta),\qquad
L = \tfrac12 m|\dot r|^2 - mgy.$$

With a vertical drive ($a_x = 0$, $a_y = a$) fast enough, $a^2\omega^2 > 2gl$, the
inverted position is stable (Kapitza's pendulum).
"""

import jax.numpy as jnp

from .._eom.particles import particle_lagrangian


def positions(*, l=1.0, ax=0.0, ay=0.0, omega=1.0):
    r"""$r(q, t) = (a_x\cos\omega t + l\sin\theta, a_y\cos\omega t - l\cos\theta)$,
    shape `(1, 2)`."""

    def r(q, t):
        theta = q[0]
        c = jnp.cos(omega * t)
        return jnp.stack([ax * c + l * jnp.sin(theta), ay * c - l * jnp.cos(theta)])[
            None
        ]

    return r


def lagrangian(*, m=1.0, l=1.0, g=1.0, ax=0.0, ay=0.0, omega=1.0):
    r"""$L = \frac12 m|\dot r|^2 - mgy$ by `lagrax.particle_lagrangian`,
    $q = (\theta,)$."""
    masses = jnp.reshape(jnp.asarray(m, dtype=float), (1,))
    return particle_lagrangian(
        masses,
        positions(l=l, ax=ax, ay=ay, omega=omega),
        lambda r, t: masses[0] * g * r[0, 1],
    )


def acceleration(q, qdot, t=0.0, *, m=1.0, l=1.0, g=1.0, ax=0.0, ay=0.0, omega=1.0):
    r"""The hand-derived equation of motion: the pendulum in the support's frame, with
    gravity $g + \ddot s_y$ and the inertial force $-m\ddot s_x$,

    $$l\ddot\theta = -(g + \ddot s_y)\sin\theta - \ddot s_x\cos\theta,\qquad
    \ddot s = -\omega^2(a_x, a_y)\cos\omega t.$$
    """
    theta = q[0]
    c = jnp.cos(omega * t)
    sx_dd = -(omega**2) * ax * c
    sy_dd = -(omega**2) * ay * c
    return jnp.stack([-((g + sy_dd) * jnp.sin(theta) + sx_dd * jnp.cos(theta)) / l])


def kapitza_critical_frequency(*, a=1.0, l=1.0, g=1.0):
    r"""$\omega_c = \sqrt{2gl}/a$: a vertical drive of amplitude $a$ and frequency
    $\omega > \omega_c$ stabilizes the inverted pendulum.

    From Kapitza's averaging ($a \ll l$, $\omega \gg \sqrt{g/l}$): an approximate
    criterion, not an exact one.
    """
    return jnp.sqrt(2 * g * l) / a
