r"""From particles, forces and constraints to Lagrangians and generalized forces.

Lagrange's derivation from d'Alembert's principle, as an API. $N$ particles at
$r_i(q, t)$ (shape `(N, d)`, $d = 2$ or $3$) in $n$ generalized coordinates give

$$T = \frac12\sum_i m_i|\dot r_i|^2,\qquad
\dot r = \frac{\partial r}{\partial q}\dot q + \frac{\partial r}{\partial t},\qquad
Q_j = \sum_i F_i\cdot\frac{\partial r_i}{\partial q_j},$$

so that $\frac{d}{dt}\partial_{\dot q}L - \partial_q L = Q$ with $L = T - V$. The
velocity is one forward-mode JVP of $r(q, t)$ along $(\dot q, 1)$ and
$Q = (\partial r/\partial q)^\top F$ one reverse-mode VJP: the Jacobian
$\partial r/\partial q$ is never formed on the hot path. Only the checks
(`degrees_of_freedom`, `check_embedding`) form Jacobians.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import (
    as_real_array,
    as_time,
    call_user as _call_user,
    check_callable,
    describe,
    is_concrete,
    positive_scalar,
)
from .._custom_types import GeneralizedForce, Lagrangian


Positions = Callable[[jax.Array, jax.Array], jax.Array]

_POSITIONS = "positions(q, t) -> r of shape (N, d)"
_POTENTIAL = "potential(r, t) -> scalar"
_CARTESIAN_FORCE = "cartesian_force(r, v, t) -> F of shape (N, d)"


def _as_time_like(t, dtype):
    # `t` arrives as a Python float, a weakly typed scalar or a tracer; it must share
    # the dtype of `q` to carry a tangent alongside it.
    return jnp.asarray(t, dtype=dtype)


def _check_positions_output(r, n_particles=None):
    shape = getattr(r, "shape", None)
    dtype = getattr(r, "dtype", None)
    if shape is None or len(shape) != 2 or shape[-1] not in (2, 3):
        hint = (
            " For a single particle return shape (1, d), e.g. `r[None]`."
            if shape is not None and len(shape) == 1
            else ""
        )
        raise ValueError(
            "`positions` must return the particle positions as an array of shape "
            f"(N, d) with d = 2 or 3; positions(q, t) returned {describe(r)}.{hint}"
        )
    if shape[0] == 0:
        raise ValueError(
            "`positions` must return at least one particle; positions(q, t) returned "
            f"shape {tuple(shape)}."
        )
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(
            "`positions` must return real floating-point positions; positions(q, t) "
            f"returned {describe(r)}."
        )
    if n_particles is not None and shape[0] != n_particles:
        raise ValueError(
            f"`positions` returned {shape[0]} particles (shape {tuple(shape)}) but "
            f"`masses` has {n_particles} entries: they must match, one mass per row."
        )


def _check_scalar_output(out, name, call, what):
    shape = getattr(out, "shape", None)
    dtype = getattr(out, "dtype", None)
    if shape != () or dtype is None or not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(
            f"`{name}` must return a real floating-point scalar ({what}); {call} "
            f"returned {describe(out)}. Sum the terms into a scalar."
        )


def _positions_and_velocities(positions, q, qdot, t, n_particles=None):
    r"""$(r, \dot r)$ from one JVP of `positions` along $(\dot q, 1)$."""
    t = _as_time_like(t, q.dtype)
    # Shapes only (`jax.eval_shape`): a user error in `positions` is reported naming
    # `positions` rather than the Lagrangian, at trace time, at no run-time cost.
    _check_positions_output(
        _call_user(positions, "positions", _POSITIONS, q, t), n_particles
    )
    r, v = jax.jvp(positions, (q, t), (qdot, jnp.ones_like(t)))
    return r, v, t


def _as_masses(masses):
    if isinstance(masses, str | bytes) or masses is None or callable(masses):
        raise TypeError(
            "`masses` must be a 1-D array of positive particle masses, shape (N,); "
            f"got {describe(masses)}."
        )
    try:
        if isinstance(masses, list | tuple):
            masses = jnp.asarray(masses)
        dtype = jnp.result_type(masses)
    except TypeError as e:
        raise TypeError(
            "`masses` must be a 1-D array of positive particle masses, shape (N,); "
            f"got {describe(masses)}."
        ) from e
    if jnp.issubdtype(dtype, jnp.integer):
        # Integer masses are harmless (unlike integer coordinates, which carry no
        # tangents): promote them to the default float.
        masses = jnp.asarray(masses, dtype=jnp.result_type(float))
    masses = as_real_array(masses, "masses")
    if masses.ndim != 1 or masses.shape[0] == 0:
        raise ValueError(
            "`masses` must be a 1-D array with one positive mass per particle, shape "
            f"(N,) with N >= 1; got shape {masses.shape}. For one particle write "
            "`jnp.array([m])`."
        )
    # numpy, not jnp: under `jit` a jnp op on a concrete closure constant is a tracer.
    values = np.asarray(masses) if is_concrete(masses) else None
    if values is not None and not np.all(np.isfinite(values) & (values > 0)):
        raise ValueError(
            f"`masses` must be positive and finite; got {np.asarray(masses)!r}."
        )
    return masses


def particle_lagrangian(
    masses, positions: Positions, potential: Callable | None = None
) -> Lagrangian:
    r"""The Lagrangian $L = T - V$ of $N$ particles at positions $r_i(q, t)$.

    $$L(q, \dot q, t) = \frac12\sum_{i=1}^N m_i|\dot r_i|^2 - V(r(q, t), t),\qquad
    \dot r = \frac{\partial r}{\partial q}\dot q + \frac{\partial r}{\partial t},$$

    with $\dot r$ from one forward-mode JVP of `positions` along $(\dot q, 1)$ (no
    Jacobian matrix). The constraints are built into `positions` (as in
    $r_i = r_i(q_1, \ldots, q_n, t)$): a moving support or a rotating frame is an
    explicit `t` in `positions`, and Lagrange's equations then carry the
    $\partial^2 L/\partial\dot q\,\partial t$ term.

    **Arguments:**

    - `masses`: the particle masses $m_i$, a 1-D array of shape `(N,)`, positive.
    - `positions`: `positions(q, t) -> r` of shape `(N, d)`, $d = 2$ or $3$, one row per
        particle (in the order of `masses`).
    - `potential`: optional `potential(r, t) -> scalar`, the potential energy $V$ of the
        conservative applied forces (gravity, springs between particles, ...). Forces
        without a potential go in `force=` through `generalized_force` or
        `dissipation_force`.

    **Returns:**

    `L(q, qdot, t) -> scalar`, for `lagrax.accelerations`, `lagrax.simulate`, ...

    **Raises:**

    - `TypeError`: `masses` is not a real array; `positions` or `potential` is not
        callable, or (when `L` is first called or traced) returns the wrong dtype, or
        `potential` does not return a scalar.
    - `ValueError`: `masses` is not 1-D, or not positive and finite; `positions` does
        not return shape `(N, d)` with $d \in \{2, 3\}$ and `N == len(masses)`.

    **Example:**

    ```python
    def positions(q, t):  # a pendulum of length 1 as a particle in the plane
        return jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])[None]

    L = lagrax.particle_lagrangian(
        jnp.array([1.0]), positions, lambda r, t: 9.81 * r[0, 1]
    )
    ```
    """
    masses = _as_masses(masses)
    check_callable(positions, "positions", "a function positions(q, t) -> (N, d)")
    if potential is not None:
        check_callable(potential, "potential", "a function potential(r, t) -> scalar")
    n_particles = masses.shape[0]

    def L(q, qdot, t):
        r, v, t = _positions_and_velocities(positions, q, qdot, t, n_particles)
        m = masses.astype(r.dtype)
        T = 0.5 * jnp.sum(m * jnp.sum(v * v, axis=-1))
        if potential is None:
            return T
        _check_scalar_output(
            _call_user(potential, "potential", _POTENTIAL, r, t),
            "potential",
            "potential(r, t)",
            "the potential energy V",
        )
        return T - potential(r, t)

    return L


def generalized_force(
    positions: Positions, cartesian_force: Callable
) -> GeneralizedForce:
    r"""The generalized force of Cartesian forces on the particles.

    $$Q_j = \sum_{i=1}^N F_i\cdot\frac{\partial r_i}{\partial q_j},\qquad
    Q = \left(\frac{\partial r}{\partial q}\right)^\top F,$$

    with $F_i = F_i(r, \dot r, t)$ evaluated at $r(q, t)$ and
    $\dot r = (\partial r/\partial q)\dot q + \partial r/\partial t$. One linearization
    of `positions` gives $r$, $\dot r$ (a JVP) and $Q$ (its transpose, a VJP). Only the
    applied forces go in: constraint forces do no virtual work and drop out.

    **Arguments:**

    - `positions`: `positions(q, t) -> r` of shape `(N, d)`, as in
        `particle_lagrangian`.
    - `cartesian_force`: `cartesian_force(r, v, t) -> F` of shape `(N, d)`, the applied
        force on each particle (drag, friction, a drive, or any force at all).

    **Returns:**

    `force(q, qdot, t) -> Q` of shape `(n,)`, for the `force=` argument of
    `lagrax.accelerations` and `lagrax.simulate`.

    **Raises:**

    - `TypeError`: an argument is not callable; (when called or traced)
        `cartesian_force` returns a non-float array.
    - `ValueError`: (when called or traced) `positions` does not return shape `(N, d)`;
        `cartesian_force` does not return the shape of `r`.

    **Example:**

    ```python
    def positions(q, t):  # a pendulum of length 1 as a particle in the plane
        return jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])[None]

    L = lagrax.systems.pendulum.lagrangian()
    q0, qdot0 = jnp.array([1.0]), jnp.array([0.0])
    drag = lagrax.generalized_force(positions, lambda r, v, t: -0.1 * v)
    sol = lagrax.simulate(L, q0, qdot0, 0.0, 10.0, force=drag)
    ```
    """
    check_callable(positions, "positions", "a function positions(q, t) -> (N, d)")
    check_callable(
        cartesian_force, "cartesian_force", "a function cartesian_force(r, v, t) -> F"
    )

    def force(q, qdot, t):
        t = _as_time_like(t, q.dtype)
        _check_positions_output(_call_user(positions, "positions", _POSITIONS, q, t))
        r, linear = jax.linearize(positions, q, t)
        v = linear(qdot, jnp.ones_like(t))
        F = _call_user(cartesian_force, "cartesian_force", _CARTESIAN_FORCE, r, v, t)
        if getattr(F, "shape", None) != r.shape:
            raise ValueError(
                "`cartesian_force` must return one force per particle, of the shape "
                f"of r, {r.shape}; cartesian_force(r, v, t) returned {describe(F)}."
            )
        if not jnp.issubdtype(F.dtype, jnp.floating):
            raise TypeError(
                "`cartesian_force` must return real floating-point forces; "
                f"cartesian_force(r, v, t) returned {describe(F)}."
            )
        F = cartesian_force(r, v, t)
        Q, _ = jax.linear_transpose(linear, q, t)(F.astype(r.dtype))
        return Q

    return force


def dissipation_force(R: Callable) -> GeneralizedForce:
    r"""The generalized force of a Rayleigh dissipation function $R(q, \dot q, t)$.

    $$Q = -\frac{\partial R}{\partial\dot q}.$$

    For linear drag $F_i = -b_i\dot r_i$, $R = \frac12\sum_i b_i|\dot r_i|^2$; then
    $Q\cdot\dot q = -2R$ is the power dissipated. Along a trajectory the Jacobi integral
    obeys $dh/dt = Q\cdot\dot q - \partial L/\partial t$.

    **Arguments:**

    - `R`: the Rayleigh function, `R(q, qdot, t) -> scalar`.

    **Returns:**

    `force(q, qdot, t) -> Q` of shape `(n,)`, for `force=` of `lagrax.accelerations`
    and `lagrax.simulate`.

    **Raises:**

    - `TypeError`: `R` is not callable; (when called or traced) `R` does not return a
        real floating-point scalar.
    """
    check_callable(R, "R", "a Rayleigh function R(q, qdot, t) -> scalar")

    def force(q, qdot, t):
        out = _call_user(R, "R", "R(q, qdot, t) -> scalar", q, qdot, t)
        _check_scalar_output(
            out, "R", "R(q, qdot, t)", "the Rayleigh dissipation function"
        )
        return -jax.grad(R, argnums=1)(q, qdot, t)

    return force


def _as_configuration(r):
    r = as_real_array(r, "r")
    if r.ndim != 2 or r.shape[-1] not in (2, 3) or r.shape[0] == 0:
        raise ValueError(
            "`r` must be the particle positions, an array of shape (N, d) with N >= 1 "
            f"and d = 2 or 3; got shape {r.shape}. For one particle write "
            "`jnp.array([[x, y, z]])`."
        )
    return r


def _constraint_values(constraints, r, t):
    check_callable(constraints, "constraints", "a function constraints(r, t) -> (k,)")
    out = _call_user(constraints, "constraints", "constraints(r, t) -> (k,)", r, t)
    shape = getattr(out, "shape", None)
    dtype = getattr(out, "dtype", None)
    if shape is None or len(shape) > 1 or not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(
            "`constraints` must return the k constraint values f(r, t) as a 1-D real "
            f"float array of shape (k,); constraints(r, t) returned {describe(out)}."
        )

    def f(r):
        return jnp.reshape(constraints(r, t), (-1,))

    values = f(r)
    # ∂f/∂r, (k, dN): a check, not the hot path, so the Jacobian is fine here.
    jac = jax.jacfwd(f)(r).reshape(values.shape[0], r.size)
    return values, jac


def _rank(A):
    """Numerical rank with numpy's default tolerance, max(shape)·eps·σ_max."""
    if 0 in A.shape:
        return jnp.zeros((), jnp.int32)
    s = jnp.linalg.svd(A, compute_uv=False)
    tol = max(A.shape) * jnp.finfo(A.dtype).eps * jnp.max(s)
    return jnp.sum(s > tol).astype(jnp.int32)


def _violation(values, jac, r, rtol):
    r"""$|f_i|$ relative to $\|\nabla f_i\|\,\|r\|$, the change of $f_i$ under a
    relative change of $r$: scale-free, so $f = |r|^2 - a^2$ and $f = |r| - a$ are
    judged alike."""
    if values.shape[0] == 0:
        return jnp.zeros((), r.dtype)
    scale = jnp.linalg.norm(jac, axis=1) * jnp.maximum(
        jnp.linalg.norm(r), jnp.finfo(r.dtype).tiny
    )
    tiny = jnp.finfo(r.dtype).tiny
    return jnp.max(jnp.abs(values) / (rtol * jnp.maximum(scale, tiny)))


def _time_and_rtol(t, rtol, dtype):
    return as_time(t, "t", dtype), positive_scalar(rtol, "rtol", dtype)


# One compiled program each for the checks' arithmetic: called eagerly, op by op, it
# compiles a small XLA program per operation (about a hundred on a first call).
@eqx.filter_jit
def _surface(constraints, r, t, rtol):
    """The constraint values at `r`, the degrees of freedom there, and how far `r`
    is off the surface relative to `rtol` (`_violation`)."""
    values, jac = _constraint_values(constraints, r, t)
    return values, r.size - _rank(jac), _violation(values, jac, r, rtol)


def degrees_of_freedom(constraints: Callable, r, t=0.0, *, rtol=1e-8):
    r"""Degrees of freedom, $n = dN - \mathrm{rank}(\partial f/\partial r)$.

    For $N$ particles in $d$ dimensions under holonomic constraints $f(r, t) = 0$
    ($k$ of them), $n = 3N - k$ when the constraints are independent; the
    rank of the constraint Jacobian at the configuration $r$ counts the independent
    ones.

    **Arguments:**

    - `constraints`: `constraints(r, t) -> f` of shape `(k,)` ($k = 0$ allowed).
    - `r`: a configuration on the constraint surface, shape `(N, d)`, $d \in \{2, 3\}$.
    - `t`: time.
    - `rtol`: how far off the surface `r` may be: $|f_i| \le$ `rtol`
        $\cdot\|\nabla f_i\|\,\|r\|$.

    **Returns:**

    $n$: a Python `int` in an eager call; an integer array under `jit`/`vmap` (where a
    violated constraint raises an equinox runtime error instead of a `ValueError`).

    **Raises:**

    - `TypeError`: `constraints` is not callable; `r` or `t` is not a real float.
    - `ValueError`: `r` not of shape `(N, d)`; `constraints` does not return shape
        `(k,)`; `r` does not satisfy the constraints (the rank off the constraint
        surface says nothing about the system: for $|r|^2 = a^2$ at $r = 0$ it is 0).

    **Example:**

    ```python
    sphere = lambda r, t: jnp.array([jnp.sum(r**2) - 1.0])
    lagrax.degrees_of_freedom(sphere, jnp.array([[0.0, 0.0, 1.0]]))  # 2
    ```
    """
    r = _as_configuration(r)
    t, rtol = _time_and_rtol(t, rtol, r.dtype)
    values, n, ratio = _surface(constraints, r, t, rtol)
    if is_concrete(r, t, rtol, values):
        if not bool(ratio <= 1):
            raise ValueError(
                "`r` does not satisfy the constraints: constraints(r, t) = "
                f"{np.asarray(values).tolist()} at r = {np.asarray(r).tolist()}, "
                f"t = {float(t)} (tolerance rtol={float(rtol):g} relative to "
                "|∇f|·|r|). Degrees of freedom are counted on the constraint surface."
            )
        return int(n)
    return eqx.error_if(
        n, ~(ratio <= 1), "`r` does not satisfy the constraints (degrees_of_freedom)."
    )


@eqx.filter_jit
def _embedding(positions, constraints, q, t, rtol):
    """`check_embedding`'s measures at `(q, t)` (one compiled program: `_surface`):
    `r`, the constraint values, the degrees of freedom, the rank of ∂r/∂q, and the
    violation and the leak off the surface, each relative to `rtol`."""
    r = positions(q, t).astype(q.dtype)
    values, jac_f = _constraint_values(constraints, r, t)
    n = q.shape[0]
    jac_r, dr_dt = jax.jacfwd(positions, argnums=(0, 1))(q, t)
    jac_r = jac_r.reshape(r.size, n)
    dr_dt = dr_dt.reshape(r.size)
    df_dt = jax.jacfwd(lambda t: jnp.reshape(constraints(r, t), (-1,)))(t)
    dof = r.size - _rank(jac_f)
    rank_r = _rank(jac_r)
    violated = _violation(values, jac_f, r, rtol)
    # Tangency: the cosine between each constraint normal ∇f_i and each coordinate
    # direction ∂r/∂q_j (and the motion of r along t) must vanish.
    tiny = jnp.finfo(r.dtype).tiny
    grad_norm = jnp.maximum(jnp.linalg.norm(jac_f, axis=1), tiny)
    col_norm = jnp.maximum(jnp.linalg.norm(jac_r, axis=0), tiny)
    leak_q = jnp.abs(jac_f @ jac_r) / (grad_norm[:, None] * col_norm[None, :])
    speed = jnp.maximum(jnp.linalg.norm(dr_dt), tiny)
    leak_t = jnp.abs(jac_f @ dr_dt + df_dt) / (grad_norm * speed)
    leak = (
        jnp.maximum(jnp.max(leak_q, initial=0.0), jnp.max(leak_t, initial=0.0)) / rtol
    )
    return r, values, dof, rank_r, violated, leak


def check_embedding(
    positions: Positions, constraints: Callable, q, t=0.0, *, rtol=1e-8
):
    r"""Checks that $r(q, t)$ gives valid generalized coordinates for $f(r, t) = 0$.

    Three conditions, at the given $(q, t)$:

    1. the constraints hold, $f(r(q, t), t) = 0$;
    2. the coordinates are independent: $\partial r/\partial q$ has full column rank
        $n$ = `len(q)` (no redundant coordinate, no coordinate singularity such as the
        azimuth at a pole);
    3. there are enough of them and they stay on the constraint surface: $n$ equals
        `degrees_of_freedom(constraints, r, t)`, and every coordinate velocity is
        tangent to it, $\frac{\partial f}{\partial r}\frac{\partial r}{\partial q} = 0$
        and $\frac{\partial f}{\partial r}\frac{\partial r}{\partial t}
        + \frac{\partial f}{\partial t} = 0$.

    **Arguments:**

    - `positions`: `positions(q, t) -> r` of shape `(N, d)`.
    - `constraints`: `constraints(r, t) -> f` of shape `(k,)`.
    - `q`: generalized coordinates, 1-D float array.
    - `t`: time.
    - `rtol`: relative tolerance of the equality tests (1 and the tangency part of 3).

    **Returns:**

    $n$, the number of degrees of freedom (= `len(q)`): a Python `int` in an eager
    call, an integer array under `jit`/`vmap`, where a failed check raises an equinox
    runtime error naming the failed condition.

    **Raises:**

    - `ValueError`: the constraints are violated at $r(q, t)$; there are too few
        coordinates (fewer than the degrees of freedom); the coordinates are redundant
        or singular ($\partial r/\partial q$ rank-deficient); or $r(q, t)$ leaves the
        constraint surface. Also bad shapes of `q`, `r` or the constraint values.
    - `TypeError`: an argument is not callable or not a real float array.
    """
    check_callable(positions, "positions", "a function positions(q, t) -> (N, d)")
    q = as_real_array(q, "q")
    if q.ndim != 1 or q.shape[0] == 0:
        raise ValueError(
            "`q` must be a 1-D array of generalized coordinates, shape (n,) with "
            f"n >= 1; got shape {q.shape}."
        )
    t, rtol = _time_and_rtol(t, rtol, q.dtype)
    _check_positions_output(_call_user(positions, "positions", _POSITIONS, q, t))
    n = q.shape[0]
    r, values, dof, rank_r, violated, leak = _embedding(
        positions, constraints, q, t, rtol
    )
    if is_concrete(q, t, rtol, r, values):
        where = f"q = {np.asarray(q).tolist()}, t = {float(t)}"
        if not bool(violated <= 1):
            raise ValueError(
                f"`positions` violates `constraints`: at {where}, r = "
                f"{np.asarray(r).tolist()} gives constraints(r, t) = "
                f"{np.asarray(values).tolist()} (tolerance rtol={float(rtol):g} "
                "relative to |∇f|·|r|)."
            )
        dof, rank_r = int(dof), int(rank_r)
        if n < dof:
            raise ValueError(
                f"Too few coordinates: the constraints leave {dof} degrees of freedom "
                f"({r.size} Cartesian coordinates minus {r.size - dof} independent "
                f"constraints) but `q` has {n}. `positions` describes only part of "
                "the allowed motion."
            )
        if rank_r < n:
            raise ValueError(
                f"Redundant or singular coordinates: ∂r/∂q has rank {rank_r} < "
                f"{n} = len(q) at {where}, so the coordinates are not independent "
                "there (a coordinate that moves nothing, two that move the same way, "
                "or a coordinate singularity such as the azimuth at a pole)."
            )
        if n > dof or not bool(leak <= 1):
            raise ValueError(
                f"`positions` leaves the constraint surface: at {where} the "
                f"constraints allow {dof} degrees of freedom and `q` has {n}, and "
                "(∂f/∂r)(∂r/∂q) or (∂f/∂r)(∂r/∂t) + ∂f/∂t is not zero (largest "
                f"normal component relative to rtol: {float(leak):.3g}). Some "
                "coordinate moves the particles off the constraints."
            )
        return n
    out = jnp.asarray(n, jnp.int32)
    out = eqx.error_if(out, ~(violated <= 1), "`positions` violates `constraints`.")
    out = eqx.error_if(out, n < dof, "Too few coordinates for the constraints.")
    out = eqx.error_if(
        out, rank_r < n, "Redundant or singular coordinates: ∂r/∂q is rank-deficient."
    )
    out = eqx.error_if(
        out, (n > dof) | ~(leak <= 1), "`positions` leaves the constraint surface."
    )
    return out
