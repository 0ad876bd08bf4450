"""The pre-keys of the library's disk cache of executables: a later process (here:
after emptying this process's table) finds a sweep's executable by a key computed
without tracing, and loads it without lowering; every part of what determines the
program changes the pre-key; values without a faithful text take no pre-key."""

import collections
import enum
import os
import subprocess
import sys
import types

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._cache import executables, faithful
from lagrax.systems import asymmetric_well, cycloid, pendulum, rotating_hoop


# A cheap program to compile: Tsit5, a quarter swing, no error estimate.
SWEEP = dict(solver=dfx.Tsit5(), method="quarter", error_estimate=False)
SWEEP.update(rtol=1e-10, atol=1e-10)
Q0 = np.linspace(0.1, 2.5, 8)
LOOSE = dict(rtol=1e-5, atol=1e-5)

_LOWERINGS = []


@pytest.fixture
def cache(executable_cache, monkeypatch):
    folder, loads, new_process = executable_cache

    # Programs lowered by `cached_call` (JAX's in-process caches may spare a lowering
    # its monitoring event).
    program_key = executables._program_key

    def lowered(lowered, options):
        _LOWERINGS.append(lowered)
        return program_key(lowered, options)

    monkeypatch.setattr(executables, "_program_key", lowered)

    def later_process():
        new_process()
        _LOWERINGS.clear()

    return folder, loads, later_process


def _names(folder, suffix):
    return sorted(p.name for p in folder.iterdir() if p.suffix == suffix)


def test_a_later_process_loads_by_prekey_without_lowering(cache):
    folder, loads, new_process = cache
    first = lagrax.sweep_periods(pendulum.lagrangian(g=1.3), Q0, **SWEEP)
    assert loads == [False]
    # (Keys "d…": answers `executables.remembered` keeps, e.g. which compile options
    # the installed XLA takes, asked by whichever test of a process comes first.)
    keys = [n for n in _names(folder, ".key") if not n.startswith("d")]
    assert len(_names(folder, ".bin")) == 1 and len(keys) == 1
    # A later process: the same script, loaded without lowering, bit for bit.
    new_process()
    again = lagrax.sweep_periods(pendulum.lagrangian(g=1.3), Q0, **SWEEP)
    assert loads == [False, True] and _LOWERINGS == []
    np.testing.assert_array_equal(again.periods, first.periods)
    np.testing.assert_array_equal(again.num_steps, first.num_steps)
    # The same body with another g, and another rtol: arguments of the same program.
    exact = pendulum.period(Q0, g=2.0)
    new_process()
    other = lagrax.sweep_periods(pendulum.lagrangian(g=2.0), Q0, **SWEEP)
    assert loads[-1] is True and _LOWERINGS == []
    new_process()
    loose = lagrax.sweep_periods(pendulum.lagrangian(g=2.0), Q0, **SWEEP | LOOSE)
    assert loads[-1] is True and _LOWERINGS == []
    assert len(_names(folder, ".bin")) == 1
    np.testing.assert_allclose(other.periods, exact, rtol=1e-8, atol=0)
    assert not np.allclose(other.periods, first.periods)
    assert (loose.num_steps < other.num_steps).all()
    np.testing.assert_allclose(loose.periods, exact, rtol=1e-4, atol=0)


class _Stop(Exception):
    pass


@pytest.fixture
def prekeys(monkeypatch, tmp_path, without_jax_cache):
    """`prekey(L, q0, **options)`: the pre-key of that sweep's program (None where it
    has none) and, with `lower=True`, the key of its lowered text; nothing is
    compiled."""
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    found = []

    def entry(self, lower=False):
        key = None
        if lower:
            key = executables._program_key(self.jitted.lower(*self.args), self.options)
        found.append((self.prekey, key))
        raise _Stop

    def prekey(L, q0, lower=False, **options):
        monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())
        monkeypatch.setattr(executables._Found, "entry", lambda s: entry(s, lower))
        with pytest.raises(_Stop):
            lagrax.sweep_periods(L, q0, **(SWEEP | options))
        return found[-1] if lower else found[-1][0]

    return prekey


def _potential(V):
    """A Lagrangian of one body and one constant, `V` its only difference."""
    return lambda q, qdot, t: 0.5 * jnp.sum(qdot**2) - 2.0 * jnp.sum(V(q))


def test_what_determines_the_program_changes_the_prekey(prekeys):
    base = prekeys(pendulum.lagrangian(), Q0)
    assert base is not None
    assert prekeys(_potential(jnp.cos), Q0) != prekeys(_potential(jnp.sin), Q0)
    assert prekeys(pendulum.lagrangian(g=3.0, r=0.5), Q0 + 0.1) == base
    assert prekeys(pendulum.lagrangian(), Q0, rtol=1e-6) == base
    others = [
        prekeys(cycloid.lagrangian(), Q0 * 0.3),  # another body
        prekeys(pendulum.lagrangian(), Q0, method="half"),
        prekeys(pendulum.lagrangian(), Q0, lanes=4),
        prekeys(pendulum.lagrangian(), Q0, error_estimate=True),
        prekeys(pendulum.lagrangian(), Q0, solver=dfx.Dopri5()),
        prekeys(pendulum.lagrangian(), Q0, max_steps=100),
        prekeys(pendulum.lagrangian(), Q0.astype(np.float32), **LOOSE),  # dtype
        prekeys(pendulum.lagrangian(), Q0[:5]),  # another shape
        prekeys(pendulum.lagrangian(), Q0, sort=False),  # the order: an argument
    ]
    assert None not in others
    assert len(set(others[:-1])) == len(others) - 1 and base not in others[:-1]
    assert others[-1] == base
    # JAX's configuration is part of it.
    with jax.default_matmul_precision("highest"):
        assert prekeys(pendulum.lagrangian(), Q0) not in (None, base)
    assert prekeys(pendulum.lagrangian(), Q0) == base


def _own_cos():
    """cos with a `custom_jvp` rule made anew (a closure: compared by identity)."""

    @jax.custom_jvp
    def cos(x):
        return jnp.cos(x)

    cos.defjvp(lambda p, t: (jnp.cos(p[0]), -jnp.sin(p[0]) * t[0]))
    return cos


def test_values_without_a_faithful_text_take_no_prekey(prekeys):
    assert prekeys(_potential(_own_cos()), Q0) is None

    def host_cos(x):
        return np.cos(x)

    def with_callback(q, qdot, t):
        shape = jax.ShapeDtypeStruct(q.shape, q.dtype)
        return 0.5 * jnp.sum(qdot**2) + jnp.sum(jax.pure_callback(host_cos, shape, q))

    assert prekeys(with_callback, Q0) is None


def test_a_nested_jit_is_written_out(prekeys):
    def make(n):
        @jax.jit
        def potential(q):
            return jnp.sum(jnp.cos(q)) + jnp.sum(q**n)

        return lambda q, qdot, t: 0.5 * jnp.sum(qdot**2) + potential(q)

    two = prekeys(make(2), Q0)
    assert two is not None and prekeys(make(2), Q0) == two
    assert prekeys(make(4), Q0) not in (None, two)


class _Colour(enum.Enum):
    RED = 1


def test_faithful_text_admits_only_what_it_writes_out():
    text = faithful.text
    assert text(0.0) != text(-0.0) and text(1) != text(1.0) != text(True)
    assert text(np.float64(np.nan)) != text(np.float64(-np.nan))
    assert text((1, "a")) != text([1, "a"]) and text({"a": 1}) == text({"a": 1})
    assert text(np.arange(3)) != text(np.arange(3.0)) != text(np.arange(4.0))
    assert text(np.arange(6).reshape(2, 3)) != text(np.arange(6).reshape(3, 2))
    assert text(dfx.Tsit5()) != text(dfx.Dopri5())
    assert text(jax.lax.sin_p) != text(jax.lax.cos_p)
    assert text(np.dtype("float32")) != text(np.dtype(">f4"))
    for refused in (
        lambda x: x,
        len,
        object(),
        _Colour.RED,  # (a type of this module)
        np.zeros(1 << 14),  # (too large to write out)
        np.array([object()]),
        jnp.ones(3),
        eqx.nn.Lambda(jnp.sin),  # (a function field)
        jax.extend.core.Primitive("sin"),  # (a primitive of nobody's)
    ):
        with pytest.raises(faithful.Unfaithful):
            text(refused)


def test_a_stale_or_damaged_link_falls_back_to_lowering(cache):
    folder, loads, new_process = cache
    first = lagrax.sweep_periods(pendulum.lagrangian(), Q0, **SWEEP)
    ((entry,), (link,)) = _names(folder, ".bin"), _names(folder, ".key")
    # The executable removed: the pre-key names nothing; compiled and written anew.
    (folder / entry).unlink()
    new_process()
    again = lagrax.sweep_periods(pendulum.lagrangian(), Q0, **SWEEP)
    assert loads == [False, False] and len(_LOWERINGS) == 1
    np.testing.assert_array_equal(again.periods, first.periods)
    assert _names(folder, ".bin") == [entry] and _names(folder, ".key") == [link]
    # The link damaged: found by lowering, and recorded again.
    (folder / link).write_bytes(b"not a key")
    new_process()
    lagrax.sweep_periods(pendulum.lagrangian(), Q0, **SWEEP)
    assert loads[-1] is True and len(_LOWERINGS) == 1
    new_process()
    lagrax.sweep_periods(pendulum.lagrangian(), Q0, **SWEEP)
    assert loads[-1] is True and _LOWERINGS == []


def test_distinct_programs_never_share_a_prekey(prekeys):
    # (Lowered, not compiled.) Pendulum variants share a program and a pre-key.
    cases = [
        (pendulum.lagrangian(), Q0, {}),
        (pendulum.lagrangian(g=2.0), Q0, {}),
        (pendulum.lagrangian(), Q0, dict(method="half")),
        (rotating_hoop.lagrangian(), Q0 * 0.5, {}),
        (asymmetric_well.lagrangian(), Q0 * 0.3, {}),
        (_potential(jnp.cos), Q0, {}),
        (_potential(jnp.sin), Q0, {}),
    ]
    pairs = {prekeys(L, q0, lower=True, **kw) for L, q0, kw in cases}
    by_prekey = collections.defaultdict(set)
    for prekey, key in pairs:
        assert prekey is not None
        by_prekey[prekey].add(key)
    assert all(len(keys) == 1 for keys in by_prekey.values())
    assert len(by_prekey) == 6


@pytest.mark.slow
def test_distinct_programs_never_share_a_prekey_all_systems(prekeys):
    from lagrax import systems

    pairs = set()
    for name in dir(systems):
        module = getattr(systems, name)
        if not (
            isinstance(module, types.ModuleType)
            and module.__name__.startswith("lagrax.systems.")
            and callable(getattr(module, "lagrangian", None))
        ):
            continue
        for kw in ({}, dict(method="half"), dict(solver=dfx.Dopri5())):
            try:
                pairs.add(prekeys(module.lagrangian(), Q0 * 0.2, lower=True, **kw))
            except ValueError:  # (not a one-coordinate Lagrangian)
                break
    assert len(pairs) >= 18
    by_prekey = collections.defaultdict(set)
    for prekey, key in pairs:
        by_prekey[prekey].add(key)
    assert None not in by_prekey
    assert all(len(keys) == 1 for keys in by_prekey.values())


# A later process for real: a fresh interpreter, the cache filled by this one.
_LATER = """
import sys
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
import diffrax as dfx
import lagrax
from lagrax._cache import executables
from lagrax.systems import pendulum

# Programs lowered by the library's cache of executables.
lowerings = []
program_key = executables._program_key
executables._program_key = lambda *a: [lowerings.append(a), program_key(*a)][1]
q0 = np.linspace(0.1, 2.5, 8)
res = lagrax.sweep_periods(
    pendulum.lagrangian(g=1.7), q0, solver=dfx.Tsit5(), method="quarter",
    error_estimate=False, rtol=1e-10, atol=1e-10,
)
print(len(lowerings))
print(" ".join(repr(float(T)) for T in res.periods))
"""


@pytest.mark.slow
def test_a_fresh_process_loads_by_prekey(cache, tmp_path):
    folder, loads, new_process = cache
    lagrax.sweep_periods(pendulum.lagrangian(g=1.3), Q0, **SWEEP)
    env = dict(os.environ, LAGRAX_CACHE_DIR=str(folder))
    run = subprocess.run(
        [sys.executable, "-c", _LATER],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    count, periods = run.stdout.strip().splitlines()
    assert count == "0"
    new_process()
    here = lagrax.sweep_periods(pendulum.lagrangian(g=1.7), Q0, **SWEEP)
    assert [float(T) for T in periods.split()] == [float(T) for T in here.periods]


def test_the_choice_of_stepper_is_kept_for_later_processes(
    monkeypatch, tmp_path, without_jax_cache
):
    from lagrax._jaxpr.canonical import canonical_lagrangian
    from lagrax._period import solver as period_solver

    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    decided = []
    resolve = period_solver._resolve
    monkeypatch.setattr(
        period_solver, "_resolve", lambda *a: [decided.append(a[0]), resolve(*a)][1]
    )
    solver = lagrax.Taylor(fallback=dfx.Dopri8())

    def choose(V):
        monkeypatch.setattr(period_solver, "_RESOLVED", collections.OrderedDict())
        L_c, consts = canonical_lagrangian(_potential(V), np.float64)
        return period_solver.resolved_solver(L_c, consts, solver, np.float64)

    # cos has a Taylor recurrence, erf has none: decided once each, then read.
    assert choose(jnp.cos) == lagrax.Taylor() and len(decided) == 1
    assert choose(jax.scipy.special.erf) == dfx.Dopri8() and len(decided) == 2
    assert choose(jnp.cos) == lagrax.Taylor() and len(decided) == 2
    assert choose(jax.scipy.special.erf) == dfx.Dopri8() and len(decided) == 2
    assert len(_names(tmp_path, ".key")) == 2
    # Where the Lagrangian has no faithful text: decided every time, nothing kept.
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path / "other"))

    assert choose(_own_cos()) == lagrax.Taylor() and len(decided) == 3
    assert choose(_own_cos()) == lagrax.Taylor() and len(decided) == 4
    assert not (tmp_path / "other").exists()


def test_a_sweeps_derivative_takes_a_prekey(monkeypatch, tmp_path, without_jax_cache):
    # (Nothing compiled: stopped where the derivative program would be looked up.)
    monkeypatch.setenv("LAGRAX_CACHE_DIR", str(tmp_path))
    found = []

    def entry(self):
        assert self.options is not None  # (the derivative's, with XLA's elemental
        found.append(self.prekey)  # emitters; the forward sweep's has none)
        raise _Stop

    monkeypatch.setattr(executables._Found, "entry", entry)

    def prekey(L, **options):
        monkeypatch.setattr(executables, "_PROGRAMS", collections.OrderedDict())
        mean = lambda q: lagrax.sweep_periods(L, q, **(SWEEP | options)).periods.mean()
        with pytest.raises(_Stop):
            jax.grad(mean)(Q0)
        return found[-1]

    first = prekey(pendulum.lagrangian(g=1.3))
    assert first is not None and prekey(pendulum.lagrangian(g=2.0)) == first
    assert prekey(pendulum.lagrangian(), method="half") not in (None, first)


def _double_pendulum(g):
    def L(q, qdot, t):
        c = jnp.cos(q[0] - q[1])
        kinetic = qdot[0] ** 2 + 0.5 * qdot[1] ** 2 + qdot[0] * qdot[1] * c
        return kinetic + 2 * g * jnp.cos(q[0]) + g * jnp.cos(q[1])

    return L


def test_simulate_batch_a_rebuilt_L_reuses_the_program_and_a_later_process_its_prekey(
    cache,
):
    folder, loads, new_process = cache
    q0 = jnp.asarray([[0.3, -0.2], [0.9, 0.4], [-0.6, 0.1]])
    run = lambda g, t1, **kw: lagrax.simulate_batch(
        _double_pendulum(g), q0, jnp.zeros_like(q0), 0.0, t1,
        solver=lagrax.Taylor(order=8), rtol=1e-12, atol=1e-12, lanes=2, **kw,
    )  # fmt: skip
    a = run(1.0, 2.0)
    assert loads == [False] and len(_names(folder, ".key")) == 1
    # Another g in the same process: the same program, g one of its arguments. From
    # rest, q(t; g) = q(t sqrt(g); 1): g = 4 to t = 1 ends where g = 1 ends at t = 2
    # (with a stale g it would end where g = 1 does at t = 1).
    b = run(4.0, 1.0)
    assert loads == [False] and len(executables._PROGRAMS) == 1
    np.testing.assert_allclose(b.ys[0][:, -1], a.ys[0][:, -1], rtol=0, atol=1e-9)
    assert not np.allclose(run(1.0, 1.0).ys[0][:, -1], a.ys[0][:, -1], atol=1e-3)
    # A later process: found by its pre-key, loaded without lowering, bit for bit.
    new_process()
    again = run(4.0, 1.0)
    assert loads == [False, True] and _LOWERINGS == []
    np.testing.assert_array_equal(again.ys[0], b.ys[0])
    np.testing.assert_array_equal(again.stats["num_steps"], b.stats["num_steps"])
    # A force (a function) has no faithful text: no pre-key, the program by lowering.
    new_process()
    run(1.0, 1.0, force=lambda q, qdot, t: -0.1 * qdot)
    assert len(_LOWERINGS) == 1 and len(_names(folder, ".key")) == 1
