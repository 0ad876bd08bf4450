r"""`sweep_periods`: the period methods ("matched", "half", "full", "quarter") over
the batch kernel (`kernel.py`: one compiled loop per device, its step, its queue
and event location), the far turning point, the error estimate, sharding over
devices, and autodiff.

The error estimate of a Taylor "matched" sweep is a first-order bound summed in the
same loop (`_screen`): per step, the error bound of the step (its truncation, from
the last coefficients, and the rounding of the state) as a time shift along the orbit
and an energy error, which moves the end of the leg by its leverage
$\int ds/\dot q^2$ over the rest of it (Gauss–Legendre on the step's velocity
polynomial); and the far turning point's band times $d\tau/dE$, the finite part of
that integral from rest. Lanes it cannot vouch for are solved again at looser
tolerances in two more passes of the same loop, compacted to the front of the queue
(the others are never loaded). Measured (pendulum, 4096 amplitudes, rtol 1e-13, one
core): the bound is 13-52x above the true error floored at 1e-14 on every lane, no
lane needs the second solve, and a default sweep runs ~1.6x faster than with the
second solve for every lane.

Forward-mode autodiff goes through the loop (`jax.jvp`, `jax.jacfwd`); `jax.grad`
works through a `custom_jvp` whose tangents come from that forward mode: the periods
are independent per lane, so their derivative with respect to the release points is
diagonal (one forward pass), and their derivative with respect to parameters that `L`
closes over takes one forward pass per parameter, for the inputs being differentiated
only (the `custom_jvp` sees the others' tangents as symbolic zeros: dT/dq0 of a
Lagrangian with 17 scalar parameters, 4096 amplitudes, one core: 6.7 s -> 0.42 s
a call).
"""

import functools
from collections.abc import Callable
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P
from jaxtyping import Array, Float, Int

from .._checks import as_real_array, check_callable, check_devices, positive_int
from .._eom.mechanics import _accelerations
from .._jaxpr.fusion import one_fusion
from .._jaxpr.trig import vectorized_trig
from .._results import (
    COORDINATE_SINGULARITY,
    ENERGY_DRIFT,
    NONFINITE_INPUT,
    NOT_OSCILLATING,
    NOT_SYMMETRIC,
    ROOT_FIND_FAILED,
    SINGULAR_MASS,
    SOLVER_FAILED,
    status_message,
    SUCCESS,
    TOLERANCE_NOT_MET,
)
from .._taylor.coefficients import Taylor
from .kernel import (
    _Pass,
    _pass,
    _Tableau,
    MAX_SPEED,
    POSITION,
    resolve_solver,
    stepper,
    TURNING,
)
from .period import _check_options


# Safeguarded Newton for the far turning point converges in ~5 iterations from the
# bracket; the loop stops when every lane has converged.
_MAX_NEWTON = 60
_MAX_EXPAND = 40


def _at_rest(L, consts, dtype):
    """q -> L(q, 0, 0) for a scalar q, with sines and cosines XLA vectorizes
    (`_trig.sincos`; each a libm call per lane otherwise): for the turning-point
    searches and tests, which evaluate it many times per lane."""
    z1, z = jnp.zeros((1,), dtype), jnp.zeros((), dtype)
    return vectorized_trig(lambda q: L(jnp.reshape(q, (1,)), z1, z, *consts))


@eqx.filter_jit
def _far_turning_point(L, consts, q0, q_m, with_band=True):
    r"""The turning point beyond $q_m$ on the energy level of a release at rest at
    $q_0$: the root of $F(q) = L(q, 0) - L(q_0, 0)$ (for $L$ even in $\dot q$ and
    without explicit time, the energy at rest is $-L(q, 0)$), $F > 0$ between the
    turning points. Bracketed from the mirror image of $q_0$ outward by growing
    Newton steps, then safeguarded Newton. Returns `(q1, found, band, in_range)`,
    `band` the rounding band of $q_1$ (zeros without `with_band`: only the error
    estimate reads it), `in_range` False where L at $q_0$ was not finite with the
    vectorized sines (an argument beyond their range, see `_trig`)."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    # ~20 values of L and its slope per lane (0.65 -> 0.13 ms per 4096 pendulum
    # lanes with the vectorized sines, measured). Beyond their range (|argument| >
    # 8.2e5) they are NaN: `in_range` says where L at the release point was finite.
    Lr = _at_rest(L, consts, dtype)
    Lr_v = jax.vmap(Lr)
    dF = jax.vmap(jax.grad(Lr))
    # Each value of L is computed once and carried (for the pendulum each is a libm
    # call per lane, ~8 ns: recomputed for F, its rounding and each loop's test,
    # they were most of this function's 0.74 ms per 4096 lanes, measured).
    E0 = Lr_v(q0)
    # F = L(q) - L(q0) is known only to the rounding of the two values of L: inside
    # that band every point is the turning point as far as float64 can tell.
    noise = lambda Lq: 4 * eps * (jnp.abs(Lq) + jnp.abs(E0))
    d = q_m - q0
    out = jnp.sign(d)  # away from the release point
    a, b = q_m, q_m + d  # the mirror image of q0: the root itself if the well is
    La, Lb = Lr_v(a), Lr_v(b)  # mirror-symmetric, up to rounding
    Fa, Fb = La - E0, Lb - E0

    def expand(c):
        # Still inside the well at b: step outward by a Newton step times 1, 2, 4, …
        # (for a convex F Newton undershoots), never less than a few ulps, and by
        # |d| times the same factor where F does not fall outward (a shoulder).
        a, b, Fa, Fb, Lb, k = c
        more = Fb > noise(Lb)
        slope = -out * dF(b)
        newton = Fb / jnp.where(slope > 0, slope, 1.0)
        step = jnp.where(slope > 0, newton, jnp.abs(d)) * 2.0**k
        step = jnp.maximum(step, 4 * eps * jnp.maximum(jnp.abs(b), jnp.abs(d)))
        b2 = jnp.where(more, b + out * step, b)
        L2 = Lr_v(b2)
        new = dict(
            a=jnp.where(more, b, a),
            b=b2,
            Fa=jnp.where(more, Fb, Fa),
            Fb=jnp.where(more, L2 - E0, Fb),
            Lb=jnp.where(more, L2, Lb),
        )
        # (Each loop's new values from one fusion, as in the sweep's loop: 8 -> 3
        # and 6 -> 2 kernels; the default sweep's backend compile 3.26-3.51 ->
        # 3.20-3.34 s, three alternated pairs, one core.)
        new = one_fusion(new)
        return (*new.values(), k + 1)

    a, b, Fa, Fb, Lb, _ = jax.lax.while_loop(
        lambda c: jnp.any(c[3] > noise(c[4])) & (c[5] < _MAX_EXPAND),
        expand,
        (a, b, Fa, Fb, Lb, 0),
    )
    at_b = jnp.abs(Fb) <= noise(Lb)  # e.g. the mirror image, in a symmetric well
    found = ((Fb <= 0) | at_b) & (Fa > 0) & jnp.isfinite(a) & jnp.isfinite(b)
    secant = a + (b - a) * Fa / jnp.where(Fa != Fb, Fa - Fb, 1.0)
    x = jnp.where(found, jnp.where(at_b, b, secant), q0)

    def newton(c):
        a, b, x, done, k = c
        Lx = Lr_v(x)
        fx = Lx - E0
        done = done | (jnp.abs(fx) <= noise(Lx))
        a, b = jnp.where(fx > 0, x, a), jnp.where(fx > 0, b, x)
        x_new = x - fx / dF(x)
        ok = jnp.isfinite(x_new) & ((x_new - a) * (x_new - b) < 0)
        x_new = jnp.where(ok, x_new, 0.5 * (a + b))
        done = done | (jnp.abs(x_new - x) <= 2 * eps * jnp.abs(x))
        new = dict(a=a, b=b, x=jnp.where(done, x, x_new), done=done)
        new = one_fusion(new)
        return (*new.values(), k + 1)

    _, _, x, _, _ = jax.lax.while_loop(
        lambda c: jnp.any(found & ~c[3]) & (c[4] < _MAX_NEWTON),
        newton,
        (a, b, x, ~found | at_b, 0),
    )
    # The tangent of the root by the implicit function theorem (zero primal).
    # (At the root F = 0: the slope's own tangent multiplies F and is dropped.)
    slope = jax.lax.stop_gradient(dF(x))
    Lx = Lr_v(x)
    f0 = Lx - E0
    corr = -f0 / slope
    corr = jnp.where(found & jnp.isfinite(corr), corr, 0.0)
    root = x + (corr - jax.lax.stop_gradient(corr))
    in_range = jnp.isfinite(E0)
    if not with_band:
        return root, found, jnp.zeros_like(x), in_range
    # How far the root is undetermined: the rounding scatter of F near the root,
    # measured (the user's L may round by many ulps, or by half of one), over its
    # slope. Nine values of F spaced 64 ulps apart (the middle one is f0), against
    # the tangent line.
    h = 64 * eps * jnp.maximum(jnp.abs(x), eps)
    scatter = jnp.zeros_like(x)
    for j in (-4, -3, -2, -1, 1, 2, 3, 4):
        fj = Lr_v(x + j * h) - E0
        scatter = jnp.maximum(scatter, jnp.abs(fj - f0 - slope * j * h))
    half_ulp = 0.5 * eps * jnp.maximum(jnp.abs(Lx), jnp.abs(E0))
    band = (scatter + half_ulp) / jnp.abs(slope)
    return root, found, band, in_range


class _Method(eqx.Module):
    """A period method as passes of the kernel."""

    tab: "_Tableau | Taylor"
    method: str = eqx.field(static=True)
    width: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    estimate: bool = eqx.field(static=True)

    @property
    def pass_(self):
        legs = 2 if self.method == "full" else 1
        return _Pass(self.tab, legs, self.width, self.max_steps, self.screened)

    @property
    def screened(self):
        """Whether the error estimate is the first-order bound where it vouches."""
        taylor = isinstance(self.tab, Taylor)
        return self.estimate and self.method == "matched" and taylor


def _run_method(
    L, m, q0, consts, rtols, atols, t_max, energy_tol, shift, screened=False
):
    """One solve of every lane by `m.method` (per-lane tolerances): periods (NaN on
    failure), statuses, steps, executed lane-steps, and the far side of each swing.
    `shift`: for "matched", how many rounding bands to move each far turning point.

    `screened` ("matched" with a Taylor step and the error estimate): the first-order
    error bound of each lane (`_screen`), and a second solve, at `_LOOSER` times the
    tolerances from the far turning point moved across its band, of only the lanes
    that bound cannot vouch for, in the same loop. Then returns also the bound, which
    lanes were solved again, their second periods and statuses."""
    n = q0.shape[0]
    zeros = jnp.zeros_like(q0)
    live = jnp.ones(q0.shape, bool)
    kinds = lambda kind: jnp.full(q0.shape, kind, jnp.int32)
    run = lambda q0, targets, kind, rtols, atols, live: _pass(
        L,
        m.pass_,
        (
            q0,
            targets,
            kinds(kind) if isinstance(kind, int) else kind,
            rtols,
            atols,
            live,
        ),
        consts,
        t_max,
        energy_tol,
    )
    if m.method != "matched":
        kind, factor = {
            "half": (TURNING, 2.0),
            "quarter": (MAX_SPEED, 4.0),
            "full": (TURNING, 1.0),
        }[m.method]
        res, executed = run(q0, zeros, kind, rtols, atols, live)
        status, t_e, q_e, qd_e, steps = res[:5]
        # The far side of the swing, for `_blame_coordinates`: where the solve
        # stopped, or past the point of maximum speed by as much again.
        q_far = 2 * q_e - q0 if kind == MAX_SPEED else q_e
        if kind == MAX_SPEED:
            # T = 4 t(q0 -> q_m) holds for a well mirror-symmetric about q_m: the
            # mirror image of q0 must be a turning point (to rtol across the swing).
            symmetric = _is_turning_point(
                L, consts, q0, q_far, rtols * jnp.abs(q_e - q0)
            ) & _mirror_symmetric(L, consts, q0, q_e, qd_e, rtols)
            status = jnp.where((status == SUCCESS) & ~symmetric, NOT_SYMMETRIC, status)
        T = jnp.where(status == SUCCESS, factor * t_e, jnp.nan)
        return T, status, steps, executed, q_far

    # Two quarter legs, each from rest at its own turning point, meeting at the
    # point of maximum speed: nothing is integrated through the bottom of the swing.
    # Both legs run through ONE instance of the kernel: a while loop over the
    # passes whose body is the pass (its trip count is not a constant XLA can see,
    # so it is not unrolled; a `lax.scan` of two was, and gained nothing). Two calls
    # of `_pass` put two copies of the kernel in the program: XLA compiled their
    # identical fusions once, but everything else twice, and the forward-mode
    # derivative's tangent kernels twice. Measured, one core, Taylor: first call of
    # a default sweep 3.34-3.43 -> 3.17-3.22 s (HLO 11.6k -> 7.5k lines); first
    # `jax.jit(jax.grad(...))` of a 64-amplitude default sweep 13.7-13.9 -> 10.0-10.3 s.
    # With `screened`, the second solve's two legs are passes 2 and 3 of the same loop.
    def after_a(res, lanes, shift):
        st_a, t_a, q_m, qd_a = res[0][:4]
        q0 = lanes[0]
        # Any point of leg A serves as the meeting point: leg B ends at its
        # position. Where the point of maximum speed cannot be located (a well
        # whose curvature vanishes at its bottom, q̈ = -q³: q̈ has a triple zero in
        # time there and no Newton or secant converges), the last accepted state
        # before it is used; the two legs' speeds must still agree there (`match`,
        # below).
        meet = (st_a == ROOT_FIND_FAILED) & jnp.isfinite(q_m) & jnp.isfinite(t_a)
        st_a = jnp.where(meet & (qd_a != 0), SUCCESS, st_a)  # (moving: not the release)
        q1, found, band, in_range = _far_turning_point(L, consts, q0, q_m, m.estimate)
        # (L beyond the vectorized sines' range: the solver's failure, not the well's.)
        st_a = jnp.where((st_a == SUCCESS) & ~in_range, SOLVER_FAILED, st_a)
        # (Only where shifted: a band that rounding leaves undefined, NaN next to a
        # singular point, must not turn the requested solve's start into NaN,
        # reported as a non-finite release point.)
        q1 = q1 + jnp.where(shift != 0, shift * band, 0.0)
        go = found & (st_a == SUCCESS)
        lanes_b = (jnp.where(go, q1, jnp.nan), q_m, kinds(POSITION), *lanes[3:])
        return lanes_b, (q0, st_a, q1, found, go, band)

    def combine(res_a, res_b, aux, rtols):
        (_, t_a, q_m, qd_a, steps_a), terms_a = res_a[0][:5], res_a[0][5:]
        (st_b, t_b, _, qd_b, steps_b), terms_b = res_b[0][:5], res_b[0][5:]
        q0, st_a, q1, found, go, band = aux
        tol = jnp.sqrt(rtols) if energy_tol is None else energy_tol
        match = jnp.abs(jnp.abs(qd_a) - jnp.abs(qd_b)) <= tol * jnp.abs(qd_a)
        status = jnp.select(
            [st_a != SUCCESS, ~found, st_b != SUCCESS, ~match],
            [
                st_a,
                jnp.full_like(st_a, NOT_OSCILLATING),
                st_b,
                jnp.full_like(st_a, ENERGY_DRIFT),
            ],
            st_a,
        )
        q_far = jnp.where(found, q1, 2 * q_m - q0)
        T = jnp.where(status == SUCCESS, 2 * (t_a + t_b), jnp.nan)
        steps = steps_a + jnp.where(go, steps_b, 0)
        bound = _screen(T, t_a, t_b, terms_a, terms_b, band, rtols)
        return T, status, steps, res_a[1] + res_b[1], q_far, bound

    lanes0 = (q0, zeros, kinds(MAX_SPEED), rtols, atols, live)
    # (The same argument types as in the loop: the traced pass is reused there.)
    res_shape = jax.eval_shape(lambda: run(*lanes0))
    blank = lambda tree: jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), tree)
    aux_shape = jax.eval_shape(lambda r: after_a(r, lanes0, shift)[1], res_shape)
    rounds = 2 if screened else 1

    def next_round(T, status, bound):
        """After round 0: the lanes its bound cannot vouch for, first (`perm`), at
        looser tolerances; the others are not loaded."""
        redo = (status == SUCCESS) & ~(bound <= PROMISE * rtols)
        i32 = lambda x: x.astype(jnp.int32)
        count = jnp.sum(i32(redo))
        first = jnp.cumsum(i32(redo)) - 1
        rest = count + jnp.cumsum(i32(~redo)) - 1
        pos = i32(jnp.where(redo, first, rest))  # lane i goes to position pos[i]
        perm = jnp.zeros_like(pos).at[pos].set(jnp.arange(n, dtype=jnp.int32))
        live = jnp.arange(n) < count
        # (Round 1 only estimates: no tangents.)
        sg = jax.lax.stop_gradient
        lanes = (
            jnp.where(live, sg(q0)[perm], jnp.nan),
            zeros,
            kinds(MAX_SPEED),
            _LOOSER * rtols[perm],
            _LOOSER * atols[perm],
            live,
        )
        return lanes, pos, count

    if rounds == 1:

        def body(c):
            k, lanes, res_a, aux, _ = c
            res = run(*lanes)
            leg_a = k % 2 == 0
            lanes, aux = jax.lax.cond(
                leg_a, lambda: after_a(res, lanes, shift), lambda: (lanes, aux)
            )
            res_a = jax.tree.map(lambda x, y: jnp.where(leg_a, x, y), res, res_a)
            return k + 1, lanes, res_a, aux, res

        # (2 on every lane, but not a constant XLA can see through.)
        passes = jnp.where(jnp.all(rtols > -1.0), 2, 1).astype(jnp.int32)
        init = (jnp.zeros((), jnp.int32), lanes0, *blank((res_shape, aux_shape)))
        init = (*init, blank(res_shape))
        _, _, res_a, aux, res_b = jax.lax.while_loop(
            lambda c: c[0] < passes, body, init
        )
        return combine(res_a, res_b, aux, rtols)[:5]

    # Round 1 (passes 2 and 3) starts leg B from the far turning point moved across
    # its band, and runs only where round 0 left lanes to solve again. Each round's
    # results are combined in the loop (one copy of that code in the program), and
    # kept packed: one array per round (fewer fusions to compile).
    def packed(out):
        T, status, steps, executed, q_far, bound = out
        f = lambda x: x.astype(q0.dtype)
        return jnp.stack([T, f(status), f(steps), q_far, bound]), executed

    rounds_shape = jax.eval_shape(
        lambda r, a: packed(combine(r, r, a, rtols)), res_shape, aux_shape
    )
    rounds_shape = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct((2,) + x.shape, x.dtype), rounds_shape
    )

    def body(c):
        k, lanes, res_a, aux, rounds_, pos, passes = c
        res = run(*lanes)
        leg_a = k % 2 == 0

        def after_b():
            out = combine(res_a, res, aux, lanes[3])
            i = (k - 1) // 2
            r = jax.tree.map(lambda all_, x: all_.at[i].set(x), rounds_, packed(out))

            def new_round():
                T, status, _, _, _, bound = out
                lanes_1, pos_1, count = next_round(T, status, bound)
                more = jnp.where(count > 0, passes, 2).astype(passes.dtype)
                return lanes_1, pos_1, more

            lanes_, pos_, more = jax.lax.cond(
                k == 1, new_round, lambda: (lanes, pos, passes)
            )
            return lanes_, aux, r, pos_, more

        shift_k = jnp.where(k >= 2, 1.0, 0.0).astype(q0.dtype)
        lanes, aux, rounds_, pos, passes = jax.lax.cond(
            leg_a,
            lambda: (*after_a(res, lanes, shift_k), rounds_, pos, passes),
            after_b,
        )
        res_a = jax.tree.map(lambda x, y: jnp.where(leg_a, x, y), res, res_a)
        return k + 1, lanes, res_a, aux, rounds_, pos, passes

    # (4 passes, but not a constant XLA can see through.)
    passes = jnp.where(jnp.all(rtols > -1.0), 4, 1).astype(jnp.int32)
    init = (
        jnp.zeros((), jnp.int32),
        lanes0,
        blank(res_shape),
        blank(aux_shape),
        blank(rounds_shape),
        jnp.zeros(q0.shape, jnp.int32),
        passes,
    )
    _, _, _, _, (rounds_, ex), pos, passes = jax.lax.while_loop(
        lambda c: c[0] < c[-1], body, init
    )
    i32 = lambda x: x.astype(jnp.int32)
    T, status, steps, q_far, bound = rounds_[0]
    status, steps = i32(status), i32(steps)
    # (Without round 1, nothing to redo: its outputs are blank.)
    redo = (status == SUCCESS) & ~(bound <= PROMISE * rtols) & (passes > 2)
    T2, status2, steps2 = rounds_[1][:3, pos]
    steps = steps + jnp.where(redo, i32(steps2), 0)
    T, status2 = T, i32(status2)
    executed = ex[0] + jnp.where(passes > 2, ex[1], 0)
    return T, status, steps, executed, q_far, bound, redo, T2, status2


# A failed lane whose mass ∂²L/∂q̇² falls below this fraction of its largest value
# between the release point and the far side of the swing failed because of the
# coordinates (Huygens' cycloid in θ near its cusp: the mass is 2mR²(1 - cos θ)).
_VANISHING_MASS = 1e-6
_MASS_SAMPLES = 33


@eqx.filter_jit
def _blame_coordinates(L, consts, q0, q_far, status):
    """`coordinate_singularity` for failed lanes whose mass vanishes on the swing."""
    dtype = q0.dtype
    z1, z = jnp.zeros((1,), dtype), jnp.zeros((), dtype)
    Lp = lambda q, qd, t: L(q, qd, t, *consts)

    def mass(q):
        _, (M, _) = _accelerations(Lp, jnp.reshape(q, (1,)), z1, z, fuse=False)
        return jnp.abs(M[0, 0])

    def vanishes(q0, q_far):
        w = jnp.linspace(0.0, 1.0, _MASS_SAMPLES, dtype=dtype)
        ms = jax.vmap(mass)(q0 + w * (q_far - q0))
        ms = jnp.where(jnp.isfinite(ms), ms, 0.0)
        return jnp.min(ms) <= _VANISHING_MASS * jnp.max(ms)

    # A mass singular at the release point already has its own status.
    failed = (
        (status != SUCCESS) & (status != SINGULAR_MASS) & (status != NONFINITE_INPUT)
    )
    failed = failed & jnp.isfinite(q0) & jnp.isfinite(q_far)
    # Only failed lanes need it: under vmap the check costs 33 mass evaluations for
    # every lane, so it is skipped (lax.cond) when no lane failed.
    blame = jax.lax.cond(
        jnp.any(failed),
        lambda: jax.vmap(vanishes)(q0, jnp.where(failed, q_far, q0)) & failed,
        lambda: jnp.zeros_like(failed),
    )
    return jnp.where(blame, COORDINATE_SINGULARITY, status)


# The error estimate: a second solve at `_LOOSER` times the tolerances (for
# "matched", from the far turning point moved across its rounding band), and
# `_SAFETY` times the difference. Calibrated on exact periods (tests/test_estimate.py).
_LOOSER = 10.0
_SAFETY = 3.0
#: A lane's period is trusted when its estimate is below this many times rtol.
PROMISE = 100.0
# The first-order bound (`_screen`): its safety factor, and the largest leverage
# ∫ds/v² (lane units) of a leg past its first step for which it is used: beyond,
# rounding of the force, which it does not model, may be amplified (near a hump).
_SCREEN_SAFETY = 3.0
_SCREEN_LEVERAGE = 100.0


def _screen(T, t_a, t_b, terms_a, terms_b, band, rtols):
    r"""A first-order bound on the relative error of "matched"'s period from its
    own solve (Taylor steps), without a second solve.

    Each step's error (its truncation bound, the rounding of the state) moves the
    leg's end in two ways: along the orbit, a time shift $\delta q/|\dot q|$; across
    it, an energy error $\delta E$, which changes the time left to the end of the
    leg by $\partial\tau/\partial E|_q = -\int \mathrm dt/(M\dot q^2)$ over the rest of
    the leg (the second solution of the variational equation by reduction of order:
    the flow $(\dot q, \ddot q)$ is the first, the Wronskian is $\propto 1/M$). The
    kernel sums both per leg (`ph`, `J`). Leg B starts at a far turning point known
    to within `band`: its energy, and the leg's time by $d\tau/dE$, the Hadamard
    finite part of $\int_0 \mathrm dt/(M\dot q^2)$ from rest (`F`; zero for a
    harmonic well: isochronous). Bounded by absolute values; a constant mass is
    assumed (infinite `G` otherwise, from `_finish`), and a leg whose leverage `G`
    exceeds `_SCREEN_LEVERAGE` is not bounded here (infinite)."""
    eps = jnp.finfo(T.dtype).eps
    T, t_a, t_b, band = jax.lax.stop_gradient((T, t_a, t_b, band))
    ph_a, J_a, _, G_a = terms_a
    ph_b, J_b, F_b, G_b = terms_b
    err = 2 * (ph_a + J_a + ph_b + J_b + band * jnp.abs(F_b)) + 16 * eps * (t_a + t_b)
    bound = _SCREEN_SAFETY * err / jnp.abs(T) + 64 * eps
    usable = (G_a <= _SCREEN_LEVERAGE) & (G_b <= _SCREEN_LEVERAGE)
    usable = usable & jnp.isfinite(bound) & jnp.isfinite(band)
    return jnp.where(usable, bound, jnp.inf)


def _second_solve_estimate(T, status, T2, status2):
    """The estimate from a second solve at looser tolerances: `_SAFETY` times the
    relative difference plus 64 ulps; infinite where the looser solve failed and
    the requested one did not (that says nothing sure)."""
    eps = jnp.finfo(T.dtype).eps
    est = _SAFETY * jnp.abs(T2 - T) / jnp.abs(T) + 64 * eps
    return jnp.where((status == SUCCESS) & (status2 != SUCCESS), jnp.inf, est)


def _periods(L, m, devices, q0, consts, rtol, atol, t_max, energy_tol):
    """`_device_periods` on every device, each over its share of the lanes (device d
    takes lanes d, d + D, ...: neighbouring amplitudes cost about the same, so
    interleaving balances the devices), gathered once at the end, in input order and
    replicated on every device (and process).

    The whole method runs per device, not pass by pass: each device goes through its
    passes at its own pace and the devices meet once. Sharding each pass instead (a
    gather after every pass and the second round's lanes compacted across devices)
    held two devices in step two to four times a sweep: one process with two CPU
    devices ran no faster than with one (measured, default sweep), and between
    processes every gather was a round trip of the collectives."""
    D = len(devices)
    if D == 1:
        return _device_periods(L, m, q0, consts, rtol, atol, t_max, energy_tol)
    n = q0.shape[0]
    per = -(-n // D)
    if per * D > n:  # padded lanes repeat the last one; they are dropped below
        q0 = jnp.concatenate([q0, jnp.broadcast_to(q0[-1], (per * D - n,))])

    def local(q0, consts, rtol, atol, t_max, energy_tol):
        out = _device_periods(L, m, q0[0], consts, rtol, atol, t_max, energy_tol)
        T, status, steps, executed, est = out
        lanes = tuple(jax.lax.all_gather(x, "lanes") for x in (T, status, steps, est))
        return lanes, jax.lax.psum(executed, "lanes")

    (T, status, steps, est), executed = jax.shard_map(
        local,
        mesh=Mesh(np.array(devices), ("lanes",)),
        in_specs=(P("lanes"), P(), P(), P(), P(), P()),
        out_specs=P(),
        check_vma=False,
    )(q0.reshape(per, D).T, consts, rtol, atol, t_max, energy_tol)
    back = lambda x: x.T.reshape(-1)[:n]
    return back(T), back(status), back(steps), executed, back(est)


def _device_periods(L, m, q0, consts, rtol, atol, t_max, energy_tol):
    """Periods, statuses, steps, executed lane-steps and error estimates. With
    `m.screened` the estimate is the first-order bound (`_screen`), and a second
    solve only of the lanes it cannot vouch for (`_run_method`); otherwise the
    estimate's second solve runs in the same queue as the first (the second half of
    the lanes, at looser tolerances): one compiled kernel, balanced work."""
    n = q0.shape[0]
    full = lambda x, k: jnp.full((n,), k * x, q0.dtype)
    if m.screened:
        rtols, atols = full(rtol, 1.0), full(atol, 1.0)
        out = _run_method(L, m, q0, consts, rtols, atols, t_max, energy_tol, 0.0, True)
        T, status, steps, executed, q_far, bound, redo, T2, status2 = out
        # The bound where it vouches for a lane; the second solve's estimate where not.
        est = jnp.where(redo, _second_solve_estimate(T, status, T2, status2), bound)
    elif m.estimate:
        lanes = jnp.concatenate([q0, q0])
        rtols = jnp.concatenate([full(rtol, 1.0), full(rtol, _LOOSER)])
        atols = jnp.concatenate([full(atol, 1.0), full(atol, _LOOSER)])
        shift = jnp.concatenate([jnp.zeros(n, q0.dtype), jnp.ones(n, q0.dtype)])
        T, status, steps, executed, q_far = _run_method(
            L, m, lanes, consts, rtols, atols, t_max, energy_tol, shift
        )
        T, T2, status, status2 = T[:n], T[n:], status[:n], status[n:]
        steps, q_far = steps[:n] + steps[n:], q_far[:n]
        est = _second_solve_estimate(T, status, T2, status2)
    else:
        rtols, atols = full(rtol, 1.0), full(atol, 1.0)
        T, status, steps, executed, q_far = _run_method(
            L, m, q0, consts, rtols, atols, t_max, energy_tol, 0.0
        )
        status = _blame_coordinates(L, consts, q0, q_far, status)
        T = jnp.where(status == SUCCESS, T, jnp.nan)
        return T, status, steps, executed, jnp.full_like(T, jnp.nan)
    est = jax.lax.stop_gradient(jnp.where(status == SUCCESS, est, jnp.nan))
    unmet = (status == SUCCESS) & ~(est <= PROMISE * rtol)
    status = jnp.where(unmet, TOLERANCE_NOT_MET, status)
    status = _blame_coordinates(L, consts, q0, q_far, status)
    T = jnp.where(status == SUCCESS, T, jnp.nan)
    return T, status, steps, executed, est


@eqx.filter_jit
def _is_turning_point(L, consts, q0, q, tol):
    """Whether q is, within `tol` in q plus rounding, on the energy level of a release
    at rest at q0: |L(q, 0) - L(q0, 0)| <= rounding + tol |∂L/∂q(q, 0)|."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    # Beyond the vectorized sines' range L is NaN here and the test fails; such a
    # lane has already failed in the loop ("solver failed": its steps use the same
    # sines), and only a success is ever turned into "not symmetric".
    Lr = _at_rest(L, consts, dtype)

    def one(q0, q, tol):
        Lq, dLq = jax.value_and_grad(Lr)(q)
        Lq0 = Lr(q0)
        noise = 4 * eps * (jnp.abs(Lq) + jnp.abs(Lq0))
        return jnp.abs(Lq - Lq0) <= noise + tol * jnp.abs(dLq)

    return jax.vmap(one)(q0, q, tol)


# Where "quarter" tests the mirror symmetry of L across the swing (fractions of
# it, away from simple ratios; the turning point itself is tested on its own), and
# against `PROMISE`, defined below (read at trace time).
_MIRROR_POINTS = (0.2763932, 0.5527864, 0.8291796)


@eqx.filter_jit
def _mirror_symmetric(L, consts, q0, q_m, qd_m, rtols):
    """Whether L is mirror-symmetric about `q_m` across the swing, as
    T = 4 t(q0 -> q_m) assumes: L(q_m + y, w) = L(q_m - y, -w) at three points
    y inside the swing, at rest (the potential) and at the speed |q̇_m| of the
    meeting point (the mass too), to `PROMISE` rtol of the well's depth
    |L(q_m, 0) - L(q0, 0)| plus rounding (the centre q_m is only as exact as the
    integration). Sampled, not proven: a well whose far side differs between these
    points only is not detected; but one whose far turning point merely happens to
    be the mirror image of q0 (an asymmetric well at one amplitude: V = x²/2 +
    x³(x² - 1)/10 released at 1) is, where the turning-point test alone reported
    a success 4% off. A velocity term that is a total derivative, f(q) q̇, breaks
    the literal symmetry and is refused too (`"matched"` handles it). Cost, measured
    (pendulum, 4096 lanes, one core): ~0.25 ms, XLA's cosine being ~8 ns a value;
    a Taylor "quarter" sweep at rtol 1e-14 3.33 -> 3.64-3.70 ms. The eight values of
    L per lane are one array: written out as eight calls, XLA copied L's program into
    each of its readers inside the sweep (32 cosines per lane in the compiled
    program; 8 points now); a "quarter" sweep with the error estimate (8192 lanes
    through this check) 578-618k -> 670-776k periods/s (one core, five alternated
    pairs), the same statuses."""
    dtype = q0.dtype
    eps = jnp.finfo(dtype).eps
    z = jnp.zeros((), dtype)
    Lr = lambda q, w: L(jnp.reshape(q, (1,)), jnp.reshape(w, (1,)), z, *consts)

    def one(q0, q_m, qd_m, rtol):
        # (At the speed of the meeting point: the potential and the mass at once; a
        # coincidence cancelling the two at every point is not sought.)
        y = np.array(_MIRROR_POINTS, dtype) * (q0 - q_m)
        w = jnp.full(y.shape, jnp.abs(qd_m))
        # (The eight values of L as one array: see the docstring.)
        Ls = jax.vmap(Lr)(
            jnp.concatenate([jnp.stack([q_m, q0]), q_m + y, q_m - y]),
            jnp.concatenate([jnp.stack([z, z]), w, -w]),
        )
        depth = jnp.abs(Ls[0] - Ls[1])
        a, b = Ls[2:5], Ls[5:]
        noise = 8 * eps * (jnp.abs(a) + jnp.abs(b))
        return jnp.isfinite(depth) & jnp.all(
            jnp.abs(a - b) <= noise + PROMISE * rtol * depth
        )

    return jax.vmap(one)(q0, q_m, qd_m, rtols)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _periods_diff(L, m, devices, q0, consts, rtol, atol, t_max, energy_tol):
    return _periods(L, m, devices, q0, consts, rtol, atol, t_max, energy_tol)


def _periods_jvp(L, m, devices, primals, tangents):
    q0, consts, rtol, atol, t_max, energy_tol = primals
    dq0, dconsts = tangents[0], tangents[1]
    periods_of = lambda q0, consts: _periods(
        L, m, devices, q0, consts, rtol, atol, t_max, energy_tol
    )
    # Lanes are independent: dT_i/dq0_j is diagonal, one forward pass for all of it;
    # each scalar parameter L closes over takes one more forward pass. Only for the
    # inputs whose tangent is not a symbolic zero (`symbolic_zeros=True`): the
    # derivative with respect to q0 alone of a Lagrangian with many parameters is
    # one forward pass, not one per parameter.
    leaves, treedef = jax.tree.flatten(consts)
    dleaves = treedef.flatten_up_to(dconsts)
    inexact = [jnp.issubdtype(jnp.result_type(x), jnp.inexact) for x in leaves]
    wanted = [ok and not _is_zero(dx) for ok, dx in zip(inexact, dleaves)]
    no_consts = [jnp.zeros_like(x) for x in leaves]
    directions = [] if _is_zero(dq0) else [(jnp.ones_like(q0), no_consts)]
    for i, (x, ok) in enumerate(zip(leaves, wanted)):
        if not ok:
            continue
        for j in range(int(np.size(x))):
            basis = list(no_consts)
            # (A leaf may be a Python scalar with a dtype, `TypedFloat`: no `.shape`.)
            e = jnp.zeros(np.size(x), jnp.result_type(x)).at[j].set(1)
            basis[i] = e.reshape(np.shape(x))
            directions.append((jnp.zeros_like(q0), basis))
    int_tangent = lambda y: np.zeros(np.shape(y), jax.dtypes.float0)
    tangents_of = lambda out, dT: (
        dT,
        int_tangent(out[1]),
        int_tangent(out[2]),
        int_tangent(out[3]),
        jnp.zeros_like(out[4]),
    )
    if not directions:  # (every tangent a symbolic zero)
        out = periods_of(q0, consts)
        return out, tangents_of(out, jnp.zeros_like(out[0]))
    dq_dirs = jnp.stack([d[0] for d in directions])
    dc_dirs = [jnp.stack([d[1][k] for d in directions]) for k in range(len(leaves))]

    def tangent(dq, dc):
        dc = [
            c if ok else np.zeros(np.shape(x), jax.dtypes.float0)
            for c, x, ok in zip(dc, leaves, inexact)
        ]
        out, dout = jax.jvp(periods_of, (q0, consts), (dq, treedef.unflatten(dc)))
        return out, dout[0]

    # The primal outputs come from the same forward pass (unbatched over the
    # directions): one copy of the sweep in the compiled program, not two.
    out, jac = jax.vmap(tangent, out_axes=(None, 0))(dq_dirs, dc_dirs)  # (dirs, n)
    k = 0
    dT = jnp.zeros_like(out[0])
    if not _is_zero(dq0):
        dT, k = jac[0] * dq0, 1
    for x, dx, ok in zip(leaves, dleaves, wanted):
        if not ok:
            continue
        size = int(np.size(x))
        dT = dT + jnp.tensordot(jnp.reshape(dx, (-1,)), jac[k : k + size], axes=1)
        k += size
    return out, tangents_of(out, dT)


_periods_diff.defjvp(_periods_jvp, symbolic_zeros=True)


def _is_zero(t):
    """Whether a tangent is a symbolic zero (the input is not being differentiated)."""
    return t is None or type(t) is jax.custom_derivatives.SymbolicZero


def _sweep_call(L, m, devices, q0, order, consts, rtol, atol, t_max, energy_tol):
    """`_periods_diff` as one compiled call: one dispatch instead of a dozen (measured:
    ~3 ms of Python and dispatch per call, a third of a 4096-amplitude Taylor sweep
    on one core). The lanes run in the order `order` (a permutation of the inputs);
    the outputs come back in input order."""
    return _sweep_jit(L, m, devices)(q0, order, consts, rtol, atol, t_max, energy_tol)


@functools.lru_cache(maxsize=64)
def _sweep_jit(L, m, devices):
    """`_sweep_body` compiled for one Lagrangian, method and device set: a plain
    `jax.jit` (its C++ dispatch), not `eqx.filter_jit`, whose Python-side flattening
    and hashing of the static arguments cost ~0.3-0.5 ms per call, ~7% of a default
    4096-amplitude sweep on one core (measured)."""
    return jax.jit(functools.partial(_sweep_body, L, m, devices))


def _sweep_body(L, m, devices, q0, order, consts, rtol, atol, t_max, energy_tol):
    out = _periods_diff(L, m, devices, q0[order], consts, rtol, atol, t_max, energy_tol)
    back = lambda x: jnp.zeros_like(x).at[order].set(x, unique_indices=True)
    out = (back(out[0]), back(out[1]), back(out[2]), out[3], back(out[4]))
    # The total of the steps too: `jnp.sum` outside costs an XLA compile of its own
    # (~80 ms on a first call, measured).
    return out, jnp.sum(out[2])


class _WithParameters(eqx.Module):
    """A Lagrangian that is a pytree with float arrays (an `eqx.Module` with
    parameters), as a hashable function of `(q, qdot, t, *arrays)`."""

    static: Any = eqx.field(static=True)
    treedef: Any = eqx.field(static=True)

    def __call__(self, q, qdot, t, *arrays):
        dynamic = jax.tree.unflatten(self.treedef, arrays)
        return eqx.combine(dynamic, self.static)(q, qdot, t)


def closure_converted(L: Callable, dtype):
    """`L` with the tracers it closes over hoisted into explicit arguments.

    Returns `(L_c, consts)` with `L_c(q, qdot, t, *consts) == L(q, qdot, t)`. When `L`
    closes over no tracer, `L_c` is `L` itself, so the compiled
    kernel is found again on the next call with the same `L`. A Lagrangian that is
    a pytree with float arrays (an `eqx.Module` with parameters) passes them as
    `consts` (its compiled kernel is found again for new parameter values, and
    periods are differentiable with respect to them).
    """
    clean = getattr(jax._src.core, "trace_state_clean", None)
    clean = clean is not None and clean()
    z = np.zeros((1,), dtype)  # (NumPy: `jnp.zeros` compiles on a first call)
    dynamic, static = eqx.partition(L, eqx.is_inexact_array)
    arrays, treedef = jax.tree.flatten(dynamic)
    if arrays:
        L_p = _WithParameters(static, treedef)
        if clean:
            return L_p, list(arrays)
        # Tracers closed over elsewhere (a function among its fields) come after.
        converted, extra = jax.closure_convert(L_p, z, z, np.zeros((), dtype), *arrays)
        if not extra:
            return L_p, list(arrays)
        return converted, list(arrays) + list(extra)
    # Outside every transformation `L` closes over no tracer (a leaked one would
    # raise anyway): nothing to hoist, and no trace of `L` per call (with the other
    # checks ~0.5 ms before each dispatch, ~8% of a default 4096-amplitude sweep on
    # one core, measured). (A private JAX function; without it, trace as before.)
    if clean:
        return L, []
    converted, consts = jax.closure_convert(L, z, z, np.zeros((), dtype))
    if not consts:
        return L, []
    return converted, list(consts)


def one_lane(L, q0, tab, method, max_steps, rtol, atol, t_max, energy_tol, estimate):
    """`period` on the kernel: one release point (a scalar), one lane, the default
    device. Returns `(T, status, error_estimate)` as scalars."""
    cfg = _Method(tab, method, 1, max_steps, bool(estimate))
    L_c, consts = closure_converted(L, q0.dtype)
    device = (jax.devices()[0],)
    T, status, _, _, est = _periods_diff(
        L_c, cfg, device, q0[None], consts, rtol, atol, t_max, energy_tol
    )
    return T[0], status[0], est[0]


def _lane_order(q0):
    """The order the lanes run in: by decreasing |q0|, so that neighbouring lanes
    hold neighbouring release points (and, where the well's bottom is near 0, the
    largest swings, usually the longest, go first and the queue's tail is short).
    Measured (pendulum, 4096 amplitudes in random order, one core): the kernel ran
    16-18% slower on unsorted release points than on the same points sorted (Taylor
    "quarter" 4.2 vs 3.6 ms, the default 14.0 vs 11.9 ms), far more than its 2-3%
    more idle lane-steps; why XLA's loop is slower with mixed neighbours was not
    found. Sorted on the host (NumPy: ~0.1 ms for 4096); a traced `q0` (under
    `jit`, `grad`) keeps its own order."""
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
    chunk_size: int = 256,
    sort: bool = True,
    devices=None,
    progress: Callable[[int, int], None] | None = None,
    error_estimate: bool = True,
):
    r"""Periods of many release points at once: `period` over a batch, done fast.

    Each lane computes $T = t(q_0\to q_1) + t(q_1 \to q_0)$ as in `period` (by default
    with `method="matched"`, see there). The batch runs through one compiled loop per
    device: `chunk_size` lanes step together, and a lane that finishes takes the next
    release point from a queue inside the loop, so no lane waits for the slowest; the
    lanes take the release points by decreasing |q0| (`sort`), whatever their order in
    `q0` (`useful_fraction` is typically 0.98–0.99 on one device). The step
    is, by default, an order-20 Taylor step (`lagrax.Taylor`: ~3.5-4x the periods per
    second of `Dopri8` on the pendulum, at the same or better accuracy:
    `benchmarks/sweep.py`), or where L's acceleration has a primitive without a Taylor
    recurrence, or with an explicit `solver=diffrax.Dopri8()` (any adaptive explicit
    Runge–Kutta pair), that solver's step written out stage by stage from its diffrax
    tableau, with diffrax's step-size rule; `SweepResult.solver` says which. Events
    are located by re-stepping with the step length as the unknown (module docstring
    of `lagrax._period.kernel`).
    Amplitudes and tolerances are arrays: changing them never recompiles.

    Each period comes with an error estimate (`error_estimate=True`, the default).
    With the default method and a Taylor step it comes from the solve itself: a
    first-order bound that carries each step's error bound
    (truncation and rounding) to the period, as a time shift along the orbit and an
    energy error times its leverage on the rest of the leg, $\int dt/(M\dot q^2)$,
    plus the far turning point's rounding band times $d\tau/dE$ (a finite-part
    integral from rest); its sums cost ~5% of the solve. Where that bound cannot
    vouch for a lane (above 100 rtol, a leverage beyond its range, a mass that
    varies), and for every other method and solver, the lane is solved a second
    time at 10x looser tolerances (for `"matched"`, from the far turning point
    moved across the band within which float64 rounding of $L$ leaves it
    undetermined), and the estimate is 3 times the relative difference plus 64
    ulps; that second solve costs about 0.8x the first, for the lanes that need it
    only. Validated with `Taylor()` and `Dopri8` against exact periods (pendulum,
    cycloid, the asymmetric well to 0.99 of its hump against a 40-digit quadrature,
    random wells against `quadrature_period`): never below the true error; the
    second solve's ~25x above it at the median (up to ~200x where "half" integrates
    through the bottom near a separatrix, whose rounding loss is random), the bound
    ~13-50x above the true error floored at 1e-14 (the true error at the default
    tolerances is mostly rounding, ~1e-15). With lower-order pairs (`Tsit5`,
    `Dopri5`) the calibration is not established: the second solve's estimate was
    measured below the true error on some lanes (0.47x). A lane whose estimate
    exceeds 100 rtol gets status `tolerance_not_met` and no number;
    `error_estimate=False` skips the estimate.

    A failing lane is reported in `status` and never changes the others: their periods
    are bit-for-bit those of a sweep without it. Differentiable with `jax.grad`,
    `jax.jacfwd` and `jax.jvp` (with respect to `q0` and to parameters `L` closes
    over; each such scalar parameter being differentiated costs one forward pass
    through the sweep, the others nothing).

    **Arguments:**

    - `L`: the Lagrangian `L(q, qdot, t) -> scalar` of one coordinate: a function,
        or a pytree such as an `equinox.Module` whose float array fields are its
        parameters (passed to the compiled kernel as arguments).
    - `q0`: release points, a 1-D float array.
    - `solver`: default `Taylor(fallback=Dopri8())` (above); any solver `period`
        takes. For a sweep to be differentiated, `solver=diffrax.Dopri8()` compiles
        its derivative faster (`jax.grad` of 64 amplitudes, "matched", first call
        4.4 s against 10.5 s, measured) and runs it slower. Inside the kernel,
        float64 `sin` and `cos` in the equations are computed by lagrax's own
        vectorized versions (`lagrax/_trig.py`: within 1 ulp, ~5x faster than the
        C library's on a CPU) in every Runge–Kutta stage and Taylor step; their
        argument must stay within
        $2^{19}\pi/2 \approx 8.2\cdot10^5$ (radians), beyond which they are NaN
        and the lane fails (its status says so), never a wrong number.
    - `rtol`, `atol`, `max_steps`, `t_max`, `energy_tol`, `method`: as in `period`
        (the same for every lane).
    - `chunk_size`: lanes stepping together per device (static: changing it compiles
        anew). 256 suits a CPU core: on the pendulum (one core; 1024 to 65,536
        amplitudes; the defaults, Taylor and Dopri8 "quarter") it was the fastest
        of 128 to 2048 or within 7% of it. A GPU needs far more lanes in flight
        (10^4 to 10^5 per device; `benchmarks/sweep.py --gpu` times 4096 and
        65,536): not measured here, no GPU was available.
    - `error_estimate`: compute the per-lane error estimate (see above).
    - `sort`: run the lanes in order of decreasing |q0| (default True; the outputs
        stay in input order). The queue needs no sorted input to keep lanes busy,
        but the compiled loop runs 16-18% faster when neighbouring lanes hold
        neighbouring release points (measured, 4096 random amplitudes). Sorting is
        done on the host, so only where `q0` is concrete: under `jit` or `grad`,
        `q0` keeps its order (sort it yourself there if it is unsorted).
    - `devices`: the devices to share the batch over (default: all of `jax.devices()`,
        which under `jax.distributed` includes every process's devices); each device
        runs its own loop on an interleaved share, and every process receives the
        whole result.
    - `progress`: optional callback `progress(done, total)`, called as the sweep goes
        (eager calls only; the batch is then run in about 20 pieces).

    **Returns:**

    A `lagrax.SweepResult` with `periods`, `status`, `num_steps` in the input order and
    the work statistics (`useful_fraction`).

    **Raises:**

    `TypeError`/`ValueError` on bad arguments, naming the argument.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    res = lagrax.sweep_periods(L, jnp.linspace(0.01, 3.1, 4096))
    res.periods, res.status, res.useful_fraction
    ```

    **Parameter scans and gradients:** the compiled sweep is cached on the function
    object `L`, so a new closure for each parameter value
    (`lagrax.systems.pendulum.lagrangian(g=g)`) compiles again, seconds each. Make
    the parameters float array fields of an `equinox.Module` instead: they are
    arguments of the compiled sweep, a new value runs at once, and `jax.grad`
    differentiates the periods with respect to them.

    ```python
    import diffrax
    import equinox as eqx

    class Pendulum(eqx.Module):
        g: jax.Array  # a parameter: a float array field

        def __call__(self, q, qdot, t):
            return 0.5 * qdot[0] ** 2 + self.g * jnp.cos(q[0])

    q0 = jnp.linspace(0.1, 3.0, 8)
    for g in (1.0, 4.0, 9.0):  # compiled once, for the first g
        res = lagrax.sweep_periods(Pendulum(jnp.asarray(g)), q0)
    res.periods[0]  # lagrax.systems.pendulum.period(0.1, g=9.0)

    def mean_period(g):  # Dopri8 compiles its derivative faster than Taylor
        res = lagrax.sweep_periods(Pendulum(g), q0, solver=diffrax.Dopri8())
        return res.periods.mean()

    g = jnp.asarray(4.0)
    jax.grad(mean_period)(g)  # -mean_period(g) / 8, as T ∝ 1/√g
    ```
    """
    q0 = as_real_array(q0, "q0")
    if q0.ndim != 1 or q0.shape[0] == 0:
        raise ValueError(
            "`q0` must be a non-empty 1-D array of release points (one per amplitude); "
            f"got shape {q0.shape}."
        )
    rtol, atol, t_max, energy_tol, max_steps, method = _check_options(
        L, q0.dtype, solver, rtol, atol, t_max, energy_tol, max_steps, method
    )
    chunk_size = positive_int(chunk_size, "chunk_size")
    devices = check_devices(jax.devices() if devices is None else devices)
    if progress is not None:
        check_callable(progress, "progress", "a function progress(done, total)")
    dtype = q0.dtype
    solver = resolve_solver(solver, L, dtype)
    tab = stepper(solver)
    cfg = _Method(tab, method, chunk_size, max_steps, bool(error_estimate))
    L_c, consts = closure_converted(L, dtype)
    n = q0.shape[0]

    def run(q, order):
        return _sweep_call(
            L_c, cfg, devices, q, order, consts, rtol, atol, t_max, energy_tol
        )

    identity = lambda m: np.arange(m, dtype=np.int32)
    order = _lane_order(q0) if sort else identity(n)
    if progress is None:
        (periods, status, steps, executed, estimate), useful = run(q0, order)
    else:
        # The whole sweep in order, then pieces of one size (one compilation),
        # padded with the last release point, and back to input order. With NumPy
        # where q0 is concrete: op-by-op jnp here compiled each operation on a first
        # call (`lagrax sweep` 2.0-2.2 s -> 2.8-2.9 s for the pendulum, measured).
        xp = jnp if isinstance(q0, jax.core.Tracer) else np
        q_sorted = xp.asarray(q0)[order]
        size = max(chunk_size * len(devices) * 4, -(-n // 20))
        pieces = -(-n // size)
        pad = xp.full((pieces * size - n,), q_sorted[-1], q_sorted.dtype)
        padded = xp.concatenate([q_sorted, pad])
        outs = []
        for k in range(pieces):
            piece = jnp.asarray(padded[k * size : (k + 1) * size])
            outs.append(run(piece, identity(size))[0])
            jax.block_until_ready(outs[-1])
            progress(min((k + 1) * size, n), n)
        inverse = np.argsort(order)
        back = lambda i: jnp.asarray(
            xp.concatenate([xp.asarray(o[i]) for o in outs])[:n][inverse]
        )
        periods, status, steps, estimate = (back(i) for i in (0, 1, 2, 4))
        executed = sum(o[3] for o in outs)
        useful = jnp.sum(steps)
    return SweepResult(
        periods=periods,
        status=status,
        num_steps=steps,
        lane_steps_useful=useful,
        lane_steps_executed=jnp.asarray(executed),
        chunk_size=chunk_size,
        num_devices=len(devices),
        error_estimate=estimate if error_estimate else None,
        solver=solver,
    )


class SweepResult(eqx.Module):
    r"""The outcome of `sweep_periods`, in the order of the input amplitudes.

    **Fields:**

    - `periods`: the periods, NaN where `status != 0`.
    - `status`: int32 codes, 0 for success; `lagrax.status_message(code)` says what
        the others mean.
    - `num_steps`: solver steps (accepted and rejected) per amplitude, all solves of
        the lane together.
    - `lane_steps_useful`: the sum of `num_steps`, the work each lane needed.
    - `lane_steps_executed`: the lane-steps the batched loops actually ran (a vmapped
        adaptive loop steps every lane of a chunk until its slowest lane is done, and
        pads the last chunk).
    - `chunk_size`: lanes per chunk and device; `num_devices`: devices used.
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
    chunk_size: int = eqx.field(static=True)
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
