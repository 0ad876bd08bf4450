"""The library's disk cache of compiled programs (`lagrax._executables`): a program
compiled once is loaded by a later process (here: after emptying this process's
table), for any parameter values; damaged entries are compiled again; the folder
stays under its size."""

import collections
import os

import diffrax as dfx
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax import _executables as executables
from lagrax.systems import asymmetric_well, pendulum


# A cheap program to compile: Tsit5, a quarter swing, no error estimate.
SWEEP = dict(solver=dfx.Tsit5(), method="quarter", error_estimate=False)
SWEEP.update(rtol=1e-10, atol=1e-10)


@pytest.fixture
def cache(monkeypatch, tmp_path):
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())
    loads = []
    load = executables._load

    def spy(key, in_tree, out_tree):
        out = load(key, in_tree, out_tree)
        loads.append(out is not None)
        return out

    monkeypatch.setattr(executables, "_load", spy)

    def new_process():
        monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())

    return tmp_path, loads, new_process


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


def test_simulate_batch_is_compiled_once_for_later_processes(cache):
    folder, loads, new_process = cache

    def L(q, qdot, t):
        return 0.5 * jnp.sum(qdot**2) - 0.5 * jnp.sum(q**2)

    q0 = jnp.linspace(-1.0, 1.0, 12).reshape(6, 2)
    run = lambda: lagrax.simulate_batch(
        L, q0, jnp.zeros_like(q0), 0.0, 3.0, solver=lagrax.Taylor(order=8),
        rtol=1e-12, atol=1e-12,
    )  # fmt: skip
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
    executables._evict(str(tmp_path), limit=300)
    assert _files(tmp_path) == ["e2.bin", "e3.bin"]
    assert (tmp_path / "notes.txt").exists()
    executables._evict(str(tmp_path), limit=1000)
    assert _files(tmp_path) == ["e2.bin", "e3.bin"]


def test_a_sweeps_derivative_is_compiled_once_for_later_processes(cache):
    import jax

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
