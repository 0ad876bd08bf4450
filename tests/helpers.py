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
