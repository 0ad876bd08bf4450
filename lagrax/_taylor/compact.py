r"""The compact coefficient program: the recurrences as data (heyoka's compact mode).

`program.py` and `system.py` write the recurrences of a vector field's program out
order by order: XLA compiles one straight-line program per Lagrangian, whose size
grows with orders x nodes and whose compile grows faster still. Here the same
recurrences run in ONE program per *size class*, the equations being data:

- Every variable of the flattened program (`_Program`) is a *slot* of one tape
    `T[slot, order, lane]`, order 0 its value.
- Orders $k \ge 1$: the nodes are grouped by dependency level (a node reads at
    order $k$ only nodes of lower levels) into *blocks* of at most `Gc` Cauchy and
    `Gl` linear nodes, each block one vectorized operation over its nodes and lanes,
    its operands gathered by index arrays, its outputs written as one contiguous
    slice. Two forms cover every recurrence of `recurrences.py`:

    $$\text{linear: } y_k = c_0 X_k + c_1 Y_k,\qquad
    \text{Cauchy: } y_k = c_3\Bigl(c_0 X_k + \sum_{j=0}^{k}
    \bigl(c_1 + c_2 \tfrac{j}{k}\bigr) P_j Q_{k-j}\Bigr),$$

    with per-lane coefficients $c$ set at order 0 (e.g. $c_3 = 1/w_0$ for a quotient
    $u/w$; a product of series has $c = (0, 1, 0, 1)$; a sine $s$ with its cosine
    $c$, $P = u$, $Q = c$, $c_2 = 1$). A term whose operand is the node's own, still
    unknown, coefficient $y_k$ reads zero: the tape's orders above 0 start at zero
    in every step.
- Order 0: the nodes grouped by level and *family* (arithmetic, transcendental, a
    mass-matrix factorization), each block evaluating its family's functions on
    gathered operands and selecting by opcode, and writing each node's value and
    coefficients.
- The loop over blocks is a `lax.fori_loop` whose length and index arrays are
    arguments: the compiled program depends on the tape's sizes (a size class), not
    on the Lagrangian, so one executable serves every system of its class and lives
    in the library's disk cache. The orders are written out (their Cauchy sums then
    have exactly $k + 1$ terms).

`benchmarks/taylor_coefficients.py` measures it against the unrolled program.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._jaxpr import trig as _trig


__all__ = ["CompactTape", "build", "compact_coefficients"]

# --- opcodes --------------------------------------------------------------------------
#
# Each opcode: its order-0 family, its form at orders >= 1 ("cau", "lin" or None),
# where the form's operands come from (a, b, c: the node's operands; "o": its own
# output; "-": the zero slot), and which of them the form needs at the same order
# (`_NEEDS`; the others are read at lower orders only, and do not order the levels).

_COMMON, _RARE, _LOGIC, _TRANS = 0, 1, 2, 3

_OPS = {
    # name: (family, form, operands of the form)
    "zero": (_COMMON, "cau", ("-", "a", "b")),  # sum_j M_j x_{k-j} (x_k still zero)
    "copy": (_COMMON, "lin", ("a", "-")),
    "add": (_COMMON, "lin", ("a", "b")),
    "sub": (_COMMON, "lin", ("a", "b")),
    "neg": (_COMMON, "lin", ("a", "-")),
    "mul": (_COMMON, "cau", ("-", "a", "b")),
    "scale": (_COMMON, "lin", ("a", "-")),  # a * b, b fixed along the step
    "div": (_RARE, "cau", ("a", "b", "o")),
    "divc": (_RARE, "lin", ("a", "-")),  # a / b, b fixed
    "rdiv": (_RARE, "cau", ("-", "b", "o")),  # a / b, a fixed
    "abs": (_RARE, "lin", ("a", "-")),
    "max": (_RARE, "lin", ("a", "b")),
    "min": (_RARE, "lin", ("a", "b")),
    "select": (_COMMON, "lin", ("b", "c")),  # select_n(a, b, c): c where a
    "rem": (_RARE, "lin", ("a", "-")),  # rem(a, b), b fixed
    "sq1p": (_RARE, "cau", ("-", "a", "a")),  # 1 + a^2
    "sq1m": (_RARE, "cau", ("-", "a", "a")),  # 1 - a^2
    "logw": (_RARE, "cau", ("a", "a", "a")),  # a - a^2
    "lincomb": (_COMMON, "lin", ("a", "b")),  # coefficients from a factorization
    # order 0 only (piecewise constant):
    "lt": (_LOGIC, None, ()),
    "le": (_LOGIC, None, ()),
    "gt": (_LOGIC, None, ()),
    "ge": (_LOGIC, None, ()),
    "eq": (_LOGIC, None, ()),
    "ne": (_LOGIC, None, ()),
    "and": (_LOGIC, None, ()),
    "or": (_LOGIC, None, ()),
    "not": (_LOGIC, None, ()),
    "xor": (_LOGIC, None, ()),
    "is_finite": (_LOGIC, None, ()),
    "sign": (_LOGIC, None, ()),
    "floor": (_LOGIC, None, ()),
    "ceil": (_LOGIC, None, ()),
    "round": (_LOGIC, None, ()),
    # transcendental
    "sin": (_TRANS, "cau", ("-", "a", "b")),  # b: the partner cosine
    "cos": (_TRANS, "cau", ("-", "a", "b")),
    "sinh": (_TRANS, "cau", ("-", "a", "b")),
    "cosh": (_TRANS, "cau", ("-", "a", "b")),
    "exp": (_TRANS, "cau", ("-", "a", "o")),
    "expm1": (_TRANS, "cau", ("a", "a", "o")),
    "log": (_TRANS, "cau", ("a", "o", "a")),
    "log1p": (_TRANS, "cau", ("a", "o", "a")),
    "sqrt": (_TRANS, "cau", ("a", "o", "o")),
    "pow": (_TRANS, "cau", ("-", "a", "o")),  # a ** b, b fixed
    "tan": (_TRANS, "cau", ("-", "a", "b")),  # b: 1 + t^2
    "tanh": (_TRANS, "cau", ("-", "a", "b")),  # b: 1 - t^2
    "atan": (_TRANS, "cau", ("a", "o", "b")),  # b: 1 + a^2
    "logistic": (_TRANS, "cau", ("-", "a", "b")),  # b: s - s^2
}
OPCODE = {name: i for i, name in enumerate(_OPS)}
# Operands of a Cauchy form read at lower orders only (their term at order k has a
# zero weight, or is the unknown itself): X, P, Q needed at the same order?
_NEEDS = {
    "zero": (False, True, False),
    "sin": (False, True, False),
    "cos": (False, True, False),
    "sinh": (False, True, False),
    "cosh": (False, True, False),
    "tan": (False, True, False),
    "tanh": (False, True, False),
    "logistic": (False, True, False),
    "atan": (True, False, False),
    "log": (True, False, False),
    "log1p": (True, False, False),
}

# Primitives that, on scalars, only move or retype their operand.
_ALIAS = frozenset(
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
        "reduce_sum",
        "reduce_max",
        "reduce_min",
        "stop_gradient",
        "reduce_precision",
        "real",
        "rev",
        "optimization_barrier",
    }
)
_SAME = frozenset(
    {
        "add",
        "sub",
        "neg",
        "abs",
        "max",
        "min",
        "rem",
        "exp",
        "expm1",
        "log",
        "log1p",
        "sqrt",
        "tanh",
        "tan",
        "atan",
        "logistic",
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
    }
)


class CompactTape(eqx.Module):
    r"""A program as data for `compact_coefficients`; every field an array, so that
    tapes of one size class (`size`) share one compiled program.

    Slots number the program's variables twice: in *order-0 space* and in *series
    space*, where the outputs of each block of order 0, respectively of the orders
    above, are consecutive slots (`G0`, respectively `Gc + Gl` per block, from slot
    `head`); `perm` maps series space onto order-0 space. Both start alike: slot 0
    is zero, slot 1 one, then the series inputs ($t$, then the state's entries),
    the per-lane parameters and the constants.

    - `values` `(S,)`: each slot's order-0 value where it is a constant;
        `inputs` `(m,)`, `params` `(p,)`: their slots; `outs` `(m - 1,)`: $f$'s
        entries (series space);
    - order 0, per block: `fam0` `(B0,)` its family, `op0` `(B0, G0)` the opcodes
        and `args0` `(B0, G0, 3)` the operands (order-0 space); `seg0` `(F + 1,)`
        the blocks before each factorization; `fac_m` `(F, n^2)` each mass matrix's
        entries (row-major, padded with the identity), `fac_dst` `(F, n^2)` where
        its inverse's entries go (flat indices `4 slot + c` into the coefficients)
        and `fac_ok` `(F,)` its verdict's slot;
    - orders $\ge 1$, per block: `gat` `(B1, 3 Gc + 2 Gl)` the operands (series
        space: the Cauchy nodes' $X$, $P$, $Q$, the linear nodes' $X$, $Y$) and
        `rows` `(B1,)` its first row of the histories; `hist` `(2, H)` the slots
        whose histories the Cauchy sums read (each row's $P$ and $Q$);
    - `blocks` `(2,)`: the blocks in use at order 0 and above.
    """

    values: jax.Array
    inputs: jax.Array
    params: jax.Array
    outs: jax.Array
    perm: jax.Array
    head: jax.Array
    fam0: jax.Array
    op0: jax.Array
    args0: jax.Array
    base0: jax.Array
    seg0: jax.Array
    fac_m: jax.Array
    fac_dst: jax.Array
    fac_ok: jax.Array
    gat: jax.Array
    base1: jax.Array
    hist: jax.Array
    blocks: jax.Array
    Gc: int = eqx.field(static=True)
    Gl: int = eqx.field(static=True)

    @property
    def size(self):
        """The shapes the compiled program is specialized to."""
        return tuple(
            (name, getattr(self, name).shape)
            for name in ("values", "inputs", "params", "op0", "fac_m", "gat", "hist")
        ) + (("G", (self.Gc, self.Gl)),)


# --- building -------------------------------------------------------------------------


class _CNode:
    __slots__ = ("op", "args", "out", "form", "lvl0", "lvl1", "deps0")

    def __init__(self, op, args, out):
        self.op = op
        self.args = tuple(args)  # ids (a, b, c), None where absent
        self.out = out


class _Factor:
    """One mass-matrix factorization at order 0: `M` ids (row-major), the inverse's
    destinations `(node, coefficient)` per entry, and the verdict's id."""

    __slots__ = ("M", "dst", "ok", "lvl0", "n")

    def __init__(self, M, dst, ok, n):
        self.M, self.dst, self.ok, self.n = M, dst, ok, n


def _bucket(n, smallest=1):
    """The smallest power of two at least `n` (and `smallest`)."""
    return max(smallest, 1 << max(0, math.ceil(math.log2(max(n, 1)))))


class _Builder:
    """`_Program` (or `_SystemProgram`) -> compact nodes over integer ids."""

    def __init__(self, prog, inputs, params, outs):
        self.prog = prog
        self.series = set(prog.series)
        self.nodes = []  # _CNode
        self.factors = []
        self.alias = {}
        self.extra_consts = {}  # id -> value
        self.next = prog._next
        self.inputs = list(inputs)
        self.params = list(params)
        self.outs = list(outs)
        for avals in prog.avals.values():
            if int(np.prod(avals.shape)) != 1:
                raise NotImplementedError("the compact program holds scalars only")
        self.one = self.const(1.0)
        for node in prog.nodes:
            self.node(node)

    def new(self):
        self.next += 1
        return self.next - 1

    def const(self, value):
        i = self.new()
        self.extra_consts[i] = float(value)
        return i

    def id(self, i):
        while i in self.alias:
            i = self.alias[i]
        return i

    def is_series(self, i):
        return self.id(i) in self.series

    def emit(self, op, args, out=None, series=None):
        out = self.new() if out is None else out
        args = [None if a is None else self.id(a) for a in args]
        self.nodes.append(_CNode(op, args, out))
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
            if ins[0] in self.series:
                self.series.add(outs[0])
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
                self.emit("scale", [u, w], out)
            else:
                self.emit("mul", ins, out, series=False)
        elif kind == "div":
            if ser[0] and ser[1]:
                self.emit("div", ins, out)
            elif ser[0]:
                self.emit("divc", ins, out)
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
                raise NotImplementedError("rem with a divisor that depends on the state")
            self.emit("rem", ins, out)
        elif kind in _SAME:
            self.emit(kind, ins, out)
        else:
            raise NotImplementedError(f"no compact opcode for the primitive `{kind}`")

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
            acc = r[a]
            if terms:
                total = self._tree(terms)
                acc = self.emit("sub", [r[a], total], series=True)
            s.append(acc)
        dst = []
        for a in range(n):
            leaves = []
            for b in range(0, n, 2):
                pair = [s[b], s[b + 1] if b + 1 < n else None]
                leaf = self.emit("lincomb", pair, series=True)
                leaves.append(leaf)
                dst.append((leaf, 0))
                if b + 1 < n:
                    dst.append((leaf, 1))
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
    """The form's operand ids `(X, P, Q)` or `(X, Y)` (None: the zero slot)."""
    family, form, names = _OPS[node.op]
    where = dict(zip("abc", node.args), o=node.out)
    where["-"] = None
    return [where.get(name) for name in names]


def _levels(b):
    """Order-0 levels (every operand, and a factorization before its combinations)
    and levels at orders >= 1 (the operands each form needs at the same order)."""
    lvl0, lvl1 = {}, {}
    fac_of = {}
    for f in b.factors:
        for node_id, _ in f.dst:
            fac_of[node_id] = f
    for f in b.factors:
        f.lvl0 = None
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
        if node.form is None:
            continue
        operands = _form_operands(node)
        needs = _NEEDS.get(node.op, (True, True, True))
        deps = [
            lvl1.get(i, 0)
            for i, need in zip(operands, needs)
            if i is not None and i != node.out and need
        ]
        node.lvl1 = 1 + max(deps + [0])
        lvl1[node.out] = node.lvl1


def build(prog, inputs, params, outs, dtype, Gc=8, Gl=8, G0=16, size=None):
    """The `CompactTape` of a flattened program: `inputs` (ids of $t$ and the
    state's entries), `params` (per-lane parameter ids), `outs` ($f$'s ids).
    `size`: a dict of smallest sizes to pad to."""
    b = _Builder(prog, inputs, params, outs)
    _levels(b)
    dtype = np.dtype(dtype)
    # --- slots common to both spaces: zero, one, inputs, parameters, constants
    fixed = {b.one: 1}
    values = {0: 0.0, 1: 1.0}
    nxt = 2
    for i in b.inputs + b.params:
        fixed[i] = nxt
        nxt += 1
    consts = dict(prog.consts)
    consts.update(b.extra_consts)
    for i, v in consts.items():
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
    # --- order 0: blocks of one level and family, the factorizations between
    by0 = {}
    for nd in b.nodes:
        by0.setdefault((nd.lvl0, _OPS[nd.op][0]), []).append(nd)
    factors = sorted(range(len(b.factors)), key=lambda f: b.factors[f].lvl0)
    blocks0, seg0 = [], []
    fi = 0
    for lvl, fam in sorted(by0):
        while fi < len(factors) and b.factors[factors[fi]].lvl0 < lvl:
            seg0.append(len(blocks0))
            fi += 1
        nodes = by0[lvl, fam]
        for i in range(0, len(nodes), G0):
            blocks0.append((fam, nodes[i : i + G0]))
    seg0 += [len(blocks0)] * (len(factors) - fi + 1)
    slot0 = dict(fixed)
    cur = head
    base0 = []
    for fam, nodes in blocks0:
        base0.append((cur, len(nodes)))
        for j, nd in enumerate(nodes):
            slot0[nd.out] = cur + j
        cur += len(nodes)
    for f in b.factors:
        slot0[f.ok] = cur
        cur += 1
    used0 = cur
    # --- orders >= 1: per level, blocks of Gc Cauchy and Gl linear nodes
    by1 = {}
    for nd in b.nodes:
        if nd.form is not None:
            by1.setdefault(nd.lvl1, ([], []))[nd.form == "lin"].append(nd)
    blocks1 = []
    for lvl in sorted(by1):
        cs, ls = by1[lvl]
        for i in range(max(-(-len(cs) // Gc), -(-len(ls) // Gl))):
            blocks1.append((cs[i * Gc : (i + 1) * Gc], ls[i * Gl : (i + 1) * Gl]))
    slot1 = dict(fixed)
    rows, cur = 0, head
    base1 = []
    for cs, ls in blocks1:
        base1.append((cur, cur + len(cs), rows))
        for j, nd in enumerate(cs + ls):
            slot1[nd.out] = cur + j
        cur += len(cs) + len(ls)
        rows += len(cs)
    for nd in b.nodes:
        if nd.out not in slot1:
            slot1[nd.out] = cur
            cur += 1
    for f in b.factors:
        slot1[f.ok] = cur
        cur += 1
    used1 = cur
    # --- sizes (the size class)
    minimum = dict(size or {})
    NM = max([f.n for f in b.factors] + [minimum.get("n", 0)])
    F = max(len(b.factors), minimum.get("F", 0))
    B0 = _bucket(len(blocks0), minimum.get("B0", 4))
    B1 = _bucket(len(blocks1), minimum.get("B1", 4))
    # (Each block writes a full block of rows from its first output.)
    S = _bucket(max(used0, used1) + max(G0, Gc + Gl) + 1, minimum.get("S", 64))
    H = _bucket(rows + Gc, minimum.get("H", 16))
    P = max(len(b.params), minimum.get("p", 0))
    dummy = S - 1
    s0 = lambda i: 0 if i is None else slot0[b.id(i)]
    s1 = lambda i: 0 if i is None else slot1[b.id(i)]
    vals = np.zeros((S,), dtype)
    for s_, v in values.items():
        vals[s_] = v
    perm = np.zeros((S,), np.int32)
    for i, s_ in slot1.items():
        perm[s_] = slot0[i]
    fam0 = np.zeros((B0,), np.int32)
    op0 = np.full((B0, G0), OPCODE["zero"], np.int32)
    args0 = np.zeros((B0, G0, 3), np.int32)
    b0 = np.zeros((B0, 2), np.int32)
    for bi, (fam, nodes) in enumerate(blocks0):
        fam0[bi] = fam
        b0[bi] = base0[bi]
        for j, nd in enumerate(nodes):
            op0[bi, j] = OPCODE[nd.op]
            args0[bi, j] = [s0(a) for a in (nd.args + (None,) * 3)[:3]]
    fac_m = np.zeros((max(F, 1), max(NM, 1) ** 2), np.int32)
    fac_dst = np.full((max(F, 1), max(NM, 1) ** 2), 4 * S, np.int32)  # (dropped)
    fac_ok = np.full((max(F, 1),), dummy, np.int32)
    for row, fi in enumerate(factors):
        f = b.factors[fi]
        for r_ in range(NM):
            for c_ in range(NM):
                if r_ < f.n and c_ < f.n:
                    fac_m[row, r_ * NM + c_] = s0(f.M[r_ * f.n + c_])
                elif r_ == c_:
                    fac_m[row, r_ * NM + c_] = 1  # (the identity beyond n)
        for e, (node_id, c_) in enumerate(f.dst):
            r_, q_ = divmod(e, f.n)
            fac_dst[row, r_ * NM + q_] = 4 * slot0[node_id] + c_
        fac_ok[row] = slot0[f.ok]
    gat = np.zeros((B1, 3 * Gc + 2 * Gl), np.int32)
    b1 = np.full((B1, 3), (used1, used1, rows), np.int32)
    hist = np.zeros((2, H), np.int32)
    for bi, (cs, ls) in enumerate(blocks1):
        b1[bi] = base1[bi]
        for j, nd in enumerate(cs):
            ops = _form_operands(nd)
            x, p_, q_ = (s1(i) for i in ops)
            hist[:, base1[bi][2] + j] = (p_, q_)
            # This order's P and Q where the sum needs them; zero where they are
            # the node itself (still unknown) or weigh nothing at this order.
            needs = _NEEDS.get(nd.op, (True, True, True))
            now = [s1(i) if need and i != nd.out else 0 for i, need in zip(ops, needs)]
            gat[bi, [j, Gc + j, 2 * Gc + j]] = (x, now[1], now[2])
        for j, nd in enumerate(ls):
            x, y = (s1(i) for i in _form_operands(nd))
            gat[bi, [3 * Gc + j, 3 * Gc + Gl + j]] = (x, y)
    P_arr = np.full((P,), dummy, np.int32)
    P_arr[: len(b.params)] = [fixed[b.id(i)] for i in b.params]
    as_i = lambda x: jnp.asarray(x, jnp.int32)
    return CompactTape(
        values=jnp.asarray(vals),
        inputs=as_i([fixed[b.id(i)] for i in b.inputs]),
        params=as_i(P_arr),
        outs=as_i([s1(i) for i in b.outs]),
        perm=as_i(perm),
        head=as_i(head),
        fam0=as_i(fam0),
        op0=as_i(op0),
        args0=as_i(args0),
        base0=as_i(b0),
        seg0=as_i(seg0),
        fac_m=as_i(fac_m),
        fac_dst=as_i(fac_dst),
        fac_ok=as_i(fac_ok),
        gat=as_i(gat),
        base1=as_i(b1),
        hist=as_i(hist),
        blocks=as_i([len(blocks0), len(blocks1)]),
        Gc=Gc,
        Gl=Gl,
    )


# --- the program ---------------------------------------------------------------------


def _common(op, a, b, c, coef):
    """Order-0 value and coefficients `(c0, c1, c2, c3)` of the common opcodes:
    every one computed, the node's picked (cheap elementwise work, once a step)."""
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    p = (a != 0).astype(a.dtype)
    lin = lambda c0, c1: (c0, c1, zero, zero)
    table = {
        "zero": (zero, (zero, one, zero, one)),
        "copy": (a, lin(one, zero)),
        "add": (a + b, lin(one, one)),
        "sub": (a - b, lin(one, -one)),
        "neg": (-a, lin(-one, zero)),
        "mul": (a * b, (zero, one, zero, one)),
        "scale": (a * b, lin(b, zero)),
        "select": (jnp.where(a != 0, c, b), lin(one - p, p)),
        "lincomb": (coef[0] * a + coef[1] * b, lin(coef[0], coef[1])),
    }
    return _pick(op, table, coef)


def _rare(op, a, b, c, coef):
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    flt = lambda m: m.astype(a.dtype)
    rb = 1.0 / b
    mx, mn = flt(a >= b), flt(a <= b)
    lin = lambda c0, c1: (c0, c1, zero, zero)
    table = {
        "div": (a * rb, (one, -one, zero, rb)),
        "divc": (a * rb, lin(rb, zero)),
        "rdiv": (a * rb, (zero, -one, zero, rb)),
        "abs": (jnp.abs(a), lin(jnp.where(a >= 0, one, -one), zero)),
        "max": (jnp.maximum(a, b), lin(mx, one - mx)),
        "min": (jnp.minimum(a, b), lin(mn, one - mn)),
        "rem": (lax.rem(a, b), lin(one, zero)),
        "sq1p": (one + a * a, (zero, one, zero, one)),
        "sq1m": (one - a * a, (zero, -one, zero, one)),
        "logw": (a - a * a, (one, -one, zero, one)),
    }
    return _pick(op, table, coef)


def _logic(op, a, b, c, coef):
    truth = lambda x: x != 0
    flt = lambda m: m.astype(a.dtype)
    table = {
        "lt": (flt(a < b), None),
        "le": (flt(a <= b), None),
        "gt": (flt(a > b), None),
        "ge": (flt(a >= b), None),
        "eq": (flt(a == b), None),
        "ne": (flt(a != b), None),
        "and": (flt(truth(a) & truth(b)), None),
        "or": (flt(truth(a) | truth(b)), None),
        "not": (flt(~truth(a)), None),
        "xor": (flt(truth(a) ^ truth(b)), None),
        "is_finite": (flt(jnp.isfinite(a)), None),
        "sign": (jnp.sign(a), None),
        "floor": (jnp.floor(a), None),
        "ceil": (jnp.ceil(a), None),
        "round": (jnp.round(a), None),
    }
    return _pick(op, table, coef)


def _trans(op, a, b, c, coef, trig):
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    if trig and a.dtype == jnp.float64:
        s, co = _trig.sincos(a)
    else:
        s, co = jnp.sin(a), jnp.cos(a)
    der = (zero, zero, one, one)  # (1/k) sum_j j P_j Q_{k-j}
    r = jnp.sqrt(a)
    w = one + a * a
    table = {
        "sin": (s, der),
        "cos": (co, (zero, zero, -one, one)),
        "sinh": (jnp.sinh(a), der),
        "cosh": (jnp.cosh(a), der),
        "exp": (jnp.exp(a), der),
        "expm1": (jnp.expm1(a), (one, zero, one, one)),
        "log": (jnp.log(a), (one, zero, -one, 1.0 / a)),
        "log1p": (jnp.log1p(a), (one, zero, -one, 1.0 / (one + a))),
        "sqrt": (r, (one, -one, zero, 1.0 / (2.0 * r))),
        "pow": (a**b, (zero, -one, b + 1.0, 1.0 / a)),
        "tan": (jnp.tan(a), der),
        "tanh": (jnp.tanh(a), der),
        "atan": (jnp.arctan(a), (one, zero, -one, 1.0 / w)),
        "logistic": (jax.nn.sigmoid(a), der),
    }
    return _pick(op, table, coef)


def _pick(op, table, coef):
    """The row of `table` whose opcode is `op` (per node): a chain of selects
    (opcodes without coefficients keep `coef`)."""
    value, coefs = None, list(coef)
    for name, (v, cs) in table.items():
        hit = op == OPCODE[name]
        value = v if value is None else jnp.where(hit, v, value)
        if cs is not None:
            coefs = [jnp.where(hit, x, y) for x, y in zip(cs, coefs)]
    return value, coefs


def _factor(tape, Y, C, row, NM):
    """The inverse of one (padded) mass matrix at order 0, into the coefficients of
    its combinations; its verdict into its slot."""
    from .solve import _substitute, factor

    W = Y.shape[1]
    ent = Y[tape.fac_m[row]]  # (NM*NM, W)
    M = [[ent[r * NM + c] for c in range(NM)] for r in range(NM)]
    sign, Lf, inv, ok = factor(M, NM)
    cols = []
    for c in range(NM):
        e = [jnp.full((W,), 1.0 if r == c else 0.0, Y.dtype) for r in range(NM)]
        cols.append(_substitute(Lf, inv, e, NM))
    # (factor works on sign * M, symmetrized: its inverse times sign is M's.)
    Minv = jnp.stack([sign * cols[c][r] for r in range(NM) for c in range(NM)])
    flat = C.reshape((-1, W)).at[tape.fac_dst[row]].set(Minv, mode="drop")
    Y = Y.at[tape.fac_ok[row]].set(ok.astype(Y.dtype))
    return Y, flat.reshape(C.shape)


def _order0(tape, Y, C, trig):
    """Every node's value (order 0) and coefficients, block by block (order-0
    space), each block's family chosen by a switch on its operands' values."""
    G0 = tape.op0.shape[1]
    NM = math.isqrt(tape.fac_m.shape[1])
    W = Y.shape[1]
    i32 = lambda x: jnp.asarray(x, jnp.int32)
    families = [_common, _rare, _logic, lambda *a: _trans(*a, trig)]
    rows = jnp.arange(G0)[:, None]

    def block(bi, carry):
        Y, C = carry
        ops = tape.op0[bi][:, None]
        args = tape.args0[bi]
        start, n = tape.base0[bi, 0], tape.base0[bi, 1]
        a, b_, c = (Y[args[:, i]] for i in range(3))
        coef = lax.dynamic_slice(C, (start, i32(0), i32(0)), (G0, 4, W))
        old = lax.dynamic_slice_in_dim(Y, start, G0, 0)
        value, cs = lax.switch(
            tape.fam0[bi],
            [lambda *x, fn=fn: fn(*x) for fn in families],
            ops, a, b_, c, [coef[:, i] for i in range(4)],
        )  # fmt: skip
        # Rows past the block's nodes keep what is there (a factorization's
        # coefficients for a later block).
        keep = rows < n
        value = jnp.where(keep, value, old)
        cs = jnp.where(keep[:, :, None], jnp.stack(cs, axis=1), coef)
        Y = lax.dynamic_update_slice(Y, value, (start, i32(0)))
        C = lax.dynamic_update_slice(C, cs, (start, i32(0), i32(0)))
        return Y, C

    carry = (Y, C)
    F = tape.seg0.shape[0] - 1
    for f in range(F + 1):
        start = tape.seg0[f - 1] if f else 0
        carry = lax.fori_loop(start, tape.seg0[f], block, carry)
        if f < F and NM:
            carry = _factor(tape, *carry, f, NM)
    return carry


def _order_k(tape, Y, Hp, Hq, C, k):
    """Every series node's coefficient $k$ (series space), block by block: the
    Cauchy sums from the histories of orders below $k$ and the values of order $k$
    computed by earlier blocks (`Y`, zero where not yet computed)."""
    Gc, Gl = tape.Gc, tape.Gl
    W = Y.shape[1]
    i32 = lambda x: jnp.asarray(x, jnp.int32)
    jw = np.arange(k + 1, dtype=np.float64) / k

    def block(bi, Y):
        cs, ls, sb = (tape.base1[bi, i] for i in range(3))
        G = Y[tape.gat[bi]]
        X, Pk, Qk = G[:Gc], G[Gc : 2 * Gc], G[2 * Gc : 3 * Gc]
        X0, X1 = G[3 * Gc : 3 * Gc + Gl], G[3 * Gc + Gl :]
        P = lax.dynamic_slice(Hp, (sb, i32(0), i32(0)), (Gc, k, W))
        Q = lax.dynamic_slice(Hq, (sb, i32(0), i32(0)), (Gc, k, W))
        # sum_{j=0}^{k} P_j Q_{k-j}: the end terms from this order's values.
        end = Pk * Q[:, 0]
        s0 = P[:, 0] * Qk + end
        s1 = end
        for j in range(1, k):
            term = P[:, j] * Q[:, k - j]
            s0 = s0 + term
            s1 = s1 + jw[j] * term
        cc = lax.dynamic_slice(C, (cs, i32(0), i32(0)), (Gc, 4, W))
        cl = lax.dynamic_slice(C, (ls, i32(0), i32(0)), (Gl, 2, W))
        yc = cc[:, 3] * (cc[:, 0] * X + cc[:, 1] * s0 + cc[:, 2] * s1)
        yl = cl[:, 0] * X0 + cl[:, 1] * X1
        # (The linear nodes' rows follow the Cauchy nodes' and overwrite the
        # padding of `yc`; theirs runs into the next block's, written later.)
        Y = lax.dynamic_update_slice(Y, yc, (cs, i32(0)))
        return lax.dynamic_update_slice(Y, yl, (ls, i32(0)))

    return lax.fori_loop(0, tape.blocks[1], block, Y)


def compact_coefficients(tape: CompactTape, K: int, t, ys, params, trig=False):
    r"""The Taylor coefficients $y_0..y_K$ of $y' = f(t, y)$ about $(t, y)$ from the
    tape of $f$'s program: `ys` the state's entries (a list of `(W,)` arrays, the
    order of the tape's inputs after $t$), `params` the per-lane parameters (`(W,)`
    arrays). Returns one list of `K + 1` arrays `(W,)` per entry."""
    W = t.shape[0]
    dtype = t.dtype
    S = tape.values.shape[0]
    m = tape.inputs.shape[0]
    i32 = lambda x: jnp.asarray(x, jnp.int32)
    first = tape.inputs[0]  # (the inputs, then the parameters: consecutive slots)
    # --- order 0
    Y = jnp.broadcast_to(tape.values[:, None].astype(dtype), (S, W))
    state = jnp.stack([t, *ys])
    P = tape.params.shape[0]
    lanes = list(params) + [jnp.zeros((W,), dtype)] * (P - len(params))
    rows = jnp.concatenate([state, jnp.stack(lanes)]) if P else state
    Y = lax.dynamic_update_slice(Y, rows, (first, i32(0)))
    C = jnp.zeros((S, 4, W), dtype)
    Y, C = _order0(tape, Y, C, trig)
    Y, C = Y[tape.perm], C[tape.perm]
    # --- orders 1..K-1, the state's 2..K
    H = tape.hist.shape[1]
    Hp = jnp.zeros((H, K, W), dtype).at[:, 0].set(Y[tape.hist[0]])
    Hq = jnp.zeros((H, K, W), dtype).at[:, 0].set(Y[tape.hist[1]])
    out = [state[1:], Y[tape.outs]]
    zero_t = jnp.zeros((1, W), dtype)
    # (Every slot a block writes is written at every order before it is read;
    # the others, constants and parameters, are zero above order 0.)
    Y = jnp.zeros((S, W), dtype)
    for k in range(1, K):
        t_k = (zero_t + 1.0) if k == 1 else zero_t
        Y = lax.dynamic_update_slice(Y, jnp.concatenate([t_k, out[k]]), (first, i32(0)))
        Y = _order_k(tape, Y, Hp, Hq, C, k)
        if k < K - 1:
            Hp = Hp.at[:, k].set(Y[tape.hist[0]])
            Hq = Hq.at[:, k].set(Y[tape.hist[1]])
        out.append(Y[tape.outs] * (1.0 / (k + 1)))
    stacked = jnp.stack(out, axis=1)  # (m - 1, K + 1, W)
    return [[stacked[i, k] for k in range(K + 1)] for i in range(m - 1)]
