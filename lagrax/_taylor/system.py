r"""Taylor coefficients of a first-order system $y' = f(t, y)$ from its jaxpr.

The general case of `taylor_coefficients` (which takes the second-order scalar
$x'' = a(s, x, v)$ of the period kernel): $y$ is a list of arrays and, about
$(t, y)$,

$$y(t + h) = \sum_{k=0}^{K} y_k h^k,\qquad y_{k+1} = \frac{f_k}{k + 1},$$

with $f_k$ the $k$-th coefficient of $f(t + h, y(t + h))$, from $y_0..y_k$ by the
same per-primitive recurrences (products as Cauchy sums, $\sin$/$\cos$ as a pair,
one transcendental call per node for order 0). The orders are unrolled in Python:
one straight-line program that XLA fuses into a few loops (see `_Unrolled`).

The program works on the scalar entries of the state where the jaxpr allows
(`lagrax._jaxpr.scalarize`): a recurrence over small arrays slices and stacks every
coefficient at every order, and XLA recomputes shared terms so often that such a
step runs tens of times slower than on scalar entries (benchmarks/README.md).
"""

import math

import jax
import jax.extend
import jax.numpy as jnp
from jax import lax

from .._jaxpr import interpreter, scalarize as _scalarize
from .._jaxpr.fusion import fusion_off
from . import solve as _solve
from .program import _initial, _Order0, _Program, _Store, _Unrolled
from .recurrences import _order_k, _RULES


_RULES["solve"] = _solve.solve_rule

# Binary primitives whose value does not depend on the order of their operands.
_COMMUTATIVE = frozenset({"add", "add_any", "mul"})


class _SystemProgram(_Program):
    """A `_Program` whose series inputs are $t$ and the entries of $y$, with one
    output per entry of $f$ (`scalar`), or the leaves themselves where the jaxpr
    cannot be evaluated entry by entry."""

    def __init__(self, closed, n_series, n_params):
        self._empty()
        self._negated = {}  # id of `neg u` -> u
        self.inputs = []
        for aval in closed.in_avals[:n_series]:
            i = self._new(aval)
            self.series.add(i)
            self.inputs.append(i)
        rest = closed.in_avals[n_series : n_series + n_params]
        self.params = [self._new(a) for a in rest]
        self.outs = self._inline(closed.jaxpr, closed.consts, self.inputs + self.params)
        self.out = None
        self._prune(self.outs)

    def _emit(self, prim, args, params, outvars):
        # The autodiff jaxpr of a Lagrangian written entry by entry repeats terms up
        # to the order of operands and double negations (a chain of four pendulums:
        # 303 equations, 220 once merged; each is computed at every order).
        name = prim.name
        if name == "neg" and args[0] in self._negated:
            return [self._negated[args[0]]]
        if name in _COMMUTATIVE:
            args = sorted(args)  # exact: a + b == b + a, a * b == b * a
        if prim is not _solve.definite_solve_p:
            outs = super()._emit(prim, args, params, outvars)
            if name == "neg":
                self._negated[outs[0]] = args[0]
            return outs
        # M is symmetric (a mass matrix; `factor` symmetrizes it): its upper
        # triangle only, so the lower one is never computed.
        n = params["n"]
        args = list(args)
        for a in range(n):
            for b in range(a):
                args[a * n + b] = args[b * n + a]
        avals = [v.aval for v in outvars]
        # A "solve" node even where no input is a series (a constant acceleration:
        # a free particle, uniform gravity): `definite_solve_p` has no lowering, and
        # `_SystemOrder0` evaluates the node at order 0.
        series = any(a in self.series for a in args)
        outs = self._add("solve", prim, args, params, avals, series)
        self.series.discard(outs[-1])  # `ok`: decided at order 0
        return outs


class _SystemOrder0(_Order0):
    """Every variable at order 0, the inputs given by id."""

    def __init__(self, prog, inputs, leaves, W, trig=False):
        self._evaluate(prog, W, zip(prog.inputs, inputs), leaves, trig)

    def _node(self, node, vals, batched, trig):
        if node.kind == "solve":
            n = node.params["n"]
            x, ok = _solve.entries_solve(vals[: n * n], vals[n * n :], n)
            outs = [*x, ok]
            if any(batched):
                # `_evaluate` marks every output lane-batched when an input is; an
                # output that does not depend on the batched inputs (`ok` of a
                # constant M, the entry of a constant force) must have the axis too.
                outs = [jnp.broadcast_to(o, (self.W,)) for o in outs]
            return outs
        return super()._node(node, vals, batched, trig)


def _marked(eqn):
    return eqn.primitive.name in ("pjit", "jit") and (
        eqn.params.get("name") == _solve.MARK
    )


def _cost(jaxpr):
    """`scalarize._cost` with the marked solve counted as its entries, and the
    custom-derivative calls inlined (the program is not differentiated through
    their rules: its derivative is that of its own primitives)."""
    total = 0
    for eqn in jaxpr.eqns:
        sub = interpreter.body(eqn, custom=True)
        if _marked(eqn):
            total += sum(math.prod(v.aval.shape) for v in eqn.invars)
        elif sub is not None:
            total += _cost(sub[0])
        else:
            name = eqn.primitive.name
            if name not in _scalarize._ELEMENTWISE | _scalarize._STRUCTURAL:
                return math.inf
            if name == "pad" and any(i for *_, i in eqn.params["padding_config"]):
                return math.inf
            total += sum(math.prod(v.aval.shape) for v in eqn.outvars)
    return total


def _eval_entries(jaxpr, consts, args):
    """The jaxpr on object arrays of scalars (as `scalarize` evaluates it), each
    marked solve (`solve.definite_solve`) bound as one `definite_solve_p` on its
    entries. (Its own walk: `interpreter.evaluate` inlines the marked call.)"""
    env = {}

    def read(v):
        if isinstance(v, jax.extend.core.Literal):
            return _scalarize._const(v.val, v.aval)
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = _scalarize._const(c, v.aval)
    for v, a in zip(jaxpr.invars, args):
        env[v] = a
    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        sub = interpreter.body(eqn, custom=True)
        if _marked(eqn):
            M, rhs = ins
            n = rhs.shape[0]
            flat = [jnp.asarray(e) for e in (*M.reshape(-1), *rhs.reshape(-1))]
            res = _solve.definite_solve_p.bind(*flat, n=n)
            outs = [_scalarize._filled((n,), res[:n]), _scalarize._filled((), [res[n]])]
        elif sub is not None:
            sub_jaxpr, sub_consts = sub
            ins = ins[len(ins) - len(sub_jaxpr.invars) :]
            outs = _eval_entries(sub_jaxpr, sub_consts, ins)
        else:
            outs = _scalarize._rule(eqn, ins)
        for v, out in zip(eqn.outvars, outs):
            env[v] = out
    return [read(v) for v in jaxpr.outvars]


# The most scalar entries (`scalarize._cost`) a vector field may have for its
# program to be built entry by entry; beyond, it is built on its arrays.
_SCALAR_BUDGET = 20_000


class System:
    """The traced program of `f(t, ys, params) -> fs` and how its entries map onto
    the leaves: `ys`, `fs` lists of arrays of the same shapes, `params` a list of
    arrays that are constant over a step (order 0 only)."""

    def __init__(self, f, t, ys, params):
        spec = lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a))
        tspec, yspecs, pspecs = (
            spec(t),
            [spec(y) for y in ys],
            [spec(p) for p in params],
        )
        n = len(ys)

        def structured(t, *rest):
            return tuple(f(t, list(rest[:n]), list(rest[n:])))

        with fusion_off():  # (an identity for XLA; no recurrence rule for it)
            closed = jax.make_jaxpr(structured)(tspec, *yspecs, *pspecs)
        if len(closed.out_avals) != n or any(
            o.shape != y.shape for o, y in zip(closed.out_avals, yspecs)
        ):
            raise TypeError(
                "the vector field must return arrays of the state's shapes "
                f"{[y.shape for y in yspecs]}; got "
                f"{[o.shape for o in closed.out_avals]}."
            )
        self.shapes = [y.shape for y in yspecs]
        self.dtypes = [y.dtype for y in yspecs]
        self.sizes = [math.prod(s) for s in self.shapes]
        self.scalar = _cost(closed.jaxpr) <= _SCALAR_BUDGET
        if not self.scalar:
            self.prog = _SystemProgram(closed, 1 + n, len(params))
            return
        m = sum(self.sizes)
        out_avals = closed.out_avals

        def flat(t, *entries):
            args, i = [_scalarize._filled((), [t])], 0
            for shape, size in zip(self.shapes, self.sizes):
                args.append(_scalarize._filled(shape, entries[i : i + size]))
                i += size
            args += [_scalarize._objects(p) for p in entries[m:]]
            outs = _eval_entries(closed.jaxpr, closed.consts, args)
            return tuple(
                jnp.asarray(v, aval.dtype)
                for out, aval in zip(outs, out_avals)
                for v in out.reshape(-1)
            )

        entries = [
            jax.ShapeDtypeStruct((), y.dtype)
            for y, size in zip(yspecs, self.sizes)
            for _ in range(size)
        ]
        with fusion_off():
            flat_closed = jax.make_jaxpr(flat)(tspec, *entries, *pspecs)
        self.prog = _SystemProgram(flat_closed, 1 + m, len(params))

    def split(self, ys):
        """Lane-batched leaves `(W, *shape)` -> the program's series inputs."""
        if not self.scalar:
            return list(ys)
        return [y.reshape(y.shape[0], -1)[:, i] for y in ys for i in range(y[0].size)]

    def join(self, entries):
        """The inverse of `split`: the program's outputs -> leaves `(W, *shape)`."""
        if not self.scalar:
            return list(entries)
        out, i = [], 0
        for shape, size in zip(self.shapes, self.sizes):
            part = entries[i : i + size]
            W = part[0].shape[0] if size else 0
            out.append(jnp.stack(part, axis=-1).reshape((W, *shape)))
            i += size
        return out

    def coefficients(self, K, t, ys, params, unrolled=True, trig=False):
        r"""The coefficients $y_0..y_K$ about $(t, y)$ of every series input of the
        program (`split(ys)`): one list of `K + 1` arrays per input.

        `t` has shape `(W,)`, every leaf of `ys` and `params` the lane axis first.
        `unrolled`: all orders as one straight-line program (fast, but its compile
        time grows faster than $K^2$ times the program's size), else a
        `lax.fori_loop` over the orders on `(K + 1, W, ...)` arrays."""
        prog = self.prog
        W = t.shape[0]
        ys = self.split(ys)
        zero = _SystemOrder0(prog, [t, *ys], params, W, trig)

        def order0(o, like):
            if o in zero.val:
                return jnp.broadcast_to(zero.lanes(o), like.shape).astype(like.dtype)
            return jnp.zeros_like(like)

        f0 = [order0(o, y) for o, y in zip(prog.outs, ys)]
        lanes = {h: (lambda h=h: zero.lanes(h)) for h in prog.series if h in zero.val}
        if unrolled:
            return self._unrolled(K, zero, lanes, t, ys, f0)
        return self._looped(K, zero, lanes, t, ys, f0)

    def _unrolled(self, K, zero, lanes, t, ys, f0):
        prog = self.prog
        W, dtype = t.shape[0], t.dtype
        coefs = [[y, f] for y, f in zip(ys, f0)]
        t_id, y_ids = prog.inputs[0], prog.inputs[1:]
        store = {t_id: [t, jnp.ones((W,), dtype)]}
        store.update(zip(y_ids, coefs))
        st = _Unrolled(zero, lanes, store)
        for k in range(1, K):
            # `cur` emptied before `get`, which reads it first: it still holds the
            # previous order's coefficients (t_1 = 1, where t_k = 0 for k >= 2).
            st.k, st.kf, st.cur = k, float(k), {}
            st.cur[t_id] = st.get(t_id)
            st.cur.update((i, c[k]) for i, c in zip(y_ids, coefs))
            _order_k(st, prog)
            for c, o, y in zip(coefs, prog.outs, ys):
                f = st.cur.get(o) if o in prog.series else None
                c.append(
                    jnp.zeros_like(y) if f is None else (f / (k + 1)).astype(y.dtype)
                )
        return coefs

    def _looped(self, K, zero, lanes, t, ys, f0):
        """As `_unrolled`, the orders in a `lax.fori_loop` (`_Store`): a program of
        one order's size, whatever $K$."""
        prog = self.prog
        W, dtype = t.shape[0], t.dtype
        t_id, y_ids = prog.inputs[0], prog.inputs[1:]

        def stored(y, f):
            return jnp.zeros((K + 1, *y.shape), y.dtype).at[0].set(y).at[1].set(f)

        fixed = {t_id: (stored(t, jnp.ones((W,), dtype)), None)}
        fixed.update((i, (stored(y, f), None)) for i, y, f in zip(y_ids, ys, f0))

        def body(k, store, record=None):
            st = _Store(zero, K, k, dict(store), lanes, record)
            st.kf = k.astype(dtype)
            st.cur[t_id] = st.get(t_id)
            for i in y_ids:
                st.cur[i] = st.get(i)
            _order_k(st, prog)
            fk = [st.cur.get(o) if o in prog.series else None for o in prog.outs]
            # y_{k+1} = f_k / (k + 1), stored for the next order.
            st.k, st.kf = k + 1, st.kf + 1.0
            for i in y_ids:
                st.cur.pop(i)
            for i, f, y in zip(y_ids, fk, ys):
                st.put(i, jnp.zeros_like(y) if f is None else f / st.kf)
            return {h: st.carry[h] for h in store}

        # A dry run, shapes only, finds which series the recurrences read back
        # (those get loop-carried arrays) and which order-0 quantities they reuse
        # (computed once, outside the loop); as `taylor_coefficients` does.
        record = set()
        jax.eval_shape(lambda k: body(k, dict(fixed), record), jnp.int32(1))
        zero.cache = {key: fn() for key, fn in zero.fns.items()}
        store = dict(fixed)
        for h in record:
            if h not in store:
                store[h] = _initial(K, lanes[h]())
        handles = list(store)  # (ints and tuples: a pytree dict cannot sort them)

        def listed(k, arrays):
            out = body(k, dict(zip(handles, arrays)))
            return [out[h] for h in handles]

        arrays = lax.fori_loop(1, K, listed, [store[h] for h in handles])
        store = dict(zip(handles, arrays))
        return [list(store[i][0]) for i in y_ids]


def horner(cs, h):
    r"""$\sum_k c_k h^k$ over a list of coefficients."""
    out = cs[-1]
    for c in cs[-2::-1]:
        out = out * h + c
    return out
