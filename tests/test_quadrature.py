import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import lagrax
from lagrax._period.quadrature import (
    EQUILIBRIUM,
    ESCAPES,
    NOT_NATURAL,
    SINGULAR_MASS,
    UNRESOLVED,
)
from lagrax.systems import asymmetric_well, cycloid, pendulum


# quadrature_period compiles once per Lagrangian object and shape of q0 (a few seconds
# each): the tests share these.
PEND = pendulum.lagrangian()
WELL = asymmetric_well.lagrangian(k=1.0, a=1.0)  # barrier top at x = -1, V = 1/6


def test_pendulum_against_exact_period():
    # Small amplitudes (where cos q - cos q0 is all rounding) to 0.01 from the top.
    amps = jnp.concatenate(
        [jnp.geomspace(1e-3, 1.0, 24), jnp.linspace(1.0, jnp.pi - 1e-2, 40)]
    )
    res = lagrax.quadrature_period(pendulum.lagrangian(r=2.0, g=9.81), amps)
    exact = pendulum.period(amps, r=2.0, g=9.81)
    assert np.all(np.asarray(res.status) == 0)
    err = np.abs(np.asarray(res.periods / exact - 1))
    assert np.max(err[np.asarray(amps) <= 3.0]) < 2e-14
    assert np.max(err) < 1e-12
    # The turning point of the symmetric well is the mirror image.
    np.testing.assert_allclose(res.turning_points, -amps, rtol=1e-12)
    # The rounding estimate is an estimate: not wildly below the actual error.
    assert np.all(np.asarray(res.errors) >= err / 10)


def test_pendulum_near_the_top_is_flagged_not_wrong():
    amps = jnp.pi - jnp.array([1e-3, 1e-5, 1e-7])
    res = lagrax.quadrature_period(PEND, amps, throw=False)
    assert np.all(np.asarray(res.status) == UNRESOLVED)
    assert np.all(np.isnan(np.asarray(res.periods)))
    # With a looser rtol the first is a number, as accurate as the estimate says.
    res = lagrax.quadrature_period(PEND, amps, rtol=1e-9, throw=False)
    err = abs(float(res.periods[0] / pendulum.period(amps[0]) - 1))
    assert res.status[0] == 0 and err < 1e-9 and err < 10 * float(res.errors[0])
    with pytest.raises(ValueError, match="unstable equilibrium"):
        lagrax.quadrature_period(PEND, amps)


def test_pendulum_at_equilibria_and_beyond_the_top():
    res = lagrax.quadrature_period(PEND, jnp.array([0.0, jnp.pi, -jnp.pi]), throw=False)
    assert np.all(np.asarray(res.status) == EQUILIBRIUM)
    assert np.all(np.isnan(np.asarray(res.periods)))
    # Released at rest beyond the top it swings about 2 pi, with amplitude pi - 0.1.
    res = lagrax.quadrature_period(PEND, jnp.array([jnp.pi + 0.1, 4.0, -4.0]))
    reduced = 2 * jnp.pi - jnp.array([jnp.pi + 0.1, 4.0, 4.0])
    np.testing.assert_allclose(res.periods, pendulum.period(reduced), rtol=1e-13)
    np.testing.assert_allclose(res.turning_points[0], 3 * jnp.pi - 0.1, rtol=1e-13)


def test_cycloid_is_isochronous_in_both_coordinates():
    R, g = 1.5, 9.81
    exact = float(cycloid.period(R=R, g=g))
    # theta form: cusp at 0, bottom at pi; released anywhere off the cusp. At the cusp
    # (the first point) the theta form has a zero mass: reported, not a number.
    L_theta = cycloid.lagrangian(R=R, g=g)
    thetas = jnp.array([0.0, 1e-3, 0.1, 1.0, 2.0, 3.0, 3.1, 4.0, 6.0])
    res = lagrax.quadrature_period(L_theta, thetas, throw=False)
    assert res.status[0] == SINGULAR_MASS and jnp.isnan(res.periods[0])
    np.testing.assert_array_equal(res.status[1:], 0)
    np.testing.assert_allclose(res.periods[1:], exact, rtol=1e-13)
    np.testing.assert_allclose(
        res.turning_points[1:], 2 * jnp.pi - thetas[1:], rtol=1e-12
    )
    # u = cos(theta/2) is regular everywhere, the cusp u = 1 included.
    us = jnp.array([-1.0, -0.3, 1e-6, 0.5, 0.999, 1.0])
    res = lagrax.quadrature_period(cycloid.lagrangian_u(R=R, g=g), us)
    np.testing.assert_allclose(res.periods, exact, rtol=1e-13)


@pytest.mark.slow  # a third quadrature program
def test_cycloid_reparametrized_theta_form_agrees():
    R, g = 1.5, 9.81
    exact = float(cycloid.period(R=R, g=g))
    # The reparametrized theta form agrees where it is regular.
    L_theta = cycloid.lagrangian(R=R, g=g)
    L_u = lagrax.reparametrize(L_theta, lambda u, t: 2 * jnp.arccos(u))
    res = lagrax.quadrature_period(L_u, jnp.array([-0.9, 0.2, 0.7]))
    np.testing.assert_allclose(res.periods, exact, rtol=1e-12)


def _well_reference(x0, m, k, a):
    # Independent: the turning points in closed form (the cubic E - V deflated by the
    # known root x0) and scipy's QUADPACK with the algebraic weight for the endpoint
    # singularities (QAWS), on E - V = (a/3)(x - r1)(x - lo)(hi - x).
    beta = x0 + 3 * k / (2 * a)
    disc = np.sqrt(beta**2 - 4 * beta * x0)
    roots = np.sort([x0, (-beta - disc) / 2, (-beta + disc) / 2])
    r1, lo, hi = roots
    f = lambda x: 2 * np.sqrt(m) / np.sqrt(2 * (a / 3) * (x - r1))
    T, abserr = scipy.integrate.quad(
        f, lo, hi, weight="alg", wvar=(-0.5, -0.5), epsabs=0, epsrel=1e-13, limit=200
    )
    other = lo if np.isclose(hi, x0, rtol=0, atol=0) else hi
    return T, other


def test_asymmetric_well_against_scipy():
    m, k, a = 1.3, 2.0, 1.7  # barrier at -k/a = -1.18; top energy reached at 0.588
    xs = (k / a) * np.array([-0.99, -0.9, -0.5, -0.1, 1e-3, 0.2, 0.45, 0.499])
    res = lagrax.quadrature_period(
        asymmetric_well.lagrangian(m=m, k=k, a=a), jnp.asarray(xs)
    )
    for x0, T, q1 in zip(xs, res.periods, res.turning_points):
        T_ref, other = _well_reference(float(x0), m, k, a)
        # (1e-14 but for the last, 2e-3 below the barrier energy: 4e-13 there.)
        np.testing.assert_allclose(T, T_ref, rtol=1e-12)
        np.testing.assert_allclose(q1, other, rtol=1e-12, atol=1e-15)


def test_asymmetric_well_small_amplitude_expansion():
    x0 = jnp.array([-1e-2, -3e-3, 3e-3, 1e-2])
    res = lagrax.quadrature_period(WELL, x0)
    expansion = asymmetric_well.period_expansion(x0, m=1.0, k=1.0, a=1.0)
    dev = np.abs(np.asarray(res.periods / expansion - 1))
    # Second order is right: what is left is third order in x0 (and not zero: the
    # well is asymmetric, so +x0 and -x0 differ).
    assert np.all(dev < 2 * np.abs(np.asarray(x0)) ** 3)
    assert abs(float(res.periods[0] - res.periods[3])) > 1e-7


def test_asymmetric_well_escapes_and_equilibria():
    res = lagrax.quadrature_period(WELL, jnp.array([0.6, -1.2, -1.0, 0.0]), throw=False)
    np.testing.assert_array_equal(
        res.status, [ESCAPES, ESCAPES, EQUILIBRIUM, EQUILIBRIUM]
    )
    assert np.all(np.isnan(np.asarray(res.periods)))
    assert "does not oscillate" in res.messages()[0]
    with pytest.raises(ValueError, match="does not oscillate"):
        lagrax.quadrature_period(WELL, jnp.array([0.1, 0.6, 0.2, 0.3]))


def test_jit_vmap_and_parameters():
    amps = jnp.linspace(0.1, 3.0, 3)
    eager = lagrax.quadrature_period(PEND, amps)
    jitted = jax.jit(lambda a: lagrax.quadrature_period(PEND, a))
    np.testing.assert_array_equal(jitted(amps).periods, eager.periods)
    # vmap over a parameter closed over by L: T scales as 1/sqrt(g).
    gs = jnp.array([1.0, 4.0, 9.81])
    Ts = jax.vmap(
        lambda g: (
            lagrax.quadrature_period(
                pendulum.lagrangian(g=g), jnp.array(1.0), throw=False
            ).periods
        )
    )(gs)
    np.testing.assert_allclose(Ts, pendulum.period(1.0, g=gs), rtol=1e-13)
    # Shapes follow q0 (a (1, 3) grid reuses the program compiled for (3,)).
    grid = amps.reshape(1, 3)
    res = lagrax.quadrature_period(PEND, grid)
    assert res.periods.shape == (1, 3) and res.status.shape == (1, 3)


def test_gradient_against_exact():
    dT = jax.grad(lambda a: lagrax.quadrature_period(PEND, a, throw=False).periods)(
        jnp.array(1.2)
    )
    exact = jax.grad(pendulum.period)(jnp.array(1.2))
    np.testing.assert_allclose(dT, exact, rtol=1e-9)


def test_not_natural_lagrangians():
    # One Lagrangian, three ways of not being natural picked by a coefficient vector:
    # a term linear in qdot, a quartic one, explicit time dependence (one compile).
    def L(q, v, t, c):
        extra = c[0] * v[0] * q[0] + c[1] * v[0] ** 4 + c[2] * jnp.sin(t) * q[0] ** 2
        return PEND(q, v, t) + extra

    cs = jnp.eye(3) * 0.3
    res = jax.vmap(
        lambda c: lagrax.quadrature_period(
            lambda q, v, t: L(q, v, t, c), jnp.array(0.5), throw=False
        )
    )(cs)
    np.testing.assert_array_equal(res.status, [NOT_NATURAL] * 3)
    assert np.all(np.isnan(np.asarray(res.periods)))
    with pytest.raises(ValueError, match="not natural"):
        lagrax.quadrature_period(lambda q, v, t: L(q, v, t, cs[2]), jnp.array(0.5))
