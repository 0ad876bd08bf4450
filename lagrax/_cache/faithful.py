r"""A text that says all of a value, or none: the pre-keys of the disk cache of
executables (`lagrax._cache.executables`) are built from it.

`text(x)` writes `x` from a whitelist of kinds whose every part it writes out, so that
two values with one text are interchangeable wherever the library uses them; any
other kind raises `Unfaithful` (and the caller keys nothing on it). Admitted:

- `None`, `bool`, `int`, `str`, `bytes`, `float` and `complex` (by their bytes: a NaN's
    payload and the sign of a zero included), `Ellipsis`;
- `tuple`, `list`, `dict`, `set`, `frozenset` of admitted values (exactly these types);
- NumPy dtypes (no structured or object ones), scalars and arrays up to `MAX_ARRAY`
    bytes (their dtype, shape and bytes), and NumPy's scalar types;
- classes, enum members, named tuples and `equinox.Module`s (every dataclass field)
    of types defined at module level in lagrax or in the libraries whose versions the
    pre-key holds (`ROOTS`): what such a type does is fixed by that code;
- JAX primitives defined at module level in those libraries (by where they live), and
    jaxprs, walked equation by equation: primitive, operands (variables by order of
    definition, literals by value), parameters, abstract values, equation context;
    any effect is refused;
- devices (platform, kind, id, process), single-device shardings, empty meshes;
- the canonical Lagrangian of `lagrax._jaxpr.canonical` by its jaxpr, the literals
    it lifts to arguments written by their type only (their values are arguments).

Functions, closures, `custom_jvp` rules, instances of other types (a user's subclass
included), objects compared by identity: refused.
"""

import dataclasses
import enum
import struct
import sys

import equinox as eqx
import numpy as np
from jax.extend import core as jex_core

from .. import _compat


# The libraries whose code fixes what their module-level types and primitives do: the
# pre-key holds their versions (lagrax: its source digest).
ROOTS = (
    "lagrax",
    "jax",
    "jaxlib",
    "diffrax",
    "equinox",
    "lineax",
    "optimistix",
    "numpy",
    "ml_dtypes",
)
# Where primitives are defined.
_JAX_ROOTS = ("lagrax", "jax", "diffrax", "equinox", "lineax", "optimistix")
# The largest array written by value (bytes).
MAX_ARRAY = 1 << 16


class Unfaithful(Exception):
    """A value whose text would not say all of it."""


def text(x) -> str:
    """`x` written out whole (module docstring), or `Unfaithful`."""
    out = []
    _write(x, out)
    return "".join(out)


def module_level(obj) -> bool:
    """Whether `obj` (a class, a function) is what its module and qualified name
    name, in one of `ROOTS`: code those fix."""
    module = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None) or "<"
    if (
        not isinstance(module, str)
        or module.split(".")[0] not in ROOTS
        or "<" in qualname
    ):
        return False
    found = sys.modules.get(module)
    for part in qualname.split("."):
        found = getattr(found, part, None)
    return found is obj


def _type_name(t) -> str:
    if not module_level(t):
        raise Unfaithful(f"the type {t.__module__}.{t.__qualname__}")
    return f"{t.__module__}.{t.__qualname__}"


def _float(x) -> str:
    return struct.pack("<d", x).hex()


def _write(x, out):
    t = type(x)
    if x is None or x is Ellipsis or t is bool:
        out.append(repr(x))
    elif t is int:
        out.append(f"i{x}")
    elif t is str or t is bytes:
        out.append(repr(x))
    elif t is float:
        out.append("f" + _float(x))
    elif t is complex:
        out.append(f"c{_float(x.real)},{_float(x.imag)}")
    elif t is tuple or t is list:
        out.append("(" if t is tuple else "[")
        for v in x:
            _write(v, out)
            out.append(",")
        out.append(")" if t is tuple else "]")
    elif t is dict:
        items = sorted((text(k), text(v)) for k, v in x.items())
        out.append("{" + ",".join(f"{k}:{v}" for k, v in items) + "}")
    elif t is set or t is frozenset:
        out.append(t.__name__ + "{" + ",".join(sorted(text(v) for v in x)) + "}")
    elif t is np.dtype or isinstance(x, np.dtype):
        out.append(_dtype(x))
    elif isinstance(x, np.generic):
        out.append(f"np({_dtype(x.dtype)},{x.tobytes().hex()})")
    elif t is np.ndarray:
        out.append(_array(x))
    elif isinstance(x, type):
        if issubclass(x, np.generic) and x.__module__ == "numpy":
            out.append(f"type(numpy.{x.__name__})")
        else:
            out.append(f"type({_type_name(x)})")
    else:
        _write_object(x, t, out)


def _dtype(d) -> str:
    if d.fields is not None or d.subdtype is not None or d.kind == "O":
        raise Unfaithful(f"the dtype {d}")
    return f"dtype({d.name},{d.str},{d.kind},{d.itemsize})"


def _array(a) -> str:
    if a.nbytes > MAX_ARRAY:
        raise Unfaithful("a large array")
    data = np.ascontiguousarray(a).tobytes().hex()
    return f"array({_dtype(a.dtype)},{a.shape},{data})"


def _write_object(x, t, out):
    from .._jaxpr.canonical import CanonicalLagrangian

    if t is CanonicalLagrangian:
        out.append(f"L({x.n_params},")
        _jaxpr(x.jaxpr, out, lifted=x.lifted)
        out.append(")")
    elif isinstance(x, jex_core.ClosedJaxpr):
        out.append("closed(")
        _jaxpr(x.jaxpr, out)
        for c in x.consts:
            out.append(_array(np.asarray(c)) + ",")
        out.append(")")
    elif isinstance(x, jex_core.Jaxpr):
        _jaxpr(x, out)
    elif isinstance(x, jex_core.Primitive):
        out.append(_primitive(x))
    elif isinstance(x, enum.Enum):
        out.append(f"enum({_type_name(t)}.{x.name}=")
        _write(x.value, out)
        out.append(")")
    elif isinstance(x, tuple) and hasattr(t, "_fields"):  # a named tuple
        out.append(f"{_type_name(t)}(")
        _write(tuple(x), out)
        out.append(")")
    elif isinstance(x, eqx.Module):
        out.append(f"{_type_name(t)}(")
        for f in dataclasses.fields(x):
            out.append(f.name + "=")
            _write(getattr(x, f.name), out)
            out.append(",")
        out.append(")")
    else:
        out.append(_jax_object(x, t))


def _jax_object(x, t) -> str:
    """Devices, shardings and meshes: the few JAX objects a program's key meets."""
    import jax

    if isinstance(x, jax.Device):
        return f"device({x.platform!r},{x.device_kind!r},{x.id},{x.process_index})"
    if t is jax.sharding.SingleDeviceSharding:
        (device,) = x.device_set
        return f"single({_jax_object(device, type(device))},{x.memory_kind!r})"
    if t in (jax.sharding.AbstractMesh, jax.sharding.Mesh) and x.empty:
        return f"{t.__name__}()"
    name = f"{t.__module__}.{t.__qualname__}"
    if _compat.is_unspecified_sharding(x):
        return "UnspecifiedValue"
    raise Unfaithful(f"an object of type {name}")


# Primitives defined at module level in `ROOTS`, by identity: (primitive, where).
_PRIMITIVES: dict = {}
_SCANNED = [0]


def _primitive(p) -> str:
    found = _PRIMITIVES.get(id(p))
    if found is None and len(sys.modules) != _SCANNED[0]:
        _scan_primitives()
        found = _PRIMITIVES.get(id(p))
    if found is None or found[0] is not p:
        raise Unfaithful(f"the primitive {p}")
    return found[1]


def _scan_primitives():
    """Where each module-level primitive of `ROOTS` lives: the first place in order
    of module and name, the same in every process that imported it there."""
    _SCANNED[0] = len(sys.modules)
    places = {}
    for module_name, module in list(sys.modules.items()):
        if module_name.split(".")[0] not in _JAX_ROOTS or module is None:
            continue
        for name, value in list(getattr(module, "__dict__", {}).items()):
            if isinstance(value, jex_core.Primitive):
                place = f"{module_name}.{name}"
                best = places.get(id(value))
                if best is None or place < best[1]:
                    places[id(value)] = (value, place)
    _PRIMITIVES.clear()
    _PRIMITIVES.update(
        {k: (p, f"prim({place}:{p.name})") for k, (p, place) in places.items()}
    )


def aval_text(a) -> str:
    """An abstract value: a `ShapedArray` outside any mesh."""
    if type(a).__name__ != "ShapedArray":
        raise Unfaithful(f"the abstract value {a}")
    if any(type(d) is not int for d in a.shape):
        raise Unfaithful("a dynamic shape")
    sharding = a.sharding
    if not sharding.mesh.empty or getattr(a, "vma", frozenset()):
        raise Unfaithful("an abstract value with a mesh")
    space = getattr(a, "memory_space", None)
    return (
        f"aval({a.shape},{_dtype(np.dtype(a.dtype))},{a.weak_type},"
        f"{sharding.spec!r},{space!r})"
    )


def _ctx(ctx) -> str:
    parts = []
    for name in (
        "compute_type",
        "threefry_partitionable",
        "remove_size_one_mesh_axis",
        "xla_metadata",
    ):
        parts.append(text(getattr(ctx, name, None)))
    if not ctx.cur_abstract_mesh.empty:
        raise Unfaithful("an equation under a mesh")
    return "ctx(" + ",".join(parts) + ")"


def _jaxpr(jaxpr, out, lifted=None):
    """Appends the text of `jaxpr`: variables numbered in order of definition; a
    literal by value, or where `lifted` (`{(equation, operand): ...}`, as
    `CanonicalLagrangian` reads them) by its abstract value only."""
    if jaxpr.effects:
        raise Unfaithful("a jaxpr with effects")
    names = {}

    def define(v):
        names[v] = len(names)
        return f"v{names[v]}:{aval_text(v.aval)}"

    def operand(i, j, a):
        if isinstance(a, jex_core.Literal):
            head = f"lit({aval_text(a.aval)}"
            if lifted is not None and (i, j) in lifted:
                return head + ")"
            return head + "," + _array(np.asarray(a.val)) + ")"
        return f"v{names[a]}"

    out.append("jaxpr(consts=")
    out.append(",".join(define(v) for v in jaxpr.constvars))
    out.append(";in=")
    out.append(",".join(define(v) for v in jaxpr.invars))
    for i, eqn in enumerate(jaxpr.eqns):
        if eqn.effects:
            raise Unfaithful("an equation with effects")
        out.append(";" + _primitive(eqn.primitive) + "(")
        out.append(",".join(operand(i, j, a) for j, a in enumerate(eqn.invars)))
        out.append(";")
        _write(dict(eqn.params), out)
        out.append(";" + _ctx(eqn.ctx) + ")->")
        outs = []
        for v in eqn.outvars:
            if isinstance(v, jex_core.DropVar):
                outs.append(f"_:{aval_text(v.aval)}")
            else:
                outs.append(define(v))
        out.append(",".join(outs))
    out.append(";out=")
    out.append(",".join(operand(-1, j, a) for j, a in enumerate(jaxpr.outvars)))
    out.append(")")
