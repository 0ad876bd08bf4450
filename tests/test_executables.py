"""The library's disk cache of compiled programs (`lagrax._cache.executables`): a
program compiled once is loaded by a later process (here: after emptying this process's
table), for any parameter values; damaged entries are compiled again; the folder
stays under its size."""

import collections
import os
import subprocess
import sys

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._cache import executables, folder
from lagrax.systems import asymmetric_well, pendulum


# A cheap program to compile: Tsit5, a quarter swing, no error estimate.
SWEEP = dict(solver=dfx.Tsit5(), method="quarter", error_estimate=False)
SWEEP.update(rtol=1e-10, atol=1e-10)


@pytest.fixture
def cache(executable_cache):
    return executable_cache


def _files(folder):
    return sorted(p.name for p in folder.iterdir() if p.suffix == ".bin")


def test_a_sweep_is_compiled_once_for_later_processes(cache):
    folder, loads, new_process = cache
    q0 = jnp.linspace(0.1, 2.5, 24)
    first = lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q0, **SWEEP)
    assert loads == [False] and len(_files(folder)) == 1
    np.testing.assert_allclose(
        first.periods, pendulum.period(q0, g=1.3), rtol=1e-8, atol=0
    )
    # A later process, the same body with another parameter value: loaded, not
    # compiled (the value is an argument of the program), and right for that value.
    new_process()
    other = lagrax.sweep_periods(pendulum.lagrangian(g=2.0), q0, **SWEEP)
    assert loads == [False, True] and len(_files(folder)) == 1
    np.testing.assert_allclose(
        other.periods, pendulum.period(q0, g=2.0), rtol=1e-8, atol=0
    )
    # The first one again from disk: the same numbers, bit for bit.
    new_process()
    again = lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q0, **SWEEP)
    assert loads[-1] is True
    np.testing.assert_array_equal(again.periods, first.periods)
    np.testing.assert_array_equal(again.num_steps, first.num_steps)
    # Another body is another program; so is another number of amplitudes.
    lagrax.sweep_periods(asymmetric_well.lagrangian(), q0 * 0.3, **SWEEP)
    lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q0[:10], **SWEEP)
    assert loads[-2:] == [False, False] and len(_files(folder)) == 3


def test_a_damaged_entry_is_compiled_again(cache):
    folder, loads, new_process = cache
    q0 = jnp.linspace(0.1, 2.5, 8)
    first = lagrax.sweep_periods(pendulum.lagrangian(), q0, **SWEEP)
    (name,) = _files(folder)
    (folder / name).write_bytes(b"not an executable")
    new_process()
    again = lagrax.sweep_periods(pendulum.lagrangian(), q0, **SWEEP)
    assert loads == [False, False]
    np.testing.assert_array_equal(again.periods, first.periods)
    assert (folder / name).stat().st_size > 1000  # written anew
    new_process()
    lagrax.sweep_periods(pendulum.lagrangian(), q0, **SWEEP)
    assert loads[-1] is True


def _oscillators():
    """`(q0, run)`: `simulate_batch` of six 2-D harmonic oscillators, a cheap
    Taylor program."""

    def L(q, qdot, t):
        return 0.5 * jnp.sum(qdot**2) - 0.5 * jnp.sum(q**2)

    q0 = jnp.linspace(-1.0, 1.0, 12).reshape(6, 2)
    run = lambda: lagrax.simulate_batch(
        L, q0, jnp.zeros_like(q0), 0.0, 3.0, solver=lagrax.Taylor(order=8),
        rtol=1e-12, atol=1e-12,
    )  # fmt: skip
    return q0, run


def test_simulate_batch_is_compiled_once_for_later_processes(cache):
    folder, loads, new_process = cache

    q0, run = _oscillators()
    first = run()
    new_process()
    again = run()
    assert loads == [False, True] and len(_files(folder)) == 1
    np.testing.assert_array_equal(again.ys[0], first.ys[0])
    np.testing.assert_allclose(first.ys[0][:, -1], q0 * np.cos(3.0), atol=1e-11)


def test_off_writes_nothing(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("LAGRAX_CACHE_DIR", "")
    monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())
    q0 = jnp.linspace(0.1, 2.5, 8)
    res = lagrax.sweep_periods(pendulum.lagrangian(), q0, **SWEEP)
    assert list(tmp_path.rglob("*")) == [] and len(executables._PROGRAMS) == 0
    np.testing.assert_allclose(res.periods, pendulum.period(q0), rtol=1e-8)


def test_eviction_keeps_the_most_recently_used(tmp_path):
    for i, size in enumerate([300, 200, 100, 50]):
        path = tmp_path / f"e{i}.bin"
        path.write_bytes(b"x" * size)
        os.utime(path, (1000 + i, 1000 + i))  # e0 oldest
    (tmp_path / "notes.txt").write_bytes(b"y" * 1000)  # not an entry: kept
    folder.evict(str(tmp_path), limit=300)
    assert _files(tmp_path) == ["e2.bin", "e3.bin"]
    assert (tmp_path / "notes.txt").exists()
    folder.evict(str(tmp_path), limit=1000)
    assert _files(tmp_path) == ["e2.bin", "e3.bin"]


def test_a_sweeps_derivative_is_compiled_once_for_later_processes(cache):
    folder, loads, new_process = cache
    q0 = jnp.linspace(0.2, 2.0, 12)

    def grad(g):
        L = pendulum.lagrangian(g=g)
        return jax.grad(lambda q: lagrax.sweep_periods(L, q, **SWEEP).periods.sum())(q0)

    first = grad(1.3)
    assert loads == [False] and len(_files(folder)) == 1  # (the derivative program)
    new_process()
    other = grad(2.0)
    assert loads == [False, True] and len(_files(folder)) == 1
    # dT/dq0 scales as T: g^(-1/2).
    np.testing.assert_allclose(other, first * np.sqrt(1.3 / 2.0), rtol=1e-7)
    exact = jax.grad(lambda q: pendulum.period(q, g=1.3).sum())(q0)
    np.testing.assert_allclose(first, exact, rtol=1e-6)


def _failing_loads(monkeypatch):
    """Executables loaded from disk that raise at run time, as one does whose thunks
    name a kernel its object code lacks; and the keys removed and stored."""
    load, remove, store = executables._load, executables._remove, executables._store
    events = []

    def broken(key, in_tree, out_tree):
        if load(key, in_tree, out_tree) is None:
            return None

        def run(*args):
            raise jax.errors.JaxRuntimeError(
                "NOT_FOUND: Function select_bitcast_fusion.4 not found (type id: 1)"
            )

        return run

    def removed(key):
        events.append(("remove", key))
        remove(key)

    def stored(key, compiled):
        events.append(("store", key))
        store(key, compiled)

    monkeypatch.setattr(executables, "_load", broken)
    monkeypatch.setattr(executables, "_remove", removed)
    monkeypatch.setattr(executables, "_store", stored)
    return events, load


def test_a_loaded_executable_that_fails_is_compiled_again(cache, monkeypatch):
    folder, loads, new_process = cache
    q0 = jnp.linspace(0.1, 2.5, 8)
    first = lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q0, **SWEEP)
    (name,) = _files(folder)
    events, load = _failing_loads(monkeypatch)
    new_process()
    other = lagrax.sweep_periods(pendulum.lagrangian(g=2.0), q0, **SWEEP)
    # Loaded, failed, removed, compiled and stored again; the call's result is right.
    key = name.removesuffix(".bin")
    assert loads == [False, True] and events == [("remove", key), ("store", key)]
    np.testing.assert_allclose(
        other.periods, pendulum.period(q0, g=2.0), rtol=1e-8, atol=0
    )
    # This process keeps the fresh compile; a later one loads the new entry.
    lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q0, **SWEEP)
    assert loads == [False, True] and _files(folder) == [name]
    monkeypatch.setattr(executables, "_load", load)
    new_process()
    again = lagrax.sweep_periods(pendulum.lagrangian(g=1.3), q0, **SWEEP)
    assert loads[-1] is True
    np.testing.assert_array_equal(again.periods, first.periods)


def test_a_loaded_tape_executable_that_fails_is_compiled_again(
    monkeypatch, tmp_path, without_jax_cache
):
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(executables, "_LOADED", {})
    f = jax.jit(lambda x, y: jnp.sin(x) * y)
    x, y = jnp.linspace(0.0, 1.0, 5), jnp.float64(2.0)
    out_tree = jax.tree.structure(x)
    first = executables.call(f, "sin", out_tree, x, y)
    (name,) = _files(tmp_path)
    events, _ = _failing_loads(monkeypatch)
    monkeypatch.setattr(executables, "_LOADED", {})
    again = executables.call(f, "sin", out_tree, x, y)
    key = name.removesuffix(".bin")
    assert events == [("remove", key), ("store", key)] and _files(tmp_path) == [name]
    np.testing.assert_array_equal(again, first)
    np.testing.assert_allclose(first, 2.0 * np.sin(np.linspace(0.0, 1.0, 5)))
    assert executables._LOADED[key][1] is None  # (the fresh compile, not checked)


# In a new process: JAX's persistent compilation cache starts once per process.
_FROM_JAX_CACHE = """
import os, sys
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
from lagrax._cache import executables, folder

f = jax.jit(lambda x: jnp.where(x > 0, jnp.sin(x), jnp.cos(x)) * 2.0)
x = jnp.linspace(-1.0, 1.0, 7)
first = np.asarray(executables.cached_call(f, None, x))
folder = executables.cache_dir()
print(len(os.listdir(folder)) if os.path.isdir(folder) else 0)
print(np.allclose(first, 2.0 * np.where(x > 0, np.sin(x), np.cos(x))))
# A program JAX took from its cache, written anyway: loaded, it has no object code.
jax.clear_caches()
key = executables._program_key(f.lower(x), None)
executables._store(key, f.lower(x).compile())
executables._PROGRAMS.clear()
removed = []
remove = executables._remove
executables._remove = lambda k: [removed.append(k), remove(k)]
again = np.asarray(executables.cached_call(f, None, x))
print(executables._jax_cache_hits > 0, removed == [key], len(os.listdir(folder)))
print(np.array_equal(again, first))
"""


def test_jaxs_compilation_cache_on_nothing_is_written(tmp_path):
    # An executable JAX took from its cache serializes without its object code on
    # CPU: loaded, it fails at its first kernel (NOT_FOUND); the entry is removed
    # and the program compiled again.
    env = dict(os.environ, LAGRAX_CACHE_DIR=str(tmp_path / "lagrax"))
    run = subprocess.run(
        [sys.executable, "-c", _FROM_JAX_CACHE, str(tmp_path / "jax")],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["0", "True", "True", "True", "0", "True"]


def test_a_program_the_worker_cannot_compile_is_compiled_here(
    monkeypatch, tmp_path, without_jax_cache
):
    """Where compiling apart fails (here: no worker to start), the program is
    compiled in the process, written and run as before."""
    from lagrax._cache import apart

    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(executables, "_LOADED", {})
    monkeypatch.setattr(executables, "STATS", collections.Counter())
    monkeypatch.setattr(apart, "wanted", lambda: True)
    monkeypatch.setattr(apart, "_WORKER", str(tmp_path / "missing.py"))
    f = executables.program(lambda x, y: jnp.sin(x) * y)
    x, y = jnp.linspace(0.0, 1.0, 5), jnp.float64(2.0)
    out = executables.call(f, "sin, here", jax.tree.structure(x), x, y)
    assert dict(executables.STATS) == {"compiled": 1, "written": 1}
    assert len(_files(tmp_path)) == 1
    np.testing.assert_allclose(out, 2.0 * np.sin(np.linspace(0.0, 1.0, 5)))


def _batch_call(monkeypatch):
    """A `simulate_batch` call's specialized program, as `cached_call` gets it
    (compiled here with the disk cache off, nothing written): `(args, kwargs,
    solution)`."""
    from lagrax._trajectory import batch

    seen = []
    real = batch.cached_call
    monkeypatch.setattr(
        batch, "cached_call", lambda *a, **kw: seen.append((a, kw)) or real(*a, **kw)
    )

    _, run = _oscillators()
    with monkeypatch.context() as m:
        m.setenv("LAGRAX_CACHE_DIR", "")
        sol = run()
    ((args, kwargs),) = seen
    return args, kwargs, run, sol


def test_a_program_compiled_later_is_loaded_in_its_place(cache, monkeypatch):
    """`compile_later`: a call's specialized program compiled by a worker process
    while this one goes on; once done, a later call finds it on disk by its pre-key
    and loads it, with the numbers of the program compiled here, bit for bit."""
    from lagrax._trajectory import batch

    folder, loads, new_process = cache
    monkeypatch.setattr(executables, "_LATER", {})
    monkeypatch.setattr(executables, "STATS", collections.Counter())
    monkeypatch.setattr(executables, "_usable_cores", lambda: 2)
    monkeypatch.setenv("LAGRAX_BACKGROUND", "1")
    (jitted, options, cfg, shape, *rest), kwargs, run, here = _batch_call(monkeypatch)
    assert not executables.available(jitted, options, cfg, shape, *rest, **kwargs)
    plain = batch._plain(cfg, shape, *kwargs["origin"][1:])
    start = lambda: executables.compile_later(
        plain, jitted, options, cfg, shape, *rest, **kwargs
    )
    assert start() == "running"
    assert start() == "running"  # (one job per program)
    ((_, job),) = executables._LATER.items()
    job.thread.join(timeout=300)
    assert job.state == "done", job.state
    assert executables.later_state(jitted, options, cfg, shape, *rest, **kwargs) == (
        "done"
    )
    assert executables.available(jitted, options, cfg, shape, *rest, **kwargs)
    assert dict(executables.STATS) == {"written": 1, "compiled later": 1}
    new_process()
    again = run()
    assert loads == [True] and executables.STATS["compiled"] == 0
    np.testing.assert_array_equal(again.ys[0], here.ys[0])
    np.testing.assert_array_equal(again.ys[1], here.ys[1])


def test_nothing_is_compiled_later_without_an_idle_core(cache, monkeypatch):
    from lagrax._trajectory import batch

    monkeypatch.setattr(executables, "_LATER", {})
    monkeypatch.setenv("LAGRAX_BACKGROUND", "1")
    (jitted, options, cfg, shape, *rest), kwargs, _, _ = _batch_call(monkeypatch)
    plain = batch._plain(cfg, shape, *kwargs["origin"][1:])
    start = lambda: executables.compile_later(
        plain, jitted, options, cfg, shape, *rest, **kwargs
    )
    monkeypatch.setattr(executables, "_usable_cores", lambda: 1)
    assert start() is None
    monkeypatch.setattr(executables, "_usable_cores", lambda: 2)
    monkeypatch.setenv("LAGRAX_BACKGROUND", "0")
    assert start() is None
    monkeypatch.setenv("LAGRAX_BACKGROUND", "1")
    monkeypatch.setenv("LAGRAX_CACHE_DIR", "")
    assert start() is None
    assert executables._LATER == {}


def test_a_caller_context_the_job_cannot_see_compiles_nothing_later(cache, monkeypatch):
    """A thread traces under JAX's global settings: under a context manager of the
    caller's that enters the program (here the default matmul precision), the job
    refuses rather than name another program by the caller's pre-key."""
    from lagrax._trajectory import batch

    monkeypatch.setattr(executables, "_LATER", {})
    monkeypatch.setattr(executables, "_usable_cores", lambda: 2)
    monkeypatch.setenv("LAGRAX_BACKGROUND", "1")
    (jitted, options, cfg, shape, *rest), kwargs, _, _ = _batch_call(monkeypatch)
    plain = batch._plain(cfg, shape, *kwargs["origin"][1:])
    with jax.default_matmul_precision("highest"):
        state = executables.compile_later(
            plain, jitted, options, cfg, shape, *rest, **kwargs
        )
    assert state in ("running", "failed")  # (it fails at once)
    ((job),) = executables._LATER.values()
    job.thread.join(timeout=300)
    assert job.state == "failed" and job.worker is None
    assert not any(cache[0].iterdir())
