"""Gauss–Legendre variational integrators of orders 4 and 6, as diffrax solvers."""

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .variational import (
    _momenta,
    _newton_scales,
    _promote,
    _unwrap,
    AbstractVariationalSolver,
)


def _gauss_legendre_tableau(s):
    """`(a, b, c)` of the s-stage Gauss–Legendre collocation method, float64 NumPy."""
    if s == 2:
        r = np.sqrt(3.0)
        a = np.array([[1 / 4, 1 / 4 - r / 6], [1 / 4 + r / 6, 1 / 4]])
        b = np.array([1 / 2, 1 / 2])
        c = np.array([1 / 2 - r / 6, 1 / 2 + r / 6])
    elif s == 3:
        r = np.sqrt(15.0)
        a = np.array(
            [
                [5 / 36, 2 / 9 - r / 15, 5 / 36 - r / 30],
                [5 / 36 + r / 24, 2 / 9, 5 / 36 - r / 24],
                [5 / 36 + r / 30, 2 / 9 + r / 15, 5 / 36],
            ]
        )
        b = np.array([5 / 18, 4 / 9, 5 / 18])
        c = np.array([1 / 2 - r / 10, 1 / 2, 1 / 2 + r / 10])
    else:  # pragma: no cover - only the two concrete solvers below call this
        raise ValueError(f"no Gauss–Legendre tableau for s = {s}")
    return a, b, c


class AbstractGaussLegendre(AbstractVariationalSolver):
    r"""The $s$-stage Gauss–Legendre variational integrator, order $2s$.

    The discrete Lagrangian is the $s$-point Gauss quadrature of the action over
    the degree-$s$ polynomial through $q_0$ and $q_1$ that makes it stationary,

    $$L_d(q_0, q_1, h) = \operatorname{ext}\, h\sum_i b_i\, L(Q_i, V_i, t_0 + c_i h),
    \qquad Q_i = q_0 + h\sum_j a_{ij} V_j,\quad q_1 = q_0 + h\sum_i b_i V_i,$$

    and its discrete Euler–Lagrange equations are the symplectic partitioned
    Runge–Kutta method that Gauss–Legendre collocation is in position–momentum form
    (for Gauss the partner coefficients $\bar a_{ij} = b_j - b_j a_{ji}/b_i$ equal
    $a_{ij}$). With $P_i = \partial L/\partial\dot q(Q_i, V_i, t_i)$ and
    $F_i = \partial L/\partial q(Q_i, V_i, t_i) + Q(Q_i, V_i, t_i)$:

    $$P_i = p_0 + h\sum_j a_{ij} F_j \ (i = 1..s), \qquad
      p_1 = p_0 + h\sum_i b_i F_i, \qquad
      \frac{\partial L}{\partial\dot q}(q_1, \dot q_1, t_1) = p_1.$$

    The $s$ stage equations (unknowns: the stage velocities $V_i$) and the last one
    (unknown: $\dot q_1$, the velocity reported in the state) are solved together by
    `root_finder`, an $(s+1)n$-dimensional system. Without forces and explicit time
    dependence the map $(q_0, p_0)\mapsto(q_1, p_1)$ is symplectic and symmetric, so
    the energy error stays bounded over very long times, and the momentum conjugate to
    a cyclic coordinate is conserved up to round-off. Fixed step: use it with
    `diffrax.ConstantStepSize`.

    The state, solver state `(p, newton_iterations)`, failures and arguments are those
    of `lagrax.VariationalMidpoint` (the root finder's tolerances apply to the stage
    velocities and $\dot q_1$, in their units).
    """

    stages: ClassVar[int]

    def order(self, terms):
        return 2 * self.stages

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        term, direction = _unwrap(terms, type(self).__name__)
        L, force = term.L, term.force
        q0, qdot0 = y0
        p0, iterations = solver_state
        s0 = direction * t0
        s1 = direction * t1
        h = s1 - s0
        n = q0.shape[0]
        s = self.stages
        dtype = q0.dtype
        a, b, c = (jnp.asarray(x, dtype) for x in _gauss_legendre_tableau(s))
        ts = s0 + c * h

        def stage_forces(Q, V, t):
            dLdq, dLdv = jax.grad(L, argnums=(0, 1))(Q, V, t)
            if force is not None:
                dLdq = dLdq + force(Q, V, t)
            return dLdq, dLdv

        def stages(V):
            Q = q0[None] + h * (a @ V)
            F, P = jax.vmap(stage_forces)(Q, V, ts)
            return F, P

        # The residuals are momenta; put them in the units of the unknowns
        # (velocities) by the diagonal of their Jacobian, |M| + h² a_ii |∂²L/∂q²|
        # (bounded with max a), made relative to the velocities. In momentum units
        # round-off alone could fail the test: a stiff spring k(r - 1) carries an
        # error of eps*k, which only the h² k term scales away.
        m, kq = _newton_scales(L, q0, qdot0, s0)
        tiny = jnp.finfo(dtype).tiny
        m = jnp.maximum(m, tiny)
        vscale = 1 + jnp.max(jnp.abs(qdot0))
        mq = m + h**2 * float(np.max(np.abs(_gauss_legendre_tableau(s)[0]))) * kq
        scale = jnp.concatenate([jnp.tile(mq, s), m]) * vscale
        scale = jax.lax.stop_gradient(scale)

        def residual(z, _):
            V, qdot1 = z[: s * n].reshape(s, n), z[s * n :]
            F, P = stages(V)
            q1 = q0 + h * (b @ V)
            p1 = p0 + h * (b @ F)
            r_stages = P - p0[None] - h * (a @ F)
            r_end = _momenta(L, q1, qdot1, s1) - p1
            return jnp.concatenate([r_stages.reshape(-1), r_end]) / scale

        guess = jnp.concatenate([jnp.tile(qdot0, s), qdot0])
        sol = self._root_find(residual, guess)
        V, qdot1 = sol.value[: s * n].reshape(s, n), sol.value[s * n :]
        F, _ = stages(V)
        q1 = q0 + h * (b @ V)
        p1 = p0 + h * (b @ F)
        result = _promote(sol, sol.value, p1)
        y1 = (q1, qdot1)
        dense_info = dict(y0=y0, y1=y1)
        new_state = (p1, iterations + sol.stats["num_steps"].astype(jnp.int32))
        return y1, None, dense_info, new_state, result


class GaussLegendre4(AbstractGaussLegendre):
    r"""The 2-stage Gauss–Legendre variational integrator: order 4, symplectic.

    Stage times $t_0 + (\frac12 \mp \frac{\sqrt3}{6})h$, weights $\frac12, \frac12$.
    The step solves, for the stage velocities $V_i$ and $\dot q_1$,
    $P_i = p_0 + h\sum_j a_{ij}F_j$, $p_1 = p_0 + h\sum_i b_i F_i$,
    $\partial L/\partial\dot q(q_1, \dot q_1, t_1) = p_1$, with
    $P_i, F_i = \partial L/\partial\dot q, \partial L/\partial q\ (+Q)$ at the stages
    $Q_i = q_0 + h\sum_j a_{ij}V_j$: the discrete Euler–Lagrange equations of the
    2-point Gauss quadrature of the action. Symplectic and symmetric without forces
    or explicit time dependence: bounded energy error, Noether momenta conserved to
    round-off. State `(q, qdot)`, solver state `(p, newton_iterations)` and failures
    as `lagrax.VariationalMidpoint`. Fixed step (`diffrax.ConstantStepSize`).

    **Arguments:**

    - `root_finder`: an `optimistix.AbstractRootFinder` for the $3n$ step equations
        (default: `optimistix.Newton` at $\sqrt\varepsilon$ of the dtype, LU solve).
    - `root_find_max_steps`: the most root-finder iterations per step (default 16).

    **Example:**

    ```python
    import diffrax

    L = lagrax.systems.pendulum.lagrangian()
    q0, qdot0 = jnp.array([1.0]), jnp.array([0.0])
    sol = diffrax.diffeqsolve(lagrax.LagrangianTerm(L), lagrax.GaussLegendre4(),
                              t0=0.0, t1=100.0, dt0=0.1, y0=(q0, qdot0))
    ```
    """

    stages: ClassVar[int] = 2


class GaussLegendre6(AbstractGaussLegendre):
    r"""The 3-stage Gauss–Legendre variational integrator: order 6, symplectic.

    Stage times $t_0 + (\frac12 - \frac{\sqrt{15}}{10})h,\ t_0 + \frac h2,\
    t_0 + (\frac12 + \frac{\sqrt{15}}{10})h$, weights $\frac5{18}, \frac49,
    \frac5{18}$. The scheme is that of `lagrax.GaussLegendre4` with the 3-point Gauss
    quadrature; state, solver state and failures as `lagrax.VariationalMidpoint`.

    **Arguments:**

    - `root_finder`: an `optimistix.AbstractRootFinder` for the $4n$ step equations
        (default: `optimistix.Newton` at $\sqrt\varepsilon$ of the dtype, LU solve).
    - `root_find_max_steps`: the most root-finder iterations per step (default 16).

    **Example:**

    ```python
    import diffrax

    L = lagrax.systems.pendulum.lagrangian()
    q0, qdot0 = jnp.array([1.0]), jnp.array([0.0])
    sol = diffrax.diffeqsolve(lagrax.LagrangianTerm(L), lagrax.GaussLegendre6(),
                              t0=0.0, t1=100.0, dt0=0.2, y0=(q0, qdot0))
    ```
    """

    stages: ClassVar[int] = 3
