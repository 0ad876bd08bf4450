"""Argument checks, each written once, for every public entry point.

Every check here runs at trace time on shapes and dtypes (always available), and on
values only when they are concrete (an eager call), so that user errors surface as a
`TypeError`/`ValueError` naming the argument instead of a tracer traceback. Each entry
point calls them once, before any work: the hot path is never checked.
"""

import linecache
import math
import os
import warnings
import weakref

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core

from ._jaxpr import interpreter


def is_concrete(*xs) -> bool:
    """True when none of `xs` is a JAX tracer (so values may be inspected)."""
    return not any(
        isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs)
    )


def describe(x) -> str:
    """A short description of what was received, for error messages."""
    if isinstance(x, type):
        return f"the class {x.__name__} (pass an instance, e.g. {x.__name__}())"
    if callable(x) and not hasattr(x, "shape"):
        return f"callable {getattr(x, '__name__', type(x).__name__)}"
    shape = getattr(x, "shape", None)
    dtype = getattr(x, "dtype", None)
    if shape is not None:
        return f"array of shape {tuple(shape)} and dtype {dtype}"
    return f"{type(x).__name__} {x!r}"


def check_callable(f, name: str, expected: str):
    if not callable(f):
        raise TypeError(f"`{name}` must be {expected}; got {describe(f)}.")


def as_real_array(x, name: str):
    """Converts `x` to a JAX array with a real floating dtype, or raises."""
    check_real(x, name)
    return as_array(x)


def as_array(x):
    """`jnp.asarray(x)`; a NumPy array by `jax.device_put` (the same dtype and weak
    type), which copies it where `jnp.asarray` compiles a small program for each
    shape and dtype on a process's first call (tens of milliseconds)."""
    if type(x) is np.ndarray:
        return jax.device_put(x)
    return jnp.asarray(x)


def check_real(x, name: str):
    """Raises unless `x` is an array (or number) of a real floating dtype."""
    if isinstance(x, str | bytes) or x is None:
        raise TypeError(
            f"`{name}` must be an array of real floating-point numbers; got "
            f"{describe(x)}."
        )
    try:
        dtype = jnp.result_type(x)
    except TypeError as e:
        raise TypeError(
            f"`{name}` must be an array of real floating-point numbers; got "
            f"{describe(x)}."
        ) from e
    if not jnp.issubdtype(dtype, jnp.floating):
        if jnp.issubdtype(dtype, jnp.complexfloating):
            what = "a complex dtype"
        elif jnp.issubdtype(dtype, jnp.integer) or jnp.issubdtype(dtype, jnp.bool_):
            what = f"the non-floating dtype {np.dtype(dtype).name}"
        else:
            what = f"dtype {dtype}"
        raise TypeError(
            f"`{name}` must have a real floating dtype (float32 or float64); got "
            f"{what}. Write e.g. `jnp.array([1.0])` rather than `jnp.array([1])`."
        )


def as_real_promoting_ints(x, name: str):
    """`as_real_array`, with Python ints and integer arrays promoted to the default
    float (harmless for a length or an angle in whole radians, unlike coordinates,
    which carry tangents). Strings, complex, bool: rejected."""
    if not isinstance(x, str | bytes | bool) and x is not None:
        try:
            dtype = jnp.result_type(x)
        except TypeError:
            dtype = None
        if dtype is not None and jnp.issubdtype(dtype, jnp.integer):
            x = jnp.asarray(x, dtype=jnp.result_type(float))
    return as_real_array(x, name)


def positive_array(x, name: str):
    """A real float array (ints promoted), positive wherever its values are known."""
    x = as_real_promoting_ints(x, name)
    # numpy, not jnp: inside a jit trace a jnp op on a concrete array is a tracer.
    if is_concrete(x) and not np.all(np.asarray(x) > 0):
        raise ValueError(f"`{name}` must be positive; got {np.asarray(x)!r}.")
    return x


def as_state(q, qdot, qname: str = "q", qdotname: str = "qdot"):
    """Checks and converts a state `(q, qdot)`: 1-D, same length, real float."""
    q = as_real_array(q, qname)
    qdot = as_real_array(qdot, qdotname)
    if q.ndim != 1:
        raise ValueError(
            f"`{qname}` must be a 1-D array of generalized coordinates (shape (n,)); "
            f"got shape {q.shape}. For one degree of freedom write `jnp.array([x])`."
        )
    if qdot.ndim != 1:
        raise ValueError(
            f"`{qdotname}` must be a 1-D array of generalized velocities (shape "
            f"(n,)); got shape {qdot.shape}."
        )
    if q.shape != qdot.shape:
        raise ValueError(
            f"`{qname}` and `{qdotname}` must have the same length; got "
            f"{qname}.shape={q.shape} and {qdotname}.shape={qdot.shape}."
        )
    if q.shape[0] == 0:
        raise ValueError(
            f"`{qname}` must have at least one coordinate; got shape (0,)."
        )
    dtype = jnp.result_type(q, qdot)
    return q.astype(dtype), qdot.astype(dtype)


def as_time(t, name: str, dtype):
    """A scalar time (a Python number, or a real float array) as an array of
    `dtype`: converted by NumPy where it is concrete (`_as_dtype`)."""
    if not isinstance(t, int | float):
        check_real(t, name)
    if np.ndim(t) != 0:
        raise ValueError(f"`{name}` must be a scalar time; got shape {np.shape(t)}.")
    return _as_dtype(t, dtype)


def _as_dtype(x, dtype):
    """`x` as an array of `dtype`: a tracer by JAX; a concrete value by NumPy, unless
    it is a JAX array of `dtype` already (a `jnp` conversion of a concrete value
    compiles an XLA computation on a process's first call; a NumPy scalar is also no
    device transfer before every dispatch)."""
    if isinstance(x, jax.core.Tracer):
        return jnp.asarray(x, dtype=dtype)
    if isinstance(x, jax.Array) and x.dtype == dtype and not x.weak_type:
        return x
    return np.asarray(x, dtype)


def check_finite(x, name: str):
    """Raises if `x` is concrete and has a NaN or infinite entry."""
    # numpy, not jnp: inside a jit trace a jnp op on a concrete array is a tracer.
    if is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
        raise ValueError(
            f"`{name}` must be finite; got {np.asarray(x)!r} (an entry is not finite)."
        )


def positive_scalar(x, name: str, dtype, *, optional: bool = False):
    """A positive finite scalar (a tolerance, a time limit) as an array of `dtype`.

    `None` passes through when `optional`. Values are checked when concrete."""
    if x is None and optional:
        return None
    if not (isinstance(x, int | float) and not isinstance(x, bool)):
        check_real(x, name)
        if np.ndim(x) != 0:
            raise ValueError(f"`{name}` must be a scalar; got shape {np.shape(x)}.")
    if is_concrete(x):
        value = x if isinstance(x, int | float) else float(x)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"`{name}` must be a positive finite number; got {value}.")
    return _as_dtype(x, dtype)


def positive_int(x, name: str, *, minimum: int = 1) -> int:
    """A Python (or numpy) int of at least `minimum`; never a bool."""
    if isinstance(x, bool) or not isinstance(x, int | np.integer) or x < minimum:
        what = "a positive int" if minimum == 1 else f"an int >= {minimum}"
        raise ValueError(f"`{name}` must be {what}; got {x!r}.")
    return int(x)


def lane_count(
    value, name: str, devices, per_device: int, *, cpu: int, accelerator: int
):
    """The lanes per device of a compiled loop: `value` checked, or by default `cpu`
    on a CPU and, on an accelerator, enough for every item of a device's share up
    to `accelerator` (a GPU needs far more lanes in flight than a CPU core: the
    CPU's default leaves it mostly idle)."""
    if value is not None:
        return positive_int(value, name)
    if devices[0].platform == "cpu":
        return cpu
    return max(1, min(int(per_device), accelerator))


def warn_if_below_eps(rtol, dtype, *, stacklevel: int = 2):
    """Warns when a concrete `rtol` is finer than the machine epsilon of `dtype`.

    `stacklevel` as seen from the caller: 2 points the warning at the caller's
    caller (the user of a public entry point that calls this directly)."""
    eps = float(jnp.finfo(dtype).eps)
    if is_concrete(rtol) and float(rtol) < eps:
        warnings.warn(
            f"rtol={float(rtol):g} is below the machine epsilon of "
            f"{jnp.dtype(dtype).name} ({eps:.2g}): the result cannot reach it. Enable "
            "float64 (JAX's x64 mode, set by the caller) or loosen rtol.",
            stacklevel=stacklevel + 1,
        )


def tolerances(rtol, atol, dtype, *, stacklevel: int = 2):
    """`rtol` and `atol` as positive scalars of `dtype`, warning on rtol < eps."""
    rtol = positive_scalar(rtol, "rtol", dtype)
    atol = positive_scalar(atol, "atol", dtype)
    warn_if_below_eps(rtol, dtype, stacklevel=stacklevel + 1)
    return rtol, atol


def check_instance(value, name: str, cls, expected: str | None = None):
    """Raises unless `value` is an instance of `cls` (`None` is the caller's job)."""
    if not isinstance(value, cls):
        expected = expected or f"a `{cls.__module__.split('.')[0]}.{cls.__name__}`"
        raise TypeError(f"`{name}` must be {expected}; got {describe(value)}.")


def check_choice(value, name: str, choices):
    """`value` if it is one of the strings `choices`, else raises."""
    if not (isinstance(value, str) and value in choices):
        raise ValueError(f"`{name}` must be one of {sorted(choices)}; got {value!r}.")
    return value


def check_devices(devices) -> tuple:
    """A non-empty sequence of `jax.Device`s, as a tuple."""
    expected = (
        f"`devices` must be a non-empty sequence of jax devices; got {devices!r}."
    )
    if isinstance(devices, jax.Device | str) or not hasattr(devices, "__iter__"):
        raise TypeError(expected)
    devices = tuple(devices)
    if len(devices) == 0 or not all(isinstance(d, jax.Device) for d in devices):
        raise TypeError(expected)
    return devices


# ------------------------------------------------------------- user functions


def call_user(f, name, signature, *args):
    """`jax.eval_shape(f, *args)`, with a user error in `f` re-raised naming `f`, and
    an out-of-range index in `f` reported (`check_indices`)."""
    try:
        out = jax.eval_shape(f, *args)
    except (TypeError, ValueError) as e:
        if str(e).startswith("`"):  # already a lagrax message naming its argument
            raise
        shapes = ", ".join(
            f"{jnp.dtype(a.dtype).name}{list(a.shape)}" if hasattr(a, "shape") else "?"
            for a in args
        )
        if isinstance(e, jax.errors.ConcretizationTypeError):
            why = (
                "Python control flow or float() on a value that depends on the "
                "arguments (use jnp.where or jax.lax.cond)"
            )
        else:
            why = type(e).__name__
        raise (TypeError if isinstance(e, TypeError) else ValueError)(
            f"`{name}` must be a JAX-traceable function {signature}; calling it "
            f"with arguments {shapes} failed: {why}: {str(e).splitlines()[0]}"
        ) from e
    check_indices(f, name, signature.split(" ->")[0], *args)
    return out


# Functions already probed by `check_indices`, with the shapes and dtypes they were
# probed at: an eager loop over `accelerations` probes its `L` once.
_PROBED = weakref.WeakKeyDictionary()


def _probed(f) -> set:
    """The argument signatures `f` was checked at (a fresh set where `f` cannot be
    a weak key: not hashable, e.g. an `eqx.Module` with array fields)."""
    try:
        return _PROBED.setdefault(f, set())
    except TypeError:
        return set()


# ------------------------------------------------------ out-of-range indexing
#
# JAX clamps an out-of-range index silently (`q[1]` of a shape-`(1,)` `q` reads `q[0]`).
# The check below evaluates the user's jaxpr at concrete values and looks at the index
# operands of every gather, dynamic slice and scatter before binding it.

_LAGRAX = os.path.dirname(os.path.abspath(__file__))

# A gather that asks for clamping or filling (`jnp.take(..., mode="clip")`,
# `x.at[i].get(mode="fill")`) gets what it asks for. Plain indexing (`q[i]`, `q[idx]`)
# gathers with `PROMISE_IN_BOUNDS` or slices dynamically, and is checked.
_EXPLICIT_MODES = (
    jax.lax.GatherScatterMode.CLIP,
    jax.lax.GatherScatterMode.FILL_OR_DROP,
)


def _clamps(eqn) -> bool:
    """Whether `eqn` indexes at run-time indices that JAX would clamp silently."""
    name = eqn.primitive.name
    if name == "gather":
        return eqn.params["mode"] not in _EXPLICIT_MODES
    return name in ("dynamic_slice", "dynamic_update_slice") or name.startswith(
        "scatter"
    )


def _indexes_dynamically(jaxpr) -> bool:
    """Whether `jaxpr` (or a jaxpr nested in it: calls, branches, loop bodies)
    has an equation that `_clamps`."""
    return any(
        _clamps(eqn)
        or any(
            _indexes_dynamically(sub) for sub in jex_core.jaxprs_in_params(eqn.params)
        )
        for eqn in interpreter.equations(jaxpr, custom=True)
    )


def _out_of_range(eqn, ins):
    """`(index, axis, size)` of the first out-of-range index of an equation that
    `_clamps`, at the concrete operands `ins`, or None."""
    name, params = eqn.primitive.name, eqn.params
    shape = eqn.invars[0].aval.shape
    if name == "dynamic_slice":
        axes, sizes, starts = range(len(shape)), params["slice_sizes"], ins[1:]
    elif name == "dynamic_update_slice":
        axes, sizes, starts = range(len(shape)), eqn.invars[1].aval.shape, ins[2:]
    elif name == "gather":
        axes = params["dimension_numbers"].start_index_map
        sizes = [params["slice_sizes"][a] for a in axes]
        starts = ins[1]
    else:  # a scatter: the window of `updates` in each operand dimension
        dn = params["dimension_numbers"]
        windows = iter(eqn.invars[2].aval.shape[d] for d in dn.update_window_dims)
        unit = set(dn.inserted_window_dims) | set(dn.operand_batching_dims)
        window = [1 if d in unit else next(windows) for d in range(len(shape))]
        axes = dn.scatter_dims_to_operand_dims
        sizes = [window[a] for a in axes]
        starts = ins[1]
    axes = list(axes)
    starts = np.asarray(starts).reshape(-1, len(axes))
    upper = np.array([shape[a] - size for a, size in zip(axes, sizes)])
    bad = ((starts < 0) | (starts > upper)).ravel()
    if not bad.any():
        return None
    row, col = divmod(int(np.argmax(bad)), len(axes))
    return int(starts[row, col]), axes[col], shape[axes[col]]


class _OutOfRange(Exception):
    def __init__(self, eqn, found):
        self.eqn, self.found = eqn, found


def _run(closed, args):
    return interpreter.evaluate(
        closed.jaxpr, closed.consts, args, _checked, custom=True
    )


def _cond(params, ins):
    branches = params["branches"]
    return _run(branches[int(np.clip(ins[0], 0, len(branches) - 1))], ins[1:])


def _while(params, ins):
    nc, nb = params["cond_nconsts"], params["body_nconsts"]
    cconsts, bconsts, carry = ins[:nc], ins[nc : nc + nb], ins[nc + nb :]
    while bool(_run(params["cond_jaxpr"], [*cconsts, *carry])[0]):
        carry = _run(params["body_jaxpr"], [*bconsts, *carry])
    return carry


def _scan(params, ins):
    nc, nk = params["num_consts"], params["num_carry"]
    consts, carry, xs = ins[:nc], ins[nc : nc + nk], ins[nc + nk :]
    steps = range(params["length"])
    ys = [None] * len(steps)
    for i in reversed(steps) if params["reverse"] else steps:
        outs = _run(params["jaxpr"], [*consts, *carry, *(x[i] for x in xs)])
        carry, ys[i] = outs[:nk], outs[nk:]
    avals = params["jaxpr"].out_avals[nk:]
    return [
        *carry,
        *(
            jnp.stack([y[j] for y in ys]) if ys else jnp.zeros((0, *a.shape), a.dtype)
            for j, a in enumerate(avals)
        ),
    ]


# Control flow whose bodies are evaluated with the check where they index.
_NESTED = {"cond": _cond, "while": _while, "scan": _scan}


def _checked(eqn, ins):
    """The interpreter's rule: `eqn` bound at the concrete `ins`, once its indices
    are checked."""
    if _clamps(eqn):
        found = _out_of_range(eqn, ins)
        if found is not None:
            raise _OutOfRange(eqn, found)
    elif eqn.primitive.name in _NESTED and any(
        _indexes_dynamically(sub) for sub in jex_core.jaxprs_in_params(eqn.params)
    ):
        return _NESTED[eqn.primitive.name](eqn.params, ins)
    return interpreter.bind(eqn, ins)


def _where(eqn) -> str:
    """` at file:line (`source`)`: the innermost frame of the equation's traceback
    outside JAX and lagrax's private modules (the user's indexing), or `""`."""
    traceback = getattr(eqn.source_info, "traceback", None)
    for frame in getattr(traceback, "frames", ()):
        path = os.path.abspath(frame.file_name)
        if (
            "site-packages" in path
            or f"{os.sep}jax{os.sep}" in path
            or path.startswith(os.path.join(_LAGRAX, "_"))
        ):
            continue
        line = linecache.getline(path, frame.line_num).strip()
        source = f" (`{line}`)" if line else ""
        return f" at {os.path.basename(path)}:{frame.line_num}{source}"
    return ""


def _concrete(x):
    """`x` if concrete, else zeros of its shape and dtype (a value to probe with)."""
    return x if is_concrete(x) else np.zeros(jnp.shape(x), jnp.result_type(x))


def check_indices(f, name: str, signature: str, *args):
    """Raises if `f(*args)` indexes an array out of range.

    JAX clamps an out-of-range index silently (`q[1]` of a shape-`(1,)` `q` reads
    `q[0]`), so a Lagrangian written for more coordinates than it is given would
    return wrong numbers without an error. Where `f`'s jaxpr gathers, slices or
    scatters at run-time indices, it is evaluated outside any enclosing `jit`/`vmap`
    trace, at the arguments where they are concrete and at zeros of their shape where
    they are traced (and likewise for traced values `f` closes over), and every such
    index is checked against the shape it indexes. Validation only: nothing of this is
    staged into the computation. Other failures of `f` are left to the other checks.
    """
    key = tuple((jnp.shape(a), jnp.result_type(a)) for a in args)
    if key in _probed(f):
        return
    try:
        closed = jax.make_jaxpr(f)(*args)
        if _indexes_dynamically(closed.jaxpr):
            # (Evaluated op by op: each op compiles on a first call.)
            with jax.core.eval_context():
                interpreter.evaluate(
                    closed.jaxpr,
                    [_concrete(c) for c in closed.consts],
                    [_concrete(a) for a in jax.tree_util.tree_leaves(args)],
                    _checked,
                    custom=True,
                )
    except _OutOfRange as e:
        index, axis, size = e.found
        shape = tuple(e.eqn.invars[0].aval.shape)
        shapes = ", ".join(f"{jnp.dtype(d).name}{list(s)}" for s, d in key)
        raise ValueError(
            f"`{name}` must index its arguments within their shapes; {signature} "
            f"with arguments {shapes} got out-of-bounds indexing for array of shape "
            f"{shape}: index {index} is out of bounds for axis {axis} with size "
            f"{size}{_where(e.eqn)}. JAX would clamp the index silently (q[1] of a q "
            "of shape (1,) reads q[0]) and give wrong numbers: index only the "
            "coordinates the function is given."
        ) from None
    except (TypeError, ValueError) as e:
        if str(e).startswith("`"):  # a lagrax message from a nested check
            raise
        return  # a broken `f` is reported by the other checks
    except Exception:
        return
    _probed(f).add(key)


def check_lagrangian(L, q, qdot, t, *, what: str = ""):
    """`L` is callable and returns a real float scalar at `(q, qdot, t)`.

    `what` qualifies "the Lagrangian" in the message (e.g. " of one degree of
    freedom")."""
    check_callable(L, "L", "a function L(q, qdot, t) -> scalar")
    out = call_user(L, "L", "L(q, qdot, t) -> scalar", q, qdot, t)
    shape = getattr(out, "shape", None)
    dtype = getattr(out, "dtype", None)
    if shape != () or dtype is None or not jnp.issubdtype(dtype, jnp.floating):
        got = (
            f"shape {shape} and dtype {dtype}"
            if shape is not None
            else f"a {type(out).__name__}"
        )
        raise TypeError(
            f"`L` must return a real floating-point scalar (the Lagrangian{what}); "
            f"L(q, qdot, t) with q of shape {q.shape} returned {got}. Sum or index the "
            "terms into a scalar."
        )


def check_force(force, q, qdot, t):
    check_callable(force, "force", "a function force(q, qdot, t) -> Q of shape (n,)")
    out = call_user(force, "force", "force(q, qdot, t) -> Q", q, qdot, t)
    if getattr(out, "shape", None) != q.shape or not jnp.issubdtype(
        out.dtype, jnp.floating
    ):
        raise TypeError(
            f"`force` must return a generalized force Q of shape {q.shape} (one entry "
            f"per coordinate) and real floating dtype; force(q, qdot, t) returned "
            f"{describe(out)}."
        )


def prepare(L, q, qdot, t, force=None, names=("q", "qdot", "t")):
    """Checks a Lagrangian, a state and a time (and a force) once: `(q, qdot, t)` as
    arrays of one float dtype."""
    q, qdot = as_state(q, qdot, names[0], names[1])
    t = as_time(t, names[2], q.dtype)
    for x, name in zip((q, qdot, t), names):
        check_finite(x, name)  # eager only: a NaN state is a user error, not M's
    check_lagrangian(L, q, qdot, t)
    if force is not None:
        check_force(force, q, qdot, t)
    return q, qdot, t


# Lagrangians already found to be of one degree of freedom, per dtype: the check
# traces L, a noticeable share of a warm sweep's call, and a function object's shape
# contract does not change between calls.
_ONE_DOF_OK: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _coordinates_read(L, dtype, most: int = 6):
    """The fewest coordinates, 2 to `most`, at which `L` returns a scalar, or None.

    A Lagrangian written for n coordinates fails on one in many ways (`a, b = q`, a
    matrix of shape (n, n), `q[1]`): trying wider shapes names n, whatever the way."""
    t = jax.ShapeDtypeStruct((), dtype)
    for n in range(2, most + 1):
        q = jax.ShapeDtypeStruct((n,), dtype)
        try:
            if jax.eval_shape(L, q, q, t).shape == ():
                return n
        except Exception:  # noqa: BLE001 - the user's code, at a shape it may refuse
            continue
    return None


class CoordinatesError(ValueError):
    """A Lagrangian of `coordinates` coordinates where one was expected."""

    def __init__(self, message: str, coordinates: int):
        super().__init__(message)
        self.coordinates = coordinates


def check_one_dof(L, dtype):
    """`L` is a Lagrangian of one coordinate (`q` of shape `(1,)`) in `dtype`."""
    dtype = jnp.dtype(dtype)
    try:
        if dtype in _ONE_DOF_OK.get(L, ()):
            return
    except TypeError:  # not weak-referenceable or not hashable: check every time
        pass
    z = np.zeros((1,), dtype)  # (NumPy: `jnp.zeros` compiles on a first call)
    try:
        check_lagrangian(
            L,
            z,
            z,
            np.zeros((), dtype),
            what=" of one degree of freedom, q of shape (1,)",
        )
    except (TypeError, ValueError) as e:
        n = _coordinates_read(L, dtype)
        if n is None:
            raise
        raise CoordinatesError(
            "`L` must be a Lagrangian of one coordinate, q of shape (1,); it has "
            f"{n} coordinates (L(q, qdot, t) runs with q and qdot of shape ({n},)); "
            f"for more coordinates use lagrax.simulate. At shape (1,): {e}",
            n,
        ) from None
    try:
        _ONE_DOF_OK.setdefault(L, set()).add(dtype)
    except TypeError:
        pass


def check_solvable(qddot, M, ok, q, qdot, t, names=("q", "qdot", "t")):
    """In an eager call, raises on a singular or indefinite mass matrix `M` (`ok`
    False) or non-finite accelerations at `(q, qdot, t)`."""
    if not is_concrete(q, qdot, t, qddot):
        return
    where = (
        f"{names[0]}={np.asarray(q)}, {names[1]}={np.asarray(qdot)}, "
        f"{names[2]}={float(t)}"
    )
    if not bool(ok):
        raise ValueError(
            "The mass matrix M = ∂²L/∂qdot² is singular or indefinite at "
            f"{where}: M = {np.asarray(M).tolist()}. Lagrange's equations cannot "
            "be solved for the accelerations there; if this is a coordinate "
            "singularity, change coordinates (see `lagrax.reparametrize`)."
        )
    if not bool(jnp.all(jnp.isfinite(qddot))):
        raise ValueError(
            f"The accelerations are not finite at {where}: "
            f"qddot = {np.asarray(qddot)}. Check L (and force) there."
        )
