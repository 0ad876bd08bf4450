r"""`lagrax.Taylor` as a diffrax solver: a step, its error estimate, its dense output.

A step of length $h$ from $(t_0, y_0)$ expands the solution of $y' = f(t, y)$ to order
$K$ about $(t_0, y_0)$ (coefficients by recurrence from the jaxpr of $f$, see
`lagrax._taylor.system`) and evaluates the polynomial at $h$. The polynomial is the
solution over the whole step, so it is also the step's dense output: `SaveAt(ts=...)`,
`Solution.evaluate` and the root finding of `diffrax.Event` read it, not a
lower-order interpolant.

The error estimate is the trajectories' step-length rule (`simulate_batch`'s) written
as an error: per entry $i$ of $y$,

$$e_i(h) = C\,\Bigl(|h| \max_{K-3 \le j \le K} |y_{j,i}|^{1/j}\Bigr)^{K+1},$$

$C$ times the first term dropped, extrapolated from the last orders as
$(h/\rho_i)^{K+1}$ with $\rho_i$ the radius of convergence, of error order $K + 1$.
A diffrax controller that keeps $e_i \le \text{atol} + \text{rtol} |y_i|$ then
proposes, after each step, the step the rule would choose at its start (scaled by
its `safety`): the coefficients are computed before the step length is known, as
diffrax's interface asks, and a step is rejected only where the rule's step shrinks
by more than `1 - safety` from one step to the next.
"""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from .._compat import unwrap_time
from .._jaxpr.fusion import one_fusion
from .._jaxpr.switches import switches
from .._taylor.stepper import TRUNCATION
from .._trajectory.term import LagrangianTerm
from . import compact


class TaylorInterpolation(dfx.AbstractLocalInterpolation):
    r"""The step's own polynomial, $y(t) = \sum_{k=0}^K y_k (t - t_0)^k$ on
    $[t_0, t_1]$: the dense output of `lagrax.Taylor`."""

    t0: jax.Array
    t1: jax.Array
    coeffs: list  # per leaf of y: an array (K + 1, *shape), lowest order first

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is not None:
            return jtu.tree_map(jnp.subtract, self.evaluate(t1), self.evaluate(t0))
        tau = t0 - self.t0

        def horner(c):
            out = c[-1]
            for ck in c[-2::-1]:
                out = out * tau + ck
            return out

        return jtu.tree_map(horner, self.coeffs)


def _ode_term(terms):
    """The `diffrax.ODETerm` inside `terms` (through diffrax's time reversal)."""
    inner, _ = unwrap_time(terms)
    if not isinstance(inner, dfx.ODETerm):
        raise TypeError(
            "lagrax.Taylor solves ordinary differential equations: `terms` must be a "
            f"diffrax.ODETerm (or a subclass such as lagrax.LagrangianTerm); got "
            f"{type(inner).__name__}."
        )
    return terms


# Programs of at least this many nodes times orders take the compact program: it
# compiles in about a second (the unrolled one's compile grows faster than the
# program, minutes for a double pendulum under a default `jit`), and runs slower.
_COMPACT_FROM = 400


def _compact_tape(system, K, dtype):
    """`(tape, traced constants)` of the step's program (`lagrax._taylor.compact`),
    or None where the unrolled program is taken: a small program, one not
    evaluated entry by entry, or a primitive without a compact opcode."""
    if not system.scalar or len(system.prog.nodes) * K < _COMPACT_FROM:
        return None
    prog = system.prog
    try:
        return compact.build(
            prog, prog.inputs, prog.params, prog.outs, dtype, traced=True
        )
    except NotImplementedError:
        return None


def _error(cs, h, K):
    r"""$e(h) = C (|h| \max_j |c_j|^{1/j})^{K+1}$ over the last four orders, in
    base 2."""
    lg = None
    for j in range(max(1, K - 3), K + 1):
        a = jnp.abs(cs[j])
        lj = jnp.where(a > 0, jnp.log2(jnp.where(a > 0, a, 1.0)), -jnp.inf) / j
        lg = lj if lg is None else jnp.maximum(lg, lj)
    return jnp.exp2((K + 1) * (jnp.log2(jnp.abs(h)) + lg) + float(np.log2(TRUNCATION)))


def _switches(terms, t0, y0, args) -> bool:
    """Whether the vector field switches branch with the state or time (see
    `lagrax._jaxpr.switches`): for a `lagrax.LagrangianTerm`, whether `L` or its
    force does (the mechanics around them only guards its solve)."""
    inner, _ = unwrap_time(terms)
    if isinstance(inner, LagrangianTerm) and isinstance(y0, tuple) and len(y0) == 2:
        state = (y0[0], y0[1], t0)
        if switches(inner.L, state):
            return True
        return inner.force is not None and switches(inner.force, state)
    return switches(lambda t, y: inner.vf(t, y, args), (t0, y0))


def _defect(cs, f1, h, K):
    r"""$|h|\,|f(t_1, y_1) - p'(h)| / (K + 1)$: the vector field where the step
    ends against the polynomial's derivative there. For an analytic vector field,
    about the first term the step drops (far below `_error`'s $C$ times it); where a
    branch of it (`jnp.where`, `abs`, `max`, ...) switches inside the step, the
    polynomial continues the old branch and this is large: the controller rejects the
    step and shrinks the next, as a Runge–Kutta pair's estimate makes it do."""
    h = jax.lax.stop_gradient(h)
    dp = cs[K] * K
    for k in range(K - 1, 0, -1):
        dp = dp * h + cs[k] * k
    return jnp.abs(h) * jnp.abs(f1 - dp) / (K + 1)


class AbstractTaylorSolver(dfx.AbstractAdaptiveSolver):
    """The diffrax side of `lagrax.Taylor` (see its docstring)."""

    order: eqx.AbstractVar[int]

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., TaylorInterpolation]] = (
        TaylorInterpolation
    )

    def error_order(self, terms):
        """$K + 1$: the order of the step's error estimate."""
        return self.order + 1

    def strong_order(self, terms):
        """None: ordinary differential equations only."""
        return None

    def init(self, terms, t0, t1, y0, args):
        """No state between steps (diffrax's interface)."""
        _ode_term(terms)
        return None

    def func(self, terms, t0, y0, args):
        """The vector field at `(t0, y0)` (diffrax's interface)."""
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        """One Taylor step from `t0` to `t1` (diffrax's interface: the state at
        `t1`, the error estimate, the polynomial for dense output, no solver state,
        the result)."""
        del solver_state, made_jump
        from .system import horner, System  # (system imports the recurrences)

        _ode_term(terms)
        K = self.order
        leaves, treedef = jtu.tree_flatten(y0)
        dynamic, static = eqx.partition(args, eqx.is_array)
        arg_leaves, arg_def = jtu.tree_flatten(dynamic)
        t0 = jnp.asarray(t0)
        # d/dt of an ODE term's `contr` (1, or -1 through diffrax's time reversal).
        unit = jnp.asarray(terms.contr(t0, t0 + 1), t0.dtype)

        def f(t, ys, params):
            u, *rest = params
            a = eqx.combine(jtu.tree_unflatten(arg_def, rest), static)
            out = terms.vf_prod(t, jtu.tree_unflatten(treedef, ys), a, u)
            out_leaves, out_def = jtu.tree_flatten(out)
            if out_def != treedef:
                raise TypeError(
                    "the vector field must return a pytree of the state's structure "
                    f"{treedef}; got {out_def}."
                )
            return out_leaves

        system = System(f, t0, leaves, [unit, *arg_leaves])
        lane = lambda a: jnp.asarray(a)[None]
        params = [lane(p) for p in (unit, *arg_leaves)]
        found = _compact_tape(system, K, t0.dtype)
        if found is None:
            coefs = system.coefficients(K, lane(t0), [lane(y) for y in leaves], params)
        else:
            # (The Lagrangian's constants arrive traced, through diffrax's loop:
            # the tape takes them as parameters.)
            tape, constants = found
            entries = system.split([lane(y) for y in leaves])
            params += [lane(c).astype(t0.dtype) for c in constants]
            lanes = compact.lane_function(tape, K, trig=True, inline=True)
            coefs = lanes(lane(t0), entries, params)
        h = jnp.asarray(t1 - t0, t0.dtype)
        ends = [horner(c, h) for c in coefs]
        sg = jax.lax.stop_gradient
        values = {}
        for i, c in enumerate(coefs):
            values[("y1", i)] = ends[i]
            values[("err", i)] = sg(_error(c, h, K))
        if _switches(terms, t0, y0, args):
            # The vector field where the step ends (the program at order 1): the
            # defect (`_defect`) sees a branch that switched inside the step.
            if found is None:
                ys1 = [sg(y) for y in system.join(ends)]
                f1 = system.coefficients(1, lane(t0 + h), ys1, params)
            else:
                lanes1 = compact.lane_function(tape, 1, trig=True, inline=True)
                f1 = lanes1(lane(t0 + h), [sg(y) for y in ends], params)
            for i, c in enumerate(coefs):
                defect = sg(_defect(c, f1[i][1], h, K))
                values["err", i] = jnp.maximum(values["err", i], defect)
        # One loop for the new state and the estimate: without it XLA copies the
        # recurrence into each output's loop (see `one_fusion`).
        values = one_fusion(values)
        n = len(coefs)
        y1 = system.join([values["y1", i] for i in range(n)])
        err = system.join([values["err", i] for i in range(n)])
        orders = [system.join([c[k] for c in coefs]) for k in range(K + 1)]
        dense = [jnp.stack([o[i] for o in orders])[:, 0] for i in range(len(leaves))]
        unflat = lambda xs: jtu.tree_unflatten(treedef, [x[0] for x in xs])
        dense_info = dict(coeffs=jtu.tree_unflatten(treedef, dense))
        return unflat(y1), unflat(err), dense_info, None, dfx.RESULTS.successful
