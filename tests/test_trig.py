"""The vectorized float64 sine and cosine of
`lagrax._jaxpr.trig` (used by the sweep kernel) against mpmath at 200 bits and
against the C library."""

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from hypothesis import given, strategies as st

from lagrax._jaxpr.trig import _RANGE, sincos, vectorized_trig


mpmath.mp.prec = 200
_sincos = jax.jit(sincos)


def _ulps(values, exact):
    """|value - exact| in units of the last place of the correctly rounded result."""
    out = []
    for v, e in zip(values, exact):
        spacing = np.spacing(abs(float(e))) if e != 0 else np.finfo(float).tiny
        out.append(abs(float((mpmath.mpf(float(v)) - e) / mpmath.mpf(spacing))))
    return np.array(out)


def _exact(xs):
    xs = [mpmath.mpf(float(x)) for x in xs]
    return [mpmath.sin(x) for x in xs], [mpmath.cos(x) for x in xs]


def _hard_points():
    """Doubles nearest to multiples of pi/2 (where the reduction cancels most bits)
    and their neighbours, up to the end of the range."""
    k = np.unique(np.geomspace(1, 5.2e5, 400).astype(np.int64))
    x = k * (np.pi / 2)
    return np.concatenate([x, np.nextafter(x, 0), np.nextafter(x, np.inf)])


@pytest.mark.parametrize("scale", [1e-9, np.pi / 4, 4.0, 1e3, _RANGE])
def test_within_one_ulp_of_the_exact_value(scale):
    rng = np.random.default_rng(int(np.log2(scale) + 40))
    xs = rng.uniform(-scale, scale, 400)
    s, c = map(np.asarray, _sincos(jnp.asarray(xs)))
    es, ec = _exact(xs)
    assert _ulps(s, es).max() < 1.0
    assert _ulps(c, ec).max() < 1.0


def test_within_one_ulp_near_multiples_of_half_pi():
    xs = _hard_points()
    s, c = map(np.asarray, _sincos(jnp.asarray(xs)))
    es, ec = _exact(xs)
    # The results here are as small as ~1e-17 relative to x: a reduction with too
    # few bits of pi/2 is off by many ulps.
    assert np.min(np.minimum(np.abs(s), np.abs(c))) < 1e-12
    assert _ulps(s, es).max() < 1.0
    assert _ulps(c, ec).max() < 1.0


@given(st.floats(-_RANGE, _RANGE, allow_nan=False))
def test_within_one_ulp_anywhere_in_range(x):
    s, c = _sincos(jnp.asarray(x))
    es, ec = _exact([x])
    assert _ulps([s], es)[0] < 1.0
    assert _ulps([c], ec)[0] < 1.0


def test_agrees_with_the_c_library_over_a_million_points():
    rng = np.random.default_rng(0)
    xs = rng.uniform(-1e4, 1e4, 1_000_000)
    s, c = map(np.asarray, _sincos(jnp.asarray(xs)))
    assert np.max(np.abs(s - np.sin(xs)) / np.spacing(np.abs(np.sin(xs)))) <= 1.0
    assert np.max(np.abs(c - np.cos(xs)) / np.spacing(np.abs(np.cos(xs)))) <= 1.0
    # Mostly the same bits (glibc rounds correctly; fdlibm's kernels do ~90%).
    assert np.mean(s == np.sin(xs)) > 0.8


def test_special_values():
    xs = jnp.array([0.0, -0.0, 1e-300, -5e-324, _RANGE, -_RANGE])
    s, c = _sincos(xs)
    np.testing.assert_array_equal(np.signbit(s[:4]), [False, True, False, True])
    np.testing.assert_array_equal(s[:4], xs[:4])
    np.testing.assert_array_equal(c[:4], 1.0)
    assert np.all(np.isfinite(s[4:])) and np.all(np.isfinite(c[4:]))


@pytest.mark.parametrize(
    "x", [np.inf, -np.inf, np.nan, np.nextafter(_RANGE, np.inf), -1e6, 1e300]
)
def test_outside_the_range_is_nan_never_a_wrong_number(x):
    s, c = _sincos(jnp.asarray(x))
    assert np.isnan(s) and np.isnan(c)


def test_derivatives_are_the_other_function():
    xs = jnp.linspace(-7.0, 7.0, 57)
    ds = jax.vmap(jax.grad(lambda x: sincos(x)[0]))(xs)
    dc = jax.vmap(jax.grad(lambda x: sincos(x)[1]))(xs)
    s, c = sincos(xs)
    np.testing.assert_array_equal(ds, c)
    np.testing.assert_array_equal(dc, -s)
    # Forward mode, second order: d²/dx² sin = -sin.
    d2 = jax.vmap(jax.jacfwd(jax.jacfwd(lambda x: sincos(x)[0])))(xs)
    np.testing.assert_allclose(d2, -np.sin(np.asarray(xs)), rtol=0, atol=1e-15)


def _primitives(f, *args):
    names = set()

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            names.add(eqn.primitive.name)
            for p in eqn.params.values():
                if isinstance(p, jax.extend.core.ClosedJaxpr):
                    walk(p.jaxpr)
                elif isinstance(p, jax.extend.core.Jaxpr):
                    walk(p)

    walk(jax.make_jaxpr(f)(*args).jaxpr)
    return names


def test_vectorized_trig_replaces_float64_sines_inside_nested_calls():
    @jax.jit
    def inner(q):
        return jnp.cos(q) * q

    def f(q, p):
        return jnp.sin(q) + inner(p) ** 2

    def f32(q):
        return jnp.sin(q.astype(jnp.float32))

    q, p = jnp.asarray(0.7), jnp.asarray(-2.5)
    g = vectorized_trig(f)
    assert {"sin", "cos"} <= _primitives(f, q, p)
    names = _primitives(g, q, p)
    assert "sin" not in names and "cos" not in names
    # float32 keeps XLA's own sine (the constants here are float64 ones).
    assert "sin" in _primitives(vectorized_trig(f32), q)
    assert vectorized_trig(f32)(q) == f32(q)
    np.testing.assert_allclose(jax.jit(g)(q, p), f(q, p), rtol=4e-16)
    # Under vmap and differentiated, as the sweep kernel uses it.
    qs = jnp.linspace(-3.0, 3.0, 11)
    grad = jax.vmap(jax.grad(lambda q: g(q, p)))(qs)
    np.testing.assert_allclose(grad, np.cos(np.asarray(qs)), rtol=4e-16, atol=1e-16)


# The same failure, its message naming the range, every time with the default solver
# in the next test; with Dopri8 ("quarter", a program of its own) with -m slow.
@pytest.mark.slow
def test_a_sweep_beyond_the_range_fails_its_lanes_never_a_wrong_period():
    import diffrax as dfx

    import lagrax

    # cos(q + 2e6 pi) is the pendulum's cos q, exactly in exact arithmetic; its
    # argument is beyond the vectorized sine's range.
    L = lambda q, qd, t: 0.5 * qd[0] ** 2 + jnp.cos(q[0] + 2e6 * jnp.pi)
    res = lagrax.sweep_periods(
        L, jnp.array([0.5, 1.0]), solver=dfx.Dopri8(), method="quarter"
    )
    assert not np.any(res.ok)
    assert np.all(np.isnan(res.periods))
    assert all("8.2e5" in m for m in res.messages())


def test_a_default_sweep_beyond_the_range_fails_its_lanes():
    import lagrax

    # The default: Taylor steps with the error bound's sums (the C library's sines
    # in the step), then the far turning point, whose values of L use the
    # vectorized sine: NaN there, and the lane fails as the solver's, never as a
    # period or as "not oscillating".
    L = lambda q, qd, t: 0.5 * qd[0] ** 2 + jnp.cos(q[0] + 2e6 * jnp.pi)
    res = lagrax.sweep_periods(L, jnp.array([0.5, 1.0]))
    assert not np.any(res.ok)
    assert np.all(np.isnan(res.periods))
    assert all("8.2e5" in m for m in res.messages())
    # The same pendulum within the range: both lanes succeed.
    near = lambda q, qd, t: 0.5 * qd[0] ** 2 + jnp.cos(q[0] + 2e4 * jnp.pi)
    assert np.all(lagrax.sweep_periods(near, jnp.array([0.5, 1.0])).ok)


def test_the_controllers_root_is_accurate_and_the_same_in_every_lane():
    # Dopri8's step-size factor inv ** (1/8) by three square roots (`_kernel._root`):
    # within 2 ulp of the exact root, and the same bits whatever a value's position
    # in the array (vector body or scalar remainder of XLA's loop), which a sweep's
    # lanes rely on (results independent of chunk size).
    from lagrax._stepper.controller import _root

    rng = np.random.default_rng(0)
    x = 10.0 ** rng.uniform(-12, 12, 37)
    f = jax.jit(lambda x: _root(x, 8.0))
    together = np.asarray(f(jnp.asarray(x)))
    alone = np.array([float(f(jnp.asarray(xi[None]))[0]) for xi in x])
    np.testing.assert_array_equal(together, alone)
    exact = np.array([float(mpmath.root(mpmath.mpf(float(xi)), 8)) for xi in x])
    assert np.max(np.abs(together - exact) / np.spacing(exact)) <= 2
    # Not a power of two: the plain power.
    np.testing.assert_allclose(
        np.asarray(_root(jnp.asarray(x), 5.0)), x**0.2, rtol=4e-16
    )
