r"""`Taylor`: the Taylor integrator, as a solver to pass.

What its docstring leaves out:

- In the period kernel (`period`, `sweep_periods`) the step factor is Jorba and
  Zou's at a fixed order, $h = e^{-0.7/(K-1)}\,\varepsilon^{1/K}\rho$ (the last term
  kept about $\varepsilon/2$), with $\varepsilon$ on the lane's scaled state, and a
  step is never longer than `max_step`.
- The step's check across a switch of the acceleration is its defect
  $h\,\lVert \ddot q(t_1) - p_{\ddot q}(h)\rVert_\infty/((K+1)\varepsilon)$ (the
  acceleration where the step ends against its polynomial's; about $1/C$ for a
  smooth one): above 1 `simulate_batch` rejects the step and shortens the next; as a
  diffrax solver the defect joins the error estimate; the period kernel, which never
  rejects a step, fails a lane whose defect exceeds 100. A Lagrangian without a
  switch pays nothing.
- As a diffrax solver the error estimate is the step rule per entry,
  $e_i = C\,(|h| \max_{K-3 \le j \le K} |y_{j,i}|^{1/j})^{K+1}$: a
  `diffrax.PIDController` keeps $e_i \le$ atol + rtol $|y_i|$ and proposes the
  rule's step for the next, rejecting a step only where the rule's step shrinks
  faster than its `safety`.
- An event is the root of the event function's polynomial with one Newton
  correction by the exact event value; where that does not settle to round-off,
  the step is re-taken from its start with the step length as the unknown, as for
  Runge–Kutta solvers.
- For $n \ge 3$ coordinates the mass-matrix solve of `lagrax.vector_field` is
  expanded with one factorization of $M_0$ per step. Programs of a few hundred
  nodes times orders or more run as the compact program; smaller ones are written
  out order by order (fastest).
"""

import enum
import math
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .diffrax_solver import AbstractTaylorSolver
from .program import taylor_coefficients


__all__ = ["Taylor"]


# The order where none is given and none is chosen: the period kernel's and the
# diffrax solver's (tuned there).
DEFAULT_ORDER = 20
# `chosen_order`'s lowest: the lowest order measured (benchmarks/orders.py).
LOWEST_ORDER = 12


class _Order(enum.IntEnum):
    """`order` where none was given: `CHOSEN` equals `DEFAULT_ORDER` (the period
    kernel and the diffrax solver step at it, and `Taylor()` equals itself rebuilt
    from its fields) and marks the order for `simulate_batch` to choose per call.
    (An enumeration member: the disk cache's pre-keys write it out.)"""

    CHOSEN = DEFAULT_ORDER

    def __repr__(self):  # (`Taylor()` prints as it is built: `Taylor(order=None)`)
        return "None"


def _order_or_default(order):
    return _Order.CHOSEN if order is None else order


def order_is_chosen(solver) -> bool:
    """Whether `solver`'s order was left to `chosen_order` (`Taylor(order=None)`)."""
    return solver.order is _Order.CHOSEN


def chosen_order(tol) -> int:
    """The Taylor order of `Taylor`'s docstring for the tolerance `tol` (a float, or
    None where it is not known when traced)."""
    if tol is None or not tol > 0:
        return DEFAULT_ORDER
    # heyoka.py's order for `tol`, rounded up to an even order.
    K = math.ceil(1 - math.log(tol) / 2)
    return min(max(K + K % 2, LOWEST_ORDER), DEFAULT_ORDER)


class Taylor(AbstractTaylorSolver):
    r"""A Taylor integrator of order $K$ (heyoka.py's method): a diffrax solver, and
    the stepper of `simulate_batch`, `period` and `sweep_periods`.

    Each step expands the solution to order $K$ about its start (the Taylor
    coefficients by recurrences from the jaxpr of the vector field, one
    transcendental call per node per step) and takes its length from the last
    coefficients, before the step:

    $$h = \Bigl(\frac{\varepsilon}{C}\Bigr)^{1/(K+1)} \rho,\qquad
    \rho = \min_{K-3 \le j \le K} \lVert y_j\rVert_\infty^{-1/j},\qquad
    \varepsilon = \text{atol} + \text{rtol}\,\lVert y_0\rVert_\infty,\qquad C = 256,$$

    so that the first term dropped is about $\varepsilon/C$: at the same `rtol` and
    `atol` a solve ends as close to the exact solution as with `diffrax.Dopri8()`, or
    closer (`benchmarks/README.md`). The polynomial is the solution over the whole
    step: dense output (`SaveAt(ts=...)`, `Solution.evaluate`) and events
    (`diffrax.Event`, a period's turning points) read it.

    **Where it runs:**

    - `lagrax.simulate(..., solver=lagrax.Taylor())`, or
        `diffrax.diffeqsolve(term, lagrax.Taylor(), ...)` with any `diffrax.ODETerm`
        whose vector field has a recurrence for each of its primitives (e.g.
        `lagrax.vector_field(L)`) and any pytree state: its error estimate, of order
        $K + 1$, drives a `diffrax.PIDController`. Forward mode and
        `diffrax.RecursiveCheckpointAdjoint` differentiate it (not
        `BacksolveAdjoint`). Under your own `jit` and `vmap` it needs no compiler
        option: a large step program (the double pendulum at order 20) is computed
        by a compact program (the recurrences as data, as heyoka.py's compact mode),
        which XLA compiles in seconds.
    - `simulate_batch` (its default solver), `period` and `sweep_periods` (whose
        default is `Taylor(fallback=diffrax.Dopri8())`).

    **Limits:** the coefficients follow the branch a Lagrangian takes at the step's
    start (`jnp.where` on a comparison, `abs`, `max`, `floor`, ...): past a switch
    the polynomial continues the old branch. Where `L` has such a switch, each step
    is checked where it ends and rejected across it (by `simulate_batch`, and as a
    diffrax solver through its error estimate);
    the period kernel fails such a lane (`solver_failed`) and a `fallback` steps it
    instead. A primitive without a recurrence raises `NotImplementedError` at the
    first call, naming it; in the period kernel a `fallback` steps there too, and
    where the coefficients' program is too large to unroll (the θ-form cycloid, the
    rotating hoop), where the loop over orders runs slower than `Dopri8`.
    `SweepResult.solver` says which stepped.

    **Arguments:**

    - `order`: $K \geq 2$, the degree of the polynomials, or `None` (default):
        `simulate_batch` then chooses it per call from the tolerance, as heyoka.py
        does, rounded up to an even order (an odd order ends farther from the
        solution at the same tolerance), within $[12, 20]$:
        $K = 2\lceil\lceil 1 - \ln(\text{tol})/2\rceil / 2\rceil$ with tol the
        tightest release's $\max(\text{rtol}, \text{atol})$: 12 down to 1e-9, 14
        to 1e-11, 16 to 1e-13, 18 at 1e-14, 20 from 1e-15 on and where the
        tolerances are traced (each order its own compiled program: give `order`
        to keep one program across tolerances). Elsewhere (the period kernel, the
        diffrax solver) `None` means 20, the order heyoka.py picks for float64 at
        its default tolerance. Figures: `benchmarks/README.md`.
    - `max_step`: the period kernel's longest step in the lane's units of time,
        $\sqrt{|q_0| / |\ddot q_0|}$ (default 2, a third of a small oscillation's
        period, so that no event is stepped over); unused elsewhere.
    - `fallback`: `None` (default), or an adaptive explicit Runge–Kutta diffrax
        solver for the period kernel to step with where the Taylor step cannot
        (above).

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    sol = lagrax.simulate(L, jnp.array([1.0]), jnp.array([0.0]), 0.0, 10.0,
                          solver=lagrax.Taylor(), rtol=1e-12, atol=1e-12)
    ```
    """

    order: int = eqx.field(static=True, default=None, converter=_order_or_default)
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

    def _unrolls(self, accel: Callable, dtype, *params) -> bool:
        """Whether the period kernel computes `accel`'s coefficients at this order as
        one straight-line program (of at most ~2500 equations) rather than by the
        slower loop over orders (raises `NotImplementedError` for a primitive
        without a recurrence): `accel(s, x, v, *params)` with scalars `s, x, v` and
        `params` shape-dtype specs or arrays without a lane axis. Traced once,
        nothing is evaluated."""
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
