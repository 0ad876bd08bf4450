r"""The $k$-th Taylor coefficient of each primitive from the lower ones.

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

Why this is worth doing: on CPU, XLA's float64 `sin` is a scalar libm call per
element while multiply-adds vectorize, so an order-20 Taylor step costs about as much
as a few sines, against 13 sines for one step of an 8th-order Runge–Kutta method.

Each rule below, `rule(store, node) -> [coefficients]`, gives the $k$-th coefficient
($k \geq 1$) of a series node's outputs from the store of lower ones; `None` stands
for an exact zero.
"""

import jax
import jax.numpy as jnp


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
        if st.triangular:
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
