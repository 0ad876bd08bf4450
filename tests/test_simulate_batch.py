"""`lagrax.simulate_batch`: the refilling Taylor loop against exact solutions and
`simulate`, saved times, per-release spans and outcomes, the fallback."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax

from .helpers import counting_compiles


def oscillator(q, qdot, t):
    # x'' = -x: q(t) = q0 cos t + v0 sin t.
    return 0.5 * jnp.sum(qdot**2) - 0.5 * jnp.sum(q**2)


def exact(q0, v0, t):
    return q0 * np.cos(t) + v0 * np.sin(t), -q0 * np.sin(t) + v0 * np.cos(t)


TAYLOR = lagrax.Taylor(order=10)


def test_refilling_lanes_per_release_spans_and_directions():
    # 7 releases through 3 lanes: the queue refills; spans differ, two run backwards.
    rng = np.random.default_rng(0)
    q0 = rng.uniform(-1, 1, (7, 2))
    v0 = rng.uniform(-1, 1, (7, 2))
    t1 = np.array([1.0, 5.0, 0.5, 9.0, -2.0, 3.0, -7.5])
    sol = lagrax.simulate_batch(
        oscillator, q0, v0, 0.0, t1, solver=TAYLOR, rtol=1e-13, atol=1e-13, lanes=3
    )
    assert sol.ys[0].shape == (7, 1, 2) and sol.ts.shape == (7, 1)
    assert np.all(np.asarray(sol.result == dfx.RESULTS.successful))
    np.testing.assert_allclose(sol.ts[:, 0], t1)
    q, v = exact(q0, v0, t1[:, None])
    np.testing.assert_allclose(sol.ys[0][:, 0], q, atol=1e-11)
    np.testing.assert_allclose(sol.ys[1][:, 0], v, atol=1e-11)
    # Longer spans take more steps, each release its own count.
    steps = np.asarray(sol.stats["num_steps"])
    assert steps[3] > steps[0] > 0


def test_under_a_callers_jit_with_its_compiler_options():
    # Inside a user's `jit` the loop is traced into that program (a nested `jit`
    # takes no compiler options); the same states as the eager call.
    q0, v0 = np.array([[1.0, 0.2], [0.3, -0.4]]), np.array([[0.0, 0.1], [-0.5, 0.0]])

    def end(q0, t1):
        sol = lagrax.simulate_batch(
            oscillator, q0, v0, 0.0, t1, solver=TAYLOR, rtol=1e-12, atol=1e-12
        )
        return sol.ys[0][:, -1]

    options = {"xla_cpu_use_fusion_emitters": False}
    jitted = jax.jit(end, compiler_options=options)(jnp.asarray(q0), 2.0)
    np.testing.assert_allclose(jitted, end(q0, 2.0), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(jitted, exact(q0, v0, 2.0)[0], atol=1e-10)


def test_saved_times_from_the_step_polynomials():
    ts = jnp.linspace(0.0, 6.0, 25)  # several per step at this tolerance
    q0 = np.array([[1.0], [0.3]])
    v0 = np.array([[0.0], [-0.5]])
    sol = lagrax.simulate_batch(
        oscillator,
        q0,
        v0,
        0.0,
        6.0,
        solver=TAYLOR,
        rtol=1e-12,
        atol=1e-12,
        saveat=dfx.SaveAt(ts=ts),
    )
    assert sol.ys[0].shape == (2, 25, 1)
    q, v = exact(q0[:, None, :], v0[:, None, :], np.asarray(ts)[None, :, None])
    np.testing.assert_allclose(sol.ys[0], q, atol=1e-10)
    np.testing.assert_allclose(sol.ys[1], v, atol=1e-10)


def test_agrees_with_simulate_and_reports_failures_per_release():
    def L(q, qdot, t):
        # A mass q^2 that vanishes at q = 0: released there, q'' is NaN.
        return 0.5 * q[0] ** 2 * qdot[0] ** 2 - 0.5 * (q[0] - 1.0) ** 2

    q0 = np.array([[1.5], [0.0], [0.8]])
    v0 = np.zeros((3, 1))
    sol = lagrax.simulate_batch(
        L, q0, v0, 0.0, 2.0, solver=TAYLOR, rtol=1e-12, atol=1e-12, throw=False
    )
    ok = np.asarray(sol.result == dfx.RESULTS.successful)
    assert list(ok) == [True, False, True]
    assert np.asarray(sol.result == dfx.RESULTS.nonfinite)[1]
    assert np.isnan(np.asarray(sol.ys[0][1])).all()  # never a number for a failure
    for i in (0, 2):
        ref = lagrax.simulate(
            L, q0[i], v0[i], 0.0, 2.0, solver=dfx.Dopri8(), rtol=1e-13, atol=1e-13
        )
        np.testing.assert_allclose(sol.ys[0][i, -1], ref.ys[0][-1], atol=1e-10)
    with pytest.raises(RuntimeError, match="1 of 3 releases failed"):
        lagrax.simulate_batch(L, q0, v0, 0.0, 2.0, solver=TAYLOR)


def test_max_steps_per_release():
    q0, v0 = np.array([[1.0], [1.0]]), np.zeros((2, 1))
    sol = lagrax.simulate_batch(
        oscillator,
        q0,
        v0,
        0.0,
        np.array([0.1, 50.0]),
        solver=TAYLOR,
        max_steps=8,
        throw=False,
    )
    assert np.asarray(sol.result == dfx.RESULTS.successful)[0]
    assert np.asarray(sol.result == dfx.RESULTS.max_steps_reached)[1]


def spring(k):
    return lambda q, qdot, t: 0.5 * jnp.sum(qdot**2) - 0.5 * k * jnp.sum(q**2)


def test_other_solvers_run_vmap_of_simulate():
    q0, v0 = np.array([[1.0], [0.5]]), np.zeros((2, 1))
    run = lambda q0, t1, k=1.0: lagrax.simulate_batch(
        spring(k), q0, v0, 0.0, t1, solver=dfx.Tsit5(), rtol=1e-10, atol=1e-10
    )
    sol = run(q0, 1.0)
    q, _ = exact(q0, v0, 1.0)
    np.testing.assert_allclose(sol.ys[0][:, -1], q, atol=1e-8)
    # Other releases and span, a rebuilt L with another stiffness (x'' = -4x): the
    # program compiled for the first call, no compile.
    q1 = np.array([[0.25], [-2.0]])
    with counting_compiles() as compiles:
        again = jax.block_until_ready(run(q1, 0.75, k=4.0))
        assert compiles() == 0
    np.testing.assert_allclose(again.ys[0][:, -1], q1 * np.cos(1.5), atol=1e-8)
    # Staged into a caller's `jit`: that program compiles the solve, same numbers.
    staged = jax.jit(lambda q: run(q, 1.0).ys[0][:, -1])(jnp.asarray(q0))
    np.testing.assert_allclose(staged, sol.ys[0][:, -1], rtol=1e-12, atol=1e-14)


def test_taylor_steps_with_its_fallback_where_it_has_no_recurrence():
    # asinh has no Taylor recurrence: Taylor() names it, Taylor(fallback=...) is the
    # fallback's batch, as in `simulate`.
    L = lambda q, qd, t: 0.5 * jnp.sum(qd**2) - jnp.sum(jnp.arcsinh(q) ** 2)
    q0, v0 = np.array([[0.5], [-1.0], [2.0]]), np.zeros((3, 1))
    kw = dict(rtol=1e-10, atol=1e-10)
    with pytest.raises(NotImplementedError, match="asinh"):
        lagrax.simulate_batch(L, q0, v0, 0.0, 2.0, solver=lagrax.Taylor(), **kw)
    taylor = lagrax.Taylor(fallback=dfx.Tsit5())
    want = lagrax.simulate_batch(L, q0, v0, 0.0, 2.0, solver=dfx.Tsit5(), **kw)
    got = lagrax.simulate_batch(L, q0, v0, 0.0, 2.0, solver=taylor, **kw)
    assert np.all(np.asarray(got.result == dfx.RESULTS.successful))
    np.testing.assert_array_equal(got.ys[0], want.ys[0])
    np.testing.assert_array_equal(got.ys[1], want.ys[1])
    # A Lagrangian Taylor steps is unchanged by the fallback.
    plain = lagrax.simulate_batch(oscillator, q0, v0, 0.0, 2.0, **kw)
    same = lagrax.simulate_batch(oscillator, q0, v0, 0.0, 2.0, solver=taylor, **kw)
    np.testing.assert_array_equal(same.ys[0], plain.ys[0])


def test_bad_shapes():
    with pytest.raises(ValueError, match=r"shape \(B, n\)"):
        lagrax.simulate_batch(oscillator, np.zeros(3), np.zeros(3), 0.0, 1.0)
    with pytest.raises(ValueError, match="`t1` must be a scalar or of shape"):
        lagrax.simulate_batch(
            oscillator, np.zeros((3, 1)), np.zeros((3, 1)), 0.0, np.ones(2)
        )


def test_step_length_exp2():
    # The trajectory step's 2^x (multiply-adds and exponent bits) against jnp.exp2:
    # a few digits suffice for a step length; the limits are exp2's.
    from lagrax._trajectory.batch import _exp2

    x = jnp.linspace(-1021.5, 1023.5, 100_001, dtype=jnp.float64)
    np.testing.assert_allclose(_exp2(x), jnp.exp2(x), rtol=1e-6)
    edge = jnp.array([jnp.inf, -jnp.inf, jnp.nan, 1025.0, -1100.0, 0.0])
    np.testing.assert_array_equal(
        _exp2(edge), [jnp.inf, 0.0, jnp.nan, jnp.inf, 0.0, 1.0]
    )
    # In float32 (its own exponent bits, no float64 in a float32 loop).
    x32 = jnp.linspace(-125.5, 127.5, 10_001, dtype=jnp.float32)
    assert _exp2(x32).dtype == jnp.float32
    np.testing.assert_allclose(_exp2(x32), jnp.exp2(x32), rtol=1e-5)
    np.testing.assert_array_equal(
        _exp2(edge.astype(jnp.float32)), [jnp.inf, 0.0, jnp.nan, jnp.inf, 0.0, 1.0]
    )


# (A float64 value stored into the float32 lane parameters warns, and will raise in a
# later JAX.)
@pytest.mark.filterwarnings("error::FutureWarning")
def test_float32_releases():
    # float32 releases stay float32 through the loop and meet a float32 tolerance.
    q0 = jnp.linspace(0.1, 1.0, 5, dtype=jnp.float32)[:, None]
    sol = lagrax.simulate_batch(
        oscillator,
        q0,
        jnp.zeros_like(q0),
        0.0,
        2.0,
        solver=TAYLOR,
        rtol=1e-5,
        atol=1e-5,
    )
    q, v = sol.ys
    assert q.dtype == jnp.float32
    assert np.all(sol.result == dfx.RESULTS.successful)
    q_ex, v_ex = exact(np.asarray(q0, np.float64), 0.0, 2.0)
    np.testing.assert_allclose(q[:, -1], q_ex, atol=1e-4)


def test_long_integration_keeps_its_time_exact():
    # ~3000 steps: a time rounded once per step drifts by ~sqrt(steps) ulps of
    # t = 300, a phase error of ~4e-13 here; kept as a two-float sum, ~2e-15.
    q0 = np.array([[1.0], [0.6]])
    v0 = np.zeros((2, 1))
    t1 = np.array([300.0, -300.0])
    sol = lagrax.simulate_batch(
        oscillator, q0, v0, 0.0, t1, solver=TAYLOR, rtol=1e-16, atol=1e-16
    )
    q, v = exact(q0, v0, t1[:, None])
    assert np.asarray(sol.stats["num_steps"]).min() > 2000
    np.testing.assert_allclose(sol.ys[0][:, -1], q, rtol=0, atol=2e-14)
    np.testing.assert_allclose(sol.ys[1][:, -1], v, rtol=0, atol=2e-14)


def _double_pendulum(g):
    def L(q, qdot, t):
        t1, t2, w1, w2 = q[0], q[1], qdot[0], qdot[1]
        T = w1**2 + 0.5 * w2**2 + w1 * w2 * jnp.cos(t1 - t2)
        return T + 2 * g * jnp.cos(t1) + g * jnp.cos(t2)

    return L


def test_compact_tier_equals_the_specialized_program(monkeypatch):
    """The compact tier (one program per size class, the equations as data) gives
    the specialized program's states to rounding; a rebuilt L with another
    parameter value runs through the same executable."""
    from lagrax._cache import executables

    q0 = np.random.default_rng(1).uniform(-1, 1, (5, 2))
    run = lambda g: lagrax.simulate_batch(
        _double_pendulum(g), q0, np.zeros_like(q0), 0.0, 2.0, solver=TAYLOR,
        rtol=1e-12, atol=1e-12, lanes=4,
    )  # fmt: skip
    states = lambda sol: np.concatenate([sol.ys[0][:, -1], sol.ys[1][:, -1]], 1)
    monkeypatch.setenv("LAGRAX_COMPACT", "0")
    ref = {g: states(run(g)) for g in (9.81, 3.0)}
    monkeypatch.setenv("LAGRAX_COMPACT", "2")
    np.testing.assert_allclose(states(run(9.81)), ref[9.81], rtol=0, atol=1e-12)
    loaded = len(executables._LOADED)
    np.testing.assert_allclose(states(run(3.0)), ref[3.0], rtol=0, atol=1e-12)
    assert len(executables._LOADED) == loaded


def _two_oscillators():
    q0 = np.array([[0.5, -0.2], [0.1, 0.3]])
    return lagrax.simulate_batch(
        oscillator, q0, np.zeros_like(q0), 0.0, 1.0, solver=TAYLOR, rtol=1e-10,
        atol=1e-10,
    )  # fmt: skip


def test_tiers_compact_first_then_specialized(monkeypatch):
    """A Lagrangian whose specialized program compiles for long runs on the compact
    program first, and on the specialized one once the time spent on the compact
    one reaches that compile (saying so once); a short compile goes straight to
    the specialized program."""
    import collections

    from lagrax._trajectory import batch

    calls = []
    monkeypatch.setattr(
        batch, "cached_call", lambda *a, **k: calls.append(1) or real(*a, **k)
    )
    real = lagrax._cache.executables.cached_call
    monkeypatch.setattr(batch, "_SPENT", collections.Counter())
    monkeypatch.setattr(batch, "_NOTIFIED", set())
    monkeypatch.setenv("LAGRAX_COMPACT", "1")
    run = _two_oscillators
    monkeypatch.setattr(batch, "_compile_estimate", lambda nodes, order: 1e3)
    first = run()
    assert not calls and sum(batch._SPENT.values()) > 0
    (cfg,) = batch._SPENT
    batch._SPENT[cfg] = 1e3
    with pytest.warns(UserWarning, match="specialized"):
        second = run()
    assert calls == [1]
    np.testing.assert_allclose(second.ys[0], first.ys[0], rtol=0, atol=1e-12)
    monkeypatch.setattr(batch, "_compile_estimate", lambda nodes, order: 1.0)
    batch._SPENT.clear()
    run()
    assert calls == [1, 1]


def test_tiers_stay_compact_where_the_specialized_step_would_loop(monkeypatch):
    """Beyond the unroll budget the specialized step loops over the orders and runs
    slower than the compact program: however long a Lagrangian has run on the
    compact tier, it stays there, and no compile is started for later."""
    import collections

    from lagrax._trajectory import batch

    calls, later = [], []
    real = lagrax._cache.executables.cached_call
    monkeypatch.setattr(
        batch, "cached_call", lambda *a, **k: calls.append(1) or real(*a, **k)
    )
    monkeypatch.setattr(
        batch.executables, "compile_later", lambda *a, **k: later.append(1)
    )
    monkeypatch.setattr(batch, "_SPENT", collections.Counter())
    monkeypatch.setattr(batch, "_NOTIFIED", set())
    monkeypatch.setenv("LAGRAX_COMPACT", "1")
    monkeypatch.setattr(batch, "_compile_estimate", lambda nodes, order: 1e3)
    monkeypatch.setattr(batch, "_UNROLL_BUDGET", 0)
    first = _two_oscillators()
    (cfg,) = batch._SPENT
    batch._SPENT[cfg] = 1e4
    second = _two_oscillators()
    assert not calls and not later
    np.testing.assert_array_equal(second.ys[0], first.ys[0])
    # Within the budget, the same call goes to the specialized program.
    monkeypatch.setattr(batch, "_UNROLL_BUDGET", 10**9)
    with pytest.warns(UserWarning, match="specialized"):
        _two_oscillators()
    assert calls == [1]


def test_the_tiers_count_the_specialized_steps_own_nodes(monkeypatch):
    """The tier rule's count of the specialized step's nodes is the step's own (L's
    constants reach that program as arguments, which it keeps as nodes: more than
    the compact tape's program, whose constants fold)."""
    from lagrax._jaxpr.canonical import canonical_lagrangian
    from lagrax._trajectory import batch

    seen = []
    real = batch.SystemTaylorStepper.coefficients

    def spy(self, *args):
        seen.append(len(self.system.prog.nodes))
        return real(self, *args)

    monkeypatch.setattr(batch.SystemTaylorStepper, "coefficients", spy)
    monkeypatch.setenv("LAGRAX_COMPACT", "0")
    L = _double_pendulum(9.81)
    L_c, consts = canonical_lagrangian(L, jnp.float64, 2)
    _, nodes = batch._tape(L_c, consts, None, 2, jnp.float64)
    step_nodes = batch._step_nodes(L_c, consts, None, 2, jnp.float64)
    q0 = jnp.zeros((3, 2))
    jax.make_jaxpr(
        lambda q: lagrax.simulate_batch(L, q, q, 0.0, 0.1, solver=TAYLOR).ys
    )(q0)
    assert seen and set(seen) == {step_nodes} and step_nodes > nodes


def test_tiers_compile_the_specialized_program_later(monkeypatch, executable_cache):
    """Where a core is idle, from the second call of a Lagrangian on the compact
    tier, its specialized program compiles in a worker process; the compact tier
    runs the calls meanwhile (no ski rental), and the specialized program takes
    over once on disk."""
    import collections

    from lagrax._cache import executables
    from lagrax._trajectory import batch

    folder, loads, _ = executable_cache
    calls = []
    real = executables.cached_call
    monkeypatch.setattr(
        batch, "cached_call", lambda *a, **k: calls.append(1) or real(*a, **k)
    )
    monkeypatch.setattr(batch, "_SPENT", collections.Counter())
    monkeypatch.setattr(executables, "_LATER", {})
    monkeypatch.setattr(executables, "_LOADED", {})  # (as in a new process)
    monkeypatch.setattr(executables, "_usable_cores", lambda: 2)
    monkeypatch.setenv("LAGRAX_BACKGROUND", "1")
    monkeypatch.setattr(batch, "_compile_estimate", lambda nodes, order: 1e-3)
    monkeypatch.setattr(batch, "_COMPACT_FROM", 0.0)
    monkeypatch.setenv("LAGRAX_COMPACT", "1")
    run = _two_oscillators
    first = run()  # (the compact program compiled and written: the tier's first)
    assert not calls and executables._LATER == {}
    # Compiled apart with its loops each one function (`executables.program`).
    (entry,) = folder.glob("*.bin")
    text = executables._LOADED[entry.stem][0].as_text()
    whole, loops = text.count('xla_cpu_small_call="true"'), text.count(" while(")
    assert whole == loops > 1, (whole, loops)
    run()  # (the spent time is past the estimate: the job, not the rental)
    ((job),) = executables._LATER.values()
    assert not calls and job.state in ("running", "done")
    job.thread.join(timeout=300)
    assert job.state == "done"
    third = run()
    assert calls == [1] and loads[-1] is True
    np.testing.assert_allclose(third.ys[0], first.ys[0], rtol=0, atol=1e-12)
