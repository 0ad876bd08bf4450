"""`lagrax.Taylor` in the period kernel: accuracy against exact periods, every method,
failing lanes, gradients and errors."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax._results import NONFINITE_INPUT, NOT_OSCILLATING
from lagrax.systems import cycloid, pendulum
from tests.test_period import asymmetric, asymmetric_reference


PENDULUM = pendulum.lagrangian()
TAYLOR = lagrax.Taylor()
AMPS = jnp.linspace(0.05, 3.05, 48)


def _sweep(L, q0, **kw):
    kw = dict(dict(solver=TAYLOR, rtol=1e-13, atol=1e-13, lanes=16), **kw)
    return lagrax.sweep_periods(L, q0, **kw)


# "matched" (the default method) with its error estimate (the default too):
# test_estimate_bounds_error below, with -m slow.
@pytest.mark.parametrize("method", ["quarter", "half"])
def test_pendulum_periods_exact(method):
    res = _sweep(PENDULUM, AMPS, method=method, error_estimate=False)
    assert np.all(np.asarray(res.status) == 0)
    err = np.abs(np.asarray(res.periods) / np.asarray(pendulum.period(AMPS)) - 1)
    # "half" integrates through the bottom of the swing (amplified near the
    # separatrix, as with any solver); "quarter" stays at the tolerance.
    assert np.max(err) < (1e-11 if method == "half" else 1e-12), np.max(err)


def test_events_are_located_inside_the_crossing_step(monkeypatch):
    """Each event is located in the step that crosses it, from the step's own
    polynomials (no trial steps): ~5 steps per quarter period of the pendulum at rtol
    1e-14 (with trials, as before: ~9). With the polynomial root made useless (no
    Newton iterations: its last correction is then far above round-off), every lane
    falls back to trials from the located estimate, and gets the same periods to
    round-off, in more steps."""
    q0 = AMPS  # (the shape and options of the "quarter" sweep above; rtol is traced)
    exact = np.asarray(pendulum.period(q0))
    kw = dict(method="quarter", rtol=1e-14, atol=1e-14, error_estimate=False)
    fast = _sweep(PENDULUM, q0, **kw)
    steps = np.asarray(fast.num_steps)
    assert steps.mean() < 6.0, steps.mean()
    import lagrax._period.events as events_module

    monkeypatch.setattr(events_module, "_ROOT_LOW_ITERS", 0)
    monkeypatch.setattr(events_module, "_ROOT_FULL_ITERS", 0)
    # A new body (compiled programs are keyed on L's jaxpr, not on the function
    # object): the kernel is traced again with the constants above. Negating twice
    # is exact, so the equations of motion are the pendulum's.
    slow = _sweep(lambda q, qd, t: -(-PENDULUM(q, qd, t)), q0, **kw)
    assert np.all(np.asarray(slow.status) == 0)
    assert np.asarray(slow.num_steps).mean() > steps.mean() + 1
    for res in (fast, slow):
        err = np.abs(np.asarray(res.periods) / exact - 1)
        assert err.max() < 1e-14, err.max()


def test_first_step_from_rest_not_too_long():
    """From rest the odd coefficients of x(s) vanish; a step length from the last two
    orders then rested on one coefficient that crosses zero near q0 = 2.23692 (the
    period was off by 1.8e-9 at rtol 1e-13). The last four orders keep it honest.
    (As many release points as AMPS: the same compiled sweep.)"""
    q0 = jnp.linspace(2.2360, 2.2378, AMPS.shape[0])
    res = _sweep(PENDULUM, q0, method="quarter", error_estimate=False)
    err = np.abs(np.asarray(res.periods) / np.asarray(pendulum.period(q0)) - 1)
    assert np.max(err) < 1e-12, err


# The theta-form cycloid's order-20 program is too large to unroll: compiling the
# looped kernel is the cost. The asymmetric well with Taylor() is checked every time in
# tests/test_estimate.py, and the looped kernel against the unrolled one in
# tests/test_taylor.py.
@pytest.mark.slow
def test_cycloid_isochronous_and_asymmetric_well():
    L = cycloid.lagrangian()
    q0 = jnp.linspace(0.3, 3.0, 12)  # theta from the bottom at pi: both sides
    res = _sweep(L, jnp.pi + q0 - 1.5, method="matched")
    T = np.asarray(res.periods)
    assert np.all(np.asarray(res.status) == 0)
    assert np.max(np.abs(T / (4 * np.pi) - 1)) < 1e-12
    x0 = np.array([-0.6, -0.3, 0.2, 0.4])
    res = _sweep(asymmetric, jnp.asarray(x0), method="matched")
    ref = np.array([asymmetric_reference(x) for x in x0])
    assert np.all(np.asarray(res.status) == 0)
    assert np.max(np.abs(np.asarray(res.periods) / ref - 1)) < 1e-10


# A program of its own. Taylor, "matched", the estimate at rtol 1e-13 runs every time
# in tests/test_estimate.py (test_pendulum_default_method_meets_1e12_with_bounded_
# estimates[taylor]: 256 amplitudes to 3.1, error <= 1e-12 <= estimate), and with a
# chunk smaller than the sweep (lanes refilled) in tests/test_period.py
# (test_sorted_lanes_return_in_input_order: chunk 8, estimate >= error).
@pytest.mark.slow
def test_estimate_bounds_error():
    # "matched": the periods exact to the tolerance, and the estimate above the error.
    # (Without the estimate: tests/test_estimate.py, on the pendulum up to π - 1e-3.)
    res = _sweep(PENDULUM, AMPS, method="matched", error_estimate=True)
    err = np.abs(np.asarray(res.periods) / np.asarray(pendulum.period(AMPS)) - 1)
    est = np.asarray(res.error_estimate)
    assert np.all(np.asarray(res.status) == 0)
    assert np.max(err) < 1e-12, np.max(err)
    assert np.all(est >= err), np.min(est / np.maximum(err, 1e-300))


def test_failing_lanes_leave_others_alone():
    # AMPS with two lanes spoiled (the shape and options of the sweeps above: their
    # compiled program); the others in other chunks than without the spoiled ones.
    bad = AMPS.at[jnp.array([1, 30])].set(jnp.array([jnp.nan, 0.0]))
    a = _sweep(PENDULUM, AMPS, method="quarter", error_estimate=False)
    b = _sweep(PENDULUM, bad, method="quarter", error_estimate=False)
    st = np.asarray(b.status)
    assert st[1] == NONFINITE_INPUT and st[30] == NOT_OSCILLATING
    assert np.isnan(np.asarray(b.periods)[[1, 30]]).all()
    good = np.ones(AMPS.shape[0], bool)
    good[[1, 30]] = False
    assert np.all(st[good] == 0)
    np.testing.assert_array_equal(
        np.asarray(b.periods)[good], np.asarray(a.periods)[good]
    )


# A one-lane program of its own: `period` with Taylor (the default solver) within
# 1e-12 of the exact period runs every time in tests/test_estimate.py
# (test_period_returns_its_estimate_on_request).
@pytest.mark.slow
def test_period_matches_exact():
    q0 = jnp.asarray(1.3)
    T = lagrax.period(PENDULUM, q0, solver=TAYLOR, method="quarter", rtol=1e-13)
    assert abs(float(T) / float(pendulum.period(q0)) - 1) < 1e-12


@pytest.mark.slow  # ~35 s on one core (compiling the forward-mode kernel);
# tests/test_gradients.py checks gradients through the kernel in the default suite.
def test_gradient_matches_exact():
    q0 = jnp.asarray(1.3)
    f = lambda q: lagrax.period(
        PENDULUM, q, solver=TAYLOR, method="quarter", rtol=1e-13, error_estimate=False
    )
    dT = jax.grad(f)(q0)
    exact = jax.grad(pendulum.period)(q0)
    assert abs(float(dT) / float(exact) - 1) < 1e-8


@pytest.mark.slow  # ~25 s on one core; parameter gradients of the kernel are also
# tested in the default suite (a track's parameters, tests/test_gradients.py).
def test_gradient_with_respect_to_a_parameter():
    def T_of_g(g):
        L = pendulum.lagrangian(g=g)
        res = lagrax.sweep_periods(
            L,
            jnp.array([0.7, 2.0]),
            solver=TAYLOR,
            method="quarter",
            error_estimate=False,
            lanes=2,
        )
        return jnp.sum(res.periods)

    g = jnp.asarray(2.0)
    exact = jax.grad(lambda g: jnp.sum(pendulum.period(jnp.array([0.7, 2.0]), g=g)))(g)
    assert abs(float(jax.grad(T_of_g)(g)) / float(exact) - 1) < 1e-8


# A Dopri8 program of its own. Every time in tests/test_estimate.py
# (test_the_default_steps_with_taylor_where_it_can): a plain Taylor() names `erf`, and
# the default falls back to Dopri8, every lane a success.
@pytest.mark.slow
def test_unsupported_primitive_is_named():
    def L(q, qdot, t):
        return 0.5 * qdot[0] ** 2 - jax.lax.erf(q[0]) * q[0]

    with pytest.raises(NotImplementedError, match="erf"):
        _sweep(L, jnp.array([0.5]), method="quarter", error_estimate=False)
    # A diffrax solver handles the same Lagrangian.
    res = lagrax.sweep_periods(L, jnp.array([0.5]), method="quarter")
    assert int(res.status[0]) == 0


@pytest.mark.parametrize(
    "kwargs, exc",
    [
        (dict(order=1), ValueError),
        (dict(order=2.5), TypeError),
        (dict(order=True), TypeError),
        (dict(max_step=0.0), ValueError),
        (dict(max_step=float("inf")), ValueError),
        (dict(fallback=3), TypeError),
        (dict(fallback=lagrax.Taylor()), TypeError),
        (dict(fallback=dfx.Kvaerno5()), TypeError),
    ],
)
def test_bad_taylor_arguments(kwargs, exc):
    with pytest.raises(exc, match=f"`{next(iter(kwargs))}`"):
        lagrax.Taylor(**kwargs)


# The Taylor step's constant was the fault: Taylor every time, Dopri8 with -m slow
# (a float32 program each).
@pytest.mark.parametrize(
    "solver",
    [TAYLOR, pytest.param(dfx.Dopri8(), marks=pytest.mark.slow)],
    ids=["taylor", "dopri8"],
)
def test_float32_release_points_stay_float32(solver):
    # A float32 sweep under x64: the Taylor step's constant was a NumPy float64
    # scalar, which promoted the loop's carry to float64 (a while_loop type error).
    a = jnp.linspace(0.1, 3.0, 16, dtype=jnp.float32)
    res = lagrax.sweep_periods(PENDULUM, a, solver=solver, rtol=1e-5, atol=1e-5)
    assert res.periods.dtype == jnp.float32
    assert np.all(np.asarray(res.status) == 0)
    exact = np.asarray(pendulum.period(np.asarray(a, np.float64)))
    assert np.max(np.abs(np.asarray(res.periods, np.float64) / exact - 1)) < 1e-5
