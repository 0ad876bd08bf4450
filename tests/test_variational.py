"""Variational integrators (midpoint, Gauss–Legendre 4 and 6): order, invariants,
diffrax use, failures."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import lagrax
from lagrax._trajectory.variational import _discrete_momenta
from lagrax.systems import pendulum

from .helpers import tree_allclose


PENDULUM = lagrax.systems.pendulum.lagrangian(m=1.0, r=1.0, g=1.0)


def spherical_pendulum(m=1.0, r=1.0, g=1.0):
    """q = (theta, phi), theta from the downward vertical: phi is cyclic."""

    def L(q, qdot, t):
        theta, _ = q
        kinetic = 0.5 * m * r**2 * (qdot[0] ** 2 + jnp.sin(theta) ** 2 * qdot[1] ** 2)
        return kinetic + m * g * r * jnp.cos(theta)

    return L


def double_pendulum(m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0):
    def L(q, qdot, t):
        a, b = q
        da, db = qdot
        kinetic = 0.5 * (m1 + m2) * l1**2 * da**2 + 0.5 * m2 * l2**2 * db**2
        kinetic = kinetic + m2 * l1 * l2 * da * db * jnp.cos(a - b)
        potential = -(m1 + m2) * g * l1 * jnp.cos(a) - m2 * g * l2 * jnp.cos(b)
        return kinetic - potential

    return L


def _solve(L, y0, t1, h, *, saveat=None, solver=None, t0=0.0, force=None, **kw):
    return dfx.diffeqsolve(
        lagrax.LagrangianTerm(L, force=force),
        lagrax.VariationalMidpoint() if solver is None else solver,
        jnp.asarray(t0),  # arrays, not Python floats: no recompilation per value
        jnp.asarray(t1),
        jnp.asarray(h),
        y0,
        saveat=dfx.SaveAt(t1=True) if saveat is None else saveat,
        stepsize_controller=dfx.ConstantStepSize(),
        **kw,
    )


def _reference(L, y0, t1, t0=0.0, force=None):
    return dfx.diffeqsolve(
        lagrax.LagrangianTerm(L, force=force),
        dfx.Dopri8(),
        jnp.asarray(t0),
        jnp.asarray(t1),
        0.01,
        y0,
        stepsize_controller=dfx.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100_000,
    )


def test_discrete_momenta_are_the_gradients_of_the_discrete_lagrangian():
    L = double_pendulum(m2=2.0, l2=0.7)
    q0, q1 = jnp.array([0.3, -1.2]), jnp.array([0.35, -1.1])
    t0, h = 0.2, 0.05

    def Ld(q0, q1):
        return h * L((q0 + q1) / 2, (q1 - q0) / h, t0 + h / 2)

    pm, pp = _discrete_momenta(L, None, q0, q1 - q0, t0, h)
    d0, d1 = jax.grad(Ld, argnums=(0, 1))(q0, q1)
    assert tree_allclose((pm, pp), (-d0, d1), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "L",
    [PENDULUM, pytest.param(double_pendulum(), marks=pytest.mark.slow)],
    ids=["pendulum", "double"],
)
def test_second_order_convergence(L):
    n = 1 if L is PENDULUM else 2
    y0 = (jnp.full((n,), 2.5 if n == 1 else 1.0), jnp.zeros(n))
    t1 = 4.0
    ref = _reference(L, y0, t1)
    hs = np.array([0.2, 0.1, 0.05, 0.025, 0.0125])
    errors = []
    for h in hs:
        sol = _solve(L, y0, t1, h)
        assert sol.result == dfx.RESULTS.successful
        errors.append(
            max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(sol.ys, ref.ys))
        )
    order, _ = np.polyfit(np.log(hs), np.log(errors), 1)
    assert 1.9 < order < 2.1, (order, errors)


def _energy_window_maxima(solver, h, periods, windows=10):
    T = float(pendulum.period(2.5))
    y0 = (jnp.array([2.5]), jnp.array([0.0]))
    nsteps = int(round(periods * T / h))
    sol = _solve(
        PENDULUM,
        y0,
        periods * T,
        h,
        solver=solver,
        saveat=dfx.SaveAt(steps=True),
        max_steps=nsteps + 1,
    )
    assert sol.result == dfx.RESULTS.successful
    qs, qdots = sol.ys
    keep = np.isfinite(np.asarray(sol.ts))
    energy = jax.jit(jax.vmap(lambda q, v: lagrax.energy(PENDULUM, q, v, 0.0)))(
        qs, qdots
    )
    error = np.abs(np.asarray(energy)[keep] - float(lagrax.energy(PENDULUM, *y0)))
    return np.array([w.max() for w in np.array_split(error, windows)])


def _energy_drift_check(periods):
    T = float(pendulum.period(2.5))
    h = T / 40
    # Comparable cost: the midpoint step takes ~3 Newton iterations; Tsit5 at twice
    # the step takes 6 stages per 2h, i.e. the same number of evaluations per h.
    vi = _energy_window_maxima(lagrax.VariationalMidpoint(), h, periods)
    rk = _energy_window_maxima(dfx.Tsit5(), 2 * h, periods)
    # Variational: the same bound in the last tenth of the run as in the first.
    assert vi[-1] < 1.05 * vi[0], vi
    # Explicit RK: a secular (linear) drift, several times its early error by the end.
    assert rk[-1] > 5 * rk[0], rk
    assert rk[-1] > vi[-1], (rk, vi)


def test_energy_bounded_no_drift_1e3_periods():
    _energy_drift_check(1_000)


@pytest.mark.slow
def test_energy_bounded_no_drift_1e4_periods():
    _energy_drift_check(10_000)


def test_noether_momentum_of_cyclic_coordinate_exact():
    L = spherical_pendulum()
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.2, 1.3]))
    saveat = dfx.SaveAt(steps=True, solver_state=True)
    nsteps = 2000
    sol = _solve(L, y0, nsteps * 0.05, 0.05, saveat=saveat, max_steps=nsteps)
    assert sol.result == dfx.RESULTS.successful
    qs, qdots = sol.ys
    p_phi = jax.jit(jax.vmap(lambda q, v: lagrax.momenta(L, q, v, 0.0)))(qs, qdots)[
        :, 1
    ]
    p_phi0 = float(lagrax.momenta(L, *y0, 0.0)[1])
    eps = np.finfo(np.float64).eps
    # Round-off only: a random walk of about an ulp per step, ~sqrt(2000) ulps.
    bound = 10 * np.sqrt(nsteps) * eps * abs(p_phi0)
    assert np.max(np.abs(np.asarray(p_phi) - p_phi0)) < bound
    # The momentum the scheme advances (the solver state) is carried over exactly:
    # p1 = p0 + h ∂L/∂φ(midpoint), and ∂L/∂φ is exactly 0.
    p_end = sol.solver_state[0][1]
    assert float(p_end) == float(lagrax.momenta(L, *y0, 0.0)[1])
    # An explicit solver at the same step is much further off: the test is sharp.
    rk = _solve(L, y0, nsteps * 0.05, 0.05, solver=dfx.Tsit5(), max_steps=nsteps)
    p_rk = float(lagrax.momenta(L, rk.ys[0][-1], rk.ys[1][-1], 0.0)[1])
    assert abs(p_rk - p_phi0) > 1e4 * eps * abs(p_phi0)


def test_time_reversible():
    y0 = (jnp.array([2.5]), jnp.array([0.0]))
    fwd = _solve(PENDULUM, y0, 5.0, 0.05)
    y1 = jax.tree_util.tree_map(lambda x: x[-1], fwd.ys)
    back = _solve(PENDULUM, y1, 0.0, -0.05, t0=5.0)
    assert back.result == dfx.RESULTS.successful
    y0_back = jax.tree_util.tree_map(lambda x: x[-1], back.ys)
    assert tree_allclose(y0_back, y0, rtol=0, atol=1e-10)
    # ... and not trivially: the state did move.
    assert not tree_allclose(y1, y0, rtol=0, atol=1e-2)


def test_vmap_and_saveat_match_a_python_loop():
    ts = jnp.linspace(0.0, 3.0, 7)
    q0s = jnp.array([[0.5], [1.5], [2.5]])

    @jax.jit
    @jax.vmap
    def batch(q0):
        y0 = (q0, jnp.zeros(1))
        return _solve(PENDULUM, y0, 3.0, 0.01, saveat=dfx.SaveAt(ts=ts)).ys

    qs, qdots = batch(q0s)
    assert qs.shape == (3, 7, 1)
    for i, q0 in enumerate(q0s):
        one = _solve(PENDULUM, (q0, jnp.zeros(1)), 3.0, 0.01, saveat=dfx.SaveAt(ts=ts))
        assert tree_allclose((qs[i], qdots[i]), one.ys, rtol=1e-12, atol=1e-12)
    # Saved at t=0: exactly the initial state.
    assert tree_allclose(qs[:, 0], q0s, rtol=0, atol=0)


def test_progress_meter_runs():
    sol = _solve(
        PENDULUM,
        (jnp.array([1.0]), jnp.array([0.0])),
        1.0,
        0.1,
        progress_meter=dfx.TextProgressMeter(),
    )
    assert sol.result == dfx.RESULTS.successful


def test_damping_force_and_time_dependence_converge():
    c = 0.3

    def L(q, qdot, t):  # a pendulum whose support length changes slowly in time
        r = 1.0 + 0.1 * jnp.sin(t)
        return 0.5 * r**2 * qdot[0] ** 2 + r * jnp.cos(q[0])

    def force(q, qdot, t):
        return -c * qdot

    y0 = (jnp.array([1.0]), jnp.array([0.0]))
    ref = _reference(L, y0, 3.0, force=force)
    errs = []
    for h in (0.02, 0.01):
        sol = _solve(L, y0, 3.0, h, force=force)
        errs.append(max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(sol.ys, ref.ys)))
    assert errs[0] < 1e-3
    assert 3.0 < errs[0] / errs[1] < 5.0, errs  # second order: ~4x per halving


def test_newton_failure_is_reported_not_nan_success():
    # One Newton iteration can never pass the Cauchy test (it needs two): a failure.
    y0 = (jnp.array([1.0]), jnp.array([0.0]))
    sol = _solve(
        PENDULUM,
        y0,
        1.0,
        0.1,
        solver=lagrax.VariationalMidpoint(root_find_max_steps=1),
        throw=False,
    )
    assert sol.result == dfx.RESULTS.nonlinear_max_steps_reached

    # A potential that is NaN for q < 0, crossed by a large step: Newton's iterates go
    # non-finite; the lane fails, its neighbour in the batch does not.
    def L(q, qdot, t):
        return 0.5 * qdot[0] ** 2 - 1.0 / jnp.sqrt(q[0]) + 0.0 * q[0]

    @jax.vmap
    def batch(v0):
        y0 = (jnp.array([1.0]), jnp.array([v0]))
        return _solve(L, y0, 2.0, 0.5, throw=False)

    sols = batch(jnp.array([0.1, -5.0]))
    ok = np.asarray(sols.result == dfx.RESULTS.successful)
    assert ok.tolist() == [True, False]
    assert np.all(np.isfinite(np.asarray(sols.ys[0][0])))


def test_wrong_term_is_a_clear_error():
    with pytest.raises(Exception, match="LagrangianTerm"):
        dfx.diffeqsolve(
            dfx.ODETerm(lagrax.vector_field(PENDULUM)),
            lagrax.VariationalMidpoint(),
            0.0,
            1.0,
            0.1,
            (jnp.array([1.0]), jnp.array([0.0])),
        )


def test_bad_arguments():
    for cls in (lagrax.VariationalMidpoint, lagrax.GaussLegendre4):
        with pytest.raises(ValueError, match="root_find_max_steps"):
            cls(root_find_max_steps=0)
        with pytest.raises(ValueError, match="root_find_max_steps"):
            cls(root_find_max_steps=2.5)
        with pytest.raises(TypeError, match="root_finder"):
            cls(root_finder=optx.Newton)  # the class, not an instance
        with pytest.raises(TypeError, match="root_finder"):
            cls(root_finder="newton")
    with pytest.raises(TypeError, match="L"):
        lagrax.LagrangianTerm(3.0)


# --------------------------------------------------------------- Gauss–Legendre 4, 6

GAUSS = [(lagrax.GaussLegendre4, 4), (lagrax.GaussLegendre6, 6)]
GAUSS_IDS = ["GL4", "GL6"]
# GL4 runs every time; GL6, the same checks with another tableau, with `-m slow`
# (its order is checked every time, by the convergence test).
GAUSS_CLASSES = [
    pytest.param(lagrax.GaussLegendre4, id="GL4"),
    pytest.param(lagrax.GaussLegendre6, id="GL6", marks=pytest.mark.slow),
]


@pytest.mark.parametrize(("cls", "order"), GAUSS, ids=GAUSS_IDS)
@pytest.mark.parametrize(
    "L",
    [PENDULUM, pytest.param(double_pendulum(), marks=pytest.mark.slow)],
    ids=["pendulum", "double"],
)
def test_gauss_legendre_convergence_order(cls, order, L):
    n = 1 if L is PENDULUM else 2
    y0 = (jnp.full((n,), 2.5 if n == 1 else 1.0), jnp.zeros(n))
    t1 = 4.0
    ref = _reference(L, y0, t1)
    # Errors between ~1e-4 and ~1e-11: above the reference's ~1e-13, below the
    # pre-asymptotic range.
    if order == 4:
        hs = np.array([0.4, 0.2, 0.1, 0.05])
    elif n == 1:
        hs = 0.5 / 2.0 ** np.arange(4)
    else:  # the double pendulum at 1 rad is pre-asymptotic for GL6 at h = 0.5
        hs = 0.25 / 2.0 ** np.arange(3)
    errors = []
    for h in hs:
        sol = _solve(L, y0, t1, h, solver=cls())
        assert sol.result == dfx.RESULTS.successful
        errors.append(
            max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(sol.ys, ref.ys))
        )
    assert min(errors) > 1e-12, errors  # not at the reference's round-off
    measured, _ = np.polyfit(np.log(hs), np.log(errors), 1)
    assert order - 0.25 < measured < order + 0.25, (measured, errors)
    assert cls().order(None) == order


@pytest.mark.slow  # three solvers compiled; each order is checked every time above
def test_gauss_legendre_beats_midpoint_at_same_step():
    y0 = (jnp.array([2.5]), jnp.array([0.0]))
    ref = _reference(PENDULUM, y0, 4.0)

    def error(solver):
        sol = _solve(PENDULUM, y0, 4.0, 0.1, solver=solver)
        return max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(sol.ys, ref.ys))

    solvers = (lagrax.VariationalMidpoint, *[c for c, _ in GAUSS])
    e2, e4, e6 = (error(s()) for s in solvers)
    assert e6 < 1e-2 * e4 < 1e-4 * e2, (e2, e4, e6)


# 1000 periods of each; the no-drift of the variational family is checked every time
# by test_energy_bounded_no_drift_1e3_periods (the midpoint rule).
@pytest.mark.slow
@pytest.mark.parametrize(
    ("cls", "h_per_period"),
    [
        pytest.param(lagrax.GaussLegendre4, 10, id="GL4"),
        pytest.param(lagrax.GaussLegendre6, 5, id="GL6", marks=pytest.mark.slow),
    ],
)
def test_gauss_legendre_energy_bounded_no_drift(cls, h_per_period):
    T = float(pendulum.period(2.5))
    h = T / h_per_period
    vi = _energy_window_maxima(cls(), h, 1_000)
    # Bounded: as large in the last tenth of 1000 periods as in the first, not more;
    # and at truncation level (well above round-off), so the test is not vacuous.
    assert vi[-1] < 1.05 * vi[0], vi
    assert vi[0] > 1e-9, vi
    # Tsit5, even at a smaller step (T/20), drifts over the same run.
    rk = _energy_window_maxima(dfx.Tsit5(), T / 20, 1_000)
    assert rk[-1] > 5 * rk[0], rk


# The midpoint rule's exact Noether momentum runs every time.
@pytest.mark.slow
@pytest.mark.parametrize("cls", GAUSS_CLASSES)
def test_gauss_legendre_noether_momentum_exact(cls):
    L = spherical_pendulum()
    y0 = (jnp.array([1.0, 0.0]), jnp.array([0.2, 1.3]))
    saveat = dfx.SaveAt(steps=True, solver_state=True)
    nsteps = 1000
    sol = _solve(
        L, y0, nsteps * 0.2, 0.2, solver=cls(), saveat=saveat, max_steps=nsteps
    )
    assert sol.result == dfx.RESULTS.successful
    qs, qdots = sol.ys
    p_phi = jax.jit(jax.vmap(lambda q, v: lagrax.momenta(L, q, v, 0.0)))(qs, qdots)[
        :, 1
    ]
    p_phi0 = float(lagrax.momenta(L, *y0, 0.0)[1])
    eps = np.finfo(np.float64).eps
    bound = 10 * np.sqrt(nsteps) * eps * abs(p_phi0)
    assert np.max(np.abs(np.asarray(p_phi) - p_phi0)) < bound
    assert abs(float(sol.solver_state[0][1]) - p_phi0) < bound
    # The energy moves at truncation level meanwhile: the step is not trivially small.
    energy = jax.jit(jax.vmap(lambda q, v: lagrax.energy(L, q, v, 0.0)))(qs, qdots)
    assert float(jnp.max(jnp.abs(energy - energy[0]))) > 1e3 * bound


@pytest.mark.parametrize("cls", GAUSS_CLASSES)
def test_gauss_legendre_time_reversible(cls):
    y0 = (jnp.array([2.5]), jnp.array([0.0]))
    fwd = _solve(PENDULUM, y0, 5.0, 0.25, solver=cls())
    y1 = jax.tree_util.tree_map(lambda x: x[-1], fwd.ys)
    back = _solve(PENDULUM, y1, 0.0, -0.25, t0=5.0, solver=cls())
    assert back.result == dfx.RESULTS.successful
    y0_back = jax.tree_util.tree_map(lambda x: x[-1], back.ys)
    assert tree_allclose(y0_back, y0, rtol=0, atol=1e-10)
    assert not tree_allclose(y1, y0, rtol=0, atol=1e-2)


# Gauss-Legendre under jit and vmap runs every time in the per-lane failures test.
@pytest.mark.slow
@pytest.mark.parametrize("cls", GAUSS_CLASSES)
def test_gauss_legendre_vmap_jit_match_a_python_loop(cls):
    ts = jnp.linspace(0.0, 3.0, 7)
    q0s = jnp.array([[0.5, 0.1], [1.5, -0.3], [2.5, 0.0]])
    L = double_pendulum(m2=2.0)

    def one(q0):
        y0 = (q0, jnp.zeros(2))
        return _solve(L, y0, 3.0, 0.05, solver=cls(), saveat=dfx.SaveAt(ts=ts))

    sols = jax.jit(jax.vmap(one))(q0s)
    assert sols.ys[0].shape == (3, 7, 2)
    assert np.all(np.asarray(sols.result == dfx.RESULTS.successful))
    for i, q0 in enumerate(q0s):
        assert tree_allclose(
            jax.tree_util.tree_map(lambda x: x[i], sols.ys),
            one(q0).ys,
            rtol=1e-12,
            atol=1e-12,
        )


@pytest.mark.parametrize("cls", GAUSS_CLASSES)
def test_gauss_legendre_failures_per_lane(cls):
    y0 = (jnp.array([1.0]), jnp.array([0.0]))
    sol = _solve(PENDULUM, y0, 1.0, 0.1, solver=cls(root_find_max_steps=1), throw=False)
    assert sol.result == dfx.RESULTS.nonlinear_max_steps_reached

    def L(q, qdot, t):  # NaN for q < 0
        return 0.5 * qdot[0] ** 2 - 1.0 / jnp.sqrt(q[0]) + 0.0 * q[0]

    @jax.jit
    @jax.vmap
    def batch(v0):
        y0 = (jnp.array([1.0]), jnp.array([v0]))
        return _solve(L, y0, 2.0, 0.5, solver=cls(), throw=False)

    sols = batch(jnp.array([0.1, -5.0, 0.2]))
    ok = np.asarray(sols.result == dfx.RESULTS.successful)
    assert ok.tolist() == [True, False, True]
    assert np.all(np.isfinite(np.asarray(sols.ys[0][0])))
    assert np.all(np.isfinite(np.asarray(sols.ys[0][2])))


# The midpoint rule's force and time dependence converge every time.
@pytest.mark.slow
@pytest.mark.parametrize("cls", GAUSS_CLASSES)
def test_gauss_legendre_force_and_time_dependence_converge(cls):
    c = 0.3

    def L(q, qdot, t):
        r = 1.0 + 0.1 * jnp.sin(t)
        return 0.5 * r**2 * qdot[0] ** 2 + r * jnp.cos(q[0])

    def force(q, qdot, t):
        return -c * qdot

    y0 = (jnp.array([1.0]), jnp.array([0.0]))
    ref = _reference(L, y0, 3.0, force=force)
    order = cls().order(None)
    errs = []
    for h in (0.3, 0.15):
        sol = _solve(L, y0, 3.0, h, solver=cls(), force=force)
        errs.append(max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(sol.ys, ref.ys)))
    assert errs[1] > 1e-12, errs
    assert 0.6 * 2**order < errs[0] / errs[1] < 1.5 * 2**order, errs


def test_root_finder_argument():
    y0 = (jnp.array([2.5]), jnp.array([0.0]))
    default = _solve(PENDULUM, y0, 2.0, 0.1)
    tight = _solve(
        PENDULUM,
        y0,
        2.0,
        0.1,
        solver=lagrax.VariationalMidpoint(
            root_finder=optx.Newton(rtol=1e-12, atol=1e-12)
        ),
    )
    assert tight.result == dfx.RESULTS.successful
    assert tree_allclose(default.ys, tight.ys, rtol=0, atol=1e-13)
    # A root finder given as an argument is the one used: chord iterations (Jacobian
    # frozen) with a loose tolerance give a different, still converged, answer.
    loose = _solve(
        PENDULUM,
        y0,
        2.0,
        0.1,
        solver=lagrax.GaussLegendre4(root_finder=optx.Chord(rtol=1e-3, atol=1e-3)),
        saveat=dfx.SaveAt(t1=True, solver_state=True),
    )
    assert loose.result == dfx.RESULTS.successful
    ref = _solve(PENDULUM, y0, 2.0, 0.1, solver=lagrax.GaussLegendre4())
    assert not tree_allclose(loose.ys, ref.ys, rtol=0, atol=1e-14)
    assert tree_allclose(loose.ys, ref.ys, rtol=0, atol=1e-3)
