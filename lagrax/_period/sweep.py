r"""`sweep_periods`: periods of many release points through the period kernel, one
compiled call per sweep, in input order."""

import dataclasses
import functools

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._cache import executables
from .._checks import (
    as_real_array,
    check_devices,
    check_instance,
    is_concrete,
    lane_count,
)
from .._jaxpr.canonical import canonical_lagrangian
from .._jaxpr.fusion import elemental_options, vector_options
from .._results import status_message, SUCCESS
from .._taylor.taylor import Taylor
from . import tier
from .autodiff import forward_jacobian, forward_mode, periods_diff, tangents_of
from .device import Periods
from .methods import Method
from .options import check_options
from .solver import resolved_solver, stepper_of


# Lanes per device on a CPU by default (also `lagrax sweep`'s: they share programs).
CPU_LANES = 256


def _lane_order(q0):
    """The order the lanes run in: by decreasing |q0|, so that neighbouring lanes
    hold neighbouring release points (and, where the well's bottom is near 0, the
    largest swings, usually the longest, go first and the queue's tail is short).
    The compiled loop runs markedly slower on unsorted release points than on the
    same points sorted, far more than its few more idle lane-steps account for.
    Sorted on the host (NumPy); a traced `q0` (under `jit`, `grad`) keeps its own
    order."""
    n = q0.shape[0]
    if isinstance(q0, jax.core.Tracer) or not q0.is_fully_addressable:
        return np.arange(n, dtype=np.int32)
    return np.argsort(-np.abs(np.asarray(q0)), kind="stable").astype(np.int32)


def sweep_periods(
    L,
    q0,
    *,
    solver: "dfx.AbstractAdaptiveSolver | Taylor" = Taylor(fallback=dfx.Dopri8()),
    rtol=1e-13,
    atol=1e-13,
    max_steps: int = 4096,
    t_max=None,
    energy_tol=None,
    method: str = "matched",
    lanes: int | None = None,
    sort: bool = True,
    devices=None,
    progress_meter: dfx.AbstractProgressMeter = dfx.NoProgressMeter(),
    error_estimate: bool = True,
):
    r"""Periods of many release points at once: `period` over a batch, done fast.

    Each lane computes $T = t(q_0\to q_1) + t(q_1 \to q_0)$ as `period` does (by
    default with `method="matched"`, see there), and comes with an estimate of its
    relative error. The batch runs in one compiled loop per device: `lanes` lanes
    step together, and a lane that finishes takes the next release point from a
    queue inside the loop, so no lane waits for the slowest. The step is, by
    default, an order-20 Taylor step (`lagrax.Taylor`); where L's acceleration has a
    primitive without a Taylor recurrence or a program too large to unroll, or with
    an explicit `solver=diffrax.Dopri8()` (any adaptive explicit Runge–Kutta pair),
    that solver's step, written out stage by stage from its diffrax tableau.
    `SweepResult.solver` says which stepped. Speed and accuracy against heyoka.py,
    scipy and diffrax: `benchmarks/README.md`.

    A failing lane is reported in `status` (its period NaN) and never changes the
    others: their periods are bit-for-bit those of a sweep without it.
    Differentiable with `jax.grad`, `jax.jacfwd` and `jax.jvp` with respect to `q0`
    and to parameters `L` closes over (each scalar parameter differentiated costs one
    forward pass through the sweep).

    **Error estimate** (`error_estimate=True`, the default). With a Taylor step and
    `"matched"` or `"quarter"` it comes from the solve itself: a first-order bound
    that carries each step's error bound (truncation and rounding) to the period,
    plus the far turning point's rounding band times $d\tau/dE$. Where that bound
    cannot vouch for a lane (above 100 rtol, a leverage beyond its range, a mass that
    varies), the lane is solved a second time at 10x tighter tolerances, from the
    far turning point moved across its band. For every other method and solver the
    lane is solved a second time at 10x tighter tolerances, nearer the truth than
    the first solve (`"half"`, and `"full"` where L is even in $\dot q$, by
    `"matched"`: through the bottom of the swing they lose to the energy errors of
    their steps by an amount that does not scale with the tolerance), and where a
    leg starts at the far turning point, once more from it moved across its
    rounding band, so that the band's share of the error adds to the estimate
    instead of cancelling the truncation's. The estimate is 4 times the relative
    differences, plus a fraction of rtol (where a lane's error happens to cancel at
    one tolerance and not at the other, the two solves agree better than either
    agrees with the truth: 0.02 with `Dopri8`, 0.3 with pairs of lower order such
    as `Tsit5` and `Dopri5`, 0.1 with a Taylor step), plus 16 ulps. A lane whose
    estimate exceeds 100 rtol gets status `tolerance_not_met` and no number. In the
    validation runs (`benchmarks/accuracy.py --periods`: the pendulum to
    $\pi - 10^{-3}$ and an asymmetric well to 0.99 of its hump, rtol $10^{-13}$ and
    $10^{-10}$, every method with `Taylor()`, `Dopri8`, `Tsit5` and `Dopri5`) no
    estimate was below the true error, and the median estimate was within 25 times
    it.

    **What compiles:** one program per body of `L` (its float constants are
    arguments: a Lagrangian rebuilt with other parameter values reuses it), solver,
    `method`, `lanes`, `max_steps`, `error_estimate`, device set and size class of the
    amplitude count: an eager sweep of $n$ amplitudes runs the program of the smallest
    of 8, 12, 16, 24, 32, 48, ... (powers of two and 1.5 times them) that holds $n$,
    padded with NaN release points, which take no step (under `jit`, the count
    itself). Tolerances, `t_max` and `energy_tol` are arguments. On a CPU an eager
    sweep's program is kept on disk
    (`$LAGRAX_CACHE_DIR`, else `~/.cache/lagrax/executables`, at most 1 GiB, least
    recently used removed first; `LAGRAX_CACHE_DIR=""` turns it off): a later
    process loads it instead of compiling. While JAX's persistent compilation cache
    is on (`jax.config.update("jax_compilation_cache_dir", ...)`) it keeps the
    programs and the library writes none of its own. A new Lagrangian's first eager
    sweeps on a CPU may run on a compact program, compiled once per machine for all
    Lagrangians of a size class (a one-line notice when it compiles), until the time
    spent there would pay for the Lagrangian's own program.

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar` of one coordinate: a function,
        or a pytree such as an `equinox.Module` whose float array fields are its
        parameters.
    - `q0`: release points, a non-empty 1-D float array.
    - `solver`: default `Taylor(fallback=Dopri8())`, or any solver `period` takes.
        Inside the kernel, float64 `sin` and `cos` are lagrax's own vectorized
        versions (within 1 ulp), for arguments up to $2^{19}\pi/2 \approx
        8.2\cdot10^5$ radians: beyond, the lane fails (`solver_failed`).
    - `rtol`, `atol`, `max_steps`, `t_max`, `energy_tol`, `method`: as in `period`,
        the same for every lane.
    - `lanes`: lanes stepping together per device (static). Default: 256 on a CPU;
        on a GPU, every amplitude of a device's share, up to 262,144 (a GPU needs
        many lanes in flight).
    - `sort`: run the lanes in order of decreasing |q0| (default True; the outputs
        stay in input order): the compiled loop runs faster when neighbouring lanes
        hold neighbouring release points. Done on the host, so only where `q0` is
        concrete (under `jit` or `grad`, sort it yourself).
    - `devices`: the devices to share the batch over (default: all of
        `jax.devices()`, which under `jax.distributed` includes every process's);
        each runs its own loop on an interleaved share, and every process receives
        the whole result.
    - `progress_meter`: a diffrax progress meter (default
        `diffrax.NoProgressMeter()`), e.g. `diffrax.TqdmProgressMeter()`: an eager
        sweep then runs in about 20 pieces and steps the meter after each.
    - `error_estimate`: compute the per-lane error estimate (above; default True).

    **Returns:** a `lagrax.SweepResult`, in the input order: `periods` (NaN where
    failed), `status` (int codes, 0 for success; `lagrax.PeriodStatus`), `num_steps`,
    `error_estimate` (None with `error_estimate=False`), `solver` (the one that
    stepped), and the work statistics `lane_steps_useful`, `lane_steps_executed`,
    `useful_fraction`, `lanes`, `num_devices`.

    **Raises:** `TypeError`/`ValueError` on bad arguments, naming the argument.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    res = lagrax.sweep_periods(L, jnp.linspace(0.01, 3.1, 4096))
    res.periods, res.status, res.error_estimate
    ```

    A parameter scan reuses the compiled sweep; `jax.grad` differentiates with
    respect to a parameter `L` closes over:

    ```python
    import diffrax

    q0 = jnp.linspace(0.1, 3.0, 8)
    for g in (1.0, 4.0, 9.0):  # compiled once, for the first g
        res = lagrax.sweep_periods(lagrax.systems.pendulum.lagrangian(g=g), q0)
    res.periods[0]  # lagrax.systems.pendulum.period(0.1, g=9.0)

    def mean_period(g):  # Dopri8 compiles its derivative faster than Taylor
        L = lagrax.systems.pendulum.lagrangian(g=g)
        return lagrax.sweep_periods(L, q0, solver=diffrax.Dopri8()).periods.mean()

    jax.grad(mean_period)(4.0)  # -mean_period(4.0) / 8, as T ∝ 1/√g
    ```
    """
    q0 = as_real_array(q0, "q0")
    if q0.ndim != 1 or q0.shape[0] == 0:
        raise ValueError(
            "`q0` must be a non-empty 1-D array of release points (one per amplitude); "
            f"got shape {q0.shape}."
        )
    opts = check_options(
        L, q0.dtype, solver, rtol, atol, t_max, energy_tol, max_steps, method
    )
    devices = check_devices(jax.devices() if devices is None else devices)
    per_device = -(-size_class(q0.shape[0]) // len(devices))
    lanes = lane_count(
        lanes,
        "lanes",
        devices,
        per_device,
        cpu=CPU_LANES,
        accelerator=1 << 18,
    )
    check_instance(
        progress_meter,
        "progress_meter",
        dfx.AbstractProgressMeter,
        "a diffrax progress meter, e.g. diffrax.TqdmProgressMeter()",
    )
    dtype = q0.dtype
    # (Keyed on what L computes: a rebuilt L with new parameter values reuses the
    # program compiled for the first.)
    L_c, consts = canonical_lagrangian(L, dtype)
    n = q0.shape[0]
    solver = resolved_solver(L_c, consts, solver, dtype)
    cfg = Method(
        stepper_of(solver),
        opts.method,
        lanes,
        opts.max_steps,
        bool(error_estimate),
    )
    args = (consts, opts.rtol, opts.atol, opts.t_max, opts.energy_tol)

    def run(q, order):
        # Nothing traced, nothing to differentiate: the compiled call without the
        # derivative rule's wrapper (whose eager dispatch costs as much as a small
        # sweep),
        # through the tiers and the library's disk cache of executables.
        if is_concrete(q, args):
            return _eager(L_c, cfg, devices, q, order, args)
        return _sweep_call(L_c, cfg, devices, q, order, *args)

    order = _lane_order(q0) if sort else np.arange(n, dtype=np.int32)
    if not isinstance(progress_meter, dfx.NoProgressMeter):
        size = max(lanes * len(devices) * 4, -(-n // 20))
        out, useful = _in_pieces(run, q0, order, size, progress_meter)
    elif is_concrete(q0, args) and size_class(n) > n:
        out, useful = _padded(run, q0, order, size_class(n))
    else:
        out, useful = run(q0, order)
    return SweepResult(
        periods=out.periods,
        status=out.status,
        num_steps=out.steps,
        lane_steps_useful=useful,
        lane_steps_executed=jnp.asarray(out.executed),
        lanes=lanes,
        num_devices=len(devices),
        error_estimate=out.estimate if error_estimate else None,
        solver=solver,
    )


def size_class(n: int) -> int:
    """The amplitudes a sweep of `n` is compiled for: the smallest of 8, 12, 16,
    24, 32, ... (powers of two and one and a half times them) that holds `n`, so
    that one program serves a range of counts (the extra lanes padded with NaN
    release points, which end at their release)."""
    k = max(3, (max(n, 1) - 1).bit_length())  # (2^k >= n)
    three_quarters = 3 << (k - 2)
    return three_quarters if three_quarters >= max(n, 8) else 1 << k


def _padded(run, q0, order, size) -> tuple[Periods, Array]:
    """`run` of the sweep padded to `size` amplitudes with NaN release points, run
    last (they end at their release, status `nonfinite_input`, no step taken), the
    results of the first `q0.shape[0]` back (NumPy, `jax.device_put`: op-by-op jnp
    compiles each operation on its first call)."""
    n = q0.shape[0]
    q = np.concatenate([np.asarray(q0), np.full((size - n,), np.nan, q0.dtype)])
    order = np.concatenate([order, np.arange(n, size, dtype=np.int32)])
    out, _ = run(q, order)
    cut = lambda x: jax.device_put(np.asarray(x)[:n])
    steps = np.asarray(out.steps)[:n]
    out = Periods(
        cut(out.periods),
        cut(out.status),
        jax.device_put(steps),
        out.executed,
        cut(out.estimate),
    )
    return out, jax.device_put(steps.sum())


def _eager(L_c, cfg, devices, q, order, args):
    """The compiled sweep of concrete inputs: the specialized program where it is
    compiled or on disk, or where the compact tier does not apply or its work
    would repay the specialized compile; else the compact program, where its
    executable is at hand (`tier.py`)."""
    wide = devices[0].platform == "cpu"
    jitted = _sweep_jit(L_c, cfg, devices, False, wide)
    origin = (_sweep_jit, L_c, cfg, devices, False, wide)
    call = (jitted, vector_options() if wide else None, q, order, *args)
    specialized = lambda: executables.cached_call(
        *call, origin=origin, out_tree=_OUT_TREE
    )
    n = q.shape[0]
    kind = "sweep" if n > 1 else "period"
    plan = None
    if tier.always() or not executables.available(*call, origin=origin):
        waiting = executables.later_state(*call, origin=origin) == "running"
        plan = tier.plan(
            L_c, args[0], cfg.stepper, (cfg, devices), n, q.dtype, kind, waiting
        )
    if plan is None:
        return specialized()
    if not tier.always() and plan.repeated():
        # A job that repeats: where a core is idle, the specialized program compiles
        # there meanwhile, and takes over once on disk.
        plain = _sweep_jit(L_c, cfg, devices)
        executables.compile_later(plain, *call, origin=origin, out_tree=_OUT_TREE)
    m = dataclasses.replace(cfg, stepper=plan.stepper)
    # (With XLA's elemental CPU emitters: the compact program, loops over the
    # tape's blocks, compiles faster.)
    elemental = devices[0].platform == "cpu"
    compact = tier.Compact(
        plan,
        _sweep_jit(plan.L, m, devices, elemental),
        (plan.L, m, devices, elemental),
        _OUT_TREE,
        (q, order, plan.consts, *args[1:]),
    )
    return compact.run(kind, specialized)


def _in_pieces(run, q0, order, size, meter, pad=None) -> tuple[Periods, Array]:
    """The sweep in order, in pieces of one size (one compilation) padded with
    `pad` (default: the last release point), the progress `meter` (if any) stepped
    after each; back in input order, with the total of the steps. With NumPy where q0 is
    concrete, and `jax.device_put` to hand the results back: op-by-op jnp compiles
    each operation (even `jnp.asarray`) on its first call."""
    n = q0.shape[0]
    traced = isinstance(q0, jax.core.Tracer)
    xp, device = (jnp, jnp.asarray) if traced else (np, jax.device_put)
    q_sorted = xp.asarray(q0)[order]
    pieces = -(-n // size)
    fill = q_sorted[-1] if pad is None else pad
    padded = xp.concatenate(
        [q_sorted, xp.full((pieces * size - n,), fill, q_sorted.dtype)]
    )
    outs = []
    state = None if meter is None else meter.init()
    for k in range(pieces):
        piece = padded[k * size : (k + 1) * size]
        outs.append(run(piece, np.arange(size, dtype=np.int32))[0])
        if meter is not None:
            jax.block_until_ready(outs[-1])
            state = meter.step(state, min((k + 1) * size, n) / n)
    if meter is not None:
        meter.close(state)
    inverse = np.argsort(order)
    joined = lambda f: xp.concatenate([xp.asarray(f(o)) for o in outs])[:n][inverse]
    steps = joined(lambda o: o.steps)
    out = Periods(
        device(joined(lambda o: o.periods)),
        device(joined(lambda o: o.status)),
        device(steps),
        device(sum(xp.asarray(o.executed) for o in outs)),
        device(joined(lambda o: o.estimate)),
    )
    return out, device(xp.sum(steps))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _sweep_call(L, m, devices, q0, order, consts, rtol, atol, t_max, energy_tol):
    """`periods_diff` as one compiled call: one dispatch instead of a dozen (their
    Python and dispatch cost as much as a small sweep). The lanes run in the order
    `order` (a permutation of the inputs); the outputs come back in input order."""
    return _sweep_jit(L, m, devices)(q0, order, consts, rtol, atol, t_max, energy_tol)


def _sweep_call_jvp(L, m, devices, primals, tangents):
    """Forward mode as `periods_diff`'s, through one compiled call of its own. Where
    that call is the program that runs (an eager `jax.grad`, `jvp`, `jacfwd`: the
    values are concrete), it compiles with XLA's elemental CPU emitters: the fusion
    emitters recompute parts of the Taylor step's tangent program (`ELEMENTAL`). The
    forward sweep keeps the fusion emitters, which run it faster."""
    q0, order, consts, *rest = primals
    elemental = is_concrete(q0, consts) and devices[0].platform == "cpu"
    jitted = _sweep_jit(L, m, devices, elemental)
    run = lambda q0, consts: jitted(q0, order, consts, *rest)
    jacobian = None
    if is_concrete(primals):
        # The forward passes as one program of their own (`_jacobian`).
        jacobian = functools.partial(_jacobian, L, m, devices, elemental, order, rest)

    (out, useful), dT = forward_mode(
        run, q0, consts, tangents[0], tangents[2], jacobian
    )
    no_tangent = np.zeros(np.shape(useful), jax.dtypes.float0)
    return (out, useful), (tangents_of(out, dT), no_tangent)


def _jacobian(L, m, devices, elemental, order, rest, q0, consts, with_q, wanted):
    """`forward_jacobian` of the sweep (`_sweep_call_jvp`), compiled: the
    specialized program through the library's disk cache of executables
    (`cached_call`: a later process loads it) where it is compiled or on disk, or
    where the compact tier does not apply or its work would repay the specialized
    compile (`tier.py`); else the compact program's."""
    jac = _jacobian_jit(L, m, devices, elemental, with_q, wanted)
    options = elemental_options() if elemental else None
    origin = (_jacobian_jit, L, m, devices, elemental, with_q, wanted)
    call = (jac, options, q0, order, consts, *rest)
    specialized = lambda: executables.cached_call(
        *call, origin=origin, out_tree=_JACOBIAN_OUT_TREE
    )
    n = q0.shape[0]
    plan = None
    if tier.always() or not executables.available(*call, origin=origin):
        waiting = executables.later_state(*call, origin=origin) == "running"
        plan = tier.plan(
            L, consts, m.stepper, (m, devices), n, q0.dtype, "jacobian", waiting
        )
    if plan is None:
        return specialized()
    if not tier.always() and plan.repeated():  # (as `_eager`'s)
        plain = _jacobian_jit(L, m, devices, False, with_q, wanted)
        executables.compile_later(
            plain, *call, origin=origin, out_tree=_JACOBIAN_OUT_TREE
        )
    m_t = dataclasses.replace(m, stepper=plan.stepper)
    # (The tapes are constants; the parameters padded beyond the Lagrangian's are
    # not differentiated: the same directions.)
    tapes = len(jax.tree.leaves(plan.consts[0]))
    pad = len(plan.consts) - 1 - len(wanted)
    wanted_t = (False,) * tapes + tuple(wanted) + (False,) * pad
    compact = tier.Compact(
        plan,
        _jacobian_jit(plan.L, m_t, devices, elemental, with_q, wanted_t),
        (plan.L, m_t, devices, elemental, with_q, wanted_t),
        _JACOBIAN_OUT_TREE,
        (q0, order, plan.consts, *rest),
    )
    return compact.run("jacobian", specialized)


@functools.lru_cache(maxsize=64)
def _jacobian_jit(L, m, devices, elemental, with_q, wanted):
    """`forward_jacobian` of the compiled sweep, compiled (`_sweep_call_jvp`); the
    compiler options are the outer program's (a nested `jit` takes none)."""
    jitted = _sweep_jit(L, m, devices)

    def jacobian(q0, order, consts, *rest):
        run = lambda q0, consts: jitted(q0, order, consts, *rest)
        return forward_jacobian(run, q0, consts, with_q, wanted)

    options = elemental_options() if elemental else None
    return jax.jit(jacobian, compiler_options=options)


_sweep_call.defjvp(_sweep_call_jvp, symbolic_zeros=True)


# The structure of `_sweep_body`'s outputs, and of its forward jacobian's.
_OUT_TREE = jax.tree.structure((Periods(*[0] * 5), 0))
# The compact sweep's loops compiled as one function each: those whose iteration
# reads and writes fewer bytes (`executables.program`'s `loop_bytes`).
_INNER_LOOPS = 10_000_000
_JACOBIAN_OUT_TREE = jax.tree.structure(((Periods(*[0] * 5), 0), 0))


@functools.lru_cache(maxsize=64)
def _sweep_jit(L, m, devices, elemental=False, wide=False):
    """`_sweep_body` compiled for one Lagrangian, method and device set: a plain
    `jax.jit` (its C++ dispatch), not `eqx.filter_jit`, whose Python-side flattening
    and hashing of the static arguments cost a noticeable part of a sweep. `wide`:
    with `vector_options()`, for a program that is not called inside another (a
    `jit` with compile options cannot be)."""
    body = functools.partial(_sweep_body, L, m, devices)
    if elemental:
        # (`executables.program`: the compact tier's, which `executables.call`
        # compiles where XLA keeps its loops whole, so that a busy second core, e.g.
        # compiling the specialized program, does not hold up its loops' parts; its
        # inner loops, the Taylor coefficients' and the steps', each one function:
        # its outer loops too would lengthen the compile for no faster sweep.)
        return executables.program(body, elemental_options(), loop_bytes=_INNER_LOOPS)
    return jax.jit(body, compiler_options=(vector_options() or None) if wide else None)


def _sweep_body(L, m, devices, q0, order, consts, rtol, atol, t_max, energy_tol):
    out = periods_diff(L, m, devices, q0[order], consts, rtol, atol, t_max, energy_tol)
    back = lambda x: jnp.zeros_like(x).at[order].set(x, unique_indices=True)
    out = Periods(
        back(out.periods),
        back(out.status),
        back(out.steps),
        out.executed,
        back(out.estimate),
    )
    # The total of the steps too: `jnp.sum` outside costs an XLA compile of its own.
    return out, jnp.sum(out.steps)


class SweepResult(eqx.Module):
    r"""The outcome of `sweep_periods`, in the order of the input amplitudes.

    **Fields:**

    - `periods`: the periods, NaN where `status != 0`.
    - `status`: int32 codes, 0 for success; `lagrax.status_message(code)` says what
        the others mean.
    - `num_steps`: solver steps (accepted and rejected) per amplitude, all solves of
        the lane together.
    - `lane_steps_useful`: the sum of `num_steps`, the work each lane needed.
    - `lane_steps_executed`: the lane-steps the compiled loops ran (every lane
        steps at every iteration: a lane left without work at the queue's end
        counts here, not in `lane_steps_useful`).
    - `lanes`: lanes per loop and device; `num_devices`: devices used.
    - `error_estimate`: the per-lane estimate of the relative error (None when not
        asked for).
    - `solver`: the solver that stepped the lanes (for the default
        `Taylor(fallback=Dopri8())`, the plain `Taylor()` or its fallback).
    """

    periods: Float[Array, " n"]
    status: Int[Array, " n"]
    num_steps: Int[Array, " n"]
    lane_steps_useful: Int[Array, ""]
    lane_steps_executed: Int[Array, ""]
    lanes: int = eqx.field(static=True)
    num_devices: int = eqx.field(static=True)
    error_estimate: Float[Array, " n"] | None = None
    solver: object = eqx.field(static=True, default=None)

    @property
    def useful_fraction(self) -> Array:
        """Useful lane-steps over executed ones (1.0 = no lane ever waited)."""
        return self.lane_steps_useful / jnp.maximum(self.lane_steps_executed, 1)

    @property
    def ok(self) -> Array:
        """Boolean mask of the successful amplitudes."""
        return self.status == SUCCESS

    def messages(self) -> list[str]:
        """`status_message` of each amplitude (a Python list; eager only)."""
        return [status_message(c) for c in np.asarray(self.status)]
