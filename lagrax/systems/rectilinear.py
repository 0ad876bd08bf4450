r"""Rectilinear motion: a particle of mass $m$ on a line in a potential $V(x)$.

$L = \frac12 m\dot x^2 - V(x)$, and Lagrange's equation recovers Newton's
$m\ddot x = -V'(x) = F_x$.
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp

from .._checks import check_callable


def harmonic(x):
    r"""$V(x) = \frac12 x^2$, the default potential."""
    return 0.5 * x**2


def lagrangian(potential: Callable = harmonic, *, m=1.0):
    r"""$L(q, \dot q, t) = \frac12 m\dot x^2 - V(x)$ with $q = (x,)$.

    **Arguments:** `potential`: `V(x) -> scalar` (a JAX function; default `harmonic`);
    `m`: the mass.

    **Returns:** `L(q, qdot, t)`.

    **Raises:** `TypeError` if `potential` is not callable.
    """
    check_callable(potential, "potential", "a function V(x) -> scalar")

    def L(q, qdot, t):
        return 0.5 * m * qdot[0] ** 2 - potential(q[0])

    return L


def acceleration(q, qdot=None, t=0.0, *, potential=harmonic, m=1.0, force_x=None):
    r"""Newton's $\ddot x = F_x / m$, elementwise in `q`.

    $F_x = -V'(x)$ is `force_x(x)` when given by hand, else the derivative of
    `potential`; `qdot` and `t` do not enter.
    """
    if force_x is None:
        return -jnp.vectorize(jax.grad(potential))(q) / m
    return jnp.asarray(force_x(q)) / m
