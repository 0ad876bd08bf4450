"""Which stepper the period kernel steps with, from the solver a user passes, and
what the period programs are compiled for: the canonical Lagrangian and its solver.

`sweep_periods` and `period` compile one program per Lagrangian and static
configuration. Keyed on the canonical function (`lagrax._jaxpr.canonical`), a rebuilt
`L` with the same body and new parameter values finds the program compiled for the
first one, and so does the choice of stepper (Taylor or its fallback), which traces
the acceleration's Taylor program.
"""

import collections
import weakref

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import executables
from .._jaxpr.canonical import canonical_lagrangian
from .._jaxpr.switches import switches
from .._stepper.base import AbstractStepper
from .._stepper.runge_kutta import RungeKuttaStepper
from .._taylor.stepper import TaylorStepper
from .._taylor.taylor import Taylor
from .units import scaled_acceleration


def stepper_of(solver) -> AbstractStepper | None:
    """The stepper of a solver: `lagrax.Taylor`'s, or a diffrax explicit Runge–Kutta
    pair's (None for any other solver)."""
    if isinstance(solver, Taylor):
        return TaylorStepper(order=solver.order, max_step=solver.max_step)
    return RungeKuttaStepper.of(solver)


# Whether `Taylor` covers a Lagrangian, per function object (weakly held): the check
# traces the acceleration, which every eager call would otherwise repeat.
_TAYLOR_SUPPORT = weakref.WeakKeyDictionary()


def resolve_solver(solver, L, dtype):
    """The solver the kernel steps with: `Taylor(fallback=...)` is a plain `Taylor`
    where every primitive of L's acceleration has a recurrence, its program can be
    unrolled and L has no switch of branch, its fallback elsewhere (decided from the
    jaxpr, once per function, dtype and solver; nothing is evaluated)."""
    if not (isinstance(solver, Taylor) and solver.fallback is not None):
        return solver
    try:
        known = _TAYLOR_SUPPORT.setdefault(L, {})
    except TypeError:  # not weakly referenceable: decide anew
        known = {}
    key = (jnp.dtype(dtype).name, solver)
    if key not in known:
        plain = Taylor(order=solver.order, max_step=solver.max_step)
        accel_one = scaled_acceleration(L, ())
        scalar = jax.ShapeDtypeStruct((), dtype)
        accel = lambda s, x, v, q0, Qs, tau: accel_one(q0, Qs, tau, s, x, v)
        # With a recurrence for every primitive, and a program small enough to be
        # unrolled: the loop over orders runs slower than the fallback (see `Taylor`).
        try:  # (tracing the order-K program also finds a primitive without one)
            supported = plain._unrolls(accel, dtype, scalar, scalar, scalar)
        except NotImplementedError:
            supported = False
        # Where L switches branch with the state or time, a Taylor step across a
        # switch fails its lane (see `Taylor`); the fallback steps through it.
        one = jax.ShapeDtypeStruct((1,), dtype)
        supported = supported and not switches(L, (one, one, scalar))
        known[key] = plain if supported else solver.fallback
    return known[key]


# The stepper chosen per (canonical L, dtype, solver), most recently used last.
_RESOLVED: collections.OrderedDict = collections.OrderedDict()
_MAX_RESOLVED = 256


def canonical_inputs(L, solver, dtype):
    """`(L_c, consts, solver)`: the canonical Lagrangian (`L_c(q, qdot, t, *consts)
    == L(q, qdot, t)`), its lifted constants, and the solver the kernel steps with
    (`resolve_solver`), decided once per canonical function."""
    L_c, consts = canonical_lagrangian(L, dtype)
    return L_c, consts, resolved_solver(L_c, consts, solver, dtype)


def resolved_solver(L_c, consts, solver, dtype):
    """`resolve_solver` for the canonical `L_c`, decided once per canonical
    function, dtype and solver."""
    key = (L_c, np.dtype(dtype).name, solver)
    try:
        found = _RESOLVED.get(key)
    except TypeError:  # an unhashable solver: decide anew
        return _resolve(L_c, consts, solver, dtype)
    if found is None:
        found = _RESOLVED[key] = _resolve_kept(L_c, consts, solver, dtype)
        if len(_RESOLVED) > _MAX_RESOLVED:
            _RESOLVED.popitem(last=False)
    else:
        _RESOLVED.move_to_end(key)
    return found


def _resolve_kept(L_c, consts, solver, dtype):
    """`_resolve`, its answer (Taylor, or its fallback) kept on disk with the
    compiled programs for later processes: deciding traces the order-K Taylor
    program, about as long as loading a sweep's executable."""
    if not (isinstance(solver, Taylor) and solver.fallback is not None):
        return solver
    plain = Taylor(order=solver.order, max_step=solver.max_step)
    decide = lambda: _resolve(L_c, consts, solver, dtype) is not solver.fallback
    origin = (resolved_solver, L_c, np.dtype(dtype).name, solver)
    return plain if executables.remembered(origin, decide) else solver.fallback


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
