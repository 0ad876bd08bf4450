"""Each fact `lagrax._compat` relies on, checked against the installed dependencies:
these fail loudly when one moves (a fact that stops holding must be dropped or
rewritten, not left to fail silently)."""

import os
import subprocess
import sys
import textwrap

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

from lagrax import _compat
from lagrax._jaxpr.fusion import (
    ELEMENTAL,
    elemental_options,
    vector_options,
    WIDE,
    wide_vectors,
)
from lagrax._trajectory.simulate import elemental


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
    assert not _compat.is_unspecified_sharding(
        jax.sharding.SingleDeviceSharding(jax.devices()[0])
    )


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


# ------------------------------------------------ the library's calls and their hosts


def test_top_level_is_false_under_every_transformation():
    seen = []

    def f(x):  # (a new function per transformation: none reuses another's trace)
        seen.append(_compat.top_level())
        return x

    assert _compat.top_level()  # (False where JAX's opaque trace state is gone)
    jax.jit(lambda x: f(x))(1.0)
    jax.vmap(lambda x: f(x))(jnp.ones(2))
    jax.grad(lambda x: f(x))(1.0)
    jax.jvp(lambda x: f(x), (1.0,), (1.0,))
    jax.make_jaxpr(lambda x: f(x))(1.0)
    assert seen == [False] * 5
    assert _compat.top_level()


def test_xla_takes_the_elemental_emitters_option():
    # Fails when the installed XLA no longer knows `xla_cpu_use_fusion_emitters`:
    # then every eager CPU program compiles with XLA's default emitters (slower
    # Taylor steps, longer compiles); see `lagrax._jaxpr.fusion`.
    assert _compat.compiles_with(tuple(ELEMENTAL.items()))
    assert elemental_options() == {**ELEMENTAL, **vector_options()}


def test_xla_takes_the_wide_vectors_option_and_computes_the_same():
    # Fails when the installed XLA no longer knows `xla_cpu_prefer_vector_width`
    # (then programs on AMD's AVX-512 run at XLA's default width, slower); the
    # option changes no result, bit for bit.
    assert _compat.compiles_with(tuple(WIDE.items()))
    assert vector_options() == (WIDE if wide_vectors() else {})

    def f(x, y):
        return jax.lax.fori_loop(0, 5, lambda i, x: jnp.sin(x) * y + jnp.cos(x) / y, x)

    x = jnp.linspace(-3.0, 3.0, 1001)
    y = jnp.linspace(0.5, 2.0, 1001)
    plain = jax.jit(f)(x, y)
    wide = jax.jit(f, compiler_options=WIDE)(x, y)
    np.testing.assert_array_equal(wide, plain)


def test_an_option_xla_refuses_is_not_passed():
    refused = {"xla_cpu_no_such_option_in_any_xla": False}
    assert not _compat.compiles_with(tuple(refused.items()))
    assert _compat.accepted_options(refused) == {}
    assert _compat.accepted_options({**refused, **ELEMENTAL}) == {}


def test_an_elemental_call_inside_a_callers_transformation_runs():
    # JAX refuses compile options on a `jit` staged into a caller's `jit` or `grad`
    # (a ValueError); `elemental` then runs the function in the caller's program.
    f = lambda x: jnp.sin(x) * x
    fast = elemental(f)
    df = lambda x: jnp.cos(x) * x + jnp.sin(x)
    np.testing.assert_allclose(fast(0.5), f(0.5), rtol=1e-15)
    np.testing.assert_allclose(jax.jit(fast)(0.5), f(0.5), rtol=1e-15)
    np.testing.assert_allclose(jax.grad(fast)(0.5), df(0.5), rtol=1e-15)
    np.testing.assert_allclose(jax.vmap(fast)(jnp.ones(2)), f(jnp.ones(2)))
    # (The refusal itself, so that the above exercises the fallback.)
    options = jax.jit(f, compiler_options=ELEMENTAL)
    try:
        jax.jit(lambda x: options(x))(0.5)
    except ValueError:
        pass
    else:
        raise AssertionError("JAX took compile options on a nested jit")


_SEEN = []


class _Probe(dfx.AbstractSolver):
    """Euler's method that records what `diffeqsolve` hands it (in `_SEEN`, while
    tracing) and the direction of time (as its solver state)."""

    term_structure = dfx.AbstractTerm
    interpolation_cls = dfx.LocalLinearInterpolation

    def order(self, terms):
        return 1

    def init(self, terms, t0, t1, y0, args):
        inner, direction = _compat.unwrap_time(terms)
        _SEEN.append((terms, inner))
        return jnp.asarray(direction)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1 = y0 + terms.vf_prod(t0, y0, args, terms.contr(t0, t1))
        return y1, None, dict(y0=y0, y1=y1), solver_state, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def test_diffeqsolve_hands_solvers_the_term_through_a_time_wrapper():
    # Fails when diffrax's wrapper of terms changes: then `lagrax.Taylor` and the
    # variational integrators refuse every term (they name what they got).
    f = lambda t, y, args: -y
    term = dfx.ODETerm(f)
    saveat = dfx.SaveAt(t1=True, solver_state=True)
    for t1, sign in ((1.0, 1), (-1.0, -1)):
        _SEEN.clear()
        sol = dfx.diffeqsolve(
            term, _Probe(), 0.0, t1, 0.5 * sign, jnp.ones(()), saveat=saveat
        )
        assert _SEEN
        for terms, inner in _SEEN:
            # (Handed a wrapper, not the term: the unwrapping has work to do.)
            assert not isinstance(terms, dfx.ODETerm)
            assert type(inner) is dfx.ODETerm and inner.vector_field is f
        assert int(sol.solver_state) == sign
        np.testing.assert_allclose(sol.ys, 0.5**2 if sign > 0 else 1.5**2)
    assert _compat.unwrap_time(term) == (term, 1)


_SPLIT = """
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
f = lambda x: jax.lax.fori_loop(0, 3, lambda i, x: jnp.sin(x) * 1.0001 + x, x)
options = {"xla_cpu_use_fusion_emitters": False}
x = jnp.ones(500_000)
text = jax.jit(f, compiler_options=options).lower(x).compile().as_text()
print(text.count('outer_dimension_partitions":["'))
"""


def test_one_thread_environment_keeps_a_programs_loops_whole():
    """In a process started with `one_thread_environment`, XLA splits no loop
    across threads; with a pool of two it splits this one. If the first fails, XLA
    no longer reads the variable (the programs `lagrax._cache.apart` compiles are
    split again: slower, not wrong)."""
    counts = {}
    for name, extra in (("one", _compat.one_thread_environment()), ("two", {})):
        env = {**os.environ, "PJRT_NPROC": "2", **extra}
        proc = subprocess.run(
            [sys.executable, "-c", _SPLIT], env=env, capture_output=True, text=True
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        counts[name] = int(proc.stdout.split()[-1])
    assert counts["one"] == 0 and counts["two"] >= 1, counts


_WHOLE = """
import jax, jax.numpy as jnp
f = lambda x: jax.lax.fori_loop(0, 3, lambda i, x: jnp.sin(x) * 1.0001 + x, x)
text = jax.jit(f).lower(jnp.ones(100_000)).compile().as_text()
print(text.count('xla_cpu_small_call="true"'))
"""


def test_whole_loop_environment_compiles_a_loop_as_one_function():
    """In a process started with `whole_loop_environment`, XLA compiles this loop
    (800 kB an iteration, over XLA's default threshold) as one function; without,
    it does not. If the first fails, XLA no longer reads the option (the compact
    programs `lagrax._cache.apart` compiles run op by op again: slower, not wrong);
    if the process fails, LLVM refuses the option not to unroll loops (those
    programs then compile in the caller's process); the user's own flags are kept."""
    counts = {}
    for name in ("whole", "plain"):
        env = {**os.environ, "XLA_FLAGS": "--xla_cpu_enable_fast_math=false"}
        if name == "whole":
            env = _compat.whole_loop_environment(env, 1 << 62)
            assert env["XLA_FLAGS"].startswith("--xla_cpu_enable_fast_math=false ")
        proc = subprocess.run(
            [sys.executable, "-c", _WHOLE], env=env, capture_output=True, text=True
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        counts[name] = int(proc.stdout.split()[-1])
    assert counts["whole"] >= 1 and counts["plain"] == 0, counts
