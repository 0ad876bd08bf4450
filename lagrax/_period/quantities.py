r"""What the period program evaluates of a Lagrangian, in one place.

The program reads $L$ through a few quantities: the acceleration (with the mass and
whether it is definite) at a point, the same in a lane's own units and its
derivative along the flow (the jerk), the Jacobi energy, $L$ itself and $L$ at rest
with its slope. `mechanics(L, consts)` gives them:

- `AutodiffMechanics`: from $L$'s jaxpr by JAX's autodiff, compiled into the program
  (the specialized program, fast to run, seconds to compile per Lagrangian);
- `CompactMechanics`: from two compact tapes (`lagrax._taylor.compact`), $L$ as
  data: the program is the same for every Lagrangian whose tapes fit its size
  class, so that a new $L$ costs its tapes, not a compile. The *step* tape is the
  acceleration in a lane's units (the Taylor step's coefficients and the
  accelerations in the loop); the *point* tape every other quantity at a point of
  phase space, derivatives included (the jerk along the flow, the slope of $L$),
  traced by JAX's autodiff before the tape is built.

Each method works on one lane (scalars, or `(1,)` for coordinates) and is vmapped by
its caller, except `lane_field_accel` and `leg_ends`, over lanes.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .._eom.mechanics import _accelerations, _jacobi
from .._jaxpr.trig import vectorized_trig
from .._taylor.compact import compact_values, CompactTape


class PeriodTapes(eqx.Module):
    r"""The compact tapes of one Lagrangian (`lagrax._period.tier.tapes_of`):

    - `step`: $f(s, (x, v); (q_0, Q, \tau, *p)) = (v, a)$, the acceleration in a
        lane's own units;
    - `point`: $(t; q, \dot q; *p) \mapsto$ the quantities `POINT` names:
        $\ddot q$, the mass, whether it is definite, the Jacobi energy and the
        scale of its rounding, $L$, $\partial L/\partial q$, and the jerk
        $\dddot q$ along the flow.
    """

    step: CompactTape
    point: CompactTape


# The point tape's outputs.
POINT = ("qddot", "mass", "ok", "energy", "scale", "value", "slope", "jerk")
QDDOT, MASS, OK, ENERGY, SCALE, VALUE, SLOPE, JERK = range(len(POINT))


class CompactLagrangian(eqx.Module):
    """A Lagrangian as data: `consts = (PeriodTapes, *params)`. Equal for every
    Lagrangian whose tapes are of one size class with as many parameters, so that
    the compiled period program is shared."""

    sizes: tuple = eqx.field(static=True)
    n_params: int = eqx.field(static=True)

    def __call__(self, q, qdot, t, *consts):
        return CompactMechanics(self, list(consts)).value(q, qdot, t)


def mechanics(L, consts):
    """The period program's view of `L(q, qdot, t, *consts)`."""
    if isinstance(L, CompactLagrangian):
        return CompactMechanics(L, list(consts))
    return AutodiffMechanics(L, list(consts))


class AutodiffMechanics(eqx.Module):
    """The quantities by JAX's autodiff of `L`'s jaxpr."""

    L: object = eqx.field(static=True)
    consts: list

    def lp(self, q, qdot, t):
        return self.L(q, qdot, t, *self.consts)

    def accelerations(self, q, qdot, t, fuse=None):
        """`(qddot, (M, ok))` at one point (`lagrax.accelerations`' unchecked core)."""
        return _accelerations(self.lp, q, qdot, t, fuse=fuse)

    def jacobi(self, q, qdot, t):
        """The energy and the scale of its rounding."""
        return _jacobi(self.lp, q, qdot, t)

    def value(self, q, qdot, t):
        return self.lp(q, qdot, t)

    def point(self, q, qdot, t, fuse=None):
        """`accelerations` and `jacobi` at one point."""
        return self.accelerations(q, qdot, t, fuse), self.jacobi(q, qdot, t)

    def rest_and_end(self, q0, q_end, qdot_end, t_end):
        """`jacobi` at rest at `q0` and `point` at the end of a leg (scalars)."""
        zero = jnp.zeros((), q0.dtype)
        start = self.jacobi(q0[None], zero[None], zero)
        return start, self.point(q_end[None], qdot_end[None], t_end, fuse=False)

    def end_accel_and_jerk(self, r, s, x, v):
        """`end_accel` and `end_jerk` there."""
        a = self.end_accel(r, s, x, v)
        return a, self.end_jerk(r, s, x, v, a)

    def leg_end(self, r, s, x, v):
        """`rest_and_end` at the release point and the end `(s, x, v)` of a lane's leg
        (its units, `r`: its `Release`), with `end_accel_and_jerk` there."""
        q_end, qdot_end, t_end = r.q0 + r.Qs * x, (r.Qs / r.tau) * v, r.tau * s
        start, end = self.rest_and_end(r.q0, q_end, qdot_end, t_end)
        return start, end, *self.end_accel_and_jerk(r, s, x, v)

    def end_accels(self, r, points):
        """`end_accel` at several points `(s, x, v)`."""
        return [self.end_accel(r, *p) for p in points]

    def leg_ends(self, r, s, x, v, central_points):
        """Over lanes: each lane's `leg_end`, and None (`finish` takes the jerk by
        central differences, `central_points`, with `end_accels` where needed)."""
        return jax.vmap(self.leg_end)(r, s, x, v), None

    def scaled_acceleration(self, fuse=None):
        """The acceleration in a lane's own units: `accel(q0, Qs, tau, s, x, v)`."""

        def accel_one(q0, Qs, tau, s, x, v):
            Vs, As = Qs / tau, Qs / tau**2
            qddot, _ = self.accelerations(
                (q0 + Qs * x)[None], (Vs * v)[None], tau * s, fuse=fuse
            )
            # Behind a select (As > 0 always: the same values), the division has one
            # reader: XLA's CPU fusion will not copy an expensive op to several
            # readers and would split the Taylor step's fusion instead.
            return jnp.where(As != 0, qddot[0] / As, jnp.nan)

        return accel_one

    def lane_field_accel(self):
        """`scaled_acceleration` over lanes for the steps, traced once and reused by
        every call site (not inlined into the loop's jaxpr: `jvp` and `vmap` of the
        call are then done once for all sites; XLA inlines the calls), with sines
        and cosines XLA vectorizes. Without `one_fusion`: inside a step that is one
        fusion, a nested reduce would split it."""
        plain = self.scaled_acceleration(fuse=False)
        return jax.jit(jax.vmap(vectorized_trig(plain)))

    def scalar_accel(self):
        """`scalar_accel(s, x, v, p)` of one lane (`p = (q0, Qs, tau)`): what Taylor
        coefficients are computed from."""
        accel_one = self.scaled_acceleration()
        return lambda s, x, v, p: accel_one(*p, s, x, v)

    def end_accel(self, r, s, x, v):
        """The acceleration in the lane's units at the end of its leg (`r`: its
        `Release`)."""
        qddot, _ = self.accelerations(
            (r.q0 + r.Qs * x)[None], (r.Qs / r.tau * v)[None], r.tau * s, fuse=False
        )
        return qddot[0] * r.tau**2 / r.Qs

    def end_jerk(self, r, s, x, v, a):
        """d/ds of `end_accel` along the flow."""
        return jax.jvp(
            lambda s, x, v: self.end_accel(r, s, x, v),
            (s, x, v),
            (jnp.ones_like(s), v, a),
        )[1]

    def rest(self, dtype):
        """q -> L(q, 0, 0) for a scalar q, with sines and cosines XLA vectorizes
        (each a libm call per lane otherwise): for the turning-point searches and
        tests, which evaluate it many times per lane."""
        z1, z = jnp.zeros((1,), dtype), jnp.zeros((), dtype)
        return vectorized_trig(lambda q: self.lp(jnp.reshape(q, (1,)), z1, z))

    def rest_slope(self, dtype):
        """q -> dL/dq (q, 0, 0)."""
        return jax.grad(self.rest(dtype))

    def rest_value_and_slope(self, dtype):
        return jax.value_and_grad(self.rest(dtype))

    def rest_lanes(self, dtype):
        """`qs -> L(qs, 0, 0)` over lanes (`qs` of shape `(lanes,)` or `(k, lanes)`:
        several points per lane, one evaluation each)."""
        one = jax.vmap(self.rest(dtype))
        return lambda qs: one(qs) if qs.ndim == 1 else jnp.stack([one(q) for q in qs])

    def rest_lanes_with_slope(self, dtype):
        """`(qs, k) -> (L(qs, 0, 0), dL/dq)` over lanes; for `qs` of shape `(m,
        lanes)`, the values at every row and the slope at row `k`."""
        value, slope = jax.vmap(self.rest(dtype)), jax.vmap(self.rest_slope(dtype))

        def both(qs, k=0):
            if qs.ndim == 1:
                return value(qs), slope(qs)
            return jnp.stack([value(q) for q in qs]), slope(qs[k])

        return both


class CompactMechanics(eqx.Module):
    """The quantities from the compact tapes in `consts[0]` (`PeriodTapes`), the
    parameters in `consts[1:]`. Each method works on one lane as its autodiff
    twin does; under `vmap` every lane is one wide evaluation of the tape
    (`_wide`), and a call at several points evaluates them together."""

    L: CompactLagrangian = eqx.field(static=True)
    consts: list

    @property
    def tapes(self) -> PeriodTapes:
        return self.consts[0]

    @property
    def params(self):
        return list(self.consts[1:])

    def _points(self, t, q, qdot):
        """The point tape's outputs at points (arrays of one shape): `(8, *shape)`."""
        return _evaluate(self.tapes.point, self.params, [t, q, qdot])

    def _at(self, q, qdot, t):
        """At one point of `(1,)` coordinates: the 8 outputs."""
        return self._points(t, q[0], qdot[0])

    def accelerations(self, q, qdot, t, fuse=None):
        out = self._at(q, qdot, t)
        return out[QDDOT][None], (out[MASS][None, None], out[OK] != 0)

    def jacobi(self, q, qdot, t):
        out = self._at(q, qdot, t)
        return out[ENERGY], out[SCALE]

    def value(self, q, qdot, t):
        return self._at(q, qdot, t)[VALUE]

    def point(self, q, qdot, t, fuse=None):
        out = self._at(q, qdot, t)
        accel = (out[QDDOT][None], (out[MASS][None, None], out[OK] != 0))
        return accel, (out[ENERGY], out[SCALE])

    def rest_and_end(self, q0, q_end, qdot_end, t_end):
        zero = jnp.zeros((), q0.dtype)
        out = self._points(
            jnp.stack([zero, t_end]),
            jnp.stack([q0, q_end]),
            jnp.stack([zero, qdot_end]),
        )
        start, end = out[:, 0], out[:, 1]
        accel = (end[QDDOT][None], (end[MASS][None, None], end[OK] != 0))
        return (start[ENERGY], start[SCALE]), (accel, (end[ENERGY], end[SCALE]))

    def _end(self, r, s, x, v):
        """The point tape at a lane's `(s, x, v)` (its units, `r`: its `Release`),
        as `AutodiffMechanics.end_accel` maps them."""
        return self._points(r.tau * s, r.q0 + r.Qs * x, r.Qs / r.tau * v)

    def end_accel(self, r, s, x, v):
        return self._end(r, s, x, v)[QDDOT] * r.tau**2 / r.Qs

    def end_accel_and_jerk(self, r, s, x, v):
        r"""The acceleration in the lane's units and its derivative along the flow,
        $\tau^3/Q$ times the jerk."""
        out = self._end(r, s, x, v)
        return out[QDDOT] * r.tau**2 / r.Qs, out[JERK] * r.tau**3 / r.Qs

    def end_jerk(self, r, s, x, v, a):
        return self._end(r, s, x, v)[JERK] * r.tau**3 / r.Qs

    def leg_ends(self, r, s, x, v, central_points):
        """Over lanes: each lane's `AutodiffMechanics.leg_end`, and the accelerations in
        its units at the points `central_points(s, x, v, a)` (a: the acceleration at
        the end) where some lane's jerk is not finite (the central difference's),
        from one evaluation site: a loop of one iteration, or two."""
        return self._ends(None, r, (s, x, v), central_points)[3]

    def release_and_leg_ends(self, q0, run, central_points):
        """`leg_ends` of a pass, and the evaluation at rest at each release point
        `q0` before it, from one evaluation site: `run(out)`, given the point tape's
        outputs there (`(8, 2, lanes)`, both columns the same), runs the pass's
        loop and returns `(Release, (s, x, v) at the legs' ends, what else it
        gives)`; returns those three and `leg_ends`' outputs. A loop of two
        iterations, or three."""
        zero = jnp.zeros_like(q0)
        points = (jnp.stack([zero, zero]), jnp.stack([q0, q0]), jnp.stack([zero, zero]))
        blank = jnp.zeros((len(POINT), 2) + q0.shape, q0.dtype)
        shapes = jax.eval_shape(run, blank)
        r, ends, extra = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
        return self._ends((run, points), r, ends, central_points, extra)

    def _ends(self, first, r, ends, central_points, extra=None):
        """The loop of `leg_ends` (with `first = (run, points)`: of
        `release_and_leg_ends`, from its iteration 0 at `points`). Returns `(r,
        ends, extra, leg_ends' outputs)`."""

        def points_of(r, s, x, v):
            # (At rest at the release point, and the end, as `leg_end`.)
            zero = jnp.zeros_like(s)
            return (
                jnp.stack([zero, r.tau * s]),
                jnp.stack([r.q0, r.q0 + r.Qs * x]),
                jnp.stack([zero, r.Qs / r.tau * v]),
            )

        def end_of(r, out):
            end = out[:, 1]
            return end[QDDOT] * r.tau**2 / r.Qs, end[JERK] * r.tau**3 / r.Qs

        def at_ends(i, out, r, ends, extra, outs):
            outs = jnp.where(i == 1, out, outs)
            a, jerk = end_of(r, outs)
            central = central_points(*ends, a)
            tau, Qs = r.tau[None], r.Qs[None]
            s, x, v = (jnp.stack(p) for p in zip(*central))
            points = (tau * s, r.q0[None] + Qs * x, Qs / tau * v)
            return points, r, ends, extra, outs, jnp.any(~jnp.isfinite(jerk))

        def at_start(i, out, r, ends, extra, outs):
            r, ends, extra = first[0](out)
            return points_of(r, *ends), r, ends, extra, outs, jnp.zeros((), bool)

        def body(c):
            i, points, r, ends, extra, outs, _, _ = c
            out = self._points(*points)
            args = (i, out, r, ends, extra, outs)
            if first is None:
                new = at_ends(*args)
            else:
                new = jax.lax.cond(i == 0, at_start, at_ends, *args)
            points, r, ends, extra, outs, bad = new
            return i + 1, points, r, ends, extra, outs, out, bad

        s = ends[0]
        blank = jnp.zeros((len(POINT), 2) + s.shape, s.dtype)
        start, points = (1, points_of(r, *ends)) if first is None else (0, first[1])
        init = (jnp.asarray(start, jnp.int32), points, r, ends, extra, blank, blank)
        init += (jnp.zeros((), bool),)
        run = lambda c: (c[0] <= 1) | ((c[0] == 2) & c[7])
        _, _, r, ends, extra, outs, last, _ = jax.lax.while_loop(run, body, init)
        start, end = outs[:, 0], outs[:, 1]
        accel = (end[QDDOT][:, None], (end[MASS][:, None, None], end[OK] != 0))
        a, jerk = end_of(r, outs)
        legs = (
            (start[ENERGY], start[SCALE]),
            (accel, (end[ENERGY], end[SCALE])),
            a,
            jerk,
        )
        accels = list(last[QDDOT] * r.tau[None] ** 2 / r.Qs[None])
        return r, ends, extra, (legs, accels)

    def end_accels(self, r, points):
        s, x, v = (jnp.stack(p) for p in zip(*points))
        expand = lambda u: u[None]
        rows = jax.tree.map(expand, r)
        accel = self._end(rows, s, x, v)[QDDOT] * rows.tau**2 / rows.Qs
        return list(accel)

    def _scaled(self, q0, Qs, tau, s, x, v):
        """The step tape's acceleration (arrays of one shape)."""
        out = _evaluate(self.tapes.step, self.params, [s, x, v], [q0, Qs, tau])
        return out[1]

    def scaled_acceleration(self, fuse=None):
        return self._scaled

    def lane_field_accel(self):
        """Over lanes directly: the lanes are the evaluation's width."""
        return self._scaled

    def scalar_accel(self):
        """The step tape with the parameters (read by `CompactTaylorStepper`)."""
        return CompactAccel(self.tapes.step, self.params)

    def _rest(self, qs):
        """`(L, dL/dq)` at rest at `qs` (any shape)."""
        zero = jnp.zeros_like(qs)
        out = self._points(zero, qs, zero)
        return out[VALUE], out[SLOPE]

    def rest(self, dtype):
        return lambda q: self._rest(q)[0]

    def rest_slope(self, dtype):
        return lambda q: self._rest(q)[1]

    def rest_value_and_slope(self, dtype):
        return self._rest

    def rest_lanes(self, dtype):
        return lambda qs: self._rest(qs)[0]

    def rest_lanes_with_slope(self, dtype):
        def both(qs, k=0):
            values, slopes = self._rest(qs)
            return values, (slopes if qs.ndim == 1 else slopes[k])

        return both


class CompactAccel(eqx.Module):
    """The step tape with the Lagrangian's parameters: a `LaneField`'s
    `scalar_accel` in the compact tier (`CompactTaylorStepper` reads the tape)."""

    tape: CompactTape
    params: list

    def __call__(self, s, x, v, p):
        return _evaluate(self.tape, self.params, [s, x, v], list(p))[1]


def _evaluate(tape, params, ins, lane_params=()):
    """The tape's outputs at points: `ins` its series inputs `(t, y...)`, then its
    parameters, `lane_params` (arrays) and the Lagrangian's `params` (scalars),
    all broadcast to one shape. Returns `(outputs, *shape)`."""
    ins = list(ins) + list(lane_params) + list(params)
    shape = jnp.broadcast_shapes(*(jnp.shape(u) for u in ins))
    dtype = jnp.result_type(*ins)
    xs = jnp.stack([jnp.broadcast_to(u, shape).astype(dtype).reshape(-1) for u in ins])
    n_series = len(ins) - len(lane_params) - len(params)
    out = _wide(tape, xs, n_series)
    return out.reshape(out.shape[:1] + shape)


def _values(tape, xs, n_series):
    """`compact_values` over the lanes of `xs` `(inputs, W)` (the series inputs,
    then the parameters): `(outputs, W)`."""
    return compact_values(
        tape, xs[0], list(xs[1:n_series]), list(xs[n_series:]), trig=True
    )


def _wide(tape, xs, n_series):
    """`_values`, which under `vmap` evaluates every lane in one call of width
    lanes x W (the period program evaluates L lane by lane in several places; a
    vmapped evaluation would carry the lanes as a leading axis of every array,
    each lane a strided access), and whose derivatives are those of `_values`
    (forward mode: the periods' tangents), likewise wide under `vmap`."""

    def plain(tape, xs):
        return _values(tape, xs, n_series)

    def tangent(tape, xs, dxs):
        return jax.jvp(lambda xs: plain(tape, xs), (xs,), (dxs,))

    # (The tape an argument, not a closure: under a caller's `jit` it is a tracer.
    # It is a constant of the program: its tangent is not read.)
    @jax.custom_jvp
    def run(tape, xs):
        return _lanes(plain)(tape, xs)

    @run.defjvp
    def _jvp(primals, tangents):
        tape, xs = primals
        return _lanes(tangent)(tape, xs, tangents[1])

    return run(tape, xs)


def _lanes(fn):
    """`fn(tape, *xs)` (arrays whose last axis is the lanes; outputs likewise), whose
    `vmap` folds the batch into the lanes: one call, wider. A batch of tapes runs
    as plain `vmap`."""

    @jax.custom_batching.custom_vmap
    def run(tape, *xs):
        return fn(tape, *xs)

    @run.def_vmap
    def rule(axis_size, in_batched, tape, *xs):
        if any(jax.tree.leaves(in_batched[0])):  # (a batch of tapes: as it comes)
            axes = (jax.tree.map(lambda b: 0 if b else None, in_batched[0]),)
            axes += tuple(0 if b else None for b in in_batched[1:])
            out = jax.vmap(run, in_axes=axes)(tape, *xs)
            return out, jax.tree.map(lambda _: True, out)
        wide = []
        for x, batched in zip(xs, in_batched[1:]):
            if not batched:
                x = jnp.broadcast_to(x, (axis_size, *x.shape))
            wide.append(jnp.moveaxis(x, 0, -2).reshape(*x.shape[1:-1], -1))
        out = _lanes(fn)(tape, *wide)

        def back(o):
            return jnp.moveaxis(o.reshape(*o.shape[:-1], axis_size, -1), -2, 0)

        out = jax.tree.map(back, out)
        return out, jax.tree.map(lambda _: True, out)

    return run
