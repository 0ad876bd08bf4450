"""Each fact `lagrax._compat` relies on, checked against the installed dependencies:
these fail loudly when one moves (a fact that stops holding must be dropped or
rewritten, not left to fail silently)."""

import os
import subprocess
import sys
import textwrap

import jax
import numpy as np

from lagrax import _compat


def _python(code, *args, **env):
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **env},
    )
    return proc.returncode, proc.stdout, proc.stderr


_WRITE = """
    import sys, jax, jax.numpy as jnp
    from jax.experimental import serialize_executable
    jax.config.update("jax_enable_x64", True)
    a = jnp.array([[4.0, 2.0], [2.0, 3.0]])
    compiled = jax.jit(jnp.linalg.cholesky).lower(a).compile()
    payload, in_tree, out_tree = serialize_executable.serialize(compiled)
    open(sys.argv[1], "wb").write(payload)
"""
_LOAD = """
    import sys, jax, jax.numpy as jnp
    from jax.experimental import serialize_executable
    jax.config.update("jax_enable_x64", True)
    from lagrax import _compat
    if sys.argv[2] == "prepare":
        assert _compat.prepare_lapack()
    a = jnp.array([[4.0, 2.0], [2.0, 3.0]])
    in_tree = jax.tree.structure(((a,), {}))
    out_tree = jax.tree.structure(a)
    f = serialize_executable.deserialize_and_load(
        open(sys.argv[1], "rb").read(), in_tree, out_tree
    )
    print(*f(a).ravel().tolist())
"""


def test_prepare_lapack_lets_a_fresh_process_run_a_loaded_lapack_executable(tmp_path):
    """jaxlib sets up its LAPACK kernels at lowering, not at loading: an executable
    that calls one, loaded in a fresh process that lowered nothing, crashes it; after
    `prepare_lapack` it runs. If the control stops crashing, jaxlib sets them up at
    loading now: `prepare_lapack` is no longer needed there."""
    path = tmp_path / "cholesky.bin"
    rc, _, err = _python(_WRITE, path)
    assert rc == 0, err
    assert _compat.prepare_lapack(), "this jaxlib is not in _compat._LAPACK_CHECKED"
    rc, out, err = _python(_LOAD, path, "prepare")
    assert rc == 0, err
    L = np.linalg.cholesky(np.array([[4.0, 2.0], [2.0, 3.0]]))
    np.testing.assert_allclose([float(x) for x in out.split()], L.ravel(), rtol=1e-15)
    rc, _, _ = _python(_LOAD, path, "no")
    assert rc != 0, "a loaded LAPACK executable ran without prepare_lapack"


def test_the_trace_context_says_what_a_context_manager_changes():
    plain = _compat.trace_context()
    assert isinstance(plain, tuple) and plain
    with jax.numpy_rank_promotion("warn"):
        assert _compat.trace_context() != plain
    with jax.default_matmul_precision("highest"):
        assert _compat.trace_context() != plain
    assert _compat.trace_context() == plain


def test_a_nested_jits_unspecified_sharding_is_recognized():
    closed = jax.make_jaxpr(jax.jit(lambda x: 2 * x))(1.0)
    (eqn,) = closed.jaxpr.eqns
    shardings = eqn.params["in_shardings"] + eqn.params["out_shardings"]
    assert shardings and all(_compat.is_unspecified_sharding(s) for s in shardings)
    assert not _compat.is_unspecified_sharding(jax.sharding.SingleDeviceSharding(
        jax.devices()[0]
    ))


_HITS = """
    import sys, jax, jax.numpy as jnp
    from lagrax import _compat
    seen = []
    jax.monitoring.register_event_listener(lambda e, **kw: seen.append(e))
    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    f = lambda x: jnp.sin(x) * 3 + 1
    jax.jit(f)(1.0).block_until_ready()
    assert _compat.JAX_CACHE_HIT_EVENT not in seen
    jax.clear_caches()
    jax.jit(f)(1.0).block_until_ready()
    print(seen.count(_compat.JAX_CACHE_HIT_EVENT))
"""


def test_jaxs_persistent_cache_reports_a_hit_by_its_event(tmp_path):
    rc, out, err = _python(_HITS, tmp_path / "jax")
    assert rc == 0, err
    assert int(out) >= 1, "JAX served a program from its cache without the event"

