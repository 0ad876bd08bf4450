r"""The compact coefficient program: the recurrences as data (heyoka's compact mode).

`program.py` and `system.py` write the recurrences of a vector field's program out
order by order: XLA compiles one straight-line program per Lagrangian, whose size
grows with orders x nodes and whose compile grows faster still. Here the same
recurrences run in ONE program per *size class*, the equations being data (a
`CompactTape`), as heyoka's compact mode runs them:

- Every node of the flattened program (`_Program`) computes its $k$-th coefficient
    by one of three forms, with $X, Y, P, Q$ its operands' series:

    $$\text{Cauchy: } y_k = d\,\bigl(c_0 X_k + c_1 \textstyle\sum_{j=0}^{k}
    P_j Q_{k-j}\bigr) + e\,\tfrac1k \textstyle\sum_{j=0}^{k} j P_j Q_{k-j},
    \qquad \text{linear: } y_k = s_0 X_k + s_1 Y_k,$$

    with $c, s$ constants of the node (a product $c = (0, 1)$, $d = 1$, $e = 0$; a
    sine with its cosine as $Q$: $c = (0, 0)$, $e = 1$) and $d, e$ (and a linear
    node's $s$ where it depends on the state, e.g. a `where`) per lane, set at
    order 0 (a quotient $u/w$: $d = 1/w_0$). A term whose operand is the node's
    own, still unknown, coefficient $y_k$ reads zero.
- Orders $k \ge 1$ run level by level (a node reads at order $k$ only nodes of
    lower levels); a level is blocks of `Gc` Cauchy nodes, then of `Gl` linear
    nodes with constant and with per-lane coefficients, each block one vectorized
    operation over its nodes and lanes: its operands gathered by index arrays,
    its outputs one contiguous slice of the values of order $k$. A Cauchy sum's
    terms $0 < j < k$ read only orders below $k$: they are summed before the
    levels, once per order for every Cauchy node at once, from *histories* (the
    coefficients of each distinct operand, stored once, order by order, and read
    through each node's indices), one function per order (a switch) so that each
    sums exactly its terms; a block adds the terms $j = 0, k$ with its operands of
    order $k$.
- Order 0 runs level by level too, each level's nodes in blocks of one *family*
    (affine, other arithmetic, logic, sine and cosine, other transcendental, a
    mass-matrix factorization), evaluating the primitives and setting the
    per-lane coefficients.
- The loops over levels, blocks and orders are `lax.fori_loop`s whose bounds and
    index arrays are arguments: the compiled program depends on the tape's sizes
    and the families it holds (its size class), not on the Lagrangian, so one
    executable serves every system of its class and can live in the library's
    disk cache. Inside a caller's `jit` (`lagrax.Taylor` as a diffrax solver) the
    tape is concrete and `inline_coefficients` compiles it alone: the blocks of a
    level merged into one operation with constant indices, unrolled within the
    loop over orders.

`benchmarks/taylor_coefficients.py` measures it against the unrolled program.
"""

import functools
import hashlib
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._jaxpr import trig as _trig


__all__ = ["CompactTape", "build", "compact_coefficients"]

# --- opcodes --------------------------------------------------------------------------

# Order-0 families: each block of order 0 holds nodes of one.
AFFINE, RARE, LOGIC, SINCOS, TRANS = range(5)
_FAMILY_NAMES = ("affine", "rare", "logic", "sincos", "trans")

# name: (order-0 family, form at orders >= 1, the form's operands (a, b, c: the
# node's; "o": its own output; "-": zero), its constant coefficients).
_OPS = {
    "zero": (AFFINE, "cau", ("-", "a", "b"), (0.0, 1.0)),  # sum_j M_j x_{k-j}
    "add": (AFFINE, "slin", ("a", "b"), (1.0, 1.0)),
    "sub": (AFFINE, "slin", ("a", "b"), (1.0, -1.0)),
    "neg": (AFFINE, "slin", ("a", "-"), (-1.0, 0.0)),
    "copy": (AFFINE, "slin", ("a", "-"), (1.0, 0.0)),
    "scalec": (AFFINE, "slin", ("a", "-"), None),  # a * (a literal b)
    "mul": (AFFINE, "cau", ("-", "a", "b"), (0.0, 1.0)),
    "div": (RARE, "cau", ("a", "b", "o"), (1.0, -1.0)),
    "rdiv": (RARE, "cau", ("-", "b", "o"), (0.0, -1.0)),  # a / b, a fixed
    "divc": (RARE, "dlin", ("a", "-"), None),  # a / b, b fixed
    "scale": (RARE, "dlin", ("a", "-"), None),  # a * b, b fixed
    "abs": (RARE, "dlin", ("a", "-"), None),
    "max": (RARE, "dlin", ("a", "b"), None),
    "min": (RARE, "dlin", ("a", "b"), None),
    "select": (RARE, "dlin", ("b", "c"), None),  # select_n(a, b, c): c where a
    "lincomb": (RARE, "dlin", ("a", "b"), None),  # coefficients of a factorization
    "rem": (RARE, "slin", ("a", "-"), (1.0, 0.0)),  # rem(a, b), b fixed
    "sq1p": (RARE, "cau", ("-", "a", "a"), (0.0, 1.0)),  # 1 + a^2
    "sq1m": (RARE, "cau", ("-", "a", "a"), (0.0, -1.0)),  # 1 - a^2
    "logw": (RARE, "cau", ("a", "a", "a"), (1.0, -1.0)),  # a - a^2
    "sin": (SINCOS, "cau", ("-", "a", "b"), (0.0, 0.0)),  # b: its cosine
    "cos": (SINCOS, "cau", ("-", "a", "b"), (0.0, 0.0)),
    "sinh": (TRANS, "cau", ("-", "a", "b"), (0.0, 0.0)),
    "cosh": (TRANS, "cau", ("-", "a", "b"), (0.0, 0.0)),
    "exp": (TRANS, "cau", ("-", "a", "o"), (0.0, 0.0)),
    "expm1": (TRANS, "cau", ("a", "a", "o"), (1.0, 0.0)),
    "log": (TRANS, "cau", ("a", "o", "a"), (1.0, 0.0)),
    "log1p": (TRANS, "cau", ("a", "o", "a"), (1.0, 0.0)),
    "sqrt": (TRANS, "cau", ("a", "o", "o"), (1.0, -1.0)),
    "pow": (TRANS, "cau", ("-", "a", "o"), (0.0, -1.0)),  # a ** b, b fixed
    "tan": (TRANS, "cau", ("-", "a", "b"), (0.0, 0.0)),  # b: 1 + t^2
    "tanh": (TRANS, "cau", ("-", "a", "b"), (0.0, 0.0)),  # b: 1 - t^2
    "atan": (TRANS, "cau", ("a", "o", "b"), (1.0, 0.0)),  # b: 1 + a^2
    "logistic": (TRANS, "cau", ("-", "a", "b"), (0.0, 0.0)),  # b: s - s^2
    **{
        name: (LOGIC, None, (), None)
        for name in (
            "lt",
            "le",
            "gt",
            "ge",
            "eq",
            "ne",
            "and",
            "or",
            "not",
            "xor",
            "is_finite",
            "sign",
            "floor",
            "ceil",
            "round",
        )
    },  # fmt: skip
}
OPCODE = {name: i for i, name in enumerate(_OPS)}
# Which Cauchy operands `(X, P, Q)` a node reads at the same order: the others are
# read at lower orders only (their term at order k weighs nothing, or is the unknown
# itself), and do not order the levels.
_NEEDS = {
    "zero": (False, True, False),
    **{name: (False, True, False) for name in ("sin", "cos", "sinh", "cosh")},
    **{name: (False, True, False) for name in ("tan", "tanh", "logistic")},
    **{name: (True, False, False) for name in ("atan", "log", "log1p")},
}
# Which Cauchy sums a node's form weighs: its plain sum only (products, quotients),
# its weighted sum only (derivatives of functions: sin, exp, ...), or both.
_SUMS = {
    **{
        name: 0
        for name in ("zero", "mul", "div", "rdiv", "sq1p", "sq1m", "logw", "sqrt")
    },
    **{
        name: 1
        for name in (
            "sin", "cos", "sinh", "cosh", "exp", "expm1", "log", "log1p", "tan",
            "tanh", "atan", "logistic",
        )
    },
    "pow": 2,
}  # fmt: skip
# The affine family's order-0 value, alpha a + beta b + gamma a b.
_AFFINE = {
    "zero": (0.0, 0.0, 0.0),
    "add": (1.0, 1.0, 0.0),
    "sub": (1.0, -1.0, 0.0),
    "neg": (-1.0, 0.0, 0.0),
    "copy": (1.0, 0.0, 0.0),
    "mul": (0.0, 0.0, 1.0),
}

# Primitives that, on scalars, only move or retype their operand.
_ALIAS = frozenset(
    {
        "copy", "copy_p", "convert_element_type", "reshape", "squeeze",
        "expand_dims", "broadcast_in_dim", "transpose", "slice", "concatenate",
        "reduce_sum", "reduce_max", "reduce_min", "stop_gradient",
        "reduce_precision", "real", "rev", "optimization_barrier", "stack",
        "dynamic_slice",
    }
)  # fmt: skip
# Primitives that are an opcode under their own name.
_SAME = frozenset(
    {
        "add", "sub", "neg", "abs", "max", "min", "exp", "expm1", "log", "log1p",
        "sqrt", "lt", "le", "gt", "ge", "eq", "ne", "and", "or", "not", "xor",
        "is_finite", "sign", "floor", "ceil", "round",
    }
)  # fmt: skip


class CompactTape(eqx.Module):
    r"""A program as data for `compact_coefficients`: index arrays, constants and
    sizes, so that tapes of one size class (`size`) share one compiled program.

    Slots number the program's variables twice: in *order-0 space* and in *series
    space*, each block's outputs consecutive slots; `perm` maps series space onto
    order-0 space. Both start alike: slot 0 is zero, slot 1 one, then the series
    inputs ($t$, then the state's entries), the per-lane parameters and the
    constants (`values`). `outs`: the slots of $f$'s entries (series space).

    Order 0: `seq0` its blocks in the level order (`(family, block)`; `op0`,
    `arg0` the operands in order-0 space, `out0` the first output and count,
    `prm0` the affine coefficients); `seg0` the blocks before each factorization
    (`fac_m` its matrix's entries, padded with the identity; `fac_dst` where its
    inverse's entries go, as flat indices into the per-lane coefficients; `fac_ok`
    its verdict's slot).

    Orders $\ge 1$: `seq1` the blocks in the level order (`(kind, block,
    count)`) of Cauchy, constant-linear and per-lane-linear nodes: `cgat`,
    `sgat`, `dgat` their operands, `cout` (first output, first history row),
    `sout`, `dout`; `sst` the constant coefficients of linear nodes; `hist` the
    slots whose histories the Cauchy sums read (each row's $P$ and $Q$), `hcst`
    each row's constants $(c_0, c_1)$ and whether it weighs its plain and its
    weighted sum, `hslot` its node's slot; `hnode` the distinct slots of `hist`
    (the operands whose histories the inner sums keep once each, `_operand_sums`)
    and `hidx` each row's $P$ and $Q$ as indices into `hnode`. `blocks`: the
    blocks in use at order 0 and above. `windows`: the inner sums from a history
    per row, a few orders a branch (`_windowed_sums`: a smaller program, whose
    load counts where the work is small, as for the period tier's 1-DOF tapes).
    """

    values: jax.Array
    inputs: jax.Array
    params: jax.Array
    outs: jax.Array
    perm: jax.Array
    seq0: jax.Array
    op0: jax.Array
    arg0: jax.Array
    out0: jax.Array
    prm0: jax.Array
    seg0: jax.Array
    fac_m: jax.Array
    fac_dst: jax.Array
    fac_ok: jax.Array
    cgat: jax.Array
    cout: jax.Array
    sgat: jax.Array
    sout: jax.Array
    sst: jax.Array
    dgat: jax.Array
    dout: jax.Array
    hist: jax.Array
    seq1: jax.Array
    blocks: jax.Array
    hcst: jax.Array
    hslot: jax.Array
    hnode: jax.Array
    hidx: jax.Array
    families: tuple = eqx.field(static=True)
    caps0: tuple = eqx.field(static=True)  # (order-0 blocks per family)
    windows: bool = eqx.field(static=True, default=False)

    @property
    def size(self):
        """What the compiled program is specialized to: the arrays' shapes and the
        order-0 families present."""
        shapes = tuple(
            (name, getattr(self, name).shape)
            for name in (
                "values", "inputs", "params", "seq0", "op0", "fac_m", "cgat",
                "sgat", "dgat", "hist", "hnode", "seq1",
            )
        )  # fmt: skip
        return shapes + (
            ("families", self.families),
            ("caps0", self.caps0),
            ("windows", self.windows),
        )

    def sizes(self) -> dict:
        """The smallest sizes (`build`'s `size`) that give another tape this one's
        size class, or a class that holds both (`join`)."""
        out = dict(
            S=self.values.shape[0],
            NB0=self.seq0.shape[0],
            n=math.isqrt(self.fac_m.shape[1]) if self.fac_m.shape[1] > 1 else 0,
            F=self.fac_m.shape[0] if self.fac_m.shape[1] > 1 else 0,
            H=self.hist.shape[1],
            U=self.hnode.shape[0],
            p=self.params.shape[0],
            NB=self.seq1.shape[0],
            B1cau=self.cgat.shape[0],
            B1slin=self.sgat.shape[0],
            B1dlin=self.dgat.shape[0],
            Gc=self.cgat.shape[2],
            Gl=self.sgat.shape[2],
            G0=self.op0.shape[1],
            families=self.families,
            windows=self.windows,
        )
        out.update({f"B0{f}": cap for f, cap in zip(self.families, self.caps0)})
        return out


def join(*sizes) -> dict:
    """The smallest sizes that hold each of `sizes` (`CompactTape.sizes`)."""
    out = {}
    for size in sizes:
        for key, value in size.items():
            if key == "families":
                out[key] = tuple(sorted(set(out.get(key, ())) | set(value)))
            else:
                out[key] = max(out.get(key, 0), value)
    return out


# --- building -------------------------------------------------------------------------


class _CNode:
    __slots__ = (
        "op", "args", "out", "form", "lvl0", "lvl1", "coef", "affine", "sargs",
        "dropped",
    )  # fmt: skip

    def __init__(self, op, args, out):
        self.op = op
        self.args = tuple(args)  # ids (a, b, c), None where absent
        self.out = out
        self.coef = _OPS[op][3]  # (at orders >= 1)
        self.affine = _AFFINE.get(op)
        self.sargs = None  # (its operands at orders >= 1 where not `args`)
        self.dropped = False  # (not computed at orders >= 1)


class _Factor:
    """One mass-matrix factorization at order 0: `M` ids (row-major), the inverse's
    destinations `(node, coefficient)` per entry, and the verdict's id."""

    __slots__ = ("M", "dst", "ok", "lvl0", "n")

    def __init__(self, M, dst, ok, n):
        self.M, self.dst, self.ok, self.n = M, dst, ok, n
        self.lvl0 = None


def _bucket(n, smallest=1):
    """The smallest power of two at least `n` (and `smallest`)."""
    return max(smallest, 1 << max(0, math.ceil(math.log2(max(n, 1)))))


def _bucket3(n, smallest=1):
    """The smallest power of two, or three times one, at least `n` (and `smallest`):
    for a size that costs in proportion at every order (the history rows)."""
    p = _bucket(n)
    return max(smallest, 3 * p // 4 if p >= 4 and 3 * p // 4 >= n else p)


class _Builder:
    """`_Program` (or `_SystemProgram`) -> compact nodes over integer ids."""

    def __init__(self, prog, inputs, params, outs):
        self.prog = prog
        self.series = set(prog.series)
        self.nodes = []
        self.factors = []
        self.alias = {}
        self.consts = dict(prog.consts)
        self.next = prog._next
        self.inputs = list(inputs)
        self.params = list(params)
        self.outs = list(outs)
        for aval in prog.avals.values():
            if int(np.prod(aval.shape)) != 1:
                raise NotImplementedError("the compact program holds scalars only")
        self.one = self.const(1.0)
        for node in prog.nodes:
            self.node(node)

    def new(self):
        self.next += 1
        return self.next - 1

    def const(self, value):
        i = self.new()
        self.consts[i] = float(value)
        return i

    def literal(self, i):
        """The value of `i` where it is a concrete constant, else None."""
        v = self.consts.get(self.id(i))
        if v is None or isinstance(v, jax.core.Tracer) or np.size(v) != 1:
            return None
        return float(np.asarray(v).reshape(()))

    def id(self, i):
        while i in self.alias:
            i = self.alias[i]
        return i

    def emit(self, op, args, out=None, series=None):
        out = self.new() if out is None else out
        args = [None if a is None else self.id(a) for a in args]
        node = _CNode(op, args, out)
        self.nodes.append(node)
        if series is None:
            series = any(a is not None and a in self.series for a in args)
        if series and _OPS[op][1] is not None:
            self.series.add(out)
        else:
            self.series.discard(out)
        return out

    def node(self, node):
        kind = node.kind
        ins = [self.id(i) for i in node.ins]
        outs = list(node.outs)
        ser = [i in self.series for i in ins]
        if kind in _ALIAS:
            self.alias[outs[0]] = ins[0]
            return
        if kind in ("sincos", "sinhcosh"):
            s, c = outs
            first, second = ("sin", "cos") if kind == "sincos" else ("sinh", "cosh")
            self.emit(first, [ins[0], c], s, series=ser[0])
            self.emit(second, [ins[0], s], c, series=ser[0])
            return
        if kind == "solve":
            return self.solve(node, ins, outs)
        (out,) = outs
        if kind in ("mul", "dot_general"):
            if ser[0] and ser[1]:
                self.emit("mul", ins, out)
            elif ser[0] or ser[1]:
                u, w = ins if ser[0] else ins[::-1]
                lit = self.literal(w)
                if lit is None:
                    self.emit("scale", [u, w], out)
                else:
                    self.emit("scalec", [u, w], out)
                    self.nodes[-1].coef = (lit, 0.0)
                    self.nodes[-1].affine = (lit, 0.0, 0.0)
            else:
                self.emit("mul", ins, out, series=False)
        elif kind == "div":
            if ser[0] and ser[1]:
                self.emit("div", ins, out)
            elif ser[0]:
                lit = self.literal(ins[1])
                if lit is None:
                    self.emit("divc", ins, out)
                else:
                    self.emit("scalec", ins, out)
                    self.nodes[-1].coef = (1.0 / lit, 0.0)
                    self.nodes[-1].affine = (1.0 / lit, 0.0, 0.0)
            elif ser[1]:
                self.emit("rdiv", ins, out)
            else:
                self.emit("div", ins, out, series=False)
        elif kind == "add_any":
            self.emit("add", ins, out)
        elif kind == "select_n":
            if len(ins) != 3:
                raise NotImplementedError("select_n of more than two cases")
            self.emit("select", ins, out, series=ser[1] or ser[2])
        elif kind == "pow":
            if ser[1]:
                raise NotImplementedError("a power with a series exponent")
            self.emit("pow", ins, out)
        elif kind == "rsqrt":
            self.emit("pow", [ins[0], self.const(-0.5)], out)
        elif kind == "cbrt":
            self.emit("pow", [ins[0], self.const(1.0 / 3.0)], out)
        elif kind == "integer_pow" and node.params["y"] == 0:
            self.emit("copy", [self.one], out, series=False)
        elif kind in ("integer_pow", "square"):
            # (Of a series, `_Program` expands it into products: here the operand
            # is fixed along the step, e.g. a per-lane parameter.)
            self.power(ins[0], 2 if kind == "square" else node.params["y"], out)
        elif kind in ("sin", "cos", "sinh", "cosh"):  # (of a fixed operand)
            self.emit(kind, [ins[0], None], out, series=False)
        elif kind in ("tan", "tanh"):
            w = self.new()
            self.emit(kind, [ins[0], w], out)
            self.emit("sq1p" if kind == "tan" else "sq1m", [out], w, series=ser[0])
        elif kind == "atan":
            w = self.emit("sq1p", [ins[0]])
            self.emit("atan", [ins[0], w], out)
        elif kind == "logistic":
            w = self.new()
            self.emit("logistic", [ins[0], w], out)
            self.emit("logw", [out], w, series=ser[0])
        elif kind == "clamp":
            lo, x, hi = ins
            m = self.emit("max", [x, lo])
            self.emit("min", [m, hi], out)
        elif kind == "rem":
            if ser[1]:
                raise NotImplementedError(
                    "rem with a divisor that depends on the state"
                )
            self.emit("rem", ins, out)
        elif kind in _SAME:
            self.emit(kind, ins, out)
        else:
            raise NotImplementedError(f"no compact opcode for the primitive `{kind}`")

    def power(self, u, n, out):
        """`u ** n` (an integer `n != 0`, `u` fixed along the step) by binary
        powering, into `out`."""
        if n < 0:
            w = self.new()
            self.power(u, -n, w)
            self.emit("div", [self.one, w], out, series=False)
            return
        result, base = None, u
        while n:
            if n & 1:
                last = n == 1
                if result is None:
                    result = base
                else:
                    result = self.emit(
                        "mul", [result, base], out if last else None, series=False
                    )
            n >>= 1
            if n:
                base = self.emit("mul", [base, base], series=False)
        if result == u or self.id(result) != self.id(out):
            self.emit("copy", [result], out, series=False)

    def solve(self, node, ins, outs):
        r"""$M x = r$: $s = r - \sum_b M_{ab} x_b$ at orders $\ge 1$ (the sums over
        lower orders of $x$), then $x = M_0^{-1} s$ as linear combinations whose
        coefficients the factorization writes at order 0."""
        n = node.params["n"]
        M, r = ins[: n * n], ins[n * n :]
        xs, ok = outs[:n], outs[n]
        s = []
        for a in range(n):
            terms = [
                self.emit("zero", [M[a * n + b], xs[b]], series=True)
                for b in range(n)
                if M[a * n + b] in self.series
            ]
            s.append(
                self.emit("sub", [r[a], self._tree(terms)], series=True)
                if terms
                else r[a]
            )
        dst = []
        for a in range(n):
            leaves = []
            for b in range(0, n, 2):
                pair = [s[b], s[b + 1] if b + 1 < n else None]
                leaf = self.emit("lincomb", pair, series=True)
                leaves.append(leaf)
                dst += [(leaf, 0)] + ([(leaf, 1)] if b + 1 < n else [])
            self._tree(leaves, out=xs[a])
        self.factors.append(_Factor(list(M), dst, ok, n))

    def _tree(self, ids, out=None):
        """`sum(ids)` by pairwise additions (depth log2), the last one into `out`."""
        ids = list(ids)
        if len(ids) == 1 and out is not None:
            self.emit("copy", ids, out, series=True)
            return out
        while len(ids) > 1:
            nxt = []
            for i in range(0, len(ids) - 1, 2):
                last = len(ids) == 2
                nxt.append(
                    self.emit("add", ids[i : i + 2], out if last else None, series=True)
                )
            if len(ids) % 2:
                nxt.append(ids[-1])
            ids = nxt
        return ids[0]


def _form_operands(node):
    """The form's operand ids, `(X, P, Q)` or `(X, Y)` (None: the zero slot)."""
    where = dict(zip("abc", node.args if node.sargs is None else node.sargs))
    where["o"] = node.out
    where["-"] = None
    return [where.get(name) for name in _OPS[node.op][2]]


# Constant-linear opcodes of one operand, $y = c x$ at orders >= 1 (`rem` by a fixed
# divisor: its derivative is its operand's).
_SCALED = frozenset({"neg", "copy", "scalec", "rem"})
# Products whose plain sum's constant a factor of an operand folds into.
_PRODUCTS = frozenset({"mul", "zero"})


def _fold_scaled(b):
    r"""At orders $\ge 1$, a constant-linear node or a product reads through the
    nodes $u = c\,x$ of one operand among its operands (`_SCALED`: a negation, a
    constant factor, a copy): $s_0 u + s_1 v = (s_0 c) x + s_1 v$, and a product's
    plain sum takes $c$ into its constant ($c_1 \sum P_j Q_{k-j}$ with $P = c x$ is
    $(c_1 c) \sum x_j Q_{k-j}$). A node $u$ that nothing reads at orders $\ge 1$
    then is not computed there: fewer nodes and fewer levels (an expression's
    signs and constant factors cost no block). Order 0 computes every node as
    written."""
    scaled = {}  # u -> (x, c), x itself not of `_SCALED`
    for nd in b.nodes:
        if nd.out not in b.series:
            continue
        form = _OPS[nd.op][1]
        args = list(nd.args)
        coef = nd.coef
        # (The form's terms: which argument each weighs, by `_OPS`' names.)
        terms = [(t, "abc".index(n)) for t, n in enumerate(_OPS[nd.op][2]) if n in "ab"]
        if form == "slin" and coef is not None:
            for t, pos in terms:
                if args[pos] in scaled:
                    args[pos], c = scaled[args[pos]]
                    coef = tuple(w * c if i == t else w for i, w in enumerate(coef))
        elif nd.op in _PRODUCTS:
            c1 = coef[1]
            for _, pos in terms:
                if args[pos] in scaled:
                    args[pos], c = scaled[args[pos]]
                    c1 *= c
            coef = (coef[0], c1)
        if tuple(args) != nd.args:
            nd.sargs, nd.coef = tuple(args), coef
        if nd.op in _SCALED and coef is not None and args[0] in b.series:
            scaled[nd.out] = (args[0], coef[0])
    # The nodes read at orders >= 1 (by a form, or as an output).
    read = {b.id(i) for i in b.outs}
    for nd in b.nodes:
        if nd.out in b.series and _OPS[nd.op][1] is not None:
            read.update(i for i in _form_operands(nd) if i is not None and i != nd.out)
    for nd in b.nodes:
        nd.dropped = nd.out in scaled and nd.out not in read


def _levels(b):
    """Order-0 levels (every operand, and a factorization before its combinations)
    and levels at orders >= 1 (the operands each form needs at the same order)."""
    lvl0, lvl1 = {}, {}
    fac_of = {node_id: f for f in b.factors for node_id, _ in f.dst}
    for node in b.nodes:
        deps = [lvl0.get(a, 0) for a in node.args if a is not None]
        f = fac_of.get(node.out)
        if f is not None:
            if f.lvl0 is None:
                f.lvl0 = 1 + max([lvl0.get(m, 0) for m in f.M] + [0])
                lvl0[f.ok] = f.lvl0
            deps.append(f.lvl0)
        node.lvl0 = 1 + max(deps + [0])
        lvl0[node.out] = node.lvl0
        node.form = _OPS[node.op][1] if node.out in b.series else None
        if node.dropped:
            node.form = None
        if node.form == "slin" and node.op not in _AFFINE and node.coef is None:
            node.form = "dlin"
        if node.form is None:
            continue
        needs = _NEEDS.get(node.op, (True, True, True))
        deps = [
            lvl1.get(i, 0)
            for i, need in zip(_form_operands(node), needs)
            if i is not None and i != node.out and need
        ]
        node.lvl1 = 1 + max(deps + [0])
        lvl1[node.out] = node.lvl1


def _family(node):
    fam = _OPS[node.op][0]
    return fam


def build(
    prog, inputs, params, outs, dtype, Gc=8, Gl=8, G0=16, size=None, traced=False
):
    """The `CompactTape` of a flattened program: `inputs` (ids of $t$ and the
    state's entries), `params` (per-lane parameter ids), `outs` ($f$'s ids).
    `size`: a dict of smallest sizes to pad to, and of the nodes per block (`Gc`
    Cauchy, `Gl` linear nodes at orders >= 1, `G0` at order 0) where it holds
    them (they override the keywords: a tape of few nodes per level, e.g. a
    1-DOF Lagrangian's, runs fastest in narrow blocks, whose padding rows cost
    as much as nodes). `traced=True`: constants that are
    tracers (values of an enclosing trace) become parameters after `params`, and
    the result is `(tape, their values)`.

    **Raises:** `NotImplementedError` where a variable has more than one entry, a
    primitive has no opcode, or (without `traced`) a constant is not concrete."""
    extra = [
        i for i, v in prog.consts.items() if isinstance(v, jax.core.Tracer)
    ]  # (scalars: checked with every variable below)
    if extra and not traced:
        raise NotImplementedError("a compact tape needs concrete constants")
    b = _Builder(prog, inputs, list(params) + extra, outs)
    for i in extra:
        b.consts.pop(i)
    _fold_scaled(b)
    _levels(b)
    dtype = np.dtype(dtype)
    minimum = dict(size or {})
    Gc, Gl, G0 = (minimum.get(k, v) for k, v in (("Gc", Gc), ("Gl", Gl), ("G0", G0)))
    # --- slots common to both spaces: zero, one, inputs, parameters, constants
    fixed = {b.one: 1}
    values = {0: 0.0, 1: 1.0}
    nxt = 2
    for i in b.inputs + b.params:
        fixed[i] = nxt
        nxt += 1
    for i, v in b.consts.items():
        if i in fixed:
            continue
        if isinstance(v, jax.core.Tracer):
            raise NotImplementedError("a compact tape needs concrete constants")
        v = np.asarray(v)
        if v.size != 1:
            raise NotImplementedError("a compact tape holds scalar constants")
        fixed[i] = nxt
        values[nxt] = v.reshape(()).item()
        nxt += 1
    head = nxt
    get0 = get1 = None  # (set below)

    # --- order 0: per level, blocks of one family; factorizations between levels
    fams = sorted({_family(nd) for nd in b.nodes})
    by0 = {}
    for nd in b.nodes:
        by0.setdefault(nd.lvl0, {}).setdefault(_family(nd), []).append(nd)
    levels0 = sorted(by0)
    blocks0 = {f: [] for f in range(len(_FAMILY_NAMES))}
    lev0 = []
    for lvl in levels0:
        row = []
        for f in range(len(_FAMILY_NAMES)):
            nodes = by0[lvl].get(f, [])
            start = len(blocks0[f])
            if f in _ONE_OPCODE:
                groups = {}
                for nd in nodes:
                    groups.setdefault(nd.op, []).append(nd)
            else:
                groups = {None: nodes}
            for group in groups.values():
                blocks0[f] += [group[i : i + G0] for i in range(0, len(group), G0)]
            row.append((start, len(blocks0[f])))
        lev0.append(row)
    order = sorted(range(len(b.factors)), key=lambda i: b.factors[i].lvl0)
    slot0 = dict(fixed)
    cur = head
    for lvl_i, lvl in enumerate(levels0):
        for f in range(len(_FAMILY_NAMES)):
            start, end = lev0[lvl_i][f]
            for nodes in blocks0[f][start:end]:
                for j, nd in enumerate(nodes):
                    slot0[nd.out] = cur + j
                cur += len(nodes)
    for f in b.factors:
        slot0[f.ok] = cur
        cur += 1
    used0 = cur

    # --- orders >= 1: per level, blocks of each form
    # Kinds of block: Cauchy (plain sum, weighted sum, both), linear (constant,
    # per-lane coefficients); a sequence of (kind, block) level by level.
    forms = ("cau", "slin", "dlin")
    by1 = {}
    for nd in b.nodes:
        if nd.form is not None:
            kind = _SUMS[nd.op] if nd.form == "cau" else 2 + forms.index(nd.form)
            by1.setdefault(nd.lvl1, {}).setdefault(kind, []).append(nd)
    levels1 = sorted(by1)
    blocks1 = {form: [] for form in forms}
    seq = []
    slot1 = dict(fixed)
    cur, rows = head, 0
    firsts = {form: [] for form in forms}
    for lvl in levels1:
        for kind in sorted(by1[lvl]):
            nodes = by1[lvl][kind]
            form = "cau" if kind < 3 else forms[kind - 2]
            G = Gc if form == "cau" else Gl
            for i in range(0, len(nodes), G):
                group = nodes[i : i + G]
                seq.append((kind, len(blocks1[form]), len(group)))
                blocks1[form].append(group)
                firsts[form].append((cur, rows))
                for j, nd in enumerate(group):
                    slot1[nd.out] = cur + j
                cur += len(group)
                if form == "cau":
                    rows += len(group)
    # (A block writes a full block of rows: the last one's padding lands before
    # the slots that stay zero above order 0.)
    cur += max(Gc, Gl)
    for nd in b.nodes:
        if nd.out not in slot1:
            slot1[nd.out] = cur
            cur += 1
    for f in b.factors:
        slot1[f.ok] = cur
        cur += 1
    used1 = cur

    # --- sizes (the size class)
    NM = max([f.n for f in b.factors] + [minimum.get("n", 0)])
    F = max(len(b.factors), minimum.get("F", 0))
    S = _bucket(max(used0, used1) + max(G0, Gc, Gl) + 1, minimum.get("S", 64))
    L0 = len(levels0)
    B0 = {f: _bucket(len(blocks0[f]), minimum.get(f"B0{f}", 1)) for f in fams}
    B1 = {
        form: _bucket(len(blocks1[form]), minimum.get(f"B1{form}", 1)) for form in forms
    }
    H = _bucket3(rows + Gc, minimum.get("H", 16))
    P = max(len(b.params), minimum.get("p", 0))
    fams = tuple(sorted(set(fams) | set(minimum.get("families", ()))))
    for f in fams:
        B0.setdefault(f, _bucket(len(blocks0[f]), minimum.get(f"B0{f}", 1)))
    dummy = S - 1
    s0 = lambda i: 0 if i is None else slot0[b.id(i)]
    s1 = lambda i: 0 if i is None else slot1[b.id(i)]
    del get0, get1

    vals = np.zeros((S,), dtype)
    for s_, v in values.items():
        vals[s_] = v
    perm = np.zeros((S,), np.int32)
    for i, s_ in slot1.items():
        perm[s_] = slot0[i]
    # Order 0: the families' blocks concatenated, `lev0` offset to match.
    nF = len(fams)
    offs = np.cumsum([0] + [B0[f] for f in fams])
    B0t = int(offs[-1])
    lev = np.zeros((L0, nF, 2), np.int32)
    op0 = np.full((B0t, G0), OPCODE["zero"], np.int32)
    arg0 = np.zeros((B0t, G0, 3), np.int32)
    out0 = np.zeros((B0t, 2), np.int32)
    out0[:, 0] = used0  # (unused blocks write past the slots in use)
    prm0 = np.zeros((B0t, 3, G0), dtype)
    for lvl_i in range(len(levels0)):
        for fi, f in enumerate(fams):
            start, end = lev0[lvl_i][f]
            lev[lvl_i, fi] = (offs[fi] + start, offs[fi] + end)
    # The blocks in one sequence, level by level: (family, block); a factorization
    # after the blocks of the levels up to its own.
    seq0_list, seg0 = [], []
    for lvl_i, lvl in enumerate(levels0):
        while len(seg0) < len(order) and b.factors[order[len(seg0)]].lvl0 < lvl:
            seg0.append(len(seq0_list))
        for fi in range(nF):
            seq0_list += [(fi, row) for row in range(*lev[lvl_i, fi])]
    seg0 += [len(seq0_list)] * (len(order) + 1 - len(seg0))
    seq0 = np.zeros((_bucket(len(seq0_list), minimum.get("NB0", 4)), 2), np.int32)
    seq0[: len(seq0_list)] = seq0_list
    for fi, f in enumerate(fams):
        for bi, nodes in enumerate(blocks0[f]):
            row = offs[fi] + bi
            out0[row] = (slot0[nodes[0].out], len(nodes))
            for j, nd in enumerate(nodes):
                op0[row, j] = OPCODE[nd.op]
                arg0[row, j] = [s0(a) for a in (nd.args + (None,) * 3)[:3]]
                if nd.affine is not None:
                    prm0[row, :, j] = nd.affine
    fac_m = np.zeros((max(F, 1), max(NM, 1) ** 2), np.int32)
    fac_dst = np.full((max(F, 1), max(NM, 1) ** 2), 2 * S, np.int32)  # (dropped)
    fac_ok = np.full((max(F, 1),), dummy, np.int32)
    for row, fi in enumerate(order):
        f = b.factors[fi]
        for r_ in range(NM):
            for c_ in range(NM):
                if r_ < f.n and c_ < f.n:
                    fac_m[row, r_ * NM + c_] = s0(f.M[r_ * f.n + c_])
                elif r_ == c_:
                    fac_m[row, r_ * NM + c_] = 1  # (the identity beyond n)
        for e, (node_id, c_) in enumerate(f.dst):
            r_, q_ = divmod(e, f.n)
            fac_dst[row, r_ * NM + q_] = 2 * slot0[node_id] + c_
        fac_ok[row] = slot0[f.ok]
    # Orders >= 1.
    cgat = np.zeros((B1["cau"], 3, Gc), np.int32)
    cout = np.full((B1["cau"], 2), (used1, rows), np.int32)
    hcst = np.zeros((4, H), dtype)
    hslot = np.zeros((H,), np.int32)
    sgat = np.zeros((B1["slin"], 2, Gl), np.int32)
    sout = np.full((B1["slin"],), used1, np.int32)
    sst = np.zeros((B1["slin"], 2, Gl), dtype)
    dgat = np.zeros((B1["dlin"], 2, Gl), np.int32)
    dout = np.full((B1["dlin"],), used1, np.int32)
    hist = np.zeros((2, H), np.int32)
    for bi, nodes in enumerate(blocks1["cau"]):
        cout[bi] = firsts["cau"][bi]
        for j, nd in enumerate(nodes):
            ops = _form_operands(nd)
            x, p_, q_ = (s1(i) for i in ops)
            hist[:, firsts["cau"][bi][1] + j] = (p_, q_)
            # This order's P and Q where the sum needs them; zero where they are
            # the node itself (still unknown) or weigh nothing at this order.
            needs = _NEEDS.get(nd.op, (True, True, True))
            now = [s1(i) if need and i != nd.out else 0 for i, need in zip(ops, needs)]
            cgat[bi, :, j] = (x, now[1], now[2])
            row = firsts["cau"][bi][1] + j
            hcst[:, row] = (*nd.coef, _SUMS[nd.op] != 1, _SUMS[nd.op] != 0)
            hslot[row] = firsts["cau"][bi][0] + j
    for bi, nodes in enumerate(blocks1["slin"]):
        sout[bi] = firsts["slin"][bi][0]
        for j, nd in enumerate(nodes):
            sgat[bi, :, j] = [s1(i) for i in _form_operands(nd)]
            sst[bi, :, j] = nd.coef
    for bi, nodes in enumerate(blocks1["dlin"]):
        dout[bi] = firsts["dlin"][bi][0]
        for j, nd in enumerate(nodes):
            dgat[bi, :, j] = [s1(i) for i in _form_operands(nd)]
    seq1 = np.zeros((_bucket(len(seq), minimum.get("NB", 4)), 3), np.int32)
    seq1[: len(seq)] = seq
    # The distinct operands of the rows in use (slot 0 first: the padding rows').
    distinct = np.unique(np.concatenate([[0], hist[:, :rows].reshape(-1)]))
    hnode = np.zeros((_bucket3(distinct.size, minimum.get("U", 16)),), np.int32)
    hnode[: distinct.size] = distinct
    hidx = np.searchsorted(distinct, hist).astype(np.int32)
    P_arr = np.full((P,), dummy, np.int32)
    P_arr[: len(b.params)] = [fixed[b.id(i)] for i in b.params]
    # (NumPy arrays: concrete even where the tape is built inside a trace.)
    as_i = lambda x: np.asarray(x, np.int32)
    tape = CompactTape(
        values=np.asarray(vals),
        inputs=as_i([fixed[b.id(i)] for i in b.inputs]),
        params=as_i(P_arr),
        outs=as_i([s1(i) for i in b.outs]),
        perm=as_i(perm),
        seq0=as_i(seq0),
        op0=as_i(op0),
        arg0=as_i(arg0),
        out0=as_i(out0),
        prm0=np.asarray(prm0),
        seg0=as_i(seg0),
        fac_m=as_i(fac_m),
        fac_dst=as_i(fac_dst),
        fac_ok=as_i(fac_ok),
        cgat=as_i(cgat),
        cout=as_i(cout),
        sgat=as_i(sgat),
        sout=as_i(sout),
        sst=np.asarray(sst),
        dgat=as_i(dgat),
        dout=as_i(dout),
        hist=as_i(hist),
        seq1=as_i(seq1),
        blocks=as_i([len(levels0), len(seq), rows]),
        hcst=np.asarray(hcst),
        hslot=as_i(hslot),
        hnode=as_i(hnode),
        hidx=as_i(hidx),
        families=fams,
        caps0=tuple(B0[f] for f in fams),
        windows=bool(minimum.get("windows", False)),
    )
    if traced:
        return tape, [prog.consts[i] for i in extra]
    return tape


# --- order 0 --------------------------------------------------------------------------


def _pick(op, table, value, d0, d1):
    """The row of `table` whose opcode is `op` (per node): a chain of selects (other
    opcodes keep `value`, `d0`, `d1`). Each row: `(value, (d0, d1) or None)`."""
    for name, (v, ds) in table.items():
        hit = op == OPCODE[name]
        value = v if value is None else jnp.where(hit, v, value)
        if ds is not None:
            d0 = jnp.where(hit, ds[0], d0)
            d1 = jnp.where(hit, ds[1], d1)
    return value, d0, d1


def _affine(op, prm, a, b, c, d0, d1, trig):
    # (Cauchy nodes here have d = 1, e = 0; linear ones constant coefficients.)
    one = jnp.ones_like(a)
    return prm[0] * a + prm[1] * b + prm[2] * (a * b), one, 0.0 * one


def _flt(m, like):
    return m.astype(like.dtype)


def _one(a):
    return jnp.ones_like(a)


# Per opcode of the rare families: `(a, b, c, d0, d1) -> (value, (d0, d1) or None)`
# (None: the per-lane coefficients stay as they are).
_RARE_FNS = {
    "div": lambda a, b, c, d0, d1: (a / b, (1.0 / b, 0.0 * a)),
    "rdiv": lambda a, b, c, d0, d1: (a / b, (1.0 / b, 0.0 * a)),
    "divc": lambda a, b, c, d0, d1: (a / b, (1.0 / b, 0.0 * a)),
    "scale": lambda a, b, c, d0, d1: (a * b, (b, 0.0 * a)),
    "abs": lambda a, b, c, d0, d1: (
        jnp.abs(a),
        (jnp.where(a >= 0, _one(a), -_one(a)), 0.0 * a),
    ),
    "max": lambda a, b, c, d0, d1: (
        jnp.maximum(a, b),
        (_flt(a >= b, a), 1.0 - _flt(a >= b, a)),
    ),
    "min": lambda a, b, c, d0, d1: (
        jnp.minimum(a, b),
        (_flt(a <= b, a), 1.0 - _flt(a <= b, a)),
    ),
    "select": lambda a, b, c, d0, d1: (
        jnp.where(a != 0, c, b),
        (1.0 - _flt(a != 0, a), _flt(a != 0, a)),
    ),
    "lincomb": lambda a, b, c, d0, d1: (d0 * a + d1 * b, None),
    "rem": lambda a, b, c, d0, d1: (lax.rem(a, b), None),
    "sq1p": lambda a, b, c, d0, d1: (1.0 + a * a, (_one(a), 0.0 * a)),
    "sq1m": lambda a, b, c, d0, d1: (1.0 - a * a, (_one(a), 0.0 * a)),
    "logw": lambda a, b, c, d0, d1: (a - a * a, (_one(a), 0.0 * a)),
}
_LOGIC_FNS = {
    "lt": lambda a, b, c, d0, d1: (_flt(a < b, a), None),
    "le": lambda a, b, c, d0, d1: (_flt(a <= b, a), None),
    "gt": lambda a, b, c, d0, d1: (_flt(a > b, a), None),
    "ge": lambda a, b, c, d0, d1: (_flt(a >= b, a), None),
    "eq": lambda a, b, c, d0, d1: (_flt(a == b, a), None),
    "ne": lambda a, b, c, d0, d1: (_flt(a != b, a), None),
    "and": lambda a, b, c, d0, d1: (_flt((a != 0) & (b != 0), a), None),
    "or": lambda a, b, c, d0, d1: (_flt((a != 0) | (b != 0), a), None),
    "not": lambda a, b, c, d0, d1: (_flt(a == 0, a), None),
    "xor": lambda a, b, c, d0, d1: (_flt((a != 0) ^ (b != 0), a), None),
    "is_finite": lambda a, b, c, d0, d1: (_flt(jnp.isfinite(a), a), None),
    "sign": lambda a, b, c, d0, d1: (jnp.sign(a), None),
    "floor": lambda a, b, c, d0, d1: (jnp.floor(a), None),
    "ceil": lambda a, b, c, d0, d1: (jnp.ceil(a), None),
    "round": lambda a, b, c, d0, d1: (jnp.round(a), None),
}


def _sqrt_row(a, b, c, d0, d1):
    r = jnp.sqrt(a)
    return r, (0.5 / r, 0.0 * a)


def _atan_row(a, b, c, d0, d1):
    rw = 1.0 / (1.0 + a * a)
    return jnp.arctan(a), (rw, -rw)


_TRANS_FNS = {
    "sinh": lambda a, b, c, d0, d1: (jnp.sinh(a), (_one(a), _one(a))),
    "cosh": lambda a, b, c, d0, d1: (jnp.cosh(a), (_one(a), _one(a))),
    "exp": lambda a, b, c, d0, d1: (jnp.exp(a), (_one(a), _one(a))),
    "expm1": lambda a, b, c, d0, d1: (jnp.expm1(a), (_one(a), _one(a))),
    "log": lambda a, b, c, d0, d1: (jnp.log(a), (1.0 / a, -1.0 / a)),
    "log1p": lambda a, b, c, d0, d1: (
        jnp.log1p(a),
        (1.0 / (1.0 + a), -1.0 / (1.0 + a)),
    ),
    "sqrt": _sqrt_row,
    "pow": lambda a, b, c, d0, d1: (a**b, (1.0 / a, (b + 1.0) / a)),
    "tan": lambda a, b, c, d0, d1: (jnp.tan(a), (_one(a), _one(a))),
    "tanh": lambda a, b, c, d0, d1: (jnp.tanh(a), (_one(a), _one(a))),
    "atan": _atan_row,
    "logistic": lambda a, b, c, d0, d1: (jax.nn.sigmoid(a), (_one(a), _one(a))),
}


def _switched(fns):
    """A family whose blocks hold one opcode each: a switch on the block's opcode
    evaluates that one only."""
    names = list(fns)
    branch = np.zeros((len(OPCODE),), np.int32)
    for i, name in enumerate(names):
        branch[OPCODE[name]] = i

    def row(fn, a, b, c, d0, d1):
        v, ds = fn(a, b, c, d0, d1)
        return (v, d0, d1) if ds is None else (v, *ds)

    def run(op, prm, a, b, c, d0, d1, trig):
        index = jnp.asarray(branch)[op[0, 0]]
        return lax.switch(
            index, [functools.partial(row, fns[name]) for name in names],
            a, b, c, d0, d1,
        )  # fmt: skip

    return run


def _sincos(op, prm, a, b, c, d0, d1, trig):
    one = jnp.ones_like(a)
    if trig and a.dtype == jnp.float64:
        s, co = _trig.sincos(a)
    else:
        s, co = jnp.sin(a), jnp.cos(a)
    is_sin = op == OPCODE["sin"]
    return jnp.where(is_sin, s, co), one, jnp.where(is_sin, one, -one)


def _chained(fns):
    """A family whose blocks hold one opcode each, for values only: every opcode's
    value over the block and a select by the block's opcode (one loop; a switch
    would be a kernel per opcode, each a part of the executable to load). `rem`,
    a libm call per entry, behind a `cond`."""
    names = [name for name in fns if name not in ("lincomb", "rem")]

    def run(op, prm, a, b, c, trig):
        op = op[0, 0]
        value = a
        for name in names:
            value = jnp.where(op == OPCODE[name], fns[name](a, b, c, a, a)[0], value)
        if "rem" in fns:
            value = lax.cond(op == OPCODE["rem"], lambda: lax.rem(a, b), lambda: value)
        return value

    return run


def _kept(values):
    """A family function from `values`, a function of `(op, prm, a, b, c, trig)`
    whose rows keep their per-lane coefficients (the logic family's)."""
    return lambda op, prm, a, b, c, d0, d1, trig: (
        values(op, prm, a, b, c, trig),
        d0,
        d1,
    )


_FAMILY_FNS = (_affine, _switched(_RARE_FNS), _kept(_chained(_LOGIC_FNS)), _sincos,
               _switched(_TRANS_FNS))  # fmt: skip
_ONE_OPCODE = (RARE, LOGIC, TRANS)  # (families whose blocks hold one opcode)


def _family_fns(opcodes):
    """The families' functions, each switch with a branch per opcode in `opcodes`
    only (a program for one tape: smaller, compiled faster)."""
    pick = lambda fns: (
        {n: f for n, f in fns.items() if OPCODE[n] in opcodes}
        or dict([next(iter(fns.items()))])
    )
    return (_affine, _switched(pick(_RARE_FNS)), _switched(pick(_LOGIC_FNS)),
            _sincos, _switched(pick(_TRANS_FNS)))  # fmt: skip


def _cholesky(A):
    """`solve._cholesky` of `A` (`(n, n, W)`) as loops over its columns and their
    terms: a program whose size does not grow with $n$ (written out, the
    factorization and the inverse are most of a chain's compact program), each
    entry by the same operations in the same order. Returns `(L, 1 / diag(L))`."""
    n, W = A.shape[0], A.shape[2]
    idx = jnp.arange(n)[:, None]
    col_of = lambda X, k: lax.dynamic_index_in_dim(X, k, 1, keepdims=False)

    def column(j, carry):
        Lf, inv = carry
        Lj = lax.dynamic_index_in_dim(Lf, j, 0, keepdims=False)  # (n, W)

        def term(k, s):  # (every entry of column j less its term k)
            return s - col_of(Lf, k) * lax.dynamic_index_in_dim(Lj, k, 0)

        s = lax.fori_loop(0, j, term, col_of(A, j))
        d = jnp.sqrt(lax.dynamic_index_in_dim(s, j, 0))  # NaN where not definite
        r = 1.0 / d
        c = jnp.where(idx > j, s * r, jnp.where(idx == j, d, 0.0))
        Lf = lax.dynamic_update_slice_in_dim(Lf, c[:, None], j, 1)
        return Lf, lax.dynamic_update_slice_in_dim(inv, r, j, 0)

    zero = jnp.zeros((n, n, W), A.dtype)
    return lax.fori_loop(0, n, column, (zero, jnp.zeros((n, W), A.dtype)))


def _inverse(Lf, inv):
    """$(L L^T)^{-1}$ by `solve._substitute` of every column of the identity at
    once, as loops (`(n, n, W)`: row, column, lane)."""
    n, W = inv.shape
    row = lambda X, a: lax.dynamic_index_in_dim(X, a, 0, keepdims=False)
    at = lambda a, b: lax.dynamic_index_in_dim(row(Lf, a), b, 0)  # (1, W)
    eye = jnp.broadcast_to(jnp.eye(n, dtype=inv.dtype)[:, :, None], (n, n, W))

    def forward(a, z):
        s = lax.fori_loop(0, a, lambda b, s: s - at(a, b) * row(z, b), row(eye, a))
        return lax.dynamic_update_slice_in_dim(
            z, (s * lax.dynamic_index_in_dim(inv, a, 0))[None], a, 0
        )

    def backward(i, x):
        a = n - 1 - i
        s = lax.fori_loop(a + 1, n, lambda b, s: s - at(b, a) * row(x, b), row(x, a))
        return lax.dynamic_update_slice_in_dim(
            x, (s * lax.dynamic_index_in_dim(inv, a, 0))[None], a, 0
        )

    z = lax.fori_loop(0, n, forward, jnp.zeros_like(eye))
    return lax.fori_loop(0, n, backward, z)


def _factor(tape, Y, D, row, NM):
    """The inverse of one (padded) mass matrix at order 0, into the per-lane
    coefficients of its combinations; its verdict (`solve.factor`'s) into its
    slot."""
    W = Y.shape[1]
    M = _at(Y, tape.fac_m[row]).reshape(NM, NM, W)
    one = jnp.ones_like(M[0, 0])
    sign = jnp.where(M[0, 0] < 0, -one, one)
    A = sign[None, None] * 0.5 * (M + M.transpose(1, 0, 2))
    Lf, inv = _cholesky(A)
    diag = Lf[jnp.arange(NM), jnp.arange(NM)]
    d2 = diag * diag
    eps = jnp.finfo(Y.dtype).eps
    ok = jnp.all(jnp.isfinite(diag), 0) & (jnp.min(d2, 0) > NM * eps * jnp.max(d2, 0))
    ok = ok & jnp.all(jnp.isfinite(M), (0, 1))
    # (factor works on sign * M, symmetrized: its inverse times sign is M's.)
    Minv = (sign[None, None] * _inverse(Lf, inv)).reshape(NM * NM, W)
    flat = D.reshape((-1, W)).at[tape.fac_dst[row]].set(Minv, mode="drop")
    Y = Y.at[tape.fac_ok[row]].set(ok.astype(Y.dtype))
    return Y, flat.reshape(D.shape)


def _at(Y, idx):
    """`Y[idx]` for an index array into the first axis that is in range by
    construction (the tape's): a gather with its indices clipped, not wrapped
    and checked (fewer operations in the program, none at run time)."""
    return jnp.take(Y, idx, axis=0, mode="clip")


def _bound(x):
    """A loop bound from the tape: a Python int where the tape is concrete (the
    loop then a `scan`, which reverse mode differentiates), else traced."""
    return x if isinstance(x, jax.core.Tracer) else int(x)


def bounds(tape) -> tuple | None:
    """The loop bounds of a concrete tape, `(seg0, blocks, rows)` as Python ints (None
    where the tape is traced)."""
    if isinstance(tape.blocks, jax.core.Tracer) or isinstance(
        tape.seg0, jax.core.Tracer
    ):
        return None
    blocks = np.asarray(tape.blocks)
    return tuple(int(x) for x in np.asarray(tape.seg0)), int(blocks[1]), int(blocks[2])


def _order0(tape, Y, D, trig, seg=None, fns=_FAMILY_FNS):
    """Every node's value (order 0) and per-lane coefficients (order-0 space),
    block by block in the level order, each block's family a switch whose branch
    returns the block's values (small operands: `Y` and `D` are updated in place
    outside it)."""
    G0 = tape.op0.shape[1]
    NM = math.isqrt(tape.fac_m.shape[1])
    W = Y.shape[1]
    i32 = lambda x: jnp.asarray(x, jnp.int32)
    rows = jnp.arange(G0)[:, None]

    def family(fn, bi, Y, old_d):
        op = tape.op0[bi][:, None]
        args = tape.arg0[bi]
        a, b_, c = (_at(Y, args[:, i]) for i in range(3))
        prm = [tape.prm0[bi, i][:, None] for i in range(3)]
        value, d0, d1 = fn(op, prm, a, b_, c, old_d[:, 0], old_d[:, 1], trig)
        return value, jnp.stack([d0, d1], axis=1)

    branches = [functools.partial(family, fns[f]) for f in tape.families]

    def block(i, carry):
        Y, D = carry
        bi = tape.seq0[i, 1]
        start, n = tape.out0[bi, 0], tape.out0[bi, 1]
        old_y = lax.dynamic_slice_in_dim(Y, start, G0, 0)
        old_d = lax.dynamic_slice(D, (start, i32(0), i32(0)), (G0, 2, W))
        value, d = lax.switch(tape.seq0[i, 0], branches, bi, Y, old_d)
        # Rows past the block's nodes keep what is there (another block's, or a
        # factorization's coefficients).
        keep = rows < n
        value = jnp.where(keep, value, old_y)
        d = jnp.where(keep[:, :, None], d, old_d)
        Y = lax.dynamic_update_slice(Y, value, (start, i32(0)))
        return Y, lax.dynamic_update_slice(D, d, (start, i32(0), i32(0)))

    carry = (Y, D)
    F = tape.seg0.shape[0] - 1
    ends = [_bound(tape.seg0[f]) for f in range(F + 1)] if seg is None else seg
    for f in range(F + 1):
        start = ends[f - 1] if f else 0
        carry = lax.fori_loop(start, ends[f], block, carry)
        if f < F and NM:
            carry = _factor(tape, *carry, f, NM)
    return carry


# --- orders >= 1 ----------------------------------------------------------------------


def _tree_sum(xs):
    """`sum(xs)` by pairwise additions: a chain of additions is as long as its
    terms, a tree log2 of it, and the CPU overlaps the independent ones."""
    xs = list(xs)
    while len(xs) > 1:
        xs = [xs[i] + xs[i + 1] for i in range(0, len(xs) - 1, 2)] + xs[len(xs) & ~1 :]
    return xs[0]


def _tree_sum0(x):
    """`_tree_sum(list(x))` of an array along its first axis (the same pairs, the
    same rounding): its levels of an even count as one addition each, of the
    array's even and odd rows (a smaller program than one per pair)."""
    while x.shape[0] > 1 and x.shape[0] % 2 == 0:
        x = x[0::2] + x[1::2]
    return _tree_sum(list(x))


def _window_sums(p, q, plain_rows=slice(None), weighted_rows=slice(None)):
    r"""A window's products $P_i Q_i$ (`p`, `q`: `(span, rows, W)`) summed plain,
    $\sum_i P_i Q_i$, over `plain_rows` and weighted, $\sum_i (i + 1) P_i Q_i$,
    over `weighted_rows`, with `_tree_sum`'s pairs: over every row, the plain sum's
    levels as whole arrays (`_tree_sum0`); over parts of the rows, each sum from
    products of its own. (The weighted terms one by one: summed as one array,
    they round differently.)"""
    every = plain_rows == slice(None) and weighted_rows == slice(None)
    if every:
        pq = p * q
        plain, wq = _tree_sum0(pq), list(pq)
    else:
        of = lambda rows: [p[i, rows] * q[i, rows] for i in range(p.shape[0])]
        plain, wq = _tree_sum(of(plain_rows)), of(weighted_rows)
    weighted = _tree_sum([float(i) * x for i, x in enumerate(wq, 1)])
    return plain, weighted


# Orders per window step of `_windowed_sums` and `_static_sums`.
_SPAN = 4


def _operand_sums(K, C, chunks):
    r"""Every row's Cauchy terms strictly inside the sum, $\sum_{j=1}^{k-1} (u_0 +
    u_1 j / k)\, P_j Q_{k-j}$, for the rows in use (`chunks` chunks of `C` rows),
    from one history per distinct operand (`Hu`: `(K, U, W)`, order first) read
    through the rows' indices (`hidx`: `(2, H)`): rows that share an operand read
    it from one place, which the cache keeps (half the bytes of a history per
    row, whose reads bound these sums). Returns a function of `(k, Hu, hidx, u0,
    u1)`: a loop over the chunks, each a switch on the order, so that each branch
    sums exactly its terms."""

    def branch(k):
        def fn(r, Hu, hidx, u0, u1):
            a, b = (lax.dynamic_slice_in_dim(u, r, C) for u in (u0, u1))
            if k == 1:
                return jnp.zeros_like(a)
            ip, iq = lax.dynamic_slice_in_dim(hidx, r, C, 1)
            pq = [_at(Hu[j], ip) * _at(Hu[k - j], iq) for j in range(1, k)]
            plain = _tree_sum(pq)
            weighted = _tree_sum([float(j) * x for j, x in enumerate(pq, 1)])
            return a * plain + b * (weighted * (1.0 / k))

        return fn

    branches = [branch(k) for k in range(1, K)]

    def sums(k, Hu, hidx, u0, u1):
        def chunk(c, out):
            r = (c * C).astype(jnp.int32)
            value = lax.switch(k - 1, branches, r, Hu, hidx, u0, u1)
            return lax.dynamic_update_slice_in_dim(out, value, r, 0)

        return lax.fori_loop(0, chunks, chunk, jnp.zeros_like(u0))

    return sums


def _windows(K):
    """The number of windows of `_SPAN` orders that the inner terms of orders
    $2..K-1$ need."""
    return max(1, -(-(K - 2) // _SPAN))


def _window_index(k):
    """The window (a branch of `_windowed_sums`, `_static_sums`) whose span fits
    order $k$'s terms."""
    return (jnp.maximum(k, 2) - 2) // _SPAN


def _windowed_sums(K, C, chunks):
    r"""`_operand_sums`' terms for the rows in use (`chunks` chunks of `C` rows),
    from histories per row, `Hp` (`(K + _SPAN, H, W)`) and `R` (`(2K + _SPAN, H,
    W)`) holding $Q_i$
    at $K - i$, both zero where not yet computed: the window $R_{K-k+j} =
    Q_{k-j}$ lines up with $P_j$ and the terms $j \ge k$ read zeros, so that one
    branch serves every order whose terms fit its window, a multiple of `_SPAN`
    orders (a few branches, not one per order: a smaller executable). Returns a
    function of `(k, Hp, R, u0, u1)`: a loop over the chunks, each a switch on
    the window (a branch a kernel, no loop of its own)."""

    def branch(b):
        span = (b + 1) * _SPAN

        def fn(k, r, Hp, R, u0, u1):
            W = Hp.shape[2]
            inv = 1.0 / k.astype(Hp.dtype)
            zero, one = jnp.zeros((), jnp.int32), jnp.ones((), jnp.int32)
            p = lax.dynamic_slice(Hp, (one, r, zero), (span, C, W))
            q = lax.dynamic_slice(R, (K - k + 1, r, zero), (span, C, W))
            plain, weighted = _window_sums(p, q)
            rows = lambda x: lax.dynamic_slice_in_dim(x, r, C)
            return rows(u0) * plain + rows(u1) * (weighted * inv)

        return fn

    branches = [branch(b) for b in range(_windows(K))]

    def sums(k, Hp, R, u0, u1):
        index = _window_index(k)

        def chunk(c, out):
            r = (c * C).astype(jnp.int32)
            value = lax.switch(index, branches, k, r, Hp, R, u0, u1)
            return lax.dynamic_update_slice_in_dim(out, value, r, 0)

        return lax.fori_loop(0, chunks, chunk, jnp.zeros_like(u0))

    return sums


def _row_form(tape, D, P0, Q0):
    r"""Per history row (a Cauchy node), the coefficients $(\alpha, \beta, \gamma)$
    of its order-$k$ operands $(X_k, P_k, Q_k)$ and the weights `(u0, u1)` of the
    terms inside its plain and weighted sums: with them the node's coefficient is
    $\alpha X_k + \beta P_k + \gamma Q_k + \sum_{j=1}^{k-1} (u_0 + u_1 j/k) P_j
    Q_{k-j}$ (the terms $j = 0$ and $j = k$ of its sums in $\beta, \gamma$)."""
    de = _at(D, tape.hslot)
    d, e = de[:, 0], de[:, 1]
    c0, c1, plain, weighted = (tape.hcst[i][:, None] for i in range(4))
    u0 = d * c1 * plain
    u1 = e * weighted
    return jnp.stack([d * c0, (u0 + u1) * Q0, u0 * P0]), u0, u1


def _order_k(tape, Y, F, inner, D, blocks=None):
    r"""Every series node's coefficient $k$ (series space), block by block in the
    level order, from the values of order $k$ that earlier levels computed (`Y`):
    a Cauchy node's as $\alpha X_k + \beta P_k + \gamma Q_k$ plus its inner terms
    (`F`, `inner`: `_row_form`, `_operand_sums` per history row), a linear node's
    from its operands. Each block's form is a switch whose branch returns the
    block's values (small operands, so that `Y` is updated in place outside it)."""
    Gc, Gl = tape.cgat.shape[2], tape.sgat.shape[2]
    G = max(Gc, Gl)
    W = Y.shape[1]
    i32 = lambda x: jnp.asarray(x, jnp.int32)

    def rows(y):
        return (
            y
            if y.shape[0] == G
            else jnp.concatenate([y, jnp.zeros((G - y.shape[0], W), y.dtype)])
        )

    def cau(bi, Y):
        out, row = tape.cout[bi, 0], tape.cout[bi, 1]
        X, Pk, Qk = (_at(Y, tape.cgat[bi, i]) for i in range(3))
        f = lax.dynamic_slice(F, (i32(0), row, i32(0)), (3, Gc, W))
        d = lax.dynamic_slice(inner, (row, i32(0)), (Gc, W))
        return rows(f[0] * X + f[1] * Pk + f[2] * Qk + d), out

    def slin(bi, Y):
        X0, X1 = _at(Y, tape.sgat[bi, 0]), _at(Y, tape.sgat[bi, 1])
        c = tape.sst[bi]
        return rows(c[0][:, None] * X0 + c[1][:, None] * X1), tape.sout[bi]

    def dlin(bi, Y):
        out = tape.dout[bi]
        X0, X1 = _at(Y, tape.dgat[bi, 0]), _at(Y, tape.dgat[bi, 1])
        d = lax.dynamic_slice(D, (out, i32(0), i32(0)), (Gl, 2, W))
        return rows(d[:, 0] * X0 + d[:, 1] * X1), out

    # (The Cauchy kinds, plain, weighted or both sums, differ in `F` only.)
    branch = jnp.asarray([0, 0, 0, 1, 2], jnp.int32)

    def step(i, Y):
        y, out = lax.switch(
            branch[tape.seq1[i, 0]], [cau, slin, dlin], tape.seq1[i, 1], Y
        )
        return lax.dynamic_update_slice(Y, y, (out, i32(0)))

    blocks = _bound(tape.blocks[1]) if blocks is None else blocks
    return lax.fori_loop(0, blocks, step, Y)


def compact_coefficients(
    tape: CompactTape, K: int, t, ys, params, trig=False, bounds=None
):
    r"""The Taylor coefficients $y_0..y_K$ of $y' = f(t, y)$ about $(t, y)$ from the
    tape of $f$'s program: `ys` the state's entries (a list of `(W,)` arrays, the
    order of the tape's inputs after $t$), `params` the per-lane parameters (`(W,)`
    arrays). Returns one list of `K + 1` arrays `(W,)` per entry.

    `trig`: float64 sines and cosines at order 0 by `lagrax._jaxpr.trig.sincos`
    (vectorized) instead of the C library's. `bounds`: the tape's loop bounds as
    Python ints (`bounds`), for a tape passed traced (each loop then a `scan`).
    A concrete tape inside a caller's `jit`: `inline_coefficients`."""
    seg, blocks, rows = (None, None, None) if bounds is None else bounds
    tape = jax.tree.map(jnp.asarray, tape)
    W = t.shape[0]
    dtype = t.dtype
    m = tape.inputs.shape[0]
    i32 = lambda x: jnp.asarray(x, jnp.int32)
    first = tape.inputs[0]  # (the inputs, then the parameters: consecutive slots)
    # --- order 0
    Y, D, state = _inputs0(tape, t, ys, params)
    Y, D = _order0(tape, Y, D, trig, seg)
    Y, D = _at(Y, tape.perm), _at(D, tape.perm)
    # --- orders 1..K-1 of the nodes, 2..K of the state
    P0, Q0 = _at(Y, tape.hist[0]), _at(Y, tape.hist[1])
    F, u0, u1 = _row_form(tape, D, P0, Q0)
    Z = jnp.zeros((m - 1, K + 1, W), dtype)
    Z = Z.at[:, 0].set(state[1:]).at[:, 1].set(_at(Y, tape.outs))
    rows = _bound(tape.blocks[2]) if rows is None else rows
    C = tape.cgat.shape[2]
    chunks = (rows + C - 1) // C
    zero = i32(0)
    if tape.windows:
        # Histories per row, Q's reversed, zero where not yet computed.
        H = tape.hist.shape[1]
        hist = (
            jnp.zeros((K + _SPAN, H, W), dtype).at[0].set(P0),
            jnp.zeros((2 * K + _SPAN, H, W), dtype).at[K].set(Q0),
        )
        windowed = _windowed_sums(K, C, chunks)
        inner_of = lambda k, hist: windowed(k, *hist, u0, u1)

        def store(k, Y, hist):
            def put(c, hist):
                Hp, R = hist
                r = (c * C).astype(jnp.int32)
                at = lax.dynamic_slice_in_dim(tape.hist, r, C, 1)
                Hp = lax.dynamic_update_slice(Hp, _at(Y, at[0])[None], (k, r, zero))
                R = lax.dynamic_update_slice(R, _at(Y, at[1])[None], (K - k, r, zero))
                return Hp, R

            return lax.fori_loop(0, chunks, put, hist)
    else:
        # The operands' histories, order first: each order read is written before.
        U = tape.hnode.shape[0]
        hist = jnp.zeros((K, U, W), dtype).at[0].set(_at(Y, tape.hnode))
        sums = _operand_sums(K, C, chunks)
        inner_of = lambda k, Hu: sums(k, Hu, tape.hidx, u0, u1)
        store = lambda k, Y, Hu: lax.dynamic_update_slice(
            Hu, _at(Y, tape.hnode)[None], (k, zero, zero)
        )

    def order(k, carry):
        Y, hist, Z = carry
        k = k.astype(jnp.int32)
        t_k = jnp.where(k == 1, 1.0, 0.0).astype(dtype) * jnp.ones((1, W), dtype)
        y_k = lax.dynamic_index_in_dim(Z, k, 1, keepdims=False)
        Y = lax.dynamic_update_slice(Y, jnp.concatenate([t_k, y_k]), (first, zero))
        Y = _order_k(tape, Y, F, inner_of(k, hist), D, blocks)
        hist = store(k, Y, hist)
        f = _at(Y, tape.outs) / (k + 1).astype(dtype)
        Z = lax.dynamic_update_slice(Z, f[:, None], (zero, k + 1, zero))
        return Y, hist, Z

    # (Every slot a block writes is written at every order before it is read;
    # the others, constants and parameters, are zero above order 0.)
    carry = (jnp.zeros_like(Y), hist, Z)
    if K > 1:  # (K = 1: the acceleration alone, no order to recur)
        Z = lax.fori_loop(1, K, order, carry)[2]
    return [[Z[i, k] for k in range(K + 1)] for i in range(m - 1)]


# --- a concrete tape, inside a caller's trace -----------------------------------------


def _take(Y, idx):
    """`Y[idx]` for a constant index array: a slice where the indices are
    consecutive, else a gather by constant indices."""
    if idx.shape[0] == 0:
        return Y[:0]
    s, n = int(idx[0]), idx.shape[0]
    if np.array_equal(idx, np.arange(s, s + n)):
        return Y[s : s + n]
    return _at(Y, idx)


def _runs(tape):
    """The blocks at orders >= 1 of a concrete tape merged into *runs*: blocks in
    the level order none of which reads another's outputs (their outputs are
    consecutive slots). Returns `(runs, node)`: per run `(first slot, first node,
    nodes, its operands' slots (3, nodes))`; per node (in the order of their
    slots) its form (0 Cauchy, 1 constant linear, 2 per-lane linear), history row
    (-1 for a linear node), constant coefficients `(2, nodes)` and slot."""
    seq = np.asarray(tape.seq1)[: int(np.asarray(tape.blocks)[1])]
    cgat, cout = np.asarray(tape.cgat), np.asarray(tape.cout)
    sgat, sout, sst = np.asarray(tape.sgat), np.asarray(tape.sout), np.asarray(tape.sst)
    dgat, dout = np.asarray(tape.dgat), np.asarray(tape.dout)
    runs, form, hrow, cst = [], [], [], []
    first = nodes = 0
    for kind, bi, n in seq:
        fm = 0 if kind < 3 else kind - 2
        if fm == 0:
            out, row = (int(x) for x in cout[bi])
            gat = cgat[bi, :, :n]
            hrow += range(row, row + n)
        else:
            out = int((sout if fm == 1 else dout)[bi])
            ops = (sgat if fm == 1 else dgat)[bi, :, :n]
            gat = np.concatenate([ops, np.zeros((1, n), ops.dtype)])
            hrow += [-1] * n
        cst.append(sst[bi, :, :n] if fm == 1 else np.zeros((2, n), sst.dtype))
        form += [fm] * n
        follows = runs and out == runs[-1][0] + runs[-1][2]
        if follows and not ((gat >= first) & (gat < out)).any():
            s, node, count, g = runs[-1]
            runs[-1] = (s, node, count + n, np.concatenate([g, gat], axis=1))
        else:
            first = out
            runs.append((out, nodes, n, gat))
        nodes += n
    node = dict(
        form=np.asarray(form, np.int32),
        hrow=np.asarray(hrow, np.int32),
        cst=np.concatenate(cst, axis=1) if cst else np.zeros((2, 0)),
        slot=np.concatenate([np.arange(s, s + n) for s, _, n, _ in runs] or [[]]),
    )
    return runs, node


def _run_form(node, F, D):
    r"""Per node of the runs (`_runs`), the coefficients $(A_0, A_1, A_2)$ of its
    operands $(X, P, Q)$ at order $k$: a Cauchy node's `_row_form` (`F`, its
    rows in the order of `node["hrow"]`), a linear node's $(s_0, s_1, 0)$,
    constant or per lane (`D`)."""
    W = F.shape[2]
    Fz = jnp.concatenate([F, jnp.zeros((3, 1, W), F.dtype)], axis=1)
    Ac = jnp.take(Fz, node["hrow"], axis=1, mode="clip")  # (a linear node's: zero)
    Dl = _at(D, node["slot"].astype(np.int32))
    form = node["form"][:, None]
    cst = node["cst"].astype(F.dtype)
    A0 = jnp.where(form == 0, Ac[0], jnp.where(form == 2, Dl[:, 0], cst[0][:, None]))
    A1 = jnp.where(form == 0, Ac[1], jnp.where(form == 2, Dl[:, 1], cst[1][:, None]))
    return A0, A1, Ac[2]


def _rows_by_sum(tape):
    """The history rows in use of a concrete tape sorted by the sums they weigh:
    plain only, both, weighted only. Returns `(order, p, w)`: the rows, and the
    ranges `[0, p)` that weigh the plain sum and `[w, rows)` the weighted one."""
    hcst = np.asarray(tape.hcst)[:, : int(np.asarray(tape.blocks)[2])]
    plain, weighted = hcst[2] != 0, hcst[3] != 0
    groups = [plain & ~weighted, plain & weighted, ~plain & weighted]
    order = np.concatenate([np.flatnonzero(g) for g in groups]).astype(np.int32)
    return order, int(plain.sum()), int(groups[0].sum())


def _static_sums(K, u0, u1, p, w):
    r"""`_windowed_sums` over every row in use at once, for rows sorted by
    `_rows_by_sum`: each sum over the rows that weigh it only. Returns `index(k)`
    and the branches, functions of `(k, Hp, R)`."""

    def branch(b):
        span = (b + 1) * _SPAN

        def fn(k, Hp, R):
            inv = 1.0 / k.astype(Hp.dtype)
            q = lax.dynamic_slice_in_dim(R, K - k + 1, span, 0)
            plain, weighted = _window_sums(
                Hp[1 : 1 + span], q, slice(0, p), slice(w, None)
            )
            both = u0[w:p] * plain[w:] + u1[w:p] * (weighted[: p - w] * inv)
            return jnp.concatenate(
                [u0[:w] * plain[:w], both, u1[p:] * (weighted[p - w :] * inv)]
            )

        return fn

    return _window_index, [branch(b) for b in range(_windows(K))]


def _order_k_static(runs, Y, A, inner):
    """`_order_k` for a concrete tape: run by run (`_runs`), each one operation
    over its nodes, its operands gathered by constant indices, its outputs a
    fixed slice."""
    W = Y.shape[1]
    for s, i, n, gat in runs:
        X, P, Q = _take(Y, gat.reshape(-1)).reshape(3, n, W)
        A0, A1, A2 = (a[i : i + n] for a in A)
        Y = Y.at[s : s + n].set(A0 * X + A1 * P + A2 * Q + inner[i : i + n])
    return Y


def inline_coefficients(tape: CompactTape, K: int, t, ys, params, trig=False):
    r"""`compact_coefficients` of a concrete tape, for a program compiled inside a
    caller's `jit` for this tape alone: order 0's switches with the tape's
    opcodes only; at orders $\ge 1$ the blocks merged into runs unrolled, their
    forms and operands' indices constants (no switch, no dynamic index), each
    inner sum over the rows that weigh it, in a loop over orders (a program that
    grows with the tape's levels, not with levels x orders)."""
    static = tape
    opcodes = frozenset(np.unique(np.asarray(tape.op0)).tolist())
    seg, _, _ = bounds(tape)
    tape = jax.tree.map(jnp.asarray, tape)
    W, dtype = t.shape[0], t.dtype
    m = tape.inputs.shape[0]
    first = int(static.inputs[0])
    # --- order 0
    Y, D, state = _inputs0(tape, t, ys, params)
    Y, D = _order0(tape, Y, D, trig, seg, _family_fns(opcodes))
    Y, D = _at(Y, tape.perm), _at(D, tape.perm)
    # --- orders 1..K-1 of the nodes, 2..K of the state
    runs, node = _runs(static)
    rows, p, w = _rows_by_sum(static)
    at_row = np.full((tape.hist.shape[1] + 1,), rows.shape[0], np.int32)
    at_row[rows] = np.arange(rows.shape[0])
    node["hrow"] = at_row[node["hrow"]]  # (a linear node's: past the rows)
    P0, Q0 = _at(Y, tape.hist[0]), _at(Y, tape.hist[1])
    F, u0, u1 = _row_form(tape, D, P0, Q0)
    F, u0, u1, P0, Q0 = F[:, rows], u0[rows], u1[rows], P0[rows], Q0[rows]
    hist = np.asarray(static.hist)[:, rows]
    A = _run_form(node, F, D)
    index, sums = _static_sums(K, u0, u1, p, w)
    # Histories, zero where not yet computed; Q's reversed (`_windowed_sums`).
    Hp = jnp.zeros((K + _SPAN, rows.shape[0], W), dtype).at[0].set(P0)
    R = jnp.zeros((2 * K + _SPAN, rows.shape[0], W), dtype).at[K].set(Q0)
    Z = jnp.zeros((m - 1, K + 1, W), dtype)
    Z = Z.at[:, 0].set(state[1:]).at[:, 1].set(_at(Y, tape.outs))

    def order(k, carry):
        Y, Hp, R, Z = carry
        k = k.astype(jnp.int32)
        t_k = jnp.where(k == 1, 1.0, 0.0).astype(dtype) * jnp.ones((1, W), dtype)
        y_k = lax.dynamic_index_in_dim(Z, k, 1, keepdims=False)
        Y = Y.at[first : first + m].set(jnp.concatenate([t_k, y_k]))
        inner = lax.switch(index(k), sums, k, Hp, R)
        inner = _at(jnp.concatenate([inner, jnp.zeros((1, W), dtype)]), node["hrow"])
        Y = _order_k_static(runs, Y, A, inner)
        PQ = _take(Y, hist.reshape(-1)).reshape(2, 1, -1, W)
        Hp = lax.dynamic_update_index_in_dim(Hp, PQ[0], k, 0)
        R = lax.dynamic_update_index_in_dim(R, PQ[1], K - k, 0)
        f = _at(Y, tape.outs) / (k + 1).astype(dtype)
        return Y, Hp, R, lax.dynamic_update_index_in_dim(Z, f, k + 1, 1)

    # (Every slot a run writes is written at every order before it is read; the
    # others, constants and parameters, are zero above order 0.)
    if K > 1:
        Z = lax.fori_loop(1, K, order, (jnp.zeros_like(Y), Hp, R, Z))[3]
    return [[Z[i, k] for k in range(K + 1)] for i in range(m - 1)]


def _inputs0(tape, t, ys, params):
    """The slots at order 0 before any node: constants, inputs, parameters."""
    W = t.shape[0]
    dtype = t.dtype
    S = tape.values.shape[0]
    Y = jnp.broadcast_to(tape.values[:, None].astype(dtype), (S, W))
    state = jnp.stack([t, *ys])
    P = tape.params.shape[0]
    lanes = list(params) + [jnp.zeros((W,), dtype)] * (P - len(params))
    rows = jnp.concatenate([state, jnp.stack(lanes)]) if P else state
    first = tape.inputs[0]  # (the inputs, then the parameters: consecutive slots)
    Y = lax.dynamic_update_slice(Y, rows, (first, jnp.asarray(0, jnp.int32)))
    return Y, jnp.zeros((S, 2, W), dtype), state


def _first(fn):
    """A family function's value only."""
    return lambda op, prm, a, b, c, trig: fn(op, prm, a, b, c, a, a, trig)[0]


_VALUE_FNS = (_first(_affine), _chained(_RARE_FNS), _chained(_LOGIC_FNS),
              _first(_sincos), _first(_switched(_TRANS_FNS)))  # fmt: skip


def _values0(tape, Y, trig):
    """`_order0`'s values without the per-lane coefficients (for a tape without
    factorizations), block by block: a smaller program (fewer kernels) that runs
    as fast."""
    G0 = tape.op0.shape[1]
    rows = jnp.arange(G0)[:, None]

    def family(fn, bi, Y):
        args = tape.arg0[bi]
        a, b, c = (_at(Y, args[:, i]) for i in range(3))
        prm = [tape.prm0[bi, i][:, None] for i in range(3)]
        return fn(tape.op0[bi][:, None], prm, a, b, c, trig)

    branches = [functools.partial(family, _VALUE_FNS[f]) for f in tape.families]

    def block(i, Y):
        bi = tape.seq0[i, 1]
        start, n = tape.out0[bi, 0], tape.out0[bi, 1]
        old = lax.dynamic_slice_in_dim(Y, start, G0, 0)
        value = lax.switch(tape.seq0[i, 0], branches, bi, Y)
        value = jnp.where(rows < n, value, old)
        return lax.dynamic_update_slice(Y, value, (start, jnp.asarray(0, jnp.int32)))

    return lax.fori_loop(0, _bound(tape.seg0[-1]), block, Y)


def compact_values(tape: CompactTape, t, ys, params, trig=False):
    r"""The values of the tape's outputs (`outs`, its program's $f$) at one point:
    order 0 only, no series. `t`, `ys`, `params` as in `compact_coefficients`;
    returns an array `(outputs, W)`. The same compiled program evaluates any
    tape of its size class at any point."""
    tape = jax.tree.map(jnp.asarray, tape)
    Y, D, _ = _inputs0(tape, t, ys, params)
    if tape.seg0.shape[0] > 1:  # (factorizations: their inverses are in D)
        Y, _ = _order0(tape, Y, D, trig)
    else:
        Y = _values0(tape, Y, trig)
    return _at(Y, _at(tape.perm, tape.outs))


@functools.partial(jax.jit, static_argnames=("K", "trig", "bounds"))
def _jitted(tape, t, ys, params, K, trig, bounds):
    return compact_coefficients(tape, K, t, ys, params, trig, bounds)


class _Concrete:
    """A concrete tape as a static argument of `jax.jit`: equal to another of the
    same contents, so that a program traced again (diffrax traces a step several
    times) finds the first trace."""

    def __init__(self, tape):
        self.tape = tape
        digest = hashlib.sha1()
        for leaf in jax.tree.leaves(tape):
            leaf = np.asarray(leaf)
            digest.update(f"{leaf.dtype}{leaf.shape}".encode() + leaf.tobytes())
        self.key = (digest.hexdigest(), tape.families, tape.caps0)

    def __hash__(self):
        return hash(self.key)

    def __eq__(self, other):
        return isinstance(other, _Concrete) and self.key == other.key


@functools.partial(jax.jit, static_argnames=("tape", "K", "trig"))
def _inline_jitted(tape, t, ys, params, K, trig):
    return inline_coefficients(tape.tape, K, t, ys, params, trig)


# Lanes per pass of the inline program: more lanes run in passes of this many (a
# loop), whose arrays stay in the CPU's caches.
_LANES = 256


def _in_passes(fn, t, ys, params):
    """`fn(t, ys, params)` (lists of `(W,)` arrays in, a list of lists of `(W,)`
    arrays out) over `W > _LANES` lanes in passes of `_LANES` (a `lax.map`), the
    last pass padded with copies of the last lane."""
    W = t.shape[0]
    n = -(-W // _LANES)
    cut = lambda x: jnp.pad(x, (0, n * _LANES - W), mode="edge").reshape(n, _LANES)
    rows = lambda xs: jnp.stack([cut(x) for x in xs], 1) if xs else None

    def one(args):
        t, ys, params = args
        out = fn(t, list(ys), [] if params is None else list(params))
        return jnp.stack([jnp.stack(o) for o in out])

    out = lax.map(one, (cut(t), rows(ys), rows(params)))  # (n, entries, K + 1, C)
    out = jnp.moveaxis(out, 0, 2).reshape(out.shape[1], out.shape[2], -1)[..., :W]
    return [list(o) for o in out]


def traced_once(tape: CompactTape, K: int, t, ys, params, trig=False):
    """`compact_coefficients` of a concrete tape as one `jax.jit` (the tape and
    its loop bounds its arguments): traced once per size class and bounds, and
    inlined where it is staged into a caller's program."""
    return _jitted(tape, t, list(ys), list(params), K, trig, bounds(tape))


def lane_function(tape: CompactTape, K: int, trig=False, inline=False):
    """`(t, ys, params) -> coefficients` of a concrete tape (as `traced_once`) for
    which a caller's `jax.vmap` becomes more lanes of the one program (its arrays
    keep the lanes innermost, where `vmap` would add a leading axis to every
    array, each lane then a strided access). Its derivatives are those of the
    plain program (`jax.custom_jvp`: forward and reverse mode). `inline`: the
    program is compiled inside a caller's `jit`, for this tape alone
    (`inline_coefficients`), over many lanes in passes (`_in_passes`)."""
    from jax import custom_batching

    loops = bounds(tape)
    concrete = _Concrete(tape) if inline else None

    def plain(t, ys, params):
        if inline:
            one = lambda t, ys, params: _inline_jitted(concrete, t, ys, params, K, trig)
            if t.shape[0] > _LANES:
                return _in_passes(one, t, list(ys), list(params))
            return one(t, list(ys), list(params))
        return _jitted(tape, t, list(ys), list(params), K, trig, loops)

    @custom_batching.custom_vmap
    def lanes(t, ys, params):
        return plain(t, ys, params)

    @lanes.def_vmap
    def _rule(axis_size, in_batched, t, ys, params):
        W = t.shape[-1]
        flat = lambda x, batched: x.reshape(-1) if batched else jnp.tile(x, axis_size)
        t_b, ys_b, params_b = in_batched
        out = plain(
            flat(t, t_b),
            [flat(y, b) for y, b in zip(ys, ys_b)],
            [flat(p, b) for p, b in zip(params, params_b)],
        )
        out = jax.tree.map(lambda o: o.reshape(axis_size, W), out)
        return out, jax.tree.map(lambda _: True, out)

    @jax.custom_jvp
    def fn(t, ys, params):
        return lanes(t, ys, params)

    @fn.defjvp
    def _jvp(primals, tangents):
        return jax.jvp(plain, primals, tangents)

    return fn
