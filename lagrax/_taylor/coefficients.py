r"""Taylor coefficients of $x' = v$, $v' = a(s, x, v)$ by recurrence from a jaxpr.

A Taylor integrator (heyoka's method) advances the state by the polynomial
$x(s + h) = \sum_{k=0}^{K} x_k h^k$ whose coefficients come from the differential
equation itself: with $a(s + h) = \sum_k a_k h^k$,

$$x_{k+1} = \frac{v_k}{k + 1}, \qquad v_{k+1} = \frac{a_k}{k + 1},$$

and $a_k$ depends only on $x_0..x_k$, $v_0..v_k$. Each primitive of the acceleration's
jaxpr has a recurrence for its $k$-th normalized coefficient from the lower ones
(products are Cauchy convolutions; $\sin$ and $\cos$ come as a pair,
$s_k = \frac1k\sum_{j=1}^k j u_j c_{k-j}$, $c_k = -\frac1k\sum_{j=1}^k j u_j s_{k-j}$),
so all $K$ orders cost $O(K^2)$ multiply-adds per nonlinear node and one
transcendental call per node, for order 0. `jax.experimental.jet` called $K$ times
would redo every lower order each time: $O(K^3)$.

Why this is worth doing: on CPU, XLA's float64 `sin` is a scalar libm call (~8 ns per
element) while a multiply-add vectorizes (~0.2 ns), so an order-20 Taylor step costs
about as much as a few sines, against 13 sines for one step of an 8th-order
Runge–Kutta method.

Design, measured (`benchmarks/taylor_coefficients.py`):

- The jaxpr is traced once at scalar inputs, nested calls (`jit`, `custom_jvp_call`,
    ...) are inlined, duplicate equations merged (an autodiff jaxpr computes `sin q`
    once per tangent direction) and dead ones dropped.
- A variable is a *series* only if it depends differentiably on $(s, x, v)$. Everything
    else (tangent seeds, a constant mass matrix, per-lane parameters, comparisons) is
    evaluated once, at order 0, and multiplies series in $O(K)$. Outputs of
    zero-derivative primitives (`sign`, `floor`, comparisons, `is_finite`) and the
    branch of `select_n`, `max`, `abs` are decided on the order-0 coefficient.
- Orders 1..K-1 run in one `lax.fori_loop` over fixed-shape `(K + 1, W)` coefficient
    arrays; each Cauchy sum is a full-length product with a reversed, shifted copy
    (`_Store`), so half its multiply-adds hit zeros. Unrolling the orders in Python
    instead (exactly triangular sums, one `(W,)` array per coefficient) compiled in
    5-8 s at order 20 against ~0.6 s, and did not run faster (both measured on a
    loaded 2-core machine).
"""

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jex_core

from .._jaxpr import trig as _trig
from .._jaxpr.fusion import fusion_off
from .diffrax_solver import AbstractTaylorSolver


__all__ = ["Taylor", "taylor_coefficients"]

# Primitives whose output is locally constant (zero derivative): decided at order 0.
_PIECEWISE_CONSTANT = frozenset(
    {
        "sign",
        "floor",
        "ceil",
        "round",
        "is_finite",
        "eq",
        "ne",
        "lt",
        "le",
        "gt",
        "ge",
        "and",
        "or",
        "not",
        "xor",
        "iota",
        "argmax",
        "argmin",
        "nextafter",
    }
)

# Primitives linear in their floating-point operands (integer/bool operands, e.g.
# indices and predicates, are fixed at order 0): the k-th coefficient of the output is
# the primitive applied to the k-th coefficients, a constant float operand counting as
# zero. `stop_gradient` is the identity on values: the Taylor series of the trajectory
# does not care how a function would be differentiated.
_LINEAR = frozenset(
    {
        "add",
        "add_any",
        "sub",
        "neg",
        "convert_element_type",
        "broadcast_in_dim",
        "reshape",
        "squeeze",
        "expand_dims",
        "transpose",
        "slice",
        "concatenate",
        "stack",
        "unstack",
        "split",
        "pad",
        "rev",
        "reduce_sum",
        "cumsum",
        "select_n",
        "dynamic_slice",
        "dynamic_update_slice",
        "gather",
        "copy",
        "copy_p",
        "real",
        "stop_gradient",
        "reduce_precision",
        "optimization_barrier",
    }
)

# Primitives bilinear in their two operands: linear if one is constant.
_BILINEAR = frozenset({"mul", "dot_general"})

# Elementwise primitives whose operands may be rank-0 beside arrays.
_ELEMENTWISE = frozenset(
    {"add", "add_any", "sub", "mul", "div", "max", "min", "pow", "rem", "clamp"}
)

# Call-like primitives whose (primal) body is inlined: `_trig.CALLS`, and here the
# custom derivatives too (the recurrences need the primal only; `_trig` must keep
# them, as the kernel's derivative goes through its calls).
_CALLS = {
    **_trig.CALLS,
    "custom_jvp_call": "call_jaxpr",
    "custom_vjp_call": "call_jaxpr",
    "custom_vjp_call_jaxpr": "fun_jaxpr",
}

# Elementwise nonlinear primitives with a recurrence below (plus mul/dot_general/div).
_NONLINEAR = frozenset(
    {
        "sin",
        "cos",
        "sinh",
        "cosh",
        "tan",
        "tanh",
        "exp",
        "exp2",
        "expm1",
        "log",
        "log1p",
        "sqrt",
        "rsqrt",
        "cbrt",
        "square",
        "integer_pow",
        "pow",
        "div",
        "atan",
        "logistic",
        "abs",
        "max",
        "min",
        "clamp",
        "rem",
    }
)


def _supported():
    return sorted(_PIECEWISE_CONSTANT | _LINEAR | _BILINEAR | _NONLINEAR | set(_CALLS))


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
        self.nodes = []
        self.avals = {}
        self.consts = {}  # id -> value (unbatched)
        self.series = set()
        self._const_ids = {}
        self._cse = {}
        self._next = 0
        scalar = closed.in_avals[0]
        for _ in range(3):
            i = self._new(scalar)
            self.series.add(i)
        self.params = [self._new(a) for a in closed.in_avals[3 : 3 + n_params]]
        ins = list(range(3)) + self.params
        (self.out,) = self._inline(closed.jaxpr, closed.consts, ins)
        self._prune()

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
        env = {}
        for var, c in zip(jaxpr.constvars, consts):
            env[var] = self._const(c, var.aval)
        for var, i in zip(jaxpr.invars, ins):
            env[var] = i

        def read(a):
            if isinstance(a, jex_core.Literal):
                return self._const(a.val, a.aval)
            return env[a]

        for eqn in jaxpr.eqns:
            args = [read(a) for a in eqn.invars]
            name = eqn.primitive.name
            if name in _CALLS and _CALLS[name] in eqn.params:
                sub = eqn.params[_CALLS[name]]
                if isinstance(sub, jex_core.ClosedJaxpr):
                    sub_jaxpr, sub_consts = sub.jaxpr, sub.consts
                else:
                    sub_jaxpr, sub_consts = sub, ()
                n_args = len(sub_jaxpr.invars)
                outs = self._inline(sub_jaxpr, sub_consts, args[len(args) - n_args :])
            else:
                outs = self._emit(eqn.primitive, args, eqn.params, eqn.outvars)
            for var, o in zip(eqn.outvars, outs):
                env[var] = o
        return [read(a) for a in jaxpr.outvars]

    def _is_series(self, name, args, outvars):
        if not any(a in self.series for a in args):
            return False
        if name in _PIECEWISE_CONSTANT:
            return False
        if name == "integer_pow":
            return True
        return all(jnp.issubdtype(v.aval.dtype, jnp.inexact) for v in outvars)

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
            return self._add("mul", lax.mul_p, [args[0]] * 2, {}, avals, True)
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
            (u,) = self._add("mul", lax.mul_p, [args[0], ln2], {}, avals, True)
            return self._add("exp", lax.exp_p, [u], {}, avals, True)
        if name == "pow":
            u, w = args
            if w in self.series:
                # u**w = exp(w log u): a series exponent is rare (no dedicated rule).
                (lu,) = self._add("log", lax.log_p, [u], {}, avals, u in self.series)
                (e,) = self._add("mul", lax.mul_p, [w, lu], {}, avals, True)
                return self._add("exp", lax.exp_p, [e], {}, avals, True)
        return self._add(name, prim, args, params, avals, True)

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
                    else self._add("mul", lax.mul_p, [result, base], {}, [aval], True)[
                        0
                    ]
                )
            n >>= 1
            if not n:
                return result
            base = self._add("mul", lax.mul_p, [base, base], {}, [aval], True)[0]

    def _prune(self):
        """Drops equations the output does not depend on."""
        live = {self.out}
        kept = []
        for node in reversed(self.nodes):
            if any(o in live for o in node.outs):
                kept.append(node)
                live.update(node.ins)
        self.nodes = kept[::-1]


def _scalar(aval):
    return jax.core.ShapedArray((), aval.dtype)


# --- evaluation --------------------------------------------------------------------


def _bind(prim, params, vals, batched):
    """`prim.bind` with lane-batched operands (axis 0) vmapped."""
    if not any(batched):
        out = prim.bind(*vals, **params)
    else:
        axes = [0 if b else None for b in batched]
        out = jax.vmap(lambda *a: prim.bind(*a, **params), in_axes=axes)(*vals)
    return list(out) if prim.multiple_results else [out]


def _add(x, y):
    if x is None:
        return y
    if y is None:
        return x
    return x + y


def _neg(x):
    return None if x is None else -x


def _times(x, c):
    return None if x is None else x * c


class _Order0:
    """Every variable at order 0: the jaxpr evaluated on the lanes' values."""

    def __init__(self, prog, s, x, v, leaves, trig=False):
        self.prog = prog
        self.W = x.shape[0]
        self.val = {}  # order-0 value of every id
        self.bat = {}  # whether that value has the lane axis
        self.cache = {}  # order-0 quantities the recurrences reuse (masks, 1/u_0)
        self.fns = {}
        for i, c in prog.consts.items():
            self.val[i], self.bat[i] = c, False
        for i, a in zip((0, 1, 2), (s, x, v)):
            self.val[i], self.bat[i] = a, True
        for i, a in zip(prog.params, leaves):
            self.val[i], self.bat[i] = a, True
        for node in prog.nodes:
            vals = [self.val[i] for i in node.ins]
            batched = [self.bat[i] for i in node.ins]
            if node.kind == "sincos":
                if trig and vals[0].dtype == jnp.float64:
                    outs = list(_trig.sincos(vals[0]))
                else:
                    outs = [jnp.sin(vals[0]), jnp.cos(vals[0])]
            elif node.kind == "sinhcosh":
                outs = [jnp.sinh(vals[0]), jnp.cosh(vals[0])]
            else:
                outs = _bind(node.prim, node.params, vals, batched)
            for o, value in zip(node.outs, outs):
                self.val[o] = value
                self.bat[o] = any(batched)

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
    into a few loops over the lanes, with nothing stored between orders. Measured on
    the pendulum at order 20, 4096 lanes, one core: ~48 ns per lane for all orders
    and the polynomial's evaluation when they reach XLA as ONE output (against
    ~1.3 µs for the `fori_loop` over `(K + 1, W)` arrays); stacking the K + 1
    coefficients as outputs instead makes XLA recompute the whole program once per
    output (~300 ns, 36 sines); the period kernel therefore passes the step's
    outputs through one variadic reduction (`lagrax._jaxpr.fusion.one_fusion`).
    """

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


# --- recurrences: the k-th coefficient (k >= 1, traced) of each series node ---------


def _linear(st, node):
    if node.kind in _BILINEAR:
        return _bilinear(st, node)
    zero, prog = st.zero, st.zero.prog
    cs = [st.get(i) if i in prog.series else None for i in node.ins]
    kind = node.kind
    # Shape-preserving arithmetic directly (no vmap, no additions of zeros).
    if kind in ("add", "add_any", "sub") and len(cs) == 2:
        return [_add(cs[0], _neg(cs[1]) if kind == "sub" else cs[1])]
    if kind == "neg":
        return [_neg(cs[0])]
    if all(c is None for i, c in zip(node.ins, cs) if i in prog.series):
        return [None] * len(node.outs)
    vals, batched = [], []
    for i, c in zip(node.ins, cs):
        aval = prog.avals[i]
        if i in prog.series:
            shape = (zero.W,) + tuple(aval.shape)
            vals.append(jnp.zeros(shape, aval.dtype) if c is None else c)
            batched.append(True)
        elif jnp.issubdtype(aval.dtype, jnp.inexact):
            # A constant float operand has no k-th coefficient.
            vals.append(jnp.zeros(aval.shape, aval.dtype))
            batched.append(False)
        else:  # indices, predicates: fixed at order 0
            vals.append(zero.val[i])
            batched.append(zero.bat[i])
    return _bind(node.prim, node.params, vals, batched)


def _bilinear(st, node):
    u, w = node.ins
    series = st.zero.prog.series
    if u in series and w in series:
        if node.kind == "mul":
            return [st.conv(u, w)]
        if isinstance(st, _Unrolled):
            return [
                st.pairs(
                    u,
                    w,
                    lambda a, b: _bind(node.prim, node.params, [a, b], [True, True])[0],
                )
            ]
        # sum_j dot(u_j, w_{k-j}): the K + 1 terms as one batched dot_general.
        Fu, _ = st._arrays(u)
        Ww = st.window(w)
        lead = Fu.shape[:2]
        flat = lambda a: a.reshape((-1,) + a.shape[2:])
        out = _bind(node.prim, node.params, [flat(Fu), flat(Ww)], [True, True])[0]
        return [jnp.sum(out.reshape(lead + out.shape[1:]), axis=0)]
    c = st.get(u if u in series else w)
    if c is None:
        return [None]
    if node.kind == "mul":
        return [c * st.zero.const(w if u in series else u)]
    zero = st.zero
    vals = [c, zero.val[w]] if u in series else [zero.val[u], c]
    batched = [True, zero.bat[w]] if u in series else [zero.bat[u], True]
    return _bind(node.prim, node.params, vals, batched)


def _weighted(st, node, u):
    r"""The auxiliary series $j u_j$ (zero at $j = 0$), extended to order k."""
    ju = st.aux((node.outs[0], "ju"), lambda: jnp.zeros_like(st.zero.lanes(u)))
    uk = st.get(u)
    st.put(ju, jnp.zeros_like(st.zero.lanes(u)) if uk is None else uk * st.kf)
    return ju


def _inverse0(st, node, value0):
    """`1 / value0()` once per node, outside the loop: a division is ~10 multiply-adds,
    and the reciprocal serves every order."""
    return st.zero.once((node.outs[0], "inv"), lambda: 1.0 / value0())


def _sincos(st, node):
    r"""$s_k = \frac1k\sum_{j=1}^k j u_j c_{k-j}$, $c_k = \mp\frac1k\sum_{j=1}^k j u_j
    s_{k-j}$ ($-$ for sin/cos, $+$ for sinh/cosh)."""
    (u,) = node.ins
    s, c = node.outs
    ju = _weighted(st, node, u)
    sign = -1.0 if node.kind == "sincos" else 1.0
    inv_k = 1.0 / st.kf
    return [st.conv(ju, c) * inv_k, st.conv(ju, s) * (sign * inv_k)]


def _exp(st, node):
    r"""$c_k = \frac1k\sum_{j=1}^k j u_j c_{k-j}$; for `expm1` the order-0 term of
    $e^u = c + 1$ adds $j u_j$ at $j = k$."""
    (u,) = node.ins
    ju = _weighted(st, node, u)
    total = st.conv(ju, node.outs[0])
    if node.kind == "expm1":
        total = total + st.get(ju)
    return [total / st.kf]


def _log(st, node):
    r"""$c_k = \bigl(u_k - \frac1k\sum_{j=1}^{k-1} j c_j u_{k-j}\bigr) / u_0$."""
    (u,) = node.ins
    (c,) = node.outs
    shift = 1.0 if node.kind == "log1p" else 0.0
    inv = _inverse0(st, node, lambda: st.zero.lanes(u) + shift)
    jc = st.aux((c, "jc"), lambda: jnp.zeros_like(st.zero.lanes(u)))
    ck = (st.get(u) - st.conv(jc, u) / st.kf) * inv
    st.put(jc, ck * st.kf)
    return [ck]


def _sqrt(st, node):
    r"""$c_k = \bigl(u_k - \sum_{j=1}^{k-1} c_j c_{k-j}\bigr) / (2 c_0)$."""
    (u,) = node.ins
    (c,) = node.outs
    inv = _inverse0(st, node, lambda: 2.0 * st.zero.lanes(c))
    return [(st.get(u) - st.conv(c, c)) * inv]


def _power(st, node, a):
    r"""$c = u^a$: from $u c' = a u' c$,
    $c_k = \frac{1}{u_0}\Bigl(\frac{a+1}{k}\sum_{j=1}^k j u_j c_{k-j}
    - \sum_{j=1}^k u_j c_{k-j}\Bigr)$."""
    u = node.ins[0]
    (c,) = node.outs
    inv = _inverse0(st, node, lambda: st.zero.lanes(u))
    ju = _weighted(st, node, u)
    total = st.conv(ju, c) * ((a + 1.0) / st.kf) - st.conv(u, c)
    return [total * inv]


def _pow(st, node):
    return _power(st, node, st.zero.const(node.ins[1]))


def _named_power(a):
    return lambda st, node: _power(st, node, a)


def _div(st, node):
    r"""$c_k = \bigl(u_k - \sum_{j=1}^k w_j c_{k-j}\bigr) / w_0$."""
    u, w = node.ins
    series = st.zero.prog.series
    uk = st.get(u) if u in series else None
    if w not in series:
        inv = _inverse0(st, node, lambda: st.zero.const(w))
        return [_times(uk, inv)]
    inv = _inverse0(st, node, lambda: st.zero.lanes(w))
    return [_add(uk, -st.conv(w, node.outs[0])) * inv]


def _tan(st, node):
    r"""$t' = (1 \pm t^2) u'$: with the auxiliary series $w = 1 \pm t^2$,
    $t_k = \frac1k\sum_{j=1}^k j u_j w_{k-j}$, then $w_k = \pm\sum_j t_j t_{k-j}$."""
    (u,) = node.ins
    (t,) = node.outs
    sign = 1.0 if node.kind == "tan" else -1.0
    t0 = lambda: st.zero.lanes(t)
    w = st.aux((t, "w"), lambda: 1.0 + sign * t0() * t0())
    ju = _weighted(st, node, u)
    tk = st.conv(ju, w) / st.kf
    st.put(t, tk)
    st.put(w, sign * st.conv(t, t))
    return [tk]


def _logistic(st, node):
    r"""$\sigma' = (\sigma - \sigma^2) u'$, as `tan` with $w = \sigma - \sigma^2$."""
    (u,) = node.ins
    (c,) = node.outs
    c0 = lambda: st.zero.lanes(c)
    w = st.aux((c, "w"), lambda: c0() - c0() * c0())
    ju = _weighted(st, node, u)
    ck = st.conv(ju, w) / st.kf
    st.put(c, ck)
    st.put(w, ck - st.conv(c, c))
    return [ck]


def _atan(st, node):
    r"""$(1 + u^2) c' = u'$: with $w = 1 + u^2$,
    $c_k = \bigl(u_k - \frac1k\sum_{j=1}^{k-1} w_j (k-j) c_{k-j}\bigr) / w_0$."""
    (u,) = node.ins
    (c,) = node.outs
    u0 = lambda: st.zero.lanes(u)
    w = st.aux((c, "w"), lambda: 1.0 + u0() * u0())
    st.put(w, st.conv(u, u))
    inv = _inverse0(st, node, lambda: 1.0 + u0() * u0())
    jc = st.aux((c, "jc"), lambda: jnp.zeros_like(u0()))
    ck = (st.get(u) - st.conv(w, jc) / st.kf) * inv
    st.put(jc, ck * st.kf)
    return [ck]


def _mask(st, node, key, fn):
    """A boolean decided on the order-0 coefficients, computed once per node."""
    return st.zero.once((node.outs[0], key), fn)


def _pick(st, mask, a_id, b_id, negate=False):
    a, b = st.get(a_id), st.get(b_id)
    b = _neg(b) if negate else b
    if a is None and b is None:
        return None
    a = jnp.zeros_like(b) if a is None else a
    b = jnp.zeros_like(a) if b is None else b
    a, b = jnp.broadcast_arrays(a, b)
    return jnp.where(mask, a, b)


def _maxmin(st, node):
    u, w = node.ins
    op = jnp.greater_equal if node.kind == "max" else jnp.less_equal
    lanes = st.zero.lanes
    mask = _mask(st, node, "mask", lambda: op(lanes(u), lanes(w)))
    return [_pick(st, mask, u, w)]


def _abs(st, node):
    (u,) = node.ins
    mask = _mask(st, node, "mask", lambda: st.zero.lanes(u) >= 0)
    return [_pick(st, mask, u, u, negate=True)]


def _clamp(st, node):
    lo, x, hi = node.ins
    lanes = st.zero.lanes
    below = _mask(st, node, "below", lambda: lanes(x) < lanes(lo))
    above = _mask(st, node, "above", lambda: lanes(x) > lanes(hi))
    inner = _pick(st, above, hi, x)
    outer = st.get(lo)
    if inner is None and outer is None:
        return [None]
    inner = jnp.zeros_like(outer) if inner is None else inner
    outer = jnp.zeros_like(inner) if outer is None else outer
    inner, outer = jnp.broadcast_arrays(inner, outer)
    return [jnp.where(below, outer, inner)]


def _rem(st, node):
    u, w = node.ins
    if w in st.zero.prog.series:
        raise NotImplementedError(
            "Taylor coefficients: `rem` with a divisor that depends on the state."
        )
    return [st.get(u)]


_RULES = {
    "sincos": _sincos,
    "sinhcosh": _sincos,
    "exp": _exp,
    "expm1": _exp,
    "log": _log,
    "log1p": _log,
    "sqrt": _sqrt,
    "rsqrt": _named_power(-0.5),
    "cbrt": _named_power(1.0 / 3.0),
    "pow": _pow,
    "div": _div,
    "tan": _tan,
    "tanh": _tan,
    "logistic": _logistic,
    "atan": _atan,
    "max": _maxmin,
    "min": _maxmin,
    "abs": _abs,
    "clamp": _clamp,
    "rem": _rem,
}


def _order_k(st, prog):
    """Runs every series node at the store's order k (inputs already put)."""
    for node in prog.nodes:
        if node.series:
            outs = _RULES.get(node.kind, _linear)(st, node)
            for o, c in zip(node.outs, outs):
                st.put(o, c)


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


# The straight-line program's size beyond which `unrolled=True` falls back to the loop
# over orders. Measured (1 core): the pendulum's order-20 program has 942 equations
# and compiles with the kernel in ~4 s; the θ-form cycloid's has 5028 and the kernel
# had not compiled after 300 s (XLA duplicates it into each consumer fusion).
_UNROLL_BUDGET = 2000


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

        def flat(s, x, v, *leaves):
            return accel(s, x, v, *treedef.unflatten(leaves))

        scalar = jax.ShapeDtypeStruct((), dtype)
        specs = [jax.ShapeDtypeStruct(leaf.shape[1:], leaf.dtype) for leaf in leaves]
        with fusion_off():  # (an identity for XLA; no recurrence rule for it)
            closed = jax.make_jaxpr(flat)(scalar, scalar, scalar, *specs)
        out = closed.out_avals
        if len(out) != 1 or out[0].shape != ():
            raise TypeError(
                f"`accel` must return a scalar; it returned {out} at scalar inputs."
            )
        prog = _Program(closed, len(leaves))
        if unrolled:
            # Traced once: counted against the budget, then called as it is (a
            # `jit` call, which XLA inlines: re-binding its thousands of equations
            # into the caller's trace took ~0.08 s of the default sweep's first-call
            # tracing, 0.68-0.71 -> 0.60-0.61 s, one core, measured).
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


class Taylor(AbstractTaylorSolver):
    r"""A Taylor integrator (heyoka's method) for `period` and `sweep_periods`.

    Each step expands the trajectory to order $K$ about the current state with the
    coefficients of `taylor_coefficients` (recurrences from the acceleration's jaxpr,
    one transcendental call per node per step), takes the step length from the last
    coefficients (Jorba and Zou's rule, as heyoka.py does, but over the last four
    orders instead of two: from rest the odd coefficients vanish and two orders can
    rest on one coefficient passing through zero):

    $$h = e^{-0.7/(K-1)}\,\varepsilon^{1/K} \min_{K-3 \le j \le K}
    \lVert (x_j, v_j)\rVert_\infty^{-1/j},\qquad
    \varepsilon = \text{atol} + \text{rtol}\,\lVert (x_0, v_0)\rVert_\infty,$$

    (never longer than `max_step` in the lane's units of time, a fraction of its
    small-amplitude period, so that no event can be stepped over), and evaluates the
    polynomials at $h$. Nothing is rejected: the step is chosen before it is taken.
    Events are located by re-evaluating the step from the same base with Newton or
    a secant on the step length, as for Runge–Kutta solvers.

    Only for the period kernel (not a diffrax solver). The acceleration's jaxpr must
    consist of primitives with a recurrence (`taylor_coefficients` lists them). For
    one that has none, `Taylor()` raises `NotImplementedError` naming the primitive
    at the first call, and `Taylor(fallback=diffrax.Dopri8())` (the default solver of
    `sweep_periods`) steps with the fallback instead. The fallback also steps where
    the coefficients' straight-line program would exceed ~2000 equations (the
    θ-form cycloid, the rotating hoop): the kernel would then loop over the orders,
    measured 5-10x slower than Dopri8 per period and slower to compile (one core,
    4096 amplitudes: cycloid 17k against 83k periods/s, hoop 4k against 40k); a
    plain `Taylor()` still takes that loop. Which one ran is `SweepResult.solver`.
    Its forward-mode derivative compiles longer than a Runge–Kutta step's (the
    recurrence's tangent: `jax.grad` of a 64-amplitude "matched" sweep of the
    pendulum, first call 10.5 s against 4.4 s with `Dopri8`).

    **Arguments:**

    - `order`: $K$, the degree of the polynomials (default 20: the order heyoka.py
        picks for float64 at its default tolerance; $K \geq 2$).
    - `max_step`: the longest step in the lane's units of time, $\sqrt{|q_0| /
        |\ddot q_0|}$ (default 2, a third of a small oscillation's period).
    - `fallback`: `None` (default), or an adaptive explicit Runge–Kutta diffrax
        solver to step with where the acceleration has a primitive without a
        recurrence or a program too large to unroll.

    **Example:**

    ```python
    L = lagrax.systems.pendulum.lagrangian()
    res = lagrax.sweep_periods(L, jnp.linspace(0.01, 3.1, 4096), solver=lagrax.Taylor())
    ```
    """

    order: int = eqx.field(static=True, default=20)
    max_step: float = eqx.field(static=True, default=2.0)
    fallback: "dfx.AbstractERK | None" = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not isinstance(self.order, int) or isinstance(self.order, bool):
            raise TypeError(f"`order` must be an int >= 2; got {self.order!r}.")
        if self.order < 2:
            raise ValueError(f"`order` must be at least 2; got {self.order}.")
        if not (isinstance(self.max_step, (int, float)) and 0 < self.max_step < np.inf):
            raise ValueError(
                f"`max_step` must be a positive finite number; got {self.max_step!r}."
            )
        if self.fallback is not None and not (
            isinstance(self.fallback, dfx.AbstractERK)
            and getattr(type(self.fallback).tableau, "b_error", None) is not None
        ):
            raise TypeError(
                "`fallback` must be None or an adaptive explicit Runge–Kutta diffrax "
                f"solver, e.g. diffrax.Dopri8(); got {self.fallback!r}."
            )

    def supports(self, accel: Callable, dtype, *params) -> bool:
        """Whether `taylor_coefficients` has a recurrence for every primitive of
        `accel(s, x, v, *params)` (scalars `s, x, v`; `params` shape-dtype specs or
        arrays without a lane axis): traced once, nothing is evaluated."""
        lanes = [
            jax.ShapeDtypeStruct((1, *np.shape(p)), jnp.asarray(p).dtype)
            if not isinstance(p, jax.ShapeDtypeStruct)
            else jax.ShapeDtypeStruct((1, *p.shape), p.dtype)
            for p in params
        ]
        one = jax.ShapeDtypeStruct((1,), dtype)
        coeffs = taylor_coefficients(lambda s, x, v, p: accel(s, x, v, *p), 2, dtype)
        try:
            jax.eval_shape(lambda s, x, v, p: coeffs(s, x, v, p), one, one, one, lanes)
        except NotImplementedError:
            return False
        return True

    def unrolls(self, accel: Callable, dtype, *params) -> bool:
        """Whether the period kernel computes `accel`'s coefficients at this order as
        one straight-line program (at most `_UNROLL_BUDGET` equations) rather than
        by the slower loop over orders; arguments as `supports` (which must hold).
        Traced once, nothing is evaluated."""
        lanes = [
            jax.ShapeDtypeStruct((1, *p.shape), p.dtype)
            if isinstance(p, jax.ShapeDtypeStruct)
            else jax.ShapeDtypeStruct((1, *np.shape(p)), jnp.asarray(p).dtype)
            for p in params
        ]
        one = jax.ShapeDtypeStruct((1,), dtype)
        coeffs = taylor_coefficients(
            lambda s, x, v, p: accel(s, x, v, *p),
            self.order,
            dtype,
            unrolled=True,
            vectorized_trig=True,
        )
        jax.eval_shape(lambda s, x, v, p: coeffs(s, x, v, p), one, one, one, lanes)
        return coeffs.unrolled
