import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

import lagrax
from lagrax.systems import cycloid, pendulum

from .helpers import counting_compiles


# One Lagrangian object per system, shared by all tests: the compiled sweep is cached
# per (L, solver, method, lanes) and shapes, so sharing keeps the suite's compile
# time down. The pendulum's "quarter" sweeps below are of N amplitudes: one program
# (more than the 256 lanes of a chunk: lanes that finish take the next amplitudes).
PENDULUM = pendulum.lagrangian()
N = 300
CYCLOID_U = cycloid.lagrangian_u()
CYCLOID_THETA = cycloid.lagrangian()


def asymmetric(q, qdot, t):
    # V = x²/2 + x³/3: a well at 0, a hump at x = -1 (V = 1/6), no mirror symmetry.
    x = q[0]
    return 0.5 * qdot[0] ** 2 - (0.5 * x**2 + x**3 / 3)


def asymmetric_reference(x0):
    """T = 2∫ dx / sqrt(2(E - V)) between the turning points, by scipy quad."""
    V = lambda x: 0.5 * x * x + x**3 / 3
    E = V(x0)
    x1 = brentq(lambda x: V(x) - E, *((1e-12, 2.0) if x0 < 0 else (-0.9999, -1e-12)))
    lo, hi = sorted([x0, x1])
    # x = lo + (hi - lo) sin²φ removes both endpoint singularities.
    f = lambda p: (
        2
        * (hi - lo)
        * np.sin(p)
        * np.cos(p)
        / np.sqrt(2 * (E - V(lo + (hi - lo) * np.sin(p) ** 2)))
    )
    return 2 * quad(f, 0, np.pi / 2, epsabs=0, epsrel=1e-13, limit=400)[0]


@pytest.mark.parametrize(
    "n,useful", [(N, 0.0), pytest.param(4096, 0.85, marks=pytest.mark.slow)]
)
def test_pendulum_accuracy(n, useful):
    a = jnp.linspace(1e-3, jnp.pi - 1e-3, n)
    res = lagrax.sweep_periods(PENDULUM, a, method="quarter")
    assert np.all(np.asarray(res.status) == 0)
    err = np.abs(np.asarray(res.periods / pendulum.period(a)) - 1)
    assert err.max() <= 1e-12
    assert useful < float(res.useful_fraction) <= 1


@pytest.mark.slow
def test_pendulum_half_period_accuracy_benchmark_range():
    # "half" integrates past the bottom, where one rounding of θ̇ costs ~4δE/δ² of T:
    # fine to 1e-12 on the benchmark's 0.01–3.1 rad, not at π − 1e-3 (see `period`).
    a = jnp.linspace(0.01, 3.1, 512)
    res = lagrax.sweep_periods(PENDULUM, a, rtol=1e-14, atol=1e-14)
    err = np.abs(np.asarray(res.periods / pendulum.period(a)) - 1)
    assert err.max() <= 1e-12


def test_cycloid_to_the_cusp_in_u():
    # Amplitude a = π − θ0 (rolling angle from the bottom), u0 = cos(θ0/2) = sin(a/2);
    # the last one is released exactly at the cusp, u0 = 1.
    amplitude = jnp.linspace(1e-3, jnp.pi, 256)
    u0 = jnp.sin(amplitude / 2)
    assert u0[-1] == 1.0
    res = lagrax.sweep_periods(CYCLOID_U, u0)
    assert np.all(np.asarray(res.status) == 0)
    err = np.abs(np.asarray(res.periods) / float(cycloid.period()) - 1)
    assert err.max() <= 1e-12


# A program of its own (Dopri8: the θ form's Taylor program is too large to unroll).
# Every time in tests/test_estimate.py, on the default program: the cusp's status,
# failures near it as NaN (test_cusp_in_theta_names_the_coordinate_singularity) and
# 4π to 1e-11 from 0.5 to 3.0 (test_a_varying_mass_is_solved_again).
@pytest.mark.slow
def test_cycloid_theta_near_cusp_is_a_status_not_a_number():
    theta0 = jnp.array([0.0, 1e-12, 1e-8, 0.5, jnp.pi / 2])
    res = lagrax.sweep_periods(CYCLOID_THETA, theta0, max_steps=2048)
    status = np.asarray(res.status)
    # At the cusp the mass matrix is exactly singular.
    assert status[0] == lagrax._period.period.SINGULAR_MASS
    # Closer than float64 can turn around: a failure, never a number.
    assert np.all(status[1:3] != 0)
    assert np.all(np.isnan(np.asarray(res.periods[:3])))
    # Where the θ form is regular it agrees with 4π√(R/g).
    assert np.all(status[3:] == 0)
    np.testing.assert_allclose(res.periods[3:], 4 * np.pi, rtol=1e-11)


# A program of its own. The same well and kernel every time in tests/test_estimate.py
# (test_asymmetric_well_to_099_of_its_hump[taylor]: 64 releases on both sides, to 0.99
# of the hump, each within 1e-12 of its 40-digit period).
@pytest.mark.slow
def test_asymmetric_well_against_quadrature():
    # The last release is on the other side of the orbit of the second (one sweep).
    V = lambda x: 0.5 * x * x + x**3 / 3
    partner = brentq(lambda x: V(x) - V(-0.5), 1e-9, 2.0)
    x0 = np.array([-0.9, -0.5, -0.1, 0.2, 0.45, partner])
    res = lagrax.sweep_periods(asymmetric, jnp.asarray(x0))
    assert np.all(np.asarray(res.status) == 0)
    ref = np.array([asymmetric_reference(x) for x in x0[:5]])
    np.testing.assert_allclose(res.periods[:5], ref, rtol=1e-11)
    # Released on both sides of the same orbit: the same period.
    np.testing.assert_allclose(res.periods[1], res.periods[5], rtol=1e-12)


@pytest.mark.slow
def test_full_and_quarter_methods():
    x0 = jnp.array([-0.9, -0.5, 0.2, 0.45])
    half = lagrax.sweep_periods(asymmetric, x0)
    full = lagrax.sweep_periods(asymmetric, x0, method="full")
    np.testing.assert_allclose(full.periods, half.periods, rtol=1e-11)
    # "quarter" assumes mirror symmetry: this well has none, and every lane says so
    # (`not_symmetric`) instead of returning a wrong number.
    quarter = lagrax.sweep_periods(asymmetric, x0, method="quarter")
    assert np.all(np.asarray(quarter.status) == lagrax._results.NOT_SYMMETRIC)
    assert np.all(np.isnan(np.asarray(quarter.periods)))


def test_quarter_checks_symmetry_across_the_swing():
    # V = x²/2 + ε x³ (x² - 1) is asymmetric, but V(-1) = V(1): released at 1, the
    # mirror image of the release point IS the far turning point, and a test of the
    # turning point alone let "quarter" report a period 4% off as a success.
    eps = 0.1

    def L(q, qd, t):
        x = q[0]
        return 0.5 * qd[0] ** 2 - (0.5 * x**2 + eps * x**3 * (x**2 - 1.0))

    q0 = jnp.array([1.0, 0.7])
    # (The check is the method's, whatever steps: Dopri8 compiles this quintic's
    # programs in a third of the Taylor step's time.)
    dopri8 = dict(solver=dfx.Dopri8())
    quarter = lagrax.sweep_periods(L, q0, method="quarter", **dopri8)
    assert np.all(np.asarray(quarter.status) == lagrax._results.NOT_SYMMETRIC)
    assert np.all(np.isnan(np.asarray(quarter.periods)))
    assert "mirror" in quarter.messages()[0]
    matched = lagrax.sweep_periods(L, q0, **dopri8)
    ref = [float(lagrax.quadrature_period(L, float(x)).periods) for x in q0]
    np.testing.assert_allclose(matched.periods, ref, rtol=1e-12)


# Another order of the lanes, bit for bit the same outputs, failing lanes included,
# every time in tests/test_faults.py::test_results_independent_of_chunk_size_and_order;
# here (two programs of chunk 8) with -m slow.
@pytest.mark.slow
def test_sorted_lanes_return_in_input_order():
    # The lanes run in order of decreasing |q0| (`sort=True`, the default); the
    # outputs come back in input order, bit for bit those of the unsorted run (a
    # lane's arithmetic does not depend on its place), the failing lane included.
    rng = np.random.default_rng(3)
    q0 = rng.permutation(np.concatenate([np.linspace(0.05, 3.0, 40), [0.0]]))
    q0 = jnp.asarray(q0)
    a = lagrax.sweep_periods(PENDULUM, q0, lanes=8)
    b = lagrax.sweep_periods(PENDULUM, q0, lanes=8, sort=False)
    pairs = [(a.periods, b.periods), (a.status, b.status), (a.num_steps, b.num_steps)]
    for x, y in pairs:
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(
        np.asarray(a.error_estimate), np.asarray(b.error_estimate)
    )
    ok = np.asarray(q0) != 0
    assert np.all(np.asarray(a.status)[ok] == 0)
    assert np.asarray(a.status)[~ok][0] == lagrax._period.period.NOT_OSCILLATING
    exact = lagrax.systems.pendulum.period(q0[ok], r=1.0, g=1.0)
    np.testing.assert_allclose(np.asarray(a.periods)[ok], exact, rtol=1e-12)
    # The estimate bounds the error with lanes refilled (chunk 8 of 41).
    err = np.abs(np.asarray(a.periods)[ok] / np.asarray(exact) - 1)
    assert np.all(np.asarray(a.error_estimate)[ok] >= err)


def test_status_codes_at_release():
    q0 = jnp.linspace(0.5, 1.0, N).at[:2].set(jnp.array([0.0, jnp.nan]))
    res = lagrax.sweep_periods(PENDULUM, q0, method="quarter")
    status = np.asarray(res.status)
    assert list(status[:2]) == [
        lagrax._period.period.NOT_OSCILLATING,  # released at the equilibrium
        lagrax._period.period.NONFINITE_INPUT,
    ]
    assert np.all(status[2:] == 0)
    assert np.all(np.isnan(np.asarray(res.periods[:2])))


@pytest.mark.slow
def test_status_codes_along_the_way():
    inverted = lambda q, qdot, t: 0.5 * qdot[0] ** 2 + 0.5 * q[0] ** 2
    res = lagrax.sweep_periods(inverted, jnp.array([1.0, 0.5]))
    assert list(np.asarray(res.status)) == [lagrax._period.period.NOT_OSCILLATING] * 2
    few = lagrax.sweep_periods(PENDULUM, jnp.array([1.0, 2.0]), max_steps=2)
    assert np.all(np.asarray(few.status) == lagrax._results.MAX_STEPS)
    assert np.all(np.isnan(np.asarray(few.periods)))
    # A spring stiffening in time does not conserve energy: the check catches it.
    stiffening = lambda q, qdot, t: 0.5 * qdot[0] ** 2 - 0.5 * (1 + 0.1 * t) * q[0] ** 2
    res = lagrax.sweep_periods(stiffening, jnp.array([1.0, 2.0]))
    assert np.all(np.asarray(res.status) == lagrax._results.ENERGY_DRIFT)


def test_failed_lane_does_not_change_the_others():
    # Two lanes of the middle spoiled: the others run in other places of the queue.
    a = jnp.linspace(0.1, 3.0, N)
    clean = lagrax.sweep_periods(PENDULUM, a, method="quarter")
    spoiled = lagrax.sweep_periods(
        PENDULUM, a.at[150:152].set(jnp.array([jnp.nan, 0.0])), method="quarter"
    )
    keep = np.r_[0:150, 152:N]
    np.testing.assert_array_equal(
        np.asarray(spoiled.periods)[keep], np.asarray(clean.periods)[keep]
    )
    assert list(np.asarray(spoiled.status)[150:152]) == [7, 1]
    assert np.all(np.asarray(spoiled.status)[keep] == 0)


# Chunk sizes and orders, failures included, run every time in tests/test_faults.py.
@pytest.mark.slow
def test_lanes_and_order_independence():
    a = jax.random.uniform(jax.random.key(0), (200,), minval=0.1, maxval=3.0)
    big = lagrax.sweep_periods(PENDULUM, a, method="quarter")
    small = lagrax.sweep_periods(PENDULUM, a, method="quarter", lanes=64)
    np.testing.assert_allclose(small.periods, big.periods, rtol=1e-15)
    assert big.lane_steps_executed >= big.lane_steps_useful
    # The result comes back in the input order.
    np.testing.assert_allclose(big.periods, pendulum.period(a), rtol=1e-12, atol=0)


def test_no_recompilation_when_amplitudes_or_tolerances_change():
    a = jnp.linspace(0.2, 2.0, N)
    b = jax.block_until_ready(a * 1.1)  # outside the window: `*` compiles too
    lagrax.sweep_periods(PENDULUM, a, method="quarter", rtol=1e-10, atol=1e-10)
    with counting_compiles() as compiles:
        res = lagrax.sweep_periods(
            PENDULUM, b, method="quarter", rtol=1e-11, atol=1e-12
        )
        jax.block_until_ready(res)
        assert compiles() == 0
    np.testing.assert_allclose(res.periods, pendulum.period(b), rtol=1e-9)


@pytest.mark.slow  # reverse mode through the solve: ~40 s of compile on 2 cores
def test_grad_of_period_matches_exact_derivative():
    a = jnp.array([0.3, 1.0, 2.5])
    grad = jax.grad(
        lambda x: lagrax.sweep_periods(PENDULUM, x, method="quarter").periods.sum()
    )(a)
    exact = jax.vmap(jax.grad(pendulum.period))(a)
    np.testing.assert_allclose(grad, exact, rtol=1e-10)


@pytest.mark.slow
def test_grad_with_respect_to_parameters_and_cycloid():
    dT_dg = jax.grad(lambda g: lagrax.period(pendulum.lagrangian(g=g), 1.0))(2.0)
    exact = jax.grad(lambda g: pendulum.period(1.0, g=g))(2.0)
    np.testing.assert_allclose(dT_dg, exact, rtol=1e-10)
    dT_da = jax.grad(lambda a: lagrax.period(PENDULUM, a, method="quarter"))(1.0)
    np.testing.assert_allclose(dT_da, jax.grad(pendulum.period)(1.0), rtol=1e-10)
    for u0 in (0.3, 0.9, 1.0):
        assert abs(float(jax.grad(lambda u: lagrax.period(CYCLOID_U, u))(u0))) < 1e-10


@pytest.mark.slow
def test_period_eager_and_jit():
    T = lagrax.period(PENDULUM, 1.0)
    np.testing.assert_allclose(T, pendulum.period(1.0), rtol=1e-12)
    Tj = jax.jit(lambda a: lagrax.period(PENDULUM, a))(jnp.array([1.0]))
    np.testing.assert_allclose(Tj, T, rtol=1e-15)
    with pytest.raises(RuntimeError, match="not_oscillating"):
        lagrax.period(PENDULUM, 0.0)
    assert np.isnan(lagrax.period(PENDULUM, 0.0, throw=False))


def test_loop_carries_the_state_the_step_reads_exactly():
    """The loop carries the fields the Taylor step reads as one array between
    iterations (one input of the step's fusion): every field comes back bit for
    bit, signed zeros and non-finite values included, and the others untouched."""
    from lagrax._period.events import Search
    from lagrax._period.lane import Lane
    from lagrax._period.loop import _pack_state, _unpack_state

    W = 8
    rng = np.random.default_rng(0)
    special = np.array([-0.0, np.inf, -np.inf, np.nan])
    count = iter(range(100))

    def f():
        col = rng.standard_normal(W) * 10.0 ** next(count)
        col[rng.integers(W)] = special[next(count) % 4]
        return jnp.asarray(col)

    ints = lambda: jnp.asarray(rng.integers(-5, 5, W), jnp.int32)
    bools = lambda: jnp.asarray(rng.integers(0, 2, W), bool)
    search = Search(bools(), f(), f(), f(), f(), f(), f(), f(), ints())
    lane = Lane(
        p=jnp.asarray(rng.standard_normal((8, W))),
        idx=ints(),
        done=bools(),
        raw=ints(),
        sigma=f(),
        s=f(),
        x=f(),
        v=f(),
        a=f(),
        h=f(),
        steps=ints(),
        search=search,
        sums=jnp.asarray(rng.standard_normal((W, 5))),
    )
    packed = _pack_state(lane)
    assert (
        sum(np.ndim(y) > 0 and np.shape(y)[0] > W for y in jax.tree.leaves(packed)) == 1
    )
    back = _unpack_state(packed)
    before, tree = jax.tree.flatten(lane)
    after, tree_back = jax.tree.flatten(back)
    assert tree == tree_back
    for u, w in zip(before, after):
        u, w = np.asarray(u), np.asarray(w)
        assert u.dtype == w.dtype and u.shape == w.shape
        assert np.array_equal(u.view(np.uint8), w.view(np.uint8))
