import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax.systems import cycloid


R, g = 1.5, 9.81
phi_cycloid = lambda u, t: 2 * jnp.arccos(u)


def _second_derivative_along(phi, u, udot, uddot, t):
    r"""$\ddot q = \frac{d^2}{dt^2}\varphi(u(t), t)$ given $(u, \dot u, \ddot u)$."""

    def qdot(u, udot, t):
        return jax.jvp(phi, (u, t), (udot, jnp.ones_like(t)))[1]

    return jax.jvp(qdot, (u, udot, t), (udot, uddot, jnp.ones_like(t)))[1]


def test_cycloid_theta_form_reparametrized_equals_u_form(key):
    L_u = lagrax.reparametrize(cycloid.lagrangian(R=R, g=g), phi_cycloid)
    L_ref = cycloid.lagrangian_u(R=R, g=g)
    ku, kv = jax.random.split(key)
    us = jax.random.uniform(ku, (16, 1), minval=-0.95, maxval=0.95)
    udots = jax.random.normal(kv, (16, 1))
    for u, udot in zip(us, udots):
        # The Lagrangians agree, and so do the accelerations: u'' = -(g/4R) u.
        np.testing.assert_allclose(L_u(u, udot, 0.0), L_ref(u, udot, 0.0), rtol=1e-12)
        uddot = lagrax.accelerations(L_u, u, udot)
        np.testing.assert_allclose(uddot, -(g / (4 * R)) * u, rtol=1e-11, atol=1e-14)
        np.testing.assert_allclose(
            uddot, lagrax.accelerations(L_ref, u, udot), rtol=1e-11, atol=1e-14
        )
        # Mapped through phi, they are the theta form's accelerations (Huygens'
        # hand-derived equation) wherever theta is off the cusp.
        t = jnp.zeros(())
        theta = phi_cycloid(u, t)
        thetadot = jax.jvp(phi_cycloid, (u, t), (udot, jnp.ones(())))[1]
        mapped = _second_derivative_along(phi_cycloid, u, udot, uddot, t)
        theta_form = lagrax.accelerations(cycloid.lagrangian(R=R, g=g), theta, thetadot)
        np.testing.assert_allclose(mapped, theta_form, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(
            mapped,
            cycloid.acceleration(theta, thetadot, R=R, g=g),
            rtol=1e-10,
            atol=1e-12,
        )


def test_cycloid_regular_at_the_cusp_in_u_only():
    # The theta form is singular at the cusp; the u form (closed form) is not, and the
    # reparametrized form is regular right up to it.
    with pytest.raises(ValueError, match="singular"):
        lagrax.accelerations(
            cycloid.lagrangian(R=R, g=g), jnp.array([0.0]), jnp.array([0.0])
        )
    L_u = lagrax.reparametrize(cycloid.lagrangian(R=R, g=g), phi_cycloid)
    u = jnp.array([1 - 1e-6])
    np.testing.assert_allclose(
        lagrax.accelerations(L_u, u, jnp.array([0.0])), -(g / (4 * R)) * u, rtol=1e-6
    )


def _rotation(angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.array([[c, -s], [s, c]])


def test_explicit_time_rotating_frame_against_hand_derivation(key):
    # Inertial frame: a particle in an anisotropic, anharmonic potential. Rotating
    # frame x = Rot(theta(t)) u with theta = w t + a t^2 / 2 (angular acceleration a).
    m, k1, k2, c4 = 1.3, 2.0, 0.5, 0.2
    w, a = 0.7, 0.3

    def V(x):
        return 0.5 * (k1 * x[0] ** 2 + k2 * x[1] ** 2) + c4 * x[0] ** 2 * x[1] ** 2

    def L_inertial(x, xdot, t):
        return 0.5 * m * jnp.dot(xdot, xdot) - V(x)

    def phi(u, t):
        return _rotation(w * t + 0.5 * a * t**2) @ u

    L_rot = lagrax.reparametrize(L_inertial, phi)
    J = jnp.array([[0.0, -1.0], [1.0, 0.0]])
    keys = jax.random.split(key, 3)
    us = jax.random.normal(keys[0], (8, 2))
    udots = jax.random.normal(keys[1], (8, 2))
    ts = jax.random.uniform(keys[2], (8,), maxval=5.0)
    for u, udot, t in zip(us, udots, ts):
        # By hand: x'' = Rot (u'' + 2 th' J u' + th'' J u - th'^2 u), m x'' = -grad V.
        th_dot = w + a * t
        th_ddot = a
        Rot = _rotation(w * t + 0.5 * a * t**2)
        F = -jax.grad(V)(Rot @ u)
        hand = (
            Rot.T @ F / m - 2 * th_dot * (J @ udot) - th_ddot * (J @ u) + th_dot**2 * u
        )
        np.testing.assert_allclose(
            lagrax.accelerations(L_rot, u, udot, t), hand, rtol=1e-11, atol=1e-12
        )
    # Without the explicit time term (the angular acceleration's Euler force and the
    # d/dt of the momenta) the answer would differ: the test can fail.
    assert not np.allclose(th_ddot * (J @ u), 0.0)


def test_reparametrized_lagrangian_under_jit_and_vmap(key):
    L_u = lagrax.reparametrize(cycloid.lagrangian(R=R, g=g), phi_cycloid)
    us = jax.random.uniform(key, (5, 1), minval=-0.9, maxval=0.9)
    out = jax.jit(jax.vmap(lambda u: lagrax.accelerations(L_u, u, jnp.zeros(1))))(us)
    np.testing.assert_allclose(out, -(g / (4 * R)) * us, rtol=1e-11, atol=1e-14)
