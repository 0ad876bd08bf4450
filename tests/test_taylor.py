import math

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.experimental import jet

from lagrax._eom.mechanics import _accelerations
from lagrax._taylor.program import taylor_coefficients
from lagrax.systems import asymmetric_well, cycloid, driven_pendulum


K = 20


def _reference(accel, s, x, v, p, K=K):
    """Normalized coefficients of (s, x, v) per lane by K calls of `jet`:
    (K + 1, 3, W)."""

    def one(s, x, v, p):
        def f(y):
            return jnp.stack([jnp.ones_like(y[0]), y[2], accel(y[0], y[1], y[2], p)])

        y0 = jnp.stack([s, x, v])
        derivs = [f(y0)]
        for _ in range(1, K):
            _, series = jet.jet(f, (y0,), (derivs,))
            derivs.append(series[-1])
        coeffs = [y0] + [d / math.factorial(i + 1) for i, d in enumerate(derivs)]
        return jnp.stack(coeffs)

    return np.asarray(jax.jit(jax.vmap(one, out_axes=-1))(s, x, v, p))


def _check(accel, s, x, v, p, rtol=1e-13, reference=None, K=K):
    xs, vs, as_ = jax.jit(taylor_coefficients(accel, K, jnp.float64))(s, x, v, p)
    assert xs.shape == vs.shape == (K + 1, x.shape[0])
    assert as_.shape == (K, x.shape[0])
    # The bookkeeping of the docstring:
    # v_{k+1} = a_k / (k + 1), x_{k+1} = v_k / (k + 1).
    k1 = np.arange(1, K + 1)[:, None]
    np.testing.assert_allclose(vs[1:], as_ / k1, rtol=1e-15)
    np.testing.assert_allclose(xs[1:], vs[:-1] / k1, rtol=1e-15)
    # `jet` through lagrax's autodiff jaxpr takes minutes to trace and compile at
    # order 20; the hand-derived equation of motion is the same function.
    ref = _reference(reference or accel, s, x, v, p, K=K)
    for ours, theirs in ((xs, ref[:, 1]), (vs, ref[:, 2])):
        # Per order, relative to that order's largest coefficient over the lanes.
        scale = np.max(np.abs(theirs), axis=1, keepdims=True)
        err = np.abs(np.asarray(ours) - theirs) / np.where(scale > 0, scale, 1.0)
        assert np.max(err) < rtol, np.max(err, axis=1)


def _lagrange_accel(L):
    def accel(s, x, v, q0):
        return _accelerations(L, (q0 + x)[None], v[None], s)[0][0]

    return accel


def _lanes(q0, v):
    q0 = jnp.asarray(q0, jnp.float64)
    W = q0.shape[0]
    return jnp.zeros(W), jnp.zeros(W), jnp.asarray(v, jnp.float64), q0


def test_pendulum():
    L = lambda q, qdot, t: 0.5 * qdot[0] ** 2 + jnp.cos(q[0])
    hand = lambda s, x, v, q0: -jnp.sin(q0 + x)
    lanes = _lanes([0.3, 1.0, 2.0, 3.0], [0.0, 0.5, -0.2, 0.1])
    _check(_lagrange_accel(L), *lanes, reference=hand)


@pytest.mark.slow  # jet at order 20 compiles for minutes on 2 cores
def test_cycloid():
    L = cycloid.lagrangian(R=1.3, g=0.7)
    hand = lambda s, x, v, q0: cycloid.acceleration(q0 + x, v, R=1.3, g=0.7)
    lanes = _lanes([0.6, 1.5, 3.0, 5.0], [0.0, 0.3, -0.4, 0.2])
    _check(_lagrange_accel(L), *lanes, reference=hand)


@pytest.mark.slow  # jet at order 20 compiles for minutes on 2 cores
def test_asymmetric_well():
    # x**3 at x = 0 in the first lane: powers are products, no division by x_0.
    L = asymmetric_well.lagrangian(k=1.0, a=0.8)
    hand = lambda s, x, v, q0: asymmetric_well.acceleration(q0 + x, k=1.0, a=0.8)
    lanes = _lanes([0.0, -0.5, 0.4, 0.9], [0.3, 0.0, -0.1, 0.2])
    _check(_lagrange_accel(L), *lanes, reference=hand)


@pytest.mark.slow  # jet at order 20 compiles for minutes on 2 cores
def test_bead_on_polynomial_track():
    y = lambda q: 0.5 * q**2 - 0.1 * q**3 + 0.05 * q**4
    dy = jax.grad(y)
    L = lambda q, qdot, t: 0.5 * (1 + dy(q[0]) ** 2) * qdot[0] ** 2 - y(q[0])

    def hand(s, x, v, q0):
        # (1 + y'^2) q'' + y' y'' q'^2 + y' = 0
        q = q0 + x
        d1 = q - 0.3 * q**2 + 0.2 * q**3
        d2 = 1 - 0.6 * q + 0.6 * q**2
        return -(d1 * d2 * v**2 + d1) / (1 + d1**2)

    lanes = _lanes([0.2, -0.7, 1.1, 1.6], [0.0, 0.4, -0.3, 0.1])
    _check(_lagrange_accel(L), *lanes, reference=hand)


@pytest.mark.slow  # jet at order 20 compiles for minutes on 2 cores
def test_driven_pendulum_explicit_time():
    L = driven_pendulum.lagrangian(l=1.2, ax=0.2, ay=0.3, omega=2.5)
    s, x, v, q0 = _lanes([0.3, 1.0, 2.0, -1.0], [0.0, 0.5, -0.2, 0.1])
    s = jnp.array([0.0, 0.4, 1.3, 2.7])
    kw = dict(l=1.2, ax=0.2, ay=0.3, omega=2.5)
    hand = lambda s, x, v, q0: driven_pendulum.acceleration(
        (q0 + x)[None], v[None], s, **kw
    )[0]
    _check(_lagrange_accel(L), s, x, v, q0, reference=hand)


# Order 20 (slow: jet compiles for minutes on 2 cores) and order 4, which runs every
# recurrence in the default suite.
ORDERS = [pytest.param(K, marks=pytest.mark.slow), 4]


@pytest.mark.parametrize("order", ORDERS)
def test_elementary_functions(order):
    """The nonlinear recurrences one by one, against `jet`, with a pytree of per-lane
    parameters."""

    def accel(s, x, v, p, tan=jnp.tan):
        c, d = p["c"], p["d"]
        u = c + x
        return (
            jnp.exp(0.3 * u) * jnp.log(1.5 + u)
            + jnp.sqrt(2.0 + u) * v
            + tan(0.4 * u)
            - jnp.tanh(v) / (1.2 + u * u)
            + (1.3 + u) ** 1.7
            + (1.3 + u) ** d
            + jax.lax.rsqrt(2.5 + u)
            + jnp.expm1(0.2 * v)
            + jnp.log1p(0.5 * u * u)
            + jnp.cosh(0.3 * u) * jnp.sinh(0.2 * v)
            + jax.nn.sigmoid(u - v)
            + jnp.abs(u - 0.1)
            + jnp.maximum(u, 0.2 * v)
            + jnp.where(u > 0.5, u**3, -(u**2))
            + jnp.clip(u, -0.2, 0.3)
            + jnp.sin(s) * u
        )

    W = 4
    p = {"c": jnp.array([0.1, 0.6, -0.3, 0.35]), "d": jnp.array([0.5, -1.5, 2.0, 3.5])}
    s = jnp.array([0.0, 0.3, -0.2, 1.0])
    v = jnp.array([0.2, -0.1, 0.05, 0.3])
    # `jet` has no rule for tan.
    reference = lambda s, x, v, p: accel(s, x, v, p, lambda u: jnp.sin(u) / jnp.cos(u))
    _check(accel, s, jnp.zeros(W), v, p, rtol=1e-12, reference=reference, K=order)


@pytest.mark.parametrize("order", ORDERS)
def test_atan(order):
    def accel(s, x, v, c):
        return jnp.arctan(c + x) * v

    xs, vs, _ = taylor_coefficients(accel, order, jnp.float64)(
        jnp.zeros(2), jnp.zeros(2), jnp.array([0.3, -0.2]), jnp.array([0.2, 1.4])
    )
    # The same function through atan2, which `jet` knows.
    f = lambda s, x, v, c: jnp.arctan2(c + x, 1.0) * v
    lanes = jnp.zeros(2), jnp.zeros(2), jnp.array([0.3, -0.2]), jnp.array([0.2, 1.4])
    ref = _reference(f, *lanes, K=order)
    np.testing.assert_allclose(xs, ref[:, 1], rtol=1e-12, atol=1e-16)


def test_closure_over_outer_jit_tracer():
    L = lambda q, qdot, t: 0.5 * qdot[0] ** 2 + jnp.cos(q[0])
    accel = _lagrange_accel(L)

    @jax.jit
    def closed(g, s, x, v, q0):
        # g is a tracer of this jit; accel closes over it.
        f = lambda s, x, v, q0: g * accel(s, x, v, q0)
        return taylor_coefficients(f, k, jnp.float64)(s, x, v, q0)

    # The closure is what is checked: order 8 (compiled faster than 20) will do.
    k = 8
    lanes = _lanes([0.5, 2.0], [0.1, 0.0])
    xs, _, _ = closed(2.0, *lanes)
    ref = _reference(lambda s, x, v, q0: -2.0 * jnp.sin(q0 + x), *lanes, K=k)
    np.testing.assert_allclose(xs, ref[:, 1], rtol=1e-12, atol=1e-16)


def test_polynomial_step_matches_diffrax():
    """The order-20 Taylor polynomial of the pendulum, summed at h = 0.3, against a
    tight Dopri8 solve over the same step."""
    L = lambda q, qdot, t: 0.5 * qdot[0] ** 2 + jnp.cos(q[0])
    s, x, v, q0 = _lanes([0.5, 1.5, 2.8], [0.0, 0.2, -0.1])
    xs, vs, _ = taylor_coefficients(_lagrange_accel(L), K, jnp.float64)(s, x, v, q0)
    h = 0.3
    powers = h ** np.arange(K + 1)[:, None]
    x1, v1 = np.sum(xs * powers, 0), np.sum(vs * powers, 0)

    def exact(q0, v0):
        term = dfx.ODETerm(lambda t, y, args: jnp.stack([y[1], -jnp.sin(y[0])]))
        ctrl = dfx.PIDController(rtol=1e-14, atol=1e-14)
        sol = dfx.diffeqsolve(
            term,
            dfx.Dopri8(),
            0.0,
            h,
            0.01,
            jnp.stack([q0, v0]),
            stepsize_controller=ctrl,
        )
        return sol.ys[0]

    y1 = jax.vmap(exact)(q0, v)
    np.testing.assert_allclose(q0 + x1, y1[:, 0], rtol=0, atol=1e-13)
    np.testing.assert_allclose(v1, y1[:, 1], rtol=0, atol=1e-13)


def test_order_one_and_constant_acceleration():
    coeffs = taylor_coefficients(lambda s, x, v: jnp.asarray(-9.8), 3, jnp.float64)
    xs, vs, as_ = coeffs(jnp.zeros(2), jnp.array([1.0, 2.0]), jnp.array([0.5, 0.0]))
    np.testing.assert_allclose(xs[:, 0], [1.0, 0.5, -4.9, 0.0])
    np.testing.assert_allclose(as_[:, 1], [-9.8, 0.0, 0.0])
    xs, vs, as_ = taylor_coefficients(lambda s, x, v: -x, 1, jnp.float64)(
        jnp.zeros(1), jnp.ones(1), jnp.zeros(1)
    )
    np.testing.assert_allclose(xs[:, 0], [1.0, 0.0])
    np.testing.assert_allclose(vs[:, 0], [0.0, -1.0])


def test_unknown_primitive():
    coeffs = taylor_coefficients(lambda s, x, v: jax.lax.erf(x), 5, jnp.float64)
    with pytest.raises(NotImplementedError, match="`erf`"):
        coeffs(jnp.zeros(2), jnp.zeros(2), jnp.zeros(2))
    # The same primitive on a constant is evaluated once and is fine.
    coeffs = taylor_coefficients(
        lambda s, x, v: jax.lax.erf(jnp.asarray(0.5)) * x, 5, jnp.float64
    )
    xs, _, _ = coeffs(jnp.zeros(1), jnp.ones(1), jnp.zeros(1))
    assert np.isclose(xs[2, 0], 0.5 * float(jax.lax.erf(0.5)))


def _dot_accel(s, x, v, q0):
    u = jnp.stack([q0 + x, v])
    return -jnp.dot(u, jnp.stack([jnp.sin(q0 + x), 0.1 * v]))


def _mixed_accel(s, x, v, q0):
    u = q0 + x
    return (
        jnp.exp(0.3 * u) * jnp.log(1.5 + u)
        + jnp.sqrt(2.0 + u) * v
        - jnp.tanh(u) / (2.0 + jnp.cos(u))
        + jnp.maximum(u, 0.2) ** 3
        + jnp.arctan(v) * jnp.sin(0.5 * s)
    )


@pytest.mark.parametrize(
    "accel",
    [
        _lagrange_accel(lambda q, qd, t: 0.5 * qd[0] ** 2 + jnp.cos(q[0])),
        _lagrange_accel(cycloid.lagrangian()),
        _dot_accel,
        _mixed_accel,
    ],
)
def test_unrolled_matches_loop(accel):
    """The straight-line (unrolled) coefficients equal the loop's, which the tests
    above check against `jet`: same recurrences, exactly triangular sums."""
    s, x, v, q0 = _lanes(jnp.linspace(0.2, 1.4, 7), jnp.linspace(-0.3, 0.4, 7))
    s = s + 0.3
    order = 9
    loop = jax.jit(taylor_coefficients(accel, order, jnp.float64))(s, x, v, q0)
    flat = jax.jit(taylor_coefficients(accel, order, jnp.float64, unrolled=True))(
        s, x, v, q0
    )
    for ours, theirs in zip(flat, loop):
        assert len(ours) == theirs.shape[0]
        ours = np.stack([np.broadcast_to(c, theirs.shape[1:]) for c in ours])
        scale = np.max(np.abs(theirs), axis=1, keepdims=True)
        err = np.abs(ours - np.asarray(theirs)) / np.where(scale > 0, scale, 1.0)
        assert np.max(err) < 1e-13, np.max(err, axis=1)


def test_the_step_leaves_its_loop_by_select_where_transcendentals_share_it():
    # Two or more transcendental values feeding the recurrence: the stacked loop's
    # branches each recompute them (up to a hundred times slower per step), so the
    # period kernel's step takes the select; one or none: the stack.
    import types

    from lagrax._period.units import scaled_acceleration
    from lagrax._taylor.program import transcendental_reads
    from lagrax._taylor.stepper import TaylorStepper

    def field(V):
        a = scaled_acceleration(lambda q, qd, t: 0.5 * qd[0] ** 2 - V(q[0]), ())
        accel = lambda s, x, v, p: a(*p, s, x, v)  # noqa: E731
        return types.SimpleNamespace(scalar_accel=accel, params=[jnp.ones((4,))] * 3)

    fields = {
        "polynomial": field(lambda q: q**2 / 2 + q**4 / 10),
        "pendulum": field(lambda q: -jnp.cos(q)),
        "gaussian well": field(lambda q: -jnp.exp(-(q**2))),
        "sin squared": field(lambda q: jnp.sin(q) ** 2 / 2),
        "two exponentials": field(lambda q: jnp.exp(q) + jnp.exp(-q)),
    }
    counts = {
        k: transcendental_reads(f.scalar_accel, jnp.float64, f.params)
        for k, f in fields.items()
    }
    assert counts == {
        "polynomial": 0,
        "pendulum": 1,
        "gaussian well": 1,
        "sin squared": 2,
        "two exponentials": 2,
    }
    step = TaylorStepper(order=20, max_step=2.0)
    chosen = {k: step.fuses_by_select(f, jnp.float64) for k, f in fields.items()}
    assert chosen == {k: n >= 2 for k, n in counts.items()}
