"""The period methods as passes of the kernel, one leg per pass: "half" and
"quarter" in one, "full" and "matched" in two (with the error estimate, its solves
in the same passes; with the first-order error bound, a second round for the lanes
it cannot vouch for)."""

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._results import (
    ENERGY_DRIFT,
    NOT_OSCILLATING,
    NOT_SYMMETRIC,
    ROOT_FIND_FAILED,
    SOLVER_FAILED,
    SUCCESS,
)
from .._stepper.base import AbstractStepper
from .._taylor.stepper import TaylorStepper
from .estimate import needs_second_solve, screen, screen_quarter, TIGHTER
from .events import MAX_SPEED, POSITION, TURNING
from .far_turning_point import far_turning_point
from .kernel import Lanes, PassResult, run_pass
from .loop import Pass
from .quantities import mechanics
from .symmetry import is_turning_point, mirror_symmetric


class Method(eqx.Module):
    """A period method as passes of the kernel."""

    stepper: AbstractStepper
    method: str = eqx.field(static=True)
    width: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    estimate: bool = eqx.field(static=True)

    @property
    def pass_(self):
        # (One leg per pass: "full" returns in a second pass, `_swing`.)
        return Pass(self.stepper, self.width, self.max_steps, self.screened)

    @property
    def screened(self):
        """Whether the error estimate is the first-order bound where it vouches:
        Taylor steps, and legs from rest to the point of maximum speed ("matched",
        "quarter")."""
        taylor = isinstance(self.stepper, TaylorStepper)
        return self.estimate and self.method in ("matched", "quarter") and taylor


class MethodResult(eqx.Module):
    """One solve of every lane: periods (NaN on failure), statuses, steps, executed
    lane-steps, and the far side of each swing; for "matched", the first-order
    bound, and with a second round the lanes solved again (`redo`) with their
    periods and statuses there."""

    periods: Float[Array, " n"]
    status: Int[Array, " n"]
    steps: Int[Array, " n"]
    executed: Int[Array, ""]
    q_far: Float[Array, " n"]
    bound: Float[Array, " n"] | None = None
    redo: Bool[Array, " n"] | None = None
    periods2: Float[Array, " n"] | None = None
    status2: Int[Array, " n"] | None = None


class LegA(eqx.Module):
    """What "matched" keeps from its first leg for the second: the release points,
    the first leg's status, the far turning point, where it was found, the lanes
    whose second leg runs (`go`), and the far turning point's rounding band."""

    q0: Float[Array, " n"]
    status: Int[Array, " n"]
    q1: Float[Array, " n"]
    found: Bool[Array, " n"]
    go: Bool[Array, " n"]
    band: Float[Array, " n"]


class Reference(eqx.Module):
    """The error estimate's solves, run in the passes of the requested one, per lane:
    whether the lane is the reference of "half" or "full" (`ref`: solved by
    "matched"), how many rounding bands its far turning point moves (`shift`), and
    the lane whose first leg it continues (`source`: itself, or another lane's, whose
    first leg it does not run again: such lanes come last, and run only the second
    pass)."""

    ref: Bool[Array, " n"]
    shift: Float[Array, " n"]
    source: Int[Array, " n"]

    @property
    def first(self):
        """The lanes that run their own first leg."""
        return self.source == jnp.arange(self.source.shape[0])


def _continued(res: PassResult, source) -> PassResult:
    """Each lane's first-leg result from the lane `source` names (a lane that
    continues another's first leg took none of its steps)."""
    own = source == jnp.arange(source.shape[0])
    res = jax.tree.map(lambda x: x[source] if jnp.ndim(x) == 1 else x, res)
    return dataclasses.replace(res, steps=jnp.where(own, res.steps, 0))


def _kinds(q0, kind):
    return jnp.full(q0.shape, kind, jnp.int32)


class _Solve(eqx.Module):
    """The passes of one solve: `L` and what stays the same for every pass."""

    L: Callable
    m: Method
    consts: Any
    t_max: Any
    energy_tol: Any

    def run(self, lanes: Lanes) -> PassResult:
        L, m = self.L, self.m
        return run_pass(L, m.pass_, lanes, self.consts, self.t_max, self.energy_tol)

    def leg_b(
        self, res: PassResult, lanes: Lanes, shift, only=None
    ) -> tuple[Lanes, LegA]:
        """The second leg of "matched": from rest at the far turning point (moved by
        `shift` rounding bands), ending at the first leg's meeting point; with
        `only`, for those lanes alone (the others keep their first leg's status and
        take no step)."""
        st_a, t_a, q_m, qd_a = res.status, res.t_event, res.q_end, res.qdot_end
        q0 = lanes.q0
        if only is not None:
            # (NaN takes no Newton step in the far turning point's loops.)
            q0, q_m = jnp.where(only, q0, jnp.nan), jnp.where(only, q_m, jnp.nan)
        # Any point of leg A serves as the meeting point: leg B ends at its
        # position. Where the point of maximum speed cannot be located (a well
        # whose curvature vanishes at its bottom, q̈ = -q³: q̈ has a triple zero in
        # time there and no Newton or secant converges), the last accepted state
        # before it is used; the two legs' speeds must still agree there (`combine`).
        meet = (st_a == ROOT_FIND_FAILED) & jnp.isfinite(q_m) & jnp.isfinite(t_a)
        st_a = jnp.where(meet & (qd_a != 0), SUCCESS, st_a)  # (moving: not the release)
        far = far_turning_point(self.L, self.consts, q0, q_m, self.m.estimate)
        # (L beyond the vectorized sines' range: the solver's failure, not the well's.)
        out_of_range = (st_a == SUCCESS) & ~far.in_range
        if only is not None:
            out_of_range = out_of_range & only
        st_a = jnp.where(out_of_range, SOLVER_FAILED, st_a)
        # (Only where shifted: a band that rounding leaves undefined, NaN next to a
        # singular point, must not turn the requested solve's start into NaN,
        # reported as a non-finite release point.)
        q1 = far.q1 + jnp.where(shift != 0, shift * far.band, 0.0)
        go = far.found & (st_a == SUCCESS)
        if only is not None:
            go = go & only
        lanes_b = Lanes(
            jnp.where(go, q1, jnp.nan),
            q_m,
            _kinds(q0, POSITION),
            lanes.rtol,
            lanes.atol,
            lanes.live,
        )
        return lanes_b, LegA(q0, st_a, q1, far.found, go, far.band)

    def combine(self, res_a: PassResult, res_b: PassResult, a: LegA, rtols):
        """The period of "matched" from its two legs, which must meet at the same
        speed (to the energy tolerance)."""
        t_a, q_m, qd_a = res_a.t_event, res_a.q_end, res_a.qdot_end
        st_b, t_b, qd_b = res_b.status, res_b.t_event, res_b.qdot_end
        energy_tol = self.energy_tol
        tol = jnp.sqrt(rtols) if energy_tol is None else energy_tol
        match = jnp.abs(jnp.abs(qd_a) - jnp.abs(qd_b)) <= tol * jnp.abs(qd_a)
        status = jnp.select(
            [a.status != SUCCESS, ~a.found, st_b != SUCCESS, ~match],
            [
                a.status,
                jnp.full_like(a.status, NOT_OSCILLATING),
                st_b,
                jnp.full_like(a.status, ENERGY_DRIFT),
            ],
            a.status,
        )
        q_far = jnp.where(a.found, a.q1, 2 * q_m - a.q0)
        T = jnp.where(status == SUCCESS, 2 * (t_a + t_b), jnp.nan)
        steps = res_a.steps + jnp.where(a.go, res_b.steps, 0)
        bound = screen(T, t_a, t_b, res_a.terms, res_b.terms, a.band, rtols)
        executed = res_a.executed + res_b.executed
        return MethodResult(T, status, steps, executed, q_far, bound)


def run_method(
    L, m, q0, consts, rtols, atols, t_max, energy_tol, screened=False, second=None
) -> MethodResult:
    """One solve of every lane by `m.method` (per-lane tolerances).

    `second` (a `Reference`): the error estimate's solves among the lanes, for
    "matched", "half" and "full". `screened` ("matched" or "quarter" with a Taylor
    step and the error estimate): the first-order error bound of each lane
    (`estimate.screen`), and a second solve, at `TIGHTER` times the tolerances from
    the far turning point moved across its band, of only the lanes that bound cannot
    vouch for, in the same loop."""
    zeros = jnp.zeros_like(q0)
    live = jnp.ones(q0.shape, bool)
    solve = _Solve(L, m, consts, t_max, energy_tol)
    if m.method == "quarter" and screened:
        lanes0 = Lanes(q0, zeros, _kinds(q0, MAX_SPEED), rtols, atols, live)
        return _quarter_screened(solve, lanes0, rtols)
    if m.method in ("full", "half") and (m.method == "full" or second is not None):
        return _swing(solve, q0, rtols, atols, second)
    if m.method != "matched":
        return _one_pass(solve, q0, zeros, rtols, atols, live)
    if second is not None:
        live = second.first
    lanes0 = Lanes(q0, zeros, _kinds(q0, MAX_SPEED), rtols, atols, live)
    if not screened:
        return _matched(solve, lanes0, rtols, second)
    return _matched_screened(solve, lanes0, rtols, atols)


def _one_pass(solve: _Solve, q0, zeros, rtols, atols, live) -> MethodResult:
    """ "half" or "quarter": one pass to the event."""
    kind = {"half": TURNING, "quarter": MAX_SPEED}[solve.m.method]
    res = solve.run(Lanes(q0, zeros, _kinds(q0, kind), rtols, atols, live))
    return _one_pass_result(solve, q0, rtols, res)


def _one_pass_result(solve: _Solve, q0, rtols, res: PassResult) -> MethodResult:
    """The period of "half" or "quarter" from its pass."""
    kind, factor = {"half": (TURNING, 2.0), "quarter": (MAX_SPEED, 4.0)}[solve.m.method]
    status, t_e, q_e, qd_e = res.status, res.t_event, res.q_end, res.qdot_end
    # The far side of the swing, for `blame_coordinates`: where the solve stopped, or
    # past the point of maximum speed by as much again.
    q_far = 2 * q_e - q0 if kind == MAX_SPEED else q_e
    if kind == MAX_SPEED:
        # T = 4 t(q0 -> q_m) holds for a well mirror-symmetric about q_m: the mirror
        # image of q0 must be a turning point (to rtol across the swing).
        L, consts = solve.L, solve.consts
        symmetric = is_turning_point(
            L, consts, q0, q_far, rtols * jnp.abs(q_e - q0)
        ) & mirror_symmetric(L, consts, q0, q_e, qd_e, rtols)
        status = jnp.where((status == SUCCESS) & ~symmetric, NOT_SYMMETRIC, status)
    T = jnp.where(status == SUCCESS, factor * t_e, jnp.nan)
    return MethodResult(T, status, res.steps, res.executed, q_far)


def _blank(tree):
    return jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), tree)


def _matched(solve: _Solve, lanes0: Lanes, rtols, second=None) -> MethodResult:
    """Two quarter legs, each from rest at its own turning point, meeting at the
    point of maximum speed: nothing is integrated through the bottom of the swing.
    With `second` (a `Reference`), its lanes' far turning points moved by their
    `shift`, and the lanes that continue another's first leg run only the second.

    Both legs run through ONE instance of the kernel: a while loop over the passes
    whose body is the pass (its trip count is not a constant XLA can see, so it is
    not unrolled). Two calls of the pass would put two copies of the kernel in the
    program: everything but its identical fusions compiled twice, and the
    forward-mode derivative's tangent kernels twice."""
    if second is None:
        leg_b = lambda r, l: solve.leg_b(r, l, 0.0)
        res_a, aux, res_b = _two_passes(solve, lanes0, leg_b, rtols)
    else:
        every = lambda l: dataclasses.replace(l, live=jnp.ones_like(l.live))
        leg_b = lambda r, l: solve.leg_b(
            _continued(r, second.source), every(l), second.shift
        )
        res_a, aux, res_b = _two_passes(solve, lanes0, leg_b, rtols)
        res_a = _continued(res_a, second.source)
    out = solve.combine(res_a, res_b, aux, rtols)
    return MethodResult(out.periods, out.status, out.steps, out.executed, out.q_far)


def _two_passes(solve: _Solve, lanes0: Lanes, second, rtols):
    """Two passes through one instance of the kernel: `second(res, lanes) ->
    (lanes, aux)` makes the second pass's lanes from the first's results. Returns
    `(res_a, aux, res_b)`."""
    res_shape = jax.eval_shape(lambda: solve.run(lanes0))
    aux_shape = jax.eval_shape(lambda r: second(r, lanes0)[1], res_shape)

    def body(c):
        k, lanes, res_a, aux, _ = c
        res = solve.run(lanes)
        leg_a = k % 2 == 0
        lanes, aux = jax.lax.cond(
            leg_a, lambda: second(res, lanes), lambda: (lanes, aux)
        )
        res_a = jax.tree.map(lambda x, y: jnp.where(leg_a, x, y), res, res_a)
        return k + 1, lanes, res_a, aux, res

    # (2 on every lane, but not a constant XLA can see through.)
    passes = jnp.where(jnp.all(rtols > -1.0), 2, 1).astype(jnp.int32)
    init = (jnp.zeros((), jnp.int32), lanes0, *_blank((res_shape, aux_shape)))
    init = (*init, _blank(res_shape))
    _, _, res_a, aux, res_b = jax.lax.while_loop(lambda c: c[0] < passes, body, init)
    return res_a, aux, res_b


# Where `_even_in_qdot` compares L(q0, w) with L(q0, -w) (exact binary fractions).
_EVEN_SPEEDS = (0.375, 1.5)


def _even_in_qdot(L, consts, q0):
    """Whether L(q0, q̇) = L(q0, -q̇) at two speeds, to rounding: where "matched"
    (time-reversal symmetric legs) is a reference for "full". Sampled, not proven:
    an L that passes wrongly gets an estimate from the wrong period, too large."""
    mech = mechanics(L, consts)
    eps = jnp.finfo(q0.dtype).eps
    zero = jnp.zeros((), q0.dtype)

    def one(q):
        q = jnp.where(jnp.isfinite(q), q, 0.0)[None]
        even = jnp.ones((), bool)
        for w in _EVEN_SPEEDS:
            a = mech.value(q, jnp.full((1,), w, q.dtype), zero)
            b = mech.value(q, jnp.full((1,), -w, q.dtype), zero)
            even = even & (jnp.abs(a - b) <= 8 * eps * (jnp.abs(a) + jnp.abs(b)))
        return even

    return jax.vmap(one)(jax.lax.stop_gradient(q0))


def _swing(solve: _Solve, q0, rtols, atols, second) -> MethodResult:
    """ "half", and "full" (its return leg in a second pass, from rest at the
    turning point the first found), with the estimate's solves (`second`, a
    `Reference`) by "matched" where it applies ("full": where L is even in q̇;
    elsewhere "full" again).

    Through the bottom of the swing these methods lose to the energy errors their
    steps make, amplified near a hump, by an amount that does not scale with the
    tolerance (the same in a solve at tighter tolerances, so that their difference
    cannot see it), while "matched" pins the energy at both turning points. All in
    the passes of one instance of the kernel: the first runs the outgoing leg and
    the reference's first leg (each lane its own event), the second the return leg
    and the reference's second leg."""
    full = solve.m.method == "full"
    zeros = jnp.zeros_like(q0)
    if second is None:
        ref, first = jnp.zeros(q0.shape, bool), jnp.ones(q0.shape, bool)
        source = jnp.arange(q0.shape[0])
    else:
        ref, first, source = second.ref, second.first, second.source
    if full:
        ref = ref & _even_in_qdot(solve.L, solve.consts, q0)
    kinds = jnp.where(ref, MAX_SPEED, TURNING).astype(jnp.int32)
    lanes0 = Lanes(q0, zeros, kinds, rtols, atols, first)

    def next_pass(res, lanes):
        lanes = dataclasses.replace(lanes, live=jnp.ones_like(lanes.live))
        if second is None:
            lanes_m, aux = lanes, None
        else:
            res_m = _continued(res, source)
            lanes_m, aux = solve.leg_b(res_m, lanes, second.shift, only=ref)
        if not full:
            return lanes_m, aux
        # The return leg from rest where the outgoing one ended (its state carries
        # the event's tangent).
        back = ~ref & first & (res.status == SUCCESS)
        lanes = Lanes(
            jnp.where(ref, lanes_m.q0, jnp.where(back, res.q_end, jnp.nan)),
            jnp.where(ref, lanes_m.target, 0.0),
            jnp.where(ref, lanes_m.kind, TURNING).astype(jnp.int32),
            lanes.rtol,
            lanes.atol,
            lanes.live,
        )
        return lanes, aux

    res_a, aux, res_b = _two_passes(solve, lanes0, next_pass, rtols)
    if full:
        status = jnp.where(res_a.status == SUCCESS, res_b.status, res_a.status)
        T = jnp.where(status == SUCCESS, res_a.t_event + res_b.t_event, jnp.nan)
        back = res_a.status == SUCCESS
        steps = res_a.steps + jnp.where(back, res_b.steps, 0)
        own = MethodResult(T, status, steps, res_a.executed, res_a.q_end)
    else:
        own = _one_pass_result(solve, q0, rtols, res_a)
    executed = res_a.executed + res_b.executed
    if second is None:
        return dataclasses.replace(own, executed=executed)
    matched = solve.combine(_continued(res_a, source), res_b, aux, rtols)
    pick = lambda x, y: jnp.where(ref, x, y)
    out = MethodResult(
        pick(matched.periods, own.periods),
        pick(matched.status, own.status),
        pick(matched.steps, own.steps),
        executed,
        pick(matched.q_far, own.q_far),
    )
    # A lane continuing another's first leg without a reference to solve (no far
    # turning point) repeats that lane's result (it took no steps).
    again = ~first & ~ref
    take = lambda x: jnp.where(again, x[source], x)
    return MethodResult(
        take(out.periods),
        take(out.status),
        jnp.where(again, 0, out.steps),
        executed,
        take(out.q_far),
    )


def _pack(out: MethodResult, dtype):
    """A round's results as one array (fewer fusions to compile) and its work."""
    f = lambda x: x.astype(dtype)
    packed = jnp.stack([out.periods, f(out.status), f(out.steps), out.q_far, out.bound])
    return packed, out.executed


def _second_round(lanes0: Lanes, status, bound) -> tuple[Lanes, Array, Array]:
    """After the first round: the lanes its bound cannot vouch for, first (their
    positions `pos`), at tighter tolerances; the others are not loaded."""
    q0, rtols, atols = lanes0.q0, lanes0.rtol, lanes0.atol
    n = q0.shape[0]
    redo = needs_second_solve(status, bound, rtols)
    i32 = lambda x: x.astype(jnp.int32)
    count = jnp.sum(i32(redo))
    first = jnp.cumsum(i32(redo)) - 1
    rest = count + jnp.cumsum(i32(~redo)) - 1
    pos = i32(jnp.where(redo, first, rest))  # lane i goes to position pos[i]
    perm = jnp.zeros_like(pos).at[pos].set(jnp.arange(n, dtype=jnp.int32))
    live = jnp.arange(n) < count
    # (The second round only estimates: no tangents.)
    sg = jax.lax.stop_gradient
    lanes = Lanes(
        jnp.where(live, sg(q0)[perm], jnp.nan),
        lanes0.target,
        _kinds(q0, MAX_SPEED),
        TIGHTER * rtols[perm],
        TIGHTER * atols[perm],
        live,
    )
    return lanes, pos, count


def _matched_screened(solve: _Solve, lanes0: Lanes, rtols, atols) -> MethodResult:
    """ "matched" with the first-order bound: the second round (passes 2 and 3)
    starts leg B from the far turning point moved across its band, and runs only
    where the first round left lanes to solve again. Each round's results are
    combined in the loop (one copy of that code in the program), packed."""
    dtype = lanes0.q0.dtype
    res_shape = jax.eval_shape(lambda: solve.run(lanes0))
    aux_shape = jax.eval_shape(lambda r: solve.leg_b(r, lanes0, 0.0)[1], res_shape)
    rounds_shape = jax.eval_shape(
        lambda r, a: _pack(solve.combine(r, r, a, rtols), dtype), res_shape, aux_shape
    )
    rounds_shape = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct((2,) + x.shape, x.dtype), rounds_shape
    )

    def body(c):
        k, lanes, res_a, aux, rounds, pos, passes = c
        res = solve.run(lanes)
        leg_a = k % 2 == 0

        def after_b():
            out = solve.combine(res_a, res, aux, lanes.rtol)
            i = (k - 1) // 2
            r = jax.tree.map(
                lambda all_, x: all_.at[i].set(x), rounds, _pack(out, dtype)
            )

            def new_round():
                lanes_1, pos_1, count = _second_round(lanes0, out.status, out.bound)
                more = jnp.where(count > 0, passes, 2).astype(passes.dtype)
                return lanes_1, pos_1, more

            lanes_, pos_, more = jax.lax.cond(
                k == 1, new_round, lambda: (lanes, pos, passes)
            )
            return lanes_, aux, r, pos_, more

        shift_k = jnp.where(k >= 2, 1.0, 0.0).astype(dtype)
        lanes, aux, rounds, pos, passes = jax.lax.cond(
            leg_a,
            lambda: (*solve.leg_b(res, lanes, shift_k), rounds, pos, passes),
            after_b,
        )
        res_a = jax.tree.map(lambda x, y: jnp.where(leg_a, x, y), res, res_a)
        return k + 1, lanes, res_a, aux, rounds, pos, passes

    # (4 passes, but not a constant XLA can see through.)
    passes = jnp.where(jnp.all(rtols > -1.0), 4, 1).astype(jnp.int32)
    init = (
        jnp.zeros((), jnp.int32),
        lanes0,
        _blank(res_shape),
        _blank(aux_shape),
        _blank(rounds_shape),
        jnp.zeros(lanes0.q0.shape, jnp.int32),
        passes,
    )
    _, _, _, _, (rounds, ex), pos, passes = jax.lax.while_loop(
        lambda c: c[0] < c[-1], body, init
    )
    return _unpack_rounds(rounds, ex, pos, passes > 2, rtols)


def _quarter_screened(solve: _Solve, lanes0: Lanes, rtols) -> MethodResult:
    """ "quarter" with the first-order bound (one leg of "matched"'s): a second
    round, at `TIGHTER` times the tolerances, of only the lanes the bound cannot
    vouch for; both rounds through one instance of the kernel (a while loop over
    the passes, as `_matched`)."""
    dtype = lanes0.q0.dtype
    res_shape = jax.eval_shape(lambda: solve.run(lanes0))

    def round_of(lanes, res):
        out = _one_pass_result(solve, lanes.q0, lanes.rtol, res)
        bound = screen_quarter(out.periods, res.t_event, res.terms)
        return _pack(dataclasses.replace(out, bound=bound), dtype)

    rounds_shape = jax.eval_shape(round_of, lanes0, res_shape)
    rounds_shape = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct((2,) + x.shape, x.dtype), rounds_shape
    )

    def body(c):
        k, lanes, rounds, pos, passes = c
        res = solve.run(lanes)
        packed = round_of(lanes, res)
        rounds = jax.tree.map(lambda all_, x: all_.at[k].set(x), rounds, packed)

        def new_round():
            (T, status, _, _, bound), _ = packed
            lanes_1, pos_1, count = _second_round(
                lanes0, status.astype(jnp.int32), bound
            )
            more = jnp.where(count > 0, passes, 1).astype(passes.dtype)
            return lanes_1, pos_1, more

        lanes, pos, passes = jax.lax.cond(
            k == 0, new_round, lambda: (lanes, pos, passes)
        )
        return k + 1, lanes, rounds, pos, passes

    # (2 passes, but not a constant XLA can see through.)
    passes = jnp.where(jnp.all(rtols > -1.0), 2, 1).astype(jnp.int32)
    init = (
        jnp.zeros((), jnp.int32),
        lanes0,
        _blank(rounds_shape),
        jnp.zeros(lanes0.q0.shape, jnp.int32),
        passes,
    )
    _, _, (rounds, ex), pos, passes = jax.lax.while_loop(
        lambda c: c[0] < c[-1], body, init
    )
    return _unpack_rounds(rounds, ex, pos, passes > 1, rtols)


def _unpack_rounds(rounds, ex, pos, second, rtols) -> MethodResult:
    """The first round's results, with the second round's (back in lane order) where
    the bound could not vouch for a lane (`second`: whether it ran)."""
    i32 = lambda x: x.astype(jnp.int32)
    T, status, steps, q_far, bound = rounds[0]
    status, steps = i32(status), i32(steps)
    # (Without the second round, nothing to redo: its outputs are blank.)
    redo = needs_second_solve(status, bound, rtols) & second
    T2, status2, steps2 = rounds[1][:3, pos]
    steps = steps + jnp.where(redo, i32(steps2), 0)
    status2 = i32(status2)
    executed = ex[0] + jnp.where(second, ex[1], 0)
    return MethodResult(T, status, steps, executed, q_far, bound, redo, T2, status2)
