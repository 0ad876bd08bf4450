"""The built-in systems: their exact references, and the one shape every module has."""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.special import ellipkm1

import lagrax
from lagrax.systems import cycloid, pendulum


def test_pendulum_period_against_elliptic_integral():
    theta0 = np.concatenate([np.geomspace(1e-6, 1.0, 30), np.linspace(1.0, 3.14, 60)])
    r, g = 0.7, 9.81
    # K(m) through 1 − m = cos²(θ0/2): forming m = sin² first loses digits near π.
    want = 4 * np.sqrt(r / g) * ellipkm1(np.cos(theta0 / 2) ** 2)
    got = pendulum.period(jnp.asarray(theta0), r=r, g=g)
    np.testing.assert_allclose(got, want, rtol=3e-15)


def test_pendulum_period_known_ratios():
    # Published values: T/T0 = 1.180340599 at 90°, 3.901065160 at 179°.
    T0 = pendulum.small_amplitude_period()
    ratios = pendulum.period(jnp.deg2rad(jnp.array([90.0, 179.0]))) / T0
    np.testing.assert_allclose(ratios, [1.180340599, 3.901065160], atol=1e-9)


def test_pendulum_period_edges():
    T = pendulum.period(jnp.array([0.0, -0.5, 0.5, jnp.pi, 4.0]))
    assert T[0] == pytest.approx(2 * np.pi, rel=1e-15)
    assert T[1] == T[2]
    assert np.all(np.isinf(T[3:]))


def test_pendulum_period_gradient():
    theta0 = 1.3
    grad = jax.grad(lambda a: pendulum.period(a))(theta0)
    h = 1e-5
    fd = (pendulum.period(theta0 + h) - pendulum.period(theta0 - h)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-8)


def test_cycloid_period_isochronous():
    T = cycloid.period(jnp.linspace(0, jnp.pi, 5), R=0.25, g=9.81)
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


# Every system module has the same shape: one test covers them all. Per system:
# parameters away from the defaults, the number of coordinates, and the range of q
# where its hand-derived equation holds (off the poles, off the cusp).
SHAPE = {
    "asymmetric_well": (dict(m=1.3, k=0.7, a=0.4), 1, (-1.0, 1.0)),
    "charged_particle": (
        dict(m=1.3, charge=-0.7, B=(0.2, -0.4, 1.1), E=(0.3, 0.1, -0.2)),
        3,
        (-2.0, 2.0),
    ),
    "cycloid": (dict(m=1.3, R=0.7, g=9.81), 1, (0.2, 6.0)),
    "damped_pendulum": (dict(m=1.3, l=0.7, g=9.81, b=0.3, c=0.2), 1, (-3.0, 3.0)),
    "double_pendulum": (dict(m1=1.3, m2=0.6, l1=0.7, l2=1.1, g=9.81), 2, (-3.0, 3.0)),
    "driven_pendulum": (
        dict(m=1.3, l=0.7, g=9.81, ax=0.1, ay=0.2, omega=5.0),
        1,
        (-3.0, 3.0),
    ),
    "pendulum": (dict(m=1.3, r=0.7, g=9.81), 1, (-3.0, 3.0)),
    "rectilinear": (dict(potential=lambda x: x**4 - jnp.cos(x), m=1.3), 1, (-2, 2)),
    "rotating_hoop": (dict(m=1.3, R=0.7, Omega=4.0, g=9.81), 1, (-3.0, 3.0)),
    "sphere": (dict(m=1.3, R=0.7, g=9.81), 2, (0.3, 2.8)),
    "spherical_pendulum": (dict(m=1.3, l=0.7, g=9.81), 2, (0.3, 2.8)),
}


def test_every_system_is_listed():
    assert sorted(SHAPE) == sorted(lagrax.systems.SYSTEMS)


@pytest.mark.parametrize("name", sorted(SHAPE))
def test_system_module_shape(name, key):
    module = lagrax.systems.SYSTEMS[name]
    params, n, (lo, hi) = SHAPE[name]
    defaults = lagrax.systems.parameters(name)
    # Every parameter has a default, and the test sets every one of them.
    assert set(defaults) == set(params)
    assert callable(module.lagrangian())  # the defaults are accepted
    lagrangian_params = {k: v for k, v in params.items() if k in ("b", "c")}
    L = module.lagrangian(
        **{k: v for k, v in params.items() if k not in lagrangian_params}
    )
    force = None
    if hasattr(module, "force"):
        force_keys = inspect.signature(module.force).parameters
        force = module.force(**{k: v for k, v in params.items() if k in force_keys})
    kq, kv = jax.random.split(key)
    q = jax.random.uniform(kq, (20, n), minval=lo, maxval=hi)
    qdot = jax.random.normal(kv, (20, n))
    t = jnp.linspace(0.0, 2.0, 20)
    # (Under jit: one program each, not one per primitive.)
    got = jax.jit(
        jax.vmap(lambda a, b, s: lagrax.accelerations(L, a, b, s, force=force))
    )(q, qdot, t)
    want = jax.jit(jax.vmap(lambda a, b, s: module.acceleration(a, b, s, **params)))(
        q, qdot, t
    )
    assert want.shape == (20, n)
    np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11)
    if hasattr(module, "period"):
        # Against the quadrature oracle, from the same Lagrangian.
        amplitude = jnp.array([0.4, 1.3, 2.5])
        q0 = amplitude if name != "cycloid" else jnp.pi - amplitude
        oracle = lagrax.quadrature_period(L, q0).periods
        np.testing.assert_allclose(
            module.period(amplitude, **params), oracle, rtol=1e-12
        )


def test_accelerations_of_one_coordinate_take_qdot_and_t_optionally():
    a = jnp.array([0.3, 1.7])
    np.testing.assert_array_equal(
        pendulum.acceleration(a, r=0.7, g=9.81), -(9.81 / 0.7) * jnp.sin(a)
    )
    F = lambda x: -4 * x**3
    np.testing.assert_allclose(
        lagrax.systems.rectilinear.acceleration(a, force_x=F, m=2.0),
        lagrax.systems.rectilinear.acceleration(a, potential=lambda x: x**4, m=2.0),
        rtol=1e-14,
    )


def test_parameters_unknown_system():
    with pytest.raises(ValueError, match="`system` must be one of"):
        lagrax.systems.parameters("pendulm")


@pytest.mark.parametrize(
    "name",
    [n for n, m in sorted(lagrax.systems.SYSTEMS.items()) if hasattr(m, "SWEEP")],
)
def test_sweep_spec_releases_where_the_period_says(name):
    # What `lagrax sweep NAME` integrates (SWEEP.lagrangian at SWEEP.release_point of
    # the amplitude) has the module's own exact period at that amplitude.
    module = lagrax.systems.SYSTEMS[name]
    spec = module.SWEEP
    assert isinstance(spec, lagrax.systems.SweepSpec)
    assert spec.method in ("matched", "quarter", "half", "full")
    lo, hi = spec.amplitudes() if callable(spec.amplitudes) else spec.amplitudes
    if spec.bounds is not None:
        assert spec.bounds[0] < lo < hi <= spec.bounds[1]
    if not hasattr(module, "period"):
        return
    amplitude = np.array([lo + 0.3 * (hi - lo), lo + 0.9 * (hi - lo)])
    q0 = amplitude if spec.release_point is None else spec.release_point(amplitude)
    L = (spec.lagrangian or module.lagrangian)(g=9.81)
    # A quarter period from rest to the bottom (q̈ = 0), by SciPy: quick to set up,
    # and independent of lagrax's own period machinery.
    qddot = jax.jit(lambda q: lagrax.accelerations(L, q[None], jnp.zeros(1))[0])
    rhs = lambda t, y: [y[1], float(qddot(y[0]))]
    bottom = lambda t, y: float(qddot(y[0]))
    bottom.terminal = True
    for a, q in zip(amplitude, q0):
        sol = solve_ivp(rhs, (0, 100), [q, 0.0], "DOP853", rtol=1e-12, atol=1e-12,
                        events=bottom)  # fmt: skip
        T = 4 * sol.t_events[0][0]
        np.testing.assert_allclose(module.period(a, g=9.81), T, rtol=1e-9)
