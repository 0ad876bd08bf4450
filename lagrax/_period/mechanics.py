r"""What the period program evaluates of a Lagrangian, in one place.

The program reads $L$ through a few quantities: the acceleration (with the mass and
whether it is definite) at a point, the same in a lane's own units and its
derivative along the flow (the jerk), the Jacobi energy, $L$ itself and $L$ at rest
with its slope. `mechanics(L, consts)` gives them:

- `AutodiffMechanics`: from $L$'s jaxpr by JAX's autodiff, compiled into the program
  (the specialized program, fast to run, seconds to compile per Lagrangian);
- `TapeMechanics`: from tapes (`lagrax._taylor.tape`), $L$ as data: the program is
  the same for every Lagrangian whose tapes fit its sizes, so that a new $L$ costs
  its tapes, not a compile. The tapes are the acceleration in lane units, the point
  quantities and $L$ at rest, each traced once from the canonical Lagrangian with
  its constants as inputs; derivatives are their Taylor coefficients of order 1.

Each method works on one lane (scalars, or `(1,)` for coordinates) and is vmapped by
its caller, except `lane_field_accel`, over lanes.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp

from .._eom.mechanics import _accelerations, _jacobi
from .._jaxpr.trig import vectorized_trig
from .._taylor.tape import Tape, tape_coefficients, tape_series


class TapeSet(eqx.Module):
    """The tapes of one Lagrangian: `scaled` `(s, x, v, q0, Qs, tau, *params) ->
    accel` in lane units; `point` `(q, qdot, t, *params) -> (qddot, M, ok, energy,
    energy scale, L)`; `rest` `(q, *params) -> L(q, 0, 0)`."""

    scaled: Tape
    point: Tape
    rest: Tape


class TapeLagrangian(eqx.Module):
    """A Lagrangian as data: `consts = (TapeSet, *params)`. Equal for every
    Lagrangian whose tapes have the same sizes and number of parameters, so that the
    compiled period program is shared."""

    sizes: tuple = eqx.field(static=True)
    n_params: int = eqx.field(static=True)

    def __call__(self, q, qdot, t, *consts):
        return TapeMechanics(self, list(consts)).value(q, qdot, t)


def mechanics(L, consts):
    """The period program's view of `L(q, qdot, t, *consts)`."""
    if isinstance(L, TapeLagrangian):
        return TapeMechanics(L, list(consts))
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

    def end_accels(self, r, points):
        """`end_accel` at several points `(s, x, v)`."""
        return [self.end_accel(r, *p) for p in points]

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


class TapeMechanics(eqx.Module):
    """The quantities from the tapes in `consts[0]` (`TapeSet`), the parameters in
    `consts[1:]`. Primal values only: the tape path runs eagerly, outside every
    transformation."""

    L: TapeLagrangian = eqx.field(static=True)
    consts: list

    @property
    def tapes(self) -> TapeSet:
        return self.consts[0]

    @property
    def params(self):
        return list(self.consts[1:])

    def _inputs(self, points, directions=None):
        """`(inputs, points)`: each point's inputs and the parameters (scalars), then
        with `directions` theirs (the parameters' zero)."""
        dtype = self.tapes.rest.values.dtype
        cols = []
        for i, p in enumerate(points):
            col = [*p, *self.params]
            if directions is not None:
                col += [*directions[i], *([0.0] * len(self.params))]
            cols.append(jnp.stack([jnp.asarray(u, dtype) for u in col]))
        return jnp.stack(cols, axis=1)

    def _evals(self, tape, points, directions=None):
        """The tape's outputs at several points (lists of scalar inputs): shape
        `(outputs, points)`; with `directions`, their coefficients of order 1 along
        them. One interpreter for all points, and under `vmap` for all lanes
        (`_wide`)."""
        order = 0 if directions is None else 1
        xs = self._inputs(points, directions)
        return _wide(functools.partial(_series, order=order), tape, xs)[:, order]

    def _eval(self, tape, inputs, order=0, directions=None):
        """The tape's outputs at one point (scalars), or with `directions` their
        coefficients of order 1 along them."""
        dirs = None if directions is None else [directions]
        return self._evals(tape, [inputs], dirs)[:, 0]

    def _point(self, q, qdot, t):
        return self._eval(self.tapes.point, [q[0], qdot[0], t])

    def rest_and_end(self, q0, q_end, qdot_end, t_end):
        zero = jnp.zeros((), q0.dtype)
        points = [[q0, zero, zero], [q_end, qdot_end, t_end]]
        start, end = self._evals(self.tapes.point, points).T
        qddot, M, ok, h, size, _ = end
        return (start[3], start[4]), (
            (qddot[None], (M[None, None], ok != 0)),
            (h, size),
        )

    def end_accel_and_jerk(self, r, s, x, v):
        """One Taylor step's first two coefficients of the acceleration."""
        xs = self._inputs([[s, x, v, r.q0, r.Qs, r.tau]])
        a, jerk = _wide(_accel_and_jerk, self.tapes.scaled, xs)[:, 0]
        return a, jerk

    def end_accels(self, r, points):
        points = [[*p, r.q0, r.Qs, r.tau] for p in points]
        return list(self._evals(self.tapes.scaled, points)[0])

    def accelerations(self, q, qdot, t, fuse=None):
        qddot, M, ok = self._point(q, qdot, t)[:3]
        return qddot[None], (M[None, None], ok != 0)

    def jacobi(self, q, qdot, t):
        return tuple(self._point(q, qdot, t)[3:5])

    def point(self, q, qdot, t, fuse=None):
        qddot, M, ok, h, size, _ = self._point(q, qdot, t)
        return (qddot[None], (M[None, None], ok != 0)), (h, size)

    def value(self, q, qdot, t):
        return self._point(q, qdot, t)[5]

    def scaled_acceleration(self, fuse=None):
        def accel_one(q0, Qs, tau, s, x, v):
            return self._eval(self.tapes.scaled, [s, x, v, q0, Qs, tau])[0]

        return accel_one

    def lane_field_accel(self):
        """Over lanes directly (no `vmap`): the lanes are the interpreter's width."""

        def accel(q0, Qs, tau, s, x, v):
            W = s.shape[0]
            ins = [s, x, v, q0, Qs, tau]
            ins += [jnp.broadcast_to(p, (W,)) for p in self.params]
            return tape_series(self.tapes.scaled, ins, 0, trig=True)[0, 0]

        return accel

    def scalar_accel(self):
        """The tape itself, with the parameters (read by `TapeTaylorStepper`)."""
        return TapeAccel(self.tapes.scaled, self.params)

    def end_accel(self, r, s, x, v):
        return self._eval(self.tapes.scaled, [s, x, v, r.q0, r.Qs, r.tau])[0]

    def end_jerk(self, r, s, x, v, a):
        zero = jnp.zeros_like(s)
        ins = [s, x, v, r.q0, r.Qs, r.tau]
        dirs = [jnp.ones_like(s), v, a, zero, zero, zero]
        return self._eval(self.tapes.scaled, ins, 1, dirs)[0]

    def rest(self, dtype):
        return lambda q: self._eval(self.tapes.rest, [q])[0]

    def rest_slope(self, dtype):
        return lambda q: self._eval(self.tapes.rest, [q], 1, [jnp.ones_like(q)])[0]

    def _rest_lanes(self, qs, order):
        """The rest tape over lanes, `qs` flattened into one width (several points
        per lane: one interpreter, not one per point)."""
        flat = jnp.reshape(qs, (-1,))
        W = flat.shape[0]
        q_in = flat if order == 0 else jnp.stack([flat, jnp.ones_like(flat)])
        ins = [q_in] + [jnp.broadcast_to(p, (W,)) for p in self.params]
        out = tape_series(self.tapes.rest, ins, order, trig=True)[0]
        return [jnp.reshape(out[k], qs.shape) for k in range(order + 1)]

    def rest_lanes(self, dtype):
        return lambda qs: self._rest_lanes(qs, 0)[0]

    def rest_lanes_with_slope(self, dtype):
        def both(qs, k=0):
            values, slopes = self._rest_lanes(qs, 1)
            return values, (slopes if qs.ndim == 1 else slopes[k])

        return both

    def rest_value_and_slope(self, dtype):
        def both(q):
            xs = self._inputs([[q]], [[jnp.ones_like(q)]])
            out = _wide(functools.partial(_series, order=1), self.tapes.rest, xs)
            return out[0, 0, 0], out[0, 1, 0]

        return both


class TapeAccel(eqx.Module):
    """The acceleration tape in lane units with its parameters: a `LaneField`'s
    `scalar_accel` on the tape path (`TapeTaylorStepper` reads the tape)."""

    tape: Tape
    params: list

    def __call__(self, s, x, v, p):
        ins = [s, x, v, *p, *self.params]
        ins = [jnp.reshape(u, (1,)) for u in ins]
        return tape_series(self.tape, ins, 0, trig=True)[0, 0, 0]


def _series(tape, xs, order):
    """The series of the tape's outputs to `order` over lanes, shape `(outputs,
    order + 1, W)`: `xs` of shape `(n, W)`, the inputs' values, then at order 1
    their directions (`n` even)."""
    if order == 0:
        ins = list(xs)
    else:
        half = xs.shape[0] // 2
        ins = [jnp.stack([u, d]) for u, d in zip(xs[:half], xs[half:])]
    return tape_series(tape, ins, order, trig=True)


def _accel_and_jerk(tape, xs):
    """The acceleration tape's value and its derivative along the flow over lanes,
    shape `(2, W)`: a Taylor step's coefficients of order 0 and 1 (`xs`: `(s, x, v,
    *params)`, each of shape `(W,)`)."""
    return tape_coefficients(tape, 2, xs[0], xs[1], xs[2], list(xs[3:]), trig=True)[2]


def _wide(fn, tape, xs):
    """`fn(tape, xs)` (`xs` of shape `(n, W)`, outputs with the lanes last), which
    under `vmap` evaluates every lane in one interpreter of width lanes x W: the
    period program evaluates L lane by lane in several places (the release, the end
    of a leg, ...), and a vmapped interpreter compiles to several times the code of
    a wide one."""

    @jax.custom_batching.custom_vmap
    def run(tape, xs):
        return fn(tape, xs)

    @run.def_vmap
    def rule(axis_size, in_batched, tape, xs):
        if not in_batched[1]:
            xs = jnp.broadcast_to(xs, (axis_size, *xs.shape))
        if any(jax.tree.leaves(in_batched[0])):  # (a batch of tapes: as it comes)
            axes = (jax.tree.map(lambda b: 0 if b else None, in_batched[0]), 0)
            return jax.vmap(run, in_axes=axes)(tape, xs), True
        n, W = xs.shape[1:]
        out = _wide(fn, tape, jnp.moveaxis(xs, 0, 1).reshape(n, axis_size * W))
        out = out.reshape(*out.shape[:-1], axis_size, W)
        return jnp.moveaxis(out, -2, 0), True

    return run(tape, xs)
