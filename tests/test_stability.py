"""Where methods fail: each failure is reported, and each cure works."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax.systems import cycloid, pendulum


def elastic_lagrangian(k):
    def L(q, qdot, t):
        r, theta = q
        kinetic = 0.5 * (qdot[0] ** 2 + r**2 * qdot[1] ** 2)
        return kinetic - 0.5 * k * (r - 1.0) ** 2 + r * jnp.cos(theta)

    return L


K = 1e8
STIFF = elastic_lagrangian(K)
STIFF_Y0 = (jnp.array([1.0 + np.cos(1.0) / K, 1.0]), jnp.array([0.0, 0.0]))


def test_stiff_spring_explicit_solver_reports_max_steps():
    sol = lagrax.simulate(
        STIFF, *STIFF_Y0, 0.0, 2.0, rtol=1e-6, atol=1e-6, max_steps=256, throw=False
    )
    assert sol.result == dfx.RESULTS.max_steps_reached
    assert int(sol.stats["num_steps"]) == 256  # stopped there: no hang
    with pytest.raises(RuntimeError, match="max_steps|maximum number"):
        lagrax.simulate(STIFF, *STIFF_Y0, 0.0, 2.0, rtol=1e-6, atol=1e-6, max_steps=256)


def _energy_error(L, sol, y0):
    E0 = lagrax.energy(L, *y0)
    qs, qdots = sol.ys
    E = jax.vmap(lambda q, v: lagrax.energy(L, q, v, 0.0))(qs, qdots)
    return float(jnp.max(jnp.abs(E - E0)))


def test_stiff_spring_cured_by_variational_step():
    # h = 0.01 steps over the spring's period 2π/1e4 ~ 6e-4 by a factor 16: explicit
    # RK is unstable there, the midpoint variational step is not.
    h, nsteps = 0.01, 200
    sol = dfx.diffeqsolve(
        lagrax.LagrangianTerm(STIFF),
        lagrax.VariationalMidpoint(),
        0.0,
        h * nsteps,
        h,
        STIFF_Y0,
        saveat=dfx.SaveAt(steps=True),
        stepsize_controller=dfx.ConstantStepSize(),
        max_steps=nsteps,
    )
    assert sol.result == dfx.RESULTS.successful
    assert _energy_error(STIFF, sol, STIFF_Y0) < 1e-4
    # ... and the pendulum angle is right: against the rigid pendulum (the spring
    # stretches by ~1e-8), integrated accurately.
    rigid = lagrax.simulate(
        pendulum.lagrangian(),
        STIFF_Y0[0][1:],
        STIFF_Y0[1][1:],
        0.0,
        h * nsteps,
        rtol=1e-10,
        atol=1e-10,
    )
    assert abs(float(sol.ys[0][-1, 1] - rigid.ys[0][-1, 0])) < 1e-3


@pytest.mark.slow
def test_stiff_spring_cured_by_implicit_solver():
    sol = lagrax.simulate(
        STIFF,
        *STIFF_Y0,
        0.0,
        2.0,
        solver=dfx.Kvaerno5(),
        rtol=1e-6,
        atol=1e-6,
        max_steps=256,
        throw=False,
    )
    assert sol.result == dfx.RESULTS.successful


def on_one_arch(theta):
    theta = np.asarray(theta)
    return bool(np.all(np.isfinite(theta) & (theta >= 0) & (theta <= 2 * np.pi)))


# The cusp as a status and the u-form regular at it run every time in
# tests/test_period.py and tests/test_transform.py.
@pytest.mark.slow
def test_cycloid_near_cusp_failure_is_detected_and_u_form_cures_it():
    t1 = 4 * np.pi  # one period for every amplitude: exact final state = start
    ts = jnp.linspace(0.0, t1, 101)
    theta0 = 1e-8
    sol = lagrax.simulate(
        cycloid.lagrangian(),
        jnp.array([theta0]),
        jnp.array([0.0]),
        0.0,
        t1,
        rtol=1e-10,
        atol=1e-10,
        saveat=dfx.SaveAt(ts=ts),
        max_steps=20_000,
        throw=False,
    )
    theta = np.asarray(sol.ys[0][:, 0])
    # Either the solver reports the failure, or the physics does: the bob left the
    # arch (through the far cusp), which no solution of this Lagrangian does.
    failed = sol.result != dfx.RESULTS.successful
    assert failed or not on_one_arch(theta), (dfx.RESULTS[sol.result], theta[-1])

    # Released at the cusp itself, an eager call refuses the singular start.
    with pytest.raises(ValueError, match="singular"):
        lagrax.simulate(
            cycloid.lagrangian(), jnp.array([0.0]), jnp.array([0.0]), 0.0, 1
        )

    # The cure: u = cos(θ/2), a harmonic oscillator with u(t) = u0 cos(t/2).
    u0 = np.cos(theta0 / 2)
    sol_u = lagrax.simulate(
        cycloid.lagrangian_u(),
        jnp.array([u0]),
        jnp.array([0.0]),
        0.0,
        t1,
        rtol=1e-10,
        atol=1e-10,
        saveat=dfx.SaveAt(ts=ts),
    )
    assert sol_u.result == dfx.RESULTS.successful
    u = np.asarray(sol_u.ys[0][:, 0])
    np.testing.assert_allclose(u, u0 * np.cos(np.asarray(ts) / 2), rtol=0, atol=1e-8)
    assert on_one_arch(cycloid.theta_from_u(jnp.asarray(u)))


def test_cycloid_away_from_cusp_theta_form_is_fine():
    # The check above is not trigger-happy: an ordinary release passes it.
    t1 = 4 * np.pi
    theta0 = 0.5
    sol = lagrax.simulate(
        cycloid.lagrangian(),
        jnp.array([theta0]),
        jnp.array([0.0]),
        0.0,
        t1,
        rtol=1e-10,
        atol=1e-10,
        saveat=dfx.SaveAt(ts=jnp.linspace(0.0, t1, 101)),
    )
    assert on_one_arch(sol.ys[0][:, 0])
    assert abs(float(sol.ys[0][-1, 0]) - theta0) < 1e-6


def _pendulum_period_error(dtype, tol):
    T = float(pendulum.period(2.5))
    sol = lagrax.simulate(
        pendulum.lagrangian(),
        jnp.array([2.5], dtype),
        jnp.array([0.0], dtype),
        jnp.asarray(0.0, dtype),
        jnp.asarray(T, dtype),
        rtol=tol,
        atol=tol,
        max_steps=20_000,
    )
    assert sol.ys[0].dtype == dtype  # no silent upcast
    return max(abs(float(sol.ys[0][-1, 0]) - 2.5), abs(float(sol.ys[1][-1, 0])))


def test_float32_stops_improving_where_float64_goes_on():
    with pytest.warns(UserWarning, match="machine epsilon"):
        err32_tight = _pendulum_period_error(jnp.float32, 1e-10)
    err32_loose = _pendulum_period_error(jnp.float32, 1e-6)
    err64_tight = _pendulum_period_error(jnp.float64, 1e-10)
    eps32 = float(np.finfo(np.float32).eps)
    # float32 cannot resolve the state below ~eps32 * |q|: asking 1e-10 buys nothing.
    assert err32_tight > eps32
    assert err32_tight > 0.1 * err32_loose
    # float64 keeps going.
    assert err64_tight < 1e-8
    assert err64_tight < 1e-2 * err32_tight
