"""Property-based tests (hypothesis): invariants that must hold for random systems.

Each random system is drawn from a seed by numpy (matrices of a given size); the
simulations are jitted with the system's matrices as arguments, so examples of the same
size share one compiled program.
"""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import lagrax


seeds = st.integers(min_value=0, max_value=2**32 - 1)


def _spd(rng, n, shift=1.0):
    A = rng.standard_normal((n, n))
    return A @ A.T / n + shift * np.eye(n)


def _quadratic(M, G, K):
    r"""$L = \frac12\dot q^\top M\dot q + \dot q^\top G q - \frac12 q^\top K q$."""

    def L(q, qdot, t):
        return 0.5 * qdot @ M @ qdot + qdot @ G @ q - 0.5 * q @ K @ q

    return L


@jax.jit
def _quadratic_accelerations(M, G, K, q, qdot):
    return lagrax.accelerations(_quadratic(M, G, K), q, qdot)


@given(n=st.integers(1, 6), seed=seeds)
def test_accelerations_of_quadratic_lagrangians(n, seed):
    # By hand: p = M qdot + G q, so d/dt p = M qddot + G qdot; dL/dq = G^T qdot - K q.
    # Lagrange: M qddot = (G^T - G) qdot - K q (only the antisymmetric, gyroscopic,
    # part of G acts; its symmetric part is the total derivative of q^T G_s q / 2).
    rng = np.random.default_rng(seed)
    M = _spd(rng, n)
    G = rng.standard_normal((n, n))
    K = rng.standard_normal((n, n))
    K = K + K.T
    q = rng.standard_normal(n)
    qdot = rng.standard_normal(n)
    expected = np.linalg.solve(M, (G.T - G) @ qdot - K @ q)
    got = _quadratic_accelerations(*map(jnp.asarray, (M, G, K, q, qdot)))
    scale = np.abs(expected).max() + 1.0
    np.testing.assert_allclose(got, expected, rtol=1e-11, atol=1e-11 * scale)


@jax.jit
def _covariance_pair(M, G, K, A, B, eps, u0, udot0, ts):
    L = _quadratic(M, G, K)

    def phi(u, t):
        return A @ u + eps * jnp.tanh(B @ u)

    q0, qdot0 = jax.jvp(lambda u: phi(u, 0.0), (u0,), (udot0,))
    kwargs = dict(saveat=dfx.SaveAt(ts=ts), rtol=1e-11, atol=1e-11, solver=dfx.Tsit5())
    sol_q = lagrax.simulate(L, q0, qdot0, ts[0], ts[-1], **kwargs)
    sol_u = lagrax.simulate(
        lagrax.reparametrize(L, phi), u0, udot0, ts[0], ts[-1], **kwargs
    )
    return sol_q.ys[0], jax.vmap(lambda u: phi(u, 0.0))(sol_u.ys[0])


@settings(max_examples=10)
@given(n=st.sampled_from([1, 3]), seed=seeds)
def test_covariance_under_point_transformations(n, seed):
    # Simulating L' = reparametrize(L, phi) and mapping back through phi gives the
    # trajectory of L, for a random invertible phi(u) = A u + eps tanh(B u): A well
    # conditioned, eps small enough that dphi/du = A + eps diag(sech^2) B stays
    # invertible (|eps B| < smallest singular value of A / 2).
    rng = np.random.default_rng(seed)
    M, K = _spd(rng, n), _spd(rng, n)
    G = 0.5 * rng.standard_normal((n, n))
    A = np.eye(n) + 0.3 * rng.standard_normal((n, n)) / np.sqrt(n)
    B = rng.standard_normal((n, n))
    eps = 0.5 * np.linalg.svd(A, compute_uv=False).min() / np.linalg.norm(B, 2)
    u0, udot0 = rng.standard_normal(n), rng.standard_normal(n)
    ts = jnp.linspace(0.0, 3.0, 7)
    qs, mapped = _covariance_pair(
        *map(jnp.asarray, (M, G, K, A, B)),
        jnp.asarray(eps),
        jnp.asarray(u0),
        jnp.asarray(udot0),
        ts,
    )
    np.testing.assert_allclose(mapped, qs, rtol=1e-7, atol=1e-8)


def _nonlinear(M0, K, G, c):
    r"""A conservative system with a cyclic first coordinate:

    $L = \frac12\dot q^\top M(q)\dot q + \dot q^\top G q - V(q)$ with $M = M_0(1 + c\,
    r/(1+r))$, $r = |q_{1:}|^2$, $V = \frac12 q_{1:}^\top K q_{1:} + \frac c4
    \sum q_{1:}^4$, and $G$'s first column zero: nothing depends on $q_0$, so $p_0$ is
    conserved (Noether), and with no explicit time the energy is conserved.
    """

    def L(q, qdot, t):
        rest = q[1:]
        r = rest @ rest
        M = M0 * (1 + c * r / (1 + r))
        V = 0.5 * rest @ K @ rest + 0.25 * c * jnp.sum(rest**4)
        return 0.5 * qdot @ M @ qdot + qdot @ G @ q - V

    return L


@jax.jit
def _invariants(M0, K, G, c, q0, qdot0, ts):
    L = _nonlinear(M0, K, G, c)
    sol = lagrax.simulate(
        L,
        q0,
        qdot0,
        ts[0],
        ts[-1],
        saveat=dfx.SaveAt(ts=ts),
        rtol=1e-11,
        atol=1e-11,
        solver=dfx.Tsit5(),
    )
    qs, qdots = sol.ys
    E = jax.vmap(lambda q, v: lagrax.energy(L, q, v))(qs, qdots)
    p = jax.vmap(lambda q, v: lagrax.momenta(L, q, v))(qs, qdots)
    return E, p[:, 0]


@settings(max_examples=10)
@given(seed=seeds)
def test_energy_and_noether_momentum_conserved(seed):
    rng = np.random.default_rng(seed)
    n = 3
    M0, K = _spd(rng, n), _spd(rng, n - 1)
    G = rng.standard_normal((n, n))
    G[:, 0] = 0.0
    q0, qdot0 = rng.standard_normal(n), rng.standard_normal(n)
    E, p0 = _invariants(
        *map(jnp.asarray, (M0, K, G)),
        jnp.asarray(0.5),
        jnp.asarray(q0),
        jnp.asarray(qdot0),
        jnp.linspace(0.0, 5.0, 11),
    )
    E, p0 = np.asarray(E), np.asarray(p0)
    assert np.ptp(E) <= 1e-8 * (np.abs(E).max() + 1)
    assert np.ptp(p0) <= 1e-8 * (np.abs(p0).max() + 1)


@jax.jit
def _there_and_back(M0, K, c, q0, qdot0, T):
    # G = 0: L is even in qdot, so the motion is time-reversible.
    n = q0.shape[0]
    L = _nonlinear(M0, K, jnp.zeros((n, n)), c)
    kwargs = dict(rtol=1e-11, atol=1e-11, solver=dfx.Tsit5())
    sol = lagrax.simulate(L, q0, qdot0, 0.0, T, **kwargs)
    q1, qdot1 = sol.ys[0][-1], sol.ys[1][-1]
    back = lagrax.simulate(L, q1, -qdot1, 0.0, T, **kwargs)
    return q1, back.ys[0][-1], -back.ys[1][-1]


@settings(max_examples=10)
@given(seed=seeds)
def test_time_reversal(seed):
    # Forward for T, reverse the velocities, forward for T again: back at the start
    # with the velocities reversed (and somewhere else in between).
    rng = np.random.default_rng(seed)
    n = 3
    M0, K = _spd(rng, n), _spd(rng, n - 1)
    q0, qdot0 = rng.standard_normal(n), rng.standard_normal(n)
    q1, q_back, qdot_back = _there_and_back(
        jnp.asarray(M0),
        jnp.asarray(K),
        jnp.asarray(0.5),
        jnp.asarray(q0),
        jnp.asarray(qdot0),
        jnp.asarray(4.0),
    )
    assert not np.allclose(q1, q0, atol=1e-3)
    np.testing.assert_allclose(q_back, q0, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(qdot_back, qdot0, rtol=1e-7, atol=1e-8)


def _final(M0, K, G, q, v):
    L = _nonlinear(M0, K, G, 0.5)
    sol = lagrax.simulate(L, q, v, 0.0, 2.0, rtol=1e-10, atol=1e-10, throw=False)
    return sol.ys[0][-1], sol.stats["num_steps"], lagrax.accelerations(L, q, v)


_final_one = jax.jit(_final)
_final_batch = jax.jit(jax.vmap(_final, in_axes=(None, None, None, 0, 0)))


# simulate batched against a loop runs every time in tests/test_simulate.py.
@pytest.mark.slow
@settings(max_examples=5)
@given(seed=seeds)
def test_vmap_equals_loop(seed):
    # simulate and accelerations: one program batched, and called lane by lane.
    rng = np.random.default_rng(seed)
    n, count = 3, 4
    M0, K = _spd(rng, n), _spd(rng, n - 1)
    G = rng.standard_normal((n, n))
    G[:, 0] = 0.0
    system = tuple(map(jnp.asarray, (M0, K, G)))
    qs = jnp.asarray(rng.standard_normal((count, n)))
    qdots = jnp.asarray(rng.standard_normal((count, n)))
    q_end, steps, qddot = _final_batch(*system, qs, qdots)
    looped = [_final_one(*system, q, v) for q, v in zip(qs, qdots)]
    np.testing.assert_allclose(
        q_end, jnp.stack([x[0] for x in looped]), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_array_equal(steps, [x[1] for x in looped])
    np.testing.assert_allclose(
        qddot, jnp.stack([x[2] for x in looped]), rtol=1e-13, atol=1e-13
    )
