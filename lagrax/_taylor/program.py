r"""The coefficient program: a jaxpr flattened once, evaluated at order 0, then
order by order with the recurrences of `recurrences.py`.

- The jaxpr is traced once at scalar inputs, nested calls (`jit`, `custom_jvp_call`,
    ...) are inlined, duplicate equations merged (an autodiff jaxpr computes `sin q`
    once per tangent direction) and dead ones dropped.
- A variable is a *series* only if it depends differentiably on $(s, x, v)$. Everything
    else (tangent seeds, a constant mass matrix, per-lane parameters, comparisons) is
    evaluated once, at order 0, and multiplies series in $O(K)$. Outputs of
    zero-derivative primitives (`sign`, `floor`, comparisons, `is_finite`) and the
    branch of `select_n`, `max`, `abs` are decided on the order-0 coefficient.
- Orders 1..K-1 come one of two ways. With `unrolled=True` (the period kernel's
    default), as one straight-line program (`_Unrolled`: exactly triangular sums, one
    `(W,)` array per coefficient), which XLA fuses with the polynomials' evaluation
    into a few loops over the lanes; it compiles longer, so a program of more than
    `_UNROLL_BUDGET` equations takes the other way. Otherwise, in one `lax.fori_loop`
    over fixed-shape `(K + 1, W)` coefficient arrays (`_Store`): each Cauchy sum is a
    full-length product with a reversed, shifted copy, so half its multiply-adds hit
    zeros, but the program's size does not grow with $K$.

`benchmarks/taylor_coefficients.py` measures both.
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._jaxpr import interpreter, trig as _trig
from .._jaxpr.fusion import fusion_off
from .recurrences import (
    _add,
    _BILINEAR,
    _bind,
    _ELEMENTWISE,
    _LINEAR,
    _NONLINEAR,
    _order_k,
    _PIECEWISE_CONSTANT,
)


__all__ = ["taylor_coefficients"]


def _supported():
    return sorted(
        _PIECEWISE_CONSTANT
        | _LINEAR
        | _BILINEAR
        | _NONLINEAR
        | set(interpreter.supported_calls(custom=True))
    )


class _Node:
    """One equation of the flattened program: `outs = kind(ins)`."""

    __slots__ = ("kind", "prim", "ins", "outs", "params", "series")

    def __init__(self, kind, prim, ins, outs, params, series):
        self.kind = kind
        self.prim = prim
        self.ins = ins
        self.outs = outs
        self.params = params
        self.series = series


class _Program:
    """A jaxpr flattened into `_Node`s over integer variable ids.

    Ids `0, 1, 2` are $s, x, v$; the next ones the per-lane parameters; then constants
    (literals and closed-over values) and equation outputs.
    """

    def __init__(self, closed, n_params):
        self._empty()
        scalar = closed.in_avals[0]
        for _ in range(3):
            i = self._new(scalar)
            self.series.add(i)
        self.params = [self._new(a) for a in closed.in_avals[3 : 3 + n_params]]
        ins = list(range(3)) + self.params
        (self.out,) = self._inline(closed.jaxpr, closed.consts, ins)
        self._prune()

    def _empty(self):
        self.nodes = []
        self.avals = {}
        self.consts = {}  # id -> value (unbatched)
        self.series = set()
        self._const_ids = {}
        self._cse = {}
        self._next = 0

    # --- building
    def _new(self, aval):
        i = self._next
        self._next += 1
        self.avals[i] = aval
        return i

    def _const(self, value, aval):
        key = None
        if np.ndim(value) == 0 and not isinstance(value, jax.core.Tracer):
            try:
                key = (np.asarray(value).item(), str(aval.dtype), aval.weak_type)
            except Exception:  # noqa: BLE001 -- an unhashable constant: no dedup
                key = None
        if key is not None and key in self._const_ids:
            return self._const_ids[key]
        i = self._new(aval)
        self.consts[i] = value
        if key is not None:
            self._const_ids[key] = i
        return i

    def _inline(self, jaxpr, consts, ins):
        # Custom-derivative calls inlined too: the recurrences need the primal only.
        return interpreter.evaluate(
            jaxpr,
            consts,
            ins,
            lambda eqn, args: self._emit(eqn.primitive, args, eqn.params, eqn.outvars),
            const=self._const,
            custom=True,
        )

    def _is_series(self, name, args, outvars):
        if not any(a in self.series for a in args):
            return False
        if name in _PIECEWISE_CONSTANT:
            return False
        if name == "integer_pow":
            return True
        # (Any floating output: a primitive whose float outputs depend on the state
        # is a series even beside integer or boolean outputs, never a constant.)
        return any(jnp.issubdtype(v.aval.dtype, jnp.inexact) for v in outvars)

    def _add(self, kind, prim, args, params, out_avals, series):
        try:
            key = (kind, tuple(args), tuple(sorted(params.items())))
            hash(key)
        except TypeError:
            key = None
        if key is not None and key in self._cse:
            return self._cse[key]
        outs = [self._new(a) for a in out_avals]
        self.nodes.append(_Node(kind, prim, tuple(args), tuple(outs), params, series))
        if series:
            self.series.update(outs)
        if key is not None:
            self._cse[key] = outs
        return outs

    def _emit(self, prim, args, params, outvars):
        name = prim.name
        avals = [v.aval for v in outvars]
        series = self._is_series(name, args, outvars)
        if not series:
            return self._add(name, prim, args, params, avals, False)
        if name not in _LINEAR | _BILINEAR | _NONLINEAR:
            raise NotImplementedError(
                f"Taylor coefficients: no recurrence for the primitive `{name}` "
                f"(in an equation of the acceleration that depends on the state). "
                f"Supported: {', '.join(_supported())}."
            )
        if name in _ELEMENTWISE:
            # Jaxprs broadcast implicitly in elementwise ops (`mul u:f64[2] w:f64[]`,
            # `mul a:f64[2,1,2] b:f64[1,1,2]`); the recurrences want equal shapes.
            args = [self._broadcast(a, avals[0]) for a in args]
        if name in ("sin", "cos"):
            s, c = self._add("sincos", None, args, {}, avals * 2, True)
            return [s if name == "sin" else c]
        if name in ("sinh", "cosh"):
            s, c = self._add("sinhcosh", None, args, {}, avals * 2, True)
            return [s if name == "sinh" else c]
        if name == "square":
            return self._mul([args[0]] * 2, avals, True)
        if name == "integer_pow":
            return [self._integer_pow(args[0], params["y"], avals[0])]
        if name == "exp2":
            ln2 = self._const(np.log(2.0).astype(avals[0].dtype), _scalar(avals[0]))
            if avals[0].shape:
                ln2 = self._add(
                    "broadcast_in_dim",
                    lax.broadcast_in_dim_p,
                    [ln2],
                    dict(shape=avals[0].shape, broadcast_dimensions=(), sharding=None),
                    avals,
                    False,
                )[0]
            (u,) = self._mul([args[0], ln2], avals, True)
            return self._add("exp", lax.exp_p, [u], {}, avals, True)
        if name == "pow":
            u, w = args
            if w in self.series:
                # u**w = exp(w log u): a series exponent is rare (no dedicated rule).
                (lu,) = self._add("log", lax.log_p, [u], {}, avals, u in self.series)
                (e,) = self._mul([w, lu], avals, True)
                return self._add("exp", lax.exp_p, [e], {}, avals, True)
        return self._add(name, prim, args, params, avals, True)

    def _mul(self, args, avals, series):
        """`_add` of a product, with the parameters JAX binds `mul` with."""
        return self._add(
            "mul", lax.mul_p, args, interpreter.mul_params(), avals, series
        )

    def _broadcast(self, a, aval):
        shape = self.avals[a].shape
        if shape == aval.shape:
            return a
        out = jax.core.ShapedArray(aval.shape, self.avals[a].dtype)
        dims = tuple(range(len(aval.shape) - len(shape), len(aval.shape)))
        params = dict(shape=aval.shape, broadcast_dimensions=dims, sharding=None)
        prim = lax.broadcast_in_dim_p
        series = a in self.series
        return self._add("broadcast_in_dim", prim, [a], params, [out], series)[0]

    def _integer_pow(self, u, n, aval):
        if n == 0:
            return self._add(
                "integer_pow", lax.integer_pow_p, [u], dict(y=0), [aval], False
            )[0]
        if n < 0:
            one = self._const(np.ones(aval.shape, aval.dtype), aval)
            p = self._integer_pow(u, -n, aval)
            return self._add("div", lax.div_p, [one, p], {}, [aval], True)[0]
        # Binary powering with products of series: u**n needs no division by u_0
        # (the power rule's would be 0/0 at u_0 = 0, e.g. x**3 at x = 0).
        result, base = None, u
        while True:
            if n & 1:
                result = (
                    base
                    if result is None
                    else self._mul([result, base], [aval], True)[0]
                )
            n >>= 1
            if not n:
                return result
            base = self._mul([base, base], [aval], True)[0]

    def transcendental_reads(self) -> int:
        """How many outputs of transcendental series nodes (a sine–cosine pair counts
        its two) other nodes read."""
        outs = {o for n in self.nodes if n.kind in _TRANSCENDENTAL for o in n.outs}
        return len({i for n in self.nodes for i in n.ins if i in outs})

    def _prune(self, outs=None):
        """Drops equations the output (or `outs`) does not depend on."""
        live = {self.out} if outs is None else set(outs)
        kept = []
        for node in reversed(self.nodes):
            if any(o in live for o in node.outs):
                kept.append(node)
                live.update(node.ins)
        self.nodes = kept[::-1]


# Series nodes whose value costs a libm call per lane (`transcendental_reads`).
_TRANSCENDENTAL = frozenset(
    {"sincos", "sinhcosh", "exp", "exp2", "expm1", "log", "log1p", "tan", "tanh"}
    | {"atan", "logistic", "pow", "sqrt", "rsqrt", "cbrt"}
)


def _scalar(aval):
    return jax.core.ShapedArray((), aval.dtype)


class _Order0:
    """Every variable at order 0: the jaxpr evaluated on the lanes' values."""

    def __init__(self, prog, s, x, v, leaves, trig=False):
        self._evaluate(prog, x.shape[0], zip((0, 1, 2), (s, x, v)), leaves, trig)

    def _evaluate(self, prog, W, inputs, leaves, trig):
        """`inputs`: `(id, lanes' values)` pairs; `leaves`: the parameters' values."""
        self.prog = prog
        self.W = W
        self.val = {}  # order-0 value of every id
        self.bat = {}  # whether that value has the lane axis
        self.cache = {}  # order-0 quantities the recurrences reuse (masks, 1/u_0)
        self.fns = {}
        for i, c in prog.consts.items():
            self.val[i], self.bat[i] = c, False
        for i, a in inputs:
            self.val[i], self.bat[i] = a, True
        for i, a in zip(prog.params, leaves):
            self.val[i], self.bat[i] = a, True
        for node in prog.nodes:
            vals = [self.val[i] for i in node.ins]
            batched = [self.bat[i] for i in node.ins]
            outs = self._node(node, vals, batched, trig)
            for o, value in zip(node.outs, outs):
                self.val[o] = value
                self.bat[o] = any(batched)

    def _node(self, node, vals, batched, trig):
        """The order-0 outputs of one node."""
        if node.kind == "sincos":
            if trig and vals[0].dtype == jnp.float64:
                return list(_trig.sincos(vals[0]))
            return [jnp.sin(vals[0]), jnp.cos(vals[0])]
        if node.kind == "sinhcosh":
            return [jnp.sinh(vals[0]), jnp.cosh(vals[0])]
        return _bind(node.prim, node.params, vals, batched)

    def lanes(self, i):
        """The order-0 value of `i` with the lane axis, `(W, *shape)`."""
        value = self.val[i]
        if self.bat[i]:
            return value
        shape = (self.W,) + tuple(self.prog.avals[i].shape)
        return jnp.broadcast_to(value, shape)

    def const(self, i):
        """A constant operand, shaped to combine with `(W, *shape)` coefficients."""
        value = self.val[i]
        if self.bat[i] or np.ndim(value) == 0:
            return value
        return jnp.asarray(value)[None]

    def once(self, key, fn):
        """`fn()` computed once, outside the loop over orders (see `_coefficients`)."""
        if key not in self.cache:
            self.fns[key] = fn
            self.cache[key] = fn()
        return self.cache[key]


class _Store:
    r"""Coefficients of the series inside one iteration $k$ of the loop over orders.

    Every stored series (a variable or an auxiliary series of a recurrence, e.g.
    $j u_j$) is a loop-carried array `F[j]` $= u_j$ of shape `(K + 1, W, ...)`, zero
    above the orders computed so far. The Cauchy sum at order $k$ is one fixed-shape
    product with a window of the reversed, zero-padded copy $R$ (`R[K - j]` $= u_j$),

    $$\sum_{j=0}^{K} F_a[j]\, R_b[K - k + j] = \sum_{j=0}^{k} a_j b_{k-j}.$$

    ($R$ is rebuilt per sum: carrying it too made XLA copy every carried array twice
    per order.) Each recurrence below relies on the slot of its own output at order $k$
    still being zero when it forms its sums, which drops the $j = 0$ (or $j = k$) term
    that holds the unknown.
    """

    triangular = False  # Cauchy sums over full-length windows

    def __init__(self, zero, K, k, carry, lanes, record):
        self.zero = zero  # order-0 data
        self.K = K
        self.k = k  # traced int
        self.carry = carry  # handle -> (F, R)
        self.lanes = lanes  # handle -> order-0 value (lane axis), for new handles
        self.record = record  # None, or the set of handles asked for (dry run)
        self.cur = {}  # handle -> k-th coefficient, computed this iteration
        self.kf = k.astype(zero.prog.avals[1].dtype)

    def _arrays(self, h):
        if h not in self.carry:
            if self.record is None:
                raise AssertionError(h)  # pragma: no cover - the dry run saw it
            self.record.add(h)
            self.carry[h] = _initial(self.K, self.lanes[h]())
        return self.carry[h]

    def aux(self, key, init0):
        """Declares an auxiliary series with order-0 coefficient `init0()`."""
        self.lanes.setdefault(key, init0)
        return key

    def get(self, h):
        """The k-th coefficient of `h`, or None when it is exactly zero (a constant)."""
        if h in self.cur:
            return self.cur[h]
        if isinstance(h, int) and h not in self.zero.prog.series:
            return None
        F, _ = self._arrays(h)
        return lax.dynamic_index_in_dim(F, self.k, 0, keepdims=False)

    def put(self, h, value):
        self.cur[h] = value
        if h in self.carry and value is not None:
            F, R = self.carry[h]
            F = lax.dynamic_update_index_in_dim(F, value, self.k, 0)
            self.carry[h] = (F, R)

    def conv(self, a, b):
        r"""$\sum_{j=0}^{k} a_j b_{k-j}$ over the coefficients stored so far."""
        Fa, _ = self._arrays(a)
        return jnp.sum(Fa * self.window(b), axis=0)

    def window(self, b):
        Fb, _ = self._arrays(b)
        pad = jnp.zeros((self.K,) + Fb.shape[1:], Fb.dtype)
        Rb = jnp.concatenate([Fb[::-1], pad])
        return lax.dynamic_slice_in_dim(Rb, self.K - self.k, self.K + 1, 0)


class _Unrolled(_Store):
    r"""The `_Store` interface (`aux` inherited) with the order $k$ a Python int:
    every series is a list of per-order `(W, ...)` arrays (`None` for an exact zero)
    and every Cauchy sum is exactly triangular, $\sum_{j=0}^{k} a_j b_{k-j}$ over the
    orders computed so far.

    All orders of one step then trace into one straight-line program that XLA fuses
    into a few loops over the lanes, with nothing stored between orders, when it
    reaches XLA as one output: with the K + 1 coefficients as separate outputs, XLA
    recomputes the whole program once per output. The period kernel therefore
    passes the step's outputs through one variadic reduction (`fusion.one_fusion`).
    """

    triangular = True  # exactly triangular sums, `pairs` below

    def __init__(self, zero, lanes, coef):
        self.zero = zero
        self.lanes = lanes  # handle -> order-0 value (lane axis)
        self.coef = coef  # handle -> list of coefficients, orders 0..k
        self.cur = {}
        self.k = 0
        self.kf = 0.0

    def _list(self, h):
        if h not in self.coef:
            self.coef[h] = [self.lanes[h]()]
        return self.coef[h]

    def get(self, h):
        if h in self.cur:
            return self.cur[h]
        if isinstance(h, int) and h not in self.zero.prog.series:
            return None
        lst = self._list(h)
        return lst[self.k] if self.k < len(lst) else None

    def put(self, h, value):
        self.cur[h] = value
        lst = self._list(h)
        lst.extend([None] * (self.k + 1 - len(lst)))
        lst[self.k] = value

    def pairs(self, a, b, prod):
        """sum_{j=0}^{k} prod(a_j, b_{k-j}) over the known, non-zero coefficients."""
        A, B = self._list(a), self._list(b)
        out = None
        for j in range(self.k + 1):
            if j < len(A) and self.k - j < len(B):
                aj, bj = A[j], B[self.k - j]
                if aj is not None and bj is not None:
                    out = _add(out, prod(aj, bj))
        if out is None:
            out = jnp.zeros_like(prod(self.lanes[a](), self.lanes[b]()))
        return out

    def conv(self, a, b):
        return self.pairs(a, b, lambda u, w: u * w)


def _unrolled_coefficients(prog, K, s, x, v, leaves, trig=False):
    """As `_coefficients`, orders unrolled: lists `xs`, `vs` (K + 1 arrays each) and
    `as_` (K arrays), each coefficient a `(W,)` array."""
    zero = _Order0(prog, s, x, v, leaves, trig)
    W = x.shape[0]
    dtype = x.dtype
    a0 = zero.lanes(prog.out) if prog.out in zero.val else jnp.zeros_like(x)
    a0 = jnp.broadcast_to(a0, (W,)).astype(dtype)
    xs, vs, as_ = [x, v], [v, a0], [a0]
    lanes = {h: (lambda h=h: zero.lanes(h)) for h in prog.series if h in zero.val}
    st = _Unrolled(zero, lanes, {0: [s, jnp.ones_like(x)], 1: xs, 2: vs})
    for k in range(1, K):
        st.k, st.kf, st.cur = k, float(k), {}
        st.cur = {0: st.get(0), 1: xs[k], 2: vs[k]}
        _order_k(st, prog)
        a = st.cur.get(prog.out) if prog.out in prog.series else None
        a = jnp.zeros_like(x) if a is None else jnp.broadcast_to(a, (W,)).astype(dtype)
        as_.append(a)
        xs.append(vs[k] / (k + 1))
        vs.append(a / (k + 1))
    return xs, vs, as_


def _initial(K, value0):
    F = jnp.zeros((K + 1,) + value0.shape, value0.dtype).at[0].set(value0)
    return F, None


def _coefficients(prog, K, s, x, v, leaves, trig=False):
    """`(xs, vs, as_)` for all lanes: order 0 by plain evaluation, orders 1..K-1 in
    a `fori_loop` whose body runs only the series nodes."""
    zero = _Order0(prog, s, x, v, leaves, trig)
    W = x.shape[0]
    dtype = x.dtype
    a0 = zero.lanes(prog.out) if prog.out in zero.val else jnp.zeros_like(x)
    a0 = jnp.broadcast_to(a0, (W,)).astype(dtype)
    # Stored from the start: x with x_1 = v_0, v with v_1 = a_0, s with s_1 = 1.
    xs = jnp.zeros((K + 1, W), dtype).at[0].set(x).at[1].set(v)
    vs = jnp.zeros((K + 1, W), dtype).at[0].set(v).at[1].set(a0)
    as_ = jnp.zeros((K, W), dtype).at[0].set(a0)
    if K == 1:
        return xs, vs, as_
    rev = lambda F: None
    ss = jnp.zeros((K + 1, W), dtype).at[0].set(s).at[1].set(1.0)
    # Order-0 coefficient of every handle a recurrence may store; the recurrences
    # add their auxiliary series here.
    lanes = {h: (lambda h=h: zero.lanes(h)) for h in prog.series if h in zero.val}

    def body(k, carry, record=None):
        store, as_ = carry
        st = _Store(zero, K, k, dict(store), lanes, record)
        st.cur[0] = jnp.broadcast_to(jnp.where(k == 1, 1.0, 0.0).astype(dtype), (W,))
        st.cur[1] = st.get(1)
        st.cur[2] = st.get(2)
        _order_k(st, prog)
        a = st.cur.get(prog.out) if prog.out in prog.series else None
        a = jnp.zeros_like(x) if a is None else jnp.broadcast_to(a, (W,)).astype(dtype)
        as_ = lax.dynamic_update_index_in_dim(as_, a, k, 0)
        # x_{k+1} = v_k/(k+1), v_{k+1} = a_k/(k+1), stored for the next order.
        vk = st.cur[2]
        st.k, st.kf = k + 1, st.kf + 1.0
        st.cur.pop(1), st.cur.pop(2)
        st.put(1, vk / st.kf)
        st.put(2, a / st.kf)
        return {h: st.carry[h] for h in store}, as_

    # A dry run, shapes only, finds which series the recurrences read back (those get
    # loop-carried arrays) and which order-0 quantities they reuse; both are then
    # computed here, outside the loop.
    fixed = {0: (ss, rev(ss)), 1: (xs, rev(xs)), 2: (vs, rev(vs))}
    record = set()
    jax.eval_shape(lambda k, a: body(k, (dict(fixed), a), record), 1, as_)
    zero.cache = {key: fn() for key, fn in zero.fns.items()}
    store = dict(fixed)
    for h in record:
        if h not in store:
            store[h] = _initial(K, lanes[h]())
    # Handles mix ints and tuples, which a pytree dict cannot sort: carry a list.
    handles = list(store)

    def listed(k, carry):
        arrays, as_ = carry
        store, as_ = body(k, (dict(zip(handles, arrays)), as_))
        return [store[h] for h in handles], as_

    arrays, as_ = lax.fori_loop(1, K, listed, ([store[h] for h in handles], as_))
    store = dict(zip(handles, arrays))
    return store[1][0], store[2][0], as_


# --- entry point --------------------------------------------------------------------


def _traced(accel, dtype, leaves, treedef):
    """`accel`'s closed jaxpr at scalar `s, x, v` and one lane of the per-lane
    parameters `leaves` (lane axis first)."""

    def flat(s, x, v, *leaves):
        return accel(s, x, v, *treedef.unflatten(leaves))

    scalar = jax.ShapeDtypeStruct((), dtype)
    specs = [jax.ShapeDtypeStruct(jnp.shape(x)[1:], x.dtype) for x in leaves]
    with fusion_off():  # (an identity for XLA; no recurrence rule for it)
        return jax.make_jaxpr(flat)(scalar, scalar, scalar, *specs)


def transcendental_reads(accel: Callable, dtype, p) -> int:
    """`_Program.transcendental_reads` of `accel(s, x, v, p)` (as `taylor_coefficients`
    calls it, `p` with a lane axis first): traced, nothing evaluated."""
    leaves, treedef = jax.tree.flatten((p,))
    closed = _traced(accel, jnp.dtype(dtype), leaves, treedef)
    return _Program(closed, len(leaves)).transcendental_reads()


# The straight-line program's size beyond which `unrolled=True` falls back to the loop
# over orders: XLA duplicates the program into each fusion that consumes it, so its
# compile time grows much faster than its size. At order 20 with L's constants as
# arguments: the pendulum's ~1,200 equations; two-term potentials (cos q + q^4,
# q^2 + q^4 + q^6, cos q + cos 2q) ~2,000-2,150, which compile in seconds and step
# several times faster than the fallback (benchmarks/README.md); a position-dependent
# mass ~3,200 and the θ-form cycloid ~6,000 do not compile in reasonable time.
_UNROLL_BUDGET = 2500


def taylor_coefficients(
    accel: Callable,
    order: int,
    dtype,
    unrolled: bool = False,
    vectorized_trig: bool = False,
) -> Callable:
    r"""Normalized Taylor coefficients of the solution of $x' = v$, $v' = a(s, x, v)$.

    About the point $(s, x, v)$ of every lane,

    $$x(s + h) = \sum_{k=0}^{K} x_k h^k,\quad v(s + h) = \sum_{k=0}^{K} v_k h^k,\quad
    a(s + h) = \sum_{k=0}^{K-1} a_k h^k,$$

    with $x_0 = x$, $v_0 = v$, $x_{k+1} = v_k/(k+1)$, $v_{k+1} = a_k/(k+1)$ and $a_k$
    the $k$-th coefficient of $a(s + h, x(s + h), v(s + h))$, computed by recurrence
    from the jaxpr of `accel` (see the module docstring).

    **Arguments:**

    - `accel`: the acceleration, a JAX function of scalars, `accel(s, x, v)` or
        `accel(s, x, v, p)` with `p` a pytree of per-lane parameters. Traced once per
        call of the returned function with `jax.make_jaxpr` at scalar `s, x, v` and
        each leaf of `p` without its lane axis. Values it closes over (including
        tracers of an enclosing `jit`) become constants of the jaxpr: order 0 only.
    - `order`: $K \geq 1$, the degree of the polynomials in $x$ and $v$.
    - `dtype`: the floating dtype of `s, x, v`.
    - `unrolled`: return Python lists of per-order `(W,)` arrays computed by a
        straight-line program (for a kernel that evaluates the polynomials in the
        same program: see `_Unrolled`) instead of stacked arrays from a loop; a
        program of more than `_UNROLL_BUDGET` equations is computed by the loop
        anyway (the same values, stacked).
    - `vectorized_trig`: order 0's float64 sines and cosines by `sincos`
        (vectorized by XLA, within 1 ulp, NaN beyond $|x| = 2^{19}\pi/2$) instead of
        the C library's (one scalar call per element on a CPU).

    **Returns:**

    `coeffs(s, x, v, p=None) -> (xs, vs, as_)`: `s, x, v` of shape `(W,)`, every leaf
    of `p` of shape `(W, ...)` (lane axis first); `xs`, `vs` of shape `(K + 1, W)`,
    `as_` of shape `(K, W)`. `p=None` calls `accel(s, x, v)`.

    **Raises:**

    - `NotImplementedError` (when `coeffs` is called, i.e. traced): a primitive that
        depends on the state has no recurrence here (the message names it);
        callers fall back to a Runge–Kutta method.

    **Example:**

    ```python
    accel = lambda s, x, v, q0: -jnp.sin(q0 + x)
    coeffs = taylor_coefficients(accel, 20, jnp.float64)
    xs, vs, as_ = coeffs(s, x, v, q0)  # x(s + h) ≈ jnp.polyval(xs[::-1], h)
    ```
    """
    K = int(order)
    if K < 1:
        raise ValueError(f"`order` must be at least 1, got {order}.")
    dtype = jnp.dtype(dtype)

    def coeffs(s, x, v, p=None):
        args = () if p is None else (p,)
        leaves, treedef = jax.tree.flatten(args)
        x = jnp.asarray(x, dtype)
        W = x.shape[0]
        s = jnp.broadcast_to(jnp.asarray(s, dtype), (W,))
        v = jnp.broadcast_to(jnp.asarray(v, dtype), (W,))
        leaves = [jnp.asarray(leaf) for leaf in leaves]
        for leaf in leaves:
            if leaf.ndim < 1 or leaf.shape[0] != W:
                raise ValueError(
                    "every leaf of the per-lane parameters `p` must have the lane "
                    f"axis first, of length {W}; got shape {leaf.shape}."
                )

        closed = _traced(accel, dtype, leaves, treedef)
        out = closed.out_avals
        if len(out) != 1 or out[0].shape != ():
            raise TypeError(
                f"`accel` must return a scalar; it returned {out} at scalar inputs."
            )
        prog = _Program(closed, len(leaves))
        if unrolled:
            # Traced once: counted against the budget, then called as it is (a
            # `jit` call, which XLA inlines), sparing the caller's trace a re-bind
            # of its thousands of equations.
            build = jax.jit(
                lambda *a: _unrolled_coefficients(
                    prog, K, *a[:3], list(a[3:]), vectorized_trig
                )
            )
            traced = build.trace(s, x, v, *leaves)
            coeffs.unrolled = len(traced.jaxpr.jaxpr.eqns) <= _UNROLL_BUDGET
            if coeffs.unrolled:
                return build(s, x, v, *leaves)
        return _coefficients(prog, K, s, x, v, leaves, vectorized_trig)

    # Whether the last trace computed a straight-line program (`unrolled` and within
    # the budget) rather than the loop over orders.
    coeffs.unrolled = False
    return coeffs
