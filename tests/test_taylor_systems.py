"""`lagrax.Taylor` on the Lagrangians the Runge–Kutta solvers integrate: constant,
q-dependent and velocity-dependent kinetic terms, explicit time, n = 1..6; through
`simulate`, a caller's `jit(vmap(...))` of it and `simulate_batch`."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._taylor.system import System


KINDS = ["constant", "q-dependent", "magnetic", "relativistic", "driven", "uniform"]


def family(kind, n):
    r"""A Lagrangian of `n` coordinates, its kinetic term of the given kind, with
    the smooth coupled potential $V$ below (n >= 3 with a $q$-independent mass
    matrix takes the mass-matrix solve with no series input)."""
    w = 1.0 + 0.25 * jnp.arange(n)
    i = jnp.arange(n)
    # exp(-|i - j|) is positive definite: a constant mass matrix with coupling.
    M = jnp.eye(n) + 0.2 * jnp.exp(-jnp.abs(i[:, None] - i[None, :]))

    def V(q):
        coupling = jnp.sum(q[:-1] * q[1:])
        return jnp.sum(w * (1 - jnp.cos(q))) + 0.05 * jnp.sum(q**4) + 0.1 * coupling

    def L(q, qd, t):
        if kind == "constant":
            return 0.5 * qd @ M @ qd - V(q)
        if kind == "q-dependent":
            s = jnp.sin(q)
            T = 0.5 * qd @ qd + 0.05 * (s @ qd) ** 2 + 0.1 * jnp.sum(q**2 * qd**2)
            return T - V(q)
        if kind == "magnetic":
            # Linear in qdot: a uniform field in the (q0, q1) plane and a
            # q-dependent vector potential.
            A = 0.2 * jnp.cos(q) @ qd
            if n >= 2:
                A = A + 0.65 * (q[0] * qd[1] - q[1] * qd[0])
            return 0.5 * qd @ qd + A - V(q)
        if kind == "relativistic":
            return -jnp.sqrt(1.0 - qd @ qd) - V(q)
        if kind == "uniform":
            # A constant acceleration (uniform gravity): no series input to the
            # mass-matrix solve at all.
            return 0.5 * qd @ qd - w @ q
        if kind == "driven":
            mass = 1.0 + 0.1 * jnp.sin(t)
            return 0.5 * mass * qd @ qd - V(q) + 0.3 * q[0] * jnp.cos(1.7 * t)
        raise ValueError(kind)

    return L


def release(n):
    return jnp.linspace(0.4, -0.3, n), jnp.linspace(0.1, 0.2, n)


def check_series(L, n, order, unrolled, t0=0.7):
    """The series of the system (q, qdot)' = f(t, q, qdot) about t0 against nested
    JVPs of the flow of (t, q, qdot): y_k = y^(k)(t0) / k!, k <= order."""
    field = lagrax.vector_field(L)
    q0, v0 = release(n)
    system = System(lambda t, ys, p: list(field(t, tuple(ys), None)), 0.0, [q0, v0], [])
    coefs = jax.jit(
        lambda t, q, v: system.coefficients(order, t, [q, v], [], unrolled=unrolled)
    )(jnp.full(1, t0), q0[None], v0[None])
    series = np.array([[float(c[k][0]) for c in coefs] for k in range(order + 1)])

    def F(y):
        q, v = field(y[0], (y[1 : n + 1], y[n + 1 :]), None)
        return jnp.concatenate([jnp.ones(1), q, v])

    def derivatives(y):
        g, out = F, []
        for _ in range(order):
            out.append(g(y)[1:])
            g = (lambda g: lambda y: jax.jvp(g, (y,), (F(y),))[1])(g)
        return out

    y = jnp.concatenate([jnp.full(1, t0), q0, v0])
    factorial = 1.0
    for k, d in enumerate(jax.jit(derivatives)(y), start=1):
        factorial *= k
        np.testing.assert_allclose(series[k], d / factorial, rtol=1e-11, atol=1e-12)


B, F, OMEGA = 1.3, 0.4, 1.7


def charged_particle(q, qd, t):
    """A charged particle in a uniform field B along z, its z an oscillator driven
    at OMEGA: constant mass matrix, n = 3, a term linear in qdot, explicit time."""
    magnetic = 0.5 * B * (q[0] * qd[1] - q[1] * qd[0])
    return 0.5 * qd @ qd + magnetic - 0.5 * q[2] ** 2 + F * q[2] * jnp.cos(OMEGA * t)


def charged_particle_exact(q0, v0, t):
    """x + iy moves with qdot_x + i qdot_y = (its start) e^{-iBt};
    z'' = -z + F cos(OMEGA t)."""
    w0 = v0[0] + 1j * v0[1]
    xy = q0[0] + 1j * q0[1] + w0 * (np.exp(-1j * B * t) - 1) / (-1j * B)
    c = F / (1 - OMEGA**2)
    z = (q0[2] - c) * np.cos(t) + v0[2] * np.sin(t) + c * np.cos(OMEGA * t)
    return np.stack([xy.real, xy.imag, z], axis=-1)


@pytest.mark.parametrize("unrolled", [True, False])
def test_charged_particle_series(unrolled):
    """Order 3 (t enters f at orders >= 2) of the charged particle: a constant mass
    matrix at n = 3, a term linear in qdot, explicit time."""
    check_series(charged_particle, 3, 3, unrolled)


def test_uniform_gravity_series():
    check_series(family("uniform", 3), 3, 3, unrolled=True)


Q0 = np.array([[0.3, -0.2, 0.1], [1.0, 0.5, -0.4]])
V0 = np.array([[0.2, 0.5, -0.3], [-1.0, 0.1, 0.2]])
T = 4.0
EXACT = np.stack([charged_particle_exact(a, b, T) for a, b in zip(Q0, V0)])
TOL = dict(rtol=1e-12, atol=1e-12)


def test_charged_particle_simulate_and_batch():
    """The system that raised an internal error (n = 3, constant mass matrix), and
    gave wrong states with explicit time, against its exact solution: `simulate`
    with `Taylor`, `simulate_batch` with its default solver."""
    taylor = lagrax.Taylor(order=10)
    sol = lagrax.simulate(charged_particle, Q0[0], V0[0], 0.0, T, solver=taylor, **TOL)
    np.testing.assert_allclose(sol.ys[0][-1], EXACT[0], atol=1e-10)
    batch = lagrax.simulate_batch(charged_particle, Q0, V0, 0.0, T, **TOL)
    assert np.all(np.asarray(batch.result == dfx.RESULTS.successful))
    np.testing.assert_allclose(batch.ys[0][:, -1], EXACT, atol=1e-10)


@pytest.mark.slow
def test_charged_particle_under_a_callers_jit_of_vmap():
    # With the compile option the `Taylor` docstring asks for under a caller's `jit`.
    def end(a, b):
        taylor = lagrax.Taylor()
        s = lagrax.simulate(charged_particle, a, b, 0.0, T, solver=taylor, **TOL)
        return s.ys[0][-1]

    options = {"xla_cpu_use_fusion_emitters": False}
    ends = jax.jit(jax.vmap(end), compiler_options=options)(Q0, V0)
    np.testing.assert_allclose(ends, EXACT, atol=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("unrolled", [True, False])
def test_family_series(kind, unrolled):
    check_series(family(kind, 3), 3, 4, unrolled)


@pytest.mark.slow
@pytest.mark.parametrize("n", range(1, 7))
@pytest.mark.parametrize("kind", KINDS)
def test_family_against_dopri8(kind, n):
    """Every kind at every n, `simulate` and `simulate_batch` with `Taylor` against
    `Dopri8` at a tighter tolerance. (Order 6: the compile of a higher order grows
    steeply with n; the recurrences are the same at every order.)"""
    L = family(kind, n)
    q0, v0 = release(n)
    T = 3.0
    tight = dict(solver=dfx.Dopri8(), rtol=1e-13, atol=1e-13)
    ref = lagrax.simulate(L, q0, v0, 0.0, T, **tight)
    taylor = lagrax.Taylor(order=6)
    kw = dict(solver=taylor, rtol=1e-12, atol=1e-12)
    sol = lagrax.simulate(L, q0, v0, 0.0, T, **kw)
    batch = lagrax.simulate_batch(L, q0[None], v0[None], 0.0, T, **kw)
    for got in (sol.ys, jax.tree.map(lambda a: a[0], batch.ys)):
        for a, b in zip(got, ref.ys):
            np.testing.assert_allclose(a[-1], b[-1], atol=1e-9)
