r"""Many trajectories at once: one compiled loop per device over refilling lanes.

`simulate_batch` integrates a batch of releases with `lagrax.Taylor` in one
`lax.while_loop` per device over `lanes` lanes, not as `jax.vmap` of a diffrax solve.
Every iteration advances every lane by one Taylor step computed on the lane-batched
arrays (the coefficient program of the vector field, unrolled over the orders and
fused by XLA into one loop over the lanes), with the step length chosen from the
last coefficients before the step (as heyoka.py does); a lane whose trajectory ends
writes its result and takes the next release from the queue, so lanes never wait for
the slowest one. States at the requested times come from the step's own polynomials.
Where L (or the force) switches branch with the state or time (`jnp.where` on a
comparison, `abs`, `max`, ...), each step is checked at its end (its defect: the
acceleration there against its polynomial's) and rejected across a switch, the next
one shorter, as a Runge–Kutta controller's estimate makes it; elsewhere no step is
rejected. With another solver it is `jax.vmap` of `lagrax.simulate`.

Why not `vmap(diffeqsolve)`: under `vmap` diffrax's loop runs every lane to the
slowest one's step count and pays its general bookkeeping per lane-step (stage loop,
controller, saving), several times the Taylor step of a small system.
"""

import collections
import dataclasses
import functools
import os
import time
import warnings
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._cache import executables
from .._cache.executables import cached_call
from .._checks import (
    as_array,
    as_real_array,
    check_callable,
    check_instance,
    is_concrete,
    lane_count,
    positive_int,
    positive_scalar,
)
from .._custom_types import GeneralizedForce, Lagrangian
from .._jaxpr.canonical import canonical_lagrangian, CanonicalLagrangian
from .._jaxpr.fusion import elemental_options
from .._jaxpr.switches import switches
from .._stepper.base import LaneField
from .._taylor import compact
from .._taylor.stepper import log2_approx, TaylorStepper, TRUNCATION
from .._taylor.system import System
from .._taylor.taylor import chosen_order, order_is_chosen, Taylor
from .simulate import elemental, simulate
from .term import _LagrangeVectorField, BoundLagrangian


# The most equations (orders x nodes of the system's program, L's constants among
# its arguments) a step unrolls: a chain of six pendulums at order 16 (8,208).
_UNROLL_BUDGET = 10_000
# The compact program's loops compiled as one function each: every loop
# (`executables.program`'s `loop_bytes`, bytes an iteration reads and writes).
_EVERY_LOOP = 1 << 62

# Per-lane outcome codes of the loop, mapped onto diffrax.RESULTS at the end.
_RUNNING, _DONE, _MAX_STEPS, _NONFINITE = 0, 1, 2, 3


_LN2 = float(np.log(2.0))


def _exp2(x):
    r"""$2^x$ to 1e-6 relative (1e-5 in float32) from multiply-adds
    and the exponent's bits of `x`'s own dtype (no libm call, no operation XLA counts
    as expensive); $+\infty$, 0 and NaN where `jnp.exp2` gives them (below the
    smallest normal: 0). A step length needs a few digits."""
    finfo = jnp.finfo(x.dtype)
    bits = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}[finfo.dtype.itemsize]
    n = jnp.floor(x)
    f = x - n  # in [0, 1)
    # 2^f on [0, 1): the degree-7 Taylor polynomial of exp(f ln 2), Horner.
    p = jnp.ones_like(f)
    for k in range(7, 0, -1):
        p = 1.0 + p * f * (_LN2 / k)
    bias = finfo.maxexp - 1
    e = jnp.clip(jnp.nan_to_num(n), finfo.minexp, bias).astype(bits)
    scale = jax.lax.bitcast_convert_type((e + bias) << finfo.nmant, x.dtype)
    out = p * scale
    out = jnp.where(x > finfo.maxexp, jnp.inf, out)
    out = jnp.where(x < finfo.minexp, 0.0, out)
    return jnp.where(jnp.isnan(x), x, out)


class SystemTaylorStepper(TaylorStepper):
    r"""The period loop's Taylor step (`TaylorStepper`: step length, polynomials,
    one fusion) with its coefficients from the program of the first-order system
    $y = (q, w)$, $q' = w$, $w' = \ddot q(\sigma	au, q, \sigma w)$ for any number
    of coordinates: a lane integrates in its own time $	au = \sigma t$, $\sigma =
    \pm 1$ its direction (`field.params`), so every step is forward."""

    system: System = eqx.field(static=True)

    # The step leaves its loop through a select (`one_fusion`'s `branch_free`): a
    # stack there made XLA emit the recurrence once per output, which LLVM merges
    # back only for small systems. XLA keeps expensive operations out of such a loop
    # and would copy the recurrence into the one of the step length's exp2, so that
    # exp2 is `exp2` below: multiply-adds and a bit shift.
    branch_free: ClassVar[bool] = True

    def exp2(self, x):
        return _exp2(x)

    def acceleration(self, s, x, v, sigma):
        """The acceleration at `(s, x, v)` (tuples of `(W,)` columns) on every lane:
        the program at order 1, whose one evaluation at order 0 fuses with the
        step."""
        n = len(x)
        state = [jnp.stack(x, axis=1), jnp.stack(v, axis=1)]
        coefs = self.system.coefficients(1, s, state, [sigma], unrolled=True, trig=True)
        return tuple(c[1] for c in coefs[n:])

    def coefficients(self, field, s, x, v):
        K = self.order
        stacked = [jnp.stack(x, axis=1), jnp.stack(v, axis=1)]
        # Unrolled, the orders are one vectorized loop over the lanes (through the
        # select of `branch_free`); looped, every order is a few hundred small
        # loops, several times slower. The budget bounds the unrolled program's
        # compile, which grows with its size (benchmarks/README.md).
        unrolled = K * len(self.system.prog.nodes) <= _UNROLL_BUDGET
        coefs = self.system.coefficients(
            K, s, stacked, [field.params], unrolled=unrolled, trig=True
        )
        n = len(x)
        # Per order, the state's columns as a tuple (`x`, `v` are tuples of (W,)
        # columns): stacked into (W, n) arrays, each order would be a fusion of its
        # own, and XLA would copy the recurrence into each.
        at = lambda cs, k: tuple(c[k] for c in cs)
        xs = [at(coefs[:n], k) for k in range(K + 1)]
        vs = [at(coefs[n:], k) for k in range(K + 1)]
        return (
            xs,
            vs,
            [jax.tree.map(lambda c: (k + 1) * c, vs[k + 1]) for k in range(K)],
        )


class CompactTaylorStepper(TaylorStepper):
    r"""`SystemTaylorStepper`'s step with the coefficients from a compact tape
    (`lagrax._taylor.compact`): the compiled step is the same for every system of
    the tape's size class, the tape an argument of the program."""

    tape: compact.CompactTape
    branch_free: ClassVar[bool] = True

    def exp2(self, x):
        return _exp2(x)

    def coefficients(self, field, s, x, v):
        K, n = self.order, len(x)
        cols = compact.compact_coefficients(
            self.tape, K, s, [*x, *v], [field.params], trig=True
        )
        xs = [tuple(c[k] for c in cols[:n]) for k in range(K + 1)]
        vs = [tuple(c[k] for c in cols[n:]) for k in range(K + 1)]
        return xs, vs, [tuple((k + 1) * c for c in vs[k + 1]) for k in range(K)]

    def acceleration(self, s, x, v, sigma):
        """The acceleration at `(s, x, v)` on every lane (the tape at order 1)."""
        n = len(x)
        cols = compact.compact_coefficients(
            self.tape, 1, s, [*x, *v], [sigma], trig=True
        )
        return tuple(c[1] for c in cols[n:])


class _Config(eqx.Module):
    """What the compiled loop depends on besides array values (hashable). `L`: the
    canonical Lagrangian (equal for every `L` with the same body: a rebuilt `L` with
    new parameter values reuses the program, its values the loop's `consts`)."""

    L: CanonicalLagrangian | None
    force: GeneralizedForce | None
    order: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    n_save: int = eqx.field(static=True)
    save_t1: bool = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    # The compact tier: the program's equations are its last argument (a tape),
    # not `L` and `force` (None).
    compact: bool = eqx.field(static=True, default=False)
    # Whether L or the force switches branch with the state or time (`switches`):
    # then every step is checked where it ends.
    checked: bool = eqx.field(static=True, default=False)


def _run(cfg, q0, v0, t0, t1, rtol, atol, ts, source):
    """All releases through `cfg.width` refilling lanes of one device.

    Returns the saved states `(B, T, 2n)` (`T` = the save times, then the end if
    `save_t1`), and per release the end time, the outcome, the steps tried and
    those of them rejected.

    Each lane carries its state as `(W, n)` arrays and its time and constants as one
    `(W, 6)` array, and the queue is one table of packed rows: a refill is one gather
    and a lane's results one scatter (each gather, scatter or small fusion is a
    separate call per iteration on a CPU, and a scatter is a loop over its rows).
    """
    B, n = q0.shape
    dtype = q0.dtype
    W = min(cfg.width, B)
    M = cfg.n_save
    rule = dict(order=cfg.order, max_step=np.inf, truncation=TRUNCATION)
    if cfg.compact:  # (`source`: the tape of the system's equations)
        stepper = CompactTaylorStepper(**rule, tape=source)
    else:  # (`source`: the values of the canonical Lagrangian's constants)
        system = _system(cfg.L, source, cfg.force, q0[0], v0[0])
        stepper = SystemTaylorStepper(**rule, system=system)
    # Whether each step is checked for a switch of L's branches inside it (see
    # `TaylorStepper.defect`): only where L or the force has one.
    checked = cfg.checked
    sign = jnp.where(t1 >= t0, 1.0, -1.0).astype(dtype)
    # One row per release: its state in its own time (q, sigma qdot), its start
    # time sigma t0 as a sum of two floats (S0 + S0_LO, the low part 0 at release),
    # its end time sigma t1, sigma and its tolerances; one idle row at B.
    # After a rejected step, HMAX is the longest next step: the rest of the
    # rejected one's span (where a branch of the acceleration switched) once a
    # shorter step is taken; infinite otherwise.
    S0, S0_LO, S1, SIGMA, RTOL, ATOL, HMAX = range(7)
    inf = jnp.full_like(t0, jnp.inf)
    consts = jnp.stack(
        [sign * t0, jnp.zeros_like(t0), sign * t1, sign, rtol, atol, inf], axis=1
    )
    rows = jnp.concatenate([q0, sign[:, None] * v0, consts], axis=1)
    idle = jnp.zeros((1, 2 * n + 7), dtype).at[0, 2 * n + SIGMA].set(1.0)
    idle = idle.at[0, 2 * n + S1].set(1.0).at[0, 2 * n + HMAX].set(jnp.inf)
    table = jnp.concatenate([rows, idle])
    # The save times in each lane's own time: sigma ts[j].
    taus = lambda p, j: p[:, SIGMA] * ts[jnp.minimum(j, M - 1)]

    def load(idx):
        row = table[jnp.minimum(idx, B)]
        return row[:, :n], row[:, n : 2 * n], row[:, 2 * n :], idx >= B

    def body(carry):
        x, v, p, ints, done, saves, ends, nxt = carry
        idx, j, steps, rejected = ints[:, 0], ints[:, 1], ints[:, 2], ints[:, 3]
        active = ~done
        s, s_lo = p[:, S0], p[:, S0_LO]
        sigma = p[:, SIGMA]
        # No acceleration: the step ends with its polynomials' (checked below where
        # L switches branch).
        lane_field = LaneField(accel=None, params=sigma)
        # Never past the end, nor past a rejected step's span, and at most one save
        # time inside a step (the state there read from the step's polynomials,
        # inside its fusion).
        to_end = (p[:, S1] - s) - s_lo
        cap = jnp.minimum(to_end, p[:, HMAX])
        if M:
            after = jnp.where(j + 1 < M, (taus(p, j + 1) - s) - s_lo, jnp.inf)
            cap = jnp.minimum(cap, after)

            def within(raw):
                qs, ws = raw.expansion.at((taus(p, j) - s) - s_lo)
                return eqx.tree_at(lambda r: r.extras, raw, (qs, ws), is_leaf=_none)

        else:
            within = None
        cols = lambda y: tuple(y[:, i] for i in range(n))
        step = stepper.step(
            lane_field, s, cols(x), cols(v), cols(x), cap, p[:, RTOL], p[:, ATOL],
            free=active, cap=cap, within=within,
        )  # fmt: skip
        x1, v1 = jnp.stack(step.x, axis=1), jnp.stack(step.v, axis=1)
        # A step across a switch of the acceleration (its defect above 1: see
        # `TaylorStepper.defect`) is rejected, and the next one is shorter, as a
        # Runge-Kutta controller shrinks its step across such a switch.
        error = step.error
        if checked:
            a_end = stepper.acceleration(s + step.h, step.x, step.v, sigma)
            rtols, atols = p[:, RTOL], p[:, ATOL]
            defect = stepper.defect(step, a_end, cols(x), cols(v), rtols, atols)
            error = jnp.where(jnp.isfinite(error), defect, jnp.nan)
        finite = jnp.isfinite(x1).all(1) & jnp.isfinite(v1).all(1) & jnp.isfinite(error)
        accept = active & finite & (error <= 1.0)
        reject = active & finite & ~accept
        # The time as a compensated sum (two floats): rounded once per step, it
        # would drift by ~sqrt(steps) ulps, a phase error that no tolerance removes
        # (heyoka.py keeps its time the same way).
        t, t_lo = _two_sum(s, step.h + s_lo)
        end = accept & (step.h >= to_end)  # the step capped at the end time
        t = jnp.where(end, p[:, S1], jnp.where(accept, t, s))
        t_lo = jnp.where(end, 0.0, jnp.where(accept, t_lo, s_lo))
        x = jnp.where(accept[:, None], x1, x)
        v = jnp.where(accept[:, None], v1, v)
        hmax = p[:, HMAX]
        shrink = _exp2(-log2_approx(error) / (cfg.order + 1))
        shrink = jnp.clip(0.9 * shrink, 0.2, 0.9)
        hmax = jnp.where(
            reject,
            step.h * shrink,
            jnp.where(accept & (step.h < hmax), hmax - step.h, jnp.inf),
        )
        steps = steps + active.astype(steps.dtype)
        rejected = rejected + reject.astype(rejected.dtype)
        if M:
            hit = accept & (j < M) & ((t - taus(p, j)) + t_lo >= 0)
            qs, ws = (jnp.stack(c, axis=1) for c in step.extras)
            ysave = jnp.concatenate([qs, p[:, SIGMA, None] * ws], axis=1)
            saves = saves.at[jnp.where(hit, idx, B), jnp.minimum(j, M - 1)].set(
                ysave, mode="drop"
            )
            j = j + hit.astype(j.dtype)
        finished = active & (end | ~finite | (steps >= cfg.max_steps))
        code = jnp.where(~finite, _NONFINITE, jnp.where(end, _DONE, _MAX_STEPS))
        row = jnp.concatenate(
            [x, sigma[:, None] * v, sigma[:, None] * t[:, None],
             code[:, None].astype(dtype), steps[:, None].astype(dtype),
             rejected[:, None].astype(dtype)],
            axis=1,
        )  # fmt: skip
        ends = ends.at[jnp.where(finished, idx, B)].set(row, mode="drop")
        # Refill: finished lanes take the next releases of the queue, in lane order.
        rank = jnp.cumsum(finished.astype(idx.dtype)) - 1
        new_idx = jnp.where(finished, nxt + rank, idx)
        x_new, v_new, p_new, idle = load(new_idx)
        x = jnp.where(finished[:, None], x_new, x)
        v = jnp.where(finished[:, None], v_new, v)
        # (As `p` stores them: the float32 releases' times and caps are float32.)
        t_p, t_lo_p, hmax_p = (jnp.asarray(a, p.dtype) for a in (t, t_lo, hmax))
        p = p.at[:, S0].set(t_p).at[:, S0_LO].set(t_lo_p).at[:, HMAX].set(hmax_p)
        p = jnp.where(finished[:, None], p_new, p)
        zero = jnp.zeros_like(j)
        ints = jnp.stack(
            [new_idx, jnp.where(finished, zero, j), jnp.where(finished, zero, steps),
             jnp.where(finished, zero, rejected)],
            axis=1,
        )  # fmt: skip
        done = jnp.where(finished, idle, done)
        nxt = nxt + jnp.sum(finished).astype(nxt.dtype)
        return x, v, p, ints, done, saves, ends, nxt

    def cond(carry):
        return jnp.any(~carry[4])

    idx0 = jnp.arange(W, dtype=jnp.int32)
    x, v, p, done = load(idx0)
    ints = jnp.stack([idx0] + [jnp.zeros_like(idx0)] * 3, axis=1)
    # Lanes with nothing to write aim past the end, and their rows are dropped: on
    # a GPU, a scatter whose lanes all write one spare row serializes those writes.
    saves = jnp.full((B, M, 2 * n), jnp.nan, dtype)
    ends = jnp.full((B, 2 * n + 4), jnp.nan, dtype)
    carry = (x, v, p, ints, done, saves, ends, jnp.int32(W))
    *_, saves, ends, _ = jax.lax.while_loop(cond, body, carry)
    m = 2 * n
    ys = saves
    if cfg.save_t1:
        ys = jnp.concatenate([ys, ends[:, None, :m]], axis=1)
    code = jnp.where(jnp.isnan(ends[:, m + 1]), _RUNNING, ends[:, m + 1])
    counts = ends[:, m + 2 : m + 4].astype(jnp.int32)
    return ys, ends[:, m], code.astype(jnp.int32), counts[:, 0], counts[:, 1]


def _system(L_c, consts, force, q, v):
    r"""The program of $q' = w$, $w' = \\ddot q(\\sigma \\tau, q, \\sigma w)$ (a lane in
    its own time, `sigma` its direction)."""
    field = _LagrangeVectorField(lambda q, qdot, t: L_c(q, qdot, t, *consts), force)

    def f(tau, ys, params):
        q, w = ys
        (sigma,) = params
        return [w, field(sigma * tau, (q, sigma * w), None)[1]]

    zero = np.zeros((), q.dtype)
    return System(f, zero, [q, v], [np.ones((), q.dtype)])


def _order(solver, rtol, atol) -> int:
    """The solver's order, or where it is left to the call (`Taylor(order=None)`)
    the one for the tightest release's tolerance (`Taylor`'s docstring)."""
    if not order_is_chosen(solver):
        return solver.order
    tol = None
    if is_concrete(rtol, atol):  # (per release, NumPy: no op-by-op compile)
        tol = float(np.min(np.maximum(np.asarray(rtol), np.asarray(atol))))
    return chosen_order(tol)


def _switches(L_c, consts, force, n, dtype) -> bool:
    """Whether L or the force switches branch with the state or time (traced once,
    nothing evaluated)."""
    q = jax.ShapeDtypeStruct((n,), dtype)
    state = (q, q, jax.ShapeDtypeStruct((), dtype))
    found = switches(lambda q, qdot, t, *c: L_c(q, qdot, t, *c), state, consts)
    return found or (force is not None and switches(force, state))


def _none(x):
    return x is None


def _two_sum(a, b):
    """`(s, e)` with `s = fl(a + b)` and `s + e = a + b` exactly (Knuth's TwoSum)."""
    s = a + b
    b_virtual = s - a
    return s, (a - (s - b_virtual)) + (b - b_virtual)


@functools.cache
def _compiled(cpu, devices):
    """`_run` compiled once per configuration; over several devices, each runs its
    own loop over its share of the releases (`jax.shard_map`); then `_assemble`d
    (`shape`: its static arguments), in the same program: op by op, its few
    operations compile on a process's first call, a third of a later process's call
    of a loaded program."""
    jitted = jax.jit(
        lambda cfg, shape, *args: _assemble(*shape, *_looped(devices)(cfg, *args)),
        static_argnums=(0, 1),
        compiler_options=elemental_options() if cpu else None,
    )
    return jitted


def _plain(cfg, shape, cpu, devices):
    """`_compiled(cpu, devices)`'s program, its static arguments bound, without
    compile options (`executables.compile_later` exports it)."""
    return jax.jit(lambda *args: _assemble(*shape, *_looped(devices)(cfg, *args)))


@functools.cache
def _compact_program(cfg, shape, cpu, devices):
    """`_compiled` for the compact tier, its static arguments bound: the program
    takes the tape as its last argument and depends on its size class only."""
    return executables.program(
        lambda *args: _assemble(*shape, *_looped(devices)(cfg, *args)),
        elemental_options() if cpu else {},
        # (Every loop one function: its loops over blocks and orders, and the step's.)
        loop_bytes=_EVERY_LOOP if cpu else None,
    )


def _looped(devices):
    """`_run`, over several devices one loop each on its share (`jax.shard_map`);
    its outputs followed by the save times (`ts_arr`, `_assemble`'s last argument)."""
    if len(devices) == 1:
        fn = _run
    else:
        mesh = jax.sharding.Mesh(np.array(devices), ("releases",))
        lanes, rep = (
            jax.sharding.PartitionSpec("releases"),
            jax.sharding.PartitionSpec(),
        )

        def fn(cfg, *args):
            return jax.shard_map(
                functools.partial(_run, cfg),
                mesh=mesh,
                in_specs=(lanes,) * 6 + (rep, rep),
                out_specs=lanes,
                check_vma=False,
            )(*args)

    # (args: q0, qdot0, t0, t1, rtol, atol, ts_arr, consts)
    return lambda cfg, *args: (*fn(cfg, *args), args[-2])


def _saveat_plan(saveat):
    """`(ts, save_t1)` for a `SaveAt` the loop supports (states at `ts`, at `t1`, or
    both), else `"vmap"` (then `jax.vmap` of `simulate` runs it: `t0=True`, `steps`,
    `dense`, a `fn`, several `SubSaveAt`s)."""
    if saveat is None:
        return None, True
    sub = saveat.subs
    if not isinstance(sub, dfx.SubSaveAt) or sub.steps or saveat.dense:
        return "vmap"
    if sub.fn is not dfx.SubSaveAt.__dataclass_fields__["fn"].default:
        return "vmap"
    ts = None if sub.ts is None else jnp.asarray(sub.ts)
    if sub.t0:
        return "vmap"
    return ts, bool(sub.t1)


def simulate_batch(
    L: Lagrangian,
    q0,
    qdot0,
    t0,
    t1,
    *,
    force: GeneralizedForce | None = None,
    solver: dfx.AbstractSolver | None = None,
    saveat: dfx.SaveAt | None = None,
    rtol=1e-8,
    atol=1e-8,
    max_steps: int = 16384,
    throw: bool = True,
    lanes: int | None = None,
    **kwargs,
) -> dfx.Solution:
    r"""Integrates Lagrange's equations from a batch of releases, batch axis first.

    The batched form of `lagrax.simulate`: release $b$ starts at
    $(q_0[b], \dot q_0[b])$ at $t_0[b]$ and ends at $t_1[b]$ (scalars apply to every
    release). With `solver=lagrax.Taylor(...)` (the default; without an `order`, its
    order chosen from the tolerance) the batch runs in one compiled loop per device
    over `lanes` lanes, a lane that finishes taking the next release from a queue:
    step lengths by `lagrax.Taylor`'s rule with
    $\varepsilon = \text{atol} + \text{rtol}\,\lVert y\rVert_\infty$ per release (at
    the same tolerances as accurate as `diffrax.Dopri8`, or more), saved states from
    the steps' polynomials. Any other solver, or a `SaveAt` or keyword the loop does
    not take (`SaveAt(t0=True)`, `steps`, `dense`, `fn`; `event`, `adjoint`, a
    `stepsize_controller`, `dt0`), runs `jax.vmap` of `lagrax.simulate` with the same
    arguments (on a CPU compiled once, for the next call with the same `L`, solver
    and keywords).

    The loop is compiled per body of `L`: a rebuilt `L` with new parameter values
    reuses it (they reach it as arguments), and on a CPU a later process loads it
    from the library's disk cache. A new Lagrangian's first eager calls on a CPU may
    run on a compact program shared by Lagrangians of a size class, until the time
    spent there would pay for its own program's compile. Under your own `jax.jit` the
    loop becomes part of your program: on a CPU give that `jit`
    `compiler_options={"xla_cpu_use_fusion_emitters": False}` (XLA's elemental
    emitters, which eager calls take): with the default emitters a large loop (the
    double pendulum at order 16) compiles several times longer. Forward mode (`jax.jvp`,
    `jax.jacfwd`) differentiates it; reverse mode does not (a `lax.while_loop`): for
    `jax.grad`, `jax.vmap` of `lagrax.simulate` with a diffrax adjoint. Speed against
    heyoka.py: `benchmarks/README.md`.

    `lagrax.Taylor(fallback=...)` batches with its fallback where L has a primitive
    without a Taylor recurrence, as in `lagrax.simulate`.

    **Arguments:** as `lagrax.simulate`, with `q0`, `qdot0` of shape `(B, n)`,
    `t0`, `t1`, `rtol`, `atol` scalars or of shape `(B,)`, `solver` by default
    `lagrax.Taylor()` (the solver the loop is built for; `simulate`'s default,
    `Tsit5()`, would run as `jax.vmap` of `simulate`), and

    - `lanes`: lanes of the compiled loop per device (static); by default 256 on a
        CPU and, on a GPU, every release of a device's share up to 131,072 (a GPU
        needs many lanes in flight).

    **Returns:**

    A `diffrax.Solution` whose every array has the batch axis first: `ts` `(B, T)`,
    `ys = (qs, qdots)` of shape `(B, T, n)`, `result` `(B,)` (per release:
    `successful`, `max_steps_reached`, or `nonfinite` where the state stopped being
    finite, e.g. a singular mass matrix), `stats["num_steps"]` `(B,)`.

    **Raises:** as `lagrax.simulate`; with `throw=True`, a `RuntimeError` naming how
    many releases failed.

    **Example:**

    ```python
    L = lagrax.systems.double_pendulum.lagrangian()
    q0 = jax.random.uniform(jax.random.key(0), (256, 2), minval=-1.0, maxval=1.0)
    sol = lagrax.simulate_batch(L, q0, jnp.zeros_like(q0), 0.0, 10.0,
                                rtol=1e-12, atol=1e-12)
    q_end = sol.ys[0][:, -1]  # q at t = 10, one row per release
    ```
    """
    check_callable(L, "L", "a function L(q, qdot, t) -> scalar")
    solver = Taylor() if solver is None else solver
    check_instance(solver, "solver", dfx.AbstractSolver, "a diffrax solver")
    if isinstance(solver, Taylor) and solver.fallback is not None:
        # As in `simulate`: where L's accelerations have a primitive without a
        # Taylor recurrence, tracing the Taylor program raises `NotImplementedError`,
        # and the caller allowed the fallback to step instead.
        kwargs = dict(
            force=force, saveat=saveat, rtol=rtol, atol=atol, max_steps=max_steps,
            throw=throw, lanes=lanes, **kwargs,
        )  # fmt: skip
        try:
            taylor = dataclasses.replace(solver, fallback=None)
            return simulate_batch(L, q0, qdot0, t0, t1, solver=taylor, **kwargs)
        except NotImplementedError:
            fallback = solver.fallback
            return simulate_batch(L, q0, qdot0, t0, t1, solver=fallback, **kwargs)
    q0 = as_real_array(q0, "q0")
    qdot0 = as_real_array(qdot0, "qdot0")
    if q0.ndim != 2 or qdot0.shape != q0.shape:
        raise ValueError(
            "`q0` and `qdot0` must have shape (B, n), the batch axis first; got "
            f"{q0.shape} and {qdot0.shape}."
        )
    dtype = jnp.result_type(q0, qdot0)
    q0, qdot0 = q0.astype(dtype), qdot0.astype(dtype)
    B = q0.shape[0]
    per_release = lambda x, name: _per_release(x, name, B, dtype)
    t0, t1 = per_release(t0, "t0"), per_release(t1, "t1")
    rtol = per_release(_positive(rtol, "rtol", dtype), "rtol")
    atol = per_release(_positive(atol, "atol", dtype), "atol")
    max_steps = positive_int(max_steps, "max_steps")
    # One loop per device, each over its share of the releases.
    devices = tuple(jax.local_devices())
    D = len(devices) if B >= len(devices) else 1
    lanes = lane_count(
        lanes, "lanes", devices, -(-B // D), cpu=256, accelerator=1 << 17
    )
    plan = _saveat_plan(saveat)
    if not isinstance(solver, Taylor) or plan == "vmap" or kwargs:
        # (Keyed on what L computes: a rebuilt L with new parameter values reuses
        # the program, its values as arguments.)
        try:
            L_c, consts = canonical_lagrangian(L, dtype, q0.shape[1])
            bound = BoundLagrangian(L_c, tuple(consts))
        except Exception:  # noqa: BLE001 -- `simulate` names what is wrong with `L`
            bound = L
        args = (bound, force, solver, saveat, max_steps, kwargs)
        args += (q0, qdot0, t0, t1, rtol, atol)
        if devices[0].platform == "cpu":
            # One program, kept for the next call with the same static parts (run op
            # by op, the vmapped solve compiles its loop again at every call), with
            # XLA's elemental emitters: the lane-batched step stays one loop.
            sol = elemental(_vmapped)(*args)
        else:
            sol = _vmapped(*args)
        return _raise_if_failed(sol, throw)
    ts, save_t1 = plan
    L_c, consts = canonical_lagrangian(L, dtype, q0.shape[1])
    consts = tuple(consts)
    cfg = _Config(
        L=L_c,
        force=force,
        order=_order(solver, rtol, atol),
        width=lanes,
        n_save=0 if ts is None else int(ts.shape[0]),
        save_t1=save_t1,
        max_steps=max_steps,
        checked=_switches(L_c, consts, force, q0.shape[1], dtype),
    )
    ts_arr = np.zeros((0,), dtype) if ts is None else ts.astype(dtype)
    cpu = jax.default_backend() == "cpu"
    args = (q0, qdot0, t0, t1, rtol, atol)
    if B % D:  # padded with copies of the last release, dropped below
        args = tuple(
            jnp.concatenate([a, jnp.repeat(a[-1:], D - B % D, 0)]) for a in args
        )
    jitted = _compiled(cpu, devices[:D])
    shape = (B, q0.shape[1], ts is not None, save_t1)
    if is_concrete(args, ts_arr, consts):  # (a later process loads it from disk,
        options = elemental_options() if cpu else None  # (pre-key: no tracing)
        call = (jitted, options, cfg, shape, *args, ts_arr, consts)
        out = _tiered(call, (_compiled, cpu, devices[:D]), q0.shape[1], dtype)
    else:
        try:
            out = jitted(cfg, shape, *args, ts_arr, consts)
        except ValueError:
            if not cpu:
                raise
            # JAX refuses compile options on a `jit` staged into a caller's program
            # (its `jit`, `grad`), which compiles it with its own (the docstring
            # says which); under `vmap` or `jvp` it takes them.
            jitted = _compiled(False, devices[:D])
            out = jitted(cfg, shape, *args, ts_arr, consts)
    ts_out, qs, vs, result, nsteps, accepted, rejected, failed = out
    result = jax.tree.unflatten(_RESULT_TREE, [result])
    sol = dfx.Solution(
        t0=t0,
        t1=t1,
        ts=ts_out,
        ys=(qs, vs),
        interpolation=None,
        stats=dict(
            num_steps=nsteps,
            num_accepted_steps=accepted,
            num_rejected_steps=rejected,
            max_steps=max_steps,
        ),
        result=result,
        solver_state=None,
        controller_state=None,
        made_jump=None,
        event_mask=None,
    )
    if throw and is_concrete(failed):  # (counted in the program: no op-by-op here)
        _raise_if_count(int(failed), B)
        return sol
    return _raise_if_failed(sol, throw)


# (The loop's program returns `result`'s array: an enumeration item's tree does
# not survive pickling, where the disk cache keeps the output structure.)
_RESULT_TREE = jax.tree.structure(dfx.RESULTS.successful)
_OUT_TREE = jax.tree.structure((0,) * 8)  # (`_assemble`'s outputs)

# --- tiers: the compact program first, the specialized one once it pays -----------
#
# The specialized program (the Lagrangian's recurrences written out) runs fastest,
# but XLA compiles it for seconds to minutes per Lagrangian; the compact program
# (`lagrax._taylor.compact`) is compiled once per size class and kept on disk, so a
# new Lagrangian costs the building of its tape, and runs several times slower. A
# call takes the specialized program where it is compiled or on disk, or where its
# compile is short (`_COMPACT_FROM`); otherwise the compact one, until the time
# spent on it with this Lagrangian and configuration reaches the specialized
# compile's (a ski rental: never more than twice the better of the two choices
# made with hindsight), as a JIT's first tier. Where the process leaves a core idle,
# the second call compiles the specialized program in a worker process there
# instead (`executables.compile_later`), which takes over once on disk.

# Estimated specialized compiles shorter than this (s) are not worth a tier.
_COMPACT_FROM = 2.0
# Seconds spent on the compact program per configuration.
_SPENT: collections.Counter = collections.Counter()
_TAPES: collections.OrderedDict = collections.OrderedDict()
_STEP_NODES: collections.OrderedDict = collections.OrderedDict()
_MAX_TAPES = 64
_NOTIFIED: set = set()


def _tiered(call, origin, n, dtype):
    """The loop's outputs through the specialized program or the compact one
    (above). `call`: `(jitted, options, cfg, shape, *args)` as `cached_call` takes
    them; `origin` its factory and arguments."""
    jitted, options, cfg, shape, *args = call
    specialized = lambda: cached_call(
        jitted, options, cfg, shape, *args, n_static=2, origin=origin
    )
    consts = args[-1]
    if not _compact_applies():
        return specialized()
    only = _compact_mode() == "2"
    if not only and _known(jitted, options, origin, (cfg, shape, *args)):
        return specialized()
    found = _tape(cfg.L, consts, cfg.force, n, dtype)
    if found is None:
        return specialized()
    tape, nodes = found
    estimate = _compile_estimate(nodes, cfg.order)
    if not only and estimate < _COMPACT_FROM:
        return specialized()
    # Beyond the unroll budget the specialized step loops over the orders, and runs
    # slower than the compact program (benchmarks/README.md): the compact tier stays.
    rents = not only and (
        cfg.order * _step_nodes(cfg.L, consts, cfg.force, n, dtype) <= _UNROLL_BUDGET
    )
    # From the second call with this configuration (a job that repeats), where a
    # core is idle, the specialized program compiles there meanwhile and takes over
    # once on disk; else, the ski rental.
    later = None
    if rents and _SPENT[cfg] > 0:
        later = executables.compile_later(
            _plain(cfg, shape, *origin[1:]), jitted, options, cfg, shape, *args,
            n_static=2, origin=origin,
        )  # fmt: skip
    if rents and later != "running" and _SPENT[cfg] >= estimate:
        _notify(cfg, estimate)
        return specialized()
    # (At most 32 lanes on the compact program: a lane group's histories, which its
    # Cauchy sums read at every order, then stay in the core's L2 cache, and its
    # gathers are vector loops where LLVM does not unroll them (`_compat.
    # whole_loop_environment`); a release's result does not depend on the lanes.)
    lanes = min(cfg.width, _COMPACT_LANES)
    compact_cfg = dataclasses.replace(
        cfg, L=None, force=None, compact=True, width=lanes
    )
    cpu, devices = origin[1:]
    static = (compact_cfg, shape, cpu, len(devices), tape.size)
    start = time.perf_counter()
    out = executables.call(
        _compact_program(compact_cfg, shape, cpu, devices),
        static,
        _OUT_TREE,
        *args[:-1],
        tape,
    )
    jax.block_until_ready(out)
    _SPENT[cfg] += time.perf_counter() - start
    return out


def _compact_mode() -> str:
    """`LAGRAX_COMPACT`: "1" or unset (the tiers above), "0" (the specialized
    program only), "2" (the compact one wherever it applies: benchmarks, tests)."""
    flag = os.environ.get("LAGRAX_COMPACT", "1").strip() or "1"
    if flag not in ("0", "1", "2"):
        raise ValueError(
            f"The environment variable LAGRAX_COMPACT must be 0, 1 or 2; got {flag!r}."
        )
    return flag


def _compact_applies() -> bool:
    """Whether the compact tier may be taken: on a CPU (executables are kept on
    disk for one process's CPU devices), unless `LAGRAX_COMPACT=0`."""
    return _compact_mode() != "0" and executables.applies()


def _known(jitted, options, origin, args) -> bool:
    """Whether the specialized program is compiled in this process or on disk
    (found by its pre-key, without tracing)."""
    return executables.available(jitted, options, *args, n_static=2, origin=origin)


def _kept(store, key, make, most=_MAX_TAPES):
    """`make()`, kept in `store` (an `OrderedDict`) under `key`, the least recently
    used dropped past `most`; made afresh where `key` is None (values that do not
    hash)."""
    if key is None:
        return make()
    if key in store:
        store.move_to_end(key)
        return store[key]
    value = store[key] = make()
    if len(store) > most:
        store.popitem(last=False)
    return value


def _key(*parts):
    """`parts` as a dictionary key, or None where they do not hash."""
    try:
        hash(parts)
    except TypeError:
        return None
    return parts


def _tape(L_c, consts, force, n, dtype):
    """`(tape, nodes)`: the compact tape of the system's equations (the constants'
    values as its own) and the number of nodes of its program, or None where it
    has none (a primitive without a compact opcode, a program not evaluated entry
    by entry)."""
    try:
        values = tuple((np.shape(c), np.asarray(c).tobytes()) for c in consts)
        key = _key(L_c, force, n, np.dtype(dtype).name, values)
    except TypeError:
        key = None

    def make():
        try:
            # (NumPy values: `jnp` would compile a small program for each on a
            # process's first call.)
            zeros = np.zeros((n,), dtype)
            system = _system(L_c, [as_array(c) for c in consts], force, zeros, zeros)
            if not system.scalar:
                raise NotImplementedError("not scalarized")
            prog = system.prog
            tape = compact.build(
                prog, prog.inputs, prog.params, prog.outs, dtype, size=_SIZE_CLASS
            )
            return tape, len(prog.nodes)
        except (NotImplementedError, TypeError, ValueError):
            return None

    return _kept(_TAPES, key, make)


def _step_nodes(L_c, consts, force, n, dtype) -> int:
    """The number of nodes of the specialized step's program, whose constants are
    arguments (traced: a constant's operations are nodes, where the tape's NumPy
    values fold), kept per Lagrangian and the constants' shapes (not values); 0
    where it cannot be traced here (the specialized program then decides)."""
    consts = [as_array(c) for c in consts]
    shapes = tuple((c.shape, c.dtype.name) for c in consts)
    key = _key(L_c, force, n, np.dtype(dtype).name, shapes)
    zeros = np.zeros((n,), dtype)

    def make():
        counted = []

        def count(*consts):
            system = _system(L_c, list(consts), force, zeros, zeros)
            counted.append(len(system.prog.nodes))
            return zeros

        try:
            jax.make_jaxpr(count)(*consts)
        except (NotImplementedError, TypeError, ValueError):
            return 0
        return counted[0]

    return _kept(_STEP_NODES, key, make)


# The compact program's lane width (`_tiered`): chain4, 256 releases, 1e-12, 128 /
# 64 / 32 / 16 lanes: 0.58 / 0.45 / 0.38 / 0.37 s (benchmarks/README.md).
_COMPACT_LANES = 32
# Every compact program holds these families at order 0 (so that most Lagrangians
# of a size share it) and these smallest sizes.
_SIZE_CLASS = dict(families=(compact.AFFINE, compact.RARE, compact.LOGIC,
                             compact.SINCOS), S=256, NB=32, L0=16)  # fmt: skip


def _compile_estimate(nodes, order) -> float:
    """Seconds the specialized program takes to trace and compile, from the nodes of
    the tape's program and the order: XLA's compile grows faster than the program
    (fitted to the double pendulum at order 14 and chains of 4 and 6 pendulums at
    order 16, one core)."""
    return 20.0 * (nodes / 244.0) ** 1.9 * (order / 16.0) ** 1.5


def _notify(cfg, estimate):
    """One line, once per configuration, where the specialized compile is long."""
    if cfg in _NOTIFIED or estimate < 10.0:
        return
    _NOTIFIED.add(cfg)
    warnings.warn(
        "lagrax.simulate_batch: compiling the Taylor program specialized to this "
        f"Lagrangian (order {cfg.order}), about {estimate:.0f} s once; later calls, "
        "also in later processes, reuse it.",
        stacklevel=4,
    )


def _assemble(B, n, has_ts, save_t1, ys, tend, code, nsteps, rejected, ts_arr):
    """The loop's outputs as a `Solution`'s arrays, and the number of releases that
    failed."""
    ys, tend, code = ys[:B], tend[:B], code[:B]
    nsteps, rejected = nsteps[:B], rejected[:B]
    times = []
    if has_ts:
        times.append(jnp.broadcast_to(ts_arr, (B, ts_arr.shape[0])))
    if save_t1:
        times.append(tend[:, None])
    R = dfx.RESULTS
    # Per release, by the enumeration's public (scalar) `where`, mapped over lanes.
    outcome = lambda c: R.where(
        c == _DONE,
        R.successful,
        R.where(c == _MAX_STEPS, R.max_steps_reached, R.nonfinite),
    )
    ok = (code == _DONE)[:, None, None]
    qs = jnp.where(ok, ys[..., :n], jnp.nan)
    vs = jnp.where(ok, ys[..., n:], jnp.nan)
    (result,) = jax.tree.leaves(jax.vmap(outcome)(code))
    return (
        jnp.concatenate(times, axis=1),
        qs,
        vs,
        result,
        nsteps,
        nsteps - rejected,  # (here, not op by op: a compile on a first call)
        rejected,
        jnp.sum(code != _DONE),
    )


def _positive(x, name, dtype):
    if jnp.ndim(x) == 0:
        return positive_scalar(x, name, dtype)
    return as_real_array(x, name).astype(dtype)


def _per_release(x, name, B, dtype):
    if is_concrete(x) and np.ndim(x) == 0:  # (NumPy: no op-by-op compile)
        return jax.device_put(np.full((B,), np.asarray(x), dtype))
    x = jnp.asarray(x, dtype)
    if x.ndim == 0:
        return jnp.broadcast_to(x, (B,))
    if x.shape != (B,):
        raise ValueError(
            f"`{name}` must be a scalar or of shape ({B},); got {x.shape}."
        )
    return x


def _vmapped(
    L, force, solver, saveat, max_steps, kwargs, q0, qdot0, t0, t1, rtol, atol
):
    """`jax.vmap` of `simulate` over the releases (a solver other than `Taylor`)."""

    def one(q, v, a, b, r, s):
        return simulate(
            L, q, v, a, b, force=force, solver=solver, saveat=saveat, rtol=r,
            atol=s, max_steps=max_steps, throw=False, **kwargs,
        )  # fmt: skip

    return jax.vmap(one)(q0, qdot0, t0, t1, rtol, atol)


def _raise_if_failed(sol, throw):
    if not throw:
        return sol
    failed = (sol.result != dfx.RESULTS.successful) & (
        sol.result != dfx.RESULTS.event_occurred
    )
    if is_concrete(failed):
        _raise_if_count(int(jnp.sum(failed)), failed.shape[0])
        return sol
    return sol.result.error_if(sol, failed)


def _raise_if_count(count, B):
    if count:
        raise RuntimeError(
            f"lagrax.simulate_batch: {count} of {B} releases failed (see "
            "`Solution.result` with throw=False)."
        )
