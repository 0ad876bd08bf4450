"""Periods with their statuses and error estimates, on one device and over many."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P
from jaxtyping import Array, Float, Int

from .._results import SUCCESS, TOLERANCE_NOT_MET
from .estimate import PROMISE, second_solve_estimate, TIGHTER
from .finish import blame_coordinates
from .methods import Reference, run_method


class Periods(eqx.Module):
    """Per lane: period (NaN unless the status is success), status, steps, error
    estimate (NaN without one); and the lane-steps executed."""

    periods: Float[Array, " n"]
    status: Int[Array, " n"]
    steps: Int[Array, " n"]
    executed: Int[Array, ""]
    estimate: Float[Array, " n"]


def periods(L, m, devices, q0, consts, rtol, atol, t_max, energy_tol) -> Periods:
    """`device_periods` on every device, each over its share of the lanes (device d
    takes lanes d, d + D, ...: neighbouring amplitudes cost about the same, so
    interleaving balances the devices), gathered once at the end, in input order and
    replicated on every device (and process).

    The whole method runs per device, not pass by pass: each device goes through its
    passes at its own pace and the devices meet once. Sharding each pass instead (a
    gather after every pass, the second round's lanes compacted across devices)
    holds the devices in step several times a sweep, and between processes every
    gather is a round trip of the collectives."""
    D = len(devices)
    if D == 1:
        return device_periods(L, m, q0, consts, rtol, atol, t_max, energy_tol)
    n = q0.shape[0]
    per = -(-n // D)
    if per * D > n:  # padded lanes repeat the last one; they are dropped below
        q0 = jnp.concatenate([q0, jnp.broadcast_to(q0[-1], (per * D - n,))])

    def local(q0, consts, rtol, atol, t_max, energy_tol):
        out = device_periods(L, m, q0[0], consts, rtol, atol, t_max, energy_tol)
        lanes = (out.periods, out.status, out.steps, out.estimate)
        lanes = tuple(jax.lax.all_gather(x, "lanes") for x in lanes)
        return lanes, jax.lax.psum(out.executed, "lanes")

    (T, status, steps, est), executed = jax.shard_map(
        local,
        mesh=Mesh(np.array(devices), ("lanes",)),
        in_specs=(P("lanes"), P(), P(), P(), P(), P()),
        out_specs=P(),
        check_vma=False,
    )(q0.reshape(per, D).T, consts, rtol, atol, t_max, energy_tol)
    back = lambda x: x.T.reshape(-1)[:n]
    return Periods(back(T), back(status), back(steps), executed, back(est))


def device_periods(L, m, q0, consts, rtol, atol, t_max, energy_tol) -> Periods:
    """Periods, statuses, steps and error estimates of the lanes of one device. With
    `m.screened` the estimate is the first-order bound, and a second solve only of
    the lanes it cannot vouch for (`run_method`); otherwise the estimate's solves
    run in the same queue as the first (after the requested lanes: at tighter
    tolerances, and from the far turning point moved across its band): one
    compiled kernel, balanced work."""
    n = q0.shape[0]
    full = lambda x, k: jnp.full((n,), k * x, q0.dtype)

    def solve(q0, rtols, atols, screened=False, second=None):
        args = (consts, rtols, atols, t_max, energy_tol, screened, second)
        return run_method(L, m, q0, *args)

    if m.screened:
        out = solve(q0, full(rtol, 1.0), full(atol, 1.0), True)
        T, status, steps, q_far = out.periods, out.status, out.steps, out.q_far
        # The bound where it vouches for a lane; the second solve's estimate where not.
        T2, status2 = out.periods2, out.status2
        est2 = second_solve_estimate(T, status, T2, status2, rtol, m.stepper)
        est = jnp.where(out.redo, est2, out.bound)
    elif m.estimate:
        # The requested solve, the second at tighter tolerances and, for the methods
        # with a far turning point, a third from it moved across its rounding band:
        # the band's share of the error is then a term of its own, not one that may
        # cancel the truncation's in the second solve. The third continues the first
        # leg of the lane whose period it is compared with ("matched": the requested
        # solve; "half", "full": their reference), running only its second leg.
        band = m.method in ("matched", "half", "full")
        k = 3 if band else 2
        tight = full(TIGHTER, 1.0)
        base = full(1.0, 1.0) if m.method == "matched" else tight
        scale = jnp.concatenate([full(1.0, 1.0), tight, base][:k])
        lanes = jnp.tile(q0, k)
        i = jnp.arange(n)
        src = i if m.method == "matched" else n + i
        second = None
        if band:
            second = Reference(
                ref=jnp.arange(k * n) >= n,
                shift=jnp.concatenate([full(0.0, 1.0), full(0.0, 1.0), full(1.0, 1.0)]),
                source=jnp.concatenate([i, n + i, src]),
            )
        out = solve(lanes, scale * rtol, scale * atol, second=second)
        T, T2 = out.periods[:n], out.periods[n : 2 * n]
        status, status2 = out.status[:n], out.status[n : 2 * n]
        steps = jnp.sum(out.steps.reshape(k, n), axis=0)
        q_far = out.q_far[:n]
        shifted = None
        if band:
            T3, status3 = out.periods[2 * n :], out.status[2 * n :]
            shifted = (T3, status3, out.periods[src], out.status[src])
        est = second_solve_estimate(T, status, T2, status2, rtol, m.stepper, shifted)
    else:
        out = solve(q0, full(rtol, 1.0), full(atol, 1.0))
        status = blame_coordinates(L, consts, q0, out.q_far, out.status)
        T = jnp.where(status == SUCCESS, out.periods, jnp.nan)
        return Periods(T, status, out.steps, out.executed, jnp.full_like(T, jnp.nan))
    est = jax.lax.stop_gradient(jnp.where(status == SUCCESS, est, jnp.nan))
    unmet = (status == SUCCESS) & ~(est <= PROMISE * rtol)
    status = jnp.where(unmet, TOLERANCE_NOT_MET, status)
    status = blame_coordinates(L, consts, q0, q_far, status)
    T = jnp.where(status == SUCCESS, T, jnp.nan)
    return Periods(T, status, steps, out.executed, est)
