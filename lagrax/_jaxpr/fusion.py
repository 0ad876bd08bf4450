r"""Make XLA compute several values in one loop, so that shared work is done once.

XLA on a CPU fuses elementwise work into loops, but a fusion has one output: a cheap
subprogram whose result several fusions consume is copied into each of them (there
is no multi-output fusion here unless a backend flag turns it on, and that flag
crashed on the sweep kernel). A vectorized program whose outputs share their
expensive part (sines and cosines, a recurrence) then computes that part once per
output. `one_fusion` routes the values through one variadic `lax.reduce`, which XLA
compiles as one loop with several outputs.
"""

import contextlib
import functools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from .._compat import accepted_options


# XLA's CPU fusion emitters (its default) cut a large fused Taylor step into
# functions at values with several readers and recompute them per caller; its
# elemental emitters keep one vectorized loop (the factors measured for a Taylor
# trajectory step and a sweep's forward-mode derivative: benchmarks/README.md). A
# compile option of lagrax's own programs, not a global flag: inside a caller's
# `jit`, the caller's options apply.
ELEMENTAL = {"xla_cpu_use_fusion_emitters": False}

# XLA's CPU compiler prefers 256-bit vectors; on an AMD processor with 512-bit ones
# (AVX-512, at full clock) that leaves half of each vector idle: 512 runs the same
# programs bit for bit, faster (benchmarks/README.md). On Intel's, whose clock may
# drop under 512-bit work, XLA's default stays (not measured).
WIDE = {"xla_cpu_prefer_vector_width": 512}


def elemental_options() -> dict:
    """`ELEMENTAL` where the installed XLA takes it, else `{}` (XLA's defaults: the
    same results, slower); with `vector_options()`."""
    return {**accepted_options(ELEMENTAL), **vector_options()}


def vector_options() -> dict:
    """`WIDE` on a CPU whose 512-bit vectors pay (`WIDE`) where the installed XLA
    takes it, else `{}`."""
    return accepted_options(WIDE) if wide_vectors() else {}


@functools.cache
def wide_vectors() -> bool:
    """Whether this machine's processor is an AMD one with AVX-512 (Linux's
    `/proc/cpuinfo`; elsewhere False: XLA's default)."""
    try:
        with open("/proc/cpuinfo") as fh:
            text = fh.read(1 << 16)
    except OSError:
        return False
    flags = next((ln for ln in text.splitlines() if ln.startswith("flags")), "")
    return "AuthenticAMD" in text and "avx512f" in flags.split()


_STATE = threading.local()


@contextlib.contextmanager
def fusion_off():
    """Within this context `one_fusion` is the plain identity: for tracers that read
    the jaxpr themselves (the Taylor recurrences have no rule for the variadic
    `reduce`, and need none for an identity)."""
    before = getattr(_STATE, "off", False)
    _STATE.off = True
    try:
        yield
    finally:
        _STATE.off = before


def fusion_is_off() -> bool:
    """Whether `one_fusion` is the identity here (inside `fusion_off`)."""
    return getattr(_STATE, "off", False)


def one_fusion(values: dict, *, branch_free: bool = False) -> dict:
    r"""The same arrays, computed by XLA in one loop over their entries.

    Each value is stacked with the reducer's identity ($-0.0$ for floats, $0$ for
    integers, False for booleans) and reduced over that new axis of length 2 by one
    variadic `lax.reduce`: exact ($-0.0 + x$ is $x$ for every float $x$, NaN and
    $\pm\infty$ included), and one fusion with many outputs, so everything the values
    share is computed once. Derivatives pass through unchanged (a `custom_jvp`
    identity: the reduction's own JVP rule fails on the symbolic zeros of integer
    tangents).

    Used for the sweep kernel's Taylor step (its step length, position and velocity
    share one straight-line recurrence, otherwise copied into each of their
    fusions), for the kernel's lane update around the step (kept a fusion of its
    own: one fusion of the step and the update together runs slower), and for the
    accelerations of systems written from particle velocities.

    `branch_free=True` pairs each value with the identity by a select instead of a
    stack. XLA emits a stack as a branch per value, and each branch's code
    recomputes what the values share (LLVM merges the copies only in small
    programs; benchmarks/README.md). A
    select reads each value twice, so XLA keeps an expensive operation (a division,
    a square root, a transcendental) out of the fusion: for values that share only
    cheap work, or whose expensive part is cheap to compute in loops of its own.

    **Arguments:** `values`, a dict of arrays of one shape (any dtypes: a variadic
    reduce takes operands of one shape); `branch_free` as above.

    **Returns:** a dict with the same keys and equal values.
    """
    if fusion_is_off():
        return dict(values)
    keys = list(values)
    fn = _fused_select if branch_free else _fused
    return dict(zip(keys, fn(*(values[k] for k in keys))))


def _identity(val):
    if val.dtype == jnp.bool_:
        return np.bool_(False)
    if jnp.issubdtype(val.dtype, jnp.floating):
        return np.array(-0.0, val.dtype)
    return np.array(0, val.dtype)


def _reduce(ops, inits):
    def reducer(a, b):
        return tuple(
            ai | bi if ai.dtype == jnp.bool_ else ai + bi for ai, bi in zip(a, b)
        )

    return tuple(jax.lax.reduce(ops, inits, reducer, (0,)))


@jax.custom_jvp
def _fused(*vals):
    ops, inits = [], []
    for val in vals:
        ident = _identity(val)
        ops.append(jnp.stack([val, jnp.full_like(val, ident)]))
        inits.append(ident)
    return _reduce(ops, inits)


@jax.custom_jvp
def _fused_select(*vals):
    ops, inits = [], []
    for val in vals:
        ident = _identity(val)
        pair = jnp.broadcast_to(val, (2, *val.shape))
        first = jax.lax.broadcasted_iota(jnp.int32, pair.shape, 0) == 0
        ops.append(jnp.where(first, pair, ident))
        inits.append(ident)
    return _reduce(ops, inits)


def _identity_jvp(fn):
    # The identity: tangents pass through (the reduction's own rule chokes on the
    # symbolic zeros of integer fields). Tangents are not fused: one fusion of a
    # gradient's whole step compiles no faster than its few large ones.
    def jvp(primals, tangents):
        return fn(*primals), tuple(tangents)

    return jvp


_fused.defjvp(_identity_jvp(_fused))
_fused_select.defjvp(_identity_jvp(_fused_select))
