"""The particle systems: autodiff against hand derivations, constraint forces that do no
virtual work, energy balance with dissipation, and exact references."""

import functools

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import lagrax
from lagrax.systems import (
    charged_particle,
    damped_pendulum,
    double_pendulum,
    driven_pendulum,
    rotating_hoop,
    sphere,
    spherical_pendulum,
)

from .helpers import random_states


# ---------------------------------------------------------------- hand derivations

_DP = dict(m1=1.3, m2=0.7, l1=1.1, l2=0.8, g=9.81)
_HOOP = dict(R=1.5, Omega=3.0, g=9.81)
_DRIVE = dict(l=1.2, g=9.81, ax=0.1, ay=0.2, omega=7.0)
_FIELDS = dict(
    m=2.0, charge=-1.5, B=jnp.array([0.3, -0.5, 1.2]), E=jnp.array([0.2, 0.1, -0.4])
)
_DRAG = dict(l=1.2, b=0.3, c=0.2)

# name: (L, force, hand q̈(q, qdot, t), n)
_SYSTEMS = {
    "sphere": (
        sphere.lagrangian(m=2.0, R=1.5, g=9.81),
        None,
        lambda q, qdot, t: sphere.acceleration(q, qdot, R=1.5, g=9.81),
        2,
    ),
    "sphere_arm": (
        sphere.arm_lagrangian(m=2.0, R=1.5, l=1.0, g=9.81),
        None,
        lambda q, qdot, t: sphere.arm_acceleration(q, qdot, R=1.5, l=1.0, g=9.81),
        1,
    ),
    "spherical_pendulum": (
        spherical_pendulum.lagrangian(m=2.0, l=1.5, g=9.81),
        None,
        lambda q, qdot, t: spherical_pendulum.acceleration(q, qdot, l=1.5, g=9.81),
        2,
    ),
    "spherical_pendulum_from_particles": (
        lagrax.particle_lagrangian(
            jnp.array([2.0]),
            spherical_pendulum.positions(l=1.5),
            lambda r, t: 2.0 * 9.81 * r[0, 2],
        ),
        None,
        lambda q, qdot, t: spherical_pendulum.acceleration(q, qdot, l=1.5, g=9.81),
        2,
    ),
    "double_pendulum": (
        double_pendulum.lagrangian(**_DP),
        None,
        lambda q, qdot, t: double_pendulum.acceleration(q, qdot, **_DP),
        2,
    ),
    "rotating_hoop": (
        rotating_hoop.lagrangian(m=2.0, **_HOOP),
        None,
        lambda q, qdot, t: rotating_hoop.acceleration(q, qdot, **_HOOP),
        1,
    ),
    "driven_pendulum": (
        driven_pendulum.lagrangian(m=2.0, **_DRIVE),
        None,
        lambda q, qdot, t: driven_pendulum.acceleration(q, qdot, t, **_DRIVE),
        1,
    ),
    "charged_particle": (
        charged_particle.lagrangian(**_FIELDS),
        None,
        lambda q, qdot, t: charged_particle.acceleration(q, qdot, **_FIELDS),
        3,
    ),
    "damped_by_generalized_force": (
        damped_pendulum.lagrangian(m=2.0, l=1.2, g=9.81),
        damped_pendulum.drag_force(**_DRAG),
        lambda q, qdot, t: damped_pendulum.acceleration(
            q, qdot, m=2.0, g=9.81, **_DRAG
        ),
        1,
    ),
    "damped_by_dissipation_force": (
        damped_pendulum.lagrangian(m=2.0, l=1.2, g=9.81),
        damped_pendulum.rayleigh_force(**_DRAG),
        lambda q, qdot, t: damped_pendulum.acceleration(
            q, qdot, m=2.0, g=9.81, **_DRAG
        ),
        1,
    ),
}


@pytest.mark.parametrize("name", sorted(_SYSTEMS))
def test_autodiff_matches_hand_derivation(name, key):
    L, force, hand, n = _SYSTEMS[name]
    qs, qdots = random_states(key, n, 64, scale=1.5)
    ts = jnp.linspace(-3.0, 3.0, 64)

    def both(q, qdot, t):
        return lagrax.accelerations(L, q, qdot, t, force=force), hand(q, qdot, t)

    ours, expected = jax.jit(jax.vmap(both))(qs, qdots, ts)
    assert np.all(np.isfinite(expected))
    np.testing.assert_allclose(ours, expected, rtol=1e-12, atol=1e-12)


def test_both_drag_routes_give_the_same_generalized_force(key):
    via_cartesian = damped_pendulum.drag_force(**_DRAG)
    via_rayleigh = damped_pendulum.rayleigh_force(**_DRAG)
    qs, qdots = random_states(key, 1, 32, scale=2.0)
    Q1, Q2 = jax.jit(
        jax.vmap(lambda q, qd: (via_cartesian(q, qd, 0.0), via_rayleigh(q, qd, 0.0)))
    )(qs, qdots)
    np.testing.assert_allclose(Q1, Q2, rtol=1e-13, atol=1e-15)
    # Released from rest the quadratic drag is 0, with finite derivatives (no |v| NaN).
    Q, grad = jax.jit(
        jax.value_and_grad(lambda w: via_cartesian(jnp.array([0.5]), w, 0.0)[0])
    )(jnp.zeros(1))
    assert float(Q) == 0.0
    assert np.all(np.isfinite(grad))


# ---------------------------------------------------------------- trajectories


@functools.cache
def _trajectory(name, t1=4.0, count=81):
    """A simulated trajectory (cached: each system's solve compiles once)."""
    L, force, _, n = _SYSTEMS_WITH_STARTS[name][:4]
    q0, qdot0 = _SYSTEMS_WITH_STARTS[name][4]
    ts = jnp.linspace(0.0, t1, count)
    sol = lagrax.simulate(
        L,
        q0,
        qdot0,
        0.0,
        t1,
        force=force,
        saveat=dfx.SaveAt(ts=ts),
        rtol=1e-11,
        atol=1e-11,
    )
    qs, qdots = sol.ys
    return ts, qs, qdots


_SYSTEMS_WITH_STARTS = {
    name: (*_SYSTEMS[name], start)
    for name, start in {
        "sphere": (jnp.array([1.2, 0.3]), jnp.array([0.4, 1.1])),
        "spherical_pendulum": (jnp.array([0.9, 0.0]), jnp.array([0.2, 1.3])),
        "double_pendulum": (jnp.array([1.0, -0.5]), jnp.array([0.0, 2.0])),
        "rotating_hoop": (jnp.array([0.3]), jnp.array([0.0])),
        "driven_pendulum": (jnp.array([0.4]), jnp.array([0.1])),
        "damped_by_generalized_force": (jnp.array([2.0]), jnp.array([0.0])),
        "damped_by_dissipation_force": (jnp.array([2.0]), jnp.array([0.0])),
    }.items()
}

# name: (masses, positions, potential V(r, t), applied non-conservative F(r, v, t))
_PARTICLES = {
    "sphere": (
        jnp.array([2.0]),
        sphere.positions(R=1.5),
        lambda r, t: 2.0 * 9.81 * r[0, 2],
        None,
    ),
    "spherical_pendulum": (
        jnp.array([2.0]),
        spherical_pendulum.positions(l=1.5),
        lambda r, t: 2.0 * 9.81 * r[0, 2],
        None,
    ),
    "double_pendulum": (
        jnp.array([_DP["m1"], _DP["m2"]]),
        double_pendulum.positions(l1=_DP["l1"], l2=_DP["l2"]),
        lambda r, t: _DP["g"] * jnp.dot(jnp.array([_DP["m1"], _DP["m2"]]), r[:, 1]),
        None,
    ),
    "rotating_hoop": (
        jnp.array([2.0]),
        rotating_hoop.positions(R=_HOOP["R"], Omega=_HOOP["Omega"]),
        lambda r, t: 2.0 * _HOOP["g"] * r[0, 2],
        None,
    ),
    "driven_pendulum": (
        jnp.array([2.0]),
        driven_pendulum.positions(
            l=_DRIVE["l"], ax=_DRIVE["ax"], ay=_DRIVE["ay"], omega=_DRIVE["omega"]
        ),
        lambda r, t: 2.0 * _DRIVE["g"] * r[0, 1],
        None,
    ),
    "damped_by_generalized_force": (
        jnp.array([2.0]),
        damped_pendulum.positions(l=_DRAG["l"]),
        lambda r, t: 2.0 * 9.81 * r[0, 1],
        damped_pendulum.air_drag(b=_DRAG["b"], c=_DRAG["c"]),
    ),
}


@pytest.mark.parametrize(
    "name",
    [
        "double_pendulum",  # two particles
        "rotating_hoop",  # explicit time in r(q, t)
        "damped_by_generalized_force",  # an applied non-conservative force
        pytest.param("sphere", marks=pytest.mark.slow),
        pytest.param("spherical_pendulum", marks=pytest.mark.slow),
        pytest.param("driven_pendulum", marks=pytest.mark.slow),
    ],
)
def test_constraint_forces_do_no_virtual_work(name):
    r"""N_i = m_i a_i − F_i, with a_i reconstructed from (q, q̇, q̈) along a simulated
    trajectory, is normal to the constraint surface: Σ_i N_i·∂r_i/∂q_j = 0."""
    L, force, _, _ = _SYSTEMS[name]
    masses, positions, potential, applied = _PARTICLES[name]
    ts, qs, qdots = _trajectory(name)

    def velocity(q, qdot, t):
        return jax.jvp(positions, (q, t), (qdot, jnp.ones_like(t)))[1]

    def residual(t, q, qdot):
        qddot = lagrax.accelerations(L, q, qdot, t, force=force)
        r, v = jax.jvp(positions, (q, t), (qdot, jnp.ones_like(t)))
        _, a = jax.jvp(velocity, (q, qdot, t), (qdot, qddot, jnp.ones_like(t)))
        F = -jax.grad(potential)(r, t)
        if applied is not None:
            F = F + applied(r, v, t)
        N = masses[:, None] * a - F
        J = jax.jacfwd(positions)(q, t)  # (N, d, n)
        work = jnp.einsum("nd,ndj->j", N, J)
        scale = jnp.einsum(
            "n,nj->j",
            jnp.linalg.norm(masses[:, None] * a, axis=1) + jnp.linalg.norm(F, axis=1),
            jnp.linalg.norm(J, axis=1),
        )
        return (
            work,
            scale,
            jnp.max(jnp.linalg.norm(N, axis=1)),
            jnp.max(jnp.linalg.norm(F, axis=1)),
        )

    work, scale, N, F = jax.jit(jax.vmap(residual))(ts, qs, qdots)
    assert np.all(np.abs(work) <= 1e-12 * scale)
    # Not vacuous: the constraints do push (gravity alone is not the whole story).
    assert np.max(N) > 0.1 * np.max(F)


def _energy_balance(L, force, q0, qdot0, t1):
    r"""h(t) − h(0) and W(t) = ∫₀ᵗ Q·q̇ dt, with W integrated alongside the state by the
    same adaptive solve (so the comparison is as exact as the solve, not a quadrature).
    """
    f = lagrax.vector_field(L, force=force)

    def augmented(t, y, args):
        (q, qdot), _ = y
        return f(t, (q, qdot), args), jnp.dot(force(q, qdot, t), qdot)

    ts = jnp.linspace(0.0, t1, 41)
    sol = dfx.diffeqsolve(
        dfx.ODETerm(augmented),
        dfx.Tsit5(),
        0.0,
        t1,
        None,
        ((q0, qdot0), jnp.zeros(())),
        saveat=dfx.SaveAt(ts=ts),
        stepsize_controller=dfx.PIDController(rtol=1e-11, atol=1e-11),
        max_steps=16384,
    )
    (qs, qdots), work = sol.ys
    h = jax.jit(jax.vmap(lambda t, q, qd: lagrax.energy(L, q, qd, t)))(ts, qs, qdots)
    return h - h[0], work


def test_energy_balance_with_dissipation():
    """The damped pendulum, drag through `dissipation_force`: dh/dt = Q·q̇."""
    L, force = _SYSTEMS["damped_by_dissipation_force"][:2]
    dh, work = jax.jit(_energy_balance, static_argnums=(0, 1, 4))(
        L, force, jnp.array([2.0]), jnp.array([0.0]), 6.0
    )
    lost = -float(dh[-1])
    assert lost > 1.0  # the drag really dissipates
    np.testing.assert_allclose(dh, work, rtol=0, atol=1e-8 * lost)


@pytest.mark.slow
def test_energy_balance_with_dissipation_by_cartesian_drag():
    L, force = _SYSTEMS["damped_by_generalized_force"][:2]
    dh, work = jax.jit(_energy_balance, static_argnums=(0, 1, 4))(
        L, force, jnp.array([2.0]), jnp.array([0.0]), 6.0
    )
    lost = -float(dh[-1])
    assert lost > 1.0
    np.testing.assert_allclose(dh, work, rtol=0, atol=1e-8 * lost)


def test_energy_balance_double_pendulum_with_drag_on_both_bobs():
    positions = double_pendulum.positions(l1=_DP["l1"], l2=_DP["l2"])
    drag = lagrax.generalized_force(
        positions, lambda r, v, t: -jnp.array([[0.4], [0.1]]) * v
    )
    L = double_pendulum.lagrangian(**_DP)
    dh, work = jax.jit(_energy_balance, static_argnums=(0, 1, 4))(
        L, drag, jnp.array([1.0, -0.5]), jnp.array([0.0, 2.0]), 5.0
    )
    lost = -float(dh[-1])
    assert lost > 1.0
    np.testing.assert_allclose(dh, work, rtol=0, atol=1e-8 * lost)


# ---------------------------------------------------------------- exact references


# Counted every time on smaller systems in tests/test_particles.py.
@pytest.mark.slow
def test_degrees_of_freedom_of_the_textbook_examples():
    R, l = 1.5, 1.0
    q_sphere, q_arm = jnp.array([0.7, 0.2]), jnp.array([0.2])
    r = sphere.positions(R=R)(q_sphere, 0.0)
    assert lagrax.degrees_of_freedom(sphere.constraints(R=R), r) == 2
    r = sphere.arm_positions(R=R, l=l)(q_arm, 0.0)
    assert lagrax.degrees_of_freedom(sphere.arm_constraints(R=R, l=l), r) == 1
    assert (
        lagrax.check_embedding(sphere.positions(R=R), sphere.constraints(R=R), q_sphere)
        == 2
    )
    assert (
        lagrax.check_embedding(
            sphere.arm_positions(R=R, l=l), sphere.arm_constraints(R=R, l=l), q_arm
        )
        == 1
    )


def test_free_particle_on_a_sphere_follows_a_great_circle():
    L = sphere.lagrangian(m=1.0, R=1.5, g=0.0)
    positions = sphere.positions(R=1.5)
    q0, qdot0 = jnp.array([1.2, 0.3]), jnp.array([0.4, 1.1])
    ts = jnp.linspace(0.0, 10.0, 41)
    sol = lagrax.simulate(
        L, q0, qdot0, 0.0, 10.0, saveat=dfx.SaveAt(ts=ts), rtol=1e-11, atol=1e-11
    )
    r = jax.jit(jax.vmap(lambda q: positions(q, 0.0)[0]))(sol.ys[0])
    r0, v0 = jax.jvp(positions, (q0, 0.0), (qdot0, 0.0))
    exact = sphere.great_circle(ts, r0[0], v0[0])
    np.testing.assert_allclose(r, exact, atol=1e-8)


@pytest.mark.slow
def test_arm_turns_uniformly():
    L = sphere.arm_lagrangian(m=1.0, R=1.5, l=1.0, g=9.81)
    ts = jnp.linspace(0.0, 5.0, 11)
    sol = lagrax.simulate(
        L, jnp.array([0.3]), jnp.array([1.7]), 0.0, 5.0, saveat=dfx.SaveAt(ts=ts)
    )
    np.testing.assert_allclose(sol.ys[0][:, 0], 0.3 + 1.7 * ts, rtol=1e-12)
    np.testing.assert_allclose(sol.ys[1][:, 0], 1.7, rtol=1e-12)


def test_conical_rate_is_an_equilibrium_of_theta():
    l, g, theta0 = 1.5, 9.81, 0.6
    L = spherical_pendulum.lagrangian(m=1.0, l=l, g=g)
    rate = spherical_pendulum.conical_rate(theta0, l=l, g=g)
    q = jnp.array([theta0, 0.3])
    qddot = jax.jit(
        jax.vmap(lambda w: lagrax.accelerations(L, q, jnp.stack([jnp.zeros(()), w])))
    )(jnp.stack([rate, 1.01 * rate]))
    np.testing.assert_allclose(qddot[0], 0.0, atol=1e-13)
    assert abs(float(qddot[1, 0])) > 1e-2  # a slightly wrong rate is not conical


@pytest.mark.slow
def test_conical_pendulum_keeps_its_angle():
    l, g, theta0 = 1.5, 9.81, 0.6
    L = spherical_pendulum.lagrangian(m=1.0, l=l, g=g)
    rate = spherical_pendulum.conical_rate(theta0, l=l, g=g)
    ts = jnp.linspace(0.0, 10.0, 21)
    sol = lagrax.simulate(
        L,
        jnp.array([theta0, 0.0]),
        jnp.stack([jnp.asarray(0.0), rate]),
        0.0,
        10.0,
        saveat=dfx.SaveAt(ts=ts),
        rtol=1e-11,
        atol=1e-11,
    )
    np.testing.assert_allclose(sol.ys[0][:, 0], theta0, atol=1e-8)
    np.testing.assert_allclose(sol.ys[0][:, 1], rate * ts, rtol=1e-8)
    # A slightly wrong rate would not stay conical: the test can fail.
    assert (
        abs(
            float(
                spherical_pendulum.acceleration(
                    jnp.array([theta0, 0.0]),
                    jnp.stack([jnp.asarray(0.0), 1.01 * rate]),
                    l=l,
                    g=g,
                )[0]
            )
        )
        > 1e-2
    )


def test_rotating_hoop_conserves_jacobi_integral_not_energy():
    L = _SYSTEMS["rotating_hoop"][0]
    ts, qs, qdots = _trajectory("rotating_hoop")
    positions = rotating_hoop.positions(R=_HOOP["R"], Omega=_HOOP["Omega"])

    def invariants(t, q, qd):
        r, v = jax.jvp(positions, (q, t), (qd, jnp.ones_like(t)))
        # T + V with T the bead's full kinetic energy: the motor's work changes it.
        total = 0.5 * 2.0 * jnp.sum(v**2) + 2.0 * _HOOP["g"] * r[0, 2]
        hand = rotating_hoop.jacobi_integral(q, qd, m=2.0, **_HOOP)
        return lagrax.energy(L, q, qd, t), hand, total

    h, hand, E = jax.jit(jax.vmap(invariants))(ts, qs, qdots)
    np.testing.assert_allclose(h, hand, rtol=1e-12)
    np.testing.assert_allclose(h, h[0], rtol=1e-9)
    assert np.ptp(E) > 1.0


@pytest.mark.parametrize("Omega", [1.5, 4.0])  # below and above sqrt(g/R) = 2.56
def test_rotating_hoop_equilibrium_and_small_oscillations(Omega):
    params = dict(R=1.5, Omega=Omega, g=9.81)
    L = rotating_hoop.lagrangian(m=2.0, **params)
    theta_star = rotating_hoop.equilibrium(**params)
    q_star, zero = jnp.stack([theta_star]), jnp.zeros(1)
    qddot, stiffness = jax.jit(
        lambda q: (
            lagrax.accelerations(L, q, zero, 0.7),
            jax.jacfwd(lambda q: lagrax.accelerations(L, q, zero, 0.7))(q),
        )
    )(q_star)
    np.testing.assert_allclose(qddot, 0.0, atol=1e-13)
    omega = rotating_hoop.small_oscillation_frequency(**params)
    np.testing.assert_allclose(-stiffness[0, 0], omega**2, rtol=1e-12)
    assert (float(theta_star) > 0) == (Omega**2 > 9.81 / 1.5)


def test_double_pendulum_normal_modes():
    L = double_pendulum.lagrangian(**_DP)
    zero = jnp.zeros(2)
    M, K = jax.jit(
        lambda q: (
            lagrax.mass_matrix(L, q, zero),
            -jax.hessian(lambda q: L(q, zero, 0.0))(q),
        )
    )(zero)
    w2 = scipy.linalg.eigh(np.asarray(K), np.asarray(M), eigvals_only=True)
    np.testing.assert_allclose(
        np.sqrt(w2), double_pendulum.normal_mode_frequencies(**_DP), rtol=1e-12
    )
    # Equal masses and lengths: (2 ∓ √2) g/l.
    w = double_pendulum.normal_mode_frequencies(m1=1.0, m2=1.0, l1=1.0, l2=1.0, g=1.0)
    np.testing.assert_allclose(w**2, [2 - np.sqrt(2), 2 + np.sqrt(2)], rtol=1e-14)


def test_charged_particle_exact_trajectory_solves_lorentz():
    """The reference itself: dr/dt = v and dv/dt = (e/m)(E + v × B) at random times."""
    q0, qdot0 = jnp.array([0.1, -0.3, 0.5]), jnp.array([0.7, 0.2, -0.4])

    def path(t):
        return charged_particle.exact_trajectory(t, q0, qdot0, **_FIELDS)

    @jax.jit
    @jax.vmap
    def check(t):
        (r, v), (dr, dv) = jax.jvp(path, (t,), (jnp.ones_like(t),))
        return dr, v, dv, charged_particle.acceleration(r, v, **_FIELDS)

    dr, v, dv, a = check(jnp.array([0.0, 0.37, 5.2]))
    np.testing.assert_allclose(dr, v, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(dv, a, rtol=1e-12, atol=1e-14)
    r, v = path(jnp.asarray(0.0))
    np.testing.assert_allclose(r, q0, atol=1e-15)
    np.testing.assert_allclose(v, qdot0, atol=1e-15)


def test_charged_particle_against_exact_and_cyclotron_period():
    """One compiled solve, two lanes: crossed fields against the exact solution, and a
    pure B field, which must return to its start after 2π/ω_c exactly."""
    m, charge = _FIELDS["m"], _FIELDS["charge"]
    B = _FIELDS["B"]
    period = 2 * jnp.pi / charged_particle.cyclotron_frequency(m=m, charge=charge, B=B)
    q0, qdot0 = jnp.array([0.1, -0.3, 0.5]), jnp.array([0.7, 0.2, -0.4])
    # Velocity across B only, for the closed orbit.
    b = B / jnp.linalg.norm(B)
    qdot_perp = qdot0 - jnp.dot(qdot0, b) * b
    # A Python float: a concrete jax Array closed over by `jit` trips check_finite.
    t1 = float(3 * period)

    def solve(E, q0, qdot0):
        L = charged_particle.lagrangian(m=m, charge=charge, B=B, E=E)
        ts = jnp.linspace(0.0, t1, 7)  # includes each whole period
        sol = lagrax.simulate(
            L, q0, qdot0, 0.0, t1, saveat=dfx.SaveAt(ts=ts), rtol=1e-12, atol=1e-12
        )
        return ts, sol.ys

    Es = jnp.stack([_FIELDS["E"], jnp.zeros(3)])
    ts, (qs, qdots) = jax.jit(jax.vmap(solve))(
        Es, jnp.stack([q0, q0]), jnp.stack([qdot0, qdot_perp])
    )
    r, v = charged_particle.exact_trajectory(ts[0], q0, qdot0, **_FIELDS)
    np.testing.assert_allclose(qs[0], r, atol=1e-9)
    np.testing.assert_allclose(qdots[0], v, atol=1e-9)
    # Pure magnetic field: back at the start after every period, and away in between.
    np.testing.assert_allclose(qs[1, ::2], np.broadcast_to(q0, (4, 3)), atol=1e-9)
    np.testing.assert_allclose(
        qdots[1, ::2], np.broadcast_to(qdot_perp, (4, 3)), atol=1e-9
    )
    assert np.min(np.linalg.norm(np.asarray(qs[1, 1::2] - q0[None]), axis=1)) > 0.1


@pytest.mark.slow
def test_kapitza_pendulum():
    """A vertical drive well above sqrt(2gl)/a holds the pendulum upside down; well
    below it, the pendulum falls. (Kapitza's criterion is approximate: wide margins.)"""
    a, l, g = 0.05, 1.0, 1.0
    critical = driven_pendulum.kapitza_critical_frequency(a=a, l=l, g=g)
    t1 = 15.0

    def run(omega):
        L = driven_pendulum.lagrangian(m=1.0, l=l, g=g, ax=0.0, ay=a, omega=omega)
        ts = jnp.linspace(0.0, t1, 301)
        sol = lagrax.simulate(
            L,
            jnp.array([jnp.pi - 0.1]),
            jnp.zeros(1),
            0.0,
            t1,
            saveat=dfx.SaveAt(ts=ts),
            rtol=1e-8,
            atol=1e-8,
        )
        return sol.ys[0][:, 0]

    theta = jax.jit(jax.vmap(run))(jnp.array([2.0, 0.5]) * critical)
    assert np.max(np.abs(theta[0] - np.pi)) < 0.3
    assert np.max(np.abs(theta[1] - np.pi)) > 1.0
