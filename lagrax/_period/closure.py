"""A Lagrangian with the tracers it closes over as explicit arguments, so that the
compiled kernel is keyed on the function and found again on the next call."""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.extend.core as jex_core
import numpy as np


class _WithParameters(eqx.Module):
    """A Lagrangian that is a pytree with float arrays (an `eqx.Module` with
    parameters), as a hashable function of `(q, qdot, t, *arrays)`."""

    static: Any = eqx.field(static=True)
    treedef: Any = eqx.field(static=True)

    def __call__(self, q, qdot, t, *arrays):
        dynamic = jax.tree.unflatten(self.treedef, arrays)
        return eqx.combine(dynamic, self.static)(q, qdot, t)


def _outside_transformations() -> bool:
    """Whether JAX is evaluating eagerly (no `jit`, `vmap`, `grad` being traced):
    then no function can close over a tracer (a leaked one would raise anyway), and
    `closure_converted` needs no trace of L, which costs more than a small sweep's
    dispatch. `take_current_trace` sets the evaluating trace for its block: the
    current trace is that one exactly outside every transformation."""
    current = jex_core.find_top_trace(())
    with jex_core.take_current_trace():
        evaluating = jex_core.find_top_trace(())
    return current is evaluating


def closure_converted(L: Callable, dtype):
    """`L` with the tracers it closes over hoisted into explicit arguments.

    Returns `(L_c, consts)` with `L_c(q, qdot, t, *consts) == L(q, qdot, t)`. When `L`
    closes over no tracer, `L_c` is `L` itself, so the compiled kernel is found again
    on the next call with the same `L`. A Lagrangian that is a pytree with float
    arrays (an `eqx.Module` with parameters) passes them as `consts` (its compiled
    kernel is found again for new parameter values, and periods are differentiable
    with respect to them).
    """
    eager = _outside_transformations()
    z = np.zeros((1,), dtype)  # (NumPy: `jnp.zeros` compiles on a first call)
    dynamic, static = eqx.partition(L, eqx.is_inexact_array)
    arrays, treedef = jax.tree.flatten(dynamic)
    if arrays:
        L_p = _WithParameters(static, treedef)
        if eager:
            return L_p, list(arrays)
        # Tracers closed over elsewhere (a function among its fields) come after.
        converted, extra = jax.closure_convert(L_p, z, z, np.zeros((), dtype), *arrays)
        if not extra:
            return L_p, list(arrays)
        return converted, list(arrays) + list(extra)
    if eager:
        return L, []
    converted, consts = jax.closure_convert(L, z, z, np.zeros((), dtype))
    if not consts:
        return L, []
    return converted, list(consts)
