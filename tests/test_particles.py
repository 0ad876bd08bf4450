"""particle_lagrangian, generalized_force, dissipation_force, degrees_of_freedom and
check_embedding: against explicit Jacobians, hand-written coordinates, and their error
paths."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax
from lagrax.systems import double_pendulum, rotating_hoop, sphere

from .helpers import random_states


def _explicit_velocity(positions, q, qdot, t):
    """ṙ = J q̇ + ∂r/∂t with J formed explicitly (the route the API avoids)."""
    J, dr_dt = jax.jacfwd(positions, argnums=(0, 1))(q, t)
    return jnp.einsum("ndj,j->nd", J, qdot) + dr_dt


def _batched(f, *args):
    """f over a batch of states, compiled once (eager loops are slow on a busy CPU)."""
    return jax.jit(jax.vmap(f))(*args)


# A time-dependent, 3-D, two-particle embedding: a rod of length 1 whose midpoint is
# carried round a circle, spinning in a plane that itself tilts with time.
def _spinning_rod(q, t):
    centre = jnp.stack([jnp.cos(0.7 * t), jnp.sin(0.7 * t), 0.1 * t])
    theta, phi = q[0], q[1]
    u = jnp.stack(
        [jnp.sin(theta) * jnp.cos(phi), jnp.sin(theta) * jnp.sin(phi), jnp.cos(theta)]
    )
    return jnp.stack([centre + 0.5 * u, centre - 0.5 * u])


_MASSES = jnp.array([1.3, 0.4])


def test_kinetic_energy_matches_explicit_jacobian(key):
    L = lagrax.particle_lagrangian(_MASSES, _spinning_rod)
    qs, qdots = random_states(key, 2, 20)
    ts = jnp.linspace(-1.0, 2.0, 20)

    def both(q, qdot, t):
        v = _explicit_velocity(_spinning_rod, q, qdot, t)
        return L(q, qdot, t), 0.5 * jnp.sum(_MASSES * jnp.sum(v**2, axis=-1))

    ours, explicit = _batched(both, qs, qdots, ts)
    np.testing.assert_allclose(ours, explicit, rtol=1e-13, atol=0)


def test_mass_matrix_is_jacobian_gram(key):
    L = lagrax.particle_lagrangian(_MASSES, _spinning_rod)
    qs, qdots = random_states(key, 2, 10)

    def both(q, qdot):
        J = jax.jacfwd(_spinning_rod)(q, 0.4)
        expected = jnp.einsum("n,ndi,ndj->ij", _MASSES, J, J)
        return lagrax.mass_matrix(L, q, qdot, 0.4), expected

    M, expected = _batched(both, qs, qdots)
    np.testing.assert_allclose(M, expected, rtol=1e-12, atol=1e-14)


def test_potential_enters_with_minus_sign():
    def positions(q, t):
        return jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])])[None]

    L = lagrax.particle_lagrangian(
        jnp.array([2.0]), positions, lambda r, t: 2.0 * 9.81 * r[0, 1]
    )
    q, qdot = jnp.array([0.7]), jnp.array([-1.1])
    hand = 0.5 * 2.0 * qdot[0] ** 2 + 2.0 * 9.81 * jnp.cos(q[0])
    assert np.isclose(L(q, qdot, 0.0), hand, rtol=1e-14)
    assert np.isclose(
        lagrax.accelerations(L, q, qdot)[0], -9.81 * np.sin(0.7), rtol=1e-13
    )


def test_integer_masses_are_promoted():
    L = lagrax.particle_lagrangian([1, 2], double_pendulum.positions())
    Lf = lagrax.particle_lagrangian(jnp.array([1.0, 2.0]), double_pendulum.positions())
    q, qdot = jnp.array([0.3, -0.2]), jnp.array([0.5, 0.1])
    assert L(q, qdot, 0.0) == Lf(q, qdot, 0.0)


def test_jit_and_vmap_match_loop(key):
    L = lagrax.particle_lagrangian(_MASSES, _spinning_rod)
    force = lagrax.generalized_force(_spinning_rod, lambda r, v, t: -0.3 * v)
    qs, qdots = random_states(key, 2, 3)

    def qddot(q, qdot):
        return lagrax.accelerations(L, q, qdot, 0.5, force=force)

    batched = _batched(qddot, qs, qdots)
    looped = jnp.stack([jax.jit(qddot)(q, qdot) for q, qdot in zip(qs, qdots)])
    np.testing.assert_allclose(batched, looped, rtol=1e-12, atol=1e-14)


def test_vmap_over_masses():
    """Masses may be traced (a sweep over parameters under vmap)."""
    q, qdot = jnp.array([0.3, -0.2]), jnp.array([0.5, 0.1])

    def acc(m2):
        masses = jnp.stack([jnp.asarray(1.0), m2])
        L = lagrax.particle_lagrangian(
            masses,
            double_pendulum.positions(),
            lambda r, t: jnp.dot(masses, r[:, 1]),
        )
        return lagrax.accelerations(L, q, qdot), double_pendulum.acceleration(
            q, qdot, m2=m2
        )

    ours, hand = jax.jit(jax.vmap(acc))(jnp.array([0.5, 1.0, 2.0]))
    np.testing.assert_allclose(ours, hand, rtol=1e-12)


# ---------------------------------------------------------------- generalized forces


def test_generalized_force_matches_explicit_jacobian_transpose(key):
    def F(r, v, t):  # velocity- and time-dependent, different on each particle
        return -0.2 * v * jnp.linalg.norm(v, axis=-1, keepdims=True) + jnp.stack(
            [jnp.sin(t) * r[1], jnp.cross(r[0], v[1])]
        )

    force = lagrax.generalized_force(_spinning_rod, F)
    qs, qdots = random_states(key, 2, 10)
    ts = jnp.linspace(-1.0, 2.0, 10)

    def both(q, qdot, t):
        r = _spinning_rod(q, t)
        v = _explicit_velocity(_spinning_rod, q, qdot, t)
        J = jax.jacfwd(_spinning_rod)(q, t)
        return force(q, qdot, t), jnp.einsum("ndj,nd->j", J, F(r, v, t))

    ours, explicit = _batched(both, qs, qdots, ts)
    np.testing.assert_allclose(ours, explicit, rtol=1e-12, atol=1e-14)


def _spring_potential(r, t):
    """Gravity on both bobs, a spring from bob 2 to the point (1, -1), and one between
    the bobs (rest length 0.5)."""
    k1, k2, g = 3.0, 5.0, 9.81
    m = jnp.array([1.3, 0.7])
    anchor = jnp.array([1.0, -1.0])
    stretch = jnp.linalg.norm(r[0] - r[1]) - 0.5
    return (
        g * jnp.dot(m, r[:, 1])
        + 0.5 * k1 * jnp.sum((r[1] - anchor) ** 2)
        + 0.5 * k2 * stretch**2
    )


def _spring_potential_in_coordinates(q):
    """The same potential written by hand in (θ1, θ2), l1 = 1.1, l2 = 0.8."""
    k1, k2, g = 3.0, 5.0, 9.81
    m1, m2, l1, l2 = 1.3, 0.7, 1.1, 0.8
    t1, t2 = q[0], q[1]
    y1 = -l1 * jnp.cos(t1)
    x2 = l1 * jnp.sin(t1) + l2 * jnp.sin(t2)
    y2 = y1 - l2 * jnp.cos(t2)
    # |r1 - r2| = l2 for the rod, so the inter-bob spring stores a constant energy.
    return (
        g * (m1 * y1 + m2 * y2)
        + 0.5 * k1 * ((x2 - 1.0) ** 2 + (y2 + 1.0) ** 2)
        + 0.5 * k2 * (l2 - 0.5) ** 2
    )


def test_conservative_force_is_minus_gradient_of_potential(key):
    positions = double_pendulum.positions(l1=1.1, l2=0.8)
    force = lagrax.generalized_force(
        positions, lambda r, v, t: -jax.grad(_spring_potential)(r, t)
    )
    masses = jnp.array([1.3, 0.7])
    L_pot = lagrax.particle_lagrangian(masses, positions, _spring_potential)
    L_kin = lagrax.particle_lagrangian(masses, positions)
    qs, qdots = random_states(key, 2, 20, scale=2.0)

    def compare(q, qdot):
        return (
            force(q, qdot, 0.0),
            -jax.grad(_spring_potential_in_coordinates)(q),
            lagrax.accelerations(L_kin, q, qdot, force=force),
            lagrax.accelerations(L_pot, q, qdot),
        )

    Q, minus_dV, with_force, with_potential = _batched(compare, qs, qdots)
    np.testing.assert_allclose(Q, minus_dV, rtol=1e-12)
    # ... and as a force it moves the system exactly as the potential in L does.
    np.testing.assert_allclose(with_force, with_potential, rtol=1e-11, atol=1e-12)


def test_gravity_generalized_force_by_hand(key):
    """Gravity on the double pendulum: Q = (−(m1+m2) g l1 sin θ1, −m2 g l2 sin θ2)."""
    m1, m2, l1, l2, g = 1.3, 0.7, 1.1, 0.8, 9.81
    weights = jnp.array([[0.0, -m1 * g], [0.0, -m2 * g]])
    force = lagrax.generalized_force(
        double_pendulum.positions(l1=l1, l2=l2), lambda r, v, t: weights
    )
    qs, qdots = random_states(key, 2, 10, scale=2.0)
    Q = _batched(lambda q, qdot: force(q, qdot, 0.0), qs, qdots)
    hand = jnp.stack(
        [-(m1 + m2) * g * l1 * jnp.sin(qs[:, 0]), -m2 * g * l2 * jnp.sin(qs[:, 1])],
        axis=1,
    )
    np.testing.assert_allclose(Q, hand, rtol=1e-13, atol=1e-13)


def test_dissipation_force_of_linear_drag_matches_cartesian_drag(key):
    """R = ½ b Σ|ṙ_i|² gives the same Q as the Cartesian force F = −b ṙ; on a fixed
    support Q·q̇ = −2R."""
    b = 0.37

    def R(q, qdot, t):
        v = _explicit_velocity(_spinning_rod, q, qdot, t)
        return 0.5 * b * jnp.sum(v**2)

    from_R = lagrax.dissipation_force(R)
    from_F = lagrax.generalized_force(_spinning_rod, lambda r, v, t: -b * v)
    still = lambda q, t: _spinning_rod(q, 0.0)
    from_F_still = lagrax.generalized_force(still, lambda r, v, t: -b * v)
    qs, qdots = random_states(key, 2, 10)

    def compare(q, qdot):
        v = _explicit_velocity(still, q, qdot, 0.0)
        return (
            from_R(q, qdot, 1.2),
            from_F(q, qdot, 1.2),
            jnp.dot(from_F_still(q, qdot, 0.0), qdot),
            -b * jnp.sum(v**2),
        )

    QR, QF, power, minus_2R = _batched(compare, qs, qdots)
    np.testing.assert_allclose(QR, QF, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(power, minus_2R, rtol=1e-12)


# ---------------------------------------------------------------- degrees of freedom


def _rod(r, t):
    return jnp.stack([jnp.sum((r[0] - r[1]) ** 2) - 1.0])


def test_degrees_of_freedom_counts():
    north = jnp.array([[0.0, 0.0, 1.0]])
    on_circle = sphere.arm_positions(R=1.0, l=1.0)(jnp.array([0.3]), 0.0)
    assert lagrax.degrees_of_freedom(sphere.constraints(R=1.0), north) == 2
    assert (
        lagrax.degrees_of_freedom(sphere.arm_constraints(R=1.0, l=1.0), on_circle) == 1
    )
    # No constraints: all 3N Cartesian coordinates.
    free = lambda r, t: jnp.zeros((0,), r.dtype)
    assert lagrax.degrees_of_freedom(free, jnp.zeros((2, 3))) == 6
    # A rigid dumbbell: 6 - 1.
    dumbbell = jnp.array([[0.0, 0.0, 0.0], [0.6, 0.8, 0.0]])
    assert lagrax.degrees_of_freedom(_rod, dumbbell) == 5
    # The same constraint written twice is one constraint: rank, not count.
    twice = lambda r, t: jnp.concatenate([_rod(r, t), 2 * _rod(r, t)])
    assert lagrax.degrees_of_freedom(twice, dumbbell) == 5
    # A planar double pendulum as two particles under two rod constraints.
    rods = lambda r, t: jnp.stack(
        [jnp.sum(r[0] ** 2) - 1.0, jnp.sum((r[1] - r[0]) ** 2) - 1.0]
    )
    r = double_pendulum.positions()(jnp.array([0.4, -1.2]), 0.0)
    assert lagrax.degrees_of_freedom(rods, r) == 2


def test_degrees_of_freedom_under_jit_and_vmap():
    f = sphere.constraints(R=2.0)
    rs = 2.0 * jnp.array([[[0.0, 0.0, 1.0]], [[0.6, 0.8, 0.0]]])
    n = jax.jit(jax.vmap(lambda r: lagrax.degrees_of_freedom(f, r)))(rs)
    assert n.tolist() == [2, 2]


def test_degrees_of_freedom_off_the_surface_raises():
    # At r = 0 the sphere's gradient vanishes: the rank (0) would claim 3 freedoms.
    with pytest.raises(ValueError, match="does not satisfy the constraints"):
        lagrax.degrees_of_freedom(sphere.constraints(R=1.0), jnp.zeros((1, 3)))
    with pytest.raises(ValueError, match="does not satisfy the constraints"):
        lagrax.degrees_of_freedom(sphere.constraints(R=1.0), jnp.array([[0, 0, 1.01]]))
    with pytest.raises(Exception, match="does not satisfy the constraints"):
        jax.jit(lambda r: lagrax.degrees_of_freedom(sphere.constraints(), r))(
            jnp.zeros((1, 3))
        )


# ---------------------------------------------------------------- embeddings


def test_check_embedding_accepts_valid_coordinates():
    assert (
        lagrax.check_embedding(
            sphere.positions(R=2.0), sphere.constraints(R=2.0), jnp.array([0.4, 2.0])
        )
        == 2
    )
    arm = dict(R=2.0, l=1.5)
    assert (
        lagrax.check_embedding(
            sphere.arm_positions(**arm), sphere.arm_constraints(**arm), jnp.array([1.0])
        )
        == 1
    )
    # Explicit time: the hoop's constraints and embedding both turn with t.
    hoop = dict(R=1.5, Omega=2.0)
    for t in (0.0, 0.3, 4.0):
        n = lagrax.check_embedding(
            rotating_hoop.positions(**hoop),
            rotating_hoop.constraints(**hoop),
            jnp.array([0.8]),
            t,
        )
        assert n == 1


def test_check_embedding_too_few_coordinates():
    fixed_phi = lambda q, t: sphere.positions()(jnp.stack([q[0], 0.3]), t)
    with pytest.raises(ValueError, match="Too few coordinates.*2 degrees of freedom"):
        lagrax.check_embedding(fixed_phi, sphere.constraints(), jnp.array([0.5]))


def test_check_embedding_redundant_coordinates():
    # θ and θ' that only enter as θ + θ': two coordinates, one motion.
    redundant = lambda q, t: sphere.positions()(jnp.stack([q[0] + q[1], q[2]]), t)
    with pytest.raises(ValueError, match="Redundant or singular.*rank 2 < 3"):
        lagrax.check_embedding(
            redundant, sphere.constraints(), jnp.array([0.2, 0.3, 1.0])
        )
    # The azimuth at the pole moves nothing: a coordinate singularity.
    with pytest.raises(ValueError, match="Redundant or singular.*rank 1 < 2"):
        lagrax.check_embedding(
            sphere.positions(), sphere.constraints(), jnp.array([0.0, 1.0])
        )


def test_check_embedding_constraint_violated():
    wrong_radius = sphere.positions(R=1.1)
    with pytest.raises(ValueError, match="`positions` violates `constraints`"):
        lagrax.check_embedding(
            wrong_radius, sphere.constraints(), jnp.array([0.5, 0.1])
        )
    # A hoop embedding that forgets to turn: right at t = 0, wrong later.
    hoop = dict(R=1.0, Omega=2.0)
    still = lambda q, t: rotating_hoop.positions(**hoop)(q, 0.0)
    lagrax.check_embedding(
        rotating_hoop.positions(**hoop),
        rotating_hoop.constraints(**hoop),
        jnp.array([0.8]),
    )
    with pytest.raises(ValueError, match="violates"):
        lagrax.check_embedding(
            still, rotating_hoop.constraints(**hoop), jnp.array([0.8]), 1.0
        )


def test_check_embedding_leaves_the_surface():
    # Sphere coordinates at a point of the arm's circle: two coordinates for one
    # freedom, and θ moves the particle off the circle.
    arm = dict(R=1.0, l=1.0)
    theta0 = 2 * jnp.arcsin(0.5)  # l = 2R sin(θ/2)
    with pytest.raises(ValueError, match="leaves the constraint surface"):
        lagrax.check_embedding(
            sphere.positions(R=1.0),
            sphere.arm_constraints(**arm),
            jnp.stack([theta0, 0.4]),
        )
    # A hoop embedding that is right at every t's start but does not turn: at t = 0 the
    # constraints hold, yet ∂f/∂r·∂r/∂t + ∂f/∂t ≠ 0.
    hoop = dict(R=1.0, Omega=2.0)
    frozen = lambda q, t: rotating_hoop.positions(**hoop)(q, 0.0)
    with pytest.raises(ValueError, match="leaves the constraint surface"):
        lagrax.check_embedding(
            frozen, rotating_hoop.constraints(**hoop), jnp.array([0.8])
        )


def test_check_embedding_under_jit_raises_at_runtime():
    check = jax.jit(
        lambda q: lagrax.check_embedding(sphere.positions(), sphere.constraints(), q)
    )
    assert int(check(jnp.array([0.5, 0.1]))) == 2
    with pytest.raises(Exception, match="rank-deficient"):
        jax.block_until_ready(check(jnp.array([0.0, 0.1])))


# ---------------------------------------------------------------- error paths


def test_reverse_mode_through_the_masses():
    # `jax.grad` transposes the scalar program the equations are evaluated as: its
    # products must carry the parameters JAX's own transpose rules require. Against
    # the hand-derived closed form, differentiated by JAX alone.
    q, qdot = jnp.array([0.3, -0.2]), jnp.array([0.1, 0.4])

    def ours(m1, m2):
        L = double_pendulum.lagrangian(m1=m1, m2=m2, l2=0.7, g=9.81)
        return lagrax.accelerations(L, q, qdot)

    def hand(m1, m2):
        return double_pendulum.acceleration(q, qdot, m1=m1, m2=m2, l2=0.7, g=9.81)

    for i in range(2):
        got = jax.grad(lambda m1, m2: ours(m1, m2)[i], argnums=(0, 1))(1.3, 0.6)
        want = jax.grad(lambda m1, m2: hand(m1, m2)[i], argnums=(0, 1))(1.3, 0.6)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
