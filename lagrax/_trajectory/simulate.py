"""The one place that talks to diffrax: vector fields and `simulate`."""

import functools
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import (
    as_time,
    check_callable,
    check_finite,
    check_instance,
    check_solvable,
    is_concrete,
    positive_int,
    prepare,
    tolerances,
)
from .._custom_types import Coordinates, GeneralizedForce, Lagrangian, RealScalarLike
from .._eom.mechanics import _accelerations_jit
from .._jaxpr.fusion import ELEMENTAL
from .._taylor.solver import Taylor
from .term import _LagrangeVectorField, LagrangianTerm


def elemental(fn):
    """`fn(*args, **kwargs)` compiled by `jax.jit` with `ELEMENTAL`, every leaf that
    is not an array static (as `equinox.filter_jit` splits them)."""

    def call(*args, **kwargs):
        leaves, treedef = jax.tree.flatten((args, kwargs))
        arrays = [x if eqx.is_array(x) else None for x in leaves]
        static = tuple(None if eqx.is_array(x) else x for x in leaves)
        return _elemental_jit(fn, treedef, static)(arrays)

    return call


@functools.lru_cache(maxsize=64)
def _elemental_jit(fn, treedef, static):
    def run(arrays):
        leaves = [a if s is None else s for a, s in zip(arrays, static)]
        args, kwargs = jax.tree.unflatten(treedef, leaves)
        return fn(*args, **kwargs)

    return jax.jit(run, compiler_options=ELEMENTAL)


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

    Solves $\frac{d}{dt}(q, \dot q) = (\dot q, \ddot q)$ with $\ddot q$ from
    `lagrax.accelerations` using `diffrax.diffeqsolve`. Works under `jit` and `vmap`
    (over `q0`, `qdot0`, times, tolerances); times and tolerances are arrays, so
    changing them does not recompile. $t_1 < t_0$ integrates backwards in time.
    Many releases at once: `lagrax.simulate_batch` (lanes refilled as trajectories
    end); under `vmap` on a GPU, past ~10^5 releases map in pieces
    (`jax.lax.map(f, xs, batch_size=100_000)` inside your `jit`): XLA compiles one
    very wide batch into a slower program (benchmarks/README.md).

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar`.
    - `q0`, `qdot0`: initial coordinates and velocities, 1-D float arrays of length n.
    - `t0`, `t1`: start and end times.
    - `force`: optional generalized force `force(q, qdot, t) -> Q`.
    - `solver`: any diffrax solver (default `Tsit5()`).
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
        names the argument); in an eager call also a singular mass matrix or non-finite
        accelerations at the initial state.
    - `RuntimeError` (eager) or an equinox runtime error (under `jit`): the solve failed
        and `throw=True`.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian(g=9.81, r=1.0)
    sol = lagrax.simulate(L, jnp.array([1.0]), jnp.array([0.0]), 0.0, 10.0)
    ```
    """
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
            stepsize_controller = default_controller(rtol, atol, t0, t1, dtype)
        else:
            if dt0 is None:
                raise ValueError(
                    f"`dt0` is required with the fixed-step solver "
                    f"{type(solver).__name__}: a step size must be given; got "
                    "dt0=None."
                )
            stepsize_controller = dfx.ConstantStepSize()
    if dt0 is not None:
        dt0 = as_time(dt0, "dt0", dtype)
        check_finite(dt0, "dt0")
        if is_concrete(dt0) and float(dt0) == 0:
            raise ValueError("`dt0` must be a nonzero initial step; got dt0=0.")
        if is_concrete(dt0, t0, t1) and float(dt0) * (float(t1) - float(t0)) < 0:
            raise ValueError(
                f"`dt0` must have the sign of t1 - t0; got dt0={float(dt0)} with "
                f"t0={float(t0)}, t1={float(t1)}."
            )
    if is_concrete(q0, qdot0, t0):  # raises on a singular start
        qddot, (M, ok) = _accelerations_jit(L, q0, qdot0, t0, force)
        check_solvable(qddot, M, ok, q0, qdot0, t0, names=("q0", "qdot0", "t0"))
    if saveat is None:
        saveat = dfx.SaveAt(t1=True)
    eager = is_concrete(q0, qdot0, t0, t1, dt0)
    # Under a trace the enclosing program compiles the solve: its body is traced in
    # place, where a nested jit would be traced and then batched again under `vmap`.
    solve = dfx.diffeqsolve
    if not eager:
        solve = getattr(solve, "__wrapped__", solve)
    if eager and isinstance(solver, Taylor) and jax.default_backend() == "cpu":
        solve = elemental(dfx.diffeqsolve)
    sol = solve(
        LagrangianTerm(L, force=force),
        solver,
        t0,
        t1,
        dt0,
        (q0, qdot0),
        saveat=saveat,
        stepsize_controller=stepsize_controller,
        max_steps=max_steps,
        event=event,
        adjoint=adjoint,
        progress_meter=progress_meter,
        throw=False,
    )
    sol = _mark_nonfinite(sol)
    if throw:
        failed = (sol.result != dfx.RESULTS.successful) & (
            sol.result != dfx.RESULTS.event_occurred
        )
        if eager and is_concrete(failed):
            if bool(jnp.any(failed)):
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
