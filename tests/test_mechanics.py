"""Autodiff equations of motion against hand derivations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax.systems import cycloid, pendulum, rectilinear

from .helpers import random_states


def _acc(L, q, qdot, t=0.0, force=None):
    return lagrax.accelerations(L, jnp.asarray(q), jnp.asarray(qdot), t, force=force)


@pytest.mark.parametrize("m,r,g", [(1.0, 1.0, 1.0), (2.5, 0.3, 9.81), (0.1, 7.0, 1.6)])
def test_pendulum_matches_hand_derivation(key, m, r, g):
    L = pendulum.lagrangian(m=m, r=r, g=g)
    q, qdot = random_states(key, 1, 50, scale=2.0)
    got = jax.jit(jax.vmap(lambda a, b: lagrax.accelerations(L, a, b, 0.0)))(q, qdot)
    want = pendulum.acceleration(q, r=r, g=g)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14 * g / r)


@pytest.mark.parametrize("m,R,g", [(1.0, 1.0, 1.0), (3.0, 0.5, 9.81)])
def test_cycloid_matches_hand_derivation(key, m, R, g):
    # Huygens' cycloid in θ: 2Rθ̈ sin(θ/2) + Rθ̇² cos(θ/2) − g cos(θ/2) = 0, off the cusp.
    L = cycloid.lagrangian(m=m, R=R, g=g)
    kq, kv = jax.random.split(key)
    theta = jax.random.uniform(kq, (50, 1), minval=0.05, maxval=2 * jnp.pi - 0.05)
    thetadot = jax.random.normal(kv, (50, 1))
    got = jax.jit(jax.vmap(lambda a, b: lagrax.accelerations(L, a, b, 0.0)))(
        theta, thetadot
    )
    want = cycloid.acceleration(theta, thetadot, R=R, g=g)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    residual = (
        2 * R * got * jnp.sin(theta / 2)
        + R * thetadot**2 * jnp.cos(theta / 2)
        - g * jnp.cos(theta / 2)
    )
    np.testing.assert_allclose(residual, 0.0, atol=1e-12 * (g + R))


def test_cycloid_u_form_is_harmonic(key):
    R, g = 0.7, 9.81
    L = cycloid.lagrangian_u(R=R, g=g)
    u, udot = random_states(key, 1, 20)
    got = jax.jit(jax.vmap(lambda a, b: lagrax.accelerations(L, a, b, 0.0)))(u, udot)
    np.testing.assert_allclose(got, -(g / (4 * R)) * u, rtol=1e-13)


def test_rectilinear_recovers_newton(key):
    def V(x):
        return 0.25 * x**4 - 0.5 * x**2 + jnp.sin(3 * x)

    def F(x):  # −V′(x) by hand
        return -(x**3) + x - 3 * jnp.cos(3 * x)

    m = 1.7
    L = rectilinear.lagrangian(V, m=m)
    q, qdot = random_states(key, 1, 40, scale=1.5)
    got = jax.jit(jax.vmap(lambda a, b: lagrax.accelerations(L, a, b, 0.0)))(q, qdot)
    np.testing.assert_allclose(
        got, rectilinear.acceleration(q, force_x=F, m=m), rtol=1e-12
    )


def test_explicit_time_mass():
    # L = ½ m(t) q̇² − ½ k q², m(t) = m0(1 + a t): m q̈ + ṁ q̇ = −k q.
    m0, a, k = 1.3, 0.4, 2.0

    def L(q, qdot, t):
        return 0.5 * m0 * (1 + a * t) * qdot[0] ** 2 - 0.5 * k * q[0] ** 2

    for q, qdot, t in [(0.3, -1.2, 0.0), (-0.7, 0.5, 2.5), (1.1, 2.0, 7.0)]:
        got = _acc(L, [q], [qdot], t)
        want = (-k * q - m0 * a * qdot) / (m0 * (1 + a * t))
        np.testing.assert_allclose(got, [want], rtol=1e-13)


def test_explicit_time_gauge_term():
    # L = ½ q̇² + f(t) q q̇: the q̇ terms cancel and only ∂²L/∂q̇∂t survives: q̈ = −f′(t) q.
    # A code that drops the ∂t term (as some peers do) gets q̈ = 0 here.
    def L(q, qdot, t):
        return 0.5 * qdot[0] ** 2 + jnp.sin(2 * t) * q[0] * qdot[0]

    for q, qdot, t in [(0.3, -1.2, 0.1), (-0.7, 0.5, 2.5)]:
        got = _acc(L, [q], [qdot], t)
        np.testing.assert_allclose(got, [-2 * np.cos(2 * t) * q], rtol=1e-13)


def test_relativistic_particle_not_quadratic(key):
    # L = −mc²√(1 − v²/c²) − V(x) in 3-D: M = mγ(I + γ² v vᵀ/c²) and
    # q̈ = (F − (F·v) v / c²) / (m γ), F = −∇V.
    m, c = 1.5, 2.0

    def V(x):
        return 0.5 * jnp.dot(x, x) + 0.1 * x[0] * x[1] * x[2]

    def L(q, qdot, t):
        return -m * c**2 * jnp.sqrt(1 - jnp.dot(qdot, qdot) / c**2) - V(q)

    q, _ = random_states(key, 3, 10)
    v = jax.random.uniform(jax.random.key(1), (10, 3), minval=-1.0, maxval=1.0)
    for qi, vi in zip(q, v):
        F = -jax.grad(V)(qi)
        gamma = 1 / jnp.sqrt(1 - jnp.dot(vi, vi) / c**2)
        want = (F - jnp.dot(F, vi) * vi / c**2) / (m * gamma)
        np.testing.assert_allclose(_acc(L, qi, vi), want, rtol=1e-12, atol=1e-14)
        M = gamma * m * (jnp.eye(3) + gamma**2 * jnp.outer(vi, vi) / c**2)
        np.testing.assert_allclose(lagrax.mass_matrix(L, qi, vi, 0.0), M, rtol=1e-12)


def test_velocity_dependent_potential():
    # Charge in a uniform magnetic field B ẑ, A = ½B(−y, x): m a = e v × B.
    m, e, B = 2.0, 1.5, 0.8

    def L(q, qdot, t):
        A = 0.5 * B * jnp.array([-q[1], q[0]])
        return 0.5 * m * jnp.dot(qdot, qdot) + e * jnp.dot(qdot, A)

    q, v = jnp.array([0.3, -0.2]), jnp.array([1.1, 0.4])
    want = (e * B / m) * jnp.array([v[1], -v[0]])
    np.testing.assert_allclose(_acc(L, q, v), want, rtol=1e-13)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_quadratic_lagrangian_against_linear_solve(key, n):
    kM, kK, kq = jax.random.split(key, 3)
    A = jax.random.normal(kM, (n, n))
    M = A @ A.T + n * jnp.eye(n)
    K = jax.random.normal(kK, (n, n))
    K = K + K.T

    def L(q, qdot, t):
        return 0.5 * qdot @ M @ qdot - 0.5 * q @ K @ q

    q, qdot = random_states(kq, n, 5)
    for qi, vi in zip(q, qdot):
        want = jnp.linalg.solve(M, -K @ qi)
        np.testing.assert_allclose(_acc(L, qi, vi), want, rtol=1e-11, atol=1e-13)
        np.testing.assert_allclose(lagrax.mass_matrix(L, qi, vi), M, rtol=1e-13)


def test_negative_definite_lagrangian_same_motion():
    L = pendulum.lagrangian(g=9.81)
    minus_L = lambda q, qdot, t: -L(q, qdot, t)
    q, v = jnp.array([0.8]), jnp.array([0.2])
    np.testing.assert_allclose(_acc(minus_L, q, v), _acc(L, q, v), rtol=1e-14)


def test_force_enters_rhs():
    L = pendulum.lagrangian(m=2.0, r=1.0, g=9.81)
    b = 0.3
    force = lambda q, qdot, t: -b * qdot
    q, v = jnp.array([0.4]), jnp.array([1.5])
    want = -9.81 * jnp.sin(0.4) - b * 1.5 / 2.0
    np.testing.assert_allclose(_acc(L, q, v, force=force), [want], rtol=1e-13)


def test_momenta_energy_mass_matrix():
    m, r, g = 1.3, 0.9, 9.81
    L = pendulum.lagrangian(m=m, r=r, g=g)
    q, v = jnp.array([0.7]), jnp.array([-1.1])
    np.testing.assert_allclose(lagrax.momenta(L, q, v), [m * r**2 * -1.1], rtol=1e-14)
    np.testing.assert_allclose(lagrax.mass_matrix(L, q, v), [[m * r**2]], rtol=1e-14)
    h = 0.5 * m * r**2 * 1.1**2 - m * g * r * np.cos(0.7)
    np.testing.assert_allclose(lagrax.energy(L, q, v), h, rtol=1e-14)


def test_singular_mass_matrix_eager_error():
    # L linear in q̇: M = 0 everywhere.
    L = lambda q, qdot, t: q[0] * qdot[0] - 0.5 * q[0] ** 2
    with pytest.raises(ValueError, match=r"singular or indefinite at q=\[0\.5\]"):
        _acc(L, [0.5], [0.1])


def test_indefinite_mass_matrix_eager_error():
    L = lambda q, qdot, t: 0.5 * (qdot[0] ** 2 - qdot[1] ** 2) - 0.5 * q @ q
    with pytest.raises(ValueError, match="indefinite"):
        _acc(L, [0.1, 0.2], [0.0, 0.0])


@pytest.mark.parametrize("n", [1, 2, 4])
def test_degenerate_mass_matrix_is_nan_under_jit(n):
    # Rank-deficient M (the last velocity absent from L), any n: NaN, never a number.
    def L(q, qdot, t):
        v = qdot[:-1]
        return 0.5 * jnp.dot(v, v) - 0.5 * jnp.dot(q, q)

    q = jnp.linspace(0.1, 0.4, n)
    out = jax.jit(lambda q, v: lagrax.accelerations(L, q, v, 0.0))(q, q)
    assert jnp.all(jnp.isnan(out))


def test_jit_vmap_equal_loop(key):
    L = cycloid.lagrangian(R=1.2, g=9.81)
    theta = jax.random.uniform(key, (16, 1), minval=0.3, maxval=6.0)
    thetadot = jnp.linspace(-1, 1, 16)[:, None]
    batched = jax.jit(jax.vmap(lambda a, b: lagrax.accelerations(L, a, b, 0.3)))
    got = batched(theta, thetadot)
    loop = jnp.stack(
        [lagrax.accelerations(L, a, b, 0.3) for a, b in zip(theta, thetadot)]
    )
    np.testing.assert_allclose(got, loop, rtol=1e-14, atol=1e-14)


def _particle_double_pendulum(m1=1.0, m2=2.0, l1=1.0, l2=0.7, g=9.81):
    # Written as people write it from particles: velocity vectors, T = ½ m v·v.
    def L(q, qdot, t):
        v1 = l1 * qdot[0] * jnp.array([jnp.cos(q[0]), jnp.sin(q[0])])
        v2 = v1 + l2 * qdot[1] * jnp.array([jnp.cos(q[1]), jnp.sin(q[1])])
        y1 = -l1 * jnp.cos(q[0])
        y2 = y1 - l2 * jnp.cos(q[1])
        T = 0.5 * m1 * jnp.dot(v1, v1) + 0.5 * m2 * jnp.dot(v2, v2)
        return T - g * (m1 * y1 + m2 * y2)

    return L


def test_particle_double_pendulum_matches_hand_derivation(key):
    from lagrax.systems import double_pendulum

    params = dict(m1=1.0, m2=2.0, l1=1.0, l2=0.7, g=9.81)
    L = _particle_double_pendulum(**params)
    q, qdot = random_states(key, 2, 64, scale=2.0)
    got = jax.jit(jax.vmap(lambda a, b: lagrax.accelerations(L, a, b, 0.0)))(q, qdot)
    want = double_pendulum.acceleration(q.T, qdot.T, **params).T
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_scalarized_equals_array_evaluation(key, n):
    from lagrax._eom.mechanics import _accelerations, _lagrange_terms, _solve_definite
    from lagrax._jaxpr.scalarize import _cost

    def L(q, qdot, t):  # cumsum, stack, dot, pad, broadcasts, explicit t
        v = jnp.cumsum(jnp.stack([qdot * jnp.cos(q), qdot * jnp.sin(q)], -1), 0)
        return 0.5 * jnp.sum(v * v) * (1 + 0.1 * t) + jnp.sum(jnp.cos(q) ** 2)

    def force(q, qdot, t):
        return -0.3 * qdot * jnp.exp(-t)

    q, qdot = random_states(key, n, 32)
    jaxpr = jax.make_jaxpr(lambda q, v: _lagrange_terms(L, q, v, 0.4))(q[0], qdot[0])
    assert _cost(jaxpr.jaxpr) < 20_000  # so the entry-by-entry path is the one taken

    def unfused(q, qdot):
        M, rhs = _lagrange_terms(L, q, qdot, 0.4)
        return _solve_definite(M, rhs + force(q, qdot, 0.4))[0]

    # (Under jit: one program each, not one per primitive.)
    fused = lambda a, b: _accelerations(L, a, b, 0.4, force)[0]
    got = jax.jit(jax.vmap(fused))(q, qdot)
    want = jax.jit(jax.vmap(unfused))(q, qdot)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
    # Derivatives through it agree too (gradients through a solve).
    g1 = jax.jit(jax.grad(lambda q: jnp.sum(fused(q, qdot[0]))))(q[0])
    g2 = jax.jit(jax.grad(lambda q: jnp.sum(unfused(q, qdot[0]))))(q[0])
    np.testing.assert_allclose(g1, g2, rtol=1e-12, atol=1e-12)


def test_scalarize_falls_back_on_unsupported_primitives():
    from lagrax._jaxpr.scalarize import _cost, scalarized

    def f(x):  # lax.cond and a custom_jvp: not evaluated entry by entry
        y = jax.lax.cond(x[0] > 0, jnp.sin, jnp.cos, x)
        return (jax.nn.relu(y) + jnp.sum(x),)

    x = jnp.array([0.5, -1.0])
    assert _cost(jax.make_jaxpr(f)(x).jaxpr) == float("inf")
    np.testing.assert_array_equal(scalarized(f, x)[0], f(x)[0])


def test_scalarize_structural_primitives(key):
    from lagrax._jaxpr.scalarize import scalarized

    def f(x, y):
        a = jnp.cumsum(x) * jnp.cumsum(y[::-1])[::-1]
        b = jnp.pad(x, (1, 2))[1:-1]
        c = jnp.einsum("i,j->ij", x, y) @ x
        d = jnp.max(x) + jnp.min(y) + jnp.concatenate([x, y])[:3] + jnp.sum(x * y)
        e = jnp.transpose(jnp.outer(x, y)).reshape(-1)[::2]
        return a, b, c, d, e, jnp.zeros((0,)) @ jnp.zeros((0,))

    x, y = jax.random.normal(key, (2, 3))
    for got, want in zip(scalarized(f, x, y), f(x, y), strict=True):
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)
    batched = jax.jit(jax.vmap(lambda x, y: scalarized(f, x, y)))
    X, Y = jax.random.normal(key, (2, 4, 3))
    for got, want in zip(batched(X, Y), jax.vmap(f)(X, Y), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("n", [1, 2])
def test_fused_accelerations_identical(key, n):
    # `one_fusion` changes how XLA schedules the work, not the arithmetic: the same
    # values to round-off (XLA may contract or reorder differently inside the one
    # loop) under jit/vmap, NaN lanes (a singular M) kept, and the same derivatives
    # (its JVP is the identity) forward and reverse.
    from lagrax._eom.mechanics import _accelerations

    def L(q, qdot, t):  # M proportional to q_0^2: singular where q_0 = 0
        v = jnp.cumsum(jnp.stack([qdot * jnp.cos(q), qdot * jnp.sin(q)], -1), 0)
        return 0.5 * jnp.sum(v * v) * q[0] ** 2 + jnp.sum(jnp.cos(q)) * (1 + t)

    q, qdot = random_states(key, n, 32)
    q = q.at[0, 0].set(0.0)  # one lane with a singular mass matrix

    def run(fuse):
        def acc(q, qdot, t):
            qddot, (M, ok) = _accelerations(L, q, qdot, t, fuse=fuse)
            return qddot, M, ok

        return jax.jit(jax.vmap(acc, (0, 0, None)))(q, qdot, 0.3)

    fused, unfused = run(True), run(False)
    for got, want in zip(fused, unfused, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(fused[2], unfused[2])
    assert not fused[2][0] and jnp.all(jnp.isnan(fused[0][0]))
    assert jnp.all(fused[2][1:]) and jnp.all(jnp.isfinite(fused[0][1:]))

    def total(q, fuse):
        return jnp.sum(_accelerations(L, q, qdot[1], 0.3, fuse=fuse)[0])

    for transform in (jax.grad, jax.jacfwd):
        np.testing.assert_allclose(
            jax.jit(transform(lambda q: total(q, True)))(q[1]),
            jax.jit(transform(lambda q: total(q, False)))(q[1]),
            rtol=1e-12,
            atol=1e-12,
        )


@pytest.mark.parametrize("branch_free", [False, True])
def test_one_fusion_is_the_identity(branch_free):
    from lagrax._jaxpr.fusion import one_fusion

    values = dict(
        x=jnp.array([0.0, -0.0, 1.5, jnp.inf, -jnp.inf, jnp.nan]),
        i=jnp.arange(6, dtype=jnp.int32) - 3,
        b=jnp.array([True, False] * 3),
    )
    out = jax.jit(lambda v: one_fusion(v, branch_free=branch_free))(values)
    assert out.keys() == values.keys()
    for k, v in values.items():
        assert out[k].dtype == v.dtype
        np.testing.assert_array_equal(out[k], v)
    # Signed zeros survive (-0.0 + 0.0 would be +0.0).
    np.testing.assert_array_equal(jnp.signbit(out["x"]), jnp.signbit(values["x"]))


def test_scalarize_folds_constants_as_xla_does():
    """Known scalars are folded by NumPy for the correctly rounded operations (no XLA
    compile per operation): bit for bit what XLA's own evaluation gives, including
    infinities, NaN, signed zeros and subnormals; others are left to XLA (None)."""
    from lagrax._jaxpr.scalarize import _fold_exact

    lax = jax.lax
    floats = [0.0, -0.0, 1.0, -2.5, 1e-310, 3.0e300, np.inf, -np.inf, np.nan, 0.1]
    unary = [lax.neg_p, lax.abs_p, lax.sqrt_p, lax.is_finite_p]
    binary = [lax.add_p, lax.sub_p, lax.mul_p, lax.div_p, lax.max_p, lax.min_p]
    binary += [lax.eq_p, lax.ne_p, lax.lt_p, lax.le_p, lax.gt_p, lax.ge_p]

    def same(a, b):
        if a is None:  # left to XLA: max/min, or where a subnormal is involved
            subnormal = any(0 < abs(float(x)) < 1e-300 for x in (*args, b))
            assert subnormal or name in ("max", "min"), (name, args, b)
            return
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype, (a.dtype, b.dtype)
        assert a.tobytes() == b.tobytes() or (np.isnan(a) and np.isnan(b)), (a, b)

    for dtype in (np.float64, np.float32):
        with np.errstate(over="ignore"):  # 3e300 is inf in float32
            xs = [np.asarray(x, dtype) for x in floats]
        for p in unary:
            for x in xs:
                args, name = [x], p.name
                same(_fold_exact(p.name, args, {}), p.bind(x))
        for p in binary:
            for x in xs:
                for y in xs:
                    args, name = [x, y], p.name
                    same(_fold_exact(p.name, args, {}), p.bind(x, y))
    args, name = [], None
    bools = [np.bool_(False), np.bool_(True)]
    for p in (lax.and_p, lax.or_p):
        for x in bools:
            for y in bools:
                same(_fold_exact(p.name, [x, y], {}), p.bind(x, y))
    same(_fold_exact("not", [bools[0]], {}), lax.not_p.bind(bools[0]))
    ints = [np.int64(7), np.int64(-3)]
    same(_fold_exact("add", ints, {}), lax.add_p.bind(*ints))
    one, two = np.float64(1.0), np.float64(2.0)
    same(_fold_exact("select_n", [bools[1], one, two], {}), two)
    params = dict(new_dtype=np.dtype(np.float64), weak_type=False, sharding=None)
    same(_fold_exact("convert_element_type", [bools[1]], params), one)
    # Integer division rounds differently in NumPy, sin is not correctly rounded,
    # max/min order signed zeros differently, arrays are not scalars: left to XLA.
    assert _fold_exact("div", ints, {}) is None
    assert _fold_exact("sin", [one], {}) is None
    assert _fold_exact("max", [np.float64(0.0), np.float64(-0.0)], {}) is None
    assert _fold_exact("add", [np.ones(2), np.ones(2)], {}) is None


def test_equations_derived_once_per_lagrangian_and_shapes():
    # A solver traces its vector field several times: the equations of one L at one
    # set of shapes are derived once, then replayed, in any later trace too.
    calls = []

    def L(q, qdot, t):
        calls.append(1)
        return 0.5 * jnp.sum(qdot**2) + jnp.sum(jnp.cos(q))

    f = lagrax.vector_field(L)
    y = (jnp.array([0.3, -0.2]), jnp.array([0.1, 0.4]))
    want = f(0.0, y, None)[1]
    first = jax.jit(lambda y: f(0.0, y, None)[1])
    np.testing.assert_allclose(first(y), want, rtol=1e-15)
    derived = len(calls)
    assert derived > 0
    other = jax.jit(jax.vmap(lambda y: 2.0 * f(0.0, y, None)[1]))
    ys = jax.tree.map(lambda x: jnp.stack([x, 2 * x]), y)
    got = other(ys)
    assert len(calls) == derived
    np.testing.assert_allclose(got[0], 2 * want, rtol=1e-15)
    # Other shapes derive again.
    jax.jit(lambda y: f(0.0, y, None)[1])((y[0][:1], y[1][:1]))
    assert len(calls) > derived


def test_equations_of_a_lagrangian_closing_over_a_tracer():
    # L built inside a transformation closes over its tracer: its equations are not
    # kept past that trace, and each trace sees its own parameter.
    def period_proxy(g):
        L = lambda q, qdot, t: 0.5 * jnp.sum(qdot**2) + g * jnp.sum(jnp.cos(q))
        f = lagrax.vector_field(L)
        y = (jnp.array([0.5]), jnp.array([0.0]))
        return f(0.0, y, None)[1][0] + f(0.0, y, None)[1][0]

    for g in (1.0, 2.5):
        np.testing.assert_allclose(jax.grad(period_proxy)(g), -2 * np.sin(0.5))
        np.testing.assert_allclose(
            jax.jit(period_proxy)(g), -2 * g * np.sin(0.5), rtol=1e-15
        )


def test_replayed_equations_serve_the_taylor_recurrences():
    # The Taylor recurrences read the equations' jaxpr with `one_fusion` off: a jaxpr
    # derived before for XLA (fusion on) must not be replayed to them.
    L = lambda q, qdot, t: 0.5 * jnp.sum(qdot**2) - 0.5 * jnp.sum(q**2)
    f = lagrax.vector_field(L)
    y = (jnp.array([1.0]), jnp.array([0.0]))
    t = jnp.zeros((), jnp.float64)  # (as the Taylor program traces it: not weak)
    np.testing.assert_allclose(jax.jit(lambda y: f(t, y, None)[1])(y), [-1.0])
    sol = lagrax.simulate_batch(
        L, jnp.ones((2, 1)), jnp.zeros((2, 1)), 0.0, 2.0, rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(sol.ys[0][:, -1, 0], np.cos(2.0), rtol=1e-10)
