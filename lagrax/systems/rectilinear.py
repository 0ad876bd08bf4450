r"""Rectilinear motion: a particle of mass $m$ on a line in a potential $V(x)$.

$L = \frac12 m\dot x^2 - V(x)$, and Lagrange's equation recovers Newton's
$m\ddot x = -V'(x) = F_x$.
"""

from collections.abc import Callable

import jax.numpy as jnp

from .._checks import check_callable


def lagrangian(potential: Callable, *, m=1.0):
    r"""$L(q, \dot q, t) = \frac12 m\dot x^2 - V(x)$ with $q = (x,)$.

    **Arguments:** `potential`: `V(x) -> scalar` (a JAX function); `m`: the mass.

    **Returns:** `L(q, qdot, t)`.

    **Raises:** `TypeError` if `potential` is not callable.
    """
    check_callable(potential, "potential", "a function V(x) -> scalar")

    def L(q, qdot, t):
        return 0.5 * m * qdot[0] ** 2 - potential(q[0])

    return L


def acceleration(x, force_x, *, m=1.0):
    r"""Newton's $\ddot x = F_x / m$, with $F_x = -V'(x)$ given by hand as `force_x`."""
    return jnp.asarray(force_x(x)) / m
