r"""Evaluate a small array function as scalar operations, so that XLA fuses it.

Why: the autodiff equations of motion of a Lagrangian written with small vectors
(particle velocities built with `jnp.array`/`jnp.stack`, `T = ½ m v·v`) are, per
lane, a program of tiny arrays: the $n+1$ tangent directions of the forward-over-
reverse pass, the transposes of indexing (`pad`), of `jnp.array` (`slice`), and
`dot_general`/`reduce_sum` over axes of length 2 or 3. Under `vmap` over lanes XLA on
a CPU compiles that into a dozen or more separate loops over the batch, joined by
concatenates, pads, and small reductions it hands to a library call, each loop
writing and re-reading memory, and recomputes shared sines and cosines in several of
them (`benchmarks/eom_overhead.py` compares it with a hand-written closed form, which
is one fused loop). Evaluated entry by entry, the same program is a graph of scalar
operations; under `vmap` every operation is then elementwise over the lanes, and XLA
fuses it into one or two loops, with common subexpressions merged.

`scalarized(f, *args)` traces `f` to a jaxpr once and re-evaluates every equation on
NumPy object arrays of JAX scalars (calls such as a `jax.jit` inside `f` inlined):
elementwise primitives entry by entry, and the structural ones (`broadcast_in_dim`,
`reshape`, `slice`, `pad`, `concatenate`, `transpose`, `dot_general`, `reduce_sum`,
`cumsum`, …) by moving entries around.
The operations and their order are those of `f` (sums in a fixed left-to-right
order), so the results agree with `f` to round-off. A jaxpr with a primitive not
handled here (loops, `cond`, gathers with traced indices, linear-algebra calls,
calls with a custom derivative) or with more than `max_entries` scalar results in
total is evaluated as `f` itself.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np

from . import interpreter


_ELEMENTWISE = frozenset(
    {
        "abs", "acos", "acosh", "add", "add_any", "and", "asin", "asinh", "atan",
        "atan2", "atanh", "cbrt", "ceil", "clamp", "convert_element_type", "copy",
        "copy_p", "cos", "cosh", "digamma", "div", "eq", "erf", "erf_inv", "erfc",
        "exp", "exp2", "expm1", "floor", "ge", "gt", "integer_pow", "is_finite",
        "le", "lgamma", "log", "log1p", "logistic", "lt", "max", "min", "mul", "ne",
        "neg", "nextafter", "not", "or", "pow", "rem", "round", "rsqrt", "select_n",
        "sign", "sin", "sinh", "sqrt", "square", "stop_gradient", "sub", "tan",
        "tanh", "xor",
    }
)  # fmt: skip
_STRUCTURAL = frozenset(
    {
        "broadcast_in_dim", "concatenate", "cumsum", "cumprod", "cummax", "cummin",
        "dot_general", "expand_dims", "iota", "pad", "reduce_max", "reduce_min",
        "reduce_sum", "reshape", "rev", "slice", "split", "squeeze", "stack",
        "transpose", "unstack",
    }
)  # fmt: skip


def _cost(jaxpr) -> float:
    """Scalar results the evaluation would create; `inf` if a primitive is unknown.
    Calls with a custom derivative count as unknown: inlining their primal would
    drop the custom rule from any derivative taken through the result."""
    total = 0
    for eqn in interpreter.equations(jaxpr):
        name = eqn.primitive.name
        if name not in _ELEMENTWISE and name not in _STRUCTURAL:
            return math.inf
        if name == "pad" and any(i for _, _, i in eqn.params["padding_config"]):
            return math.inf
        for v in eqn.outvars:
            total += math.prod(v.aval.shape)
    return total


def _filled(shape, entries):
    """An object array of `shape` holding `entries` (row-major) as they are.

    Filled through a 1-D array: assigning an array-like (a JAX tracer) to the
    element of a 0-d object array would make NumPy try to convert it.
    """
    flat = np.empty(math.prod(shape), dtype=object)
    for i, entry in enumerate(entries):
        flat[i] = entry
    return flat.reshape(shape)


def _objects(x):
    """An object array of the entries of `x` (a JAX or NumPy array or scalar)."""
    shape = np.shape(x)
    return _filled(shape, (x[idx] for idx in np.ndindex(shape)))


def _known(x) -> bool:
    """A value known while tracing (a literal, an iota, a folded constant)."""
    return isinstance(x, np.ndarray | np.generic)


def _is(x, value) -> bool:
    return _known(x) and bool(np.all(x == value))


def _bind(primitive, args, params):
    r"""`primitive.bind(*args, **params)` on scalars, folding known values.

    The tangent directions of the forward-over-reverse pass are mostly zeros; JAX
    cannot drop `x * 0` (it is NaN for infinite `x`) and XLA may not either, so
    without folding they cost as much as the useful arithmetic
    (benchmarks/README.md). Here a known zero or one is folded as JAX's own symbolic
    zero tangents would be: `x * 0 = 0`, `x + 0 = x`, `x * 1 = x`, `0 / x = 0`.
    """
    if all(_known(a) for a in args):
        folded = _fold_exact(primitive.name, args, params)
        if folded is not None:
            return folded
        with jax.ensure_compile_time_eval():
            return np.asarray(primitive.bind(*args, **params))
    name = primitive.name
    if name == "mul":
        a, b = args
        for known, other in ((a, b), (b, a)):
            if _is(known, 0):
                return known
            if _is(known, 1):
                return other
    elif name in ("add", "add_any"):
        a, b = args
        if _is(a, 0):
            return b
        if _is(b, 0):
            return a
    elif name == "sub":
        a, b = args
        if _is(b, 0):
            return a
        if _is(a, 0):
            return jax.lax.neg_p.bind(b)
    elif name == "div":
        a, b = args
        if _is(a, 0) or _is(b, 1):
            return a
    elif name == "select_n" and _known(args[0]):
        return args[1 + int(args[0])]
    return primitive.bind(*args, **params)


# Correctly rounded (IEEE) operations folded by NumPy, bit for bit what XLA gives
# (not max/min: XLA orders -0.0 below +0.0, NumPy returns its first argument):
# each `primitive.bind` on constants compiles an XLA computation once per process,
# which a first sweep would wait for.
_EXACT = {
    "add": np.add,
    "add_any": np.add,  # (tangents' sums)
    "sub": np.subtract,
    "mul": np.multiply,
    "div": np.divide,  # (floats only: integer division rounds another way)
    "neg": np.negative,
    "abs": np.abs,
    "sqrt": np.sqrt,
    "eq": np.equal,
    "ne": np.not_equal,
    "lt": np.less,
    "le": np.less_equal,
    "gt": np.greater,
    "ge": np.greater_equal,
    "and": np.bitwise_and,
    "or": np.bitwise_or,
    "not": np.invert,
    "is_finite": np.isfinite,
}


def _subnormal(x) -> bool:
    return (
        np.issubdtype(x.dtype, np.floating)
        and x != 0
        and bool(np.abs(x) < np.finfo(x.dtype).tiny)
    )


def _fold_exact(name, args, params):
    """`name` on known scalars by NumPy where that is exact, else None. Subnormal
    operands or results are left to XLA, which flushes some of them to zero
    (`sqrt(1e-310)` is 0 there, 1e-155 in NumPy: tests/test_mechanics.py)."""
    arrays = [np.asarray(a) for a in args]
    dtypes = {a.dtype for a in arrays}
    if any(a.shape != () for a in arrays) or any(_subnormal(a) for a in arrays):
        return None
    out = _fold_numpy(name, arrays, dtypes, params)
    return None if out is None or _subnormal(out) else out


def _fold_numpy(name, arrays, dtypes, params):
    if name in _EXACT and len(dtypes) == 1:
        if name in ("sqrt", "div") and not np.issubdtype(arrays[0].dtype, np.floating):
            return None
        with np.errstate(all="ignore"):
            return np.asarray(_EXACT[name](*arrays))
    if name == "select_n" and len(set(a.dtype for a in arrays[1:])) == 1:
        return np.asarray(arrays[1 + int(arrays[0])])
    if name == "convert_element_type":
        new = np.dtype(params["new_dtype"])
        old = arrays[0].dtype
        if new.kind == "f" and old.kind in "fb" or new == old:
            return np.asarray(arrays[0].astype(new))
    return None


def _add(a, b):
    return _bind(jax.lax.add_p, (a, b), {})


def _mul(a, b):
    return _bind(jax.lax.mul_p, (a, b), interpreter.mul_params())


def _fold(f, values):
    """`f` applied left to right: `f(f(v0, v1), v2)`..."""
    values = list(values)
    acc = values[0]
    for v in values[1:]:
        acc = f(acc, v)
    return acc


def _sum(values):
    return _fold(_add, values)


def _to_end(x, axes):
    """`x` with `axes` moved last and flattened into one: shape (rest..., k)."""
    rest = [d for d in range(x.ndim) if d not in axes]
    moved = np.transpose(x, rest + list(axes))
    k = math.prod(x.shape[d] for d in axes)
    return moved.reshape([x.shape[d] for d in rest] + [k])


def _const(value, aval):
    """A constant or a literal as an object array (of JAX scalars where traced)."""
    known = isinstance(value, np.ndarray) or not isinstance(value, jax.core.Tracer)
    return _objects(np.asarray(value) if known else value)


def _rule(eqn, ins):
    outs = _apply(eqn, ins)
    if not eqn.primitive.multiple_results:
        outs = [outs]
    # Indexing an object array down to one entry gives the entry itself.
    return [out if isinstance(out, np.ndarray) else _filled((), [out]) for out in outs]


def _apply(eqn, ins):  # noqa: C901 - one branch per primitive reads best
    name = eqn.primitive.name
    p = eqn.params
    if name in _ELEMENTWISE:
        shape = eqn.outvars[0].aval.shape
        ins = [np.broadcast_to(x, shape) for x in ins]
        return _filled(
            shape,
            (_bind(eqn.primitive, [x[i] for x in ins], p) for i in np.ndindex(shape)),
        )
    x = ins[0] if ins else None
    if name == "broadcast_in_dim":
        shape = p["shape"]
        expanded = [1] * len(shape)
        for i, d in enumerate(p["broadcast_dimensions"]):
            expanded[d] = x.shape[i]
        return np.broadcast_to(x.reshape(expanded), shape).copy()
    if name == "reshape":
        return x.reshape(p["new_sizes"])
    if name == "squeeze":
        return np.squeeze(x, axis=tuple(p["dimensions"]))
    if name == "expand_dims":
        return np.expand_dims(x, tuple(p["dimensions"]))
    if name == "transpose":
        return np.transpose(x, p["permutation"])
    if name == "rev":
        return np.flip(x, axis=tuple(p["dimensions"]))
    if name == "concatenate":
        return np.concatenate(ins, axis=p["dimension"])
    if name == "stack":
        return np.stack(ins, axis=p["axis"])
    if name == "unstack":
        return list(np.moveaxis(x, p["axis"], 0))
    if name == "split":
        return np.split(x, np.cumsum(p["sizes"])[:-1], axis=p["axis"])
    if name == "slice":
        strides = p["strides"] or (1,) * x.ndim
        index = zip(p["start_indices"], p["limit_indices"], strides)
        return x[tuple(slice(a, b, s) for a, b, s in index)]
    if name == "pad":
        value = ins[1][()]
        out = x
        for axis, (lo, hi, _) in enumerate(p["padding_config"]):
            keep = [slice(None)] * out.ndim
            keep[axis] = slice(max(-lo, 0), out.shape[axis] - max(-hi, 0))
            kept = out[tuple(keep)]

            def fill(width, kept=kept, axis=axis):
                shape = list(kept.shape)
                shape[axis] = width
                return [_filled(shape, [value] * math.prod(shape))] if width > 0 else []

            out = np.concatenate([*fill(lo), kept, *fill(hi)], axis=axis)
        return out
    if name in ("reduce_sum", "reduce_max", "reduce_min"):
        f = {"reduce_sum": None, "reduce_max": jnp.maximum, "reduce_min": jnp.minimum}
        flat = _to_end(x, tuple(p["axes"]))
        shape = flat.shape[:-1]
        if flat.shape[-1] == 0:
            empty = {"reduce_sum": 0, "reduce_max": -np.inf, "reduce_min": np.inf}
            value = np.asarray(empty[name], eqn.outvars[0].aval.dtype)
            return _filled(shape, [value] * math.prod(shape))
        fold = _sum if f[name] is None else lambda v: _fold(f[name], v)
        return _filled(shape, (fold(flat[i]) for i in np.ndindex(shape)))
    if name == "dot_general":
        y = ins[1]
        (lc, rc), (lb, rb) = p["dimension_numbers"]
        lf = [d for d in range(x.ndim) if d not in lc and d not in lb]
        rf = [d for d in range(y.ndim) if d not in rc and d not in rb]
        batch = [x.shape[d] for d in lb]
        free_x = [x.shape[d] for d in lf]
        free_y = [y.shape[d] for d in rf]
        k = math.prod(x.shape[d] for d in lc)
        xm = np.transpose(x, [*lb, *lf, *lc]).reshape(batch + free_x + [k])
        ym = np.transpose(y, [*rb, *rf, *rc]).reshape(batch + free_y + [k])
        zero = np.zeros((), eqn.outvars[0].aval.dtype)

        def entry(b, i, j):
            u, v = xm[b + i], ym[b + j]
            return _sum(_mul(a, c) for a, c in zip(u, v)) if len(u) else zero

        return _filled(
            tuple(batch + free_x + free_y),
            (
                entry(b, i, j)
                for b in np.ndindex(*batch)
                for i in np.ndindex(*free_x)
                for j in np.ndindex(*free_y)
            ),
        )
    if name in ("cumsum", "cumprod", "cummax", "cummin"):
        op = {
            "cumsum": _add,
            "cumprod": _mul,
            "cummax": jnp.maximum,
            "cummin": jnp.minimum,
        }[name]
        moved = np.moveaxis(x, p["axis"], -1)
        rows = []
        for idx in np.ndindex(moved.shape[:-1]):
            values = list(moved[idx])
            if p["reverse"]:
                values = values[::-1]
            acc = [values[0]]
            for v in values[1:]:
                acc.append(op(acc[-1], v))
            rows.extend(acc[::-1] if p["reverse"] else acc)
        return np.moveaxis(_filled(moved.shape, rows), -1, p["axis"])
    if name == "iota":
        shape, dim = p["shape"], p["dimension"]
        axis = np.arange(shape[dim], dtype=p["dtype"])
        along = [-1 if d == dim else 1 for d in range(len(shape))]
        return _objects(np.broadcast_to(axis.reshape(along), shape))
    raise NotImplementedError(name)  # pragma: no cover - `_cost` screens these out


def scalarized(f, *args, max_entries=20_000):
    """`f(*args)` for a function of arrays returning a tuple of arrays, evaluated
    entry by entry when its jaxpr allows (see the module docstring), else as is."""
    closed, shapes = jax.make_jaxpr(f, return_shape=True)(*args)
    if _cost(closed.jaxpr) > max_entries:
        return f(*args)
    flat = [_objects(jnp.asarray(a)) for a in jax.tree.leaves(args)]
    outs = interpreter.evaluate(closed.jaxpr, closed.consts, flat, _rule, const=_const)
    arrays = []
    for out, aval in zip(outs, closed.out_avals):
        entries = [jnp.asarray(v, aval.dtype) for v in out.reshape(-1)]
        if entries:
            arrays.append(jnp.stack(entries).reshape(aval.shape))
        else:
            arrays.append(jnp.zeros(aval.shape, aval.dtype))
    return jax.tree.unflatten(jax.tree.structure(shapes), arrays)
