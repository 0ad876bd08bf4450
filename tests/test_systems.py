"""Exact references shipped with the seed systems."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import ellipkm1

from lagrax.systems import cycloid, pendulum


def test_pendulum_period_against_elliptic_integral():
    theta0 = np.concatenate([np.geomspace(1e-6, 1.0, 30), np.linspace(1.0, 3.14, 60)])
    r, g = 0.7, 9.81
    # K(m) through 1 − m = cos²(θ0/2): forming m = sin² first loses digits near π.
    want = 4 * np.sqrt(r / g) * ellipkm1(np.cos(theta0 / 2) ** 2)
    got = pendulum.pendulum_period(jnp.asarray(theta0), r, g)
    np.testing.assert_allclose(got, want, rtol=3e-15)


def test_pendulum_period_known_ratios():
    # DESIGN.md: T/T0 = 1.180340599 at 90°, 3.901065160 at 179°.
    T0 = pendulum.small_amplitude_period()
    ratios = pendulum.pendulum_period(jnp.deg2rad(jnp.array([90.0, 179.0]))) / T0
    np.testing.assert_allclose(ratios, [1.180340599, 3.901065160], atol=1e-9)


def test_pendulum_period_edges():
    T = pendulum.pendulum_period(jnp.array([0.0, -0.5, 0.5, jnp.pi, 4.0]))
    assert T[0] == pytest.approx(2 * np.pi, rel=1e-15)
    assert T[1] == T[2]
    assert np.all(np.isinf(T[3:]))


def test_pendulum_period_gradient():
    theta0 = 1.3
    grad = jax.grad(lambda a: pendulum.pendulum_period(a))(theta0)
    h = 1e-5
    fd = (
        pendulum.pendulum_period(theta0 + h) - pendulum.pendulum_period(theta0 - h)
    ) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-8)


def test_cycloid_period_isochronous():
    T = cycloid.cycloid_period(jnp.linspace(0, jnp.pi, 5), R=0.25, g=9.81)
    np.testing.assert_allclose(T, 4 * np.pi * np.sqrt(0.25 / 9.81), rtol=1e-15)
    assert T.shape == (5,)


def test_cycloid_position_and_coordinates():
    theta = jnp.linspace(0.1, 2 * jnp.pi - 0.1, 7)
    x, z = cycloid.position(theta, R=2.0)
    np.testing.assert_allclose(x, 2.0 * (theta - np.sin(theta)), rtol=1e-14)
    np.testing.assert_allclose(z, 2.0 * (1 - np.cos(theta)), rtol=1e-12)
    np.testing.assert_allclose(
        cycloid.theta_from_u(jnp.cos(theta / 2)), theta, rtol=1e-12
    )
