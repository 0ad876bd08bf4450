"""The default method and the per-lane error estimate keep their promise.

For every successful lane of sweeps with exact (or oracle) periods, the estimate is at
least the true relative error and not more than ~100 times it (the true error floored
at 1e-14, where the estimate's own rounding floor of 64 ulps sits); lanes the estimate
cannot certify to 100 rtol are reported, never returned as numbers. And the statuses
that name a cause: a coordinate singularity on the path, a well that is not
mirror-symmetric for method "quarter".
"""

import diffrax as dfx
import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

import lagrax
from lagrax._results import (
    COORDINATE_SINGULARITY,
    NOT_SYMMETRIC,
    SINGULAR_MASS,
    SUCCESS,
    TOLERANCE_NOT_MET,
)
from lagrax.systems import asymmetric_well, cycloid, pendulum


PENDULUM = pendulum.lagrangian()
WELL = asymmetric_well.lagrangian()
FLOOR = 1e-14


def _check_bound(res, exact, *, spread=100.0):
    T = np.asarray(res.periods)
    est = np.asarray(res.error_estimate)
    ok = np.asarray(res.status) == SUCCESS
    assert ok.sum() > 0
    true = np.abs(T[ok] / np.asarray(exact)[ok] - 1)
    assert np.all(est[ok] >= true), (est[ok] / np.maximum(true, 1e-300)).min()
    assert np.all(est[ok] <= spread * np.maximum(true, FLOOR))
    # A lane that is not a success has no number, whatever its estimate.
    assert np.all(np.isnan(T[~ok]))
    return true


def test_pendulum_default_method_meets_1e12_with_bounded_estimates():
    a = jnp.linspace(0.01, 3.1, 256)
    res = lagrax.sweep_periods(PENDULUM, a)
    assert np.all(np.asarray(res.status) == SUCCESS)
    true = _check_bound(res, pendulum.period(a))
    assert true.max() <= 1e-12


def test_pendulum_near_the_separatrix():
    # Within 1e-2 of π "half" loses up to 1.7e-9; "matched" keeps 1e-12, and the lanes
    # whose far turning point float64 cannot pin down are reported, not returned.
    a = jnp.linspace(1e-3, jnp.pi - 1e-3, 256)
    res = lagrax.sweep_periods(PENDULUM, a)
    status = np.asarray(res.status)
    assert set(np.unique(status)) <= {SUCCESS, TOLERANCE_NOT_MET}
    assert (status == SUCCESS).mean() > 0.97
    true = _check_bound(res, pendulum.period(a))
    assert true.max() <= 1e-12
    unchecked = lagrax.sweep_periods(PENDULUM, a, error_estimate=False)
    err = np.abs(np.asarray(unchecked.periods / pendulum.period(a)) - 1)
    assert err.max() <= 1e-12


def test_half_near_the_separatrix_is_caught_by_the_estimate():
    a = jnp.linspace(3.0, jnp.pi - 1e-3, 64)
    res = lagrax.sweep_periods(PENDULUM, a, method="half")
    unchecked = lagrax.sweep_periods(PENDULUM, a, method="half", error_estimate=False)
    err = np.abs(np.asarray(unchecked.periods / pendulum.period(a)) - 1)
    assert err.max() > 1e-10  # the loss the estimate has to see
    status = np.asarray(res.status)
    assert np.all(status[err > 100 * 1e-13] == TOLERANCE_NOT_MET)
    _check_bound(res, pendulum.period(a))


def test_cycloid_u_form_is_isochronous_with_bounded_estimates():
    u0 = jnp.linspace(0.05, 0.99, 64)
    res = lagrax.sweep_periods(cycloid.lagrangian_u(), u0)
    assert np.all(np.asarray(res.status) == SUCCESS)
    _check_bound(res, jnp.full_like(u0, 4 * jnp.pi))


def _hump_releases(n):
    V = lambda x: 0.5 * x**2 + x**3 / 3
    left = brentq(lambda x: V(x) - 0.99 / 6, -1, 0)
    right = brentq(lambda x: V(x) - 0.99 / 6, 0, 2)
    half = n // 2
    return jnp.concatenate(
        [jnp.linspace(left, -1e-3, half), jnp.linspace(1e-3, right, n - half)]
    )


def test_asymmetric_well_to_099_of_its_hump():
    q0 = _hump_releases(128)
    ref = lagrax.quadrature_period(WELL, q0, throw=False)
    assert np.all(np.asarray(ref.status) == SUCCESS)
    res = lagrax.sweep_periods(WELL, q0)
    assert np.all(np.asarray(res.status) == SUCCESS)
    true = _check_bound(res, ref.periods)
    assert true.max() <= 1e-12


def test_quarter_refuses_an_asymmetric_well():
    q0 = jnp.array([-0.5, 0.3, 0.45])
    res = lagrax.sweep_periods(WELL, q0, method="quarter")
    assert np.all(np.asarray(res.status) == NOT_SYMMETRIC)
    assert np.all(np.isnan(np.asarray(res.periods)))
    assert "mirror" in res.messages()[0]
    # ... and accepts the symmetric pendulum.
    res = lagrax.sweep_periods(PENDULUM, jnp.array([0.5, 2.0, 3.0]), method="quarter")
    assert np.all(np.asarray(res.status) == SUCCESS)


def test_cusp_in_theta_names_the_coordinate_singularity():
    theta0 = jnp.array([0.0, 1e-12, 1e-10, 1e-8, 1e-6, 1.0])
    for method in ("matched", "half"):
        res = lagrax.sweep_periods(cycloid.lagrangian(), theta0, method=method)
        status = np.asarray(res.status)
        assert status[0] == SINGULAR_MASS  # released exactly at the cusp
        assert np.all(status[1:5] == COORDINATE_SINGULARITY), status
        assert status[5] == SUCCESS
        assert "reparametrize" in lagrax.status_message(COORDINATE_SINGULARITY)


def test_period_returns_its_estimate_on_request():
    T, est = lagrax.period(PENDULUM, 2.0, error_estimate=True)
    true = abs(float(T / pendulum.period(2.0)) - 1)
    assert true <= float(est) <= 100 * max(true, FLOOR)
    assert float(lagrax.period(PENDULUM, 2.0)) == float(T)


# A family of wells V = x²/2 + a x³/3 + b x⁴/4 (b > 0 or a small enough to keep a
# bounded swing), compiled once: the coefficients are traced.
_q0 = jnp.array([-0.6, -0.3, -0.1, 0.1, 0.3, 0.6])


def _well(p):
    a, b = p[0], p[1]

    def L(q, qdot, t):
        x = q[0]
        return 0.5 * qdot[0] ** 2 - (0.5 * x**2 + a * x**3 / 3 + b * x**4 / 4)

    return L


_sweep = jax.jit(lambda p: lagrax.sweep_periods(_well(p), _q0))
_oracle = jax.jit(
    lambda p: lagrax.quadrature_period(_well(p), _q0, throw=False).periods
)


@pytest.mark.filterwarnings("ignore")
@hypothesis.settings(max_examples=8, deadline=None)
@hypothesis.given(
    a=st.floats(-0.8, 0.8, allow_nan=False),
    b=st.floats(0.0, 1.0, allow_nan=False),
)
def test_estimate_bounds_the_error_on_random_wells(a, b):
    p = jnp.array([a, b])
    res = _sweep(p)
    ref = _oracle(p)
    usable = np.isfinite(np.asarray(ref))
    hypothesis.assume(usable.sum() >= 3)
    T = np.asarray(res.periods)[usable]
    est = np.asarray(res.error_estimate)[usable]
    ok = np.asarray(res.status)[usable] == SUCCESS
    true = np.abs(T[ok] / np.asarray(ref)[usable][ok] - 1)
    assert np.all(est[ok] >= true)
    assert np.all(true <= 1e-11)


@pytest.mark.parametrize(
    "solver, tol, bound",
    [
        (dfx.Tsit5(), 1e-10, 1e-9),
        (dfx.Dopri5(), 1e-10, 1e-9),
        (dfx.Dopri8(), 1e-12, 1e-11),
    ],
)
def test_every_explicit_tableau_runs_the_kernel(solver, tol, bound):
    # FSAL tableaux whose last stage weighs in the error estimate (Tsit5, Dopri5) as
    # well as Dopri8, whose does not. The estimate is calibrated on Dopri8 (the
    # default) only: with the 5th-order pairs it was measured below the true error
    # on some lanes (0.47x), so only Dopri8's bound is asserted here.
    a = jnp.linspace(0.1, 3.0, 32)
    res = lagrax.sweep_periods(PENDULUM, a, solver=solver, rtol=tol, atol=tol)
    assert np.all(np.asarray(res.status) == SUCCESS)
    err = np.abs(np.asarray(res.periods / pendulum.period(a)) - 1)
    assert err.max() <= bound
    if isinstance(solver, dfx.Dopri8):
        _check_bound(res, pendulum.period(a))
