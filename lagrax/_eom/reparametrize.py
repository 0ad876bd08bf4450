r"""Point transformations $q = \varphi(u, t)$ of a Lagrangian."""

from collections.abc import Callable

import jax
import jax.numpy as jnp

from .._checks import call_user, check_callable, describe
from .._custom_types import Coordinates, Lagrangian, RealScalarLike


def _check_phi(phi, u, t):
    out = call_user(phi, "phi", "phi(u, t) -> q of the new coordinates u", u, t)
    shape = getattr(out, "shape", None)
    dtype = getattr(out, "dtype", None)
    if shape is None or dtype is None or not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(
            "`phi` must return the old coordinates q as a real floating array; "
            f"phi(u, t) returned {describe(out)}."
        )
    if len(shape) != 1:
        raise ValueError(
            "`phi` must return the old coordinates q as a 1-D array of shape (n,); "
            f"phi(u, t) returned shape {tuple(shape)} for u of shape {u.shape}."
        )
    if shape != u.shape:
        raise ValueError(
            "`phi` must map n new coordinates to n old ones (a point transformation "
            f"is invertible, so q and u have the same length); phi(u, t) returned "
            f"shape {tuple(shape)} for u of shape {u.shape}."
        )


def reparametrize(
    L: Lagrangian, phi: Callable[[Coordinates, RealScalarLike], Coordinates]
) -> Lagrangian:
    r"""The same system in new coordinates $u$, where $q = \varphi(u, t)$.

    $$L'(u, \dot u, t) = L\big(\varphi(u, t),\;
        \tfrac{\partial\varphi}{\partial u}\dot u + \tfrac{\partial\varphi}{\partial t},
        \; t\big).$$

    Lagrange's equations are covariant under such point transformations: a trajectory
    $u(t)$ of $L'$ maps to the trajectory $q(t) = \varphi(u(t), t)$ of $L$ wherever
    $\partial\varphi/\partial u$ is invertible. The use is to leave a coordinate
    singularity behind: a mass matrix of $L$ that vanishes at some $q$ can be regular
    in $u$ (the cycloid at its cusp below). The velocity $\dot q$ is one forward-mode
    JVP of $\varphi$ along $(\dot u, 1)$, so the time dependence of $\varphi$ (a
    rotating or accelerating frame) is included at no extra cost and no Jacobian is
    formed.

    **Arguments:**

    - `L`: the Lagrangian in the old coordinates, `L(q, qdot, t) -> scalar`.
    - `phi`: the transformation `phi(u, t) -> q`, differentiable, with `u` and `q` 1-D
        arrays of the same length n. It is checked (shape and dtype, at trace time) the
        first time the new Lagrangian is called.

    **Returns:**

    The new Lagrangian `L'(u, udot, t) -> scalar`, a plain function like any other
    (`lagrax.accelerations`, `lagrax.simulate`, `jit` and `vmap` all apply).

    **Raises:**

    - `TypeError`: `L` or `phi` is not callable (at once); `phi` does not return a real
        floating array (when `L'` is first called).
    - `ValueError`: `phi(u, t)` does not have the shape of `u` (when `L'` is first
        called): a point transformation maps n coordinates to n.

    **Example:**

    Huygens' cycloid, with the cusp at $\theta = 0$, in $u = \cos(\theta/2)$:

    ```python
    L_theta = lagrax.systems.cycloid.lagrangian(R=1.0, g=9.81)
    L_u = lagrax.reparametrize(L_theta, lambda u, t: 2 * jnp.arccos(u))
    # Equal to 8 R² udot² - 2 g R u² (lagrax.systems.cycloid.lagrangian_u) for
    # |u| < 1; at the cusps |u| = 1 arccos itself is singular, so there use the
    # closed form.
    lagrax.accelerations(L_u, jnp.array([0.5]), jnp.array([0.0]))  # -(9.81 / 4) * 0.5
    ```
    """
    check_callable(L, "L", "a function L(q, qdot, t) -> scalar")
    check_callable(phi, "phi", "a function phi(u, t) -> q")

    def L_new(u, udot, t):
        u = jnp.asarray(u)
        udot = jnp.asarray(udot)
        dtype = jnp.result_type(u, udot, float)
        u = u.astype(dtype)
        udot = udot.astype(dtype)
        t = jnp.asarray(t, dtype=jnp.result_type(dtype, t))
        _check_phi(phi, u, t)
        # One JVP along (udot, 1) gives q and qdot = (∂φ/∂u) udot + ∂φ/∂t together.
        q, qdot = jax.jvp(phi, (u, t), (udot, jnp.ones_like(t)))
        return L(q, qdot, t)

    return L_new
