r"""A charged particle in uniform electric and magnetic fields: a velocity-dependent
potential.

In Cartesian coordinates $q = r$, with $A = \frac12 B\times r$ (symmetric gauge) and
$\varphi = -E\cdot r$,

$$L = \tfrac12 m|\dot r|^2 + e\,\dot r\cdot A(r) - e\varphi(r),$$

whose Lagrange equations are the Lorentz force law $m\ddot r = e(E + \dot r\times B)$.
The particle gyrates about $B$ at the cyclotron frequency $\omega_c = |e||B|/m$ while
drifting at $E\times B/|B|^2$.
"""

import jax.numpy as jnp
import numpy as np

from .._checks import describe


def _check_field(x, name):
    """`x` must be a real scalar or 3-vector (a scalar applies to every component)."""
    expected = f"`{name}` must be a real 3-vector (or a scalar, for every component)"
    if isinstance(x, str | bytes) or x is None or callable(x):
        raise TypeError(f"{expected}; got {describe(x)}.")
    try:
        if isinstance(x, list | tuple):  # the defaults are tuples
            x = np.asarray(x)
        dtype = jnp.result_type(x)
        shape = jnp.shape(x)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{expected}; got {describe(x)}.") from e
    if jnp.issubdtype(dtype, jnp.complexfloating) or not (
        jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)
    ):
        raise TypeError(f"{expected}; got dtype {dtype}.")
    if shape not in ((), (1,), (3,)):
        raise ValueError(f"{expected}, shape (3,); got shape {shape}.")


def _field(x, dtype):
    return jnp.broadcast_to(jnp.asarray(x, dtype=dtype), (3,))


def lagrangian(*, m=1.0, charge=1.0, B=(0.0, 0.0, 1.0), E=(0.0, 0.0, 0.0)):
    r"""$L = \frac12 m|\dot r|^2 + e\,\dot r\cdot\frac12(B\times r) + e\,E\cdot r$,
    $q = r = (x, y, z)$; `charge` is $e$, `B` and `E` are 3-vectors (a scalar is
    broadcast to all three components).

    **Raises:** `TypeError`/`ValueError` if `B` or `E` is not a real 3-vector or scalar.
    """
    _check_field(B, "B")
    _check_field(E, "E")

    def L(q, qdot, t):
        b = _field(B, q.dtype)
        e_field = _field(E, q.dtype)
        A = 0.5 * jnp.cross(b, q)
        return (
            0.5 * m * jnp.dot(qdot, qdot)
            + charge * jnp.dot(qdot, A)
            + charge * jnp.dot(e_field, q)
        )

    return L


def acceleration(
    q, qdot, t=0.0, *, m=1.0, charge=1.0, B=(0.0, 0.0, 1.0), E=(0.0, 0.0, 0.0)
):
    r"""The Lorentz force law $\ddot r = (e/m)(E + \dot r\times B)$."""
    _check_field(B, "B")
    _check_field(E, "E")
    b = _field(B, qdot.dtype)
    e_field = _field(E, qdot.dtype)
    return (charge / m) * (e_field + jnp.cross(qdot, b))


def cyclotron_frequency(*, m=1.0, charge=1.0, B=(0.0, 0.0, 1.0)):
    r"""$\omega_c = |e|\,|B|/m$."""
    _check_field(B, "B")
    # `_field`, as in `lagrangian`: a scalar B is the vector (B, B, B).
    return jnp.abs(charge) * jnp.linalg.norm(_field(B, jnp.result_type(float))) / m


def exact_trajectory(
    t, q0, qdot0, *, m=1.0, charge=1.0, B=(0.0, 0.0, 1.0), E=(0.0, 0.0, 0.0)
):
    r"""The exact solution in uniform fields ($B \ne 0$), from $(r_0, v_0)$ at $t = 0$.

    With $b = B/|B|$, signed $\Omega = e|B|/m$, drift $v_d = E\times B/|B|^2$ and
    $u_0 = v_{0\perp} - v_d$ (the part of $v_0$ across $b$, less the drift):

    $$r(t) = r_0 + (v_0\cdot b)\,b\,t + \frac{eE\cdot b}{2m}\,b\,t^2 + v_dt
        + \frac{u_0\sin\Omega t + (u_0\times b)(1 - \cos\Omega t)}{\Omega}.$$

    **Arguments:** `t`: times (any shape); `q0`, `qdot0`: shape `(3,)`; the parameters
    as in `lagrangian`.

    **Returns:** `(r, v)`, each of shape `t.shape + (3,)`.
    """
    _check_field(B, "B")
    _check_field(E, "E")
    dtype = jnp.result_type(q0, qdot0, float)
    Bv = _field(B, dtype)
    Ev = _field(E, dtype)
    t = jnp.asarray(t, dtype=dtype)
    # Vectors broadcast against t explicitly (fine under rank_promotion="raise").
    lead = (1,) * t.ndim
    vec = lambda x: jnp.reshape(x, lead + (3,))
    t = t[..., None]
    normB = jnp.linalg.norm(Bv)
    b = Bv / normB
    Omega = charge * normB / m
    v_par = jnp.dot(qdot0, b)
    a_par = charge * jnp.dot(Ev, b) / m
    v_d = jnp.cross(Ev, Bv) / normB**2
    u0 = qdot0 - v_par * b - v_d
    w0 = jnp.cross(u0, b)
    s, c = jnp.sin(Omega * t), jnp.cos(Omega * t)
    # 1 - cos written as 2 sin² (no cancellation at small Ωt).
    one_minus_c = 2 * jnp.sin(Omega * t / 2) ** 2
    q0, b, v_d, u0, w0 = map(vec, (q0, b, v_d, u0, w0))
    r = q0 + (v_par * t + 0.5 * a_par * t**2) * b + v_d * t
    r = r + (u0 * s + w0 * one_minus_c) / Omega
    v = (v_par + a_par * t) * b + v_d + u0 * c + w0 * s
    return r, v
