"""What lagrax needs from its dependencies that their public APIs do not say.

The only module that may touch a dependency's internals. One function per fact; each
has a fallback that is only slower (never wrong), and a test in `tests/test_compat.py`
that fails loudly when the dependency moves underneath.
"""

import functools
import os

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core


# ------------------------------------------------------------------ jaxlib's LAPACK

# jaxlib releases on which `prepare_lapack` was checked to set up the kernels (a
# loaded executable that calls them ran in a fresh process: tests/test_compat.py).
_LAPACK_CHECKED = ("0.10.",)


@functools.cache
def prepare_lapack() -> bool:
    """Sets up jaxlib's CPU LAPACK kernels (Cholesky, LU, triangular solves...) in
    this process, for an executable loaded from disk that calls them; False where
    this jaxlib is not known to be set up this way (such executables are then not
    kept on disk: compiled in each process instead).

    jaxlib points its LAPACK kernels at SciPy's when a program that calls one is
    lowered, not when an executable is loaded: in a new process an executable that
    was loaded without lowering anything calls a null pointer and the process dies
    (jax-ml/jax#29610). Lowering one small Cholesky factorization sets them all."""
    if not jax.lib.__version__.startswith(_LAPACK_CHECKED):
        return False
    try:
        spec = jax.ShapeDtypeStruct((2, 2), jnp.float32)
        jax.jit(jnp.linalg.cholesky).lower(spec)  # (the cache runs on a CPU only)
    except Exception:  # noqa: BLE001 -- lowering moved: such programs not kept
        return False
    return True


# ------------------------------------------------- XLA's threads within one program

# XLA's CPU client sizes its thread pool for a program's own loops when it starts,
# from this variable (else from the cores the process may use, at least one thread
# per CPU device); a program compiled there has each large loop split into as many
# parts, run in parallel (`outer_dimension_partitions` in its optimized HLO).
_POOL_VARIABLES = ("PJRT_NPROC", "NPROC")


def one_thread_environment() -> dict:
    """The environment variables under which a new process's XLA CPU client keeps
    every loop of a program on the thread that runs it (its pool of one thread).
    Where a later XLA stops reading them, a program compiled there is split as in
    any other process: only slower, as today."""
    return {_POOL_VARIABLES[0]: "1"}


# XLA's CPU runtime runs a loop op by op, each op of each iteration dispatched on its
# own; a while loop whose one iteration reads and writes fewer bytes than this backend
# option's threshold it compiles as one function instead ("small while loop
# hoisting"), which runs the compact tiers' programs of many short loops faster and
# the specialized unrolled ones slower (benchmarks/README.md). No compile option
# reaches a backend option (a map that `compiler_options` cannot set): only the
# `XLA_FLAGS` of a process started for the program. The same map passes options to
# LLVM: no loop unrolling, so that XLA's gathers of rows of few lanes (a compact
# program's operands, 32 lanes) compile to vector loops, not to scalar code unrolled
# lane by lane (3.4x faster a block at 32 lanes; the same at 128).
_WHOLE_LOOPS = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold="
_NO_UNROLL = ",-unroll-threshold=0"


def whole_loop_environment(env: dict, loop_bytes: int) -> dict:
    """`env` (a new process's environment) with `XLA_FLAGS` asking XLA's CPU compiler
    to compile each while loop of a program whose iteration reads and writes fewer
    than `loop_bytes` bytes as one function, and LLVM not to unroll loops (after any
    flags `env` holds). Where a later XLA drops the first option, its programs
    compile as in any other process: only slower, as before; where LLVM refuses the
    second, the process fails and the program compiles in the caller's
    (`lagrax._cache.apart`)."""
    flags = env.get("XLA_FLAGS", "")
    whole = f"{_WHOLE_LOOPS}{int(loop_bytes)}{_NO_UNROLL}"
    return {**env, "XLA_FLAGS": f"{flags} {whole}".strip()}


def splits_loops() -> bool:
    """Whether XLA may split a program's loops across threads in this process: it
    may run on more than one core and no pool variable keeps it to one thread (the
    pool holds at least one thread per CPU device)."""
    if jax.local_device_count() > 1:
        return True
    for name in _POOL_VARIABLES:
        value = os.environ.get(name)
        if value is not None and value.strip().isdigit():
            return int(value) > 1
    try:
        return len(os.sched_getaffinity(0)) > 1
    except (AttributeError, OSError):  # (no affinity here: the machine's count)
        return (os.cpu_count() or 1) > 1


# ------------------------------------------------------------ JAX's trace context


def trace_context():
    """JAX's own list of the settings that enter a trace (its configuration's
    context managers included), as values with a faithful text; raises where JAX
    moved it (the caller then keys its program by lowering it, never by a key that
    could name another program). No public API lists them."""
    from jax._src import config as jax_config

    context = []
    for value in jax_config.trace_context():
        if type(value).__name__ == "AxisEnv":  # (under no transformation: empty)
            names = value.spmd_axis_names or value.explicit_mesh_axis_names
            if value.axis_sizes or names:
                raise ValueError("an axis environment")
            value = "AxisEnv()"
        context.append(value)
    return tuple(context)


def is_unspecified_sharding(x) -> bool:
    """Whether `x` is JAX's placeholder for a sharding left unspecified (as a nested
    `jit`'s equation holds it); it has no public name. False where JAX renamed it:
    such a program then has no pre-key (found by lowering)."""
    t = type(x)
    return f"{t.__module__}.{t.__qualname__}" == (
        "jax._src.named_sharding.UnspecifiedValue"
    )


# --------------------------------------------------- JAX's persistent compile cache

# The `jax.monitoring` event JAX records when its persistent compilation cache serves
# a program (an executable that serializes again without its object code on a CPU).
JAX_CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"


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
