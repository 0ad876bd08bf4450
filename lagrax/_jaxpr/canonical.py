r"""A Lagrangian as what it computes: its jaxpr, with its constants lifted out.

The compiled period programs are cached per Lagrangian. Keyed on the Python function,
a new closure with the same body (`make(g)` called again, a parameter scan, an
objective that rebuilds `L` at each evaluation) compiles again, seconds for the same
program. `canonical_lagrangian(L, dtype)` traces `L` once at the sweep's shapes and
returns a function that evaluates that jaxpr with

- its floating-point constants as arguments: arrays `L` closes over, tracers of an
    enclosing transformation (as `jax.closure_convert` does), and the floating-point
    scalars that Python folded into literals (`m * g * r` of a closure becomes one
    literal `1.0` in the jaxpr);
- equality and hash by the jaxpr's structure: its equations, their parameters and
    the literals it keeps (integer literals: indices, exponents), never by the
    values lifted out.

Two Lagrangians with the same body and different parameter values then share one
canonical function (interned: the same object), so every cache keyed on it, and the
compiled programs behind them, serve both; the values reach the program as its
`consts` arguments.

Only the top level of the jaxpr is lifted: literals inside a nested `jit` stay in
its parameters and take part in the comparison, so such a Lagrangian hits the cache
only with equal values there. Parameters whose equality is object identity (the
rule of a `custom_jvp` defined inside the closure) make a new closure a new key:
a missed reuse, never a wrong one.

Tracing `L` costs a fraction of a millisecond, a tenth of a small sweep, so the result
is kept per function object with a fingerprint of everything the function reads from
outside its arguments: its code and defaults, its closure cells and the globals (and
builtins) its code names, recursively through the plain Python functions among them;
numbers by value, NumPy arrays by their bytes, containers by their contents, JAX
arrays and library modules and functions by identity (a `jax.jit` function is traced
once by JAX itself, which ignores later changes of the globals it reads). A call whose
fingerprint differs traces again. Where a read cannot be fingerprinted (an object with
attributes, a user module, a tracer of an enclosing transformation, a callable object,
a large array), `L` is traced at every call.
"""

import builtins
import collections
import functools
import types
import weakref
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np
from jax.extend import core as jex_core


__all__ = ["BoundLagrangian", "canonical_lagrangian"]

# Canonical functions by structure, most recently used last; bounded like the
# caches of compiled programs that hold them.
_INTERNED: collections.OrderedDict = collections.OrderedDict()
_MAX_INTERNED = 256


class CanonicalLagrangian:
    """`L(q, qdot, t, *consts)` evaluated from a jaxpr; equal by structure."""

    __slots__ = ("jaxpr", "lifted", "n_params", "key", "_hash", "__weakref__")

    def __init__(self, jaxpr, lifted, n_params, key):
        self.jaxpr = jaxpr
        self.lifted = lifted  # {(equation index, operand index): position in consts}
        self.n_params = n_params
        self.key = key
        self._hash = hash(key)

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return self is other or (
            isinstance(other, CanonicalLagrangian) and self.key == other.key
        )

    def __call__(self, q, qdot, t, *consts):
        jaxpr = self.jaxpr
        env = {}
        n = self.n_params

        def read(i, j, a):
            if isinstance(a, jex_core.Literal):
                k = self.lifted.get((i, j))
                return a.val if k is None else consts[n + k]
            return env[a]

        for v, x in zip(jaxpr.invars, (q, qdot, t, *consts[:n])):
            env[v] = x
        for v, k in zip(jaxpr.constvars, range(len(jaxpr.constvars))):
            env[v] = consts[n + len(self.lifted) + k]
        for i, eqn in enumerate(jaxpr.eqns):
            ins = [read(i, j, a) for j, a in enumerate(eqn.invars)]
            with eqn.ctx.manager:
                out = eqn.primitive.bind(
                    *ins, **eqn.primitive.get_bind_params(eqn.params)
                )
            outs = out if eqn.primitive.multiple_results else [out]
            for v, o in zip(eqn.outvars, outs):
                env[v] = o
        (out,) = [read(-1, j, a) for j, a in enumerate(jaxpr.outvars)]
        return out


class _WithParameters(eqx.Module):
    """A Lagrangian that is a pytree with float arrays (an `eqx.Module` with
    parameters), as a function of `(q, qdot, t, *arrays)`."""

    static: object = eqx.field(static=True)
    treedef: object = eqx.field(static=True)

    def __call__(self, q, qdot, t, *arrays):
        dynamic = jax.tree.unflatten(self.treedef, arrays)
        return eqx.combine(dynamic, self.static)(q, qdot, t)


def canonical_lagrangian(
    L: Callable, dtype, n: int = 1
) -> tuple[CanonicalLagrangian, list]:
    """`(L_c, consts)` with `L_c(q, qdot, t, *consts) == L(q, qdot, t)` for `q`,
    `qdot` of shape `(n,)` and a scalar `t` of `dtype`: `L_c` is equal (the same
    object) for every `L` that computes the same jaxpr up to its floating-point
    constants, which are `consts` (module docstring). The float array fields of a
    pytree `L` (an `eqx.Module`) come first in `consts`."""
    dtype = np.dtype(dtype)
    # `L` may read a global or a closure cell that changed since its last call, which
    # a result kept per function object would miss silently: kept with a fingerprint
    # of those reads, and only where one can be taken (module docstring).
    reads = _reads(L)
    key = (dtype, n, bool(jax.config.jax_enable_x64))
    if reads is not None:
        try:
            kept = _KEPT.get(L, {}).get(key)
        except TypeError:  # not weakly referable or not hashable
            kept, reads = None, None
        if kept is not None and kept[0] == reads:
            return kept[1], list(kept[2])
    dynamic, static = eqx.partition(L, eqx.is_inexact_array)
    arrays, treedef = jax.tree.flatten(dynamic)
    f = _WithParameters(static, treedef) if arrays else L
    z = np.zeros((n,), dtype)
    # (A new function object per call: JAX keeps traces per function object, which
    # would hand back the constants of an earlier call.)
    closed = jax.make_jaxpr(lambda *a: f(*a))(z, z, np.zeros((), dtype), *arrays)
    canon, lifted_values, kept_consts = _canonical(closed, len(arrays))
    canon = _intern(canon)
    consts = list(arrays) + lifted_values + kept_consts
    if reads is not None and not any(isinstance(c, jax.core.Tracer) for c in consts):
        _KEPT.setdefault(L, {})[key] = (reads, canon, tuple(consts))
    return canon, consts


# Per function object (dropped with it): {(dtype, n, x64): (reads, canon, consts)}.
_KEPT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

# Modules whose attributes are the library code a Lagrangian calls, not its data.
_LIBRARIES = frozenset(
    {"jax", "jaxlib", "numpy", "math", "cmath", "builtins", "operator", "functools"}
    | {"equinox", "diffrax", "lagrax"}
)
_OPAQUE_CALLABLES = (
    types.BuiltinFunctionType,
    np.ufunc,
    type(jax.jit(abs)),  # a jitted function: JAX keeps its trace per object
)
# Beyond these a read is not fingerprinted (its walk would cost what a trace does).
_MAX_BYTES = 1 << 16
_MAX_ITEMS = 256
_MAX_DEPTH = 16


class _Unreadable(Exception):
    """A read that cannot be fingerprinted: trace at every call."""


def _reads(f):
    """A fingerprint of what `f` reads besides its arguments (module docstring), or
    `None` where it cannot be taken."""
    if not isinstance(f, (types.FunctionType, functools.partial)):
        return None
    out = []
    try:
        _walk(f, out, set(), 0)
    except _Unreadable:
        return None
    return tuple(out)


def _library(obj) -> bool:
    name = getattr(obj, "__module__", None) or getattr(obj, "__name__", "")
    return isinstance(name, str) and name.partition(".")[0] in _LIBRARIES


def _walk(v, out, seen, depth):
    if depth > _MAX_DEPTH:
        raise _Unreadable
    t = type(v)
    if t in (bool, int, str, bytes, type(None)):
        out.append((t, v))
    elif t is float:
        out.append((t, v.hex()))
    elif t is complex:
        out.append((t, v.real.hex(), v.imag.hex()))
    elif isinstance(v, (np.ndarray, np.generic)):
        a = np.asarray(v)
        if a.dtype.hasobject or a.nbytes > _MAX_BYTES:
            raise _Unreadable
        out.append((np.ndarray, a.dtype, a.shape, a.tobytes()))
    elif isinstance(v, jax.core.Tracer):
        raise _Unreadable
    elif isinstance(v, jax.Array):
        out.append(_Identity(v))
    elif t in (tuple, list, dict) and len(v) > _MAX_ITEMS:
        raise _Unreadable
    elif t in (tuple, list):
        out.append((t, len(v)))
        for x in v:
            _walk(x, out, seen, depth + 1)
    elif t is dict:
        out.append((t, len(v)))
        for k, x in v.items():
            _walk(k, out, seen, depth + 1)
            _walk(x, out, seen, depth + 1)
    elif t is types.ModuleType:
        if not _library(v):
            raise _Unreadable
        out.append(_Identity(v))
    elif t is types.FunctionType:
        # Weakly: the fingerprint is kept beside a weak reference to `L` itself.
        out.append(weakref.ref(v))
        # A library's functions are code, not data, but lagrax's closures hold what a
        # user passed them (parameters, functions): their cells are read.
        library = _library(v)
        if (library and not v.__module__.startswith("lagrax")) or id(v) in seen:
            return
        seen.add(id(v))
        code = v.__code__
        out.append(_Identity(code))
        _walk(v.__defaults__, out, seen, depth + 1)
        _walk(v.__kwdefaults__, out, seen, depth + 1)
        for cell in v.__closure__ or ():
            try:
                x = cell.cell_contents
            except ValueError:  # a cell not yet filled
                out.append(("empty",))
            else:
                _walk(x, out, seen, depth + 1)
        if library:
            return
        space, spare = v.__globals__, vars(builtins)
        for name in _global_names(code):
            if name in space:
                out.append(name)
                _walk(space[name], out, seen, depth + 1)
            elif name in spare:
                out.append((name, _Identity(spare[name])))
            else:
                out.append((name, "absent"))
    elif t is functools.partial:
        _walk(v.func, out, seen, depth + 1)
        _walk(v.args, out, seen, depth + 1)
        _walk(v.keywords, out, seen, depth + 1)
    elif isinstance(v, _OPAQUE_CALLABLES) or (isinstance(v, type) and _library(v)):
        out.append(_Identity(v))
    else:
        raise _Unreadable


@functools.lru_cache(maxsize=1024)
def _global_names(code) -> tuple:
    """The names `code` and the functions defined in it look up (globals, builtins
    and attribute names alike: an attribute name read as a global costs nothing)."""
    names = list(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            names.extend(_global_names(c))
    return tuple(dict.fromkeys(names))


class BoundLagrangian(eqx.Module):
    """A canonical Lagrangian with its constants: `L(q, qdot, t)`."""

    L: "CanonicalLagrangian"
    consts: tuple

    def __call__(self, q, qdot, t):
        return self.L(q, qdot, t, *self.consts)


def _intern(canon):
    key = canon.key
    found = _INTERNED.get(key)
    if found is None:
        _INTERNED[key] = found = canon
        if len(_INTERNED) > _MAX_INTERNED:
            _INTERNED.popitem(last=False)
    else:
        _INTERNED.move_to_end(key)
    return found


def _is_float(aval):
    return np.issubdtype(aval.dtype, np.inexact)


def _canonical(closed, n_params):
    """The canonical function of a closed jaxpr `(q, qdot, t, *params) -> L`, the
    values of the literals it lifts, and its constants (all lifted: a float const
    is a parameter; the others are compared by value in the key)."""
    jaxpr = closed.jaxpr
    names = {}  # Var -> its position in order of definition

    def name(v):
        if v not in names:
            names[v] = len(names)
        return names[v]

    for v in jaxpr.invars:
        name(v)
    for v in jaxpr.constvars:
        name(v)
    lifted, values = {}, []
    kept = []
    for v, c in zip(jaxpr.constvars, closed.consts):
        if _is_float(v.aval):
            kept.append(("const", _aval_key(v.aval)))
        else:
            kept.append(("const", _aval_key(v.aval), _value_key(c)))
    eqns = []
    for i, eqn in enumerate(jaxpr.eqns):
        ins = []
        for j, a in enumerate(eqn.invars):
            if isinstance(a, jex_core.Literal):
                if _is_float(a.aval) and np.shape(a.val) == ():
                    lifted[(i, j)] = len(values)
                    values.append(np.asarray(a.val, a.aval.dtype))
                    ins.append(("lifted", _aval_key(a.aval)))
                else:
                    ins.append(("literal", _aval_key(a.aval), _value_key(a.val)))
            else:
                ins.append(name(a))
        outs = tuple(
            ("drop", _aval_key(v.aval))
            if isinstance(v, jex_core.DropVar)
            else (name(v), _aval_key(v.aval))
            for v in eqn.outvars
        )
        params = tuple(sorted((k, _param_key(p)) for k, p in eqn.params.items()))
        eqns.append((eqn.primitive.name, tuple(ins), params, outs))
    outvars = tuple(
        ("literal", _aval_key(a.aval), _value_key(a.val))
        if isinstance(a, jex_core.Literal)
        else name(a)
        for a in jaxpr.outvars
    )
    key = (
        tuple(_aval_key(v.aval) for v in jaxpr.invars),
        tuple(kept),
        tuple(eqns),
        outvars,
        n_params,
    )
    consts = [c for c in closed.consts]
    # Non-float consts are compared by value, but still passed (the jaxpr reads them
    # from its constvars, all of which come after the lifted literals).
    return CanonicalLagrangian(jaxpr, lifted, n_params, key), values, consts


def _aval_key(aval):
    shape = getattr(aval, "shape", None)
    dtype = getattr(aval, "dtype", None)
    return (type(aval).__name__, shape, dtype, getattr(aval, "weak_type", None))


def _value_key(x):
    a = np.asarray(x)
    return (a.shape, a.dtype, a.tobytes())


class _Identity:
    """A parameter compared by identity (a missed reuse, never a wrong one)."""

    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __hash__(self):
        return id(self.obj)

    def __eq__(self, other):
        return isinstance(other, _Identity) and other.obj is self.obj


def _param_key(p):
    if isinstance(p, jex_core.ClosedJaxpr):
        return ("closed", _jaxpr_key(p.jaxpr), tuple(_value_key(c) for c in p.consts))
    if isinstance(p, jex_core.Jaxpr):
        return ("jaxpr", _jaxpr_key(p))
    if isinstance(p, (tuple, list)):
        return (type(p).__name__, tuple(_param_key(x) for x in p))
    if isinstance(p, np.ndarray):
        return ("array", _value_key(p))
    if isinstance(p, (str, int, float, bool, complex, type(None), np.dtype)):
        return p
    try:
        hash(p)
    except TypeError:
        return _Identity(p)
    return p


def _jaxpr_key(jaxpr):
    """A nested jaxpr's structure, its literals included (not lifted)."""
    names = {}

    def name(v):
        if isinstance(v, jex_core.Literal):
            return ("literal", _aval_key(v.aval), _value_key(v.val))
        if isinstance(v, jex_core.DropVar):
            return ("drop", _aval_key(v.aval))
        if v not in names:
            names[v] = len(names)
        return names[v]

    head = tuple(
        (name(v), _aval_key(v.aval)) for v in (*jaxpr.constvars, *jaxpr.invars)
    )
    body = tuple(
        (
            eqn.primitive.name,
            tuple(name(a) for a in eqn.invars),
            tuple(sorted((k, _param_key(p)) for k, p in eqn.params.items())),
            tuple((name(v), _aval_key(v.aval)) for v in eqn.outvars),
        )
        for eqn in jaxpr.eqns
    )
    return head, body, tuple(name(v) for v in jaxpr.outvars)
