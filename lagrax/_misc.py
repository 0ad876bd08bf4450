"""Input checks shared by the public entry points.

Every check here runs at trace time on shapes and dtypes (always available), and on
values only when they are concrete (an eager call), so that user errors surface as a
`TypeError`/`ValueError` naming the argument instead of a tracer traceback.
"""

import jax
import jax.numpy as jnp
import numpy as np


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
    return jnp.asarray(x)


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
    t = as_real_array(t, name) if not isinstance(t, int | float) else jnp.asarray(t)
    if jnp.ndim(t) != 0:
        raise ValueError(f"`{name}` must be a scalar time; got shape {jnp.shape(t)}.")
    return jnp.asarray(t, dtype=dtype)


def check_finite(x, name: str):
    """Raises if `x` is concrete and has a NaN or infinite entry."""
    # numpy, not jnp: inside a jit trace a jnp op on a concrete array is a tracer.
    if is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
        raise ValueError(
            f"`{name}` must be finite; got {np.asarray(x)!r} (an entry is not finite)."
        )
