"""Which stepper the period kernel steps with, from the solver a user passes."""

import weakref

import jax
import jax.numpy as jnp

from .._jaxpr.switches import switches
from .._stepper.base import AbstractStepper
from .._stepper.runge_kutta import RungeKuttaStepper
from .._stepper.taylor import TaylorStepper
from .._taylor.solver import Taylor
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
