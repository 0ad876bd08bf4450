"""`Taylor`: the period kernel's Taylor integrator, as a solver to pass."""

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .diffrax_solver import AbstractTaylorSolver
from .program import taylor_coefficients


__all__ = ["Taylor"]


class Taylor(AbstractTaylorSolver):
    r"""A Taylor integrator (heyoka's method): a diffrax solver, and the stepper of
    `period`, `sweep_periods` and `simulate_batch`.

    Each step expands the trajectory to order $K$ about the current state (its Taylor
    coefficients by recurrences from the acceleration's jaxpr, one transcendental
    call per node per step) and takes the step length from the last coefficients,
    before the step: a fraction of the radius of convergence $\rho$ estimated from the
    last four orders (from rest the odd coefficients vanish, and two orders could rest
    on one coefficient passing through zero),

    $$h = \Bigl(\frac{\varepsilon}{C}\Bigr)^{1/(K+1)} \rho,\qquad
    \rho = \min_{K-3 \le j \le K} \lVert y_j\rVert_\infty^{-1/j},\qquad
    \varepsilon = \text{atol} + \text{rtol}\,\lVert y_0\rVert_\infty,\qquad C = 256,$$

    with $y_j$ the order-$j$ coefficients of the state $y = (q, \dot q)$: the first
    term the step drops, extrapolated from the last ones as $(h/\rho)^{K+1}$, is
    $\varepsilon/C$. That is about the true local error of a diffrax `Dopri8` or
    `Tsit5` step at the same tolerance (their controllers bound an embedded
    lower-order estimate, tens of times the error of the solution they keep), and of
    heyoka.py's step (which picks its order from the tolerance and steps $\rho/e^2$):
    at the same `rtol` and `atol`, `Taylor` ends as close to the exact solution as
    `Dopri8` or closer, down to float64's rounding floor (`benchmarks/accuracy.py`:
    a double pendulum, a chain of four pendulums, Kepler's problem at eccentricity
    0.9, the pendulum near its separatrix, tolerances 1e-8 to 1e-13). In the period
    kernel (`period`, `sweep_periods`) the factor is Jorba and Zou's at a fixed
    order, $h = e^{-0.7/(K-1)}\,\varepsilon^{1/K}\rho$ (the last term kept about
    $\varepsilon/2$), with $\varepsilon$ on the lane's scaled state: there a period's
    error at a tolerance is already no larger than with `Dopri8`. A step is never
    longer than `max_step` in the lane's units of time (a fraction of its
    small-amplitude period, so that no event can be stepped over).

    The coefficients follow the branches a Lagrangian takes at the step's start
    (`jnp.where` on a comparison, `abs`, `max`, `floor`, ...): past a switch the
    polynomial continues the old branch. Where `L` (or the force) has such a switch,
    each step is checked where it ends, its defect
    $h\,\lVert \ddot q(t_1) - p_{\ddot q}(h)\rVert_\infty/((K+1)\varepsilon)$
    (the acceleration there against the polynomial's; for a smooth one about the
    first term dropped over $\varepsilon$, $1/C$), and a step whose defect exceeds 1
    is rejected and the next one shortened, as a Runge–Kutta pair's estimate does
    across such a switch (`simulate_batch`; as a diffrax solver the defect joins the
    error estimate); a Lagrangian without one pays nothing. The period kernel, which
    never rejects a step, checks every step the same way and fails a lane whose step
    has a defect above 100 (`solver_failed`); `Taylor(fallback=diffrax.Dopri8())`,
    the default of `sweep_periods`, steps such a Lagrangian with its fallback there.

    The polynomials are the solution over the whole step, so an event (a turning
    point) is located inside the step that crosses it, as the root of the event
    function's polynomial with one Newton correction by the exact event value;
    where that correction does not settle to round-off, the step is re-taken from
    the same base with the step length as the unknown, as for Runge–Kutta solvers.

    **As a diffrax solver** (`diffrax.diffeqsolve(term, lagrax.Taylor(), ...)` with
    any `diffrax.ODETerm` whose vector field is built from primitives with a
    recurrence, e.g. `lagrax.vector_field(L)`, any pytree state and any number of
    coordinates; `lagrax.simulate(..., solver=lagrax.Taylor())`): each step expands
    $y' = f(t, y)$ to order $K$ about its start and evaluates the polynomial at the
    step the controller proposes. The error estimate is the rule above per entry,
    $e_i = C\,(|h| \max_{K-3 \le j \le K} |y_{j,i}|^{1/j})^{K+1}$, of error order
    $K + 1$: a `diffrax.PIDController` keeps $e_i \le$ atol + rtol $|y_i|$ and
    proposes the rule's step for the next (rejecting a step only where the rule's
    step shrinks faster than its `safety`). Dense output (`SaveAt(ts=...)`,
    `SaveAt(dense=True)`, `Solution.evaluate`) and `diffrax.Event` root finding read
    the step's own
    polynomial. Forward mode (`jax.jvp`, `jax.jacfwd`, `diffrax.ForwardMode`) and
    reverse mode through `diffrax.RecursiveCheckpointAdjoint` differentiate it;
    `BacksolveAdjoint` integrates an adjoint vector field whose jaxpr (transposed
    products) is not guaranteed to have recurrences. For $n \ge 3$ coordinates the
    mass-matrix solve of `lagrax.vector_field` is expanded with one factorization of
    $M_0$ per step. A step program of a few hundred nodes times orders or more (the
    double pendulum at order 20) is computed by a compact program (the
    recurrences as data, loops over dependency levels and orders, as heyoka.py's
    compact mode), which XLA compiles in seconds under any `jit`, yours
    included, with no compiler option; a caller's `jax.vmap` becomes its lanes.
    Smaller ones are written out order by order (fastest); `simulate` called
    outside `jit` compiles those with XLA's elemental CPU emitters.

    In the period kernel, the acceleration's jaxpr must consist of primitives with a
    recurrence. For one that has none, `Taylor()` raises
    `NotImplementedError` at the first call, naming the primitive and listing those
    supported, and `Taylor(fallback=diffrax.Dopri8())` (the default solver of
    `sweep_periods`) steps with the fallback instead. The fallback also steps where
    the coefficients' straight-line program would exceed ~2000 equations (the
    θ-form cycloid, the rotating hoop): the kernel would then loop over the orders,
    several times slower than Dopri8 per period and slower to compile; a plain
    `Taylor()` still takes that loop, and where L switches branch (above). Which
    one ran is `SweepResult.solver`. Its
    forward-mode derivative (the recurrence's tangent, for `jax.grad` of a sweep)
    compiles longer than a Runge–Kutta step's.

    **Arguments:**

    - `order`: $K$, the degree of the polynomials (default 20: the order heyoka.py
        picks for float64 at its default tolerance; $K \geq 2$).
    - `max_step`: the period kernel's longest step in the lane's units of time,
        $\sqrt{|q_0| / |\ddot q_0|}$ (default 2, a third of a small oscillation's
        period); unused by diffrax (its controller's `dtmax`) and `simulate_batch`.
    - `fallback`: `None` (default), or an adaptive explicit Runge–Kutta diffrax
        solver to step with where the acceleration has a primitive without a
        recurrence or a program too large to unroll.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    res = lagrax.sweep_periods(L, jnp.linspace(0.01, 3.1, 4096), solver=lagrax.Taylor())
    ```
    """

    order: int = eqx.field(static=True, default=20)
    max_step: float = eqx.field(static=True, default=2.0)
    fallback: "dfx.AbstractERK | None" = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not isinstance(self.order, int) or isinstance(self.order, bool):
            raise TypeError(f"`order` must be an int >= 2; got {self.order!r}.")
        if self.order < 2:
            raise ValueError(f"`order` must be at least 2; got {self.order}.")
        if not (isinstance(self.max_step, (int, float)) and 0 < self.max_step < np.inf):
            raise ValueError(
                f"`max_step` must be a positive finite number; got {self.max_step!r}."
            )
        if self.fallback is not None and not (
            isinstance(self.fallback, dfx.AbstractERK)
            and getattr(type(self.fallback).tableau, "b_error", None) is not None
        ):
            raise TypeError(
                "`fallback` must be None or an adaptive explicit Runge–Kutta diffrax "
                f"solver, e.g. diffrax.Dopri8(); got {self.fallback!r}."
            )

    def supports(self, accel: Callable, dtype, *params) -> bool:
        """Whether there is a recurrence for every primitive of
        `accel(s, x, v, *params)` (scalars `s, x, v`; `params` shape-dtype specs or
        arrays without a lane axis): traced once, nothing is evaluated."""
        coeffs = taylor_coefficients(lambda s, x, v, p: accel(s, x, v, *p), 2, dtype)
        try:
            _trace(coeffs, dtype, params)
        except NotImplementedError:
            return False
        return True

    def unrolls(self, accel: Callable, dtype, *params) -> bool:
        """Whether the period kernel computes `accel`'s coefficients at this order as
        one straight-line program (of at most ~2000 equations) rather than by the
        slower loop over orders; arguments as `supports` (which must hold). Traced
        once, nothing is evaluated."""
        coeffs = taylor_coefficients(
            lambda s, x, v, p: accel(s, x, v, *p),
            self.order,
            dtype,
            unrolled=True,
            vectorized_trig=True,
        )
        _trace(coeffs, dtype, params)
        return coeffs.unrolled


def _trace(coeffs, dtype, params):
    """`coeffs` traced for one lane: `params` (shape-dtype specs or arrays) get a lane
    axis of length 1."""
    lanes = [
        jax.ShapeDtypeStruct((1, *p.shape), p.dtype)
        if isinstance(p, jax.ShapeDtypeStruct)
        else jax.ShapeDtypeStruct((1, *np.shape(p)), jnp.asarray(p).dtype)
        for p in params
    ]
    one = jax.ShapeDtypeStruct((1,), dtype)
    jax.eval_shape(lambda s, x, v, p: coeffs(s, x, v, p), one, one, one, lanes)
