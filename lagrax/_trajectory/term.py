"""The term of Lagrange's equations: what every diffrax solver integrates."""

import diffrax as dfx
import equinox as eqx

from .._checks import check_callable
from .._custom_types import GeneralizedForce, Lagrangian
from .._eom.mechanics import _accelerations


class _LagrangeVectorField(eqx.Module):
    # What `lagrax.vector_field(L)` returns, as a Module rather than a fresh closure:
    # two terms built from the same `L` then compare equal, so `diffeqsolve` (an
    # `eqx.filter_jit`) reuses its compilation instead of recompiling on every call.
    L: Lagrangian
    force: GeneralizedForce | None

    def __call__(self, t, y, args):
        q, qdot = y
        qddot, _ = _accelerations(self.L, q, qdot, t, self.force)
        return qdot, qddot


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
