"""A tolerance means at least what it means for diffrax's Dopri8: at the same rtol and
atol, `lagrax.Taylor` (`simulate_batch`'s default solver, and as a diffrax solver)
ends no farther from the exact solution than Dopri8 does."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

import lagrax


E = 0.9  # Kepler: eccentricity (semi-major axis 1, GM 1, period 2 pi)


def kepler(q, qdot, t):
    return 0.5 * jnp.sum(qdot**2) + 1.0 / jnp.sqrt(jnp.sum(q**2))


def _kepler_state(M):
    E_ = np.array(M, dtype=float)
    for _ in range(60):  # Kepler's equation M = E - e sin E, by Newton
        E_ = E_ - (E_ - E * np.sin(E_) - M) / (1 - E * np.cos(E_))
    rate = 1.0 / (1 - E * np.cos(E_))
    q = np.stack([np.cos(E_) - E, np.sqrt(1 - E**2) * np.sin(E_)], axis=-1)
    v = np.stack([-np.sin(E_) * rate, np.sqrt(1 - E**2) * np.cos(E_) * rate], axis=-1)
    return q, v


def kepler_case(count, t1):
    """Releases at `count` mean anomalies, and their exact states at `t1`."""
    M = 2 * np.pi * np.arange(count) / count
    q0, v0 = _kepler_state(M)
    q1, v1 = _kepler_state(M + t1)
    return q0, v0, np.concatenate([q1, v1], axis=1)


def pendulum(q, qdot, t):
    return 0.5 * qdot[0] ** 2 + jnp.cos(q[0])


def pendulum_case(count, t1):
    r"""Releases from rest at large amplitudes, and their exact states at `t1`:
    $\sin(\theta/2) = k\,\mathrm{sn}(K - t, k)$, $\dot\theta = -2k\,\mathrm{cn}(K - t,
    k)$, $k = \sin(\theta_0/2)$."""
    theta0 = np.linspace(2.5, 3.0, count)
    k = np.sin(theta0 / 2)
    m = k**2
    sn, cn, _, _ = scipy.special.ellipj(scipy.special.ellipk(m) - t1, m)
    end = np.stack([2 * np.arcsin(k * sn), -2 * k * cn], axis=1)
    return theta0[:, None], np.zeros((count, 1)), end


CASES = {"kepler": (kepler, kepler_case), "pendulum": (pendulum, pendulum_case)}


def _errors(sol, end):
    ys = np.concatenate([np.asarray(sol.ys[0][:, -1]), np.asarray(sol.ys[1][:, -1])], 1)
    return np.max(np.abs(ys - end))


@pytest.mark.parametrize("name", sorted(CASES))
def test_simulate_batch_no_less_accurate_than_dopri8(name):
    L, case = CASES[name]
    q0, v0, end = case(8, 10.0)
    tol = 1e-10
    run = lambda solver: lagrax.simulate_batch(
        L, q0, v0, 0.0, 10.0, solver=solver, rtol=tol, atol=tol, max_steps=1 << 14
    )
    taylor = _errors(run(None), end)  # (its default solver, lagrax.Taylor())
    dopri8 = _errors(run(dfx.Dopri8()), end)
    assert np.isfinite(taylor) and taylor <= dopri8, (taylor, dopri8)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.parametrize("tol", [1e-8, 1e-12])
def test_taylor_as_a_diffrax_solver_no_less_accurate_than_dopri8(name, tol):
    L, case = CASES[name]
    q0, v0, end = case(8, 10.0)

    def errors(solver, options=None):
        def one(q, v):
            sol = lagrax.simulate(
                L, q, v, 0.0, 10.0, solver=solver, rtol=tol, atol=tol,
                max_steps=1 << 14,
            )  # fmt: skip
            return jnp.concatenate([sol.ys[0][-1], sol.ys[1][-1]])

        ys = jax.jit(jax.vmap(one), compiler_options=options)(q0, v0)
        return np.max(np.abs(np.asarray(ys) - end))

    elemental = {"xla_cpu_use_fusion_emitters": False}
    taylor = errors(lagrax.Taylor(order=12), elemental)
    dopri8 = errors(dfx.Dopri8())
    assert np.isfinite(taylor) and taylor <= dopri8, (taylor, dopri8)
    batch = lagrax.simulate_batch(L, q0, v0, 0.0, 10.0, rtol=tol, atol=tol)
    assert _errors(batch, end) <= dopri8
