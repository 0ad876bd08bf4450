"""Gradients of periods through the kernel with respect to parameters of a track,
the design-a-tautochrone setting, against finite differences (default suite)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lagrax


X = 0.6


def bead(a):
    """The bead on the track y = x²/2 + X² Σ_k a_k (x/X)^(2k+4), one term per a_k."""
    K = len(a)

    def L(q, qdot, t):
        x = q[0]
        s = (x / X) ** 2
        y = 0.5 * x**2 + X**2 * sum(a[k] * s ** (k + 2) for k in range(K))
        slope = x + 2 * x * sum((k + 2) * a[k] * s ** (k + 1) for k in range(K))
        return 0.5 * (1 + slope**2) * qdot[0] ** 2 - y

    return L


RELEASE = jnp.array([0.05, 0.3, 0.6])
A0 = jnp.array([1 / 8, 1 / 16, 5 / 128]) * X ** (2 * np.arange(1, 4))


# Jitted once per track size: the finite-difference points reuse one compiled sweep
# (the track's coefficients are tracers inside, hoisted out of L by closure
# conversion).
@jax.jit
def periods(a):
    return lagrax.sweep_periods(
        bead(a),
        RELEASE,
        rtol=1e-12,
        atol=1e-12,
        method="matched",
        lanes=3,
        error_estimate=False,
    ).periods


# One coefficient every time; three (a longer L, whose forward-mode kernel takes
# three times as long to compile) with `-m slow`.
@pytest.mark.parametrize(
    "K", [1, pytest.param(3, marks=pytest.mark.slow)], ids=["one_term", "three_terms"]
)
def test_jacobian_wrt_track_matches_finite_differences(K):
    """Every lane's dT/da finite (the event at the bottom of the track, x = 0, where
    the jacobian needs third derivatives of L) and equal to central differences. The
    default method, "matched", whose second leg ends at the first leg's event: its
    gradients were 15-30 % off before the event's position carried its tangent."""
    a0 = A0[:K]
    J = np.asarray(jax.jacfwd(periods)(a0))
    assert J.shape == (len(RELEASE), K) and np.isfinite(J).all(), J
    h = 1e-5
    for k in range(K):
        e = jnp.zeros(K).at[k].set(h)
        fd = (periods(a0 + e) - periods(a0 - e)) / (2 * h)
        np.testing.assert_allclose(J[:, k], np.asarray(fd), rtol=1e-5, atol=1e-9)


def test_a_module_lagrangian_with_parameters():
    # L as an `eqx.Module` with an array field: its parameters pass to the kernel as
    # arguments (no recompilation for new values), and periods are differentiable
    # with respect to them: the pendulum's T ∝ g^(-1/2), so dT/dg = -T / (2g).
    import equinox as eqx

    from lagrax.systems import pendulum

    class Pendulum(eqx.Module):
        g: jax.Array

        def __call__(self, q, qdot, t):
            return 0.5 * qdot[0] ** 2 + self.g * jnp.cos(q[0])

    a = jnp.array([0.1, 1.0, 2.0])
    exact = np.asarray(pendulum.period(a))
    for g in (1.0, 4.0):
        res = lagrax.sweep_periods(Pendulum(jnp.asarray(g)), a)
        assert np.all(np.asarray(res.status) == 0)
        np.testing.assert_allclose(res.periods, exact / np.sqrt(g), rtol=1e-12)

    # (dT/dg of a sweep: in test_derivatives_along_q0_and_every_parameter; of one
    # period, a program of its own, in the test below.)


@pytest.mark.slow  # reverse mode through one lane's kernel: its compilation is the cost
def test_a_module_lagrangians_period_is_differentiated_wrt_its_field():
    import equinox as eqx

    from lagrax.systems import pendulum

    class Pendulum(eqx.Module):
        g: jax.Array

        def __call__(self, q, qdot, t):
            return 0.5 * qdot[0] ** 2 + self.g * jnp.cos(q[0])

    grad = jax.grad(lambda m: lagrax.period(m, 1.0))(Pendulum(jnp.asarray(1.0)))
    np.testing.assert_allclose(grad.g, -0.5 * float(pendulum.period(1.0)), rtol=1e-9)


P = 5


def _pendulum_with_parameters():
    """A pendulum as an `eqx.Module` of 1 + P parameters, and its sweep of (a, g, c)."""
    import diffrax as dfx
    import equinox as eqx

    class Pendulum(eqx.Module):
        g: jax.Array
        c: jax.Array  # (1 - cos q)^(k + 2) terms of the potential, zero here

        def __call__(self, q, qdot, t):
            u = 1 - jnp.cos(q[0])
            extra = sum(self.c[k] * u ** (k + 2) for k in range(P))
            return 0.5 * qdot[0] ** 2 + self.g * jnp.cos(q[0]) - extra

    def sweep(a, g, c):
        return lagrax.sweep_periods(
            Pendulum(g, c),
            a,
            solver=dfx.Dopri8(),
            method="quarter",
            rtol=1e-12,
            atol=1e-12,
            error_estimate=False,
        ).periods

    return Pendulum(jnp.asarray(1.0), jnp.zeros(P)), sweep  # the pendulum itself


def test_only_the_differentiated_inputs_take_forward_passes():
    # The kernel's derivative takes one forward pass for q0 and one per scalar
    # parameter, but only for inputs whose tangent is not zero: dT/dq0 of a
    # Lagrangian with 1 + P parameters is one pass (no batch of 2 + P directions
    # in the program, as before). Traced, not compiled: the values are checked below.
    m, sweep = _pendulum_with_parameters()
    a = jnp.array([0.3, 1.0, 2.0])
    jac = jax.jacfwd(lambda a: sweep(a, m.g, m.c))
    dims = _leading_dims(jax.make_jaxpr(jac)(a).jaxpr)
    assert P + 2 not in dims and 3 in dims


def test_a_gradient_wrt_q0_takes_one_forward_pass_at_every_level(monkeypatch):
    # The sweep's own derivative rule runs the kernel's under `jax.jvp`: the
    # parameters not being differentiated must reach the inner rule as symbolic
    # zeros, or it adds one direction per parameter (1 + P passes instead of 1).
    # Traced, not compiled.
    import lagrax._period.autodiff as autodiff

    counts = []
    directions = autodiff._directions

    def spy(*args):
        found = directions(*args)
        counts.append(len(found))
        return found

    monkeypatch.setattr(autodiff, "_directions", spy)
    m, sweep = _pendulum_with_parameters()
    a = jnp.array([0.3, 1.0, 2.0])
    jax.make_jaxpr(jax.grad(lambda a: sweep(a, m.g, m.c).sum()))(a)
    assert counts and all(c == 1 for c in counts), counts


@pytest.mark.slow  # two forward-mode kernels compiled
def test_derivatives_along_q0_and_every_parameter():
    from lagrax.systems import pendulum

    m, sweep = _pendulum_with_parameters()
    a = jnp.array([0.3, 1.0, 2.0])
    jac = jax.jacfwd(lambda a: sweep(a, m.g, m.c))
    h = 1e-6
    exact = lambda a: np.asarray(pendulum.period(np.asarray(a, np.float64)))
    fd_a = (exact(a + h) - exact(a - h)) / (2 * h)
    np.testing.assert_allclose(np.diag(np.asarray(jac(a))), fd_a, rtol=1e-7)

    # Along q0 and every parameter at once: T ∝ g^(-1/2), so dT/dg = -T / (2g);
    # new parameter values need no new compilation, so differences in c are cheap.
    dq, dg, vc = jnp.array([1.0, -2.0, 0.5]), 0.3, jnp.linspace(0.1, 1.0, P)
    _, both = jax.jvp(sweep, (a, m.g, m.c), (dq, jnp.asarray(dg), vc))
    h = 1e-5
    fd_c = (sweep(a, m.g, m.c + h * vc) - sweep(a, m.g, m.c - h * vc)) / (2 * h)
    np.testing.assert_allclose(both, fd_a * dq - 0.5 * exact(a) * dg + fd_c, rtol=1e-6)


def _leading_dims(jaxpr):
    """The leading dimensions of every value a jaxpr computes, nested ones too."""
    dims = set()
    for eqn in jaxpr.eqns:
        dims |= {v.aval.shape[0] for v in eqn.outvars if getattr(v.aval, "shape", ())}
        for p in eqn.params.values():
            for sub in p if isinstance(p, (tuple, list)) else (p,):
                sub = getattr(sub, "jaxpr", sub)
                if hasattr(sub, "eqns"):
                    dims |= _leading_dims(sub)
    return dims


def test_the_far_turning_point_takes_its_tangent_from_the_implicit_function():
    # The far turning point of an asymmetric well (V = q²/2 + q³/5, released at rest
    # at q0 < 0) moves with q0 as the energy V(q0) dictates, dq1/dq0 = V'(q0)/V'(q1),
    # and its bracket and Newton loops carry no tangents: their while loops have as
    # many carries under `jax.jvp` as without it.
    from lagrax._period.far_turning_point import far_turning_point

    V = lambda q: 0.5 * q**2 + 0.2 * q**3
    L = lambda q, qd, t: 0.5 * qd[0] ** 2 - V(q[0])
    q0 = jnp.array([-0.3, -0.8])
    q_m = jnp.zeros(2)
    q1 = lambda q0: far_turning_point(L, [], q0, q_m).q1
    dV = jax.vmap(jax.grad(V))
    root, dq1 = jax.jvp(q1, (q0,), (jnp.ones(2),))
    assert np.all(np.asarray(root) > 0)
    np.testing.assert_allclose(dq1, dV(q0) / dV(root), rtol=1e-10)

    def carries(jaxpr):
        return sorted(len(e.invars) for e in _whiles(jaxpr))

    primal = jax.make_jaxpr(q1)(q0).jaxpr
    tangent = jax.make_jaxpr(lambda q: jax.jvp(q1, (q,), (q,)))(q0).jaxpr
    assert carries(primal) and carries(tangent) == carries(primal)


def _whiles(jaxpr):
    """The while loops of a jaxpr, nested ones too."""
    from jax._src import core

    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "while":
            yield eqn
        for sub in core.jaxprs_in_params(eqn.params):
            yield from _whiles(sub)
