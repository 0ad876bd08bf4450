"""Derivatives of periods: forward mode through the loop, and `jax.grad` through a
`custom_jvp` whose tangents come from that forward mode.

The periods are independent per lane, so their derivative with respect to the
release points is diagonal (one forward pass), and their derivative with respect to
parameters that `L` closes over takes one forward pass per parameter, for the inputs
being differentiated only (the `custom_jvp` sees the others' tangents as symbolic
zeros).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .device import Periods, periods


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def periods_diff(L, m, devices, q0, consts, rtol, atol, t_max, energy_tol):
    return periods(L, m, devices, q0, consts, rtol, atol, t_max, energy_tol)


def _periods_jvp(L, m, devices, primals, tangents):
    q0, consts, rtol, atol, t_max, energy_tol = primals
    periods_of = lambda q0, consts: (
        periods(L, m, devices, q0, consts, rtol, atol, t_max, energy_tol),
        None,
    )
    (out, _), dT = forward_mode(periods_of, q0, consts, tangents[0], tangents[1])
    return out, tangents_of(out, dT)


def forward_mode(periods_of, q0, consts, dq0, dconsts, jacobian=None):
    """`(periods_of(q0, consts), dT)`: the periods' tangent along `(dq0, dconsts)`
    (symbolic zeros for the inputs not differentiated), by one forward pass per
    direction (`_directions`). `periods_of(q0, consts) -> (Periods, aux)`.
    `jacobian(q0, consts, with_q, wanted)`: `forward_jacobian` of `periods_of`, or a
    compiled equivalent (`sweep._sweep_call_jvp`)."""
    leaves, treedef = jax.tree.flatten(consts)
    dleaves = treedef.flatten_up_to(dconsts)
    inexact = [jnp.issubdtype(jnp.result_type(x), jnp.inexact) for x in leaves]
    wanted = tuple(ok and not _is_zero(dx) for ok, dx in zip(inexact, dleaves))
    with_q = not _is_zero(dq0)
    if not (with_q or any(wanted)):  # (every tangent a symbolic zero)
        out = periods_of(q0, consts)
        return out, jnp.zeros_like(out[0].periods)
    if jacobian is None:
        jacobian = functools.partial(forward_jacobian, periods_of)
    out, jac = jacobian(q0, consts, with_q, wanted)
    k = 0
    dT = jnp.zeros_like(out[0].periods)
    if with_q:
        dT, k = jac[0] * dq0, 1
    for x, dx, ok in zip(leaves, dleaves, wanted):
        if not ok:
            continue
        size = int(np.size(x))
        dT = dT + jnp.tensordot(jnp.reshape(dx, (-1,)), jac[k : k + size], axes=1)
        k += size
    return out, dT


def forward_jacobian(periods_of, q0, consts, with_q, wanted):
    """`(periods_of(q0, consts), jac)`: per direction (`_directions`: along q0 if
    `with_q`, then each scalar of each leaf of `consts` that is `wanted`), the
    periods' derivative, `jac` of shape `(directions, n)` (diagonal in q0: lanes are
    independent)."""
    leaves, treedef = jax.tree.flatten(consts)
    directions = _directions(q0, with_q, leaves, wanted)
    # The forward passes differentiate only the inputs being differentiated: the
    # others enter as constants, so that a `custom_jvp` inside `periods_of` sees
    # them as symbolic zeros (and adds no directions of its own).
    picked = [k for k, ok in enumerate(wanted) if ok]
    dq_dirs = jnp.stack([d[0] for d in directions])
    dc_dirs = [jnp.stack([d[1][k] for d in directions]) for k in picked]

    def periods_at(q, picked_leaves):
        full = list(leaves)
        for k, x in zip(picked, picked_leaves):
            full[k] = x
        return periods_of(q if with_q else q0, treedef.unflatten(full))

    def tangent(dq, dc):
        picked_leaves = [leaves[k] for k in picked]
        if with_q:
            out, dout = jax.jvp(periods_at, (q0, picked_leaves), (dq, dc))
        else:
            f = lambda picked_leaves: periods_at(q0, picked_leaves)
            out, dout = jax.jvp(f, (picked_leaves,), (dc,))
        return out, dout[0].periods

    # The primal outputs come from the same forward pass (unbatched over the
    # directions): one copy of the sweep in the compiled program, not two. One
    # direction (a derivative along q0 alone, the usual `jax.grad`) needs no `vmap`:
    # batching the loops' while and cond bodies retraces them to a fixed point,
    # several times the tracing of the forward pass itself.
    if len(directions) == 1:
        out, jac = tangent(dq_dirs[0], [d[0] for d in dc_dirs])
        return out, jac[None]
    return jax.vmap(tangent, out_axes=(None, 0))(dq_dirs, dc_dirs)  # (dirs, n)


def _directions(q0, with_q, leaves, wanted):
    """The forward passes to run, as `(dq0, dconsts)` tangent directions. Lanes are
    independent: dT_i/dq0_j is diagonal, one pass for all of it; each scalar
    parameter L closes over takes one more. Only for the inputs whose tangent is not
    a symbolic zero (`symbolic_zeros=True`): the derivative with respect to q0 alone
    of a Lagrangian with many parameters is one pass, not one per parameter."""
    no_consts = [jnp.zeros_like(x) for x in leaves]
    directions = [(jnp.ones_like(q0), no_consts)] if with_q else []
    for i, (x, ok) in enumerate(zip(leaves, wanted)):
        if not ok:
            continue
        for j in range(int(np.size(x))):
            basis = list(no_consts)
            # (A leaf may be a Python scalar with a dtype, `TypedFloat`: no `.shape`.)
            e = jnp.zeros(np.size(x), jnp.result_type(x)).at[j].set(1)
            basis[i] = e.reshape(np.shape(x))
            directions.append((jnp.zeros_like(q0), basis))
    return directions


def tangents_of(out: Periods, dT) -> Periods:
    """The tangents of `periods`' outputs: `dT` for the periods, none for the rest."""
    int_tangent = lambda y: np.zeros(np.shape(y), jax.dtypes.float0)
    return Periods(
        dT,
        int_tangent(out.status),
        int_tangent(out.steps),
        int_tangent(out.executed),
        jnp.zeros_like(out.estimate),
    )


periods_diff.defjvp(_periods_jvp, symbolic_zeros=True)


def _is_zero(t):
    """Whether a tangent is a symbolic zero (the input is not being differentiated)."""
    return t is None or type(t) is jax.custom_derivatives.SymbolicZero
