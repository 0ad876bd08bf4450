r"""Lagrange's equations by automatic differentiation.

With $M = \partial^2 L/\partial\dot q^2$ and $p = \partial L/\partial \dot q$,

$$M\ddot q = \frac{\partial L}{\partial q}
    - \frac{\partial^2 L}{\partial\dot q\,\partial q}\dot q
    - \frac{\partial^2 L}{\partial\dot q\,\partial t} + Q.$$

The two middle terms are the JVP of $p(q, \dot q, t)$ along $(\dot q, 0, 1)$; the
columns of $M$ are its JVPs along $(0, e_i, 0)$. All $n + 1$ of them come out of one
batched forward-over-reverse pass, with $\partial L/\partial q$ as the shared primal:
no Hessian of $L$, no third-order tensor. For $n \le 2$ that pass and the closed-form
solve are evaluated entry by entry (`_scalarize.py`), which XLA fuses into one loop.
"""

import inspect
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax.extend import core as jax_core

from .._checks import check_solvable, is_concrete, prepare as _prepare
from .._custom_types import Coordinates, GeneralizedForce, Lagrangian, RealScalarLike
from .._jaxpr.canonical import BoundLagrangian, canonical_lagrangian
from .._jaxpr.fusion import fusion_is_off, one_fusion
from .._jaxpr.scalarize import scalarized
from .._taylor.solve import definite_solve


def _lagrange_terms(L, q, qdot, t):
    """Returns `(M, rhs)` with `M q̈ = rhs` the unforced Lagrange equations."""
    n = q.shape[0]
    dtype = q.dtype
    grad_L = jax.grad(L, argnums=(0, 1))

    def along(dq, dqdot, dt):
        (dLdq, _), (_, dp) = jax.jvp(grad_L, (q, qdot, t), (dq, dqdot, dt))
        return dLdq, dp

    dqs = jnp.concatenate([qdot[None], jnp.zeros((n, n), dtype)])
    dqdots = jnp.concatenate([jnp.zeros((1, n), dtype), jnp.eye(n, dtype=dtype)])
    dts = jnp.concatenate([jnp.ones((1,), dtype), jnp.zeros((n,), dtype)])
    dLdq, dps = jax.vmap(along, out_axes=(None, 0))(dqs, dqdots, dts)
    # dps[0] = (∂p/∂q) q̇ + ∂p/∂t; dps[1 + i] = ∂p/∂q̇_i, a column of the symmetric M.
    return dps[1:], dLdq - dps[0]


def _solve_definite(M, rhs):
    r"""Solves `M x = rhs` for a definite `M`; returns `(x, ok)`.

    `ok` is False when `M` is not definite (either sign), is singular to working
    precision (estimated reciprocal condition number below $n\varepsilon$) or has a
    non-finite entry. Small `n` gets a closed form: it is both faster than a batched
    LAPACK call under `vmap` and exact about the failure test.
    """
    n = M.shape[0]
    eps = jnp.finfo(M.dtype).eps
    # n <= 2 works on the scalar entries only: a reduction over M (`jnp.all`) or a
    # product with the whole (n, n) array stops XLA from fusing the solve with the
    # Lagrangian's derivatives under `vmap`.
    if n == 1:
        a = M[0, 0]
        sign = jnp.where(a < 0, -1.0, 1.0).astype(M.dtype)
        a = sign * a
        ok = (a > 0) & jnp.isfinite(a)
        x = (sign * rhs) / jnp.where(ok, a, 1.0)
        return x, ok
    if n == 2:
        sign = jnp.where(M[0, 0] < 0, -1.0, 1.0).astype(M.dtype)
        a, d = sign * M[0, 0], sign * M[1, 1]
        c = 0.5 * sign * (M[0, 1] + M[1, 0])
        b0, b1 = sign * rhs[0], sign * rhs[1]
        det = a * d - c * c
        # A NaN or infinite off-diagonal entry makes c non-finite.
        ok = (
            (a > 0)
            & (det > 2 * eps * a * d)
            & jnp.isfinite(a)
            & jnp.isfinite(d)
            & jnp.isfinite(c)
        )
        safe = jnp.where(ok, det, 1.0)
        x = jnp.stack([(d * b0 - c * b1) / safe, (a * b1 - c * b0) / safe])
        return x, ok
    sign = jnp.where(M[0, 0] < 0, -1.0, 1.0).astype(M.dtype)
    A = sign * M
    A = 0.5 * (A + A.T)
    C = jnp.linalg.cholesky(A)
    diag = jnp.diagonal(C)
    # cond(A) >= (max diag C / min diag C)^2: a cheap certificate of singularity.
    ok = jnp.all(jnp.isfinite(diag)) & (
        jnp.min(diag) ** 2 > n * eps * jnp.max(diag) ** 2
    )
    C = jnp.where(ok, C, jnp.eye(n, dtype=M.dtype))
    x = jsl.cho_solve((C, True), sign * rhs)
    ok = ok & jnp.all(jnp.isfinite(M))
    return x, ok


def _accelerations(L, q, qdot, t, force=None, *, fuse=None):
    """Unchecked core of `accelerations`: NaN where the mass matrix is degenerate.

    `fuse`: for n <= 2, compute `qddot`, `M` and `ok` in one XLA fusion
    (`one_fusion`; default on, `False` turns it off; see below). Ignored for n > 2.

    Under a trace, the equations of one `(L, force, fuse)` at one set of shapes are
    derived once and their jaxpr replayed after (`_replayed`): a solver traces its
    vector field several times (diffrax: once per trace of its step and of its
    checks), and deriving them again costs more than the rest of that tracing."""
    build = lambda q, qdot, t: _derive(L, q, qdot, t, force, fuse)
    return _replayed(build, (L, force, fuse), q, qdot, t)


# Jaxprs of `_derive` per Lagrangian (dropped with it), then per (force, fuse, avals).
_REPLAYS = weakref.WeakKeyDictionary()


def _replayed(build, key, *args):
    """`build(*args)`, from a jaxpr traced once per `key` and argument avals: under a
    trace, where the key's Lagrangian can be held weakly and hashed and the jaxpr
    closes over no tracer (one of an enclosing trace would not outlive it); else
    `build` itself (eager calls, bound methods: a new object at each access)."""
    L, *rest = key
    if is_concrete(*args) or inspect.ismethod(L):
        return build(*args)
    try:
        table = _REPLAYS.setdefault(L, {})
        # (`fusion_off`, for tracers that read the jaxpr, changes what is traced.)
        inner = (*rest, fusion_is_off(), tuple(jax.typeof(x) for x in args))
        found = table.get(inner)
    except TypeError:
        return build(*args)
    if found is False:  # (closes over a tracer)
        return build(*args)
    if found is None:
        closed, shape = jax.make_jaxpr(build, return_shape=True)(*args)
        found = closed, jax.tree.structure(shape)
        tracer = any(isinstance(c, jax.core.Tracer) for c in closed.consts)
        table[inner] = False if tracer else found
    closed, tree = found
    return jax.tree.unflatten(tree, jax_core.jaxpr_as_fun(closed)(*args))


def _derive(L, q, qdot, t, force, fuse):
    n = q.shape[0]

    def solve(q, qdot, t):
        M, rhs = _lagrange_terms(L, q, qdot, t)
        if force is not None:
            rhs = rhs + force(q, qdot, t)
        # For n > 2, a named call: a Taylor step solves with M's factorization once
        # per step, from the marked call (`lagrax._taylor.solve`).
        qddot, ok = (_solve_definite if n <= 2 else definite_solve)(M, rhs)
        return jnp.where(ok, qddot, jnp.nan), M, ok

    if n <= 2:
        # Derivatives and closed-form solve evaluated entry by entry (`scalarized`):
        # under `vmap`, one fused loop over the lanes instead of 12-20 loops of tiny
        # arrays joined by pads, concatenates and small reductions. For larger n the
        # scalar program is the slower one (XLA splits it into many fusions that
        # recompute shared terms). Figures: benchmarks/README.md (eom_overhead).
        qddot, M, ok = scalarized(solve, q, qdot, t)
        # XLA copies the whole scalar program (its sines and cosines) into every
        # fusion that reads an entry of qddot or ok; one fusion for all the outputs
        # keeps one copy. Entry by entry, because a variadic reduce needs operands
        # of one shape (a stacked qddot keeps a second copy). The Taylor
        # recurrences, which read this jaxpr, see the identity (`fusion_off`).
        if fuse is not False:  # (None, the default, fuses)
            qddot, M, ok = _fused_entries(qddot, M, ok)
    else:
        qddot, M, ok = solve(q, qdot, t)
    return qddot, (M, ok)


def _fused_entries(*arrays):
    """The same small arrays, every entry an output of one fusion (`one_fusion`)."""
    values = {(k, i): x[i] for k, x in enumerate(arrays) for i in np.ndindex(x.shape)}
    values = one_fusion(values)
    return tuple(
        jnp.stack([values[k, i] for i in np.ndindex(x.shape)]).reshape(x.shape)
        if x.ndim
        else values[k, ()]
        for k, x in enumerate(arrays)
    )


# Compiled once per (L, force, shapes): eager calls skip op-by-op dispatch.
_accelerations_jit = eqx.filter_jit(_accelerations)


def accelerations(
    L: Lagrangian,
    q: Coordinates,
    qdot: Coordinates,
    t: RealScalarLike = 0.0,
    *,
    force: GeneralizedForce | None = None,
) -> Coordinates:
    r"""Generalized accelerations $\ddot q$ from Lagrange's equations.

    Solves

    $$M\ddot q = \frac{\partial L}{\partial q}
        - \frac{\partial^2 L}{\partial\dot q\,\partial q}\dot q
        - \frac{\partial^2 L}{\partial\dot q\,\partial t} + Q,
    \qquad M = \frac{\partial^2 L}{\partial\dot q^2},$$

    for any twice-differentiable $L$: not necessarily quadratic in $\dot q$, with
    velocity-dependent potentials and explicit time dependence (the $\partial t$ term is
    kept, so a mass matrix that changes with $t$ is right).

    **Arguments:**

    - `L`: the Lagrangian, a function `L(q, qdot, t) -> scalar`. Parameters go in by
        closure or `functools.partial`.
    - `q`, `qdot`: generalized coordinates and velocities, 1-D float arrays of length n.
    - `t`: time (scalar).
    - `force`: optional non-conservative generalized force `force(q, qdot, t) -> Q`,
        shape `(n,)`, as in $\frac{d}{dt}\partial_{\dot q} L - \partial_q L = Q$.

    **Returns:**

    $\ddot q$, shape `(n,)`. Under `jit`/`vmap` (traced inputs) a mass matrix that is
    singular or indefinite gives NaN, which stops an adaptive solve with a failure
    status (see `simulate`); it is never smoothed over with a pseudo-inverse.

    **Raises:**

    - `TypeError`: `L` or `force` is not callable or returns the wrong shape; `q` or
        `qdot` is not a real float array.
    - `ValueError`: `q`, `qdot` not 1-D or of different lengths; and, in an eager call,
        a singular or indefinite mass matrix or non-finite accelerations (the message
        names `q`, `qdot`, `t` and `M`).

    **Example:**

    ```python
    L = lambda q, qdot, t: 0.5 * qdot[0] ** 2 + jnp.cos(q[0])  # pendulum, g = r = 1
    lagrax.accelerations(L, jnp.array([0.5]), jnp.array([0.0]))  # -sin(0.5)
    ```
    """
    q, qdot, t = _prepare(L, q, qdot, t, force)
    if not is_concrete(q, qdot, t):
        # Traced (a user's vector field): the same program `vector_field` runs,
        # inline: XLA compiles a nested `jit` call apart from its caller, which
        # slows the caller's solve (benchmarks/README.md).
        return _accelerations(L, q, qdot, t, force)[0]
    qddot, (M, ok) = _accelerations_jit(_bound(L, q), q, qdot, t, force)
    check_solvable(qddot, M, ok, q, qdot, t)
    return qddot


def _bound(L, q):
    """`L` as its canonical form bound to its constants, read at this call (a
    rebuilt `L` reuses the compiled program; a value `L` reads that changed since an
    earlier call is seen), or `L` itself where it has none."""
    try:
        L_c, consts = canonical_lagrangian(L, q.dtype, q.shape[0])
    except Exception:  # noqa: BLE001 -- traced as it is (its errors raised there)
        return L
    return BoundLagrangian(L_c, tuple(consts))


def mass_matrix(
    L: Lagrangian, q: Coordinates, qdot: Coordinates, t: RealScalarLike = 0.0
) -> jax.Array:
    r"""The generalized mass matrix $M = \partial^2 L / \partial\dot q^2$, `(n, n)`.

    **Arguments:** `L(q, qdot, t) -> scalar`; `q`, `qdot` 1-D float arrays; time `t`.

    **Returns:** $M$ (for $L = T - V$, $T = \frac12\dot q^\top A(q)\dot q$: $M = A(q)$).

    **Example:** for the pendulum $L = \frac12 r^2\dot\theta^2 + gr\cos\theta$,

    ```python
    L = lagrax.systems.pendulum.lagrangian(r=2.0)
    lagrax.mass_matrix(L, jnp.array([0.3]), jnp.array([0.0]))  # [[4.0]], m r² (m = 1)
    ```

    **Raises:** `TypeError`/`ValueError` on bad input, as `accelerations`.
    """
    q, qdot, t = _prepare(L, q, qdot, t)
    return jax.jacfwd(jax.grad(L, argnums=1), argnums=1)(q, qdot, t)


def momenta(
    L: Lagrangian, q: Coordinates, qdot: Coordinates, t: RealScalarLike = 0.0
) -> Coordinates:
    r"""The generalized (canonical) momenta $p = \partial L / \partial\dot q$.

    **Arguments:** `L(q, qdot, t) -> scalar`; `q`, `qdot` 1-D float arrays; time `t`.

    **Returns:** $p$, shape `(n,)`. For a cyclic coordinate ($\partial L/\partial q_j =
    0$) $p_j$ is conserved (Noether).

    **Example:** `lagrax.momenta(L, q, qdot)` is $r^2\dot\theta$ for the pendulum.

    **Raises:** `TypeError`/`ValueError` on bad input, as `accelerations`.
    """
    q, qdot, t = _prepare(L, q, qdot, t)
    return _momenta(L, q, qdot, t)


def _momenta(L, q, qdot, t):
    """Unchecked `momenta` (the variational integrators call it in their Newton
    residuals)."""
    return jax.grad(L, argnums=1)(q, qdot, t)


def energy(
    L: Lagrangian, q: Coordinates, qdot: Coordinates, t: RealScalarLike = 0.0
) -> jax.Array:
    r"""The Jacobi integral $h = \dot q \cdot p - L$, $p = \partial L/\partial\dot q$.

    $dh/dt = -\partial L/\partial t + Q\cdot\dot q$, so $h$ is conserved when $L$ has
    no explicit time dependence and there is no force; for $L = T - V$ with $T$
    quadratic in $\dot q$ it is the total energy $T + V$.

    **Arguments:** `L(q, qdot, t) -> scalar`; `q`, `qdot` 1-D float arrays; time `t`.

    **Returns:** the scalar $h$.

    **Example:** conservation along a trajectory,

    ```python
    import diffrax

    L = lagrax.systems.pendulum.lagrangian()
    q0, qdot0 = jnp.array([1.0]), jnp.array([0.0])
    ts = jnp.linspace(0.0, 10.0, 101)
    sol = lagrax.simulate(L, q0, qdot0, 0.0, 10.0, saveat=diffrax.SaveAt(ts=ts))
    h = jax.vmap(lambda q, v: lagrax.energy(L, q, v))(*sol.ys)
    h[0]  # -cos(1.0), the energy at release (conserved to about rtol after)
    ```

    **Raises:** `TypeError`/`ValueError` on bad input, as `accelerations`.
    """
    q, qdot, t = _prepare(L, q, qdot, t)
    return _jacobi(L, q, qdot, t)[0]


def _jacobi(L, q, qdot, t):
    r"""Unchecked `energy`, and $|\dot q\cdot p| + |L|$, the scale of its rounding."""
    value, p = jax.value_and_grad(L, argnums=1)(q, qdot, t)
    kinetic = jnp.dot(qdot, p)
    return kinetic - value, jnp.abs(kinetic) + jnp.abs(value)
