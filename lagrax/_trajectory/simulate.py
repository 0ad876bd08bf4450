"""`simulate`: Lagrange's equations through `diffrax.diffeqsolve`, an eager call
compiled once per body of `L` (and kept by the library's disk cache); and
`vector_field`, for a diffrax term of your own."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._cache.executables import cached_call
from .._checks import (
    as_time,
    check_callable,
    check_finite,
    check_instance,
    check_solvable,
    describe,
    is_concrete,
    positive_int,
    prepare,
    tolerances,
)
from .._compat import top_level
from .._custom_types import Coordinates, GeneralizedForce, Lagrangian, RealScalarLike
from .._eom.mechanics import _accelerations, _accelerations_jit
from .._jaxpr.canonical import canonical_lagrangian, CanonicalLagrangian
from .._jaxpr.fusion import elemental_options
from .._taylor.taylor import Taylor
from .term import _LagrangeVectorField, BoundLagrangian, LagrangianTerm


def elemental(fn):
    """`fn(*args, **kwargs)` compiled by `jax.jit` with XLA's elemental emitters
    (`elemental_options`), every leaf that is not an array static (as
    `equinox.filter_jit` splits them). With a static leaf that is not hashable,
    `fn` itself (op by op); staged into a caller's `jit` or `grad`, where JAX
    refuses compile options, `fn` itself too: the caller's program compiles it, with
    its own options."""

    def call(*args, **kwargs):
        leaves, treedef = jax.tree.flatten((args, kwargs))
        arrays = [x if eqx.is_array(x) else None for x in leaves]
        static = tuple(None if eqx.is_array(x) else x for x in leaves)
        try:
            hash(static)
        except TypeError:
            return fn(*args, **kwargs)
        jitted = _elemental_jit(fn, treedef, static)
        if top_level():
            return jitted(arrays)
        try:  # (under `vmap` or `jvp` JAX takes the options)
            return jitted(arrays)
        except ValueError:  # (staged into a caller's `jit` or `grad`: refused)
            return fn(*args, **kwargs)

    return call


@functools.lru_cache(maxsize=64)
def _elemental_jit(fn, treedef, static):
    def run(arrays):
        leaves = [a if s is None else s for a, s in zip(arrays, static)]
        args, kwargs = jax.tree.unflatten(treedef, leaves)
        return fn(*args, **kwargs)

    return jax.jit(run, compiler_options=elemental_options())


def vector_field(
    L: Lagrangian, *, force: GeneralizedForce | None = None
) -> Callable[[RealScalarLike, tuple[Coordinates, Coordinates], object], tuple]:
    r"""The first-order vector field of Lagrange's equations, for `diffrax.ODETerm`.

    $$\frac{d}{dt}\begin{pmatrix} q \\ \dot q\end{pmatrix}
        = \begin{pmatrix} \dot q \\ \ddot q(q, \dot q, t)\end{pmatrix},$$

    with $\ddot q$ from `lagrax.accelerations`.

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar`.
    - `force`: optional generalized force `force(q, qdot, t) -> Q`.

    **Returns:**

    `f(t, y, args) -> (qdot, qddot)` with `y = (q, qdot)`; `args` is ignored
    (parameters go in by closure). Where the mass matrix is singular or indefinite
    $\ddot q$ is NaN, which an adaptive diffrax solve rejects, so the step size
    collapses and the solve stops with `dt_min_reached` (as `simulate` sets it up)
    instead of integrating garbage. Inputs are not checked here, on the hot path:
    `simulate` checks them once.

    **Example:**

    ```python
    import diffrax

    L = lagrax.systems.pendulum.lagrangian()
    term = diffrax.ODETerm(lagrax.vector_field(L))
    ```
    """
    check_callable(L, "L", "a function L(q, qdot, t) -> scalar")
    if force is not None:
        check_callable(force, "force", "a function force(q, qdot, t) -> Q")
    return _LagrangeVectorField(L, force)


def default_controller(rtol, atol, t0, t1, dtype):
    """A PID controller whose step size may not collapse below a few ulps of time.

    A singular mass matrix makes the vector field NaN; diffrax rejects such steps and
    shrinks `dt` towards the singular instant forever (until `max_steps`, after
    burning all of them). Steps below ~64 ulps of the time scale carry no information,
    so we stop there with `RESULTS.dt_min_reached`: a fast, honest failure.
    """
    eps = jnp.finfo(dtype).eps
    scale = jnp.maximum(jnp.maximum(jnp.abs(t0), jnp.abs(t1)), jnp.abs(t1 - t0))
    dtmin = 64 * eps * jnp.maximum(scale, jnp.finfo(dtype).tiny)
    return dfx.PIDController(rtol=rtol, atol=atol, dtmin=dtmin, force_dtmin=False)


def check_save_times(saveat: dfx.SaveAt, t0, t1):
    """Raises on save times (`saveat.ts`, of every `SubSaveAt`) that `diffrax`
    refuses, where they and `t0`, `t1` are concrete: from t0 towards t1 (one way, as
    diffrax asks) and between them; also 1-D, real and finite. An error here names
    the argument and the first time at fault, where diffrax's own check (kept in
    its program) would raise from a callback."""
    subs = jax.tree.leaves(saveat.subs, is_leaf=lambda x: isinstance(x, dfx.SubSaveAt))
    for sub in subs:
        ts = getattr(sub, "ts", None)
        if ts is None or not is_concrete(ts, t0, t1):
            continue
        dtype = jnp.result_type(ts)
        # (diffrax takes integer times too)
        if not any(jnp.issubdtype(dtype, k) for k in (jnp.floating, jnp.integer)):
            raise TypeError(
                f"`saveat.ts` must be an array of real times; got {describe(ts)}."
            )
        if jnp.ndim(ts) != 1:
            raise ValueError(
                f"`saveat.ts` must be a 1-D array of times; got shape {jnp.shape(ts)}."
            )
        ts = np.asarray(ts, dtype=np.float64)  # (exact for float32 and float64)
        check_finite(ts, "saveat.ts")
        start, end = float(t0), float(t1)
        way = 1.0 if start < end else -1.0  # (diffrax's direction; t0 == t1 too)
        back = np.nonzero(way * ts[1:] < way * ts[:-1])[0]
        if back.size:
            i = int(back[0]) + 1
            order = "increasing" if way > 0 else "decreasing"
            raise ValueError(
                f"`saveat.ts` must run from t0 to t1 ({order}: t0={start}, "
                f"t1={end}); got ts[{i}]={ts[i]} after ts[{i - 1}]={ts[i - 1]}."
            )
        outside = np.nonzero((way * ts < way * start) | (way * ts > way * end))[0]
        if outside.size:
            i = int(outside[0])
            raise ValueError(
                f"`saveat.ts` must lie between t0={start} and t1={end}; got "
                f"ts[{i}]={ts[i]}."
            )


def _mark_nonfinite(sol: dfx.Solution) -> dfx.Solution:
    """A fixed-step solve has no error estimate to reject a NaN step: flag it here."""
    if sol.ys is None:
        return sol
    leaves = jax.tree_util.tree_leaves(sol.ys)
    has_nan = jnp.any(jnp.stack([jnp.any(jnp.isnan(x)) for x in leaves]))
    result = dfx.RESULTS.where(
        has_nan & (sol.result == dfx.RESULTS.successful),
        dfx.RESULTS.nonfinite,
        sol.result,
    )
    return eqx.tree_at(lambda s: s.result, sol, result)


def simulate(
    L: Lagrangian,
    q0: Coordinates,
    qdot0: Coordinates,
    t0: RealScalarLike,
    t1: RealScalarLike,
    *,
    force: GeneralizedForce | None = None,
    solver: dfx.AbstractSolver = dfx.Tsit5(),
    saveat: dfx.SaveAt | None = None,
    rtol: RealScalarLike = 1e-8,
    atol: RealScalarLike = 1e-8,
    dt0: RealScalarLike | None = None,
    max_steps: int = 16384,
    throw: bool = True,
    stepsize_controller: dfx.AbstractStepSizeController | None = None,
    event: dfx.Event | None = None,
    adjoint: dfx.AbstractAdjoint = dfx.RecursiveCheckpointAdjoint(),
    progress_meter: dfx.AbstractProgressMeter = dfx.NoProgressMeter(),
) -> dfx.Solution:
    r"""Integrates Lagrange's equations from $(q_0, \dot q_0)$ at $t_0$ to $t_1$.

    Solves $\frac{d}{dt}(q, \dot q) = (\dot q, \ddot q)$, with $\ddot q$ from
    `lagrax.accelerations`, by `diffrax.diffeqsolve`. Works under `jit` and `vmap`
    (over `q0`, `qdot0`, times, tolerances); times and tolerances are arrays, so
    changing them does not recompile. $t_1 < t_0$ integrates backwards in time.

    An eager call is compiled once per body of `L`: a rebuilt `L` with new
    parameter values reuses the program (its values reach it as arguments), and on
    a CPU a later process loads it from the library's disk cache. Not a call with
    `SaveAt(ts=...)`, a `dt0` and an adaptive solver, or a progress meter: each
    puts a callback to Python in the program (diffrax checks save times and `dt0`
    that way), which ties it to its process.

    Many releases at once: `lagrax.simulate_batch`, or `jax.vmap` of `simulate`
    inside your `jit`. On a CPU, give that `jit` XLA's elemental emitters,
    `compiler_options={"xla_cpu_use_fusion_emitters": False}`, as eager calls
    take them (where the installed XLA knows the option): they compile and run
    a batched Runge-Kutta solve faster (`lagrax.Taylor` needs no option: a large
    step program is computed by its compact program). On a GPU, map a very wide
    batch in pieces (`jax.lax.map(f, xs, batch_size=100_000)`): XLA compiles one
    very wide batch into a slower program. Figures: benchmarks/README.md.

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar`.
    - `q0`, `qdot0`: initial coordinates and velocities, 1-D float arrays of length n.
    - `t0`, `t1`: start and end times.
    - `force`: optional generalized force `force(q, qdot, t) -> Q`.
    - `solver`: any diffrax solver (default `Tsit5()`); `lagrax.Taylor(fallback=...)`
        steps with its fallback where L has a primitive without a Taylor recurrence.
    - `saveat`: a `diffrax.SaveAt` (default: the state at `t1` only).
    - `rtol`, `atol`: tolerances of the default PID step-size controller.
    - `dt0`: initial step (default: chosen by diffrax); required for fixed-step solvers.
    - `max_steps`: the most steps before the solve stops with `max_steps_reached`.
    - `throw`: raise if the solve fails. With `throw=False` the outcome is in
        `Solution.result`, per lane under `vmap`.
    - `stepsize_controller`: overrides the default controller (then `rtol`/`atol` are
        unused). The default for a non-adaptive solver is `ConstantStepSize()`.
    - `event`, `adjoint`, `progress_meter`: passed to `diffrax.diffeqsolve`.

    **Returns:**

    A `diffrax.Solution` with `ys = (qs, qdots)`. How failures show in `result`: a
    mass matrix that becomes singular or indefinite along the way (a coordinate
    singularity, say) gives `dt_min_reached` with an adaptive solver and `nonfinite`
    with a fixed-step one; too many steps gives `max_steps_reached`. Never a success
    with NaN states.

    **Raises:**

    - `TypeError`/`ValueError`: bad `L`, `q0`, `qdot0`, times or tolerances (the message
        names the argument); in an eager call also save times `saveat.ts` that do not
        run from `t0` to `t1`, a `dt0` of the wrong sign, a singular mass matrix or
        non-finite accelerations at the initial state.
    - `RuntimeError` (eager) or an equinox runtime error (under `jit`): the solve failed
        and `throw=True`.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian(g=9.81, r=1.0)
    sol = lagrax.simulate(L, jnp.array([1.0]), jnp.array([0.0]), 0.0, 10.0)
    ```
    """
    if isinstance(solver, Taylor) and solver.fallback is not None:
        # Where L's accelerations have a primitive without a Taylor recurrence,
        # tracing the Taylor solve raises `NotImplementedError`: the caller allowed
        # the fallback to step instead.
        kwargs = dict(
            force=force, saveat=saveat, rtol=rtol, atol=atol, dt0=dt0,
            max_steps=max_steps, throw=throw, stepsize_controller=stepsize_controller,
            event=event, adjoint=adjoint, progress_meter=progress_meter,
        )  # fmt: skip
        try:
            taylor = dataclasses.replace(solver, fallback=None)
            return simulate(L, q0, qdot0, t0, t1, solver=taylor, **kwargs)
        except NotImplementedError:
            return simulate(L, q0, qdot0, t0, t1, solver=solver.fallback, **kwargs)
    q0, qdot0, t0 = prepare(L, q0, qdot0, t0, force, names=("q0", "qdot0", "t0"))
    dtype = q0.dtype
    t1 = as_time(t1, "t1", dtype)
    check_finite(t1, "t1")
    check_instance(solver, "solver", dfx.AbstractSolver, "a diffrax solver")
    for value, name, cls in (
        (saveat, "saveat", dfx.SaveAt),
        (stepsize_controller, "stepsize_controller", dfx.AbstractStepSizeController),
        (event, "event", dfx.Event),
        (adjoint, "adjoint", dfx.AbstractAdjoint),
        (progress_meter, "progress_meter", dfx.AbstractProgressMeter),
    ):
        if value is not None:
            check_instance(value, name, cls)
    max_steps = positive_int(max_steps, "max_steps")
    if stepsize_controller is None:
        if isinstance(solver, dfx.AbstractAdaptiveSolver):
            rtol, atol = tolerances(rtol, atol, dtype)
        elif dt0 is None:
            raise ValueError(
                f"`dt0` is required with the fixed-step solver "
                f"{type(solver).__name__}: a step size must be given; got "
                "dt0=None."
            )
    if dt0 is not None:
        dt0 = as_time(dt0, "dt0", dtype)
        check_finite(dt0, "dt0")
        if is_concrete(dt0) and float(dt0) == 0:
            raise ValueError("`dt0` must be a nonzero initial step; got dt0=0.")
        # (Signs, not their product: no underflow lets a wrong sign through.)
        if is_concrete(dt0, t0, t1) and (
            np.sign(float(dt0)) * np.sign(float(t1) - float(t0)) < 0
        ):
            raise ValueError(
                f"`dt0` must have the sign of t1 - t0; got dt0={float(dt0)} with "
                f"t0={float(t0)}, t1={float(t1)}."
            )
    if saveat is None:
        saveat = dfx.SaveAt(t1=True)
    else:
        check_save_times(saveat, t0, t1)
    eager = is_concrete(q0, qdot0, t0, t1, dt0, saveat)
    # (The cached eager solve on a CPU compiles with XLA's elemental emitters: a
    # Taylor step needs them, and a Runge-Kutta solve compiles in less time for a
    # step barely slower, repaid only by very long runs; benchmarks/README.md.)
    on_cpu = jax.default_backend() == "cpu"
    taylor_cpu = isinstance(solver, Taylor) and on_cpu
    call = None
    if eager:
        # Keyed on what L computes (its canonical jaxpr), not on the Python function:
        # a rebuilt L with the same body and new parameter values runs the program
        # compiled for the first, its values as arguments.
        call = _canonical_call(
            L, force, solver, t0, t1, dt0, (q0, qdot0), saveat,
            stepsize_controller, rtol, atol, event, adjoint, progress_meter,
            max_steps,
        )  # fmt: skip
    if call is not None:
        _check_start(call, q0, qdot0, t0)
        found = _solve_cached(call, on_cpu)
    if call is not None and found is not None:
        sol, failed = found
    else:
        if is_concrete(q0, qdot0, t0):  # raises on a singular start
            qddot, (M, ok) = _accelerations_jit(L, q0, qdot0, t0, force)
            check_solvable(qddot, M, ok, q0, qdot0, t0, names=("q0", "qdot0", "t0"))
        if stepsize_controller is None:
            stepsize_controller = _default(solver, rtol, atol, t0, t1, dtype)
        # (Under a trace, diffrax's jit is staged into the enclosing program, which
        # compiles it.)
        solve = dfx.diffeqsolve
        if eager and taylor_cpu:
            solve = elemental(dfx.diffeqsolve)
        sol = _diffeqsolve(
            solve, L, force, solver, t0, t1, dt0, (q0, qdot0), saveat,
            stepsize_controller, max_steps, event, adjoint, progress_meter,
        )  # fmt: skip
        failed = _failed(sol)
    if throw:
        if eager and is_concrete(failed):
            if np.any(np.asarray(failed)):  # (NumPy: no op-by-op compile)
                raise RuntimeError(
                    "lagrax.simulate failed: "
                    f"{dfx.RESULTS[sol.result]} (after {int(sol.stats['num_steps'])} "
                    "steps). A collapsing step size (dt_min_reached) or non-finite "
                    "state usually means the mass matrix became singular: a "
                    "coordinate singularity. Pass throw=False to inspect "
                    "`Solution.result` instead."
                )
        else:
            sol = sol.result.error_if(sol, failed)
    return sol


def _default(solver, rtol, atol, t0, t1, dtype):
    """The step-size controller `simulate` uses where none is given."""
    if isinstance(solver, dfx.AbstractAdaptiveSolver):
        return default_controller(rtol, atol, t0, t1, dtype)
    return dfx.ConstantStepSize()


def _diffeqsolve(
    solve, L, force, solver, t0, t1, dt0, y0, saveat, controller, max_steps, event,
    adjoint, progress_meter,
):  # fmt: skip
    """`solve` (`diffrax.diffeqsolve`, or a compiled form of it) of Lagrange's
    equations, without throwing; non-finite states marked as a failure."""
    sol = solve(
        LagrangianTerm(L, force=force), solver, t0, t1, dt0, y0, saveat=saveat,
        stepsize_controller=controller, max_steps=max_steps, event=event,
        adjoint=adjoint, progress_meter=progress_meter, throw=False,
    )  # fmt: skip
    return _mark_nonfinite(sol)


def _failed(sol):
    """Per lane: whether the solve failed (an event is a success)."""
    return (sol.result != dfx.RESULTS.successful) & (
        sol.result != dfx.RESULTS.event_occurred
    )


# ---------------------------------------------- eager calls, keyed by what L computes


class _Hole(eqx.Module):
    """Where an array of a call stood, in the call's static part."""


_HOLE = _Hole()
_is_hole = lambda x: isinstance(x, _Hole)


def _split(tree):
    """`(static, arrays)`: `tree` with its arrays replaced by holes (hashable: the
    key of its program), and its arrays in order (as `equinox.filter_jit` splits)."""
    dynamic, static = eqx.partition(tree, eqx.is_array, replace=_HOLE)
    return static, tuple(jax.tree.leaves(dynamic))


def _join(static, arrays):
    """The tree `_split` split."""
    leaves, treedef = jax.tree.flatten(static, is_leaf=_is_hole)
    arrays = iter(arrays)
    return jax.tree.unflatten(
        treedef, [next(arrays) if _is_hole(x) else x for x in leaves]
    )


class _ConstantStep(dfx.AbstractStepSizeController):
    """`diffrax.ConstantStepSize` holding its step `dt0` itself, for `diffeqsolve`
    called with `dt0=None`: given an array `dt0`, diffrax checks its sign by a
    callback to Python, which keeps a program off the disk cache (`simulate` checks
    it on the host). The steps are `ConstantStepSize`'s, with the `dt0` diffrax
    would give it (in its time dtype, times the direction of time)."""

    dt0: object

    def wrap(self, direction):
        return _ConstantStep(self.dt0 * direction)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        dt0 = jnp.asarray(self.dt0, jnp.result_type(t0))
        return dfx.ConstantStepSize().init(
            terms, t0, t1, y0, dt0, args, func, error_order
        )

    def adapt_step_size(self, *args, **kwargs):
        return dfx.ConstantStepSize().adapt_step_size(*args, **kwargs)


# Adjoints that use `dt0` only through the controller (BacksolveAdjoint reads it).
_DT0_FREE_ADJOINTS = (dfx.RecursiveCheckpointAdjoint, dfx.DirectAdjoint)


class _DefaultController(eqx.Module):
    """`default_controller`, built inside the compiled program (a `PIDController`
    holds its norm, a function, which has no text for the disk cache's pre-key)."""

    rtol: object
    atol: object


class _SaveAt(eqx.Module):
    """A `diffrax.SaveAt` of states (no `fn`), built inside the compiled program (its
    default `fn` is a function, which has no text for the disk cache's pre-key)."""

    t0: bool
    t1: bool
    ts: object
    steps: object
    dense: bool
    solver_state: bool
    controller_state: bool
    made_jump: bool

    def build(self):
        return dfx.SaveAt(
            t0=self.t0, t1=self.t1, ts=self.ts, steps=self.steps, dense=self.dense,
            solver_state=self.solver_state, controller_state=self.controller_state,
            made_jump=self.made_jump,
        )  # fmt: skip


_SAVE_Y = dfx.SaveAt(t1=True).subs.fn  # (diffrax's default: save the state)


def _saveat_spec(saveat):
    """`saveat` as a `_SaveAt` where it is one, else `saveat` itself."""
    sub = saveat.subs
    if sub is None:
        parts = dict(t0=False, t1=False, ts=None, steps=False)
    elif type(sub) is dfx.SubSaveAt and sub.fn is _SAVE_Y:
        parts = dict(t0=sub.t0, t1=sub.t1, ts=sub.ts, steps=sub.steps)
    else:
        return saveat
    spec = _SaveAt(
        **parts, dense=saveat.dense, solver_state=saveat.solver_state,
        controller_state=saveat.controller_state, made_jump=saveat.made_jump,
    )  # fmt: skip
    try:  # (the same `SaveAt`, whatever fields a later diffrax adds)
        same = type(saveat) is dfx.SaveAt and (
            jax.tree.structure(spec.build()) == jax.tree.structure(saveat)
        )
    except Exception:  # noqa: BLE001 -- not one `_SaveAt` rebuilds
        same = False
    return spec if same else saveat


class _Call(eqx.Module):
    """An eager `simulate` call: split by `_split` into its program's key and its
    arrays (the Lagrangian's constants, the state, times, tolerances...)."""

    L: CanonicalLagrangian
    consts: tuple
    force: object
    solver: object
    t0: object
    t1: object
    dt0: object
    y0: object
    saveat: object
    controller: object
    event: object
    adjoint: object
    progress_meter: object
    max_steps: int


def _canonical_call(
    L, force, solver, t0, t1, dt0, y0, saveat, controller, rtol, atol, event,
    adjoint, progress_meter, max_steps,
):  # fmt: skip
    """The call as a `_Call`, or None where `L` has no canonical form (then the
    call runs as diffrax's, keyed on `L` itself)."""
    try:
        L_c, consts = canonical_lagrangian(L, y0[0].dtype, y0[0].shape[0])
    except Exception:  # noqa: BLE001 -- `L` traced once more as diffrax's (errors there)
        return None
    if not is_concrete(consts):  # (`L` closes over a tracer: an enclosing `grad`...)
        return None
    if controller is None:
        if isinstance(solver, dfx.AbstractAdaptiveSolver):  # (`tolerances` checked)
            controller = _DefaultController(rtol, atol)
        else:
            controller = dfx.ConstantStepSize()
    if (
        dt0 is not None
        and type(controller) is dfx.ConstantStepSize
        and event is None  # (an event's condition is given `dt0`)
        and type(adjoint) in _DT0_FREE_ADJOINTS
    ):
        controller, dt0 = _ConstantStep(dt0), None
    return _Call(
        L=L_c, consts=tuple(consts), force=force, solver=solver, t0=t0, t1=t1,
        dt0=dt0, y0=y0, saveat=_saveat_spec(saveat), controller=controller,
        event=event, adjoint=adjoint, progress_meter=progress_meter,
        max_steps=max_steps,
    )  # fmt: skip


class _Unkeyed(Exception):
    """A solve whose outputs the cached program cannot return (run as diffrax's)."""


def _solve(static, arrays):
    """The eager solve of `simulate` (`_Call` split by `_split`): the solution's
    fields as plain containers of arrays, and whether it failed.

    diffrax checks save times and `dt0` inside its program, by a callback to Python
    where they are arrays; a program with a callback cannot be written to disk, so
    a call with save times, or with a `dt0` that its controller cannot hold
    (`_ConstantStep`), is compiled once per process (`simulate` checks them on the
    host first, for an error that names the argument)."""
    return _solve_call(_join(static, arrays))


def _solve_call(c):
    """`_solve` of a joined `_Call`."""
    controller = c.controller
    if isinstance(controller, _DefaultController):
        t0, t1, dtype = c.t0, c.t1, c.y0[0].dtype
        controller = default_controller(controller.rtol, controller.atol, t0, t1, dtype)
    saveat = c.saveat.build() if isinstance(c.saveat, _SaveAt) else c.saveat
    sol = _diffeqsolve(
        dfx.diffeqsolve, BoundLagrangian(c.L, c.consts), c.force, c.solver, c.t0,
        c.t1, c.dt0, c.y0, saveat, controller, c.max_steps, c.event, c.adjoint,
        c.progress_meter,
    )  # fmt: skip
    # Plain containers (a `Solution`'s tree does not survive pickling: the disk
    # cache finds an output tree it can write only for these).
    fields = {f.name: getattr(sol, f.name) for f in dataclasses.fields(sol)}
    fields["result"] = jax.tree.leaves(sol.result)
    stats = dict(sol.stats)
    if type(stats.get("max_steps")) is int and stats["max_steps"] == c.max_steps:
        stats["max_steps"] = None  # (given back as the Python int)
    fields["stats"] = stats
    if not all(eqx.is_array(x) for x in jax.tree.leaves(fields)):
        raise _Unkeyed
    return fields, _failed(sol)


_RESULT_TREE = jax.tree.structure(dfx.RESULTS.successful)


@functools.cache
def _solve_jit(elemental: bool):
    """`_solve` compiled (with `elemental_options` on a CPU)."""
    options = elemental_options() if elemental else None
    return jax.jit(_solve, static_argnums=0, compiler_options=options)


def _solve_cached(call, elemental):
    """`(Solution, failed)` of an eager call through the library's cache of compiled
    programs (in this process, and on disk for later ones), or None where it cannot
    be keyed (then it runs as diffrax's)."""
    static, arrays = _split(call)
    try:
        hash(static)
    except TypeError:  # (an unhashable part: keyed on nothing)
        return None
    jitted = _solve_jit(elemental)
    options = elemental_options() if elemental else None
    try:
        fields, failed = cached_call(
            jitted, options, static, arrays, n_static=1, origin=(_solve_jit, elemental)
        )
    except _Unkeyed:
        return None
    fields = dict(fields)
    fields["result"] = jax.tree.unflatten(_RESULT_TREE, fields["result"])
    stats = dict(fields["stats"])
    if "max_steps" in stats and stats["max_steps"] is None:
        stats["max_steps"] = call.max_steps
    fields["stats"] = stats
    return dfx.Solution(**fields), failed


class _Start(eqx.Module):
    L: CanonicalLagrangian
    consts: tuple
    force: object
    q0: object
    qdot0: object
    t0: object


def _start(static, arrays):
    """The accelerations at the start, and whether they are finite from a definite
    mass matrix (`check_solvable` then has nothing to say)."""
    s = _join(static, arrays)
    L = BoundLagrangian(s.L, s.consts)
    qddot, (M, ok) = _accelerations(L, s.q0, s.qdot0, s.t0, s.force)
    return qddot, (M, ok), ok & jnp.all(jnp.isfinite(qddot))


@functools.cache
def _start_jit():
    """`_start` compiled: the accelerations at the start of an eager call."""
    return jax.jit(_start, static_argnums=0)


def _check_start(call, q0, qdot0, t0):
    """Raises on a singular start (`check_solvable`), from the canonical
    Lagrangian's program (a rebuilt `L` reuses it)."""
    start = _Start(call.L, call.consts, call.force, q0, qdot0, t0)
    static, arrays = _split(start)
    try:
        hash(static)
    except TypeError:
        L = BoundLagrangian(call.L, call.consts)
        qddot, (M, ok) = _accelerations_jit(L, q0, qdot0, t0, call.force)
    else:
        qddot, (M, ok), fine = cached_call(
            _start_jit(), None, static, arrays, n_static=1, origin=(_start_jit,)
        )
        if bool(fine):  # (its checks, op by op, compile on a process's first call)
            return
    check_solvable(qddot, M, ok, q0, qdot0, t0, names=("q0", "qdot0", "t0"))
