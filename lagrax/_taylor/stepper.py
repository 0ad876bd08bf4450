r"""A Taylor step of order $K$ (heyoka.py's method), its coefficients by recurrence.

The coefficients come from the acceleration's jaxpr (`taylor_coefficients`), written
out order by order; the step length comes from the last coefficients before the step
is taken, so the step itself rejects nothing: where the acceleration switches branch
inside a step, its defect says so (`TaylorStepper.defect`; the period kernel's lane
fails, a trajectory loop rejects the step). The step's outputs, and everything a caller
reads from its polynomials (`within`), leave through ONE fusion (`one_fusion`): XLA
on a CPU would otherwise copy the shared recurrence into each consumer.
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._stepper.base import (
    abs_max,
    AbstractStepper,
    fused,
    horner,
    lane_max,
    LaneField,
    StepResult,
    TaylorExpansion,
    within_or_identity,
)
from .program import taylor_coefficients, transcendental_reads


# The trajectories' step (`simulate_batch`, `Taylor` as a diffrax solver): the first
# term dropped at rtol/TRUNCATION, where the true local error of diffrax's Dopri8 and
# Tsit5 steps sits at the same tolerance (their controllers bound an embedded
# lower-order estimate, tens of times the error of the solution they keep).
# Calibrated on the error at t1 against Dopri8's (`benchmarks/accuracy.py`).
TRUNCATION = 256.0
# A loop that never rejects a step (the period kernel) fails a lane whose step has a
# defect (`TaylorStepper.defect`) above this: an analytic acceleration's is below 1.
KERNEL_DEFECT = 100.0


def log2_approx(n):
    """log2 of a positive float to 0.014 (frexp and a cubic; no libm call): the
    step-length rule's j-th roots need only a few digits."""
    m, e = jnp.frexp(n)  # n = m 2^e, m in [1/2, 1)
    t = 2.0 * m - 1.0
    return e.astype(n.dtype) - 1.0 + t * (1.4425 + t * (-0.7213 + t * 0.2788))


class TaylorStepper(AbstractStepper):
    r"""The Taylor step of order $K$ = `order`, never longer than `max_step`.

    The step length is a fraction of the radius of convergence $\rho$ estimated from
    the last four orders,

    $$h = f(\varepsilon)\,\rho,\qquad \rho = \min_{K-3 \le j \le K}
    \lVert (x_j, v_j)\rVert_\infty^{-1/j},\qquad
    \varepsilon = \text{atol} + \text{rtol}\,\lVert (x_0, v_0)\rVert_\infty,$$

    (the last four orders instead of two: from rest $x(s)$ is even, its odd
    coefficients vanish, and the last two orders would rest on one number that passes
    through zero as the amplitude varies, a first step too long on some
    amplitudes). With `truncation` $= C$ (trajectories),
    $f = (\varepsilon/C)^{1/(K+1)}$: the first term the step drops, extrapolated as
    $(h/\rho)^{K+1}$, is $\varepsilon/C$.
    With `truncation=None` (the period kernel), Jorba and Zou's (and heyoka.py's)
    factor at a fixed order, $f = e^{-0.7/(K-1)}\,\varepsilon^{1/K}$: the last term
    kept is about $\varepsilon/2$. Coefficients from `coefficients`: a subclass that
    computes them otherwise (from a tape) keeps the rest of the step.

    With an acceleration (`field.accel`, the period kernel) and `checked` (its caller
    clears it where the acceleration has no switch: `lagrax._jaxpr.switches`) the
    step checks its end: where its defect (`defect`) exceeds `KERNEL_DEFECT` its
    state is NaN, and the lane fails. Without one (`field.accel=None`, a trajectory
    loop) it ends with its polynomials' acceleration, which the caller checks
    against the true one (`defect`) where the acceleration may switch branch.
    """

    order: int = eqx.field(static=True)
    max_step: float = eqx.field(static=True)
    truncation: float | None = eqx.field(static=True, default=None, kw_only=True)
    checked: bool = eqx.field(static=True, default=True, kw_only=True)

    rejects: ClassVar[bool] = False
    # How the step's outputs leave its one loop (`fused`): see `one_fusion` and
    # `fuses_by_select`.
    branch_free: ClassVar[bool] = False

    @property
    def error_order(self):
        return self.order

    @property
    def safety(self) -> float:
        r"""$e^{-0.7/(K-1)}$, the step-length rule's factor (a weak Python float)."""
        return float(np.exp(-0.7 / (self.order - 1)))

    def radius_fraction(self, tol):
        r"""$h/\rho$ of a free step, $f(\varepsilon)$: the rule takes the radius of
        convergence $\rho$ times this."""
        return self._fraction(tol, jnp.zeros_like(tol), jnp.exp2)

    def _fraction(self, tol, lg, exp2):
        r"""$f(\varepsilon)\,2^{-\text{lg}}$, by one `exp2`."""
        K = self.order
        if self.truncation is None:
            return self.safety * exp2(jnp.log2(tol) / K - lg)
        return exp2((jnp.log2(tol) - float(np.log2(self.truncation))) / (K + 1) - lg)

    def tolerance(self, x, v, rtol, atol):
        r"""$\varepsilon = \text{atol} + \text{rtol}\,\lVert (x, v)\rVert_\infty$ per
        lane."""
        return atol + rtol * lane_max(abs_max(x, v))

    def gap(self, as_, a1, h):
        r"""$\lVert a_1 - p_a(h)\rVert_\infty$: the acceleration `a1` where the step
        ends against its polynomial's there, $p_a(h) = \sum_k a_k h^k$."""
        return lane_max(jax.tree.map(lambda a, p: jnp.abs(a - p), a1, horner(as_, h)))

    def defect(self, step: StepResult, a1, x, v, rtol, atol):
        r"""The defect of a step taken with `field.accel=None` (whose `a` is then its
        polynomial's acceleration where it ends, $p_a(h)$), as an error ratio:

        $$r = \frac{h\,\lVert a_1 - p_a(h)\rVert_\infty}{(K+1)\,\varepsilon},$$

        `a1` the true acceleration there and $\varepsilon$ the step's tolerance (from
        its start `x`, `v`). For an analytic acceleration $a_1 - p_a(h)$ is the
        truncation of $p_a$, $(K+1)/h$ times the first term the step drops, so $r$
        is that term over $\varepsilon$: $1/C$ with `truncation` $C$. Where a branch
        of the acceleration (`jnp.where`, `abs`, `max`, ...) switches inside the step,
        the polynomials, decided on the branches at its start, continue the old one,
        and $r$ is large: the step is wrong, whatever its truncation. (Computed
        outside the step's fusion, from its outputs: inside, the true acceleration
        would split it.)"""
        gap = lane_max(jax.tree.map(lambda a, p: jnp.abs(a - p), a1, step.a))
        K = self.order
        return step.h * gap / ((K + 1) * self.tolerance(x, v, rtol, atol))

    def exp2(self, x):
        """$2^x$ for the step length (a subclass may take a cheaper one)."""
        return jnp.exp2(x)

    def fuses_by_select(self, field: LaneField, dtype) -> bool:
        """Whether the step's outputs leave its loop by `one_fusion`'s select
        (`branch_free`) rather than its stack. The stack keeps the cheapest loop
        where at most one transcendental value (a sine, an exponential) feeds the
        recurrence; where two or more do (`sin(q) cos(q)`, `exp(q) + exp(-q)`),
        each branch of the stacked loop computes them again and LLVM no longer
        merges the copies, up to a hundred times slower per step
        (benchmarks/README.md)."""
        if self.branch_free:
            return True
        return transcendental_reads(field.scalar_accel, dtype, field.params) >= 2

    def coefficients(self, field: LaneField, s, x, v):
        """`(xs, vs, as_)`: lists of per-lane coefficients about `(s, x, v)`."""
        coeffs = taylor_coefficients(
            field.scalar_accel, self.order, x.dtype, True, vectorized_trig=True
        )
        return coeffs(s, x, v, field.params)

    def step(
        self, field: LaneField, s, x, v, a, h, rtol, atol, *, free, cap, within=None
    ) -> StepResult:
        K = self.order
        xs, vs, as_ = self.coefficients(field, s, x, v)
        tol = self.tolerance(x, v, rtol, atol)
        # The root test in the log domain, max_j log2(n_j) / j, and one exp2: XLA's
        # CPU backend calls libm's scalar `pow` once per lane, its exp2 vectorizes.
        lg = None
        for j in range(max(1, K - 3), K + 1):
            n = lane_max(abs_max(xs[j], vs[j]))
            lj = jnp.where(n > 0, log2_approx(n), -jnp.inf) / j
            lg = lj if lg is None else jnp.maximum(lg, lj)
        # (Each exp2 with one reader: see `fused` below.)
        h_jz = self._fraction(tol, lg, self.exp2)
        h = jnp.where(free, jnp.minimum(h_jz, jnp.minimum(cap, self.max_step)), h)
        h = jax.lax.stop_gradient(h)
        x1, v1 = horner(xs, h), horner(vs, h)
        if field.accel is None:  # (its caller checks it: `defect`)
            a1 = horner(as_, h)
        else:
            a1 = field.accel(s + h, x1, v1)
        raw = StepResult(x1, v1, a1, h, None, TaylorExpansion(xs, vs, as_, tol))
        raw = within_or_identity(within)(raw)
        x_end = raw.x
        if field.accel is not None and self.checked:
            # A loop that never rejects a step (the period kernel) fails a lane whose
            # step crossed a switch of the acceleration: a non-finite state. A step
            # its caller ended early (at an event) is not checked: a branch that
            # switches at the event itself is no error of the step.
            gap = jnp.where(raw.h < h, 0.0, h * self.gap(as_, a1, h))
            broken = gap > KERNEL_DEFECT * (K + 1) * tol
            x_end = jax.tree.map(lambda y: jnp.where(broken, jnp.nan, y), x_end)
        # One loop for every output: the recurrence is computed once. It stays one
        # loop only while no expensive op in it (a division, a transcendental) has
        # several readers and the acceleration has no `one_fusion` of its own;
        # otherwise XLA's CPU fusion splits it and copies the recurrence into each
        # part (several times slower per lane-step). (No output more: each is a
        # branch of that loop, which may recompute what they share.)
        x1, v1, a1, h, extras = fused(
            x_end,
            raw.v,
            raw.a,
            raw.h,
            raw.extras,
            branch_free=self.fuses_by_select(field, jax.tree.leaves(x)[0].dtype),
        )
        # Chosen before it is taken: never rejected; a non-finite step fails.
        error = jnp.where(jnp.isfinite(h), 0.0, jnp.nan)
        return StepResult(x1, v1, a1, h, error, None, extras)
