"""A Lagrangian with branches (`jnp.where`, `abs`, ...): a Taylor step decides them at
its start, so a step across a switch is checked at its end and shortened (trajectories)
or fails its lane (the period kernel); never a wrong number."""

import diffrax as dfx
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest

import lagrax
from lagrax._jaxpr.switches import switches


W_POS, W_NEG = np.sqrt(2.0), 2.0  # V = q^2 for q > 0, 2 q^2 for q < 0


def piecewise(q, qdot, t):
    return 0.5 * jnp.sum(qdot**2) - jnp.sum(jnp.where(q > 0, q**2, 2 * q**2))


def piecewise_exact(q0, v0, t):
    """The exact state of each coordinate at `t`: half a harmonic swing at each
    frequency, matched at q = 0."""
    E = 0.5 * v0**2 + np.where(q0 > 0, q0**2, 2 * q0**2)
    a_pos, a_neg = np.sqrt(E) / 1.0, np.sqrt(E / 2.0)
    half = np.pi / W_POS
    period = half + np.pi / W_NEG
    phase0 = np.where(
        q0 >= 0,
        np.arctan2(q0 * W_POS / a_pos, v0 / a_pos) / W_POS,
        half + np.arctan2(-q0 * W_NEG / a_neg, -v0 / a_neg) / W_NEG,
    )
    phase = np.mod(phase0 + t, period)
    pos = phase < half
    q = np.where(
        pos, a_pos * np.sin(W_POS * phase), -a_neg * np.sin(W_NEG * (phase - half))
    )
    v = np.where(
        pos,
        a_pos * W_POS * np.cos(W_POS * phase),
        -a_neg * W_NEG * np.cos(W_NEG * (phase - half)),
    )
    return np.concatenate([q, v], axis=-1)


Q0 = np.array([[0.5, -0.3], [0.8, 0.1], [-0.7, 0.2]])
V0 = np.array([[0.1, 0.4], [-0.2, 0.0], [0.3, -0.5]])


def test_switches_found_in_the_lagrangian_only():
    z = jnp.zeros(2)
    state = (z, z, 0.0)
    smooth = lambda q, qd, t: 0.5 * jnp.sum(qd**2) + jnp.sum(jnp.cos(q))
    assert not switches(smooth, state)
    assert switches(piecewise, state)
    assert switches(lambda q, qd, t: smooth(q, qd, t) - jnp.sum(jnp.abs(q) ** 3), state)
    assert switches(lambda q, qd, t: smooth(q, qd, t) * jnp.maximum(t, 1.0), state)
    # A comparison of a parameter alone is no switch of the state.
    assert not switches(
        lambda q, qd, t, k: jnp.where(k > 0, k, 1.0) * smooth(q, qd, t), state, (1.0,)
    )
    # The guards of a q-dependent mass matrix's solve (definite, finite) are: the
    # vector field has them, L has not.
    curved = lambda q, qd, t: 0.5 * (2 + jnp.cos(q[0])) * jnp.sum(qd**2)
    assert not switches(curved, state)
    vf = lambda t, q, v: lagrax.LagrangianTerm(curved).vf(t, (q, v), None)
    assert switches(vf, (0.0, z, z))


def test_simulate_batch_shortens_the_step_across_a_switch():
    sol = lagrax.simulate_batch(piecewise, Q0, V0, 0.0, 10.0, rtol=1e-12, atol=1e-12)
    ys = np.concatenate([np.asarray(sol.ys[0][:, -1]), np.asarray(sol.ys[1][:, -1])], 1)
    exact = np.stack([piecewise_exact(q, v, 10.0) for q, v in zip(Q0, V0)])
    assert np.max(np.abs(ys - exact)) < 1e-9  # (4.7e-4 to 0.2 before)
    assert np.all(np.asarray(sol.stats["num_rejected_steps"]) > 0)
    steps = np.asarray(sol.stats["num_steps"])
    accepted = np.asarray(sol.stats["num_accepted_steps"])
    assert np.all(accepted + np.asarray(sol.stats["num_rejected_steps"]) == steps)


def test_a_switch_that_never_flips_costs_no_step():
    smooth = lambda q, qd, t: 0.5 * jnp.sum(qd**2) - jnp.sum(q**2)
    flagged = lambda q, qd, t: smooth(q, qd, t) + jnp.where(q[0] > 1e3, 1.0, 0.0)
    run = lambda L: lagrax.simulate_batch(L, Q0, V0, 0.0, 10.0, rtol=1e-12, atol=1e-12)
    plain, checked = run(smooth), run(flagged)
    assert np.all(np.asarray(checked.stats["num_rejected_steps"]) == 0)
    np.testing.assert_array_equal(checked.stats["num_steps"], plain.stats["num_steps"])
    np.testing.assert_array_equal(checked.ys[0], plain.ys[0])


def test_taylor_as_a_diffrax_solver_across_a_switch():
    sol = lagrax.simulate(
        piecewise, Q0[0], V0[0], 0.0, 10.0, solver=lagrax.Taylor(order=8),
        rtol=1e-12, atol=1e-12, max_steps=1 << 14,
    )  # fmt: skip
    y = np.concatenate([np.asarray(sol.ys[0][-1]), np.asarray(sol.ys[1][-1])])
    assert np.max(np.abs(y - piecewise_exact(Q0[0], V0[0], 10.0))) < 1e-9


def _kinked_period(q0, c):
    """The period in V = q^2 + c (q - 1/2)^2 [q > 1/2] by a 30-digit quadrature
    split at the kink."""
    mpmath.mp.dps = 30
    half = mpmath.mpf(1) / 2
    V = lambda q: q**2 + (c * (q - half) ** 2 if q > half else 0)
    E = V(mpmath.mpf(q0))
    f = lambda q: 1 / mpmath.sqrt(2 * max(E - V(q), mpmath.mpf(10) ** -40))
    return float(2 * mpmath.quad(f, [-mpmath.sqrt(E), 0, half, mpmath.mpf(q0)]))


# The switch check is the Taylor step's, whichever the method: the default method
# every time, "half" (two programs of its own) with -m slow.
@pytest.mark.parametrize(
    "method", ["matched", pytest.param("half", marks=pytest.mark.slow)]
)
def test_period_kernel_never_a_wrong_period_across_a_switch(method):
    c = 1e-8  # a small kink: the energy check cannot see it
    V = lambda q: q**2 + c * jnp.where(q > 0.5, (q - 0.5) ** 2, 0.0)
    L = lambda q, qd, t: 0.5 * qd[0] ** 2 - V(q[0])
    q0 = np.array([0.3, 0.8, 1.2])
    res = lagrax.sweep_periods(L, q0, solver=lagrax.Taylor(), method=method)
    status, T = np.asarray(res.status), np.asarray(res.periods)
    assert status[0] == 0 and abs(T[0] / (np.pi * np.sqrt(2.0)) - 1) < 1e-12
    for i in (1, 2):  # their swings cross the kink at q = 1/2
        ok = status[i] == 0
        assert not ok or abs(T[i] / _kinked_period(q0[i], c) - 1) < 1e-11, (i, T[i])
    # (matched: success with 2e-10 on both before; it fails them now)
    assert np.all(status[1:] == lagrax.status_code(lagrax.PeriodStatus.solver_failed))
    solved = lagrax.sweep_periods(L, q0, solver=dfx.Dopri8(), method=method)
    T8 = np.asarray(solved.periods)
    assert all(abs(T8[i] / _kinked_period(q0[i], c) - 1) < 1e-11 for i in (1, 2))


def test_default_sweep_steps_a_switching_lagrangian_with_its_fallback():
    c = 1e-8
    V = lambda q: q**2 + c * jnp.where(q > 0.5, (q - 0.5) ** 2, 0.0)
    L = lambda q, qd, t: 0.5 * qd[0] ** 2 - V(q[0])
    res = lagrax.sweep_periods(L, np.array([0.3, 1.2]))
    assert isinstance(res.solver, dfx.Dopri8)
    assert np.all(np.asarray(res.status) == 0)
    assert abs(float(res.periods[1]) / _kinked_period(1.2, c) - 1) < 1e-11


def test_period_step_checks_its_end_only_where_the_lagrangian_switches():
    from lagrax._jaxpr.canonical import canonical_lagrangian
    from lagrax._period.loop import _checked
    from lagrax._taylor.stepper import TaylorStepper

    step = TaylorStepper(order=20, max_step=np.inf)
    smooth = lagrax.systems.pendulum.lagrangian()
    kinked = lambda q, qd, t: (
        0.5 * jnp.sum(qd**2)
        - jnp.sum(q**2 + 1e-8 * jnp.where(q > 0.5, (q - 0.5) ** 2, 0.0))
    )
    checked = {}
    for name, L in (("smooth", smooth), ("kinked", kinked)):
        L_c, consts = canonical_lagrangian(L, np.float64)
        checked[name] = _checked(step, L_c, consts, np.float64).checked
    assert checked == {"smooth": False, "kinked": True}
