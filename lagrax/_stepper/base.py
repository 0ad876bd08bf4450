r"""The stepper interface: one step of an explicit integrator over many lanes.

A loop over lanes (the period loop, a batched trajectory loop) advances every lane of

$$x' = v,\qquad v' = a(s, x, v)$$

by one step per iteration. It hands the work to a stepper, as diffrax's loop hands it
to `solver.step`: the stepper says where each lane's step ends, how long the step was
and how good it was; the loop decides what to do with it (accept, locate an event,
save, hand a lane in). A new integrator is a new `AbstractStepper`, not a new branch
in a loop.
"""

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._jaxpr.fusion import one_fusion


class LaneField(eqx.Module):
    r"""The equation $x' = v$, $v' = a(s, x, v; p)$ on every lane, as read by a step.

    - `accel`: `accel(s, x, v) -> a` over lanes (arrays with the lane axis first), the
        lanes' parameters bound: the Runge–Kutta stages and the acceleration at the end
        of a step.
    - `scalar_accel`: `scalar_accel(s, x, v, p) -> a` for one lane (scalars `s, x, v`,
        `p` without its lane axis): what Taylor coefficients are computed from.
    - `params`: the per-lane parameters `p` (a pytree, lane axis first).
    """

    accel: Callable
    scalar_accel: Callable | None = None
    params: Any = None


def horner(cs, t):
    r"""$\sum_k c_k t^k$ for the coefficients `cs` (lowest first), each an array or a
    pytree of arrays (a state given as its `(lanes,)` columns), leaf by leaf."""

    def one(*leaves):
        out = leaves[-1]
        for c in leaves[-2::-1]:
            out = out * t + c
        return out

    return jax.tree.map(one, *cs)


def horner_with_derivative(cs, t):
    r"""$\sum_k c_k t^k$ and its derivative in $t$."""
    p, dp = cs[-1], jnp.zeros_like(cs[-1])
    for c in cs[-2::-1]:
        dp = dp * t + p
        p = p * t + c
    return p, dp


class TaylorExpansion(eqx.Module):
    r"""A step's solution as polynomials about its start $(s, x, v)$:

    $$x(s + \tau) = \sum_{k=0}^{K} x_k \tau^k,\quad v(s + \tau) = \sum_{k=0}^{K} v_k
    \tau^k,\quad a(s + \tau) \approx \sum_{k=0}^{K-1} a_k \tau^k,$$

    the solution itself for every $0 \le \tau \le h$ (a step of any length up to $h$
    from the same start is these polynomials at $\tau$): dense output, and the place
    to look for an event inside the step.
    """

    xs: list[Array]
    vs: list[Array]
    as_: list[Array]
    tol: Array  # the per-lane tolerance the step length was chosen for

    def at(self, tau):
        """The state `(x, v)` at `s + tau`."""
        return horner(self.xs, tau), horner(self.vs, tau)


class StepResult(eqx.Module):
    """One step of every lane.

    - `x`, `v`: the state where the step ends, `a` the acceleration there (the next
        step's first stage).
    - `h`: the step length taken.
    - `error`: the error ratio, the step accepted where it is at most 1; NaN where the
        step failed. A stepper that chooses its length before taking the step gives 0
        (or NaN).
    - `expansion`: the step's polynomials (`TaylorExpansion`), where the stepper has
        them; only inside the step (`within`, see `AbstractStepper.step`).
    - `extras`: what the caller's `within` computed from the step, inside its fusion.
    """

    x: Float[Array, " lanes *n"]
    v: Float[Array, " lanes *n"]
    a: Float[Array, " lanes *n"]
    h: Float[Array, " lanes"]
    error: Float[Array, " lanes"] | None
    expansion: TaylorExpansion | None = None
    extras: Any = None

    def finite(self) -> Bool[Array, " lanes"]:
        """Lanes whose step gave finite numbers."""
        ok = jnp.isfinite(self.error) & all_coordinates(jnp.isfinite(self.x))
        ok = ok & all_coordinates(jnp.isfinite(self.v))
        return ok & all_coordinates(jnp.isfinite(self.a))


def _columns(x, op):
    """`op` folded over the `(lanes,)` columns of `x`: elementwise, so that XLA keeps
    it in the step's one fusion (a reduction over the coordinates would end the
    fusion, and XLA would then copy the recurrence into each part)."""
    if x.ndim <= 1:
        return x
    flat = x.reshape(x.shape[0], -1)
    out = flat[:, 0]
    for c in range(1, flat.shape[1]):
        out = op(out, flat[:, c])
    return out


def all_coordinates(mask):
    """A per-lane mask from one per coordinate (lanes first)."""
    return _columns(mask, jnp.logical_and)


def lane_max(x):
    """The largest entry per lane (lanes first): the norm of a lane's state (an
    array, or a pytree of them: the columns of a state)."""
    leaves = [_columns(leaf, jnp.maximum) for leaf in jax.tree.leaves(x)]
    out = leaves[0]
    for leaf in leaves[1:]:
        out = jnp.maximum(out, leaf)
    return out


def abs_max(x, v):
    r"""$\max(|x|, |v|)$ entry by entry, for arrays or pytrees of them."""
    return jax.tree.map(lambda a, b: jnp.maximum(jnp.abs(a), jnp.abs(b)), x, v)


def fused(*trees, branch_free=False):
    """The same pytrees of arrays, computed by XLA in one loop (`one_fusion`, with
    its `branch_free`): what a step computes shares its stages or its recurrence,
    computed once. Leaves of shape `(lanes, ...)` pass as their `(lanes,)` columns
    (a variadic reduction takes operands of one shape)."""
    leaves, treedef = jax.tree.flatten(trees)
    columns = {}
    for i, leaf in enumerate(leaves):
        flat = leaf.reshape(leaf.shape[0], -1) if leaf.ndim > 1 else leaf
        for c in range(flat.shape[1] if leaf.ndim > 1 else 1):
            columns[i, c] = flat[:, c] if leaf.ndim > 1 else flat
    out = one_fusion(columns, branch_free=branch_free)
    rebuilt = []
    for i, leaf in enumerate(leaves):
        if leaf.ndim > 1:
            cols = [out[i, c] for c in range(leaf[0].size)]
            rebuilt.append(jnp.stack(cols, axis=1).reshape(leaf.shape))
        else:
            rebuilt.append(out[i, 0])
    return jax.tree.unflatten(treedef, rebuilt)


class AbstractStepper(eqx.Module):
    r"""One step of an explicit integrator for $x' = v$, $v' = a(s, x, v)$ over lanes.

    Today every array has shape `(lanes,)` (one coordinate per lane); nothing in the
    interface assumes it: a state of shape `(lanes, n)` steps the same way, with the
    per-lane norms (`lane_max`, the error ratio's root mean square) over the
    coordinates.

    A stepper provides:

    - `error_order`: the order $k$ of its error control, the step-size controller's
        exponent $1/k$.
    - `rejects`: True where a step may be rejected by its error ratio (an embedded
        Runge–Kutta pair, with the controller choosing the next length); False where
        the stepper chooses each step's length before taking it (Taylor: the error
        ratio is 0, or NaN where the step failed).
    - `step(...)`: below. Everything a caller computes from the step (an event inside
        it, dense output at requested times, error-bound terms) goes in `within`, so
        that it shares the step's one fusion: on a CPU XLA would otherwise compute
        the step's stages or recurrence again for each reader.

    How loops use it: the period loop (`lagrax/_period/loop.py`) steps, asks
    `IController.adapt` for the next length, and locates its event inside the step
    (`within`, from `raw.expansion`) or by trial steps of a given length (lanes not
    `free`). A trajectory loop caps each free step at its end time (`cap`) and reads
    the states at requested times that fall inside the step from
    `raw.expansion.at(tau)` in `within`; with a stepper without polynomials it ends
    its steps at those times instead (`h`). A Taylor stepper whose coefficients come
    from elsewhere (a tape) overrides `TaylorStepper.coefficients` and keeps the
    rest of the step.
    """

    error_order: eqx.AbstractVar[float]
    rejects: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def step(
        self,
        field: LaneField,
        s,
        x,
        v,
        a,
        h,
        rtol,
        atol,
        *,
        free,
        cap,
        within: Callable[[StepResult], StepResult] | None = None,
    ) -> StepResult:
        """One step of every lane from `(s, x, v)`, `a` the acceleration there.

        **Arguments:**

        - `field`: the equation (`LaneField`).
        - `h`: the requested step length per lane: taken as it is where the stepper
            does not choose its own, and on lanes that are not `free`.
        - `rtol`, `atol`: per-lane tolerances.
        - `free`: lanes whose step length the stepper may choose (up to `cap`); the
            others take exactly `h` (an event's trial step).
        - `cap`: the longest step a free lane may choose.
        - `within`: `within(raw) -> raw`, computed from the step before it leaves
            its fusion: it may read `raw.expansion`, end the step elsewhere (`x`, `v`,
            `a`, `h`) and set `raw.extras`.

        **Returns:** a `StepResult` (without `expansion`).
        """


def within_or_identity(within):
    return (lambda raw: raw) if within is None else within
