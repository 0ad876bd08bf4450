r"""Taylor coefficients from a tape: the acceleration's program as data.

`taylor_coefficients` turns the acceleration's jaxpr into a program specialized to
it, which XLA compiles (fast to run, seconds to compile for each Lagrangian). Here
the same recurrences run in ONE fixed program that reads the equations as data, a
*tape*: per node an opcode, up to three operand slots and an output slot, and the
constants' values. With `L` as data, the compiled program is the same for every
Lagrangian whose tape fits its size: a new `L` costs the building of its tape
(tracing, no XLA compile), and a compiled executable can be kept across
Lagrangians and processes.

The interpreter carries every slot's coefficients in one array `C` of shape
`(slots, K + 1, W)`. Order 0 is one `lax.fori_loop` over the nodes with a
`lax.switch` on the opcode that evaluates the primitive; orders $1..K$ are a loop
over orders around a loop over the nodes that depend on the inputs (`series`),
each computing its $k$-th coefficient by the recurrences of `taylor_coefficients`
(Cauchy products as one full-length product with a reversed, shifted window, half
of whose terms are zeros). Sine and cosine (likewise sinh and cosh, and the
auxiliary series of tan, tanh, atan and the logistic function) are separate nodes,
each reading the other's lower orders: one output per node.

Two modes: `tape_coefficients` solves $x' = v$, $v' = a(s, x, v, p)$ for the
polynomials of a Taylor step ($x_{k+1} = v_k/(k+1)$, $v_{k+1} = a_k/(k+1)$ after
each order); `tape_series` propagates given input series through any program (at
order 1: values and directional derivatives, e.g. of the energy or of $L$ at rest).

Only scalar programs (every variable of one entry, float or bool) with the
primitives that have an opcode here are taped; `build_tape` raises
`NotImplementedError` otherwise (the caller then compiles the specialized program).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._jaxpr import trig as _trig
from .._jaxpr.fusion import fusion_off
from .program import _Program


__all__ = ["Tape", "build_tape", "tape_coefficients", "tape_series"]

# Opcodes with a recurrence at every order, then those evaluated at order 0 only
# (piecewise constant: comparisons, logic, rounding).
_WITH_SERIES = (
    "nop",
    "copy",
    "add",
    "sub",
    "neg",
    "mul",
    "div",
    "scale",
    "unscale",
    "sin",
    "cos",
    "sinh",
    "cosh",
    "exp",
    "expm1",
    "log",
    "log1p",
    "sqrt",
    "pow",
    "tan",
    "tanh",
    "atan",
    "logistic",
    "abs",
    "max",
    "min",
    "select",
)
_ORDER0_ONLY = (
    "lt",
    "le",
    "gt",
    "ge",
    "eq",
    "ne",
    "and",
    "or",
    "not",
    "is_finite",
    "sign",
    "floor",
    "ceil",
)
OPS = {name: i for i, name in enumerate(_WITH_SERIES + _ORDER0_ONLY)}

# Primitives that, on arrays of one entry, only move or retype it.
_COPY = frozenset(
    {
        "copy",
        "copy_p",
        "convert_element_type",
        "reshape",
        "squeeze",
        "expand_dims",
        "broadcast_in_dim",
        "transpose",
        "slice",
        "concatenate",
        "stack",
        "reduce_sum",
        "reduce_max",
        "reduce_min",
        "stop_gradient",
        "reduce_precision",
        "real",
        "rev",
        "dynamic_slice",
        "optimization_barrier",
    }
)
# Primitives that are an opcode as they are (`dot_general` of one entry: a product).
_DIRECT = {
    **{name: name for name in _WITH_SERIES[2:] if name not in ("select",)},
    **{name: name for name in _ORDER0_ONLY},
    "add_any": "add",
    "dot_general": "mul",
}


class Tape(eqx.Module):
    r"""A scalar program as data: the inputs are slots $1..n$ (slot 0 holds zero),
    then constants and one slot per node.

    - `ops`: int32 `(nodes, 5)`, rows `(opcode, a, b, c, out)` of slot numbers,
        padded with no-ops; `forms` (int32 `(nodes, 6)`: `X, Y, P, Q, out, pick`)
        and `coefs` (`(nodes, 4)`): how each row's higher orders are formed
        (`_FORMS`);
    - `values`: each slot's value at order 0 where it is a constant (zeros
        elsewhere);
    - `series`: the rows evaluated past order 0 (those that depend on the inputs),
        padded; `n_nodes`, `n_series`: the rows in use;
    - `outputs`: the output slots.
    """

    ops: jax.Array
    forms: jax.Array
    coefs: jax.Array
    values: jax.Array
    series: jax.Array
    n_nodes: jax.Array
    n_series: jax.Array
    outputs: jax.Array

    @property
    def size(self):
        """`(slots, nodes)`: the shapes a compiled interpreter is specialized to."""
        return self.values.shape[0], self.ops.shape[0]


def _bucket(n, smallest=32):
    """The power of two at or above `n`: compiled sizes come in powers of two, so
    that tapes of similar size share one executable."""
    return max(smallest, 1 << math.ceil(math.log2(max(n, 1))))


class _TapeProgram(_Program):
    """`_Program`'s flattening (calls inlined, duplicates merged, integer powers of
    series expanded into products, sines paired with cosines) for any inputs, the
    `series` ones depending on the state, and any number of outputs."""

    def __init__(self, closed, series):
        self._empty()
        self.inputs = [self._new(a) for a in closed.in_avals]
        self.series.update(self.inputs[i] for i in series)
        self.params = []
        self.outs = self._inline(closed.jaxpr, closed.consts, self.inputs)
        self.out = None
        self._prune(self.outs)


def build_tape(fn, n_in, dtype, series=(0, 1, 2), size=None) -> Tape:
    r"""The tape of `fn(*scalars)` (`n_in` scalar inputs of the float `dtype`;
    returns a scalar or a tuple of scalars), its inputs `series` depending on the
    state (the others are fixed along a step: parameters). `size = (slots, nodes)`
    pads to at least these sizes (powers of two at or above what it needs).

    **Raises:**

    `NotImplementedError` where a variable has more than one entry or an integer
    dtype, a primitive has no opcode here, or a constant is not concrete.
    """
    dtype = np.dtype(dtype)
    scalar = jax.ShapeDtypeStruct((), dtype)

    def flat(*args):
        out = fn(*args)
        return tuple(out) if isinstance(out, (tuple, list)) else (out,)

    with fusion_off():  # (an identity for XLA; no opcode for it)
        closed = jax.make_jaxpr(flat)(*([scalar] * n_in))
    prog = _TapeProgram(closed, series)
    return _Rows(prog, dtype).tape(size)


class _Rows:
    """`_TapeProgram` numbered into slots and opcode rows."""

    def __init__(self, prog, dtype):
        self.prog = prog
        self.dtype = dtype
        self.values = {}  # slot -> constant value
        self.rows = []  # (opcode, a, b, c, out)
        self.series_rows = []
        self.next = prog._next + 1
        self._consts = {}
        self.alias = {}  # slot -> the slot it copies (no row for a copy)
        self.is_series = {i + 1 for i in prog.series}
        for i, aval in prog.avals.items():
            _check_scalar(aval)
        for i, value in prog.consts.items():
            if isinstance(value, jax.core.Tracer):
                raise NotImplementedError("a tape needs concrete constants")
            value = np.asarray(value)
            if value.size != 1:
                raise NotImplementedError("a tape holds scalars only")
            self.values[self.slot(i)] = value.reshape(()).astype(dtype)
        for node in prog.nodes:
            self.node(node)

    def slot(self, i):
        s = i + 1  # (slot 0 is the zero slot)
        return self.alias.get(s, s)

    def new(self):
        self.next += 1
        return self.next - 1

    def const(self, value):
        value = float(value)
        if value not in self._consts:
            slot = self._consts[value] = self.new()
            self.values[slot] = np.asarray(value, self.dtype)
        return self._consts[value]

    def row(self, op, a=0, b=0, c=0, out=None, series=False):
        out = self.new() if out is None else out
        if series:
            self.series_rows.append(len(self.rows))
        self.rows.append((OPS[op], a, b, c, out))
        return out

    def node(self, node):
        kind, series = node.kind, node.series
        ins = [self.slot(i) for i in node.ins]
        outs = [self.slot(o) for o in node.outs]
        row = lambda op, *args, out=None: self.row(op, *args, out=out, series=series)
        if kind in ("sincos", "sinhcosh"):
            s, c = outs
            first, second = ("sin", "cos") if kind == "sincos" else ("sinh", "cosh")
            row(first, ins[0], c, out=s)
            row(second, ins[0], s, out=c)
            return
        (out,) = outs
        series_in = [i in self.is_series for i in ins]
        if kind in _COPY:
            self.alias[out] = ins[0]
        elif kind in ("mul", "dot_general", "div") and series and not all(series_in):
            # A product with (or a quotient by) an operand fixed along the step
            # scales the other: no Cauchy product (`_FORMS`: "scale").
            if kind == "div" and not series_in[0]:
                row("div", *ins, out=out)
            elif kind == "div":
                row("unscale", *ins, out=out)
            else:
                u, w = ins if series_in[0] else ins[::-1]
                row("scale", u, w, out=out)
        elif kind == "select_n":
            if len(ins) != 3:
                raise NotImplementedError("select_n of more than two cases")
            row("select", *ins, out=out)
        elif kind in ("square", "integer_pow"):
            n = 2 if kind == "square" else node.params["y"]
            self.power(ins[0], n, out, row)
        elif kind == "exp2":
            u = row("mul", ins[0], self.const(np.log(2.0)))
            row("exp", u, out=out)
        elif kind == "rsqrt":
            row("pow", ins[0], self.const(-0.5), out=out)
        elif kind == "pow":
            row("pow", ins[0], ins[1], out=out)
        elif kind in ("tan", "tanh"):
            # t' = (1 ± t²) u': the auxiliary w = 1 ± t² after t, read at lower
            # orders only.
            w = self.new()
            row(kind, ins[0], w, out=out)
            tt = row("mul", out, out)
            row("add" if kind == "tan" else "sub", self.const(1.0), tt, out=w)
        elif kind == "atan":
            uu = row("mul", ins[0], ins[0])
            d = row("add", self.const(1.0), uu)
            row("atan", ins[0], d, out=out)
        elif kind == "logistic":
            w = self.new()
            row("logistic", ins[0], w, out=out)
            rest = row("sub", self.const(1.0), out)
            row("mul", out, rest, out=w)
        elif kind in _DIRECT:
            row(_DIRECT[kind], *ins, out=out)
        else:
            raise NotImplementedError(f"no tape opcode for the primitive `{kind}`")

    def power(self, u, n, out, row):
        """u**n (integer n) by binary powering, as `_Program` expands series."""
        if n == 0:
            row("copy", self.const(1.0), out=out)
            return
        if n < 0:
            p = self.new()
            self.power(u, -n, p, row)
            row("div", self.const(1.0), p, out=out)
            return
        result, base = None, u
        while True:
            if n & 1:
                if result is None:
                    result = base
                else:
                    result = row("mul", result, base)
            n >>= 1
            if not n:
                break
            base = row("mul", base, base)
        self.alias[out] = result

    def tape(self, size):
        slots = max([self.next, *(o + 1 for o in self.values)])
        S = _bucket(max(slots, size[0] if size else 0))
        N = _bucket(max(len(self.rows), size[1] if size else 0))
        ops = np.zeros((N, 5), np.int32)
        forms = np.zeros((N, 6), np.int32)
        coefs = np.zeros((N, 4), self.dtype)
        names = list(OPS)
        for i, row in enumerate(self.rows):
            ops[i] = row
            forms[i], coefs[i] = _form(names[row[0]], *row[1:])
        values = np.zeros((S,), self.dtype)
        for slot, value in self.values.items():
            values[slot] = value
        series = np.zeros((N,), np.int32)
        series[: len(self.series_rows)] = self.series_rows
        outputs = np.asarray([self.slot(o) for o in self.prog.outs], np.int32)
        if any(
            o not in self.values
            and o > len(self.prog.inputs)
            and o not in {r[4] for r in self.rows}
            for o in outputs
        ):
            raise NotImplementedError("an output with no row")
        return Tape(
            ops=jnp.asarray(ops),
            forms=jnp.asarray(forms),
            coefs=jnp.asarray(coefs),
            values=jnp.asarray(values),
            series=jnp.asarray(series),
            n_nodes=jnp.asarray(len(self.rows), jnp.int32),
            n_series=jnp.asarray(len(self.series_rows), jnp.int32),
            outputs=jnp.asarray(outputs),
        )


def _check_scalar(aval):
    if int(np.prod(aval.shape)) != 1:
        raise NotImplementedError("a tape holds scalars only (one entry per variable)")
    if not (jnp.issubdtype(aval.dtype, jnp.floating) or aval.dtype == jnp.bool_):
        raise NotImplementedError(f"a tape holds floats and bools, not {aval.dtype}")


# --- the interpreter -----------------------------------------------------------------

# How each opcode's k-th coefficient (k >= 1) is formed from the series of slots:
#   y_k = d (c1 X_k + c2 Y_k + sum_j (c3 + c4 g j / k) P_j Q_{k-j}),
# or, for a choice decided at order 0 ("pick"), y_k = X_k where `mask` else Y_k. The
# slots X, Y, P, Q come from the operands a, b, c and the output ("o") itself, whose
# k-th coefficient is still zero while it is formed (the unknown term drops out of
# the sum); g, d and mask are per lane, from order 0 (`_order0_branches`). One
# formula for every opcode, with at most one Cauchy product: the loop over orders
# runs without a branch per opcode.
_FORMS = {
    "copy": dict(X="a", c1=1.0),
    "add": dict(X="a", Y="b", c1=1.0, c2=1.0),
    "sub": dict(X="a", Y="b", c1=1.0, c2=-1.0),
    "neg": dict(X="a", c1=-1.0),
    "mul": dict(P="a", Q="b", c3=1.0),
    # A series times a value fixed along the step (d = b), or over one (d = 1/b).
    "scale": dict(X="a", c1=1.0),
    "unscale": dict(X="a", c1=1.0),
    # y = a/b: y_k = (a_k - sum_{j>0} b_j y_{k-j}) / b_0.
    "div": dict(X="a", c1=1.0, P="b", Q="o", c3=-1.0),
    # s' = c u', c' = -s u' (b: the partner); sinh, cosh; t' = w u' with the
    # auxiliary w (b): tan 1 + t², tanh 1 - t², logistic σ(1 - σ).
    "sin": dict(P="a", Q="b", c4=1.0),
    "cos": dict(P="a", Q="b", c4=-1.0),
    "sinh": dict(P="a", Q="b", c4=1.0),
    "cosh": dict(P="a", Q="b", c4=1.0),
    "tan": dict(P="a", Q="b", c4=1.0),
    "tanh": dict(P="a", Q="b", c4=1.0),
    "logistic": dict(P="a", Q="b", c4=1.0),
    "exp": dict(P="a", Q="o", c4=1.0),
    # e = expm1(u): e' = (e + 1) u'.
    "expm1": dict(X="a", c1=1.0, P="a", Q="o", c4=1.0),
    # u l' = u' (log1p: (1 + u) l' = u'): l_k = (u_k - (1/k) sum j l_j u_{k-j}) / d.
    "log": dict(X="a", c1=1.0, P="o", Q="a", c4=-1.0),
    "log1p": dict(X="a", c1=1.0, P="o", Q="a", c4=-1.0),
    # r² = u: r_k = (u_k - sum_{0<j<k} r_j r_{k-j}) / (2 r_0).
    "sqrt": dict(X="a", c1=1.0, P="o", Q="o", c3=-1.0),
    # y = u^p, u y' = p u' y: y_k = sum_j ((p + 1) j / k - 1) u_j y_{k-j} / u_0
    # (g = p + 1; the j = 0 term holds y_k, still zero).
    "pow": dict(P="a", Q="o", c3=-1.0, c4=1.0),
    # y = atan u with D = 1 + u² (b): D y' = u'.
    "atan": dict(X="a", c1=1.0, P="o", Q="b", c4=-1.0),
    "abs": dict(X="a", c1=1.0),  # d = ±1
    "max": dict(X="a", Y="b", pick=1),
    "min": dict(X="a", Y="b", pick=1),
    "select": dict(X="c", Y="b", pick=1),
}
_SLOTS = ("X", "Y", "P", "Q", "o")
_COEFS = ("c1", "c2", "c3", "c4")


def _form(op, a, b, c, out):
    """`(X, Y, P, Q, out, pick)` (0: the zero slot) and `(c1, c2, c3, c4)` of a
    row."""
    form = _FORMS.get(op, {})
    where = dict(a=a, b=b, c=c, o=out)
    slots = [where[form.get(k, k)] if k in form or k == "o" else 0 for k in _SLOTS]
    return slots + [form.get("pick", 0)], [form.get(k, 0.0) for k in _COEFS]


# Order 0 by families of opcodes: one branch per family computes every member and
# picks one (cheap elementwise work, done once per step), so that each place the
# interpreter is inlined compiles a few branches, not one per opcode.
_FAMILIES = (
    (
        "nop", "copy", "add", "sub", "neg", "mul", "div", "scale", "unscale", "abs",
        "max", "min", "select", "lt", "le", "gt", "ge", "eq", "ne", "and", "or",
        "not", "is_finite", "sign", "floor", "ceil",
    ),
    ("sin", "cos"),
    ("exp", "expm1", "sinh", "cosh", "tanh", "logistic"),
    ("log", "log1p", "sqrt", "pow", "tan", "atan"),
)  # fmt: skip
_FAMILY = np.zeros(len(OPS), np.int32)
_MEMBER = np.zeros(len(OPS), np.int32)
for _f, _names in enumerate(_FAMILIES):
    for _m, _name in enumerate(_names):
        _FAMILY[OPS[_name]], _MEMBER[OPS[_name]] = _f, _m


def _order0_branches(trig):
    """Per family, from the operands' values at order 0 and the member: the output's
    value and its `(g, d, mask)` for the orders above (`_FORMS`)."""
    truth = lambda x: x != 0
    flt = lambda mask, like: mask.astype(like.dtype)

    def pick(member, rows):
        """`rows[member]`: each row `(value, g, d, mask)`, `None` meaning 1. A chain
        of selects on the scalar `member`: one elementwise fusion (stacking the rows
        and indexing them compiles to several times the code)."""
        picked = []
        for i in range(4):
            out = None
            for m, r in enumerate(rows):
                x = jnp.ones_like(r[0]) if r[i] is None else r[i]
                out = x if out is None else jnp.where(member == m, x, out)
            picked.append(out)
        return tuple(picked)

    def arith(a, b, c, member):
        sign = jnp.where(a >= 0, 1.0, -1.0)
        plain = lambda v: (v, None, None, None)
        return pick(
            member,
            [
                plain(jnp.zeros_like(a)),
                plain(a),
                plain(a + b),
                plain(a - b),
                plain(-a),
                plain(a * b),
                (a / b, None, 1.0 / b, None),
                (a * b, None, b, None),
                (a / b, None, 1.0 / b, None),
                (jnp.abs(a), None, sign, None),
                (jnp.maximum(a, b), None, None, flt(a >= b, a)),
                (jnp.minimum(a, b), None, None, flt(a <= b, a)),
                (jnp.where(truth(a), c, b), None, None, flt(truth(a), a)),
                plain(flt(a < b, a)),
                plain(flt(a <= b, a)),
                plain(flt(a > b, a)),
                plain(flt(a >= b, a)),
                plain(flt(a == b, a)),
                plain(flt(a != b, a)),
                plain(flt(truth(a) & truth(b), a)),
                plain(flt(truth(a) | truth(b), a)),
                plain(flt(~truth(a), a)),
                plain(flt(jnp.isfinite(a), a)),
                plain(jnp.sign(a)),
                plain(jnp.floor(a)),
                plain(jnp.ceil(a)),
            ],
        )

    def trigonometric(a, b, c, member):
        if trig and a.dtype == jnp.float64:
            s, co = _trig.sincos(a)
        else:
            s, co = jnp.sin(a), jnp.cos(a)
        return pick(member, [(s, None, None, None), (co, None, None, None)])

    def exponential(a, b, c, member):
        e, em1 = jnp.exp(a), jnp.expm1(a)
        plain = lambda v: (v, None, None, None)
        return pick(
            member,
            [
                plain(e),
                plain(em1),
                plain(jnp.sinh(a)),
                plain(jnp.cosh(a)),
                plain(jnp.tanh(a)),
                plain(jax.nn.sigmoid(a)),
            ],
        )

    def logarithmic(a, b, c, member):
        r = jnp.sqrt(a)
        return pick(
            member,
            [
                (jnp.log(a), None, 1.0 / a, None),
                (jnp.log1p(a), None, 1.0 / (1.0 + a), None),
                (r, None, 1.0 / (2.0 * r), None),
                (a**b, b + 1.0, 1.0 / a, None),
                (jnp.tan(a), None, None, None),
                (jnp.arctan(a), None, 1.0 / b, None),
            ],
        )

    return [arith, trigonometric, exponential, logarithmic]


def _put(C, val, slot, k):
    """`C` with the coefficient `k` of `slot` set to `val` (traced indices)."""
    i32 = lambda i: jnp.asarray(i, jnp.int32)
    return lax.dynamic_update_slice(C, val[None, None, :], (i32(slot), i32(k), i32(0)))


def _initial(tape, K, W, dtype, inputs):
    """Every slot's series: the inputs' (slots 1, 2, ...; each of shape `(W,)`, its
    value, or `(K + 1, W)`), the constants' values at order 0, zeros elsewhere. One
    concatenation: an update per input is a kernel per input in every place the
    interpreter is inlined."""
    S, n = tape.values.shape[0], len(inputs)
    series = lambda u: jnp.zeros((K + 1, W), dtype).at[0].set(jnp.broadcast_to(u, (W,)))
    ins = jnp.stack([u if u.ndim == 2 else series(u) for u in inputs])
    consts = jnp.broadcast_to(tape.values[1 + n :, None, None], (S - 1 - n, 1, W))
    consts = jnp.concatenate([consts, jnp.zeros((S - 1 - n, K, W), dtype)], axis=1)
    return jnp.concatenate([jnp.zeros((1, K + 1, W), dtype), ins, consts])


def _order0(tape, C, trig):
    """Every node at order 0, and each row's `(g, d, mask)` per lane."""
    branches = _order0_branches(trig)
    N, W = tape.ops.shape[0], C.shape[2]
    G = jnp.ones((N, 3, W), C.dtype)
    family, member = jnp.asarray(_FAMILY), jnp.asarray(_MEMBER)

    def node(i, carry):
        C, G = carry
        op, a, b, c, out = (tape.ops[i, j] for j in range(5))
        operands = (C[a, 0], C[b, 0], C[c, 0], member[op])
        val, *gdm = lax.switch(family[op], branches, *operands)
        G = lax.dynamic_update_index_in_dim(G, jnp.stack(gdm), i, 0)
        return _put(C, val, out, 0), G

    return lax.fori_loop(0, tape.n_nodes, node, (C, G))


def _order(tape, C, G, k):
    """Every series node's coefficient `k` (`_FORMS`)."""
    K1 = C.shape[1]
    j = jnp.arange(K1)
    back = jnp.clip(k - j, 0, K1 - 1)
    below = (j <= k).astype(C.dtype)[:, None]
    jk = (j.astype(C.dtype) / k.astype(C.dtype))[:, None]

    def node(i, C):
        row = tape.series[i]
        X, Y, P, Q, out, pick = (tape.forms[row, m] for m in range(6))
        c1, c2, c3, c4 = (tape.coefs[row, m] for m in range(4))
        g, d, mask = G[row, 0], G[row, 1], G[row, 2]
        xk, yk = C[X, k], C[Y, k]
        # (Only the rows with a Cauchy product compute one: a branch on a scalar
        # costs less than a product over every order and lane.)
        product = lambda: jnp.sum(
            (c3 + c4 * jk * g[None]) * C[P] * (C[Q][back] * below), axis=0
        )
        # (Short series: the product always, a branch is kernels of its own.)
        if K1 > 3:
            conv = lax.cond((c3 != 0) | (c4 != 0), product, lambda: jnp.zeros_like(xk))
        else:
            conv = product()
        y = (c1 * xk + c2 * yk + conv) * d
        y = jnp.where(pick != 0, jnp.where(mask != 0, xk, yk), y)
        return _put(C, y, out, k)

    return lax.fori_loop(0, tape.n_series, node, C)


def tape_coefficients(tape: Tape, order: int, s, x, v, params=(), trig=False):
    r"""The Taylor coefficients of $x' = v$, $v' = a$ with $a$ the tape's first
    output and its inputs $(s, x, v, *params)$, about $(s, x, v)$ of every lane:
    `(xs, vs, as_)` of shapes `(K + 1, W)`, `(K + 1, W)`, `(K, W)`, as
    `taylor_coefficients` returns them. `params`: per-lane arrays of shape `(W,)`,
    constant along the step. `trig`: float64 sines and cosines at order 0 by
    `lagrax._jaxpr.trig.sincos` (vectorized) instead of the C library's."""
    K = int(order)
    x = jnp.asarray(x)
    W, dtype = x.shape[0], x.dtype
    lanes = lambda u: jnp.broadcast_to(jnp.asarray(u, dtype), (W,))
    s_h = jnp.zeros((K + 1, W), dtype).at[0].set(lanes(s)).at[1].set(1.0)  # s + h
    ins = [s_h, x, lanes(v), *(lanes(p) for p in params)]
    C = _initial(tape, K, W, dtype, ins)
    C, G = _order0(tape, C, trig)
    out = tape.outputs[0]
    C = C.at[2, 1].set(C[3, 0]).at[3, 1].set(C[out, 0])

    def orders(k, C):
        C = _order(tape, C, G, k)
        # x_{k+1} = v_k/(k+1), v_{k+1} = a_k/(k+1) (slots 2 and 3), read before one
        # update: two updates, the second reading C between them, made XLA copy C.
        both = jnp.stack([C[3, k], C[out, k]]) / (k + 1).astype(dtype)
        i32 = lambda i: jnp.asarray(i, jnp.int32)
        return lax.dynamic_update_slice(C, both[:, None], (i32(2), i32(k + 1), i32(0)))

    if K > 3:
        C = lax.fori_loop(1, K, orders, C)
    else:  # (a few orders written out: a loop is kernels of its own)
        for k in range(1, K):
            C = orders(jnp.asarray(k, jnp.int32), C)
    return C[2], C[3], C[out, :K]


def tape_series(tape: Tape, inputs, order: int = 1, trig=False):
    r"""The series of the tape's outputs to `order`, from its inputs' series
    `inputs` (one array per input, of shape `(order + 1, W)`, or `(W,)` for an
    input fixed at order 0). Returns shape `(outputs, order + 1, W)`: at order 1,
    the values and the derivatives along the direction of the inputs' first
    coefficients."""
    K = int(order)
    first = jnp.asarray(inputs[0])
    W, dtype = first.shape[-1], first.dtype
    C = _initial(tape, K, W, dtype, [jnp.asarray(u, dtype) for u in inputs])
    C, G = _order0(tape, C, trig)
    # (A few orders written out: a loop is kernels of its own.)
    for k in range(1, K + 1):
        C = _order(tape, C, G, jnp.asarray(k, jnp.int32))
    return C[tape.outputs]
