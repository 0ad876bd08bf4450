import contextlib

import jax
import jax.numpy as jnp
import numpy as np


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    """True when two pytrees have the same structure and all leaves are close."""
    same = jax.tree_util.tree_structure(x) == jax.tree_util.tree_structure(y)
    return same and all(
        np.allclose(a, b, rtol=rtol, atol=atol)
        for a, b in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y))
    )


def random_states(key, n, count, scale=1.0):
    kq, kv = jax.random.split(key)
    q = scale * jax.random.normal(kq, (count, n), dtype=jnp.float64)
    qdot = scale * jax.random.normal(kv, (count, n), dtype=jnp.float64)
    return q, qdot


_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


@contextlib.contextmanager
def counting_compiles():
    """`with counting_compiles() as count:`, `count()` the XLA compiles so far in the
    block (JAX's monitoring event). On leaving, a new program is compiled in the
    same window and must be counted: where JAX renames the event, a test asserting
    "no compile" fails instead of passing vacuously."""
    seen = []

    def listener(event, duration, **kwargs):
        if event == _COMPILE_EVENT:
            seen.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield lambda: len(seen)
        before = len(seen)
        unique = float(np.random.default_rng().uniform(1, 2))  # (its own program)
        jax.block_until_ready(jax.jit(lambda x: x * unique)(np.float64(1)))
        assert len(seen) > before, f"no {_COMPILE_EVENT!r} event for a new program"
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
