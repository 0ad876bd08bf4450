"""Variational (symplectic, momentum-preserving) integrators, as diffrax solvers.

`AbstractVariationalSolver` holds what every such solver shares (the Lagrangian term,
the Newton root finder, the momentum carried in the solver state);
`VariationalMidpoint` is the second-order one. The Gauss–Legendre solvers of orders 4
and 6 are in `_gauss_legendre.py`.
"""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from .._checks import describe
from .._compat import unwrap_time
from .._eom.mechanics import _momenta
from .term import LagrangianTerm


def _unwrap(
    term, solver_name="VariationalMidpoint"
) -> tuple[LagrangianTerm, jax.Array]:
    # diffeqsolve wraps every term in a wrapper that flips time when t1 < t0; the
    # discrete Lagrangian needs the real times, so undo it here.
    term, direction = unwrap_time(term)
    direction = jnp.asarray(direction)
    if not isinstance(term, LagrangianTerm):
        raise TypeError(
            f"`terms` must be a `lagrax.LagrangianTerm(L)`: {solver_name} is "
            "built from the Lagrangian itself, not from a vector field; got "
            f"{type(term).__name__}. Pass `lagrax.LagrangianTerm(L, force=...)` to "
            "`diffrax.diffeqsolve`, or use `lagrax.simulate(L, ..., "
            f"solver=lagrax.{solver_name}(), dt0=h)`."
        )
    return term, direction


def _newton_scales(L, q0, qdot0, t0):
    r"""$(|\mathrm{diag}\,M|, |\mathrm{diag}\,\partial^2L/\partial q^2|)$ at the start
    of a step: the units in which the Newton residuals (momenta) are put back into the
    units of the unknowns."""
    m = jnp.abs(jnp.diag(jax.jacfwd(_momenta, argnums=2)(L, q0, qdot0, t0)))
    dLdq = jax.grad(L, argnums=0)
    kq = jnp.abs(jnp.diag(jax.jacfwd(dLdq, argnums=0)(q0, qdot0, t0)))
    return m, kq


def _promote(sol, *values):
    """The optimistix result as a diffrax one; `nonfinite` for a non-finite answer."""
    result = dfx.RESULTS.promote(sol.result)
    finite = jnp.array(True)
    for value in values:
        finite = finite & jnp.all(jnp.isfinite(value))
    return dfx.RESULTS.where(
        (result == dfx.RESULTS.successful) & ~finite, dfx.RESULTS.nonfinite, result
    )


class AbstractVariationalSolver(dfx.AbstractSolver):
    r"""A fixed-step variational integrator built from a `lagrax.LagrangianTerm`.

    The state is `y = (q, qdot)`; the solver state is `(p, newton_iterations)`, the
    momentum the scheme advances (never recomputed from `qdot`, so it never drifts)
    and a running count of Newton iterations. Each step solves its implicit equations
    with `root_finder` (at most `root_find_max_steps` iterations, `throw=False`); a
    solve that does not converge ends the diffrax solve with the optimistix result
    promoted to `diffrax.RESULTS`, and a non-finite answer with `nonfinite`.
    """

    root_finder: optx.AbstractRootFinder | None = None
    root_find_max_steps: int = eqx.field(static=True, default=16)

    # Any term passes diffrax's own compatibility check (whose message names no
    # argument); `init` then rejects anything but a `LagrangianTerm` with a message
    # naming `terms`.
    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., dfx.LocalLinearInterpolation]] = (
        dfx.LocalLinearInterpolation
    )

    def __check_init__(self):
        if self.root_finder is not None and not isinstance(
            self.root_finder, optx.AbstractRootFinder
        ):
            raise TypeError(
                "`root_finder` must be None or an optimistix root finder (an instance "
                "of `optimistix.AbstractRootFinder`), e.g. "
                "`optimistix.Newton(rtol=1e-8, atol=1e-8)`; got "
                f"{describe(self.root_finder)}."
            )
        steps = self.root_find_max_steps
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(
                f"`root_find_max_steps` must be a positive int; got {steps!r}."
            )

    def _root_finder(self, dtype):
        if self.root_finder is not None:
            return self.root_finder
        tol = float(jnp.finfo(dtype).eps) ** 0.5
        # Cauchy termination: both the Newton update (in the units of the unknowns, as
        # diffrax's tolerances) and the residual (made relative in `step`) are small.
        # (optimistix 0.1.0's rate-based test, cauchy_termination=False, reports
        # "diverged" at the second iteration unless it has already converged.)
        return optx.Newton(rtol=tol, atol=tol, linear_solver=lx.LU())

    def _root_find(self, residual, guess):
        return optx.root_find(
            residual,
            self._root_finder(guess.dtype),
            guess,
            max_steps=self.root_find_max_steps,
            throw=False,
        )

    def init(self, terms, t0, t1, y0, args):
        term, direction = _unwrap(terms, type(self).__name__)
        q0, qdot0 = y0
        p0 = _momenta(term.L, q0, qdot0, direction * t0)
        return p0, jnp.array(0, dtype=jnp.int32)

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def _discrete_momenta(L, force, q0, dq, t0, h):
    r"""$(-\partial L_d/\partial q_0 - f^-_d,\ \partial L_d/\partial q_1 + f^+_d)$ at
    $q_1 = q_0 + \Delta q$.

    With $L_d = h L(\bar q, v, \bar t)$, $\bar q = (q_0+q_1)/2$, $v = (q_1-q_0)/h$,
    $\bar t = t_0 + h/2$ the chain rule gives
    $\mp\partial L_d/\partial q_{0,1} = \partial L/\partial \dot q \mp
    \tfrac h2\,\partial L/\partial q$, evaluated at the midpoint. Written this way (one
    gradient of $L$) rather than as `grad` of $L_d$, which is the same up to the
    rounding of $h \cdot (1/h)$. The forces are the midpoint Lagrange–d'Alembert
    ones, $f^\pm_d = \tfrac h2 Q(\bar q, v, \bar t)$.

    The unknown is the displacement $\Delta q$, not $q_1$: $v = \Delta q/h$ then
    carries no cancellation. With $q_1$ as unknown, $(q_1 - q_0)/h$ has an absolute
    error $\varepsilon |q|/h$: an angle that has wound up to 100 rad, at $h = 0.01$,
    would lose 12 digits of its momentum to it.
    """
    qbar = q0 + 0.5 * dq
    v = dq / h
    tbar = t0 + 0.5 * h
    dLdq, dLdv = jax.grad(L, argnums=(0, 1))(qbar, v, tbar)
    half = 0.5 * h * dLdq
    if force is not None:
        half = half + 0.5 * h * force(qbar, v, tbar)
    return dLdv - half, dLdv + half


class VariationalMidpoint(AbstractVariationalSolver):
    r"""The midpoint variational integrator, built from the Lagrangian $L$.

    The discrete Lagrangian is the midpoint rule for the action over one step $h$,

    $$L_d(q_0, q_1, h) = h\, L\!\left(\frac{q_0+q_1}{2},\ \frac{q_1-q_0}{h},\
        t_0 + \frac h2\right),$$

    and the step is the discrete Euler–Lagrange equations in position–momentum form
    (with the midpoint Lagrange–d'Alembert forces $f^\pm_d = \tfrac h2 Q$ if a force is
    given):

    $$p_0 = -\frac{\partial L_d}{\partial q_0}(q_0, q_1) - f^-_d, \qquad
      p_1 = \frac{\partial L_d}{\partial q_1}(q_0, q_1) + f^+_d.$$

    The first equation is implicit in $q_1$; it is solved by `root_finder` (Newton
    with an autodiff Jacobian and an LU solve by default), together with
    $\partial L/\partial \dot q(q_1, \dot q_1, t_1) = p_1$ for the velocity reported
    in the state. Without forces and explicit time dependence the map
    $(q_0, p_0) \mapsto (q_1, p_1)$ is symplectic, so the energy error stays bounded
    (no secular drift) over very long times, and a momentum conjugate to a cyclic
    coordinate is conserved exactly, up to round-off. Second order, symmetric, fixed
    step: use it with `diffrax.ConstantStepSize` (any `dt0`).

    **State.** As everywhere in lagrax the state is `y = (q, qdot)`. The momentum $p$,
    the quantity the scheme actually advances, is carried in the solver state (so it
    is never recomputed from `qdot` and never drifts); `qdot` is its exact inverse
    Legendre transform. The solver state is `(p, newton_iterations)`: read it with
    `diffrax.SaveAt(..., solver_state=True)` to count the Newton iterations
    honestly (each forms and LU-factorises a $2n\times 2n$ Jacobian).

    **Failure.** A Newton solve that does not converge ends the solve with the
    optimistix result promoted to `diffrax.RESULTS` (`nonlinear_divergence`,
    `nonlinear_max_steps_reached`, `singular`), never with a NaN state and success.

    **Arguments:**

    - `root_finder`: an `optimistix.AbstractRootFinder` for the step's equations, as
        in diffrax's implicit solvers. Default (`None`): `optimistix.Newton` with
        `rtol = atol =` $\sqrt\varepsilon$ of the state's dtype and a `lineax.LU()`
        linear solve (the Jacobian is not symmetric in general). Its tolerances apply
        to the displacement $q_1 - q_0$ and the velocity $\dot q_1$ (in their units),
        and `atol` to the residual relative to the momenta. Newton converges
        quadratically and the last update is applied after the test passes, so the
        solution is accurate to ~$\varepsilon$ all the same; a tighter test can fail
        on round-off alone (a stiff spring's $k(r-1)$ makes $\dot q$ uncertain by
        $h\varepsilon k/m$).
    - `root_find_max_steps`: the most root-finder iterations per step (default 16).

    **Raises:**

    - `TypeError`: `root_finder` is not an `optimistix.AbstractRootFinder`;
        (in `diffrax.diffeqsolve`) the term is not a `lagrax.LagrangianTerm`: a plain
        `diffrax.ODETerm(lagrax.vector_field(L))` carries no Lagrangian to build the
        scheme from. `lagrax.simulate` passes a `LagrangianTerm` itself.
    - `ValueError`: `root_find_max_steps` is not a positive int.

    **Example:**

    ```python
    import diffrax

    L = lagrax.systems.pendulum.lagrangian()
    q0, qdot0 = jnp.array([1.0]), jnp.array([0.0])
    sol = diffrax.diffeqsolve(lagrax.LagrangianTerm(L), lagrax.VariationalMidpoint(),
                              t0=0.0, t1=10.0, dt0=0.01, y0=(q0, qdot0))
    ```
    """

    def order(self, terms):
        return 2

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        term, direction = _unwrap(terms, "VariationalMidpoint")
        L, force = term.L, term.force
        q0, qdot0 = y0
        p0, iterations = solver_state
        s0 = direction * t0
        s1 = direction * t1
        h = s1 - s0
        n = q0.shape[0]

        guess = jnp.concatenate([h * qdot0, qdot0])
        # The residuals are momenta, in whatever units L has. Optimistix stops when
        # the update is small (in the units of dq and qdot1) AND |residual| < atol, so
        # the residual is put in the units of the unknowns: divided by the diagonal
        # of its Jacobian, |M|/h + (h/4)|d²L/dq²| for the first equation and |M| for
        # the second (made relative to the velocities). In momentum units round-off
        # alone could fail the test: a stiff spring k(r - 1) carries an error of
        # eps*k, which only the (h/4)k term of the Jacobian scales away.
        m, kq = _newton_scales(L, q0, qdot0, s0)
        tiny = jnp.finfo(q0.dtype).tiny
        m = jnp.maximum(m, tiny)
        mq = jnp.maximum(m / jnp.abs(h) + 0.25 * jnp.abs(h) * kq, tiny)
        vscale = 1 + jnp.max(jnp.abs(qdot0))
        scale = jnp.concatenate([mq, m * vscale])
        scale = jax.lax.stop_gradient(scale)

        def residual(z, _):
            dq, qdot1 = z[:n], z[n:]
            pm, pp = _discrete_momenta(L, force, q0, dq, s0, h)
            r = jnp.concatenate([pm - p0, _momenta(L, q0 + dq, qdot1, s1) - pp])
            return r / scale

        sol = self._root_find(residual, guess)
        dq, qdot1 = sol.value[:n], sol.value[n:]
        q1 = q0 + dq
        pm, pp = _discrete_momenta(L, force, q0, dq, s0, h)
        # p1 = p0 + (p1 - p0), with p0 = pm solved for and p1 - p0 = pp - pm =
        # h (∂L/∂q + Q) at the midpoint: a momentum whose coordinate L does not
        # depend on (and no force acts on) is then carried over bit for bit, as in
        # the Gauss–Legendre solvers, instead of inheriting the Newton residual,
        # which would random-walk over a long run.
        p1 = p0 + (pp - pm)
        result = _promote(sol, sol.value, p1)
        y1 = (q1, qdot1)
        dense_info = dict(y0=y0, y1=y1)
        new_state = (p1, iterations + sol.stats["num_steps"].astype(jnp.int32))
        return y1, None, dense_info, new_state, result


VariationalMidpoint.__init__.__doc__ = """**Arguments:**

- `root_finder`: an `optimistix.AbstractRootFinder` (default: `optimistix.Newton` at
    $\\sqrt\\varepsilon$ of the dtype with `lineax.LU()`).
- `root_find_max_steps`: the most root-finder iterations per step (default 16).
"""
