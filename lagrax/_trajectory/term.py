"""The term of Lagrange's equations: what every diffrax solver integrates."""

import weakref

import diffrax as dfx
import equinox as eqx
import jax
from jax.extend import core as jax_core

from .._checks import check_callable, is_concrete
from .._custom_types import GeneralizedForce, Lagrangian
from .._eom.mechanics import _accelerations
from .._jaxpr.canonical import BoundLagrangian as BoundLagrangian
from .._jaxpr.fusion import fusion_is_off


class _LagrangeVectorField(eqx.Module):
    # What `lagrax.vector_field(L)` returns, as a Module rather than a fresh closure:
    # two terms built from the same `L` then compare equal, so `diffeqsolve` (an
    # `eqx.filter_jit`) reuses its compilation instead of recompiling on every call.
    L: Lagrangian
    force: GeneralizedForce | None

    def __call__(self, t, y, args):
        q, qdot = y
        if isinstance(self.L, BoundLagrangian):
            return qdot, _bound_accelerations(self.L, q, qdot, t, self.force)
        qddot, _ = _accelerations(self.L, q, qdot, t, self.force)
        return qdot, qddot


# Jaxprs of the accelerations per canonical Lagrangian (dropped with it), then per
# (force, fusion off, avals), the constants among their inputs.
_DERIVED = weakref.WeakKeyDictionary()


def _bound_accelerations(bound, q, qdot, t, force):
    """The accelerations of `bound`; under a trace, derived once per canonical
    Lagrangian and replayed (a solver traces its vector field several times, and
    deriving costs more than the rest of that tracing). The constants are inputs of
    the kept jaxpr: closed over, they would be tracers of the enclosing program,
    which no jaxpr kept past it may hold (`_accelerations` derives again at every
    trace for such a Lagrangian)."""
    args = (q, qdot, t, *bound.consts)
    if is_concrete(args):
        return _accelerations(bound, q, qdot, t, force)[0]

    def derive(q, qdot, t, *consts):
        return _accelerations(BoundLagrangian(bound.L, consts), q, qdot, t, force)[0]

    try:
        table = _DERIVED.setdefault(bound.L, {})
        key = (force, fusion_is_off(), tuple(jax.typeof(x) for x in args))
        closed = table.get(key)
    except TypeError:  # (an unhashable force)
        return derive(*args)
    if closed is None:
        closed = jax.make_jaxpr(derive)(*args)
        if any(isinstance(c, jax.core.Tracer) for c in closed.consts):
            return derive(*args)  # (`force` closes over a tracer: not kept)
        table[key] = closed
    (qddot,) = jax_core.jaxpr_as_fun(closed)(*args)
    return qddot


class LagrangianTerm(dfx.ODETerm):
    r"""The term of Lagrange's equations, carrying the Lagrangian itself.

    It is a `diffrax.ODETerm` for the first-order system
    $\frac{d}{dt}(q, \dot q) = (\dot q, \ddot q)$ (so every diffrax solver accepts it),
    and it also keeps `L` and `force`, which `lagrax.VariationalMidpoint` needs: a
    variational integrator is built from the Lagrangian, not from the vector field.

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar`.
    - `force`: optional generalized non-conservative force `force(q, qdot, t) -> Q`.

    **Example:**

    ```python
    import diffrax

    L = lagrax.systems.pendulum.lagrangian()
    q0, qdot0 = jnp.array([1.0]), jnp.array([0.0])
    term = lagrax.LagrangianTerm(L)
    sol = diffrax.diffeqsolve(term, lagrax.VariationalMidpoint(), 0.0, 10.0, 0.01,
                              (q0, qdot0))
    ```
    """

    L: Lagrangian
    force: GeneralizedForce | None

    def __init__(self, L: Lagrangian, force: GeneralizedForce | None = None):
        check_callable(L, "L", "a function L(q, qdot, t) -> scalar")
        if force is not None:
            check_callable(force, "force", "a function force(q, qdot, t) -> Q")
        self.L = L
        self.force = force
        self.vector_field = _LagrangeVectorField(L, force)
