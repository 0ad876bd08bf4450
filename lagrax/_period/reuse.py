"""What the period programs are compiled for: the canonical Lagrangian and its solver.

`sweep_periods` and `period` compile one program per Lagrangian and static
configuration. Keyed on the canonical function (`lagrax._jaxpr.canonical`), a rebuilt
`L` with the same body and new parameter values finds the program compiled for the
first one, and so does the choice of stepper (Taylor or its fallback), which traces
the acceleration's Taylor program.
"""

import collections

import jax
import numpy as np

from .._jaxpr.canonical import canonical_lagrangian
from .solver import resolve_solver


# The stepper chosen per (canonical L, dtype, solver), most recently used last.
_RESOLVED: collections.OrderedDict = collections.OrderedDict()
_MAX_RESOLVED = 256


def canonical_inputs(L, solver, dtype):
    """`(L_c, consts, solver)`: the canonical Lagrangian (`L_c(q, qdot, t, *consts)
    == L(q, qdot, t)`), its lifted constants, and the solver the kernel steps with
    (`resolve_solver`), decided once per canonical function."""
    L_c, consts = canonical_lagrangian(L, dtype)
    key = (L_c, np.dtype(dtype).name, solver)
    try:
        found = _RESOLVED.get(key)
    except TypeError:  # an unhashable solver: decide anew
        return L_c, consts, _resolve(L_c, consts, solver, dtype)
    if found is None:
        found = _RESOLVED[key] = _resolve(L_c, consts, solver, dtype)
        if len(_RESOLVED) > _MAX_RESOLVED:
            _RESOLVED.popitem(last=False)
    else:
        _RESOLVED.move_to_end(key)
    return L_c, consts, found


def _resolve(L_c, consts, solver, dtype):
    """`resolve_solver` for `L_c` with its constants abstract, as the compiled
    kernel sees them (arguments, not values to fold)."""
    out = []

    def probe(*consts):
        out.append(
            resolve_solver(solver, lambda q, qd, t: L_c(q, qd, t, *consts), dtype)
        )
        return 0.0

    specs = [
        jax.ShapeDtypeStruct(np.shape(c), jax.numpy.result_type(c)) for c in consts
    ]
    jax.make_jaxpr(probe)(*specs)
    return out[0]
