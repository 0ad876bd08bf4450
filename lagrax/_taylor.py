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

- The jaxpr is traced once at scalar inputs, nested calls (`jit`, `custom_jvp_call`, ...)
    are inlined, duplicate equations merged (an autodiff jaxpr computes `sin q` once
    per tangent direction) and dead ones dropped.
- A variable is a *series* only if it depends differentiably on $(s, x, v)$. Everything
    else (tangent seeds, a constant mass matrix, per-lane parameters, comparisons) is
    evaluated once, at order 0, and multiplies series in $O(K)$. Outputs of
    zero-derivative primitives (`sign`, `floor`, comparisons, `is_finite`) and the
    branch of `select_n`, `max`, `abs` are decided on the order-0 coefficient.
- Orders are unrolled in Python, each coefficient a separate `(W,)` array: the
    convolutions are exactly triangular (no masked half), XLA fuses each order into a
    few loops over the lanes, and the compiled program has no loop-carried state.
"""

import functools
import operator
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jex_core


__all__ = ["taylor_coefficients"]

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

# Call-like primitives whose (primal) body is inlined.
_CALLS = {
    "pjit": "jaxpr",
    "jit": "jaxpr",
    "closed_call": "call_jaxpr",
    "core_call": "call_jaxpr",
    "remat": "jaxpr",
    "checkpoint": "jaxpr",
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


# --- evaluation helpers ------------------------------------------------------------


def _bind(prim, params, vals, batched):
    """`prim.bind` with lane-batched operands (axis 0) vmapped."""
    if not any(batched):
        out = prim.bind(*vals, **params)
    else:
        axes = [0 if b else None for b in batched]
        out = jax.vmap(lambda *a: prim.bind(*a, **params), in_axes=axes)(*vals)
    return list(out) if prim.multiple_results else [out]


def _conv(a, b, k, lo=1, hi=None):
    r"""$\sum_{j=lo}^{hi} a_j b_{k-j}$ over the coefficients present (None: zero)."""
    hi = k if hi is None else hi
    terms = []
    for j in range(lo, hi + 1):
        if j < len(a) and k - j < len(b):
            aj, bkj = a[j], b[k - j]
            if aj is not None and bkj is not None:
                terms.append(aj * bkj)
    if not terms:
        return None
    return functools.reduce(operator.add, terms)


def _add(x, y):
    if x is None:
        return y
    if y is None:
        return x
    return x + y


def _scale(c, x):
    return None if x is None else c * x


class _Run:
    """The coefficient arrays of one call: order 0 by plain evaluation, then order by
    order through the series equations only."""

    def __init__(self, prog, s, x, v, leaves):
        self.prog = prog
        self.W = x.shape[0]
        self.val = {}  # order-0 value of every id
        self.bat = {}  # whether that value has the lane axis
        self.ser = {}  # id -> list of coefficients (None: exactly zero)
        self.aux = {}
        for i, c in prog.consts.items():
            self.val[i], self.bat[i] = c, False
        for i, a in zip((0, 1, 2), (s, x, v)):
            self.val[i], self.bat[i] = a, True
        for i, a in zip(prog.params, leaves):
            self.val[i], self.bat[i] = a, True
        for node in prog.nodes:
            self._order0(node)
        for i in prog.series:
            if i in self.val:
                self.ser[i] = [self._lanes(i)]

    def _lanes(self, i):
        """Order-0 value with the lane axis, broadcast if it has none."""
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

    def _order0(self, node):
        vals = [self.val[i] for i in node.ins]
        batched = [self.bat[i] for i in node.ins]
        if node.kind == "sincos":
            outs = [jnp.sin(vals[0]), jnp.cos(vals[0])]
        elif node.kind == "sinhcosh":
            outs = [jnp.sinh(vals[0]), jnp.cosh(vals[0])]
        else:
            outs = _bind(node.prim, node.params, vals, batched)
        for o, value in zip(node.outs, outs):
            self.val[o] = value
            self.bat[o] = any(batched)

    def coef(self, i, k):
        """The k-th coefficient of `i` (None: exactly zero), constants included."""
        if i in self.ser:
            return self.ser[i][k]
        return self.const(i) if k == 0 else None

    def zeros(self, i):
        return jnp.zeros((self.W,) + tuple(self.prog.avals[i].shape),
                         self.prog.avals[i].dtype)

    def materialize(self, k):
        """Makes XLA keep the k-th coefficients in buffers.

        Every later order reads them; left to itself XLA fuses each producer into its
        consumers and recomputes the whole lower-order recurrence inside every fusion
        (measured at order 20: 10x the run time and 5x the compile time).
        """
        ids = [i for i, c in self.ser.items() if len(c) > k and c[k] is not None]
        aux = [(key, c) for key, c in self.aux.items() if isinstance(c, list)]
        aux = [(key, c) for key, c in aux if len(c) > k and c[k] is not None]
        vals = [self.ser[i][k] for i in ids] + [c[k] for _, c in aux]
        vals = lax.optimization_barrier(vals)
        for i, value in zip(ids, vals[: len(ids)]):
            self.ser[i][k] = value
        for (_, c), value in zip(aux, vals[len(ids) :]):
            c[k] = value

    def step(self, node, k):
        """Appends the k-th coefficients (k >= 1) of the node's outputs."""
        outs = _RULES.get(node.kind, _linear)(self, node, k)
        for o, c in zip(node.outs, outs):
            self.ser[o].append(c)


# --- recurrences (k >= 1); `r.ser[i]` holds coefficients 0..k-1 of each output -------


def _linear(r, node, k):
    if node.kind in _BILINEAR:
        return _bilinear(r, node, k)
    if node.kind not in _LINEAR:
        raise AssertionError(node.kind)  # pragma: no cover - filtered at build time
    prog = r.prog
    cs = [r.ser[i][k] if i in r.ser else None for i in node.ins]
    if all(c is None for i, c in zip(node.ins, cs) if i in r.ser):
        return [None] * len(node.outs)
    vals, batched = [], []
    for i, c in zip(node.ins, cs):
        inexact = jnp.issubdtype(prog.avals[i].dtype, jnp.inexact)
        if i in r.ser:
            vals.append(r.zeros(i) if c is None else c)
            batched.append(True)
        elif inexact:  # a constant float operand has no k-th coefficient
            vals.append(jnp.zeros(prog.avals[i].shape, prog.avals[i].dtype))
            batched.append(False)
        else:
            vals.append(r.val[i])
            batched.append(r.bat[i])
    kind = node.kind
    # Shape-preserving arithmetic directly (no vmap, no additions of zeros).
    if kind in ("add", "add_any", "sub") and len(vals) == 2:
        a, b = (c if i in r.ser else None for i, c in zip(node.ins, cs))
        if kind == "sub":
            b = None if b is None else -b
        return [_add(a, b)]
    if kind == "neg":
        return [-vals[0]]
    return _bind(node.prim, node.params, vals, batched)


def _bilinear(r, node, k):
    u, w = node.ins
    if u in r.ser and w in r.ser:
        if node.kind == "mul":
            return [_conv(r.ser[u], r.ser[w], k, lo=0)]
        terms = []
        for j in range(k + 1):
            a, b = r.ser[u][j], r.ser[w][k - j]
            if a is not None and b is not None:
                terms.append(_bind(node.prim, node.params, [a, b], [True, True])[0])
        return [functools.reduce(operator.add, terms) if terms else None]
    c = r.ser[u][k] if u in r.ser else r.ser[w][k]
    if c is None:
        return [None]
    if node.kind == "mul":
        const = r.const(w if u in r.ser else u)
        return [c * const]
    vals = [c, r.val[w]] if u in r.ser else [r.val[u], c]
    batched = [True, r.bat[w]] if u in r.ser else [r.bat[u], True]
    return _bind(node.prim, node.params, vals, batched)


def _weighted(r, node, u, k):
    r"""The list $j u_j$, $j = 0..k$, kept per node and extended one order a call."""
    ju = r.aux.setdefault((node.outs[0], "ju"), [None])
    uk = r.ser[u][k] if u in r.ser else None
    ju.append(_scale(float(k), uk))
    return ju


def _sincos(r, node, k):
    (u,) = node.ins
    s, c = (r.ser[o] for o in node.outs)
    ju = _weighted(r, node, u, k)
    sign = -1.0 if node.kind == "sincos" else 1.0
    sk = _scale(1.0 / k, _conv(ju, c, k))
    ck = _scale(sign / k, _conv(ju, s, k))
    return [sk, ck]


def _exp(r, node, k):
    (u,) = node.ins
    ju = _weighted(r, node, u, k)
    c = r.ser[node.outs[0]]
    if node.kind == "expm1":
        # exp(u) = c + 1: the same recurrence with the order-0 coefficient shifted.
        c = [c[0] + 1.0] + c[1:]
    return [_scale(1.0 / k, _conv(ju, c, k))]


def _inverse0(r, node, key, value):
    """A reciprocal of an order-0 quantity, computed once per node (divisions are
    ~10x a multiply-add, and it is reused at every order)."""
    k = (node.outs[0], key)
    if k not in r.aux:
        r.aux[k] = 1.0 / value
    return r.aux[k]


def _log(r, node, k):
    (u,) = node.ins
    us = r.ser[u]
    c = r.ser[node.outs[0]]
    u0 = us[0] + 1.0 if node.kind == "log1p" else us[0]
    inv = _inverse0(r, node, "inv", u0)
    jc = r.aux.setdefault((node.outs[0], "jc"), [None])
    jc.append(_scale(float(k - 1), c[k - 1]) if k > 1 else None)
    # c_k = (u_k - (1/k) sum_{j=1}^{k-1} j c_j u_{k-j}) / u_0
    acc = _scale(-1.0 / k, _conv(jc, us, k, lo=1, hi=k - 1))
    num = _add(us[k], acc)
    return [None if num is None else num * inv]


def _sqrt(r, node, k):
    (u,) = node.ins
    c = r.ser[node.outs[0]]
    inv = _inverse0(r, node, "inv", 2.0 * c[0])
    num = _add(r.ser[u][k], _scale(-1.0, _conv(c, c, k, lo=1, hi=k - 1)))
    return [None if num is None else num * inv]


def _power(r, node, k, a):
    r"""$c = u^a$: from $u c' = a u' c$,
    $c_k = \frac{1}{u_0}\sum_{j=1}^k \left(\frac{(a+1)j}{k} - 1\right) u_j c_{k-j}$."""
    (u,) = node.ins[:1]
    us = r.ser[u]
    c = r.ser[node.outs[0]]
    inv = _inverse0(r, node, "inv", us[0])
    if isinstance(a, float):
        terms = [
            ((a + 1.0) * j / k - 1.0) * us[j] * c[k - j]
            for j in range(1, k + 1)
            if us[j] is not None
        ]
        total = functools.reduce(operator.add, terms) if terms else None
    else:
        ju = _weighted(r, node, u, k)
        jterm = _conv(ju, c, k)
        jterm = None if jterm is None else jterm * ((a + 1.0) / k)
        total = _add(jterm, _scale(-1.0, _conv(us, c, k)))
    return [None if total is None else total * inv]


def _pow(r, node, k):
    u, w = node.ins
    if u not in r.ser:  # constant base, series exponent: rewritten at build time
        raise AssertionError("pow")  # pragma: no cover
    value = r.val[w]
    if not r.bat[w] and not isinstance(value, jax.core.Tracer) and np.ndim(value) == 0:
        a = float(value)
    else:
        a = r.const(w)
    return _power(r, node, k, a)


def _named_power(a):
    return lambda r, node, k: _power(r, node, k, a)


def _div(r, node, k):
    u, w = node.ins
    q = r.ser[node.outs[0]]
    uk = r.ser[u][k] if u in r.ser else None
    if w not in r.ser:
        inv = _inverse0(r, node, "inv", r.const(w))
        return [None if uk is None else uk * inv]
    # c_k = (u_k - sum_{j=1}^k w_j c_{k-j}) / w_0
    inv = _inverse0(r, node, "inv", r.ser[w][0])
    num = _add(uk, _scale(-1.0, _conv(r.ser[w], q, k)))
    return [None if num is None else num * inv]


def _tan(r, node, k):
    r"""$t' = (1 \pm t^2) u'$ with the auxiliary series $w = 1 \pm t^2$."""
    (u,) = node.ins
    t = r.ser[node.outs[0]]
    sign = 1.0 if node.kind == "tan" else -1.0
    w = r.aux.setdefault((node.outs[0], "w"), [1.0 + sign * t[0] * t[0]])
    ju = _weighted(r, node, u, k)
    tk = _scale(1.0 / k, _conv(ju, w, k))
    t_new = t + [tk]
    w.append(_scale(sign, _conv(t_new, t_new, k, lo=0)))
    return [tk]


def _logistic(r, node, k):
    r"""$\sigma' = (\sigma - \sigma^2) u'$."""
    (u,) = node.ins
    c = r.ser[node.outs[0]]
    w = r.aux.setdefault((node.outs[0], "w"), [c[0] - c[0] * c[0]])
    ju = _weighted(r, node, u, k)
    ck = _scale(1.0 / k, _conv(ju, w, k))
    c_new = c + [ck]
    w.append(_add(ck, _scale(-1.0, _conv(c_new, c_new, k, lo=0))))
    return [ck]


def _atan(r, node, k):
    r"""$(1 + u^2) c' = u'$: with $w = 1 + u^2$,
    $c_k = \bigl(u_k - \frac1k\sum_{j=1}^{k-1} w_j (k-j) c_{k-j}\bigr) / w_0$."""
    (u,) = node.ins
    us = r.ser[u]
    c = r.ser[node.outs[0]]
    w = r.aux.setdefault((node.outs[0], "w"), [1.0 + us[0] * us[0]])
    w.append(_conv(us, us, k, lo=0))
    inv = _inverse0(r, node, "inv", w[0])
    jc = r.aux.setdefault((node.outs[0], "jc"), [None])
    jc.append(_scale(float(k - 1), c[k - 1]) if k > 1 else None)
    acc = _scale(-1.0 / k, _conv(w, jc, k, lo=1, hi=k - 1))
    num = _add(us[k], acc)
    return [None if num is None else num * inv]


def _branch(r, node, key, fn):
    """A boolean decided on the order-0 coefficients, computed once per node."""
    k = (node.outs[0], key)
    if k not in r.aux:
        r.aux[k] = fn()
    return r.aux[k]


def _pick(r, mask, a_id, b_id, k):
    a, b = r.coef(a_id, k), r.coef(b_id, k)
    if a is None and b is None:
        return None
    a = jnp.zeros_like(b) if a is None else a
    b = jnp.zeros_like(a) if b is None else b
    a, b = jnp.broadcast_arrays(a, b)
    return jnp.where(jnp.broadcast_to(mask, a.shape), a, b)


def _maxmin(r, node, k):
    u, w = node.ins
    op = jnp.greater_equal if node.kind == "max" else jnp.less_equal
    mask = _branch(r, node, "mask", lambda: op(r._lanes(u), r._lanes(w)))
    return [_pick(r, mask, u, w, k)]


def _abs(r, node, k):
    (u,) = node.ins
    mask = _branch(r, node, "mask", lambda: r.ser[u][0] >= 0)
    uk = r.ser[u][k]
    return [None if uk is None else jnp.where(mask, uk, -uk)]


def _clamp(r, node, k):
    lo, x, hi = node.ins
    below = _branch(r, node, "below", lambda: r._lanes(x) < r._lanes(lo))
    above = _branch(r, node, "above", lambda: r._lanes(x) > r._lanes(hi))
    inner = _pick(r, above, hi, x, k)
    outer = r.coef(lo, k)
    if inner is None and outer is None:
        return [None]
    inner = jnp.zeros_like(outer) if inner is None else inner
    outer = jnp.zeros_like(inner) if outer is None else outer
    inner, outer = jnp.broadcast_arrays(inner, outer)
    return [jnp.where(jnp.broadcast_to(below, inner.shape), outer, inner)]


def _rem(r, node, k):
    u, w = node.ins
    if w in r.ser:
        raise NotImplementedError(
            "Taylor coefficients: `rem` with a divisor that depends on the state."
        )
    return [r.ser[u][k]]


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


# --- entry point --------------------------------------------------------------------


def taylor_coefficients(accel: Callable, order: int, dtype) -> Callable:
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
        closed = jax.make_jaxpr(flat)(scalar, scalar, scalar, *specs)
        out = closed.out_avals
        if len(out) != 1 or out[0].shape != ():
            raise TypeError(
                f"`accel` must return a scalar; it returned {out} at scalar inputs."
            )
        prog = _Program(closed, len(leaves))
        run = _Run(prog, s, x, v, leaves)
        xs, vs, as_ = [x], [v], []
        for k in range(K):
            if k > 0:
                run.ser[1].append(xs[k])
                run.ser[2].append(vs[k])
                run.ser[0].append(jnp.ones_like(s) if k == 1 else None)
                for node in prog.nodes:
                    if node.series:
                        run.step(node, k)
                run.materialize(k)
            if prog.out in run.ser:
                a = run.ser[prog.out][k]
            else:
                a = run._lanes(prog.out) if k == 0 else None
            a = jnp.zeros_like(x) if a is None else jnp.broadcast_to(a, x.shape)
            a = a.astype(dtype)
            as_.append(a)
            vs.append(a / (k + 1))
            xs.append(vs[k] / (k + 1))
        return jnp.stack(xs), jnp.stack(vs), jnp.stack(as_)

    return coeffs
