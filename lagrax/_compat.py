"""What lagrax relies on in its dependencies beyond their documented behaviour: one
function per fact, each with a fallback that is only slower (or an error that says
what is missing), each checked by `tests/test_compat.py`, which fails when the
dependency changes underneath."""

import functools

import diffrax as dfx
import jax
import numpy as np
from jax.extend import core as jex_core


# ------------------------------------------------ the library's calls and their hosts


@functools.cache
def _top_state():
    """JAX's trace state with no transformation active (its evaluation context)."""
    with jax.core.eval_context():
        return jex_core.get_opaque_trace_state()


def top_level() -> bool:
    """Whether no JAX transformation (`jit`, `vmap`, `grad`...) is active here, from
    JAX's opaque trace state (`jax.extend.core`). Fallback where that API moves:
    False, so that callers take their path under a transformation (trace `L` per
    call, compile with the caller's options), which is only slower."""
    try:
        return jex_core.get_opaque_trace_state() == _top_state()
    except Exception:  # noqa: BLE001 -- the API moved: as under a transformation
        return False


def accepted_options(options: dict) -> dict:
    """`options` where the installed XLA compiles a program with them, else `{}`: a
    compile option that a later XLA drops (refused by name) is then not passed, and
    the program compiles with XLA's defaults, which is only slower. Checked once per
    process by compiling a trivial program, and kept in the library's disk cache
    (the answer depends on the jaxlib version, which its keys hold)."""
    items = tuple(sorted(options.items()))
    return dict(items) if _accepted(items) else {}


@functools.cache
def _accepted(items) -> bool:
    from ._cache import executables  # (imports this module)

    return executables.remembered((compiles_with, items), lambda: compiles_with(items))


def compiles_with(items) -> bool:
    """Whether a trivial program compiles with the compile options `items` (pairs)."""
    try:
        f = jax.jit(lambda x: x + 1, compiler_options=dict(items))
        f.lower(np.float32(0)).compile()
    except Exception:  # noqa: BLE001 -- refused (XLA names the option): not passed
        return False
    return True


def unwrap_time(term):
    """`(inner, direction)`: the term a user gave `diffrax.diffeqsolve`, and the sign
    of time, through the wrapper in which `diffeqsolve` hands every term to the
    solver (it integrates `t1 < t0` as increasing `-t`). Recognized as a diffrax
    term with the fields `term` and `direction` (its class is not exported). Where
    diffrax changes it: `(term, 1)`, and the solvers that need the inner term raise,
    naming what they got."""
    direction = 1
    while _time_wrapper(term):
        direction = direction * term.direction
        term = term.term
    return term, direction


def _time_wrapper(term) -> bool:
    return (
        isinstance(term, dfx.AbstractTerm)
        and isinstance(getattr(term, "term", None), dfx.AbstractTerm)
        and hasattr(term, "direction")
    )
