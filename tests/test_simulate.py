"""Trajectories: invariants, the cycloid reduction, batching, failure reports."""

import subprocess
import sys

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax.systems import cycloid, pendulum


def test_energy_conserved_pendulum():
    L = pendulum.lagrangian(m=1.2, r=0.8, g=9.81)
    ts = jnp.linspace(0, 30, 301)
    sol = lagrax.simulate(
        L,
        jnp.array([2.5]),
        jnp.array([0.0]),
        0.0,
        30.0,
        solver=dfx.Dopri8(),
        rtol=1e-11,
        atol=1e-11,
        saveat=dfx.SaveAt(ts=ts),
    )
    qs, qdots = sol.ys
    h = jax.jit(jax.vmap(lambda q, v: lagrax.energy(L, q, v, 0.0)))(qs, qdots)
    assert np.max(np.abs(h - h[0])) / abs(h[0]) < 1e-9
    # and the swing really is large: it reaches the other side.
    assert np.min(qs) < -2.4


# A configuration-dependent mass matrix's energy is checked every time in
# tests/test_properties.py.
@pytest.mark.slow
def test_energy_conserved_double_pendulum_like_coupled_system():
    # Two coupled coordinates with a configuration-dependent mass matrix.
    def L(q, qdot, t):
        c = jnp.cos(q[0] - q[1])
        T = qdot[0] ** 2 + 0.5 * qdot[1] ** 2 + qdot[0] * qdot[1] * c
        V = -2 * jnp.cos(q[0]) - jnp.cos(q[1])
        return T - V

    ts = jnp.linspace(0, 10, 101)
    sol = lagrax.simulate(
        L,
        jnp.array([1.0, -0.5]),
        jnp.array([0.0, 0.3]),
        0.0,
        10.0,
        rtol=1e-10,
        atol=1e-10,
        saveat=dfx.SaveAt(ts=ts),
    )
    h = jax.jit(jax.vmap(lambda q, v: lagrax.energy(L, q, v, 0.0)))(*sol.ys)
    assert np.max(np.abs(h - h[0])) < 1e-8


def test_cycloid_reduction_along_trajectory():
    # u = cos(θ/2) obeys ü = −(g/4R) u: the classical change of variable, checked on a
    # trajectory computed in θ (which stays away from the cusp for θ0 = 1.0).
    R, g = 0.6, 9.81
    L = cycloid.lagrangian(R=R, g=g)
    ts = jnp.linspace(0, 5, 201)
    theta0 = 1.0
    sol = lagrax.simulate(
        L,
        jnp.array([theta0]),
        jnp.array([0.0]),
        0.0,
        5.0,
        solver=dfx.Dopri8(),
        rtol=1e-12,
        atol=1e-12,
        saveat=dfx.SaveAt(ts=ts),
    )
    theta, thetadot = sol.ys[0][:, 0], sol.ys[1][:, 0]
    thetaddot = jax.jit(
        jax.vmap(lambda a, b: lagrax.accelerations(L, a[None], b[None])[0])
    )(theta, thetadot)
    u = jnp.cos(theta / 2)
    uddot = -0.25 * jnp.cos(theta / 2) * thetadot**2 - 0.5 * jnp.sin(theta / 2) * (
        thetaddot
    )
    np.testing.assert_allclose(uddot, -(g / (4 * R)) * u, atol=1e-11)
    # and u(t) is the harmonic oscillation u0 cos(ωt), ω = √(g/4R), at every saved time.
    omega = np.sqrt(g / (4 * R))
    np.testing.assert_allclose(u, np.cos(theta0 / 2) * np.cos(omega * ts), atol=1e-9)


def test_vmap_jit_equal_loop():
    L = pendulum.lagrangian(g=9.81)
    q0s = jnp.linspace(0.1, 3.0, 6)[:, None]

    def run(q0):
        return lagrax.simulate(L, q0, jnp.zeros(1), 0.0, 3.0, rtol=1e-9, atol=1e-9)

    batched = jax.jit(jax.vmap(run))(q0s)
    for i, q0 in enumerate(q0s):
        single = run(q0)
        np.testing.assert_allclose(batched.ys[0][i], single.ys[0], rtol=1e-12)


def test_no_recompile_when_numbers_change():
    traces = []

    def L(q, qdot, t):
        traces.append(None)  # runs only while tracing
        return 0.5 * qdot[0] ** 2 + jnp.cos(q[0])

    @jax.jit
    def run(q0, t1, rtol):
        return lagrax.simulate(L, q0, jnp.zeros(1), 0.0, t1, rtol=rtol, atol=rtol).ys

    run(jnp.array([0.5]), 2.0, 1e-8)
    n = len(traces)
    assert n > 0
    run(jnp.array([1.5]), 3.0, 1e-10)
    run(jnp.array([2.5]), 7.0, 1e-6)
    assert len(traces) == n


def test_backward_in_time_returns():
    L = pendulum.lagrangian(g=9.81)
    q0, v0 = jnp.array([1.2]), jnp.array([0.3])
    fwd = lagrax.simulate(L, q0, v0, 0.0, 4.0, rtol=1e-12, atol=1e-12)
    q1, v1 = fwd.ys[0][-1], fwd.ys[1][-1]
    back = lagrax.simulate(L, q1, v1, 4.0, 0.0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(back.ys[0][-1], q0, atol=1e-9)
    np.testing.assert_allclose(back.ys[1][-1], v0, atol=1e-9)


def _shrinking_mass(c):
    # M = 1 − c t: singular at t = 1/c, indefinite after.
    return lambda q, qdot, t: 0.5 * (1 - c * t) * qdot[0] ** 2 - 0.5 * q[0] ** 2


def test_singular_lane_fails_others_untouched():
    cs = jnp.array([0.0, 1.0, 0.1])

    def run(c):
        return lagrax.simulate(
            _shrinking_mass(c), jnp.array([1.0]), jnp.zeros(1), 0.0, 2.0, throw=False
        )

    sol = jax.jit(jax.vmap(run))(cs)
    ok = np.asarray(sol.result == dfx.RESULTS.successful)
    assert ok.tolist() == [True, False, True]
    assert bool((sol.result == dfx.RESULTS.dt_min_reached)[1])
    # the failing lane stopped quickly instead of burning max_steps
    assert sol.stats["num_steps"][1] < 1000
    alone = jax.jit(run)(cs[0])
    np.testing.assert_array_equal(sol.ys[0][0], alone.ys[0])


def test_fixed_step_nonfinite_is_reported():
    sol = lagrax.simulate(
        _shrinking_mass(1.0),
        jnp.array([1.0]),
        jnp.zeros(1),
        0.0,
        2.0,
        solver=dfx.Euler(),
        dt0=0.01,
        throw=False,
    )
    assert sol.result == dfx.RESULTS.nonfinite


def test_throw_eager_raises_clear_error():
    with pytest.raises(RuntimeError, match="minimum step size"):
        lagrax.simulate(_shrinking_mass(1.0), jnp.array([1.0]), jnp.zeros(1), 0.0, 2.0)


def test_max_steps_reported():
    sol = lagrax.simulate(
        pendulum.lagrangian(),
        jnp.array([1.0]),
        jnp.zeros(1),
        0.0,
        100.0,
        max_steps=5,
        throw=False,
    )
    assert sol.result == dfx.RESULTS.max_steps_reached


def test_library_leaves_x64_alone():
    code = "import jax, lagrax; print(jax.config.jax_enable_x64)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "False"


def test_taylor_steps_with_its_fallback_where_it_has_no_recurrence():
    # asinh has no Taylor recurrence: Taylor() names it, Taylor(fallback=...) is the
    # fallback's solve, eager and under jit.
    L = lambda q, qd, t: 0.5 * qd[0] ** 2 - jnp.arcsinh(q[0]) ** 2
    q0, v0 = jnp.array([0.5]), jnp.array([0.0])
    kw = dict(rtol=1e-10, atol=1e-10)
    with pytest.raises(NotImplementedError, match="asinh"):
        lagrax.simulate(L, q0, v0, 0.0, 2.0, solver=lagrax.Taylor(), **kw)
    taylor = lagrax.Taylor(fallback=dfx.Dopri8())
    want = lagrax.simulate(L, q0, v0, 0.0, 2.0, solver=dfx.Dopri8(), **kw).ys[0]
    got = lagrax.simulate(L, q0, v0, 0.0, 2.0, solver=taylor, **kw).ys[0]
    np.testing.assert_array_equal(got, want)
    f = jax.jit(
        lambda q: lagrax.simulate(L, q, v0, 0.0, 2.0, solver=taylor, **kw).ys[0]
    )
    np.testing.assert_allclose(f(q0), want, rtol=1e-14)
